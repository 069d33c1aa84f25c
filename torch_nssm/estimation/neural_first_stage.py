"""A first stage for networks: train ``f`` and ``g`` by robust simulation error over short windows.

A network ``f`` starts far from anything (an :class:`~torch_nssm.neural.MLPTransition` starts at the
random walk), and EM from there lets the process noise explain what ``f`` does not simulate yet.
Neural state-space models are trained by *simulation error* instead, over windows of ``horizon``
samples (truncated-horizon multiple shooting; SUBNET: Beintema, Schoukens & Toth 2021/2023;
Forgione & Piga 2021), and this stage does that before EM:

* every window is simulated noise-free from its own first state and the output errors, scaled by
  a robust spread of ``y``, enter a **robust loss**: Cauchy, its scale 2.385 times the errors'
  robust standard deviation (1.4826 MAD), so outliers and badly simulated windows do not steer
  the fit (``loss="squared"``: the least-squares baseline for Gaussian noise);
* ``optimizer="lbfgs"`` (default): the windows tile the record, each window's first state is a free
  parameter (in units of the network's state normalisation ``x_scale``), and full-batch LBFGS runs
  in rounds of ``eval_every`` iterations, the Cauchy scale re-estimated from the current errors at
  the start of each round; phases of doubling window length follow, past ``4 * horizon`` while
  a phase improves the held-out score;
* ``optimizer="adam"`` (SUBNET's scheme): windows start anywhere, each window's first state comes
  from an **encoder** (an MLP of the ``encoder_lags`` outputs and inputs before it, trained
  jointly), and Adam runs over minibatches of windows with a cosine-decaying step size;
* both **stop early** on the held-out final part of each record (``validation_fraction``): its free
  run, continued from the training part's last state (LBFGS) or from the encoded state (Adam), is
  scored after every round or every ``eval_every`` steps by the trimmed RMS of its output errors
  (the largest 10 %, outliers, left out); training (each LBFGS phase) ends after ``patience``
  evaluations without a better score, ``max_iter`` being a safeguard;
* the parameters kept are those of the best held-out score, except with LBFGS on short held-out
  parts (fewer than 10,000 samples in all, a weak guide alone): there every evaluation also scores
  the whole records' free run from the fitted first states (long records in stretches of about
  4,000 samples, each from its first window's state), and the iterate kept has the best held-out
  score among those whose free run is within 1.2 times the best one, unless its held-out score is
  more than twice the best.

The result is kept when the whole record's free run from the fitted first state is better than the
start's.  On the pendulum of the suite (2,000 samples, 3 % outliers, ``MLPTransition(2, 1,
hidden=(32,))``) LBFGS reaches a validation free-run RMSE of 0.029 rad in 2,000 iterations (the
early stop ending each phase) where Adam over encoded windows reach 0.049 rad in 1,000 steps; on
Silverbox (90,372 samples, a 3-state network) LBFGS reaches 0.82 mV on the full arrow in 2,825
iterations, its windows up to 1,600 samples (``benchmarks/neural.py``, ``benchmarks/README.md``).
The entry point is :func:`neural_first_stage`; design notes: ``docs/design.md`` ("How a neural fit starts").
"""

from __future__ import annotations

import copy
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from .._stats import MAD_TO_STD
from ..core.model import SequenceBatch, StateSpaceModel
from .first_stage import NETWORK_LAYERS, FirstStageReport

__all__ = [
    "NeuralFirstStageOptions",
    "NeuralFirstStageReport",
    "StateEncoder",
    "default_options",
    "holds_network",
    "neural_first_stage",
    "fit_initial_states",
    "start_noise_levels",
    "trimmed_rms",
]

#: Cauchy's 95 %-efficiency constant: the loss's scale in units of the errors' robust s.d.
CAUCHY_C = 2.385
#: Normalised encoder inputs are clipped to this many robust standard deviations (an outlier in the
#: encoder's past then moves the encoded state by a bounded amount).
ENCODER_CLIP = 5.0
#: Share of the largest held-out errors left out of the early-stopping score.
TRIM = 0.1
#: LBFGS: iterations per window-length phase at most.  A safeguard: the held-out early stop ends
#: each phase first on the records measured (phases of 150-925 iterations on the pendulum,
#: Wiener-Hammerstein, oscillator and tanks of the suite and on Silverbox); a tighter cap stops
#: training while the held-out score still improves (200 per phase: Silverbox 3.4 mV against
#: 1.47 mV on the full arrow).
LBFGS_MAX_ITER = 1000
#: LBFGS: iterations per phase at most when no record is long enough for a held-out part: the
#: training windows' score then keeps improving, so the cap, not the patience, ends each phase.
LBFGS_MAX_ITER_NO_HOLDOUT = 200
#: LBFGS: held-out evaluations (rounds of ``eval_every`` iterations) without a better score before
#: a phase stops, where the held-out parts hold at least ``SHORT_HOLDOUT`` samples (Silverbox:
#: patience 10 ends at the same held-out score in 1.7 times the CPU).
LBFGS_PATIENCE = 6
#: LBFGS: the same where the held-out parts are shorter.  A short held-out part is a weak guide of
#: progress: on the suite's Bouc-Wen (450 held-out samples) its score rises by 16 % over 450
#: iterations while the validation RMSE falls by 25 %, and the phase of 200-sample windows that
#: follows improves both only after 225 iterations.  Patience 20 there: Bouc-Wen 2.98e-5 -> 1.45e-5
#: m, the oscillator's network seeds 0 / 1 / 2 0.058 / 0.070 / 0.177 -> 0.039 / 0.032 / 0.050 mm,
#: the pendulum, Wiener-Hammerstein and the tanks unchanged, at 1-10 times the CPU (first stage
#: alone; benchmarks/README "How the neural first stage's training ends").
LBFGS_PATIENCE_SHORT_HOLDOUT = 20
#: Held-out samples (all records together) from which ``LBFGS_PATIENCE`` applies.
SHORT_HOLDOUT = 10_000
#: LBFGS with short held-out parts: the iterate kept has the best held-out score among those whose
#: whole records' free run (from the fitted first states) is within this factor of the best one.
#: A short held-out part alone keeps iterates that simulate the training part poorly: on 28
#: trainings of the suite's plants and the pendulum family better in 11, worse in one (6 %), the
#: pendulum family's worst 2.58 -> 1.73 times the physical model (benchmarks/README "Which iterate
#: the first stage keeps").
FREE_RUN_SLACK = 1.2
#: ... unless its held-out score is more than this factor above the best one: the held-out end
#: then sees what the training part does not (the suite's tanks: a level above the training
#: part's range; the rule's iterate scores 27 times the best there, 1.0-1.41 times on the other
#: 26 trainings' snapshots), and the best held-out score's iterate is kept.
HELD_OUT_GUARD = 2.0
#: The free run of ``FREE_RUN_SLACK`` runs a long record in stretches of about this many samples,
#: side by side, each from its first window's fitted state: longer than the records the rule is
#: measured on (2,000-3,000 samples, run whole); on the suite's axis (25,000 samples) 6 stretches
#: instead of one run of 25,000 steps per evaluation, which doubled the first stage's CPU.
FREE_RUN_SPAN = 4000


