"""scikit-learn compatibility of ``RobustNSSMEstimator``.

The estimator is a *regressor of sequences*: ``fit(u, y)`` with ``u`` the inputs (scikit-learn's
``X``) and ``y`` the outputs, ``predict(u)`` the model's free-run output, ``score`` its R².
scikit-learn's common checks run through ``parametrize_with_checks`` on a small model whose ``f``
takes any number of inputs.  Passing (sklearn 1.9.1, 43 checks): check_complex_data,
check_dict_unchanged, check_do_not_raise_errors_in_init_or_set_params,
check_dont_overwrite_parameters, check_dtype_object, check_estimator_cloneable,
check_estimator_repr, check_estimator_sparse_array, check_estimator_sparse_matrix,
check_estimator_sparse_tag, check_estimator_tags_renamed, check_estimators_dtypes,
check_estimators_fit_returns_self, check_estimators_nan_inf, check_estimators_partial_fit_n_features,
check_estimators_pickle (also on read-only memmaps), check_estimators_unfitted,
check_f_contiguous_array_estimator, check_fit2d_1feature, check_fit2d_1sample,
check_fit2d_predict1d, check_fit_check_is_fitted, check_fit_idempotent, check_fit_score_takes_y,
check_get_params_invariance, check_mixin_order, check_n_features_in,
check_no_attributes_set_in_init, check_non_transformer_estimators_n_iter,
check_pipeline_consistency, check_positive_only_tag_during_fit, check_readonly_memmap_input,
check_regressors_int, check_regressors_no_decision_function,
check_regressors_train (3 variants; with the ``poor_score`` tag: a free run is not fitted row by
row), check_requires_y_none, check_set_params, check_supervised_y_2d, check_supervised_y_no_nan,
check_valid_tag_types.  Skipped by scikit-learn itself: check_array_api_input (needs
``SCIPY_ARRAY_API=1``) and check_regressor_data_not_an_array (its array-like part passes, then
it skips its pandas part when pandas is not installed).

Expected to fail (``EXPECTED_FAILED``), and why:

``check_methods_sample_order_invariance``, ``check_methods_subset_invariance``
    The rows of ``u`` are a time series, not i.i.d. samples: the prediction at time ``k`` is
    the state reached from ``u_0 .. u_{k-1}``, so permuting or subsetting rows changes it.
``check_fit1d``
    A 1-D ``u`` is a valid single input channel ``(N,)`` (as a 1-D ``y`` is one output).
``check_estimators_empty_data_messages``
    Empty data is rejected (``ValueError``), but ``u`` of shape ``(N, 0)`` is meaningful: a
    system without input; the check demands that it be refused.
``check_n_features_in_after_fitting``
    A wrong number of input columns is refused with a ``ValueError`` that names ``u`` (the
    argument the user passed), not scikit-learn's wording "X has n features...".
``check_regressor_multioutput``
    The number of outputs is fixed by the user's ``g``; the check fits 5 outputs with a
    one-output ``g`` (the estimator refuses, naming ``g`` and the shapes).  Several outputs work
    when ``g`` returns them (see ``test_multi_output``).
``check_parameters_default_constructible``
    ``f`` and ``g`` (the model) have no sensible default, and ``dtype`` defaults to
    ``torch.float64``, not one of the types the check allows.
``check_estimators_overwrite_params``
    The check compares ``joblib.hash`` of each parameter with that of a ``deepcopy``; a deep
    copy of a torch tensor never hashes like the original (torch pickles storages per object),
    so ``f`` and ``g`` always "differ".  ``test_fit_does_not_change_f_and_g`` checks the same
    thing with ``state_dict`` equality.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.utils.estimator_checks import parametrize_with_checks
from torch import nn

from torch_nssm import LinearInParameters, RobustNSSMEstimator

EXPECTED_FAILED = {
    "check_methods_sample_order_invariance": "time series: rows are not exchangeable",
    "check_methods_subset_invariance": "time series: a prediction depends on earlier inputs",
    "check_fit1d": "a 1-D u is one input channel",
    "check_estimators_empty_data_messages": "u of shape (N, 0) is a system without input",
    "check_n_features_in_after_fitting": "the error names u, not X",
    "check_regressor_multioutput": "the number of outputs is fixed by g",
    "check_parameters_default_constructible": "f and g have no default; dtype is a torch dtype",
    "check_estimators_overwrite_params": "joblib.hash(deepcopy(tensor)) != joblib.hash(tensor)",
}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class AnyInputTransition(LinearInParameters):
    """``f(x, u) = a x + b * sum(u)``: accepts any number of inputs (for the generic checks)."""

    def __init__(self, a: float = 0.5, b: float = 0.1):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(float(a), dtype=torch.float64))
        self.b = nn.Parameter(torch.tensor(float(b), dtype=torch.float64))

    def features(self, x, u):
        return torch.stack([x[..., 0], u.sum(-1)], -1).unsqueeze(-2), torch.zeros_like(x)


class LinearObservation(LinearInParameters):
    """``g(x, u) = c x`` repeated over ``p`` outputs with one gain each."""

    def __init__(self, c=(1.0,)):
        super().__init__()
        self.c = nn.Parameter(torch.tensor(c, dtype=torch.float64))

    def features(self, x, u):
        p = self.c.shape[0]
        eye = torch.eye(p, dtype=x.dtype, device=x.device)
        return x[..., None] * eye, torch.zeros(*x.shape[:-1], p, dtype=x.dtype, device=x.device)


def small_estimator(**kw) -> RobustNSSMEstimator:
    params = dict(x0_mean=[0.0], n_particles=20, n_iter=2, tol=0.0, random_state=0)
    params.update(kw)
    return RobustNSSMEstimator(AnyInputTransition(), LinearObservation(), **params)


@parametrize_with_checks(
    [small_estimator()], expected_failed_checks=lambda est: EXPECTED_FAILED
)
def test_sklearn_common_checks(estimator, check):
    check(estimator)


def toy_data(n=60, nu=1, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, nu))
    x = np.zeros(n)
    for k in range(n - 1):
        x[k + 1] = 0.7 * x[k] + u[k].sum() + 0.3 * rng.standard_normal()
    y = x + 0.2 * rng.standard_normal(n)
    return u, y


def test_get_set_params_and_clone():
    est = small_estimator(n_iter=3)
    params = est.get_params()
    assert params["f"] is est.f and params["g"] is est.g
    assert params["n_iter"] == 3 and "n_init" in params and "warm_start" in params
    g2 = LinearObservation((2.0,))
    assert est.set_params(g=g2, n_particles=30) is est
    assert est.g is g2 and est.n_particles == 30
    twin = clone(est)
    assert twin is not est and twin.f is not est.f and twin.g is not est.g  # deep copies
    assert twin.get_params()["n_particles"] == 30
    assert torch.equal(twin.g.c, est.g.c)
    with pytest.raises(ValueError, match="Invalid parameter 'bogus'"):
        est.set_params(bogus=1)


def test_init_stores_parameters_only():
    est = small_estimator()
    assert set(vars(est)) == set(est.get_params(deep=False))  # deep adds f__*, g__* (nested)
    assert not any(k.endswith("_") for k in vars(est))


def test_fit_does_not_change_f_and_g():
    f, g = AnyInputTransition(), LinearObservation()
    before = [{k: v.clone() for k, v in m.state_dict().items()} for m in (f, g)]
    u, y = toy_data()
    est = RobustNSSMEstimator(f, g, x0_mean=[0.0], n_particles=20, n_iter=3, tol=0.0).fit(u, y)
    for m, b in zip((f, g), before):
        assert all(torch.equal(m.state_dict()[k], v) for k, v in b.items())
    assert est.f_ is not f and est.g_ is not g
    assert est.f_.a.item() != f.a.item()  # the fitted copy moved


@pytest.mark.parametrize(
    "method, args",
    [
        ("predict", ("u",)),
        ("score", ("u", "y")),
        ("smooth", ("u", "y")),
        ("filter", ("u", "y")),
        ("log_likelihood", ("u", "y")),
        ("simulate", ("u",)),
    ],
)
def test_not_fitted_error(method, args):
    u, y = toy_data()
    data = {"u": u, "y": y}
    with pytest.raises(NotFittedError, match="not fitted yet"):
        getattr(small_estimator(), method)(*(data[a] for a in args))


def test_fit_is_deterministic_with_a_seed():
    u, y = toy_data()
    a = small_estimator(random_state=3).fit(u, y)
    b = small_estimator(random_state=3).fit(u, y)
    np.testing.assert_array_equal(a.history_["g.c"], b.history_["g.c"])
    np.testing.assert_array_equal(a.predict(u), b.predict(u))
    np.testing.assert_array_equal(a.history_["log_likelihood"], b.history_["log_likelihood"])
    c = small_estimator(random_state=4).fit(u, y)  # other particles: another likelihood estimate
    assert not np.array_equal(a.history_["log_likelihood"], c.history_["log_likelihood"])


def test_multi_output():
    u, y = toy_data()
    y2 = np.stack([y, 2 * y + 0.1 * np.random.default_rng(1).standard_normal(len(y))], 1)
    est = RobustNSSMEstimator(
        AnyInputTransition(), LinearObservation((1.0, 1.0)), x0_mean=[0.0], n_particles=30,
        n_iter=4, tol=0.0, random_state=0,
    ).fit(u, y2)
    assert est.n_outputs_ == 2 and est.Rv_.shape == (2, 2)
    assert est.predict(u).shape == (60, 2)
    assert np.isfinite(est.score(u, y2))
    assert est.g_.c[1].item() == pytest.approx(2 * est.g_.c[0].item(), rel=0.25)
