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

The log-likelihood, which EM climbs, must also not move the same way at every step of the window
(one large step of a climb inflates the steps' standard deviation past the climb: by that alone
the suite's oscillator stops at 9 iterations, at 8x the true model's error, while its
log-likelihood still rises by thousands an iteration), and its last estimate must not lie far
below the window's (a particle filter's log-likelihood estimate has heavy tails: an occasional
estimate thousands of units low, after which EM recovers over a few iterations).  Measured on
the development suite: benchmarks/README.md, "When EM stops".

The noise parameters are also judged against their standard errors.  The complete-data ones
(:meth:`~torch_nssm.core.noise.base.MeasurementNoise.convergence_scales`) are too small where the states
carry little information (a small process noise): EM's rate of convergence in a parameter is the
fraction of its information that is missing (Dempster, Laird & Rubin 1977; Meng & Rubin's
supplemented EM), so the observed-data standard error is the complete-data one over
``sqrt(1 - rate)``, with the rate measured over the window (:func:`em_rate`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["STATIONARY_WINDOW", "stationary", "em_rate", "has_converged"]

#: Iterations over which the drift is compared with the jitter.
STATIONARY_WINDOW = 5

#: A net change within this many standard deviations of the jitter (scaled to the window) is noise.
JITTER_Z = 2.0

#: The median absolute deviation of normal draws times this is their standard deviation.
MAD_TO_SD = 1.4826

#: A last log-likelihood estimate this many robust standard deviations below the window's median
#: is an outlier of the estimate (or the first step of a fall), not a point to stop at.
LOW_Z = 3.0


def stationary(values, rtol: float, atol: float = 0.0, climbing: bool = False) -> bool:
    """Whether the sequence ``values`` (iterations along the first axis) has stopped drifting over its
    last :data:`STATIONARY_WINDOW` steps: per entry, ``|v[-1] - v[-1-K]|`` at most ``JITTER_Z`` times
    the standard deviation of the steps times ``sqrt(K)``, or at most ``rtol * |v[-1]| + atol``.

    ``climbing``: a sequence that EM increases (the log-likelihood estimate).  Within the jitter
    then also needs the steps not all of one sign, and the last value not below the window's
    median by more than :data:`LOW_Z` robust standard deviations (:data:`MAD_TO_SD` times the
    median absolute deviation of the window's other values)."""
    K = STATIONARY_WINDOW
    v = np.asarray(values, dtype=float)
    if v.shape[0] < K + 1:
        return False
    v = v[-(K + 1) :].reshape(K + 1, -1)
    if not np.all(np.isfinite(v)):
        return False
    steps = np.diff(v, axis=0)
    drift = np.abs(v[-1] - v[0])
    noise = drift <= JITTER_Z * steps.std(axis=0, ddof=1) * math.sqrt(K)
    if climbing:
        monotone = np.all(steps > 0, axis=0) | np.all(steps < 0, axis=0)
        centre = np.median(v[:-1], axis=0)
        spread = MAD_TO_SD * np.median(np.abs(v[:-1] - centre), axis=0)
        noise &= ~monotone & (v[-1] >= centre - LOW_Z * spread)
    return bool(np.all(noise | (drift <= rtol * np.abs(v[-1]) + atol)))


#: The largest EM rate :func:`em_rate` reports: at most a tenfold inflation of a standard error.
MAX_RATE = 0.99


def em_rate(values) -> np.ndarray:
    """EM's rate of convergence per entry of ``values`` (iterations along the first axis) over the
    last :data:`STATIONARY_WINDOW` steps: the least-squares ratio of each step to the one before,
    clipped to ``[0, MAX_RATE]`` (0 where the steps alternate, as Monte Carlo jitter does)."""
    v = np.asarray(values, dtype=float)
    v = v[-(STATIONARY_WINDOW + 1) :].reshape(min(v.shape[0], STATIONARY_WINDOW + 1), -1)
    steps = np.diff(v, axis=0)
    if steps.shape[0] < 2:
        return np.zeros(v.shape[1])
    num = np.sum(steps[1:] * steps[:-1], axis=0)
    den = np.sum(steps[:-1] ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.clip(np.nan_to_num(rate), 0.0, MAX_RATE)


#: A positive parameter with a standard error (the noise family's :meth:`convergence_scales`) has
#: converged once its net change over the window is below this fraction of it (observed-data:
#: inflated by EM's rate).  At half of it a Wiener-Hammerstein record's process noise (ten
#: entries, each creeping a few % per window) does not stop within 100 iterations, for a free run
#: that is the first stage's; at one it stops at 25, and no other stop on the suite moves
#: (benchmarks/README.md, "When EM stops").
SE_FRACTION = 1.0


def has_converged(
    history: dict, n_obs: int, tol: float, rtol: float = 1e-4, scales: dict | None = None
) -> bool:
    """Whether EM's ``history`` (every parameter and ``"log_likelihood"`` at every iteration) shows
    no drift any more: the log-likelihood estimate within its jitter or within ``tol`` per
    observation and iteration over the window, and every recorded parameter within its jitter or
    ``rtol`` (relative).  The parameters in ``scales`` (positive ones, e.g. variances: their
    relative standard errors) are compared on the log scale (a covariance matrix: its
    log-variances and correlations, :func:`_coordinates`), and also pass within
    :data:`SE_FRACTION` of their observed-data standard error (the complete-data one inflated by
    EM's rate, :func:`em_rate`)."""
    scales = scales or {}
    if tol <= 0:
        return False
    lls = history.get("log_likelihood", [])
    if len(lls) < STATIONARY_WINDOW + 1:
        return False
    if not stationary(lls, 0.0, atol=tol * max(n_obs, 1) * STATIONARY_WINDOW, climbing=True):
        return False
    for key, values in history.items():
        if key == "log_likelihood" or key.startswith(("rejected.", "accelerated")):
            continue
        series = np.asarray([np.asarray(v, dtype=float) for v in values[-(STATIONARY_WINDOW + 1) :]])
        if series.size == 0:
            continue
        if key in scales:
            for coords, complete_se in _coordinates(series, scales[key], n_obs):
                se = complete_se / np.sqrt(1.0 - em_rate(coords))
                if not stationary(coords, 0.0, atol=np.maximum(rtol, SE_FRACTION * se)):
                    return False
        elif not stationary(series, rtol):
            return False
    return True


def _coordinates(series: np.ndarray, relative_se, n_obs: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The coordinates in which a positive parameter's drift is judged, each with its
    complete-data standard error: the logarithm (its relative standard error ``relative_se``),
    and for a covariance matrix (square in its last two axes) the log-variances and the
    correlations (standard error ``(1 - r**2) / sqrt(n_obs)``): the logarithm of a small
    covariance between two states swings by whole units while it changes sign."""
    T = series.shape[0]
    se = np.asarray(relative_se, dtype=float)
    shape = series.shape[1:]
    se = se.reshape(shape) if se.size == math.prod(shape) else np.broadcast_to(se, shape)
    if series.ndim < 3 or series.shape[-1] != series.shape[-2] or series.shape[-1] < 2:
        return [(np.log(np.abs(series) + 1e-300).reshape(T, -1), se.reshape(-1))]
    p = series.shape[-1]
    variances = np.abs(np.diagonal(series, axis1=-2, axis2=-1)) + 1e-300
    sd = np.sqrt(variances)
    rows, cols = np.triu_indices(p, 1)
    corr = series[..., rows, cols] / (sd[..., rows] * sd[..., cols])
    corr_se = (1.0 - np.clip(corr[-1], -1.0, 1.0) ** 2) / math.sqrt(max(n_obs, 1))
    diag_se = np.diagonal(se, axis1=-2, axis2=-1)
    return [
        (np.log(variances).reshape(T, -1), diag_se.reshape(-1)),
        (corr.reshape(T, -1), np.maximum(corr_se, 1e-12).reshape(-1)),
    ]
