"""``noise=`` as a specification object (``torch_nssm.noise``): the same fit as its name with the
shortcut parameters, scikit-learn's parameter handling, the refusal of an object together with
changed shortcuts, and the starts taken at a fitted noise (distilled start, bootstrap)."""

from __future__ import annotations

import pickle
import warnings

import numpy as np
import pytest
import torch
from sklearn.base import clone

from torch_nssm import RobustNSSMEstimator
from torch_nssm.core.noise import NOISE_SHORTCUTS, noise_spec, restart_parameters
from torch_nssm.datasets import make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.noise import Gaussian, StudentT, StudentTPerOutput


def _estimator(**kw) -> RobustNSSMEstimator:
    options = dict(x0_mean=[0.0], Rw_init=0.1, Rv_init=0.1, n_particles=40, n_iter=3, tol=0, random_state=0)
    options.update(kw)
    return RobustNSSMEstimator(PaperTransition(0.9, 1.0), PaperObservation(1.0), **options)


@pytest.fixture(scope="module")
def data():
    return make_paper_example(n_samples=120, outlier_fraction=0.1, random_state=2)


def _fit(est, data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return est.fit(data.u, data.y)


@pytest.mark.parametrize(
    "name, shortcuts, spec",
    [
        ("student-t", dict(dof_init=3.0, dof_bounds=(1.0, 50.0)), StudentT(dof=3.0, dof_bounds=(1.0, 50.0))),
        ("student-t", dict(fit_dof=False), StudentT(fit_dof=False)),
        ("gaussian", {}, Gaussian()),
    ],
)
def test_an_object_fits_as_its_name_with_the_shortcuts(data, name, shortcuts, spec):
    by_name = _fit(_estimator(noise=name, **shortcuts), data)
    by_object = _fit(_estimator(noise=spec), data)
    for key, values in by_name.history_.items():
        np.testing.assert_array_equal(by_object.history_[key], values)
    np.testing.assert_array_equal(by_object.Rv_, by_name.Rv_)
    assert by_object.dof_ == by_name.dof_
    if shortcuts.get("fit_dof") is False:
        assert np.all(by_object.history_["dof"] == 5.0) and "dof" not in by_object.standard_errors_


def test_scikit_learn_parameters_clone_and_pickle(data):
    spec = StudentT(dof=4.0, dof_bounds=(2.0, 100.0))
    est = _estimator(noise=spec)
    assert est.get_params()["noise"] is spec
    copy = clone(est)
    assert copy.noise == spec and copy.noise is not spec  # scikit-learn deep-copies it
    est.set_params(noise=Gaussian())
    assert est.get_params()["noise"] == Gaussian()
    assert "StudentT(dof=4.0" in repr(copy)
    fitted = _fit(copy, data)
    loaded = pickle.loads(pickle.dumps(fitted))
    assert loaded.noise == spec and loaded.dof_ == fitted.dof_
    np.testing.assert_array_equal(loaded.predict(data.u), fitted.predict(data.u))


def test_an_object_with_changed_shortcuts_is_refused(data):
    with pytest.raises(ValueError, match=r"noise=StudentT.*holds its own options.*dof_init=3\.0"):
        _estimator(noise=StudentT(), dof_init=3.0).fit(data.u, data.y)
    with pytest.raises(ValueError, match=r"fit_dof=False"):
        _estimator(noise=Gaussian(), fit_dof=False).fit(data.u, data.y)
    # the defaults, spelled differently, are not a change
    noise_spec(StudentT(), dof_init=5, fit_dof=np.True_, dof_bounds=[0.1, 1000.0])
    with pytest.raises(TypeError, match="noise must be one of"):
        _estimator(noise=3).fit(data.u, data.y)


def test_the_estimator_defaults_are_the_registry_shortcuts():
    """The shortcuts' defaults live in the registry (the estimator forwards, never reads, them)."""
    import inspect

    params = inspect.signature(RobustNSSMEstimator).parameters
    assert {k: params[k].default for k in NOISE_SHORTCUTS} == NOISE_SHORTCUTS


def test_specifications_check_their_options():
    with pytest.raises(ValueError, match="dof must be positive and finite"):
        StudentT(dof=float("inf"))
    with pytest.raises(ValueError, match="dof must be > 0"):
        StudentT(dof=0.0)
    with pytest.raises(ValueError, match="dof_bounds must satisfy 0 < low < high"):
        StudentTPerOutput(dof_bounds=(5.0, 1.0))
    assert StudentTPerOutput(dof=[3, 12]).dof == (3.0, 12.0)
    with pytest.raises(ValueError, match=r"dof_init must be one number or 2 \(one per output\), got 3"):
        StudentTPerOutput(dof=[3, 4, 5]).initial(torch.eye(2, dtype=torch.float64))


def test_starts_at_a_fitted_noise_keep_the_way_it_was_given(data):
    """By name: the shortcut of the fitted value (``dof_init``); as an object: the object at it."""
    fitted = _fit(_estimator(), data)
    assert restart_parameters("student-t", fitted._fitted_noise()) == {"dof_init": fitted.dof_}
    spec = StudentT(dof_bounds=(1.0, 100.0))
    fitted = _fit(_estimator(noise=spec), data)
    start = restart_parameters(spec, fitted._fitted_noise())
    assert start == {"noise": StudentT(dof=fitted.dof_, dof_bounds=(1.0, 100.0))}


def test_distilled_start_and_bootstrap_with_the_per_output_family():
    """The per-output family's fitted dofs (one per output) start the next fit: the distilled start's
    ``dof_init`` and the bootstrap's refits."""
    from torch_nssm.blocks.linear import LinearObservation, LinearTransition
    from torch_nssm.datasets.two_sensors import make_two_sensor_example
    from torch_nssm.starts import distilled_start

    d = make_two_sensor_example(150, glitch_fraction=0.1, random_state=0)
    g = LinearObservation(2, 1, 2)
    g.C.requires_grad_(False)
    est = RobustNSSMEstimator(
        LinearTransition(2, 1), g, x0_mean=np.zeros(2), Rv_init=np.diag([0.2, 0.2]), dof_init=10.0,
        noise="student-t-per-output", n_particles=40, n_iter=3, tol=0, random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(est, d.u, d.y, n_iter=3, n_jitter=0, return_info=True)
        np.testing.assert_array_equal(warm.dof_init, info.reference.dof_)
        assert warm.dof_init.shape == (2,) and np.all(warm.dof_init != 10.0)
        fitted = warm.fit(d.u, d.y)
        assert fitted.history_["dof"][0].tolist() == warm.dof_init.tolist()
        boot = fitted.bootstrap(d.u, n_boot=2, n_iter=1, n_particles=20, random_state=0)
    assert boot.samples["dof"].shape == (2, 2)