@dataclass
class NeuralFirstStageOptions:
    """Settings of :func:`neural_first_stage`.

    Attributes
    ----------
    optimizer : {"lbfgs", "adam"}
        Full-batch LBFGS over tiled windows with free first states (default), or Adam over
        minibatches of windows whose first states come from an encoder (SUBNET).
    horizon : int
        Window length: samples simulated from each window's first state.
    loss : {"cauchy", "squared"}
        Robust (default) or least-squares loss of the scaled output errors.
    validation_fraction : float
        Final share of each record held out for the early stop (used where it holds at least
        ``2 * horizon`` samples; 0: no hold-out, the training windows' trimmed RMS decides).
    max_iter : int or None
        LBFGS iterations per window-length phase, or Adam steps, at most (default 1,000 per phase,
        a safeguard: the patience ends training first on the records measured; 200 per phase
        when no record is long enough for a held-out part, where the patience rarely ends it; Adam:
        3,000).
    max_horizon : int or None
        LBFGS: the longest window; the phases double ``horizon`` up to it.  Default: at least
        to ``4 * horizon``, then on while a phase improves the held-out score, up to the longest
        record's training part (``4 * horizon`` when nothing is held out).
    eval_every : int or None
        LBFGS iterations per round, or Adam steps between evaluations (default 25, and one pass
        over the windows clipped to 25-250 steps).
    patience : int or None
        Evaluations without improvement of the held-out score before stopping (LBFGS: per phase,
        each phase measured against the best score of all phases; default 20 where the held-out
        parts hold fewer than 10,000 samples, 6 where they hold more or nothing is held out;
        Adam: 12).
    max_seconds : float or None
        Wall-clock budget of the training loop.
    batch_size : int
        Adam: windows per step.
    learning_rate : float
        Adam: the initial step size (cosine decay to 1/20 of it over ``max_iter`` steps).
    encoder_lags : int
        Adam: past outputs and inputs the encoder reads (SUBNET's ``n_a = n_b``).
    encoder_hidden : tuple of int
        Adam: hidden widths of the encoder (tanh).
    clip_norm : float
        Adam: gradient-norm clip.
    weight_decay : float
        An L2 penalty on the network: ``weight_decay`` times the sum of the squared weights of the
        linear layers of ``f`` and ``g`` (not their biases, the encoder or the windows' first
        states) is added to the mean per-sample loss (default 0: none; measured as mixed across
        the suite's plants, ``benchmarks/README.md``, "Initialisations, weight decay, a longer
        held-out end and a linear bypass on short records").
    """

    optimizer: str = "lbfgs"
    horizon: int = 50
    loss: str = "cauchy"
    validation_fraction: float = 0.15
    max_iter: int | None = None
    max_horizon: int | None = None
    eval_every: int | None = None
    patience: int | None = None
    max_seconds: float | None = None
    batch_size: int = 256
    learning_rate: float = 3e-3
    encoder_lags: int = 20
    encoder_hidden: tuple[int, ...] = (64,)
    clip_norm: float = 10.0
    weight_decay: float = 0.0

    def check(self) -> None:
        """Raise ``ValueError`` naming a setting that is out of range."""
        if self.optimizer not in ("lbfgs", "adam"):
            raise ValueError(f"optimizer must be 'lbfgs' or 'adam', got {self.optimizer!r}")
        if self.loss not in ("cauchy", "squared"):
            raise ValueError(f"loss must be 'cauchy' or 'squared', got {self.loss!r}")
        for name, low, optional in (
            ("horizon", 2, False),
            ("batch_size", 1, False),
            ("encoder_lags", 1, False),
            ("max_iter", 1, True),
            ("eval_every", 1, True),
            ("patience", 1, True),
            ("max_horizon", 2, True),
        ):
            value = getattr(self, name)
            if value is None and optional:
                continue
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if not 0 <= self.validation_fraction < 1:
            raise ValueError(f"validation_fraction must be in [0, 1), got {self.validation_fraction!r}")
        for name in ("learning_rate", "clip_norm"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value!r}")
        decay = self.weight_decay
        if isinstance(decay, bool) or not isinstance(decay, (int, float)) or not 0 <= decay < math.inf:
            raise ValueError(f"weight_decay must be a finite number >= 0, got {decay!r}")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be None or > 0, got {self.max_seconds!r}")
        if not all(isinstance(h, int) and h >= 1 for h in self.encoder_hidden):
            raise ValueError(f"encoder_hidden must hold integers >= 1, got {self.encoder_hidden!r}")


@dataclass
class NeuralFirstStageReport:
    """What :func:`neural_first_stage` did.

    Attributes
    ----------
    accepted : bool
        Whether the trained modules were kept: the whole records' free run from the fitted first
        states is finite and better than the start's.  Otherwise ``f`` and ``g`` are restored.
    improved : bool
        Whether the whole records' free run improved (trimmed RMS of the output errors).
    free_run_before, free_run_after : float
        Trimmed RMS of the whole records' free-run output errors (in ``y``'s units; the largest
        10 % left out): the start from ``x0_mean``, and the trained model from the fitted first
        states.
    optimizer : str
    iterations : int
        LBFGS iterations or Adam steps taken.
    evaluations : int
        Held-out evaluations (the "epochs": one per LBFGS round or per ``eval_every`` Adam steps).
    best_iteration : int
        The iteration whose parameters were kept.
    train_losses, validation_losses : list of float
        Per evaluation: the training loss (LBFGS: the round's final loss, at its own Cauchy scale,
        with the weight penalty; Adam: the mean minibatch loss since the previous evaluation) and
        the held-out score (trimmed RMS of the held-out free run's scaled output errors; of the
        training windows' when nothing is held out).
    free_runs : list of float
        LBFGS with held-out parts of fewer than 10,000 samples: per evaluation, the whole records'
        free-run score from the fitted window states (trimmed RMS of the scaled output errors;
        records longer than ``FREE_RUN_SPAN`` in stretches); the iterate kept has the best
        held-out score among those within ``FREE_RUN_SLACK`` (1.2) times the best of these, unless
        that score is more than ``HELD_OUT_GUARD`` (2) times the best held-out score.  Empty
        otherwise (the best held-out score is kept).
    horizon : int
        The window length.
    n_windows : int
        LBFGS: training windows; Adam: window start positions.
    seconds : float
        Wall time of the whole stage.
    stop_reason : str
        ``"patience"``, ``"max_iter"``, ``"max_seconds"`` or ``"converged"`` (an LBFGS round
        ended without progress).
    first_states : Tensor
        The fitted first state of each record, ``(B, nx)``.
    encoder : nn.Module or None
        Adam: the trained :class:`StateEncoder`.
    loss : str
    explained : float
        Robust R² of the whole records' free run against ``y`` (set by the start policy,
        :func:`torch_nssm.estimation.start.first_stage_start`; NaN otherwise).
    free_run_scale_before_em, free_run_scale_after_em : float
        Robust scale of the training free-run errors after the stage and after EM (set by the
        simulation check after a fit, :func:`torch_nssm.estimation.start.check_simulation`).
    interrupted : bool
        Always False: the stage is not interrupted by Ctrl-C (the fit is).
    physical_stage : FirstStageReport or None
        A grey box's physical first stage before this one, the network held (set by the start
        policy, :func:`torch_nssm.estimation.start.physical_part_first`); ``None`` otherwise.
    """

    accepted: bool
    improved: bool
    free_run_before: float
    free_run_after: float
    optimizer: str
    iterations: int
    evaluations: int
    best_iteration: int
    train_losses: list[float]
    validation_losses: list[float]
    horizon: int
    n_windows: int
    seconds: float
    stop_reason: str
    first_states: Tensor
    free_runs: list[float] = field(default_factory=list)
    encoder: nn.Module | None = field(default=None, repr=False)
    loss: str = "cauchy"
    explained: float = math.nan
    free_run_scale_before_em: float = math.nan
    free_run_scale_after_em: float = math.nan
    interrupted: bool = False
    physical_stage: FirstStageReport | None = field(default=None, repr=False)


