"""Result objects of filtering and smoothing: numpy arrays a user can plot right away."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StateEstimate"]


@dataclass
class StateEstimate:
    """Filtered or smoothed state distribution of one record.

    Attributes
    ----------
    mean : ndarray, shape (N, nx)
        Posterior state means.
    cov : ndarray, shape (N, nx, nx)
        Posterior state covariances.
    outlier_weights : ndarray, shape (N,)
        ``E[lam_k | y]``: near 0 for an outlier (below 0.5 flags it), about 1 for a regular sample
        and above 1 for a small residual (up to ``(dof + p) / dof``); NaN where ``y_k`` is missing.
    log_likelihood : float
        Particle estimate of ``log p(y)`` at the parameters used.
    particles : ndarray, shape (N, L, nx), optional
        The weighted particles (only when asked for).
    weights : ndarray, shape (N, L), optional
        Their normalised weights.
    kind : str
        ``"filter"`` or ``"smoother"``.
    """

    mean: np.ndarray
    cov: np.ndarray
    outlier_weights: np.ndarray
    log_likelihood: float
    particles: np.ndarray | None = None
    weights: np.ndarray | None = None
    kind: str = "smoother"

    @property
    def std(self) -> np.ndarray:
        """Posterior standard deviations, shape (N, nx)."""
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=-2, axis2=-1), 0.0, None))

    def quantiles(self, q) -> np.ndarray:
        """Posterior quantiles of each state component, shape ``(len(q), N, nx)``.

        Weighted empirical quantiles of the particles when they were kept, otherwise the
        Gaussian approximation ``mean + z_q * std``.
        """
        q = np.atleast_1d(np.asarray(q, dtype=float))
        if np.any((q < 0) | (q > 1)):
            raise ValueError(f"q must lie in [0, 1], got {q.tolist()}")
        if self.particles is None:
            from statistics import NormalDist

            z = np.array([NormalDist().inv_cdf(min(max(v, 1e-12), 1 - 1e-12)) for v in q])
            return self.mean[None] + z[:, None, None] * self.std[None]
        order = np.argsort(self.particles, axis=1)  # (N, L, nx)
        xs = np.take_along_axis(self.particles, order, axis=1)
        w = np.broadcast_to(self.weights[..., None], self.particles.shape)
        ws = np.take_along_axis(w, order, axis=1)
        cdf = np.cumsum(ws, axis=1) - 0.5 * ws  # mid-point rule, as np.interp on each (k, d)
        last = xs.shape[1] - 1
        out = np.empty((len(q),) + self.mean.shape)
        for i, qi in enumerate(q):
            j = (cdf <= qi).sum(axis=1, keepdims=True)  # first point with cdf > q
            lo, hi = np.clip(j - 1, 0, last), np.clip(j, 0, last)
            c_lo, c_hi = np.take_along_axis(cdf, lo, 1), np.take_along_axis(cdf, hi, 1)
            x_lo, x_hi = np.take_along_axis(xs, lo, 1), np.take_along_axis(xs, hi, 1)
            gap = c_hi - c_lo
            frac = np.clip((qi - c_lo) / np.where(gap > 0, gap, 1.0), 0.0, 1.0)
            out[i] = (x_lo + np.where(gap > 0, frac, 0.0) * (x_hi - x_lo))[:, 0]
        return out

    def interval(self, level: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
        """Central credible band ``(lower, upper)`` of probability ``level``, each ``(N, nx)``."""
        lo, hi = self.quantiles([(1 - level) / 2, (1 + level) / 2])
        return lo, hi
