"""A first stage before EM: fit ``f`` and ``g`` to the records by robust simulation error.

EM from a poor start converges slowly, or into the wrong basin, when the process noise can explain
what ``f`` gets wrong.  This stage fits the free parameters of ``f`` and ``g`` and the first state
of each window by a robust (Cauchy) loss of the *noise-free simulation*'s output errors: the
output-error fit an engineer tries first, with a loss that outliers do not steer.

Horizon continuation.  Short windows (multiple shooting, each with its own first state) make the
problem nearly convex but say nothing about a time constant longer than a window, or an
integrator whose drift shows only over thousands of samples; one window over the whole record is
what the model is for but has many local minima from a poor start.  So the windows start short
(:func:`initial_horizon`, from the records' correlation time) and grow geometrically, each stage
started from the last, until one window covers each record.  Every stage is solved by
Levenberg-Marquardt (:mod:`torch_nssm.estimation.least_squares`) and *judged* by the free run over
the whole records; the stage whose free run is best is kept.  Where windows of some length make
the simulation diverge (an unstable model, an integrating plant simulated open-loop), the
continuation stops there and the report says so.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .._stats import MAD_TO_STD
from ..core.model import SequenceBatch, StateSpaceModel
from ..inference.prediction import free_run
from .free_parameters import FreeParameters
from .least_squares import Links, levenberg_marquardt

__all__ = [
    "FirstStageReport",
    "StageReport",
    "first_stage_applies",
    "initial_horizon",
    "simulation_error_fit",
]

#: Each stage's windows are this many times longer than the last stage's.
HORIZON_GROWTH = 4

#: Levenberg-Marquardt iterations (Jacobians) per stage.
STAGE_ITERATIONS = 30

#: A stage stops when a step lowers its robust loss by less than this, relatively: the next stage
#: moves the parameters more than that resolution would.
STAGE_FTOL = 1e-4


@dataclass
class StageReport:
    """One stage of the horizon continuation.

    Attributes
    ----------
    horizon : int
        Window length (samples); the last stage's windows cover each record.
    n_windows : int
    objective_before, objective_after : float
        The robust loss over the windows at the stage's start and result (the result's at the
        last run's scale, see :data:`SCALE_SHRINK`).
    free_run_scale : float
        Judge of the stage: the robust scale of the whole records' free-run output errors relative
        to that of ``y`` (mean over outputs; lower is better).
    n_iter : int
        Levenberg-Marquardt iterations.
    status : str
        The solver's stopping reason, or ``"diverged"`` (the simulation over these windows left
        the finite range at the stage's start).
    seconds : float
    track : str
        ``"continuation"`` (the growing windows) or ``"direct"`` (one window per record from the
        start).
    """

    horizon: int
    n_windows: int
    objective_before: float
    objective_after: float
    free_run_scale: float
    n_iter: int
    status: str
    seconds: float
    track: str = "continuation"


@dataclass
class FirstStageReport:
    """What the first stage did.

    Attributes
    ----------
    rmse_before, rmse_after : float
        Root mean square of the whole records' free-run output errors over the observed samples
        (outliers included) at the start and at the result.
    loss_before, loss_after : float
        The judge of the stages (:attr:`StageReport.free_run_scale`) at the start and the result.
    accepted : bool
        Whether the result was kept (its free run is better than the start's and finite).
    n_windows : int
        Number of windows of the kept stage.
    first_states : Tensor or None
        The fitted first state of every window of the kept stage ``(n_windows, nx)`` (``None`` if
        not accepted).
    record_states : Tensor or None
        The fitted first state of each record ``(B, nx)``.
    horizon : int or None
        Window length of the kept stage.
    horizon_limit : str or None
        Why the continuation stopped before one window covered each record (``None`` if it did not).
    stages : list of StageReport
    seconds : float
    interrupted : bool
        Ctrl-C stopped it: the result is the best stage completed before.
    free_run_scale_before_em, free_run_scale_after_em : float
        Set by the estimator: the robust scale (1.4826 MAD about 0) of the training records'
        free-run output errors of the first stage's model and of the EM fit.
    explained : float
        Set by the estimator: robust R² of the first stage's free run against ``y``.
    """

    rmse_before: float
    rmse_after: float
    loss_before: float
    loss_after: float
    accepted: bool
    n_windows: int
    first_states: Tensor | None = None
    record_states: Tensor | None = None
    horizon: int | None = None
    horizon_limit: str | None = None
    stages: list[StageReport] = field(default_factory=list)
    seconds: float = 0.0
    interrupted: bool = False
    free_run_scale_before_em: float = math.nan
    free_run_scale_after_em: float = math.nan
    explained: float = math.nan


#: Layers that mark a network: a model holding them gets the neural first stage
#: (:mod:`torch_nssm.estimation.neural_first_stage`) instead of this one (a simulation-error fit of
#: an untrained network is a training problem of its own, not a Levenberg-Marquardt fit of a few
#: parameters); a grey box's physical parameters get this one first, its network held
#: (:func:`torch_nssm.estimation.start.physical_part_first`).
NETWORK_LAYERS: tuple[type, ...] = (
    torch.nn.Linear,
    torch.nn.Bilinear,
    torch.nn.RNNBase,
    torch.nn.modules.conv._ConvNd,
)


def first_stage_applies(model: StateSpaceModel) -> bool:
    """Whether ``first_stage="auto"`` runs the first stage for ``model``.

    It does for physical and grey-box models: ``f`` or ``g`` has free parameters and neither holds a
    network layer (:data:`NETWORK_LAYERS`).
    """
    modules = (model.f, model.g)
    if not any(p.requires_grad for m in modules for p in m.parameters()):
        return False
    return not any(isinstance(sub, NETWORK_LAYERS) for m in modules for sub in m.modules())


# ---------------------------------------------------------------------------------------- windows
def _window_starts(data: SequenceBatch, horizon: int | None) -> list[tuple[int, int, int]]:
    """``(record, start, stop)`` of each window (windows shorter than 2 samples are dropped)."""
    out = []
    for b, n in enumerate(data.lengths.tolist()):
        step = n if horizon is None else horizon
        out += [(b, s, min(s + step, n)) for s in range(0, n, step) if min(s + step, n) - s >= 2]
    return out


def _windows(data: SequenceBatch, spans: list[tuple[int, int, int]]) -> SequenceBatch:
    return SequenceBatch.from_sequences(
        [data.u[s:e, b] for b, s, e in spans], [data.y[s:e, b] for b, s, e in spans]
    )


def _despiked(col: np.ndarray, width: int = 7) -> np.ndarray:
    """``col`` with isolated spikes replaced by the running median (a Hampel filter: deviations from
    the median of ``width`` samples beyond 4 robust standard deviations)."""
    if col.size < width:
        return col
    pad = width // 2
    padded = np.pad(col, pad, mode="edge")
    med = np.median(np.lib.stride_tricks.sliding_window_view(padded, width), axis=-1)
    dev = col - med
    s = MAD_TO_STD * np.median(np.abs(dev))
    return np.where(np.abs(dev) > 4.0 * s, med, col) if s > 0 else col


def initial_horizon(data: SequenceBatch, n_states: int) -> int:
    """The first stage's shortest windows: twice the lag at which the autocorrelation of the
    outputs (spikes removed by a running median, then clipped) falls below one half, at least
    ``max(10, 4 nx)`` samples.

    Windows about as long as the outputs' memory see the dynamics that matter at that scale and
    still start each window from a state fitted to it; shorter ones fit the local shape of the
    records only.
    """
    lags = []
    for y in data.unpad(data.y):
        y = y.detach().cpu().numpy()
        for j in range(y.shape[1]):
            col = y[:, j]
            col = col[np.isfinite(col)]
            if col.size < 8:
                continue
            col = _despiked(col)
            med = np.median(col)
            s = MAD_TO_STD * np.median(np.abs(col - med))
            if not s > 0:
                continue
            z = np.clip(col - med, -3 * s, 3 * s)
            z = z - z.mean()
            n = z.size
            spec = np.fft.rfft(z, 2 * n)
            acf = np.fft.irfft(spec * np.conj(spec))[:n]
            acf = acf / max(acf[0], 1e-300)
            below = np.nonzero(acf < 0.5)[0]
            lags.append(int(below[0]) if below.size else n)
    shortest = max(10, 4 * n_states)
    longest = int(data.lengths.max())
    lag = int(np.median(lags)) if lags else shortest
    return int(min(max(2 * lag, shortest), longest))


def _horizons(data: SequenceBatch, first: int) -> list[int]:
    longest = int(data.lengths.max())
    out = [min(first, longest)]
    while out[-1] < longest:
        out.append(min(out[-1] * HORIZON_GROWTH, longest))
    return out


# ---------------------------------------------------------------------------------------- simulation
def _simulate(forward, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Outputs ``(T, W, p)`` of the noise-free simulation from ``x0`` ``(W, nx)``, and the state after
    the last sample ``(W, nx)`` (``forward(label, x, u)`` calls ``f`` or ``g``)."""
    x, states = x0, []
    for k in range(u.shape[0]):
        states.append(x)
        x = forward("f", x, u[k])
    return forward("g", torch.stack(states), u), x


class _Shooting:
    """The scaled output errors of the simulation over a batch of windows, for many parameter
    vectors at once (the residual function of :func:`levenberg_marquardt`)."""

    def __init__(self, params: FreeParameters, windows: SequenceBatch, scale: Tensor):
        self.params = params
        self.u = windows.u
        self.mask = windows.obs_mask  # (T, W, p)
        self.y = torch.where(self.mask, windows.y, torch.zeros_like(windows.y))
        self.scale = scale
        T, W, p = windows.y.shape
        # rows window-major: (W, T * p)
        self.weight = self.mask.permute(1, 0, 2).reshape(W, T * p).to(windows.y.dtype)

    @torch.inference_mode()
    def __call__(self, thetas: Tensor, x0s: Tensor) -> tuple[Tensor, Tensor]:
        out, ends = self.params.map(_simulate, thetas, x0s, self.u, batched=(True, False))  # (S, T, W, p)
        r = torch.where(self.mask, (self.y - out) / self.scale, torch.zeros_like(out))
        S, T, W, p = r.shape
        return r.permute(0, 2, 1, 3).reshape(S, W, T * p), ends

    @torch.no_grad()
    def states_at(self, theta: Tensor, x0: Tensor, steps: list[int]) -> Tensor:
        """The simulated state of each window at its step ``steps[w]`` ``(W, nx)``."""
        x, out = x0, x0.clone()
        steps_t = torch.as_tensor(steps, device=x0.device)
        for k in range(int(max(steps)) + 1):
            here = steps_t == k
            if bool(here.any()):
                out[here] = x[here]
            if k + 1 < self.u.shape[0]:
                x = self.params.map(
                    lambda fw, xx, uu: fw("f", xx, uu), theta.unsqueeze(0), x.unsqueeze(0), self.u[k],
                    batched=(True, False),
                )[0]
        return out


def _robust_scales(values: Tensor, mask: Tensor, about_median: bool = False) -> Tensor:
    """Robust scale (1.4826 MAD about 0, or about the median) of each output's observed ``values``
    (last axis: outputs; ``mask`` of the same shape), 1 where it is not positive and finite."""
    scale = []
    for j in range(values.shape[-1]):
        col = values[..., j][mask[..., j]]
        if about_median and col.numel():
            col = col - col.median()
        s = MAD_TO_STD * col.abs().median() if col.numel() else values.new_tensor(1.0)
        scale.append(s if bool(torch.isfinite(s) & (s > 0)) else values.new_tensor(1.0))
    return torch.stack(scale)


def _output_scale(data: SequenceBatch) -> Tensor:
    """Robust spread (1.4826 MAD about the median) of each output over all observed samples."""
    return _robust_scales(data.y, torch.isfinite(data.y), about_median=True)


def _free_run_errors(model: StateSpaceModel, data: SequenceBatch, x0: Tensor) -> Tensor:
    """``y - yhat`` of each record's free run from its first state ``x0`` ``(B, nx)`` ((T, B, p), NaN
    where nothing is observed)."""
    start = StateSpaceModel(model.f, model.g, model.Rw, model.noise, x0, model.x0_cov)
    outputs = free_run(start, data.u)[1]
    return torch.where(data.obs_mask, data.y - outputs, torch.full_like(outputs, math.nan))


def _judge(errors: Tensor, y_scale: Tensor) -> float:
    """Robust scale (about 0) of the free-run errors relative to ``y``'s, mean over outputs (inf for
    a free run that left the finite range)."""
    values = []
    for j in range(errors.shape[-1]):
        e = errors[..., j]
        e = e[~torch.isnan(e)]
        if not e.numel():
            continue
        if not bool(torch.isfinite(e).all()):
            return math.inf
        values.append(float(MAD_TO_STD * e.abs().median() / y_scale[j]))
    return float(np.mean(values)) if values else math.inf


def _rmse(errors: Tensor) -> float:
    e = errors[~torch.isnan(errors)]
    if not e.numel():
        return math.nan
    return float(torch.sqrt((e * e).mean())) if bool(torch.isfinite(e).all()) else math.inf


def _record_starts(model: StateSpaceModel, data: SequenceBatch) -> Tensor:
    """Each record's free-run state path from ``x0_mean`` ``(T, B, nx)``, from where the start's
    simulation diverges (non-finite, or beyond 1e6 times the prior's scale) on: ``x0_mean``, a
    sane first state for the windows there."""
    states = free_run(model, data.u)[0]
    fallback = model.per_sequence("x0_mean", data.n_sequences).unsqueeze(0).expand_as(states)
    spread = 0.0 if model.x0_cov is None else float(model.x0_cov.diagonal().sqrt().max())
    scale = max(1.0, float(model.x0_mean.abs().max()) + spread)
    bad = ~torch.isfinite(states).all(-1, keepdim=True) | (states.abs() > 1e6 * scale).any(-1, keepdim=True)
    bad = torch.cummax(bad.to(torch.uint8), dim=0).values.bool()  # from the first bad step on
    return torch.where(bad, fallback, states)


# ---------------------------------------------------------------------------------------- the fit
#: The continuity between consecutive windows (multiple shooting): a mismatch of this fraction of
#: a state's spread over the windows' first states costs as much as one scaled output error.
CONTINUITY = 0.1


def _links(spans: list[tuple[int, int, int]], x0: Tensor) -> Links | None:
    """Which consecutive windows continue each other (the same record, adjacent), and the mismatch
    scale of each state (:data:`CONTINUITY` times its robust spread over the windows' first states)."""
    linked = [b == nb and e == ns for (b, _, e), (nb, ns, _) in zip(spans[:-1], spans[1:])]
    if not any(linked):
        return None
    med = x0.median(0).values
    spread = MAD_TO_STD * (x0 - med).abs().median(0).values
    fallback = x0.std(0) if x0.shape[0] > 1 else torch.ones_like(med)
    spread = torch.where(spread > 0, spread, fallback)
    spread = torch.where(spread > 0, spread, torch.ones_like(spread))
    return Links(torch.as_tensor(linked, device=x0.device), CONTINUITY * spread)


#: The first Levenberg-Marquardt step's damping (Marquardt's scaling) of a stage whose windows cover
#: each record (or are :data:`DIRECT_HORIZON` long) and start from the user's start: the direct
#: track, or ``horizons=None``.  That is the output-error problem with its many local minima, 30-50
#: % from its minimum; a nearly Gauss-Newton first step there jumps a slow plant into another basin
#: (the suite's tanks on seeds 1, 4, 6, 7: the direct fit's free run 5-90 times worse than scipy's
#: output-error least squares from the same start); damped by 1 it reaches that basin
#: (benchmarks/README.md, "Seeds, and the direct track's first step").  The continuation's first
#: windows are short (nearly convex: there the Gauss-Newton step is what reaches the basin, e.g. the
#: paper's example from a = b = c = 0.5 in windows of 50), its later stages and the rescaled passes
#: start at the last result: :data:`WARM_DAMPING`, as the M-step's Gauss-Newton.
COLD_DAMPING = 1.0
WARM_DAMPING = 1e-3

#: A stage's Levenberg-Marquardt run starts again from its result with the robust scale of its
#: residuals when that scale fell below the scale used by this factor (on some output), at most
#: SCALE_PASSES runs in all.  The first run's scale is that of the stage's starting errors: far from
#: the data it is large, the robust loss is then nearly least squares, and gross outliers still pull
#: the fit (the tanks' sensor offset with 5 % outliers); at the residuals' own scale they do not.
#: The soft-L1 output-error baseline of the suite and the neural first stage rescale the same way.
SCALE_SHRINK = 4.0
SCALE_PASSES = 3


def _fit_stage(
    params: FreeParameters,
    theta: Tensor,
    spans: list[tuple[int, int, int]],
    windows: SequenceBatch,
    x0: Tensor,
    max_iter: int,
    loss: str,
    cold: bool = False,
):
    """Levenberg-Marquardt over one stage's windows, consecutive windows softly continuous; the
    robust scale of the output errors fixed at the stage's start (per output), and renewed from the
    result while it shrinks by :data:`SCALE_SHRINK` (:data:`SCALE_PASSES` runs at most).  ``cold``: a
    stage of long windows from the start (its first run damped by :data:`COLD_DAMPING`)."""
    ones = torch.ones(windows.y.shape[-1], dtype=x0.dtype, device=x0.device)
    unscaled = _Shooting(params, windows, ones)
    mask = unscaled.mask.transpose(0, 1)

    def errors(th: Tensor, x: Tensor) -> Tensor:
        r = unscaled(th.unsqueeze(0), x.unsqueeze(0))[0][0]
        return r.reshape(windows.n_sequences, windows.n_steps, -1)

    scale = _robust_scales(errors(theta, x0), mask)
    links = _links(spans, x0)
    initial, iterations = None, 0
    for run in range(SCALE_PASSES):
        problem = _Shooting(params, windows, scale)
        result = levenberg_marquardt(
            problem, theta, x0, problem.weight, loss=loss, links=links, max_iter=max_iter, ftol=STAGE_FTOL,
            damping=COLD_DAMPING if cold and run == 0 else WARM_DAMPING, speculative=True,
        )
        initial = result.initial_objective if initial is None else initial
        iterations += result.n_iter
        if loss == "linear" or result.status == "not_finite" or run == SCALE_PASSES - 1:
            break
        theta, x0 = result.theta, result.local
        fresh = _robust_scales(errors(theta, x0), mask)
        if not bool((fresh * SCALE_SHRINK < scale).any()):
            break
        scale = torch.minimum(scale, fresh)
    result.initial_objective, result.n_iter = initial, iterations
    return result, problem


def simulation_error_fit(
    model: StateSpaceModel,
    data: SequenceBatch,
    *,
    segment_length: int | None = None,
    horizons: str | list[int] | None = "auto",
    max_iter: int = STAGE_ITERATIONS,
    loss: str = "cauchy",
) -> FirstStageReport:
    """Fit ``model.f``, ``model.g`` (in place) and the first states by robust simulation error.

    Parameters
    ----------
    model : StateSpaceModel
        The start; its modules' free parameters are updated in place if the fit is accepted.
    data : SequenceBatch
    segment_length : int, optional
        One stage with windows of this many samples (multiple shooting), instead of ``horizons``.
    horizons : "auto", list of int or None
        ``"auto"``: windows from :func:`initial_horizon`, growing by :data:`HORIZON_GROWTH` until one
        window covers each record (stopped early once two stages in a row do not improve the free
        run), and also one window per record (at most :data:`DIRECT_HORIZON` samples) from the
        start (a robust output-error fit); the best free run is kept, so the first stage simulates
        the records at least as well, by its judge, as a robust output-error fit from the start.
        A list: those window lengths in order; ``None``: one window per record.
    max_iter : int
        Levenberg-Marquardt iterations per stage.
    loss : {"cauchy", "soft_l1", "linear"}
        Loss of the scaled output errors (their scale: a robust spread of each stage's starting
        errors, per output).

    Returns
    -------
    FirstStageReport
        The kept stage's window and record first states; ``model.x0_mean`` is not changed.
    """
    clock = time.perf_counter()
    params = FreeParameters({"f": model.f, "g": model.g})
    if segment_length is not None:
        plan = [int(segment_length)]
    elif horizons == "auto":
        plan = _horizons(data, initial_horizon(data, model.state_dim))
    elif horizons is None:
        plan = [int(data.lengths.max())]
    else:
        plan = [int(h) for h in horizons]
    ladder = _Ladder(model, data, params, max_iter, loss)
    report = FirstStageReport(ladder.rmse0, ladder.rmse0, ladder.judged0, ladder.judged0, False, 0)
    if params.size == 0:
        report.seconds = time.perf_counter() - clock
        return report
    auto = horizons == "auto" and segment_length is None
    try:
        ladder.run(plan, report, "continuation", early_stop=auto)
        direct = min(int(data.lengths.max()), DIRECT_HORIZON)
        if auto and plan[0] < direct:
            params.assign(ladder.theta0)
            ladder.run([direct], report, "direct", early_stop=False)
    except KeyboardInterrupt:  # Ctrl-C: the best stage completed so far
        report.interrupted = True
    except (OverflowError, FloatingPointError):  # data at the edge of the floats: the best stage so far
        pass
    judged, theta_best, window_x0, record_x0, horizon, errors = ladder.best
    report.seconds = time.perf_counter() - clock
    if window_x0 is None:  # no stage simulated the records better than the start
        params.assign(ladder.theta0)
        return report
    params.assign(theta_best)
    report.accepted = True
    report.loss_after = judged
    report.rmse_after = _rmse(errors)
    report.first_states = window_x0
    report.record_states = record_x0
    report.horizon = horizon
    report.n_windows = window_x0.shape[0]
    return report


# The direct fit (one window per record from the start) always runs after the continuation: the
# continuation's free window states can settle a slow plant in a wrong basin that fits the
# training record (the tanks plant: a negative upper level, h1_max 4.7 cm against 10, training
# explained 0.996, validation RMSE 3.5 cm against output error's 0.064), where output error from
# the start, tied to one first state, finds the physical one.  On records longer than
# DIRECT_HORIZON its windows are that long (multiple shooting with long windows, batched): one
# window over a 40,000-sample record costs about 17 s per Levenberg-Marquardt iteration (a Python
# step loop over the whole record for every finite-difference column).
DIRECT_HORIZON = 2048

#: A stage improves on the best so far when its judge is lower by this fraction.
IMPROVEMENT = 0.01


class _Ladder:
    """Runs stages of windows from a start, judging each by the whole records' free run and keeping
    the best (:attr:`best`: judge, parameters, window and record first states, horizon, errors)."""

    def __init__(self, model, data, params, max_iter, loss):
        self.model, self.data, self.params = model, data, params
        self.max_iter, self.loss = max_iter, loss
        self.y_scale = _output_scale(data)
        with torch.no_grad():
            self.path = _record_starts(model, data)  # (T, B, nx)
            errors = _free_run_errors(model, data, model.per_sequence("x0_mean", data.n_sequences))
        self.judged0, self.rmse0 = _judge(errors, self.y_scale), _rmse(errors)
        self.theta0 = params.vector()
        self.best = (self.judged0, self.theta0, None, None, None, errors)
        # windows this long from the start are an output-error fit: damped first (COLD_DAMPING)
        self.long_window = min(int(data.lengths.max()), DIRECT_HORIZON)

    def run(self, plan: list[int], report: FirstStageReport, track: str, early_stop: bool) -> None:
        theta, previous, stale = self.params.vector(), None, 0
        for horizon in plan:
            tic = time.perf_counter()
            spans = _window_starts(self.data, horizon)
            windows = _windows(self.data, spans)
            if previous is None:
                x0 = torch.stack([self.path[s, b] for b, s, _ in spans])
            else:
                x0 = _continued_states(previous, spans, theta)
            try:
                result, problem = _fit_stage(
                    self.params, theta, spans, windows, x0, self.max_iter, self.loss,
                    cold=previous is None and horizon >= self.long_window,
                )
            except (RuntimeError, torch.linalg.LinAlgError) as exc:  # a module that fails on the way
                report.horizon_limit = f"the fit over windows of {horizon} samples failed ({exc})"
                return
            if result.status == "not_finite":
                report.stages.append(
                    StageReport(
                        horizon, len(spans), math.inf, math.inf, math.inf, 0, "diverged",
                        time.perf_counter() - tic, track,
                    )
                )
                reached = previous[3] if previous else None
                report.horizon_limit = (
                    f"the noise-free simulation diverges over windows of {horizon} samples"
                    + (f": the stages stop at windows of {reached} samples" if reached else "")
                )
                return
            theta = result.theta
            self.params.assign(theta)
            firsts = [i for i, (_, s, _) in enumerate(spans) if s == 0]
            record_x0 = result.local[torch.as_tensor(firsts, device=x0.device)]
            with torch.no_grad():
                errors = _free_run_errors(self.model, self.data, record_x0)
            judged = _judge(errors, self.y_scale)
            report.stages.append(
                StageReport(
                    horizon, len(spans), result.initial_objective, result.objective, judged, result.n_iter,
                    result.status, time.perf_counter() - tic, track,
                )
            )
            improved = judged < (1.0 - IMPROVEMENT) * self.best[0]
            first = self.best[2] is None and math.isfinite(judged) and judged <= self.best[0]
            if judged < self.best[0] or first:
                self.best = (judged, theta.clone(), result.local.clone(), record_x0.clone(), horizon, errors)
            stale = 0 if improved else stale + 1
            previous = (spans, result.local, problem, horizon)
            if early_stop and stale >= 2 and horizon != plan[-1]:
                report.horizon_limit = (
                    f"two stages in a row (windows of {plan[plan.index(horizon) - 1]} and {horizon} samples) "
                    "did not improve the free run of the records: the stages stop there"
                )
                return


def _continued_states(previous, spans: list[tuple[int, int, int]], theta: Tensor) -> Tensor:
    """First states of the new windows from the last stage: a new window starting where an old one
    did takes its fitted state; otherwise the old window's simulation is read at that sample."""
    old_spans, old_x0, problem, _ = previous
    index, steps = [], []
    for b, s, _ in spans:
        for i, (ob, os_, oe) in enumerate(old_spans):
            if ob == b and os_ <= s < oe:
                index.append(i)
                steps.append(s - os_)
                break
    x0 = old_x0[torch.as_tensor(index, device=old_x0.device)]
    if all(k == 0 for k in steps):
        return x0.clone()
    sub = _Shooting(problem.params, _subset(problem, index), problem.scale)
    return sub.states_at(theta, x0, steps)


def _subset(problem: _Shooting, index: list[int]) -> SequenceBatch:
    idx = torch.as_tensor(index, device=problem.u.device)
    y = torch.where(problem.mask, problem.y, torch.full_like(problem.y, math.nan))
    T = problem.u.shape[0]
    return SequenceBatch(problem.u[:, idx], y[:, idx], torch.full((len(index),), T, device=problem.u.device))
