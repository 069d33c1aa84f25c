"""When EM with particles has converged.

EM with a fixed number of particles is a stochastic algorithm: its iterates settle into a cloud of
Monte Carlo jitter around the fixed point, and the log-likelihood estimate fluctuates by a few
units whatever the parameters do.  A threshold on the change of the log-likelihood alone then
either stops too early (a slow drift smaller than the threshold) or never (jitter larger than it).
This test stops when nothing *drifts* any more: over the last :data:`STATIONARY_WINDOW` iterations,
the net change of the log-likelihood estimate and of every parameter (variances and degrees of
freedom on the log scale) is within what the iteration-to-iteration jitter explains, or below a
relative tolerance.  A parameter creeping towards its maximum (EM's slow linear convergence)
moves the same way at every iteration, so its net change outgrows its jitter and the run goes on.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["STATIONARY_WINDOW", "stationary", "has_converged"]

#: Iterations over which the drift is compared with the jitter.
STATIONARY_WINDOW = 5

#: A net change within this many standard deviations of the jitter (scaled to the window) is noise.
JITTER_Z = 2.0


def stationary(values, rtol: float, atol: float = 0.0) -> bool:
    """Whether the sequence ``values`` (iterations along the first axis) has stopped drifting over its
    last :data:`STATIONARY_WINDOW` steps: per entry, ``|v[-1] - v[-1-K]|`` at most ``JITTER_Z`` times
    the standard deviation of the steps times ``sqrt(K)``, or at most ``rtol * |v[-1]| + atol``."""
    K = STATIONARY_WINDOW
    v = np.asarray(values, dtype=float)
    if v.shape[0] < K + 1:
        return False
    v = v[-(K + 1) :].reshape(K + 1, -1)
    if not np.all(np.isfinite(v)):
        return False
    steps = np.diff(v, axis=0)
    drift = np.abs(v[-1] - v[0])
    jitter = steps.std(axis=0, ddof=1) * math.sqrt(K)
    return bool(np.all((drift <= JITTER_Z * jitter) | (drift <= rtol * np.abs(v[-1]) + atol)))


#: A positive parameter with a standard error (the noise family's :meth:`convergence_scales`) has
#: converged once its net change over the window is below this fraction of it.
SE_FRACTION = 0.5


def has_converged(
    history: dict, n_obs: int, tol: float, rtol: float = 1e-4, scales: dict | None = None
) -> bool:
    """Whether EM's ``history`` (every parameter and ``"log_likelihood"`` at every iteration) shows
    no drift any more: the log-likelihood estimate within its jitter or within ``tol`` per
    observation and iteration over the window, and every recorded parameter within its jitter or
    ``rtol`` (relative).  The parameters in ``scales`` (positive ones, e.g. variances: their
    relative standard errors) are compared on the log scale, and also pass within
    :data:`SE_FRACTION` of their standard error."""
    scales = scales or {}
    if tol <= 0:
        return False
    lls = history.get("log_likelihood", [])
    if len(lls) < STATIONARY_WINDOW + 1:
        return False
    if not stationary(lls, 0.0, atol=tol * max(n_obs, 1) * STATIONARY_WINDOW):
        return False
    for key, values in history.items():
        if key == "log_likelihood" or key.startswith(("rejected.", "accelerated")):
            continue
        series = np.asarray([np.asarray(v, dtype=float) for v in values[-(STATIONARY_WINDOW + 1) :]])
        if series.size == 0:
            continue
        if key in scales:  # relative changes: an absolute tolerance on the log scale
            series = np.log(np.abs(series) + 1e-300)
            atol = np.maximum(rtol, SE_FRACTION * np.asarray(scales[key], dtype=float).reshape(-1))
            if not stationary(series, 0.0, atol=atol):
                return False
        elif not stationary(series, rtol):
            return False
    return True
