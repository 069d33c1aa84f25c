"""A fitted model on a record, as MATLAB's ``compare``: predicted outputs and the fit in percent.

:func:`compare` predicts the outputs of one or several records (the free-run simulation, or
``k``-step-ahead predictions from the measured outputs) and scores each record's outputs with
:func:`~torch_nssm.metrics.fit_percent`, ``100 (1 - ||y - y_pred|| / ||y - mean(y)||)``.  With
``robust=True`` the samples the fitted model flags as outliers on that record are left out of the
fit: those whose smoothed outlier weight ``E[lam_k | y]`` (``estimator.smooth(u, y)``) is below
:data:`OUTLIER_WEIGHT_THRESHOLD`.  :func:`torch_nssm.plotting.plot_compare` draws the result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .metrics import fit_percent

__all__ = ["CompareResult", "compare", "OUTLIER_WEIGHT_THRESHOLD"]

#: ``robust=True`` leaves out the samples whose smoothed outlier weight is below this value where
#: the estimator has no ``outlier_threshold_`` of its own (the noise family's flagging weight).
OUTLIER_WEIGHT_THRESHOLD = 0.5


@dataclass
class CompareResult:
    """Result of :func:`compare` (``RobustNSSMEstimator.compare``).

    Attributes
    ----------
    y_pred : ndarray or list of ndarray
        The predicted outputs as ``estimator.predict`` returns them (a list for a list of records).
    fit : ndarray of shape (p,), or (n_records, p) for a list of records
        Fit in percent per output (and record): ``100 (1 - ||y - y_pred|| / ||y - mean(y)||)``
        over the samples used.
    horizon : int or None
        ``None``: the free-run simulation; ``k``: ``k``-step-ahead predictions.
    robust : str
        Which samples were left out: ``"none"`` or e.g. ``"smoothed outlier weight < 0.38"`` (the
        estimator's ``outlier_threshold_``).
    excluded : ndarray or list of ndarray, or None
        With ``robust=True``: boolean, shaped like ``y``, True where a sample was left out.
    """

    y_pred: np.ndarray | list
    fit: np.ndarray
    horizon: int | None
    robust: str = "none"
    excluded: np.ndarray | list | None = None

    def summary(self) -> str:
        """One line per record: what was predicted and the fit of each output."""
        what = "free-run simulation" if self.horizon is None else f"{self.horizon}-step-ahead prediction"
        fits = np.atleast_2d(self.fit)
        excluded = self.excluded if isinstance(self.excluded, list) else [self.excluded] * len(fits)
        lines = []
        for r, row in enumerate(fits):
            head = f"record {r}, " if len(fits) > 1 else ""
            outputs = ", ".join(
                f"{v:.1f} %" if len(row) == 1 else f"{v:.1f} % (output {j})" for j, v in enumerate(row)
            )
            tail = ""
            if self.robust != "none" and excluded[r] is not None:
                tail = f"; {int(np.sum(excluded[r]))} samples with {self.robust} left out"
            lines.append(f"{head}{what}: fit {outputs}{tail}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()


def _records(a, name: str) -> list[np.ndarray]:
    seq = a if isinstance(a, (list, tuple)) else [a]
    out = []
    for r in seq:
        arr = np.asarray(r, dtype=float)
        if arr.ndim not in (1, 2):
            raise ValueError(f"{name} must be of shape (N,) or (N, p) per record, got {arr.shape}")
        out.append(arr.reshape(len(arr), -1))
    return out


def compare(estimator, u, y, *, horizon: int | None = None, x0=None, robust: bool = False, random_state=None):
    """The fitted model's predicted outputs on a record beside the measured ones, with the fit in %.

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        A fitted estimator.
    u : array-like of shape (N,) or (N, nu), or list of them, or None
        Inputs (``None``: a model without input).
    y : array-like of shape (N,) or (N, p), or list of them
        Measured outputs (NaN: missing, left out of the fit).
    horizon : int, optional
        ``None`` (default): the free-run simulation ``estimator.predict(u, x0=x0)``, MATLAB's
        ``compare(data, sys)``; ``k``: the ``k``-step-ahead predictions
        ``estimator.predict(u, y, horizon=k)``, MATLAB's ``compare(data, sys, k)``.
    x0 : array-like, pair or "estimate", optional
        The first state of the record(s), as in ``estimator.predict`` (default: the training
        record's ``x0_mean_``; ``(mean, cov)``: what ``estimator.initial_state(u, y)`` returns;
        ``"estimate"``: from the record's first outputs).
    robust : bool, default=False
        Leave out of the fit the samples whose outlier weight ``E[lam_k | y]`` from
        ``estimator.smooth(u, y)`` on this record is below the estimator's ``outlier_threshold_``
        (its flagging rule, as ``outliers_``; :data:`OUTLIER_WEIGHT_THRESHOLD` without one): the
        glitches the model flags.  With Gaussian noise no sample has a weight below 1.
    random_state : int, optional
        Seed of the particle filter and smoother (default: the estimator's).

    Returns
    -------
    CompareResult
        ``y_pred``, ``fit`` (% per output), ``horizon``, ``robust``, ``excluded``; ``print`` shows
        the fit.
    """
    multi = isinstance(y, (list, tuple))
    ys = _records(y, "y")
    needs_y = horizon is not None or (isinstance(x0, str) and x0 == "estimate")
    if u is None:
        u = [np.zeros((len(r), 0)) for r in ys] if multi else np.zeros((len(ys[0]), 0))
    options = dict(x0=x0, random_state=random_state)
    if needs_y:
        pred = estimator.predict(u, y, horizon=horizon, **options)
    else:
        pred = estimator.predict(u, **options)
    preds = _records(pred, "the predictions")
    excluded = None
    used = ys
    label = "none"
    if robust:
        sm = estimator.smooth(u, y, x0=x0, random_state=random_state)
        sm = sm if isinstance(sm, (list, tuple)) else [sm]
        excluded, used = [], []
        threshold = getattr(estimator, "outlier_threshold_", OUTLIER_WEIGHT_THRESHOLD)
        threshold = np.asarray(threshold, dtype=float)
        for yr, s in zip(ys, sm):
            w = np.asarray(s.outlier_weights, dtype=float)
            w = w[:, None] if w.ndim == 1 else w  # (N, 1) shared, or (N, p) per output
            out = np.isfinite(yr) & (w < threshold)
            excluded.append(out)
            used.append(np.where(out, np.nan, yr))
        label = "smoothed outlier weight < " + ", ".join(f"{v:.2g}" for v in threshold.reshape(-1))
    fits = np.stack([fit_percent(yr, pr) for yr, pr in zip(used, preds)])
    shapes = [np.shape(r) for r in (y if multi else [y])]
    if excluded is not None:
        excluded = [m.reshape(s) for m, s in zip(excluded, shapes)]
    if not multi:
        return CompareResult(pred, fits[0], horizon, label, None if excluded is None else excluded[0])
    return CompareResult(pred, fits, horizon, label, excluded)