class StateEncoder(nn.Module):
    """SUBNET's encoder: the state at ``k`` from the ``lags`` outputs and inputs before ``k``.

    ``x_k = MLP([clip(y_norm_{k-lags:k}), u_norm_{k-lags:k}])``, outputs normalised by a robust
    centre and scale and clipped at :data:`ENCODER_CLIP` (missing outputs enter as 0, the centre),
    inputs by their mean and standard deviation.

    Parameters
    ----------
    lags : int
    p, nu, nx : int
        Outputs, inputs, states.
    hidden : tuple of int
    y_center, y_scale : Tensor, shape (p,)
    u_center, u_scale : Tensor, shape (nu,)
    """

    def __init__(
        self,
        lags: int,
        p: int,
        nu: int,
        nx: int,
        hidden: tuple[int, ...],
        y_center: Tensor,
        y_scale: Tensor,
        u_center: Tensor,
        u_scale: Tensor,
    ) -> None:
        super().__init__()
        self.lags = int(lags)
        kw = dict(dtype=y_center.dtype, device=y_center.device)
        layers: list[nn.Module] = []
        width = lags * (p + nu)
        for h in hidden:
            layers += [nn.Linear(width, h, **kw), nn.Tanh()]
            width = h
        layers.append(nn.Linear(width, nx, **kw))
        self.net = nn.Sequential(*layers)
        self.register_buffer("y_center", y_center.clone())
        self.register_buffer("y_scale", y_scale.clone())
        self.register_buffer("u_center", u_center.clone())
        self.register_buffer("u_scale", u_scale.clone())

    def forward(self, y_past: Tensor, u_past: Tensor) -> Tensor:
        """States ``(..., nx)`` from past outputs ``(..., lags, p)`` (NaN: missing) and inputs
        ``(..., lags, nu)``."""
        yn = ((y_past - self.y_center) / self.y_scale).clamp(-ENCODER_CLIP, ENCODER_CLIP)
        yn = torch.nan_to_num(yn, nan=0.0)
        un = (u_past - self.u_center) / self.u_scale
        return self.net(torch.cat([yn.flatten(-2), un.flatten(-2)], dim=-1))


def holds_network(model: StateSpaceModel) -> bool:
    """Whether ``f`` or ``g`` has free parameters and holds a network layer
    (:data:`~torch_nssm.estimation.first_stage.NETWORK_LAYERS`): the models this stage is for."""
    modules = (model.f, model.g)
    if not any(p.requires_grad for m in modules for p in m.parameters()):
        return False
    return any(isinstance(sub, NETWORK_LAYERS) for m in modules for sub in m.modules())


def default_options(noise_name: str) -> NeuralFirstStageOptions:
    """The stage's settings for a measurement-noise family (its ``name``): least squares for
    ``"gaussian"``, the robust (Cauchy) loss for the others."""
    return NeuralFirstStageOptions(loss="squared" if noise_name == "gaussian" else "cauchy")


def trimmed_rms(errors: Tensor, trim: float = TRIM) -> float:
    """Root mean square of ``errors`` without their largest ``trim`` share (NaN entries are missing
    values and left out; ``inf`` if an entry is infinite, NaN if none is left)."""
    e = errors.detach().reshape(-1)
    if bool(torch.isinf(e).any()):
        return math.inf
    e = e[~torch.isnan(e)]
    if e.numel() == 0:
        return math.nan
    keep = max(1, int(math.ceil((1.0 - trim) * e.numel())))
    return float((torch.sort(e.abs()).values[:keep] ** 2).mean().sqrt())


# ---------------------------------------------------------------------- helpers
def _robust_center_scale(values: Tensor) -> tuple[Tensor, Tensor]:
    """NaN-ignoring median and 1.4826 MAD of each column of ``values`` ``(n, d)`` (the standard
    deviation, then 1, where the MAD is 0 or undefined)."""
    d = values.shape[-1]
    ok = ~torch.isnan(values)
    if not bool(ok.any()):
        return values.new_zeros(d), values.new_ones(d)
    med = torch.nan_to_num(torch.nanmedian(values, dim=0).values)
    mad = MAD_TO_STD * torch.nanmedian((values - med).abs(), dim=0).values
    count = ok.sum(0).clamp_min(1)
    dev = torch.where(ok, values - med, torch.zeros_like(values))
    std = ((dev**2).sum(0) / count).sqrt()
    scale = torch.where(torch.isfinite(mad) & (mad > 0), mad, std)
    return med, torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))


