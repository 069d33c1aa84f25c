"""Scores of a fitted model's predictions, and a robust alternative to R² for records with outliers.

:meth:`RobustNSSMEstimator.score` is scikit-learn's R² (the default, as every regressor).  R²
weighs every sample by its squared residual, so a few glitches in the *measured* outputs dominate
it and cross-validation then ranks robust models by a non-robust metric.  :func:`robust_r2_score`
replaces the variances by squared robust scales (1.4826 x median absolute deviation); pass
``scoring=robust_r2_scorer`` to ``GridSearchCV`` or ``cross_val_score``, or ``robust=True`` to
``score``.  :func:`fit_percent` is MATLAB's ``compare`` fit (NRMSE in percent), per output.
"""

from __future__ import annotations

import numpy as np

from ._stats import robust_scale

__all__ = ["fit_percent", "robust_r2_score", "robust_r2_scorer"]  # noqa: F822 (robust_r2_scorer: __getattr__)


def robust_r2_score(y_true, y_pred) -> float:
    """``1 - (s(y - y_pred) / s(y))^2`` per output column, averaged; ``s`` = 1.4826 MAD, NaN ignored.

    Equals R² for Gaussian residuals; one sample in ten replaced by a glitch moves it little.

    Parameters
    ----------
    y_true, y_pred : array-like of shape (N,) or (N, p), or lists of them (records, pooled)

    Returns
    -------
    float
    """
    yt, yp = _pooled(y_true), _pooled(y_pred)
    if yt.shape != yp.shape:
        raise ValueError(f"y_true and y_pred must have the same shape, got {yt.shape} and {yp.shape}")
    scores = []
    for j in range(yt.shape[1]):
        m = ~np.isnan(yt[:, j])
        spread = robust_scale(yt[m, j], axis=0)
        resid = robust_scale(yt[m, j] - yp[m, j], axis=0, center=0.0)
        scores.append(1.0 - (resid / spread) ** 2 if spread > 0 else np.nan)
    return float(np.mean(scores))


def fit_percent(y_true, y_pred) -> np.ndarray:
    """Fit in percent per output, as MATLAB's ``compare``: ``100 (1 - ||y - y_pred|| / ||y - mean(y)||)``.

    The norms run over the observed samples of each output column (NaN in ``y_true`` is missing and
    left out; the mean is theirs).  100 is a perfect fit, 0 is no better than the mean, and it is
    negative for a worse prediction.  In terms of R² over the same samples,
    ``fit = 100 (1 - sqrt(1 - R²))``.

    Parameters
    ----------
    y_true, y_pred : array-like of shape (N,) or (N, p), or lists of them (records, pooled)

    Returns
    -------
    ndarray of shape (p,)
        NaN for an output with fewer than two observed samples or no spread.
    """
    yt, yp = _pooled(y_true), _pooled(y_pred)
    if yt.shape != yp.shape:
        raise ValueError(f"y_true and y_pred must have the same shape, got {yt.shape} and {yp.shape}")
    out = np.full(yt.shape[1], np.nan)
    for j in range(yt.shape[1]):
        m = ~np.isnan(yt[:, j])
        if m.sum() < 2:
            continue
        spread = np.linalg.norm(yt[m, j] - yt[m, j].mean())
        if spread > 0:
            out[j] = 100.0 * (1.0 - np.linalg.norm(yt[m, j] - yp[m, j]) / spread)
    return out


def _pooled(y) -> np.ndarray:
    """One array ``(N, p)`` from an array or a list of records."""
    if isinstance(y, (list, tuple)) and len(y) and np.ndim(y[0]) >= 1:
        return np.concatenate([np.asarray(a, dtype=float).reshape(len(a), -1) for a in y])
    a = np.asarray(y, dtype=float)
    return a.reshape(len(a), -1)


def __getattr__(name: str):
    """``robust_r2_scorer``: ``scoring=`` for scikit-learn's model selection, ``robust_r2_score`` of
    ``predict(u)`` (free run).  Made on first use (PEP 562): ``sklearn.metrics`` loads ~60 modules."""
    if name == "robust_r2_scorer":
        from sklearn.metrics import make_scorer

        globals()[name] = scorer = make_scorer(robust_r2_score)
        return scorer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
