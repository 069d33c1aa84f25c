"""Plots of a fit: parameter trajectories, flagged outliers, smoothed states with bands, residual tests,
measured against predicted outputs.

Each function draws on the ``ax`` it is given (or on a new figure) and returns its Axes, so plots
compose with the rest of a matplotlib figure.  matplotlib is imported when a function is called.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from sklearn.exceptions import NotFittedError

from .inference.results import StateEstimate

__all__ = [
    "plot_compare", "plot_history", "plot_outliers", "plot_parameters", "plot_residuals", "plot_states",
]

#: Entries of ``history_`` that are covariance matrices: only their upper triangle is drawn.
_SYMMETRIC = ("Rw", "Rv", "x0_cov")


def _pyplot():
    import matplotlib.pyplot as plt

    return plt


def _history(est) -> Mapping[str, np.ndarray]:
    if isinstance(est, Mapping):
        return est
    history = getattr(est, "history_", None)
    if history is None:
        raise NotFittedError(
            f"{type(est).__name__} has no history_: fit it first (or pass its history_ dict)"
        )
    return history


#: Keys of ``history_`` that are not parameters of the model (or not drawn by default).
_NOT_DRAWN = ("log_likelihood", "x0_mean", "accelerated")


def _default_params(history: Mapping[str, np.ndarray]) -> list[str]:
    """``f``'s and ``g``'s parameters, ``Rw``, ``Rv``, then the noise family's other parameters
    whose trajectory is finite (one held at ``inf`` is not drawn)."""
    names = [k for k in history if k.startswith(("f.", "g."))]
    names += [k for k in ("Rw", "Rv") if k in history]
    names += [
        k for k in history
        if k not in names and k not in _NOT_DRAWN and not k.startswith("rejected.")
        and np.all(np.isfinite(np.asarray(history[k], dtype=float)))
    ]
    return names


def _series(name: str, values: np.ndarray) -> list[tuple[str, tuple, np.ndarray]]:
    """Split an ``(n_iter + 1, *shape)`` trajectory into labelled scalar series."""
    values = np.asarray(values, dtype=float)
    shape = values.shape[1:]
    if shape == () or int(np.prod(shape)) == 1:
        return [(name, (), values.reshape(len(values)))]
    out = []
    for idx in np.ndindex(*shape):
        if name in _SYMMETRIC and len(idx) == 2 and idx[0] > idx[1]:
            continue
        label = f"{name}[{', '.join(str(i) for i in idx)}]"
        out.append((label, idx, values[(slice(None),) + idx]))
    return out


def _match_true_values(true_values, params: list[str], history) -> dict:
    """``true_values`` keyed by the plotted names they belong to (see :func:`plot_history`)."""
    true_values = dict(true_values or {})
    typos = [k for k in true_values if str(k).startswith(("f.", "g.")) and k not in history]
    if typos:
        raise ValueError(
            f"true_values has {typos}, which are not in the history; available: {sorted(history)}"
        )
    matched = {}
    for key, value in true_values.items():
        if key in params:
            name = key
        elif key in history:
            continue  # a history entry that is not plotted (x0_mean, log_likelihood, ...)
        else:
            owners = [p for p in params if p.startswith(("f.", "g.")) and p[2:] == key]
            if len(owners) > 1:
                raise ValueError(
                    f"true_values[{key!r}] is ambiguous among the plotted params {owners}: "
                    "give the qualified name"
                )
            if not owners or owners[0] in true_values:
                continue  # a setting of the data (noise, outlier_fraction, ...) or given qualified
            name = owners[0]
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"true_values[{key!r}] must be numeric, got {value!r}") from None
        if np.all(np.isfinite(arr)):
            matched[name] = arr
    return matched


def _other_family_references(true_values, history) -> dict[str, str]:
    """The plotted noise entries whose given value belongs to another noise family than the fit's,
    with the words to label them: a Gaussian variance is not the true value of a Student-t scale
    (nor the reverse).  The data's family is ``true_values["noise"]`` (a simulation's
    ``data.params``); the fit is heavy-tailed when a shape parameter of its noise family (an entry
    of the history beside ``f``, ``g``, ``Rw`` and ``Rv``, e.g. ``dof``) ends finite."""
    noise = dict(true_values or {}).get("noise")
    if not isinstance(noise, str):
        return {}
    shapes = [
        k for k in history
        if not k.startswith(("f.", "g.", "rejected.")) and k not in ("Rw", "Rv", "x0_cov", *_NOT_DRAWN)
    ]
    fit_heavy = any(bool(np.all(np.isfinite(np.asarray(history[k], dtype=float)[-1]))) for k in shapes)
    data_heavy = noise != "gaussian"
    if fit_heavy == data_heavy:
        return {}
    return {"Rv": "data's Gaussian variance" if noise == "gaussian" else f"data's {noise} scale"}


def plot_history(est, params=None, true_values=None, ax=None):
    """Parameter estimates over the EM iterations (the paper's Figs. 2 and 10).

    Parameters
    ----------
    est : RobustNSSMEstimator or dict
        A fitted estimator, or its ``history_``.
    params : str or list of str, optional
        Keys of ``history_`` to draw, e.g. ``["f.a", "g.c", "Rv", "dof", "log_likelihood"]``;
        default: every parameter of ``f`` and ``g``, ``Rw``, ``Rv`` and the noise family's other
        parameters (``dof``).  Vector and matrix entries give one line per element (the upper triangle
        of ``Rw``, ``Rv``, ``x0_cov``).
    true_values : dict, optional
        ``{name: value}`` drawn as dashed horizontal lines in the colour of the estimate
        (``value`` shaped like the entry, or a scalar).  ``name`` is a key of ``history_``
        (``"f.a"``, ``"Rv"``) or a plain parameter name (``"a"``) when exactly one plotted
        ``f.``/``g.`` parameter has it, so a simulation's ``data.params`` can be passed as it is.
        Entries that name no plotted parameter (settings such as ``noise``, or parameters left
        out by ``params``) and non-finite values (``dof=inf`` of Gaussian noise) are skipped;
        a qualified ``f.``/``g.`` name that is not in the history raises ``ValueError``.  When
        ``true_values["noise"]`` names another noise family than the fit's (Gaussian data, a
        Student-t fit), ``Rv``'s value is not its true value (a variance is not a Student-t
        scale): it is drawn dotted and labelled "data's Gaussian variance" instead of "true".
    ax : matplotlib Axes or sequence of Axes, optional
        ``None``: a new figure with one panel per parameter.  One Axes: every trajectory on it
        (with a legend).  A sequence of Axes: one per parameter.

    Returns
    -------
    Axes or ndarray of Axes
        The Axes drawn on: one Axes if one was given, else an array with one per parameter.
    """
    history = _history(est)
    if params is None:
        params = _default_params(history)
    elif isinstance(params, str):
        params = [params]
    params = list(params)
    unknown = [p for p in params if p not in history]
    if unknown:
        raise ValueError(f"params {unknown} not in the history; available: {sorted(history)}")
    if not params:
        raise ValueError("params is empty: nothing to plot")
    other_family = _other_family_references(true_values, history)
    true_values = _match_true_values(true_values, params, history)
    single = ax is not None and not isinstance(ax, (Sequence, np.ndarray))
    if ax is None:
        plt = _pyplot()
        ncols = min(3, len(params))
        nrows = -(-len(params) // ncols)
        fig, grid = plt.subplots(
            nrows, ncols, figsize=(4.0 * ncols, 2.8 * nrows), squeeze=False, layout="constrained"
        )
        axes = grid.ravel()
        for extra in axes[len(params) :]:
            fig.delaxes(extra)
        axes = axes[: len(params)]
    elif single:
        axes = [ax] * len(params)
    else:
        axes = np.asarray(ax, dtype=object).ravel()
        if len(axes) != len(params):
            raise ValueError(f"ax holds {len(axes)} Axes for {len(params)} params")
    for name, a in zip(params, axes):
        truth = true_values.get(name)
        for label, idx, values in _series(name, history[name]):
            (line,) = a.plot(np.arange(len(values)), values, label=label)
            if truth is not None:
                t = np.asarray(truth, dtype=float)
                t = t.reshape(()) if t.size == 1 else t[idx]
                kind = other_family.get(name)
                a.axhline(
                    float(t), color=line.get_color(), linestyle=":" if kind else "--", linewidth=1.0,
                    label=f"{label} ({kind or 'true'})",
                )
        a.set_xlabel("iteration")
        if not single:
            a.set_title(name)
    if single:
        ax.legend(fontsize="small")
        return ax
    return np.asarray(axes, dtype=object)


def plot_parameters(est, params=None, level: float = 0.95, intervals=None, true_values=None, ax=None):
    """Fitted parameters with their confidence intervals as error bars, one panel per parameter.

    Parameters
    ----------
    est : RobustNSSMEstimator
        A fitted estimator.
    params : str or list of str, optional
        Keys of ``standard_errors_`` (``"f.a"``, ``"Rw"``, ...); default: all of them.  Vector and
        matrix entries are drawn side by side (the lower triangle of ``Rw`` and ``Rv``).
    level : float, default=0.95
        Level of the observed-information intervals (``est.confidence_intervals(level)``).
    intervals : dict, optional
        Intervals to draw instead, keyed like ``standard_errors_`` (e.g. ``est.bootstrap(u).intervals``).
    true_values : dict, optional
        Drawn as black crosses labelled "true"; keys as in :func:`plot_history` (``data.params``
        works as it is).  A value of another noise family than the fit's (``Rv`` of Gaussian data
        beside a Student-t fit's scale) is not a true value: a grey plus labelled "data's Gaussian
        variance", with a legend.
    ax : sequence of Axes, optional
        One per parameter; a new figure if omitted.

    Returns
    -------
    ndarray of Axes
    """
    from .bootstrap import parameter_values

    if not hasattr(est, "f_"):
        raise NotFittedError(f"{type(est).__name__} is not fitted: call fit(u, y) first")
    values = parameter_values(est)
    intervals = est.confidence_intervals(level) if intervals is None else intervals
    if params is None:
        params = [k for k in values if k in intervals]
    elif isinstance(params, str):
        params = [params]
    params = list(params)
    unknown = [p for p in params if p not in values or p not in intervals]
    if unknown:
        available = sorted(set(values) & set(intervals))
        raise ValueError(f"params {unknown} have no interval; available: {available}")
    if not params:
        raise ValueError("params is empty: nothing to plot")
    other_family = _other_family_references(true_values, est.history_)
    truth = _match_true_values(true_values, params, est.history_)
    if ax is None:
        plt = _pyplot()
        ncols = min(3, len(params))
        nrows = -(-len(params) // ncols)
        fig, grid = plt.subplots(
            nrows, ncols, figsize=(3.5 * ncols, 2.8 * nrows), squeeze=False, layout="constrained"
        )
        axes = grid.ravel()
        for extra in axes[len(params) :]:
            fig.delaxes(extra)
        axes = axes[: len(params)]
    else:
        axes = np.asarray(ax, dtype=object).ravel()
        if len(axes) != len(params):
            raise ValueError(f"ax holds {len(axes)} Axes for {len(params)} params")
    for name, a in zip(params, axes):
        value = np.asarray(values[name], dtype=float)
        lo, hi = (np.broadcast_to(np.asarray(b, dtype=float), value.shape) for b in intervals[name])
        symmetric = name in _SYMMETRIC
        entries = [i for i in np.ndindex(*value.shape) if not (symmetric and len(i) == 2 and i[0] < i[1])]
        x = np.arange(len(entries))
        v = np.array([value[i] for i in entries])
        err = np.array([[value[i] - lo[i] for i in entries], [hi[i] - value[i] for i in entries]])
        a.errorbar(x, v, yerr=np.clip(err, 0.0, None), fmt="o", capsize=4, label="estimate")
        if name in truth:
            t = truth[name]
            t = t.reshape(value.shape) if t.size == value.size else np.broadcast_to(t, value.shape)
            if name in other_family:
                a.plot(x, [t[i] for i in entries], "+", color="0.5", label=other_family[name])
                a.legend(fontsize="x-small")
            else:
                a.plot(x, [t[i] for i in entries], "x", color="black", label="true")
        a.set_xticks(x)
        labels = [name if not i else f"[{', '.join(map(str, i))}]" for i in entries]
        a.set_xticklabels(labels, fontsize="small")
        a.set_title(name)
    return np.asarray(axes, dtype=object)


def plot_outliers(
    y, outlier_weights, true_outliers=None, ax=None, *, cmap="RdYlGn", t=None, threshold: float = 0.5
):
    """The outputs over time, coloured by their outlier weight ``E[lam_k | y]``.

    A weight below ``threshold`` (red with the default colormap) flags an outlier, above it (green)
    a regular sample; pass ``est.outlier_threshold_`` to colour by the estimator's flags
    (``est.outliers_``).  A regular sample's weight is about 1 and exceeds 1 when its residual is
    small (up to ``(dof + p) / dof`` for a sample on its prediction, e.g. 2 at ``dof = 1``): the
    colour bar runs from 0 to the largest weight (at least 1), yellow at ``threshold``.  Missing
    weights (NaN) are grey.

    Parameters
    ----------
    y : array-like of shape (N,) or (N, p)
        Measured outputs (NaN: missing, not drawn).
    outlier_weights : array-like of shape (N,)
        E.g. ``est.outlier_weights_`` or ``est.smooth(u, y).outlier_weights``.
    true_outliers : array-like of bool, shape (N,), optional
        Known outliers (simulations), circled in black.
    ax : matplotlib Axes, optional
        Drawn on a new figure if omitted.
    cmap : str or Colormap, default="RdYlGn"
    t : array-like of shape (N,), optional
        Time axis (default: the sample index).
    threshold : float, default=0.5
        The flagging weight, in ``(0, 1)``.

    Returns
    -------
    Axes
    """
    threshold = float(np.min(threshold))
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must lie in (0, 1), got {threshold!r}")
    y = np.asarray(y, dtype=float)
    y = y.reshape(len(y), -1) if y.ndim <= 2 else None
    if y is None:
        raise ValueError("y must be 1-D (N,) or 2-D (N, p)")
    w = np.asarray(outlier_weights, dtype=float).reshape(-1)
    n = y.shape[0]
    if w.shape[0] != n:
        raise ValueError(f"outlier_weights must have {n} entries (one per sample), got {len(w)}")
    xlabel = "sample k" if t is None else "time"
    t = np.arange(n) if t is None else np.asarray(t, dtype=float).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"t must have {n} entries, got {t.shape[0]}")
    if ax is None:
        _, ax = _pyplot().subplots(figsize=(8.0, 3.0))
    from matplotlib.colors import TwoSlopeNorm

    ok = np.isfinite(w)
    top = max(1.0, float(w[ok].max())) if ok.any() else 1.0
    norm = TwoSlopeNorm(vmin=0.0, vcenter=threshold, vmax=top)
    scatter = None
    for j in range(y.shape[1]):
        ax.plot(t, y[:, j], color="0.8", linewidth=0.8, zorder=1)
        scatter = ax.scatter(t[ok], y[ok, j], c=w[ok], cmap=cmap, norm=norm, s=14, zorder=2)
        if (~ok).any():
            ax.scatter(t[~ok], y[~ok, j], color="0.6", s=10, zorder=2)
    if true_outliers is not None:
        m = np.asarray(true_outliers, dtype=bool).reshape(-1)
        if m.shape[0] != n:
            raise ValueError(f"true_outliers must have {n} entries, got {m.shape[0]}")
        for j in range(y.shape[1]):
            ax.scatter(
                t[m],
                y[m, j],
                s=60,
                facecolors="none",
                edgecolors="k",
                linewidths=0.8,
                zorder=3,
                label="true outliers" if j == 0 else None,
            )
        ax.legend(fontsize="small", loc="best")
    if scatter is not None:
        ax.figure.colorbar(scatter, ax=ax, label="outlier weight E[λ | y]")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("y")
    return ax


def plot_states(
    estimate: StateEstimate, x_true=None, ax=None, level: float = 0.9, *, components=None, t=None
):
    """Filtered or smoothed state means with a central credible band, against true states.

    Parameters
    ----------
    estimate : StateEstimate
        From ``est.smooth(u, y)`` or ``est.filter(u, y)`` (with ``return_particles=True`` the
        band is from the weighted particles, otherwise Gaussian from the covariances).
    x_true : array-like of shape (N,) or (N, nx), optional
        Known states (simulations), drawn dashed.
    ax : matplotlib Axes, optional
    level : float, default=0.9
        Probability of the band (``0`` for none).
    components : int or list of int, optional
        State components to draw (default: all).
    t : array-like of shape (N,), optional
        Time axis (default: the sample index).

    Returns
    -------
    Axes
    """
    if not isinstance(estimate, StateEstimate):
        raise TypeError(
            f"estimate must be a StateEstimate (from smooth or filter), got {type(estimate).__name__}"
        )
    if not 0.0 <= level < 1.0:
        raise ValueError(f"level must lie in [0, 1), got {level!r}")
    mean = estimate.mean
    n, nx = mean.shape
    comps = list(range(nx)) if components is None else list(np.atleast_1d(components))
    if any(not 0 <= int(c) < nx for c in comps):
        raise ValueError(f"components must lie in [0, {nx}), got {comps}")
    xlabel = "sample k" if t is None else "time"
    t = np.arange(n) if t is None else np.asarray(t, dtype=float).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"t must have {n} entries, got {t.shape[0]}")
    if x_true is not None:
        x_true = np.asarray(x_true, dtype=float).reshape(n, -1)
        if x_true.shape[1] != nx:
            raise ValueError(f"x_true must have shape ({n}, {nx}), got {x_true.shape}")
    if ax is None:
        _, ax = _pyplot().subplots(figsize=(8.0, 3.0))
    lo = hi = None
    if level > 0:
        lo, hi = estimate.interval(level)
    for c in comps:
        (line,) = ax.plot(t, mean[:, c], label=f"x[{c}] {estimate.kind} mean")
        if lo is not None:
            ax.fill_between(
                t,
                lo[:, c],
                hi[:, c],
                color=line.get_color(),
                alpha=0.25,
                linewidth=0,
                label=f"{level:.0%} band",
            )
        if x_true is not None:
            ax.plot(
                t, x_true[:, c], color=line.get_color(), linestyle="--", linewidth=1.0, label=f"x[{c}] true"
            )
    ax.set_xlabel(xlabel)
    ax.set_ylabel("state")
    ax.legend(fontsize="small", loc="best")
    return ax


def _correlation_panel(a, lags, values, band, outside, title, xlabel):
    a.axhspan(-band, band, color="0.85", linewidth=0, label="band", zorder=0)
    a.axhline(0.0, color="0.4", linewidth=0.8, zorder=1)
    a.vlines(lags, 0.0, values, color="C0", linewidth=1.0, zorder=2)
    a.plot(lags[~outside], values[~outside], "o", color="C0", markersize=3, zorder=3)
    if outside.any():
        a.plot(lags[outside], values[outside], "o", color="C3", markersize=5, zorder=4, label="outside")
    a.set_title(title, fontsize="medium")
    a.set_xlabel(xlabel)


def plot_residuals(analysis, ax=None):
    """Residual analysis (MATLAB's ``resid``): the correlations with their confidence band.

    One row per output: the autocorrelation of its residuals (lags ``0..max_lag``), then one
    panel per input with the cross-correlation of that input and the residuals (lags
    ``-max_lag..max_lag``; positive: residuals against past inputs).  The band is shaded;
    values outside it are drawn in red.

    Parameters
    ----------
    analysis : ResidualAnalysis
        From :func:`torch_nssm.diagnostics.residual_analysis`.
    ax : matplotlib Axes or sequence of Axes, optional
        ``None``: a new figure of ``p`` rows and ``1 + nu`` columns.  A sequence (or array) of
        ``p * (1 + nu)`` Axes, filled row by row; one Axes when there is one panel (one output,
        no input).

    Returns
    -------
    ndarray of Axes, shape (p, 1 + nu)
    """
    from .diagnostics import ResidualAnalysis

    if not isinstance(analysis, ResidualAnalysis):
        raise TypeError(
            f"analysis must be a ResidualAnalysis (from residual_analysis), got {type(analysis).__name__}"
        )
    nu = analysis.cross_correlation.shape[0]
    p = analysis.autocorrelation.shape[0]
    ncols = 1 + nu
    if ax is None:
        plt = _pyplot()
        _, grid = plt.subplots(p, ncols, figsize=(4.0 * ncols, 2.8 * p), squeeze=False)
    else:
        axes = np.asarray([ax] if not isinstance(ax, (Sequence, np.ndarray)) else ax, dtype=object).ravel()
        if len(axes) != p * ncols:
            raise ValueError(f"ax holds {len(axes)} Axes for {p * ncols} panels ({p} outputs x (1 + {nu}))")
        grid = axes.reshape(p, ncols)
    pct = f"{100 * analysis.level:g} %"
    for j in range(p):
        band = float(analysis.band[j])
        _correlation_panel(
            grid[j, 0],
            analysis.lags,
            analysis.autocorrelation[j],
            band,
            analysis.outside_auto[j],
            f"output {j}: residual autocorrelation ({pct} band)",
            "lag",
        )
        for i in range(nu):
            _correlation_panel(
                grid[j, 1 + i],
                analysis.cross_lags,
                analysis.cross_correlation[i, j],
                band,
                analysis.outside_cross[i, j],
                f"input {i} -> output {j}: cross-correlation",
                "lag (> 0: past inputs)",
            )
    return grid


def plot_compare(result, y, ax=None, *, record: int = 0, t=None):
    """Measured against predicted outputs, one panel per output, the fit in percent in the legend
    (MATLAB's ``compare`` plot).

    Samples left out of a robust fit (``result.excluded``) are marked with grey crosses.

    Parameters
    ----------
    result : CompareResult
        From ``est.compare(u, y)`` (:func:`torch_nssm.evaluation.compare`).
    y : array-like of shape (N,) or (N, p), or list of them
        The measured outputs given to ``compare``.
    ax : matplotlib Axes or sequence of Axes, optional
        One Axes per output (a new figure of ``p`` rows if omitted).
    record : int, default=0
        Which record to draw when ``compare`` was given a list of records.
    t : array-like of shape (N,), optional
        Time axis (default: the sample index).

    Returns
    -------
    ndarray of Axes, shape (p,)
    """
    from .evaluation import CompareResult

    if not isinstance(result, CompareResult):
        raise TypeError(f"result must be a CompareResult (from compare), got {type(result).__name__}")
    multi = isinstance(result.y_pred, list)
    pick = (lambda a: a[record]) if multi else (lambda a: a)
    if multi and not 0 <= record < len(result.y_pred):
        raise ValueError(f"record must lie in [0, {len(result.y_pred)}), got {record!r}")
    if multi != isinstance(y, (list, tuple)):
        raise ValueError("y must be a list of records exactly when compare was given one")
    meas = np.asarray(pick(y), dtype=float)
    pred = np.asarray(pick(result.y_pred), dtype=float)
    n = meas.shape[0]
    meas, pred = meas.reshape(n, -1), pred.reshape(pred.shape[0], -1)
    if pred.shape != meas.shape:
        raise ValueError(
            f"y has shape {meas.shape}, the predictions {pred.shape}: pass the y given to compare"
        )
    fit = np.atleast_2d(result.fit)[record if multi else 0]
    excluded = result.excluded
    if excluded is not None:
        excluded = np.asarray(pick(excluded), dtype=bool).reshape(n, -1)
    p = meas.shape[1]
    xlabel = "sample k" if t is None else "time"
    t = np.arange(n) if t is None else np.asarray(t, dtype=float).reshape(-1)
    if t.shape[0] != n:
        raise ValueError(f"t must have {n} entries, got {t.shape[0]}")
    if ax is None:
        _, axes = _pyplot().subplots(p, 1, figsize=(8.0, 2.8 * p), squeeze=False, sharex=True)
        axes = axes[:, 0]
    else:
        axes = np.asarray([ax] if not isinstance(ax, (Sequence, np.ndarray)) else ax, dtype=object).ravel()
        if len(axes) != p:
            raise ValueError(f"ax holds {len(axes)} Axes for {p} outputs")
    what = "simulated" if result.horizon is None else f"{result.horizon}-step predicted"
    for j, a in enumerate(axes):
        a.plot(t, meas[:, j], color="0.55", linewidth=1.0, label="measured")
        a.plot(t, pred[:, j], color="C0", linewidth=1.0, label=f"{what}: fit {fit[j]:.1f} %")
        if excluded is not None and excluded[:, j].any():
            m = excluded[:, j]
            a.plot(t[m], meas[m, j], "x", color="0.3", markersize=5, label=f"left out ({result.robust})")
        a.set_ylabel(f"y[{j}]" if p > 1 else "y")
        a.legend(fontsize="small", loc="best")
    axes[-1].set_xlabel(xlabel)
    return axes
