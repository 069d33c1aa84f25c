"""Model-error diagnostics: residual analysis of the one-step-ahead prediction errors (MATLAB's ``resid``).

A model that has captured the dynamics leaves one-step-ahead prediction errors
``e_k = y_k - E[y_k | y_{0:k-1}]`` that are white (uncorrelated with their own past) and
uncorrelated with past inputs.  :func:`residual_analysis` computes, as MATLAB's ``resid`` does,

* the normalised autocorrelation of each output's residuals, lags ``0..max_lag``:
  ``r_ee(tau) = R_ee(tau) / R_ee(0)``, ``R_ee(tau) = 1/N sum_k e_k e_{k-tau}``;
* the normalised cross-correlation between each input and each output's residuals, lags
  ``-max_lag..max_lag``: ``r_ue(tau) = R_ue(tau) / sqrt(R_ee(0) R_uu(0))``,
  ``R_ue(tau) = 1/N sum_k e_k u_{k-tau}`` (``tau > 0``: residuals against *past* inputs, a
  misspecified input path; ``tau < 0``: against *future* inputs, a sign of output feedback);

with the large-sample band ``z_{(1+level)/2} / sqrt(N)`` of white residuals independent of the
input, and the lags where the correlations leave it.  Residuals and inputs have their (pooled)
means removed first; a residual mean that differs significantly from zero is reported separately.

The band holds for each lag on its own: for white residuals some lag out of 25 leaves a 99 % band
with probability ``1 - 0.99**25 = 22 %``, so an isolated excursion at a large lag is weak
evidence; a run of flagged small lags is strong evidence.

The tests are *linear*.  An error that reaches the output through an even nonlinearity around a
symmetric operating point can escape them: in the paper's example ``y = c cos(x)`` with a
zero-mean input, a missing input path shows up as ``-c sin(x_k) b u_{k-1}``, whose correlation
with ``u_{k-1}`` averages out; the same model error is flagged at lag 1 when the state works
around ``pi / 2``.  Passing the tests is evidence, not proof, of an adequate model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np

__all__ = ["ResidualAnalysis", "correlations", "residual_analysis", "OUTLIER_WEIGHT_THRESHOLD"]

#: ``robust=True`` leaves out samples whose outlier weight ``E[lam_k | y]`` is below this value.
OUTLIER_WEIGHT_THRESHOLD = 0.2


@dataclass
class ResidualAnalysis:
    """Result of :func:`residual_analysis` (or :func:`correlations`).

    Attributes
    ----------
    lags : ndarray of shape (max_lag + 1,)
        ``0, 1, ..., max_lag``.
    autocorrelation : ndarray of shape (p, max_lag + 1)
        Normalised autocorrelation of each output's residuals (``1`` at lag 0).
    cross_lags : ndarray of shape (2 max_lag + 1,)
        ``-max_lag, ..., max_lag``.
    cross_correlation : ndarray of shape (nu, p, 2 max_lag + 1)
        Normalised cross-correlation ``r_ue(tau)`` of input ``i`` and output ``j``'s residuals
        (``tau > 0``: residual at ``k`` against the input at ``k - tau``).
    band : ndarray of shape (p,)
        Half-width ``z_{(1+level)/2} / sqrt(N_j)`` of the confidence band, per output.
    level : float
        Probability of the band.
    n_samples : ndarray of int, shape (p,)
        Number of residuals used per output ``N_j`` (observed and, with ``robust=True``, not
        left out as outliers).
    residuals : ndarray or list of ndarray
        The residuals ``e_k`` shaped like ``y`` (NaN where ``y`` is missing; outliers included).
    used : ndarray of bool or list of them
        Shaped like ``residuals``: which residuals entered the correlations.
    outside_auto : ndarray of bool, shape (p, max_lag + 1)
        Where ``|autocorrelation| > band`` (lag 0 never); the flagged lags of output ``j`` are
        ``lags[outside_auto[j]]``.
    outside_cross : ndarray of bool, shape (nu, p, 2 max_lag + 1)
        Where ``|cross_correlation| > band``; lags ``cross_lags[outside_cross[i, j]]``.
    mean : ndarray of shape (p,)
        Mean of the used residuals (removed before the correlations).
    mean_significant : ndarray of bool, shape (p,)
        Whether ``|mean| > band * std``: a bias (offset) the model misses.
    robust : str
        How outliers were handled: ``"none"`` (all observed residuals) or
        ``"excluded outlier weight < 0.2"``.
    n_excluded : ndarray of int, shape (p,)
        Observed residuals left out as outliers, per output.
    """

    lags: np.ndarray
    autocorrelation: np.ndarray
    cross_lags: np.ndarray
    cross_correlation: np.ndarray
    band: np.ndarray
    level: float
    n_samples: np.ndarray
    residuals: np.ndarray | list
    used: np.ndarray | list
    outside_auto: np.ndarray
    outside_cross: np.ndarray
    mean: np.ndarray
    mean_significant: np.ndarray
    robust: str = "none"
    n_excluded: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))

    @property
    def white(self) -> np.ndarray:
        """Per output: no autocorrelation lag ``1..max_lag`` outside the band."""
        return ~self.outside_auto.any(axis=1)

    @property
    def independent(self) -> np.ndarray:
        """Per input/output pair ``(nu, p)``: no cross-correlation lag outside the band."""
        return ~self.outside_cross.any(axis=2)

    def summary(self) -> str:
        """The verdict in words, one line per finding."""
        pct = f"{100 * self.level:g} %"
        lines = []
        p = self.autocorrelation.shape[0]
        for j in range(p):
            if self.mean_significant[j]:
                lines.append(
                    f"output {j}: residual mean {self.mean[j]:.3g} differs from 0 (outside the {pct} band)"
                    " — the model misses an offset"
                )
            if self.outside_auto[j].any():
                lags = _fmt(self.lags[self.outside_auto[j]])
                lines.append(
                    f"output {j}: residuals not white (lag{_s(lags)} {lags} outside the {pct} band)"
                    " — the model misses dynamics"
                )
        for i in range(self.cross_correlation.shape[0]):
            for j in range(p):
                flagged = self.cross_lags[self.outside_cross[i, j]]
                past, future = flagged[flagged >= 0], flagged[flagged < 0]
                if past.size:
                    lags = _fmt(past)
                    lines.append(
                        f"input {i} -> output {j}: residuals correlated with past inputs at "
                        f"lag{_s(lags)} {lags} — the input path is misspecified"
                    )
                if future.size:
                    lags = _fmt(future)
                    lines.append(
                        f"input {i} -> output {j}: residuals correlated with future inputs at "
                        f"lag{_s(lags)} {lags} — output feedback in the data (or a misspecified model)"
                    )
        if not lines:
            lines.append(f"whiteness and independence tests passed (at the {pct} level)")
        n = ", ".join(str(int(v)) for v in self.n_samples)
        head = f"residual analysis on {n} samples per output"
        if self.robust != "none":
            excl = ", ".join(str(int(v)) for v in self.n_excluded)
            head += f"; robust: {self.robust} ({excl} left out)"
            total = self.n_samples + self.n_excluded
            share = np.where(total > 0, self.n_excluded / np.maximum(total, 1), 0.0)
            if np.any(share > 0.2):
                head += (
                    " — over 20 % of an output's samples left out: the noise model may be absorbing"
                    " model error; compare with robust=False"
                )
        return "\n".join([head] + lines)


def _fmt(lags) -> str:
    return ", ".join(str(int(v)) for v in lags)


def _s(text: str) -> str:
    return "s" if "," in text else ""


def _as_records(a, name: str) -> list[np.ndarray]:
    records = a if isinstance(a, (list, tuple)) else [a]
    out = []
    for r in records:
        r = np.asarray(r, dtype=float)
        if r.ndim == 1:
            r = r[:, None]
        if r.ndim != 2:
            raise ValueError(f"{name} must be of shape (N,) or (N, n), or a list of them; got {r.shape}")
        out.append(r)
    return out


def correlations(residuals, inputs=None, max_lag: int = 25, level: float = 0.99) -> ResidualAnalysis:
    """Auto- and cross-correlations of given residuals with their confidence band.

    The formula layer of :func:`residual_analysis`, for residuals computed elsewhere.

    Parameters
    ----------
    residuals : array-like of shape (N,) or (N, p), or list of them (records)
        NaN: a residual left out (missing output, or an outlier); it counts as zero in the lagged
        products and is not counted in ``N``, so with gaps the correlations are shrunk slightly
        towards 0 and the band is conservative.
    inputs : array-like of shape (N,) or (N, nu), or list of them, optional
        The inputs of the same records (all finite); ``None``: no cross-correlation.
    max_lag : int, default=25
    level : float, default=0.99
        Probability of the band, in (0, 1).

    Returns
    -------
    ResidualAnalysis
        Lagged products never cross a record boundary: each record contributes
        ``sum_k e_k e_{k-tau}`` over its own samples, the sums are pooled, then divided by the
        pooled ``N``.
    """
    max_lag = int(max_lag)
    if max_lag < 0:
        raise ValueError(f"max_lag must be >= 0, got {max_lag}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    multi = isinstance(residuals, (list, tuple))
    res = _as_records(residuals, "residuals")
    p = res[0].shape[1]
    if inputs is None:
        ins = [np.zeros((len(r), 0)) for r in res]
    else:
        ins = _as_records(inputs, "inputs")
    if len(ins) != len(res):
        raise ValueError(f"{len(ins)} input records for {len(res)} residual records")
    nu = ins[0].shape[1]
    for r, u in zip(res, ins):
        if r.shape[1] != p or u.shape[1] != nu or len(r) != len(u):
            raise ValueError("every record needs residuals (N, p) and inputs (N, nu) of the same length N")
        if not np.all(np.isfinite(u)):
            raise ValueError("inputs must be finite")

    used = [np.isfinite(r) for r in res]
    n = np.sum([m.sum(0) for m in used], axis=0).astype(int)  # (p,)
    if np.any(n < 2):
        raise ValueError(f"too few residuals to correlate: {n.tolist()} per output")
    mean = np.sum([np.where(m, r, 0.0).sum(0) for r, m in zip(res, used)], axis=0) / n
    u_mean = np.sum([u.sum(0) for u in ins], axis=0) / sum(len(u) for u in ins)
    e = [np.where(m, r - mean, 0.0) for r, m in zip(res, used)]
    uc = [u - u_mean for u in ins]
    n_u = sum(len(u) for u in ins)

    L = max_lag
    auto = np.zeros((p, L + 1))
    cross = np.zeros((nu, p, 2 * L + 1))
    for ek, uk in zip(e, uc):
        T = len(ek)
        for tau in range(min(L, T - 1) + 1):
            auto[:, tau] += (ek[tau:] * ek[: T - tau]).sum(0)
            # R_ue(tau) = sum_k e_k u_{k-tau}; R_ue(-tau) = sum_k e_k u_{k+tau}
            cross[:, :, L + tau] += uk[: T - tau].T @ ek[tau:]
            if tau:
                cross[:, :, L - tau] += uk[tau:].T @ ek[: T - tau]
    r_ee0 = auto[:, 0] / n  # (p,)
    r_uu0 = np.sum([(u**2).sum(0) for u in uc], axis=0) / n_u  # (nu,)
    with np.errstate(invalid="ignore", divide="ignore"):
        autocorrelation = (auto / n[:, None]) / r_ee0[:, None]
        cross_correlation = (cross / n[None, :, None]) / np.sqrt(r_uu0[:, None, None] * r_ee0[None, :, None])
    z = NormalDist().inv_cdf(0.5 * (1.0 + level))
    band = z / np.sqrt(n)
    outside_auto = np.abs(autocorrelation) > band[:, None]
    outside_auto[:, 0] = False
    outside_cross = np.abs(cross_correlation) > band[None, :, None]
    mean_significant = np.abs(mean) > band * np.sqrt(r_ee0)
    return ResidualAnalysis(
        lags=np.arange(L + 1),
        autocorrelation=autocorrelation,
        cross_lags=np.arange(-L, L + 1),
        cross_correlation=cross_correlation,
        band=band,
        level=float(level),
        n_samples=n,
        residuals=res if multi else res[0],
        used=used if multi else used[0],
        outside_auto=outside_auto,
        outside_cross=outside_cross,
        mean=mean,
        mean_significant=mean_significant,
        robust="none",
        n_excluded=np.zeros(p, dtype=int),
    )


def residual_analysis(
    estimator,
    u,
    y,
    *,
    max_lag: int = 25,
    horizon: int = 1,
    level: float = 0.99,
    robust: bool = True,
    random_state=None,
) -> ResidualAnalysis:
    """Whiteness and independence tests of a fitted model's prediction errors (MATLAB's ``resid``).

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        A fitted estimator.
    u, y : array-like or lists of them
        Inputs and outputs of one record or a list of records (NaN in ``y``: missing, left out).
        Records are pooled without lagged products across their boundaries.
    max_lag : int, default=25
        Largest lag of the correlations.
    horizon : int, default=1
        The residuals are ``y_k - estimator.predict(u, y, horizon=horizon)_k`` (``1``: the
        one-step-ahead prediction errors, the classical test).
    level : float, default=0.99
        Probability of the confidence band (per lag).
    robust : bool, default=True
        Leave out the samples the fitted model flags as outliers: those whose outlier weight
        ``E[lam_k | y]`` from ``estimator.smooth(u, y)`` is below ``OUTLIER_WEIGHT_THRESHOLD``
        (0.2).  An outlier's residual is large and would otherwise dominate every lagged product.
        Leaving them out (rather than down-weighting) keeps the band's meaning for the samples
        that remain.  If many samples are left out, the summary says so: the noise model may be
        absorbing model error, which this option then hides; compare with ``robust=False``.
        With Gaussian noise no sample has a weight below 1, so nothing is left out.
    random_state : int, optional
        Seed of the particle filter and smoother (default: the estimator's).

    Returns
    -------
    ResidualAnalysis
        ``summary()`` gives the verdict in words; :func:`torch_nssm.plotting.plot_residuals`
        draws it.
    """
    multi = isinstance(y, (list, tuple))
    ys = _as_records(y, "y")
    if u is None:
        us = [np.zeros((len(r), 0)) for r in ys]
    else:
        us = _as_records(u, "u")
    pred = estimator.predict(u, y, horizon=horizon, random_state=random_state)
    preds = _as_records(pred, "predictions")
    res = [yk - pk for yk, pk in zip(ys, preds)]
    p = res[0].shape[1]
    n_excluded = np.zeros(p, dtype=int)
    robust_label = "none"
    kept = res
    if robust:
        sm = estimator.smooth(u, y, random_state=random_state)
        sm = sm if isinstance(sm, (list, tuple)) else [sm]
        kept = []
        for r, s in zip(res, sm):
            w = np.asarray(s.outlier_weights, dtype=float)
            w = w[:, None] if w.ndim == 1 else w  # (N, 1) shared or (N, p) per output
            out = np.isfinite(r) & (w < OUTLIER_WEIGHT_THRESHOLD)
            n_excluded += out.sum(0)
            kept.append(np.where(out, np.nan, r))
        robust_label = f"excluded outlier weight < {OUTLIER_WEIGHT_THRESHOLD:g}"
    analysis = correlations(kept, us, max_lag=max_lag, level=level)
    shapes = [np.shape(r) for r in (y if multi else [y])]
    res = [r.reshape(s) for r, s in zip(res, shapes)]
    analysis.used = [m.reshape(s) for m, s in zip(analysis.used, shapes)]  # a list: kept is one
    analysis.residuals = res
    if not multi:
        analysis.residuals, analysis.used = res[0], analysis.used[0]
    analysis.robust = robust_label
    analysis.n_excluded = n_excluded
    return analysis
