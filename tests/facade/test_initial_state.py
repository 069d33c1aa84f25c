"""A new record has its own first state: ``x0=`` on predict/score/simulate/filter/smooth, and its
estimation from the record's first outputs (issue #13 item 4)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.models import PaperObservation, PaperTransition


@pytest.fixture(scope="module")
def fitted():
    d = make_paper_example(n_samples=400, outlier_fraction=0.05, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=100, n_iter=20,
            random_state=0,
        ).fit(d.u, d.y)


def _record(x0: float, n: int = 150, seed: int = 7):
    """The paper's system from a known first state (small noise)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = x0
    for k in range(n - 1):
        x[k + 1] = 0.9 * x[k] + u[k] + 0.1 * rng.standard_normal()
    return u, np.cos(x) + 0.05 * rng.standard_normal(n), x


def test_free_run_from_the_records_own_first_state(fitted):
    u, y, x = _record(x0=2.5)
    default = np.ravel(fitted.predict(u))
    own = np.ravel(fitted.predict(u, x0=[2.5]))
    err = lambda p: np.sqrt(np.mean((p[:15] - np.cos(x[:15])) ** 2))  # noqa: E731
    assert own[0] == pytest.approx(fitted.g_.c.item() * np.cos(2.5), rel=1e-9)
    assert err(own) < 0.5 * err(default)
    assert fitted.score(u, y, x0=[2.5]) > fitted.score(u, y)
    # the same for several records at once, one state each
    both = fitted.predict([u, u], x0=[[2.5], [0.0]])
    np.testing.assert_allclose(np.ravel(both[0]), own)
    np.testing.assert_allclose(both[1], fitted.predict(u, x0=[0.0]))


def test_initial_state_is_estimated_from_the_first_outputs(fitted):
    u, y, x = _record(x0=2.5)
    mean, cov = fitted.initial_state(u, y)
    assert mean.shape == (1,) and cov.shape == (1, 1)
    assert abs(mean[0] - 2.5) < 3 * np.sqrt(cov[0, 0]) + 0.15
    estimated = np.ravel(fitted.predict(u, y, x0="estimate"))
    assert estimated[0] == pytest.approx(fitted.g_.c.item() * np.cos(mean[0]), rel=1e-9)
    sm_default = fitted.smooth(u, y).mean[0, 0]
    sm_estimate = fitted.smooth(u, y, x0="estimate").mean[0, 0]
    assert abs(sm_estimate - 2.5) <= abs(sm_default - 2.5) + 0.05
    assert np.isfinite(fitted.log_likelihood(u, y, x0="estimate"))
    assert fitted.filter(u, y, x0=[2.5]).mean.shape == (150, 1)


def test_simulate_from_a_given_state(fitted):
    u, _, _ = _record(x0=0.0)
    states, _ = fitted.simulate(u, n_samples=200, random_state=0, x0=[3.0])
    spread = np.sqrt(fitted.x0_cov_[0, 0])
    assert abs(states[:, 0, 0].mean() - 3.0) < 4 * spread / np.sqrt(200) + 1e-9
    with pytest.raises(ValueError, match="simulate has no outputs to estimate x0 from"):
        fitted.simulate(u, x0="estimate")


@pytest.mark.parametrize(
    "x0, message",
    [
        ("guess", r"x0 must be 'estimate' or an array of shape \(1,\)"),
        ([1.0, 2.0], r"x0 must have shape \(1,\) or \(1, 1\)"),
        ([np.nan], "x0 contains NaN"),
    ],
)
def test_bad_initial_states_are_refused(fitted, x0, message):
    u, _, _ = _record(x0=0.0, n=20)
    with pytest.raises(ValueError, match=message):
        fitted.predict(u, x0=x0)


def test_initial_state_goes_back_in_as_x0(fitted):
    """``x0=est.initial_state(u, y)``: the pair ``(mean, cov)`` is accepted by predict, score,
    simulate, smooth, filter and compare; the free run starts at ``mean``, the prior's spread is
    ``cov``."""
    u, y, _ = _record(x0=2.5)
    pair = fitted.initial_state(u, y)
    mean, cov = pair
    np.testing.assert_array_equal(fitted.predict(u, x0=pair), fitted.predict(u, x0=mean))
    assert fitted.score(u, y, x0=pair) == fitted.score(u, y, x0=mean)
    np.testing.assert_array_equal(fitted.compare(u, y, x0=pair).fit, fitted.compare(u, y, x0=mean).fit)
    # the prior's spread is cov: the simulated first states scatter by sqrt(cov), not sqrt(x0_cov_)
    tight = (mean, np.array([[1e-10]]))
    states, _ = fitted.simulate(u, n_samples=200, random_state=0, x0=tight)
    assert states[:, 0, 0].std() < 1e-4 < np.sqrt(fitted.x0_cov_[0, 0])
    np.testing.assert_allclose(states[:, 0, 0], mean[0], atol=1e-4)
    sm = fitted.smooth(u, y, x0=tight)
    assert abs(sm.mean[0, 0] - mean[0]) < 1e-3  # a prior that tight pins the first state
    assert fitted.filter(u, y, x0=pair).mean.shape == (150, 1)
    # several records: means (B, nx) and covariances (B, nx, nx)
    pairs = fitted.initial_state([u, u[:80]], [y, y[:80]])
    assert pairs[0].shape == (2, 1) and pairs[1].shape == (2, 1, 1)
    both = fitted.predict([u, u[:80]], x0=pairs)
    np.testing.assert_allclose(np.ravel(both[0]), np.ravel(fitted.predict(u, x0=pairs[0][0])))


def test_a_bad_covariance_in_the_x0_pair_is_named(fitted):
    u, _, _ = _record(x0=0.0, n=20)
    with pytest.raises(ValueError, match=r"x0 = \(mean, cov\): cov must have shape \(1, 1\)"):
        fitted.predict(u, x0=(np.array([0.0]), np.eye(2)))
    with pytest.raises(ValueError, match="x0's covariance must be positive definite"):
        fitted.predict(u, x0=(np.array([0.0]), np.array([[-1.0]])))