def _simulate(f: nn.Module, g: nn.Module, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Noise-free outputs ``(n, T, p)`` of windows with first states ``x`` ``(n, nx)`` and inputs
    ``u`` ``(n, T, nu)``, and the state after the last step ``(n, nx)``."""
    step = _step_function(f, x, u)
    outputs = []
    for t in range(u.shape[1]):
        outputs.append(g(x, u[:, t]))
        x = step(x, t)
    return torch.stack(outputs, dim=1), x


def _step_function(f: nn.Module, x: Tensor, u: Tensor) -> Callable[[Tensor, int], Tensor]:
    """``step(x, t) = f(x, u[:, t])``: the module's own ``step_function(u)`` where it has one
    (:meth:`~torch_nssm.neural.MLPTransition.step_function`: the same numbers, bit for bit, faster)."""
    own = getattr(f, "step_function", None)
    if callable(own) and x.dim() == 2 and u.dim() == 3 and x.shape[0] == u.shape[0]:
        return own(u)
    return lambda x, t: f(x, u[:, t])


def _free_params(*modules: nn.Module) -> list[Tensor]:
    return [p for m in modules for p in m.parameters() if p.requires_grad]


def _state(*modules: nn.Module) -> list[dict]:
    return [copy.deepcopy(m.state_dict()) for m in modules]


def _load(modules, states) -> None:
    for m, s in zip(modules, states):
        m.load_state_dict(s)


def _cauchy_scale(e: Tensor, mask: Tensor) -> Tensor:
    """2.385 times the robust s.d. of the observed scaled errors (at least 1e-8)."""
    if not bool(mask.any()):
        return e.new_ones(())
    return (CAUCHY_C * MAD_TO_STD * e[mask].abs().median()).clamp_min(1e-8)


def _weight_penalty(modules: tuple, weight_decay: float) -> Tensor | float:
    """``weight_decay`` times the sum of the squared weights of the ``nn.Linear`` layers in
    ``modules`` that are estimated (0 when ``weight_decay`` is 0)."""
    if weight_decay == 0:
        return 0.0
    squares = [
        (layer.weight**2).sum()
        for module in modules
        for layer in module.modules()
        if isinstance(layer, nn.Linear) and layer.weight.requires_grad
    ]
    return weight_decay * sum(squares) if squares else 0.0


def _mean_loss(e: Tensor, mask: Tensor, scale: Tensor | None) -> Tensor:
    """Mean Cauchy loss at ``scale`` (``None``: squared errors) over the observed entries."""
    e = torch.where(mask, e, torch.zeros_like(e))
    terms = e**2 if scale is None else torch.log1p((e / scale) ** 2)
    return (terms * mask).sum() / mask.sum().clamp_min(1)


class _Problem:
    """The records in the model's dtype and device, their robust output scale, the held-out split
    and the scaled errors of simulated outputs."""

    def __init__(self, model: StateSpaceModel, data: SequenceBatch, opt: NeuralFirstStageOptions):
        ref = model.x0_mean
        kw = dict(dtype=ref.dtype, device=ref.device)
        self.u, self.y = data.u.to(**kw), data.y.to(**kw)
        self.data = SequenceBatch(self.u, self.y, data.lengths.to(ref.device))
        self.lengths = data.lengths.cpu()
        self.B, self.nx = data.n_sequences, model.state_dim
        self.p, self.nu = self.y.shape[-1], self.u.shape[-1]
        self.y_center, self.y_scale = _robust_center_scale(torch.cat(self.data.unpad(self.y)))
        rows_u = torch.cat(self.data.unpad(self.u))
        if self.nu and rows_u.shape[0] > 1:
            scale = rows_u.std(0)
            self.u_center = rows_u.mean(0)
            self.u_scale = torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))
        else:
            self.u_center, self.u_scale = self.u.new_zeros(self.nu), self.u.new_ones(self.nu)
        H = opt.horizon
        n_val = (self.lengths.double() * opt.validation_fraction).floor().long()
        n_val = torch.where(n_val >= 2 * H, n_val, torch.zeros_like(n_val))
        self.n_val = torch.where(self.lengths - n_val >= H, n_val, torch.zeros_like(n_val))
        self.val_records = [b for b in range(self.B) if int(self.n_val[b]) > 0]
        #: Held-out parts exist and hold fewer than ``SHORT_HOLDOUT`` samples: a weak guide alone.
        self.short_holdout = bool(self.val_records) and int(self.n_val.sum()) < SHORT_HOLDOUT

    def errors(self, y_obs: Tensor, y_hat: Tensor) -> tuple[Tensor, Tensor]:
        """Output errors scaled by the robust spread of ``y``, and where ``y`` is observed."""
        mask = ~torch.isnan(y_obs)
        return (torch.nan_to_num(y_obs) - y_hat) / self.y_scale, mask

    def stretches(self, rec: Tensor, k0: Tensor, k1: Tensor, length: int) -> tuple[Tensor, Tensor]:
        """Inputs and outputs ``(n, length, nu)``, ``(n, length, p)`` of samples ``k0 .. k1 - 1``
        of records ``rec`` (all ``(n,)``); past ``k1``, zero inputs and missing outputs."""
        t = k0[:, None] + torch.arange(length, device=k0.device)
        inside = (t < k1[:, None]).unsqueeze(-1)
        t = t.clamp(max=self.u.shape[0] - 1)
        u = torch.where(inside, self.u[t, rec[:, None]], torch.zeros_like(self.u[:1, 0]))
        y = torch.where(inside, self.y[t, rec[:, None]], torch.full_like(self.y[:1, 0], math.nan))
        return u, y

    def held_out(self, f, g, b: int, x: Tensor, k: int | None = None) -> Tensor:
        """Scaled free-run errors of record ``b``'s held-out part (NaN where ``y`` is missing), the
        run starting at sample ``k`` (default: the held-out part's first) from state ``x`` ``(nx,)``."""
        k0, k1 = int(self.lengths[b] - self.n_val[b]), int(self.lengths[b])
        k = k0 if k is None else k
        y_hat, _ = _simulate(f, g, x.unsqueeze(0), self.u[k:k1, b].unsqueeze(0))
        e, mask = self.errors(self.y[k0:k1, b], y_hat[0, k0 - k :])
        return torch.where(mask, e, torch.full_like(e, math.nan))

    def record_errors(self, f, g, x0: Tensor) -> Tensor:
        """Scaled free-run errors of every whole record from ``x0`` ``(B, nx)`` (NaN where ``y`` is
        missing or in the padding)."""
        with torch.no_grad():
            y_hat, _ = _simulate(f, g, x0, self.u.transpose(0, 1))
        e = (torch.nan_to_num(self.y) - y_hat.transpose(0, 1)) / self.y_scale
        return torch.where(self.data.obs_mask, e, torch.full_like(e, math.nan))


class _Best:
    """The evaluations, the best held-out score so far (the early stop's guide) and the parameters
    to keep.

    Kept: the parameters of the best held-out score; where evaluations also give the whole
    records' free-run score (``free_run``, LBFGS with short held-out parts), the best held-out score
    among the evaluations whose whole-record free run is within ``FREE_RUN_SLACK`` of the best
    one, unless that held-out score is more than ``HELD_OUT_GUARD`` times the best (then the best
    held-out score's).  The candidates are held as a Pareto front of (free run, held-out score):
    an evaluation beaten on both can never be the one kept."""

    def __init__(self, modules: tuple, extra: Tensor | None = None):
        self.modules, self.extra = modules, extra
        self.score, self.iteration, self.bad = math.inf, 0, 0
        self.kept_iteration = 0
        self.train: list[float] = []
        self.held_out: list[float] = []
        self.free_runs: list[float] = []
        self.state = self._snapshot()
        self._held_best = self.state  # the parameters of the best held-out score (at self.iteration)
        self._front: list[tuple[float, float, int, tuple]] = []  # (free run, held-out, iteration, state)

    def _snapshot(self):
        extra = None if self.extra is None else self.extra.detach().clone()
        return _state(*self.modules), extra

    def record(self, train_loss: float, score: float, iteration: int, free_run: float | None = None) -> None:
        """One evaluation: its training loss, its held-out score and (optionally) the whole
        records' free-run score."""
        self.train.append(train_loss)
        self.held_out.append(score)
        if math.isfinite(score) and score < self.score:
            self.score, self.iteration, self.bad = score, iteration, 0
            self._held_best = self._snapshot()
        else:
            self.bad += 1
        if free_run is not None:
            self.free_runs.append(free_run)
            self._update_front(free_run, score, iteration)
        self.state, self.kept_iteration = self._held_best, self.iteration
        if self._front:
            _, held, iteration, state = min(self._front, key=lambda c: c[1])
            if held <= HELD_OUT_GUARD * self.score:
                self.state, self.kept_iteration = state, iteration

    def _update_front(self, free_run: float, score: float, iteration: int) -> None:
        if not (math.isfinite(score) and math.isfinite(free_run)):
            return
        if any(w <= free_run and h <= score for w, h, _, _ in self._front):
            return  # beaten on both scores by an earlier evaluation
        front = [c for c in self._front if not (free_run <= c[0] and score <= c[1])]
        front.append((free_run, score, iteration, self._snapshot()))
        best_free = min(c[0] for c in front)
        self._front = [c for c in front if c[0] <= FREE_RUN_SLACK * best_free]

    def restore(self) -> None:
        modules, extra = self.state
        _load(self.modules, modules)
        if extra is not None:
            with torch.no_grad():
                self.extra.copy_(extra)


# ---------------------------------------------------------------------- the entry point
def neural_first_stage(
    model: StateSpaceModel,
    data: SequenceBatch,
    options: NeuralFirstStageOptions | None = None,
    *,
    generator: torch.Generator | None = None,
) -> NeuralFirstStageReport:
    """Train ``model.f`` and ``model.g`` (in place) by robust simulation error over windows.

    Parameters
    ----------
    model : StateSpaceModel
        The start: the free parameters of ``f`` and ``g`` are trained (and restored if the result
        is not accepted); ``x0_mean`` is the start's first state (the "before" free run, the first
        windows' starting state).  The noise parameters are not used.
    data : SequenceBatch
        The training records (NaN outputs: missing).
    options : NeuralFirstStageOptions, optional
    generator : torch.Generator, optional
        CPU random stream of the Adam path (encoder weights, window draws); LBFGS draws nothing.

    Returns
    -------
    NeuralFirstStageReport
        With each record's fitted first state; ``model.x0_mean`` is not changed.

    Raises
    ------
    ValueError
        If a setting is out of range, or (Adam) the records are too short for a window after the
        encoder's lags.
    """
    t_start = time.perf_counter()
    opt = options or NeuralFirstStageOptions()
    opt.check()
    problem = _Problem(model, data, opt)
    f, g = model.f, model.g
    start_state = _state(f, g)
    if opt.optimizer == "lbfgs":
        best, first_states, n_windows, stop, iterations, encoder = (
            *_train_lbfgs(model, problem, opt, t_start),
            None,
        )
    else:
        gen = generator if generator is not None else torch.Generator().manual_seed(0)
        best, first_states, n_windows, stop, iterations, encoder = _train_adam(
            model, problem, opt, gen, t_start
        )
    B = problem.B
    before = trimmed_rms(
        _with_state(f, g, start_state, problem.record_errors, model.per_sequence("x0_mean", B))
    )
    after = trimmed_rms(problem.record_errors(f, g, first_states))
    improved = math.isfinite(after) and (not math.isfinite(before) or after < before)
    accepted = improved and math.isfinite(best.score) and bool(torch.isfinite(first_states).all())
    if not accepted:
        _load((f, g), start_state)
    unit = float(problem.y_scale.mean())
    return NeuralFirstStageReport(
        accepted=accepted,
        improved=improved,
        free_run_before=before * unit,
        free_run_after=after * unit,
        optimizer=opt.optimizer,
        iterations=iterations,
        evaluations=len(best.held_out),
        best_iteration=best.kept_iteration,
        train_losses=best.train,
        validation_losses=best.held_out,
        horizon=opt.horizon,
        n_windows=n_windows,
        seconds=time.perf_counter() - t_start,
        stop_reason=stop,
        first_states=first_states.detach(),
        free_runs=best.free_runs,
        encoder=encoder,
        loss=opt.loss,
    )


def _with_state(f, g, state, fn, *args):
    """``fn(f, g, *args)`` evaluated with the modules' state ``state``, their own state restored."""
    current = _state(f, g)
    _load((f, g), state)
    try:
        return fn(f, g, *args)
    finally:
        _load((f, g), current)


# ---------------------------------------------------------------------- LBFGS over tiled windows
def _next_horizon(opt: NeuralFirstStageOptions, problem: _Problem, H: int, improved: bool) -> int | None:
    """The next LBFGS phase's window length after a phase of ``H`` (``None``: training ends).

    ``horizon`` doubles up to ``max_horizon`` if given; by default at least to ``4 * horizon``
    and beyond while the last phase improved the held-out score, up to the longest record's
    training part: longer windows weigh the slow, long-horizon behaviour that short windows
    leave free (the suite's oscillator, benchmarks/README "How the neural first stage's training
    ends")."""
    if opt.max_horizon is not None:
        top = opt.max_horizon
    elif not problem.val_records:
        top = 4 * opt.horizon
    else:
        longest = int((problem.lengths - problem.n_val).max())  # the longest training part
        top = longest if H < 4 * opt.horizon or improved else H
    return 2 * H if 2 * H <= top else None


class _Tiling:
    """Windows of length ``H`` tiling each record's training part (the last one may be shorter: its
    missing steps have zero input and a missing output), each with a free first state.

    The free parameters are the first states in units of ``state_scale`` (``x = z * state_scale``),
    so that LBFGS moves states of different units (a position in mm, a velocity in mm/s) by
    comparable amounts."""

    def __init__(self, problem: _Problem, H: int, state_scale: Tensor) -> None:
        self.problem, self.H = problem, H
        dev = problem.y.device
        ends = (problem.lengths - problem.n_val).tolist()
        self.spans = [(b, k) for b in range(problem.B) for k in range(0, int(ends[b]), H)]
        self.rec = torch.tensor([s[0] for s in self.spans], device=dev)
        self.k0 = torch.tensor([s[1] for s in self.spans], device=dev)
        self.u, self.y = problem.stretches(self.rec, self.k0, torch.as_tensor(ends, device=dev)[self.rec], H)
        self.first = [self.spans.index((b, 0)) for b in range(problem.B)]
        self.last = {b: max(i for i, s in enumerate(self.spans) if s[0] == b) for b in problem.val_records}
        self.state_scale = state_scale
        self.z = torch.zeros(len(self.spans), problem.nx, dtype=problem.y.dtype, device=dev)

    @property
    def x(self) -> Tensor:
        """The windows' first states ``(n, nx)``."""
        return self.z * self.state_scale

    def start_at(self, states: Tensor) -> None:
        """The windows' first states ``(n, nx)``, free parameters from now on (as ``z``)."""
        self.z = (states.detach() / self.state_scale).clone().requires_grad_(True)

    def errors(self, f, g) -> tuple[Tensor, Tensor]:
        """Scaled output errors of the windows' simulations ``(n, H, p)`` and where ``y`` is observed."""
        return self.problem.errors(self.y, _simulate(f, g, self.x, self.u)[0])

    @functools.cached_property
    def _free_run_stretches(self) -> tuple[Tensor, Tensor, Tensor]:
        """The windows starting the free run's stretches (every ``FREE_RUN_SPAN`` samples or so),
        and the stretches' inputs and outputs, each record's last one to its end."""
        problem, dev = self.problem, self.k0.device
        span = self.H * max(1, FREE_RUN_SPAN // self.H)
        first = torch.tensor([i for i, (_, k) in enumerate(self.spans) if k % span == 0], device=dev)
        rec, k0 = self.rec[first], self.k0[first]
        ends = (problem.lengths - problem.n_val).to(dev)[rec]
        k1 = torch.where(k0 + span >= ends, problem.lengths.to(dev)[rec], k0 + span)
        return (first, *problem.stretches(rec, k0, k1, int((k1 - k0).max())))

    @torch.no_grad()
    def free_run(self, f, g) -> float:
        """Trimmed RMS of each record's free run, held-out end included, in stretches of about
        ``FREE_RUN_SPAN`` samples (the whole record where it is shorter), each from the fitted
        state of the window that starts it: the stretches run side by side, so the cost per
        evaluation stays bounded on long records."""
        first, u, y = self._free_run_stretches
        e, mask = self.problem.errors(y, _simulate(f, g, self.x[first], u)[0])
        return trimmed_rms(torch.where(mask, e, torch.full_like(e, math.nan)))

    @torch.no_grad()
    def score(self, f, g) -> float:
        """Trimmed RMS of the held-out free runs, each continuing its record's last training window
        (of the windows' errors when nothing is held out)."""
        if not self.problem.val_records:
            e, mask = self.errors(f, g)
            return trimmed_rms(torch.where(mask, e, torch.full_like(e, math.nan)))
        errs = []
        for b in self.problem.val_records:
            i = self.last[b]
            errs.append(self.problem.held_out(f, g, b, self.x[i], int(self.k0[i])))
        return trimmed_rms(torch.cat(errs))


class _LBFGSRun:
    """One LBFGS run over a tiling's objective at a fixed Cauchy scale (its curvature pairs kept
    across rounds); a step into a diverging simulation gets a huge finite loss, so the line search
    backs off."""

    def __init__(
        self, f, g, tiling: _Tiling, scale: Tensor | None, per_round: int, weight_decay: float = 0.0
    ) -> None:
        self.f, self.g, self.tiling, self.scale = f, g, tiling, scale
        self.weight_decay = weight_decay
        self.params = _free_params(f, g) + [tiling.z]
        with torch.no_grad():
            self.start = self.loss()
        size = 1e6 * (1.0 + abs(self.start)) if math.isfinite(self.start) else 1e30
        self.penalty = torch.tensor(size, dtype=tiling.x.dtype, device=tiling.x.device)
        self.opt = torch.optim.LBFGS(
            self.params,
            lr=1.0,
            max_iter=per_round,
            line_search_fn="strong_wolfe",
            history_size=100,
            tolerance_grad=1e-12,
            tolerance_change=1e-14,
        )

    def objective(self, e: Tensor, mask: Tensor) -> Tensor:
        """The mean loss of the windows' errors ``e`` plus the weight penalty."""
        return _mean_loss(e, mask, self.scale) + _weight_penalty((self.f, self.g), self.weight_decay)

    def loss(self) -> float:
        return float(self.objective(*self.tiling.errors(self.f, self.g)))

    def _closure(self) -> Tensor:
        self.opt.zero_grad()
        loss = self.objective(*self.tiling.errors(self.f, self.g))
        if not bool(torch.isfinite(loss)):
            return self.penalty
        loss.backward()
        return loss

    def round(self, iterations: int) -> int | None:
        """Up to ``iterations`` LBFGS iterations; how many ran (``None``: the line search failed)."""
        group = self.opt.param_groups[0]
        group["max_iter"], group["max_eval"] = iterations, 4 * iterations
        state = self.opt.state[self.params[0]]
        before = int(state.get("n_iter", 0))
        try:
            self.opt.step(self._closure)
        except (RuntimeError, IndexError):
            return None
        finally:
            for prm in self.params:
                prm.grad = None
        return max(int(self.opt.state[self.params[0]].get("n_iter", 0)) - before, 1)


def _shrunk_scale(e: Tensor, mask: Tensor, scale: Tensor | None) -> Tensor | None:
    """The Cauchy scale of the current errors if it is below a quarter of ``scale`` (``scale``
    otherwise; each change is a new objective and restarts LBFGS, so only by a factor of 4)."""
    if scale is None or not bool(torch.isfinite(e[mask]).all()):
        return scale
    fresh = _cauchy_scale(e, mask)
    return fresh if bool(torch.isfinite(fresh)) and fresh < scale / 4 else scale


def _train_lbfgs(model: StateSpaceModel, problem: _Problem, opt: NeuralFirstStageOptions, t_start: float):
    """Full-batch LBFGS over windows tiling each record's training part, each window's first state
    free, in phases of doubling window length; returns ``(best, first_states, n_windows,
    stop_reason, iterations)``.

    The Cauchy scale starts at the start's errors (a smooth objective far from the data) and
    shrinks with them as the fit improves; each phase's windows start at the previous phase's
    fitted states (the start's noise-free simulation for the first phase)."""
    f, g = model.f, model.g
    max_iter = opt.max_iter or (LBFGS_MAX_ITER if problem.val_records else LBFGS_MAX_ITER_NO_HOLDOUT)
    per_round, patience = opt.eval_every or 25, opt.patience or _lbfgs_patience(problem)
    weigh_free_run = problem.short_holdout  # the kept iterate also weighs the records' free run
    first_states = torch.zeros(problem.B, problem.nx, dtype=problem.y.dtype, device=problem.y.device)
    best = _Best((f, g), first_states)
    state_scale = _network_state_scale(f, problem.nx).to(problem.y)
    with torch.no_grad():
        x0 = model.per_sequence("x0_mean", problem.B).to(problem.y)
        simulated = _simulate_states(f, x0, problem.u.transpose(0, 1))
        simulated = torch.where(torch.isfinite(simulated), simulated, x0.unsqueeze(1))
    known = None  # the previous phase's fitted window states by (record, start)
    iterations, stop, n_windows, scale = 0, "max_iter", 0, None
    H: int | None = opt.horizon
    while H is not None:
        score_before = best.score
        tiling = _Tiling(problem, H, state_scale)
        if known is None:
            tiling.start_at(simulated[tiling.rec, tiling.k0])
        else:
            tiling.start_at(torch.stack([known[span] for span in tiling.spans]))
        with torch.no_grad():
            e, mask = tiling.errors(f, g)
        n_windows = len(tiling.spans)
        if opt.loss == "cauchy":
            scale = _shrunk_scale(e, mask, scale) if scale is not None else _cauchy_scale(e, mask)
        run = _LBFGSRun(f, g, tiling, scale, per_round, opt.weight_decay)
        best.bad, phase_iter, stop, round_start = 0, 0, "max_iter", run.start
        while phase_iter < max_iter:
            done = run.round(min(per_round, max_iter - phase_iter))
            if done is None:
                stop = "converged"
                break
            phase_iter, iterations = phase_iter + done, iterations + done
            with torch.no_grad():
                first_states.copy_(tiling.x[tiling.first])
                e, mask = tiling.errors(f, g)
                round_end = float(run.objective(e, mask))
            free_run = tiling.free_run(f, g) if weigh_free_run else None
            best.record(round_end, tiling.score(f, g), iterations, free_run)
            if best.bad >= patience:
                stop = "patience"  # no better held-out score for a while
                break
            if opt.max_seconds is not None and time.perf_counter() - t_start > opt.max_seconds:
                stop = "max_seconds"
                break
            smaller = _shrunk_scale(e, mask, scale)
            if smaller is not scale:
                scale, run = smaller, _LBFGSRun(f, g, tiling, smaller, per_round, opt.weight_decay)
                round_end = run.start
            elif not round_end < round_start - 1e-9 * abs(round_start):
                stop = "converged"  # the round made no progress
                break
            round_start = round_end
        if stop == "max_seconds" or best.iteration == 0:
            break
        known = {span: tiling.x[i].detach().clone() for i, span in enumerate(tiling.spans)}
        H = _next_horizon(opt, problem, H, best.score < score_before)
    if math.isfinite(best.score):
        best.restore()
    return best, first_states.clone(), n_windows, stop, iterations


def _lbfgs_patience(problem: _Problem) -> int:
    """The LBFGS phases' default patience: longer where the held-out parts are short (a weak
    guide of progress, see ``LBFGS_PATIENCE_SHORT_HOLDOUT``)."""
    if not problem.short_holdout:  # long held-out parts, or nothing held out: the cap decides
        return LBFGS_PATIENCE
    return LBFGS_PATIENCE_SHORT_HOLDOUT


def _network_state_scale(f: nn.Module, nx: int) -> Tensor:
    """The spread of each state that the network in ``f`` is normalised by: the ``x_scale`` of the
    first submodule of ``f`` (itself included) holding finite positive ``x_scale`` of ``nx`` entries
    (:class:`~torch_nssm.neural.MLPTransition` and the other neural blocks), ones if none does.

    LBFGS moves the windows' first states in these units: in raw units a state whose spread is
    100 times another's (a velocity in mm/s beside a position in mm) has a gradient 100 times
    smaller per unit and a curvature 10,000 times smaller, and LBFGS barely moves it."""
    for module in f.modules():
        scale = getattr(module, "x_scale", None)
        if (
            isinstance(scale, Tensor)
            and tuple(scale.shape) == (nx,)
            and bool(torch.isfinite(scale).all())
            and bool((scale > 0).all())
        ):
            return scale.detach().clone()
    return torch.ones(nx, dtype=torch.float64)


def _simulate_states(f: nn.Module, x: Tensor, u: Tensor) -> Tensor:
    """The states ``(n, T, nx)`` of a noise-free run from ``x`` ``(n, nx)`` over ``u`` ``(n, T, nu)``."""
    states = []
    for t in range(u.shape[1]):
        states.append(x)
        x = f(x, u[:, t])
    return torch.stack(states, dim=1)


# ---------------------------------------------------------------------- Adam over encoded windows
def _train_adam(model, problem: _Problem, opt: NeuralFirstStageOptions, gen: torch.Generator, t_start: float):
    """Adam over minibatches of windows whose first states the encoder gives (SUBNET); returns
    ``(best, first_states, n_windows, stop_reason, steps, encoder)``."""
    f, g = model.f, model.g
    H, lags = opt.horizon, opt.encoder_lags
    max_steps = opt.max_iter or 3000
    patience = opt.patience or 12
    dev = problem.y.device
    starts = []
    for b in range(problem.B):
        end = int(problem.lengths[b] - problem.n_val[b])
        ks = torch.arange(lags, max(lags, end - H + 1))
        starts.append(torch.stack([torch.full_like(ks, b), ks], dim=1))
    starts = torch.cat(starts)
    if starts.shape[0] == 0:
        raise ValueError(
            f"the records are too short for optimizer='adam': a window needs encoder_lags + horizon = "
            f"{lags + H} samples before the held-out part; lower them or use optimizer='lbfgs'"
        )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(torch.randint(0, 2**31 - 1, (1,), generator=gen)))
        encoder = StateEncoder(
            lags,
            problem.p,
            problem.nu,
            problem.nx,
            tuple(opt.encoder_hidden),
            problem.y_center,
            problem.y_scale,
            problem.u_center,
            problem.u_scale,
        )
        with torch.no_grad():  # the untrained encoder starts near the given first state
            encoder.net[-1].weight.mul_(0.1)
            encoder.net[-1].bias.copy_(model.x0_mean.detach().reshape(-1).to(encoder.net[-1].bias))
    past, ahead = torch.arange(-lags, 0, device=dev), torch.arange(H, device=dev)

    def gather(index: Tensor):
        b, k = starts[index, 0].to(dev)[:, None], starts[index, 1].to(dev)[:, None]
        return (
            problem.y[k + past, b],
            problem.u[k + past, b],
            problem.u[k + ahead, b],
            problem.y[k + ahead, b],
        )

    @torch.no_grad()
    def score() -> float:
        if not problem.val_records:
            index = torch.arange(min(starts.shape[0], 4 * opt.batch_size))
            y_p, u_p, u_w, y_w = gather(index)
            e, mask = problem.errors(y_w, _simulate(f, g, encoder(y_p, u_p), u_w)[0])
            return trimmed_rms(torch.where(mask, e, torch.full_like(e, math.nan)))
        errs = []
        for b in problem.val_records:
            k = int(problem.lengths[b] - problem.n_val[b])
            x = encoder(problem.y[k - lags : k, b], problem.u[k - lags : k, b])
            errs.append(problem.held_out(f, g, b, x))
        return trimmed_rms(torch.cat(errs))

    modules = (f, g, encoder)
    params = _free_params(*modules)
    best = _Best(modules)
    n = starts.shape[0]
    eval_every = opt.eval_every or int(min(250, max(25, n // opt.batch_size)))
    adam = torch.optim.Adam(params, lr=opt.learning_rate)
    running, n_running, step, stop = 0.0, 0, 0, "max_iter"
    while step < max_steps:
        for group in adam.param_groups:  # cosine decay to 1/20 of the initial step size
            group["lr"] = opt.learning_rate * (0.05 + 0.475 * (1.0 + math.cos(math.pi * step / max_steps)))
        y_p, u_p, u_w, y_w = gather(torch.randint(0, n, (min(opt.batch_size, n),), generator=gen))
        adam.zero_grad()
        e, mask = problem.errors(y_w, _simulate(f, g, encoder(y_p, u_p), u_w)[0])
        loss = _mean_loss(e, mask, None if opt.loss == "squared" else _cauchy_scale(e.detach(), mask))
        loss = loss + _weight_penalty((f, g), opt.weight_decay)
        step += 1
        if bool(torch.isfinite(loss)):
            loss.backward()
            if bool(torch.isfinite(torch.nn.utils.clip_grad_norm_(params, opt.clip_norm))):
                adam.step()
                running, n_running = running + float(loss.detach()), n_running + 1
        if step % eval_every == 0 or step == max_steps:
            current = score()
            best.record(running / n_running if n_running else math.nan, current, step)
            running, n_running = 0.0, 0
            if not math.isfinite(current):  # diverged: back to the best
                best.restore()
            if best.bad >= patience:
                stop = "patience"
                break
        if opt.max_seconds is not None and time.perf_counter() - t_start > opt.max_seconds:
            stop = "max_seconds"
            break
    for prm in params:
        prm.grad = None
    if math.isfinite(best.score):
        best.restore()
    return best, _fit_first_states(model, encoder, problem), n, stop, step, encoder


def _fit_first_states(
    model: StateSpaceModel, encoder: StateEncoder | None, problem: _Problem, n: int = 200
) -> Tensor:
    """Each record's first state ``(B, nx)`` (the encoder needs a past): the Cauchy loss of the
    first ``n`` simulated outputs minimised by LBFGS over the state, from the better of
    ``x0_mean`` and the encoder's state for a record at rest at its first output (``encoder=None``:
    from ``x0_mean``)."""
    f, g = model.f, model.g
    B = problem.B
    n = int(min(n, int(problem.lengths.min())))
    u, y = problem.u[:n].transpose(0, 1), problem.y[:n].transpose(0, 1)  # (B, n, .)
    e_of = lambda x: problem.errors(y, _simulate(f, g, x, u)[0])  # noqa: E731
    with torch.no_grad():
        given = model.per_sequence("x0_mean", B).to(u)
        if encoder is None:
            at_rest = given
        else:
            y0 = torch.nan_to_num(y[:, :1], nan=0.0).expand(B, encoder.lags, problem.p)
            at_rest = encoder(y0, torch.zeros(B, encoder.lags, problem.nu, dtype=u.dtype, device=u.device))
        (e_g, mask), (e_r, _) = e_of(given), e_of(at_rest)
        scale = torch.minimum(_cauchy_scale(e_g, mask), _cauchy_scale(e_r, mask))

        def cost(e: Tensor) -> Tensor:
            return torch.nan_to_num(
                (torch.log1p((torch.where(mask, e, 0 * e) / scale) ** 2)).sum((1, 2)), nan=math.inf
            )

        start = torch.where((cost(e_r) < cost(e_g)).unsqueeze(-1), at_rest, given)
        c0 = cost(e_of(start)[0])
    x0 = start.clone().requires_grad_(True)
    frozen = _free_params(f, g)
    for prm in frozen:
        prm.requires_grad_(False)
    try:
        lbfgs = torch.optim.LBFGS([x0], lr=1.0, max_iter=50, line_search_fn="strong_wolfe")

        def closure():
            lbfgs.zero_grad()
            loss = cost(e_of(x0)[0]).sum()
            if not bool(torch.isfinite(loss)):
                return torch.tensor(1e30, dtype=x0.dtype, device=x0.device)
            loss.backward()
            return loss

        try:
            lbfgs.step(closure)
        except (RuntimeError, IndexError):
            pass
        with torch.no_grad():
            better = (cost(e_of(x0)[0]) <= c0) & torch.isfinite(x0).all(-1)
            return torch.where(better.unsqueeze(-1), x0.detach(), start)
    finally:
        for prm in frozen:
            prm.requires_grad_(True)


def fit_initial_states(model: StateSpaceModel, data: SequenceBatch, n_samples: int = 200) -> Tensor:
    """The first state of each record ``(B, nx)`` for a fitted ``f`` and ``g``: the robust (Cauchy)
    simulation error of its first ``n_samples`` outputs minimised over the state by LBFGS, from
    ``model.x0_mean`` (the deterministic counterpart of ``x0="estimate"``, for scoring a simulation
    model on a new record).

    Parameters
    ----------
    model : StateSpaceModel
        Its ``f``, ``g`` and ``x0_mean`` (the starting guess) are used.
    data : SequenceBatch
        The records (NaN outputs: missing).
    n_samples : int
        Samples of each record's beginning that the state must simulate.

    Returns
    -------
    Tensor, shape (B, nx)
    """
    if int(n_samples) < 2:
        raise ValueError(f"n_samples must be >= 2, got {n_samples!r}")
    problem = _Problem(model, data, NeuralFirstStageOptions(validation_fraction=0.0))
    return _fit_first_states(model, None, problem, int(n_samples))


@torch.no_grad()
def start_noise_levels(
    model: StateSpaceModel, data: SequenceBatch, first_states: Tensor, relative: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """Noise levels for EM after a simulation-error fit: ``Rw`` ``relative`` times the variance of
    each state along the noise-free simulation of the records from ``first_states`` (diagonal,
    floored at ``relative`` times the largest, the held process noise of a simulation model), and
    ``Rv`` the squared
    robust scale (1.4826 MAD) of that simulation's output errors per output (diagonal, floored at
    1e-12 times ``y``'s squared spread)."""
    problem = _Problem(model, data, NeuralFirstStageOptions(validation_fraction=0.0))
    states = _simulate_states(model.f, first_states.to(problem.y), problem.u.transpose(0, 1))  # (B, T, nx)
    Rw = _held_process_noise(states.transpose(0, 1), problem.data, relative)
    errors = problem.record_errors(model.f, model.g, first_states.to(problem.y)) * problem.y_scale
    flat = errors.reshape(-1, problem.p)
    rv = torch.stack(
        [
            (MAD_TO_STD * flat[:, j][~torch.isnan(flat[:, j])].abs().median()) ** 2
            if bool((~torch.isnan(flat[:, j])).any())
            else problem.y_scale[j] ** 2
            for j in range(problem.p)
        ]
    )
    rv = torch.clamp(torch.nan_to_num(rv, nan=1.0), min=1e-12 * float((problem.y_scale**2).max()))
    return Rw, torch.diag(rv)


def _held_process_noise(states: Tensor, data: SequenceBatch, relative: float) -> Tensor:
    """``relative`` times the variance of each state along a noise-free simulation ``states``
    ``(T, B, nx)`` of ``data`` (diagonal), floored at ``relative`` times the largest of them (and at
    ``1e-300``) so that no state is noise-free."""
    x = torch.cat(data.unpad(states.detach()))  # (n, nx)
    var = x.var(0) if x.shape[0] > 1 else torch.ones_like(x[0])
    var = torch.where(torch.isfinite(var), var, torch.ones_like(var))
    floor = torch.clamp(var.max() * relative, min=1e-300)
    return torch.diag(torch.clamp(relative * var, min=floor))
