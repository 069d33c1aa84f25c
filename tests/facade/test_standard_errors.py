"""The estimator's uncertainty surface: standard_errors_, confidence_intervals, parameter_covariance_,
bootstrap, fit_independent, pickling and plot_parameters."""

from __future__ import annotations

import pickle
import warnings

import numpy as np
import pytest
from sklearn.exceptions import NotFittedError

from torch_nssm import RobustNSSMEstimator, fit_independent
from torch_nssm.datasets import make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition


def _estimator(**kw) -> RobustNSSMEstimator:
    options = dict(x0_mean=[0.0], Rw_init=0.1, Rv_init=0.1, n_particles=100, n_iter=5, tol=0, random_state=0)
    options.update(kw)
    return RobustNSSMEstimator(PaperTransition(0.9, 1.0), PaperObservation(1.0), **options)


@pytest.fixture(scope="module")
def data():
    return make_paper_example(n_samples=300, random_state=1)


@pytest.fixture(scope="module")
def fitted(data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return _estimator().fit(data.u, data.y)


def test_keys_shapes_and_intervals(fitted):
    se = fitted.standard_errors_
    assert set(se) == {"f.a", "f.b", "g.c", "Rw", "Rv", "dof"}
    assert se["f.a"].shape == () and se["Rw"].shape == (1, 1)
    assert all(np.all(np.isfinite(v)) and np.all(v > 0) for v in se.values())
    ci = fitted.confidence_intervals(0.95)
    z = 1.959963984540054
    a = float(fitted.f_.a.detach())
    np.testing.assert_allclose(ci["f.a"], (a - z * se["f.a"], a + z * se["f.a"]))  # normal, symmetric
    Rw = fitted.Rw_[0, 0]
    lo, hi = ci["Rw"]
    np.testing.assert_allclose(
        np.log([lo[0, 0], hi[0, 0]]) - np.log(Rw), np.array([-1, 1]) * z * se["Rw"][0, 0] / Rw
    )
    lo90, hi90 = fitted.confidence_intervals(0.9)["dof"]
    assert lo[0, 0] > 0 and ci["dof"][0] < lo90 < fitted.dof_ < hi90 < ci["dof"][1]
    with pytest.raises(ValueError, match="level"):
        fitted.confidence_intervals(1.5)


def test_covariance_names_and_delta_method(fitted):
    names, cov = fitted.parameter_names_, fitted.parameter_covariance_
    assert names == ["f.a", "f.b", "g.c", "Rw[0, 0]", "Rv[0, 0]", "dof"]
    assert cov.shape == (6, 6)
    np.testing.assert_allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    se = fitted.standard_errors_
    np.testing.assert_allclose(
        np.sqrt(np.diag(cov)), [se["f.a"], se["f.b"], se["g.c"], se["Rw"][0, 0], se["Rv"][0, 0], se["dof"]]
    )
    # Rw = exp(2 w) on the working scale: se(Rw) = 2 Rw se(w)
    unc = fitted._parameter_uncertainty()
    se_w = np.sqrt(np.diag(np.linalg.inv(unc.information)))
    np.testing.assert_allclose(se["Rw"][0, 0], 2 * fitted.Rw_[0, 0] * se_w[3], rtol=1e-10)
    np.testing.assert_allclose(se["dof"], fitted.dof_ * se_w[5], rtol=1e-10)


def test_fixed_parameters_have_no_standard_error(data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = _estimator(noise="gaussian", fit_Rw=False, n_iter=2).fit(data.u, data.y)
    assert set(est.standard_errors_) == {"f.a", "f.b", "g.c", "Rv"}


def test_not_fitted_and_pickled(fitted):
    assert not hasattr(_estimator(), "standard_errors_")
    with pytest.raises(NotFittedError):
        _estimator().confidence_intervals()
    copy = pickle.loads(pickle.dumps(fitted))
    source = copy.__dict__.get("_uncertainty_source")  # the model and the data travel, never an E-step
    assert source is None or [type(x).__name__ for x in source] == ["StateSpaceModel", "SequenceBatch"]
    for k, v in fitted.standard_errors_.items():
        np.testing.assert_array_equal(copy.standard_errors_[k], v)


def test_fit_independent_estimators_carry_standard_errors(data):
    other = make_paper_example(n_samples=300, random_state=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = fit_independent(_estimator(), [data.u, other.u], [data.y, other.y])
        single = _estimator().fit(data.u, data.y)
    se0, se1 = fits[0].standard_errors_, fits[1].standard_errors_
    assert set(se0) == set(se1) == set(single.standard_errors_)
    assert se0["f.a"] != se1["f.a"]
    # the same data set alone: within Monte Carlo error of the batched fit's
    for k in ("f.a", "f.b", "g.c"):
        np.testing.assert_allclose(se0[k], single.standard_errors_[k], rtol=0.3)


def test_bootstrap_spread_agrees_with_the_information(fitted, data):
    boot = fitted.bootstrap(data.u, n_boot=16, random_state=0, n_iter=5)
    assert boot.samples["f.a"].shape == (16,) and boot.samples["Rw"].shape == (16, 1, 1)
    assert set(boot.intervals) == set(fitted.standard_errors_)
    for k in ("f.a", "f.b", "g.c"):
        lo, hi = boot.intervals[k]
        assert lo < np.median(boot.samples[k]) < hi
        ratio = boot.standard_errors[k] / fitted.standard_errors_[k]
        assert 0.4 < ratio < 2.5, (k, ratio)


def test_plot_parameters(fitted, data):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    from torch_nssm.plotting import plot_parameters

    axes = plot_parameters(fitted, true_values=data.params)
    assert len(axes) == 6
    assert [a.get_title() for a in axes] == ["f.a", "f.b", "g.c", "Rw", "Rv", "dof"]
    lines = axes[0].lines
    assert any(np.allclose(line.get_ydata(), 0.9) for line in lines)  # the true a
    with pytest.raises(ValueError, match="no interval"):
        plot_parameters(fitted, params="x0_mean")


def test_per_output_noise_has_diagonal_scale_and_one_dof_per_output(data):
    from torch_nssm.blocks.linear import LinearObservation

    rng = np.random.default_rng(0)
    y = np.column_stack([data.x[:, 0], 0.5 * data.x[:, 0]]) + 0.3 * rng.standard_normal((len(data.x), 2))
    g = LinearObservation(1, 1, 2, C=[[1.0], [0.5]])
    f = PaperTransition(0.9, 1.0)
    f.b.requires_grad_(False)  # with b and C both free the state's scale is not determined
    est = RobustNSSMEstimator(
        f,
        g,
        x0_mean=[0.0],
        Rw_init=0.1,
        Rv_init=np.diag([0.09, 0.09]),
        noise="student-t-per-output",
        n_particles=100,
        n_iter=3,
        tol=0,
        random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(data.u, y)
    se = est.standard_errors_
    # the structure: a diagonal scale (no off-diagonal entry estimated) and one dof per output.
    # Where the information is not positive definite (3 EM iterations, 100 particles: in 1-3 of
    # 12 seeds along g and Rw, with either Student-t family) the undetermined entries are NaN
    # with a warning; the determined ones are positive.
    d = np.diag(se["Rv"])
    assert se["Rv"].shape == (2, 2) and se["Rv"][0, 1] == 0 and np.all(np.isnan(d) | (d > 0))
    assert np.isfinite(d).any()
    assert se["dof"].shape == (2,) and se["g.C"].shape == (2, 1) and se["g.d"].shape == (2,)
    assert "Rv[0, 1]" not in est.parameter_names_ and "dof[1]" in est.parameter_names_


def test_large_modules_are_left_out_with_a_warning(data):
    from torch_nssm.blocks.neural import MLPTransition

    f = MLPTransition(1, 1, hidden=(16, 16), random_state=0)
    est = RobustNSSMEstimator(
        f, PaperObservation(1.0), x0_mean=[0.0], n_particles=50, n_iter=1, tol=0, first_stage=None,
        random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(data.u, data.y)
    with pytest.warns(RuntimeWarning, match="no standard errors for f"):
        se = est.standard_errors_
    assert set(se) == {"g.c", "Rw", "Rv", "dof"}


def test_multi_state_model_on_several_records_has_standard_errors():
    """Two states and two records: the information's sampler whitens ``transition_steps``, whose
    default returns another memory layout (through ``(B, t, ...)``); a ``view`` of it failed."""
    from torch_nssm.blocks.linear import LinearObservation, LinearTransition

    rng = np.random.default_rng(0)
    A, B = np.array([[0.8, 0.2], [-0.3, 0.6]]), np.array([[1.0], [0.5]])
    us, ys = [], []
    for _ in range(2):
        x, u = np.zeros((120, 2)), rng.standard_normal((120, 1))
        for k in range(119):
            x[k + 1] = A @ x[k] + B @ u[k] + 0.3 * rng.standard_normal(2)
        us.append(u)
        ys.append(x + 0.25 * rng.standard_normal((120, 2)))
    g = LinearObservation(2, 1, 2, fit_offset=False)
    g.C.requires_grad_(False)
    est = RobustNSSMEstimator(
        LinearTransition(2, 1, A=A, B=B), g, x0_mean=np.zeros(2), noise="gaussian",
        n_particles=50, n_iter=2, tol=0, random_state=0,
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        se = est.fit(us, ys).standard_errors_
    assert se["f.A"].shape == (2, 2) and se["f.B"].shape == (2, 1)
    assert np.isfinite(se["f.A"]).all() and (se["f.A"] > 0).all()
