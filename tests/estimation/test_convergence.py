"""When EM with particles has converged: no drift beyond the jitter, or beyond a fraction of a
standard error."""

from __future__ import annotations

import numpy as np
import torch

from torch_nssm.core.noise.student_t import dof_relative_standard_error
from torch_nssm.estimation.convergence import STATIONARY_WINDOW, has_converged, stationary


def test_jitter_is_stationary_and_a_steady_drift_is_not():
    rng = np.random.default_rng(0)
    noise = 1.0 + 0.01 * rng.standard_normal(40)
    drift = 1.0 + 0.002 * np.arange(40) + 1e-4 * rng.standard_normal(40)  # EM's slow creep
    passes = [stationary(noise[: k + 1], rtol=0.0) for k in range(STATIONARY_WINDOW, 40)]
    assert np.mean(passes) > 0.8
    assert not any(stationary(drift[: k + 1], rtol=0.0) for k in range(STATIONARY_WINDOW, 40))
    assert stationary(drift, rtol=0.05)  # within a relative tolerance it is small enough
    assert not stationary(noise[:STATIONARY_WINDOW], rtol=1.0)  # too short to tell


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
