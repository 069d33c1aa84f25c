"""When EM with particles has converged: no drift beyond the jitter, or beyond a fraction of a
standard error."""

from __future__ import annotations

import numpy as np
import torch

from torch_nssm.core.noise.student_t import dof_relative_standard_error
from torch_nssm.estimation.convergence import MAX_RATE, STATIONARY_WINDOW, em_rate, has_converged, stationary


def test_jitter_is_stationary_and_a_steady_drift_is_not():
    rng = np.random.default_rng(0)
    noise = 1.0 + 0.01 * rng.standard_normal(40)
    drift = 1.0 + 0.002 * np.arange(40) + 1e-4 * rng.standard_normal(40)  # EM's slow creep
    passes = [stationary(noise[: k + 1], rtol=0.0) for k in range(STATIONARY_WINDOW, 40)]
    assert np.mean(passes) > 0.8
    assert not any(stationary(drift[: k + 1], rtol=0.0) for k in range(STATIONARY_WINDOW, 40))
    assert stationary(drift, rtol=0.05)  # within a relative tolerance it is small enough
    assert not stationary(noise[:STATIONARY_WINDOW], rtol=1.0)  # too short to tell


def test_one_large_step_of_a_climb_is_not_jitter():
    # the suite's oscillator, iterations 4-9: a climb of thousands per iteration with one large step,
    # which inflates the steps' standard deviation (2773 x 2 > the net 5441) past the climb
    climb = [2844.0, 3655.0, 4275.0, 4862.0, 8108.0, 8285.0]
    assert np.std(np.diff(climb), ddof=1) * np.sqrt(STATIONARY_WINDOW) * 2 > climb[-1] - climb[0]
    assert stationary(climb, rtol=0.0)  # as any sequence: within its (inflated) jitter
    assert not stationary(climb, rtol=0.0, climbing=True)
    # a particle filter's occasional bad estimate: jitter in the middle of the window, not at its end
    assert stationary([2370.0, 2379.0, 636.0, 2381.0, 2368.0, 2375.0], rtol=0.0, climbing=True)
    assert not stationary([2370.0, 2379.0, 2380.0, 2381.0, 2368.0, 636.0], rtol=0.0, climbing=True)


def test_em_rate_is_the_ratio_of_successive_steps():
    assert np.allclose(em_rate(1.0 + 0.8 ** np.arange(8)), 0.8)  # linear convergence at rate 0.8
    assert em_rate(np.arange(8.0))[0] == MAX_RATE  # a steady creep: no end in sight
    assert em_rate([1.0, 2.0, 1.0, 2.0, 1.0, 2.0])[0] == 0.0  # alternating: Monte Carlo jitter
    both = em_rate(np.stack([1.0 + 0.5 ** np.arange(6), np.zeros(6)], axis=1))
    assert np.allclose(both, [0.5, 0.0])


def test_a_noise_variance_creeping_within_its_observed_standard_error_has_converged():
    # a small process noise creeping 1 % an iteration (the oscillator's velocity noise after its
    # climb): 5 % over the window, twice its complete-data standard error at 3,000 samples (2.6 %),
    # well within the observed one (EM's rate near 1: the states hold little of it)
    n, rw = 3000, {"Rw": np.array([np.sqrt(2 / 3000)])}
    slow = {**_history(8), "Rw": [np.array([[0.012 * 0.99**k]]) for k in range(8)]}
    fast = {**_history(8), "Rw": [np.array([[0.012 * 0.9**k]]) for k in range(8)]}
    assert has_converged(slow, n_obs=n, tol=1e-3, scales={"Rv": np.array([0.05]), **rw})
    assert not has_converged(fast, n_obs=n, tol=1e-3, scales={"Rv": np.array([0.05]), **rw})


def test_a_covariance_is_judged_by_its_variances_and_correlations():
    # two states' process noise: steady variances, a covariance jittering around zero (its log swings
    # by units as it changes sign): converged; the same with one variance creeping 10 % an iteration
    rng = np.random.default_rng(1)
    corr = 0.002 * rng.standard_normal(8)
    still = [np.array([[1e-4, c * 1e-4], [c * 1e-4, 1e-4]]) for c in corr]
    creeping = [m * np.array([[1.0, 1.0], [1.0, 1.0]]) for m in still]
    for k, m in enumerate(creeping):
        m[0, 0] *= 0.9**k
    rw = np.full((2, 2), np.sqrt(2 / 3000))
    base = {**_history(8), "Rv": [np.array([[0.1]])] * 8}
    assert has_converged({**base, "Rw": still}, n_obs=3000, tol=1e-3, scales={"Rw": rw})
    assert not has_converged({**base, "Rw": creeping}, n_obs=3000, tol=1e-3, scales={"Rw": rw})


def _history(n, dof_step=0.0, ll_step=0.0, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "log_likelihood": list(-1000.0 + ll_step * np.arange(n) + rng.standard_normal(n)),
        "f.a": list(0.9 + 1e-4 * rng.standard_normal(n)),
        "Rv": [np.array([[0.1 * (1 + 1e-3 * e)]]) for e in rng.standard_normal(n)],
        "dof": list(10.0 * np.exp(dof_step * np.arange(n))),
        "rejected.f": [False] * n,
    }


def test_has_converged_needs_every_parameter_still():
    rv = {"Rv": np.array([0.05])}  # relative standard error of Rv: compared on the log scale
    assert has_converged(_history(8), n_obs=1000, tol=1e-3, scales=rv)
    assert not has_converged(_history(8, ll_step=5.0), n_obs=1000, tol=1e-3, scales=rv)  # climbing
    assert not has_converged(_history(8), n_obs=1000, tol=0.0, scales=rv)  # tol=0: run all iterations
    creeping = _history(8, dof_step=0.01)  # the dof grows 1 % an iteration, steadily
    assert not has_converged(creeping, n_obs=1000, tol=1e-3, scales={**rv, "dof": np.array([1e-4])})
    # ... 5 % over the window, well within its standard error at dof 10 and 1,000 samples (20 %):
    scales = {**rv, "dof": np.array([float(dof_relative_standard_error(torch.tensor(10.0), 1, 1000))])}
    assert 0.15 < scales["dof"][0] < 0.25
    assert has_converged(creeping, n_obs=1000, tol=1e-3, scales=scales)


def test_dof_standard_error_matches_the_t_likelihood_curvature():
    from scipy import stats

    for v in (2.0, 8.0):
        x = stats.t.rvs(v, size=200_000, random_state=1)
        h = 1e-3 * v
        ll = [stats.t.logpdf(x, v + d).mean() for d in (-h, 0.0, h)]
        info = -(ll[0] - 2 * ll[1] + ll[2]) / h**2
        se = float(dof_relative_standard_error(torch.tensor(v, dtype=torch.float64), 1, 1)) * v
        assert abs(se * np.sqrt(info) - 1.0) < 0.05
