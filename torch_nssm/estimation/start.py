"""How a fit starts, and the check of its simulation after EM (docs/design.md, "How a fit starts").

:func:`plan_start` is the one entry point before EM: given the initial model, the data and the
settings it runs the first stage (:mod:`.first_stage`) and decides whether its result is kept
(:func:`keep_first_stage`: the ``SIMULATION_R2_FLOOR`` of ``first_stage="auto"``), computes the
divergence limit of the restarts (:func:`divergence_limit`) and draws their seeds
(:func:`restart_seeds`).  :meth:`Start.run_start` then gives EM run ``r`` its start: run 0 the
planned model, the others a jittered copy whose simulation stays bounded (:func:`stable_jitter`)
with ``g`` refitted to ``y`` along it (:func:`g_fitted_to_y`).  After EM, :func:`check_simulation`
compares the fit's noise-free simulation with the first stage's and, under ``fit_Rw="auto"``, runs
EM again from the first stage with the process noise held.

Nothing here warns: what happened is recorded (:class:`Start`, :class:`SimulationCheck`) and
:mod:`torch_nssm.diagnostics.fit_warnings` says it in words.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from sklearn.utils import check_random_state

from .._stats import MAD_TO_STD, quantization_step, robust_scale
from ..core.model import SequenceBatch, StateSpaceModel
from ..core.parametric import LinearInParameters
from ..inference import prediction
from ..metrics import robust_r2_score
from .first_stage import NETWORK_LAYERS, FirstStageReport, first_stage_applies, simulation_error_fit
from .neural_first_stage import (
    NeuralFirstStageOptions,
    NeuralFirstStageReport,
    default_options,
    holds_network,
    neural_first_stage,
)
from .noise_start import NoiseLadder, likeliest_process_noise

__all__ = [
    "Start",
    "StartSettings",
    "SimulationCheck",
    "plan_start",
    "check_simulation",
    "state_spread",
    "restart_seeds",
    "seeded_generator",
    "copy_model",
    "network_first_stage",
    "physical_part_first",
    "CAUCHY_TUNING",
    "SIMULATION_R2_FLOOR",
    "SIMULATION_TOLERANCE",
]

#: Tuning constant of the Cauchy weights (95 % efficiency at the normal).
CAUCHY_TUNING = 2.385

#: ``first_stage="auto"`` keeps the first stage only when its noise-free simulation explains at
#: least this share of ``y`` (robust R²).  Below it the process noise dominates.
SIMULATION_R2_FLOOR = 0.5

#: A kept first stage whose simulation explains at least this share of ``y`` (robust R²) is a
#: simulation model (``focus="simulation"`` holds its process noise).  The suite's physical plants
#: explain 0.98-0.999 at the first stage, the paper's Section 4.1 example (process noise about as
#: large as the measurement noise) 0.59-0.73: there the process noise is part of the model.
SIMULATION_MODEL_R2 = 0.9

#: How much worse than the first stage's (robust scale of the training free-run errors) a fit that
#: estimated the process noise may leave the simulation before the report says so.
SIMULATION_TOLERANCE = 1.1

#: Draws of a jittered restart before the last one is taken even though its simulation diverges.
JITTER_DRAWS = 20


@dataclass
class StartSettings:
    """The estimator's settings that shape the start.

    Attributes
    ----------
    first_stage : {"auto", "simulation", None}
    n_iter : int
        ``first_stage="auto"`` runs no first stage without EM (``n_iter=0`` evaluates a model).
    n_runs : int
        EM runs (``n_init``; 1 for ``warm_start=True``).
    init_jitter : float
        Standard deviation of the restarts' log-normal factor.
    random_state : int, RandomState or None
        Seeds the runs (:func:`restart_seeds`).
    warm : bool
        ``warm_start=True`` on a fitted estimator: no first stage, and no warning about the start's
        simulation.
    focus : {"simulation", "prediction"}
        What the model is for (:func:`plan_start`).
    fit_Rw : bool or "auto"
    Rw_given, Rv_given, x0_cov_given : bool
        Whether the user gave ``Rw_init`` / ``Rv_init`` / ``x0_cov`` (else the start sizes them from
        the data).
    """

    first_stage: str | None
    n_iter: int
    n_runs: int
    init_jitter: float
    random_state: Any
    warm: bool = False
    focus: str = "simulation"
    fit_Rw: bool | str = "auto"
    Rw_given: bool = True
    Rv_given: bool = True
    x0_cov_given: bool = True


@dataclass
class Start:
    """The planned start of a fit's EM runs.

    Attributes
    ----------
    model : StateSpaceModel
        Run 0's start: the first stage's result if it was kept, else the given model.
    seeds : list of int
        The seed of each run (:func:`restart_seeds`).
    limit : float
        How far a restart's simulation may go before it counts as diverging.
    init_jitter : float
    first_stage : FirstStageReport, NeuralFirstStageReport or None
        What the first stage did (``None``: it did not run).
    first_stage_unimproved : bool
        ``first_stage="simulation"`` was asked and did not improve the start (EM starts from the
        given values).
    divergent_step : int or None
        The step at which the start's own noise-free simulation leaves every finite bound.
    staged : StateSpaceModel or None
        A copy of the kept first stage's model (the start of the ``fit_Rw="auto"`` re-run).
    staged_run : (Tensor, Tensor) or None
        Noise-free ``(states, outputs)`` of the kept first stage's model.
    hold_modules : bool
        EM keeps ``f``'s and ``g``'s parameters (a simulation model, :func:`plan_start`).
    interrupted : bool
        Ctrl-C came during the first stage: the start is its best stage so far, and no EM runs.
    Rv_floor : Tensor or None
        Lower bound of each output's measurement-noise variance, ``(p,)``: ``q**2 / 12`` for an
        output recorded on a grid of step ``q`` (an encoder, an A/D converter; 0 elsewhere), the
        variance of the rounding itself (:func:`measurement_floor`).  ``None``: no output on a grid.
    noise_ladder : NoiseLadder or None
        How a simulation model's starting process noise was chosen
        (:func:`.noise_start.likeliest_process_noise`); ``None`` where it was not.
    """

    model: StateSpaceModel
    seeds: list[int]
    limit: float
    init_jitter: float
    first_stage: FirstStageReport | NeuralFirstStageReport | None = None
    first_stage_unimproved: bool = False
    divergent_step: int | None = None
    staged: StateSpaceModel | None = None
    staged_run: tuple | None = field(default=None, repr=False)
    hold_modules: bool = False
    interrupted: bool = False
    Rv_floor: torch.Tensor | None = None
    noise_ladder: NoiseLadder | None = None

    def run_start(self, r: int, data: SequenceBatch, device: torch.device) -> tuple:
        """EM run ``r``'s start, its particle generator and whether its simulation stays bounded:
        run 0 from :attr:`model`, run ``r > 0`` from a jittered copy (:func:`stable_jitter`), all
        randomness from ``seeds[r]``."""
        seed = self.seeds[r]
        rs = np.random.RandomState(seed)
        if r == 0:  # the particle seed a single fit (n_init=1) uses
            return copy_model(self.model), torch.Generator(device=device).manual_seed(seed), True
        generator = seeded_generator(device, rs)
        model, stable = stable_jitter(self.model, self.init_jitter, rs, data, self.limit)
        return model, generator, stable


def plan_start(
    model: StateSpaceModel, data: SequenceBatch, settings: StartSettings, *, restarts: bool = True
) -> Start:
    """The start of a fit's EM runs: the first stage (when it runs, and kept or not), the noise
    parameters' starting values and whether EM moves ``f`` and ``g``, the divergence limit of the
    restarts and their seeds (``restarts=False``: neither, for a study's data set, whose one run
    starts at :attr:`Start.model`).

    A kept first stage whose free run explains at least :data:`SIMULATION_MODEL_R2` of ``y`` is a
    simulation model: with ``focus="simulation"`` EM keeps its ``f`` and ``g`` (the robust
    simulation-error fit is what simulates best: a free process noise would let EM trade the
    simulation for tracking) and the first state's mean, and estimates the noise around them: the
    process noise, the measurement noise (from the first stage's output errors when ``Rv_init`` is
    not given) and the outlier weights.  Otherwise EM estimates every parameter.  A process noise
    not given starts at :func:`scaled_process_noise` (a simulation model's then raised while the
    filter's likelihood grows: :func:`.noise_start.likeliest_process_noise`), and after a kept
    first stage a first-state prior not given at :func:`state_spread`.
    """
    start = Start(model, seeds=[], limit=math.inf, init_jitter=settings.init_jitter)
    if runs_first_stage(model, settings):
        start.first_stage, kept_run, start.model = first_stage_start(
            model, data, settings.first_stage, settings.random_state
        )
        start.interrupted = start.first_stage.interrupted
        start.first_stage_unimproved = not start.first_stage.accepted and settings.first_stage != "auto"
        if kept_run is not None:
            start.staged, start.staged_run = copy_model(start.model), kept_run
    simulation_model = start.staged is not None and start.first_stage.explained >= SIMULATION_MODEL_R2
    if not settings.Rw_given and not settings.warm:
        if start.staged is None:  # at least the general default: the start's steps may be tiny
            Rw = scaled_process_noise(start.model, data, UNEXPLAINED_SHARE)
            Rw = torch.maximum(Rw, torch.diag(torch.diagonal(start.model.Rw)))
        else:
            share = PROCESS_NOISE_SHARE * (SIMULATION_SHARE if simulation_model else 1.0)
            Rw = scaled_process_noise(start.model, data, share, states=start.staged_run[0])
        start.model = replace(start.model, Rw=Rw)
    if simulation_model and settings.focus == "simulation":
        start.model = simulation_start(start.model, data, start.staged_run, settings.Rv_given)
        start.staged = copy_model(start.model)
        start.hold_modules = True
    elif start.staged is not None:
        # EM estimates the first state from its smoother, under the given prior: the first stage's
        # record first state is one of the window fit's local parameters, which nothing ties to the
        # prior, and a g that does not determine the state (a cos) lets it wander far (x0 = -19
        # on the paper's example), where a prior of the given spread holds EM's smoother
        start.model = replace(start.model, x0_mean=model.x0_mean, x0_cov=model.x0_cov)
    if start.staged is not None and not settings.x0_cov_given:
        held = simulation_model and settings.focus == "simulation"  # the first stage's own run
        states = start.staged_run[0] if held else None
        start.model = replace(start.model, x0_cov=state_spread(start.model, data, states=states))
        if held:
            start.staged = copy_model(start.model)
    start.Rv_floor = measurement_floor(data)
    if start.Rv_floor is not None and not settings.Rv_given:
        start.model = replace(start.model, noise=start.model.noise.floored(start.Rv_floor))
    if start.hold_modules and not settings.Rw_given and not settings.warm:
        Rw, start.noise_ladder = likeliest_process_noise(start.model, data, stage_seed(settings.random_state))
        start.model, start.staged = replace(start.model, Rw=Rw), replace(start.staged, Rw=Rw.clone())
    if restarts:
        start.limit, start.divergent_step = divergence_limit(start.model, data, check=not settings.warm)
        start.seeds = restart_seeds(settings.random_state, settings.n_runs)
    return start


def measurement_floor(data: SequenceBatch) -> torch.Tensor | None:
    """``q**2 / 12`` per output recorded on a grid of step ``q`` (:func:`quantization_step`), else 0;
    ``None`` when no output is.  A measurement noise below the rounding's own variance is not a
    sensor's noise: EM gets there when the model tracks every encoder step, and a Student-t noise
    then collapses its dof and flags regular samples as outliers."""
    y = torch.cat(data.unpad(data.y)).detach().cpu().numpy()
    q = quantization_step(y)
    if not np.any(q > 0):
        return None
    return torch.as_tensor(q**2 / 12.0, dtype=data.y.dtype, device=data.y.device)


#: A process noise not given starts at this fraction of the variance of each state's change per step
#: along the start's noise-free simulation (a slowly varying state gets a small one) after a kept
#: first stage; a simulation model's, whose simulation explains most of ``y``, at SIMULATION_SHARE of
#: that; a start without a kept first stage, whose simulation does not explain ``y``, at
#: UNEXPLAINED_SHARE, and at least the general default ``0.1 * I``: its states must reach what
#: ``y`` asks through the process noise in the first E-steps (a small one leaves them on the model's
#: simulation: on the paper's example EM then settles where g is nearly constant, and a network at
#: its identity start, whose simulation hardly moves, does not learn).
PROCESS_NOISE_SHARE = 0.1
SIMULATION_SHARE = 0.1
UNEXPLAINED_SHARE = 1.0


@torch.no_grad()
def scaled_process_noise(
    model: StateSpaceModel, data: SequenceBatch, share: float = PROCESS_NOISE_SHARE, states=None
) -> torch.Tensor:
    """``share`` times the variance of each state's increment along the model's
    noise-free simulation (diagonal; ``states``: that simulation when the caller has it); where it
    is not finite or does not move a state, that state keeps the given ``Rw``'s diagonal entry."""
    if states is None:
        states = prediction.free_run(model, data.u)[0]
    steps = [x[1:] - x[:-1] for x in data.unpad(states) if x.shape[0] > 1]
    given = torch.diagonal(model.Rw)
    if not steps:
        return model.Rw
    d = torch.cat(steps)
    d = d[torch.isfinite(d).all(-1)]
    if d.shape[0] < 2:
        return model.Rw
    var = share * d.var(0)
    ok = torch.isfinite(var) & (var > 0)
    return torch.diag(torch.where(ok, var, given))


@torch.no_grad()
def state_spread(model: StateSpaceModel, data: SequenceBatch, states=None) -> torch.Tensor:
    """The first state's prior covariance where ``x0_cov`` is not given, after a kept first stage:
    the variance of each state along the model's noise-free simulation (diagonal), the range the
    states visit in their own units; where that simulation is not finite or does not move a
    state, that state keeps the given prior's diagonal entry (the identity's).

    A prior of unit variance is 1e10 times too broad for a state of 1e-5 m: at the first step no
    particle is near what ``y`` says, the heavy-tailed noise takes the first samples for outliers,
    its degrees of freedom collapse and the noise estimates follow; a prior on the states' own
    scale makes a fit the same in any units.  ``states``: that simulation when the caller has it."""
    if states is None:
        states = prediction.free_run(model, data.u)[0]
    given = torch.diagonal(model.x0_cov)
    x = torch.cat(data.unpad(states))
    x = x[torch.isfinite(x).all(-1)]
    if x.shape[0] < 2:
        return model.x0_cov
    var = x.var(0)
    ok = torch.isfinite(var) & (var > 0)
    return torch.diag(torch.where(ok, var, given))


@torch.no_grad()
def simulation_start(
    model: StateSpaceModel, data: SequenceBatch, run: tuple, Rv_given: bool
) -> StateSpaceModel:
    """EM's start for a simulation model: unless given, the measurement noise's scale from the
    robust spread (1.4826 MAD about 0) of the output errors of the first stage's simulation ``run``
    (states, outputs)."""
    start = model
    if Rv_given:
        return start
    errors = torch.cat(data.unpad(data.y - run[1])).cpu().numpy()
    spread = robust_scale(errors, axis=0, center=0.0)
    current = torch.diagonal(model.Rv).cpu().numpy()
    var = np.where(np.isfinite(spread) & (spread > 0), spread**2, current)
    Rv = torch.diag(torch.as_tensor(var, dtype=model.Rv.dtype, device=model.Rv.device))
    return replace(start, noise=start.noise.replace(Rv=Rv))


def runs_first_stage(model: StateSpaceModel, settings: StartSettings) -> bool:
    """Whether the first stage runs from ``model`` (``first_stage`` and, for ``"auto"``, the model:
    free parameters in ``f`` or ``g``, physical or a network)."""
    if settings.warm:
        return False
    if settings.first_stage == "auto":  # a start for EM: none needed without EM (n_iter=0 evaluates a model)
        return settings.n_iter > 0 and (first_stage_applies(model) or holds_network(model))
    return settings.first_stage == "simulation"


def first_stage_start(
    model: StateSpaceModel, data: SequenceBatch, mode: str, random_state: Any = None
) -> tuple[FirstStageReport | NeuralFirstStageReport, tuple | None, StateSpaceModel]:
    """The robust simulation-error fit from ``model``: its report, the noise-free simulation
    ``(states, outputs)`` of its result if that is kept (else ``None``), and EM's start.

    A model whose ``f`` or ``g`` holds a network layer gets the neural first stage
    (:func:`network_first_stage`: a grey box's physical part first; the settings of its noise
    family, seeded by an integer ``random_state``, else 0), any other the physical one
    (:func:`~torch_nssm.estimation.first_stage.simulation_error_fit`); what follows is the same."""
    given = copy_model(model)
    if holds_network(model):
        generator = torch.Generator().manual_seed(stage_seed(random_state))
        report, first_states = network_first_stage(model, data, default_options(model.noise.name), generator)
        if not report.accepted and first_states is not None:  # only a grey box's physical part improved
            report = report.physical_stage
    else:
        report = simulation_error_fit(model, data)
        first_states = report.record_states
    if not report.accepted:
        return report, None, given
    staged = replace(model, x0_mean=first_states.mean(0))
    run = prediction.free_run(staged, data.u)
    report.explained = explained_share(run[1], data)
    if keep_first_stage(report, mode):
        return report, run, staged
    report.accepted = False
    report.first_states = None
    return report, None, given


def network_first_stage(
    model: StateSpaceModel, data: SequenceBatch, options: NeuralFirstStageOptions, generator: torch.Generator
) -> tuple[FirstStageReport | NeuralFirstStageReport, torch.Tensor | None]:
    """The first stage of a model holding a network, in place: a grey box's physical parameters
    first (:func:`physical_part_first`), then every parameter by the neural first stage from there.
    Returns the neural stage's report (``physical_stage``: the physical one) and each record's
    fitted first state: the neural stage's, the physical stage's where only that improved the free
    run (the modules at its fit), ``None`` where neither did (the modules as given).  A physical
    stage stopped by Ctrl-C is returned as it is (``interrupted``), the network untrained."""
    physical = physical_part_first(model, data)
    if physical is not None and physical.interrupted:
        return physical, physical.record_states if physical.accepted else None
    if physical is not None and physical.accepted:
        model = replace(model, x0_mean=physical.record_states.mean(0))
    report = neural_first_stage(model, data, options, generator=generator)
    report.physical_stage = physical
    if report.accepted:
        return report, report.first_states
    if physical is not None and physical.accepted:
        return report, physical.record_states
    return report, None


def physical_part_first(model: StateSpaceModel, data: SequenceBatch) -> FirstStageReport | None:
    """A grey box's physical parameters by the physical first stage before the network trains.

    Runs where ``f`` has free parameters outside its network layers (a
    :class:`~torch_nssm.neural.GreyBoxTransition`'s physical part) and ``g`` holds no network: the
    network layers' parameters of ``f`` are held (a correction that starts at zero leaves the
    physical model) while :func:`~torch_nssm.estimation.first_stage.simulation_error_fit` fits the
    others (``g``'s too) in place; ``None`` elsewhere (a network alone, a neural ``g``).  The
    neural first stage then trains every parameter from there.  From the physical part's start
    (30-50 % off) instead, the neural first stage lets the network carry the physics: on the
    pendulum with a dry friction its physical model lacks, 0.026 rad in 1,397 CPU s with ``g/l``
    left at 11.9 (the truth 19.6), against 0.017 rad in 265 s with ``g/l`` at 19.5 this way
    (benchmarks/README.md, "Grey boxes where the physics has a gap")."""
    if any(isinstance(sub, NETWORK_LAYERS) for sub in model.g.modules()):
        return None  # an untrained network as g: no physical model to fit f through
    layers = [sub for sub in model.f.modules() if isinstance(sub, NETWORK_LAYERS)]
    held = [p for sub in layers for p in sub.parameters() if p.requires_grad]
    in_layers = {id(p) for sub in layers for p in sub.parameters()}
    if not any(p.requires_grad and id(p) not in in_layers for p in model.f.parameters()):
        return None
    for prm in held:
        prm.requires_grad_(False)
    try:
        return simulation_error_fit(model, data)
    finally:
        for prm in held:
            prm.requires_grad_(True)


def stage_seed(random_state: Any) -> int:
    """The neural first stage's seed: ``random_state`` if it is an integer, else 0 (the stage is
    then repeatable, and the restarts' seeds, :func:`restart_seeds`, draw nothing for it)."""
    return int(random_state) if isinstance(random_state, (int, np.integer)) else 0


def keep_first_stage(report: FirstStageReport | NeuralFirstStageReport, mode: str) -> bool:
    """Whether EM starts from the first stage's result: always for ``"simulation"``; for ``"auto"``
    when its simulation explains at least ``SIMULATION_R2_FLOOR`` of ``y``.  Below it the process
    noise dominates ``y`` and a simulation-error fit is no guide to the parameters (the paper's
    example: robust R² 0.47-0.65 at the true values, and the first stage can land in a wrong
    basin), so EM starts from the given values."""
    return mode != "auto" or report.explained >= SIMULATION_R2_FLOOR


def explained_share(outputs: torch.Tensor, data: SequenceBatch) -> float:
    """Robust R² of time-major ``outputs`` ``(T, B, p)`` against ``y``."""
    yt = torch.cat(data.unpad(data.y)).cpu().numpy()
    return float(robust_r2_score(yt, torch.cat(data.unpad(outputs)).cpu().numpy()))


def divergence_limit(model: StateSpaceModel, data: SequenceBatch, check: bool) -> tuple[float, int | None]:
    """How far a restart's simulation may go before it counts as diverging: 1e3 times the larger of
    the start's own free-run range and the prior's scale.  With ``check``, also the step at which
    the start's own simulation leaves every finite bound (1e6 times that scale; ``None``: it
    does not)."""
    states, _ = prediction.free_run(model, data.u[:1000])
    finite = states[torch.isfinite(states)]
    prior = float(model.x0_mean.abs().max() + model.x0_cov.diagonal().sqrt().max())
    own = float(finite.abs().max()) if finite.numel() else 0.0
    scale = max(1.0, prior, own if own < 1e6 else 0.0)
    step = prediction.first_divergent_step(states, 1e6 * scale) if check else None
    return 1e3 * scale, step


def restart_seeds(random_state, n_runs: int) -> list[int]:
    """The seed of each EM run: run 0 the estimator's own (the one its ``_generator()`` draws), run
    ``r > 0`` the ``r``-th of a sequence drawn up front, so that run ``r`` depends on
    ``random_state`` and ``r`` alone (not on how many draws the earlier restarts' jitter needed)."""
    rs = check_random_state(random_state)
    first = int(rs.randint(0, 2**31 - 1))
    return [first] + [int(v) for v in rs.randint(0, 2**31 - 1, size=n_runs - 1)]


def seeded_generator(device: torch.device, rs: np.random.RandomState) -> torch.Generator:
    """A torch generator on ``device`` seeded by one draw of ``rs``."""
    gen = torch.Generator(device=device)
    gen.manual_seed(int(rs.randint(0, 2**31 - 1)))
    return gen


def copy_model(model: StateSpaceModel) -> StateSpaceModel:
    """``model`` with copies of its modules (the tensors are not updated in place)."""
    return replace(model, f=copy.deepcopy(model.f), g=copy.deepcopy(model.g))


def stable_jitter(
    base: StateSpaceModel, scale: float, rs: np.random.RandomState, data: SequenceBatch, limit: float
) -> tuple[StateSpaceModel, bool]:
    """A jittered restart whose noise-free simulation stays bounded, with ``g`` refitted to ``y``
    (up to ``JITTER_DRAWS`` draws), and whether one was found (else: the last draw as drawn)."""
    for _ in range(JITTER_DRAWS):
        start = jittered(base, scale, rs)
        if prediction.divergence(start, data.u, limit) is None:
            return g_fitted_to_y(start, data), True
    return start, False


def jittered(model: StateSpaceModel, scale: float, rs: np.random.RandomState) -> StateSpaceModel:
    """A copy whose free module parameters are multiplied by ``exp(scale * N(0, 1))``."""
    new = copy_model(model)
    with torch.no_grad():
        for module in (new.f, new.g):
            for p in module.parameters():
                if p.requires_grad:
                    eps = torch.from_numpy(rs.standard_normal(tuple(p.shape))).to(p)
                    p.mul_(torch.exp(scale * eps))
    return new


@torch.no_grad()
def g_fitted_to_y(model: StateSpaceModel, data: SequenceBatch, n_reweight: int = 3) -> StateSpaceModel:
    """For a ``g`` linear in its parameters: its free parameters refitted to ``y`` along the noise-free
    simulation of ``f`` (robust least squares, Cauchy weights), so that a restart's ``g`` has the
    scale of the data whatever the jitter drew.  Other modules are left as drawn."""
    g = model.g
    if not isinstance(g, LinearInParameters) or not bool(g.free_mask().any()):
        return model
    states, _ = prediction.free_run(model, data.u)
    mask = data.obs_mask  # (T, B, p)
    x, u, y = states[mask.any(-1)], data.u[mask.any(-1)], data.y[mask.any(-1)]
    m = mask[mask.any(-1)].to(y.dtype)
    precision = torch.diag_embed(m)  # missing components carry no weight
    weight = torch.ones(y.shape[0], dtype=y.dtype, device=y.device)
    backup = copy.deepcopy(g.state_dict())
    for _ in range(n_reweight + 1):
        g.solve_weighted_least_squares(x, u, y, weight, precision)
        r = torch.nan_to_num(y - g(x, u)) * m
        size = r.abs().sum(-1)
        scale = MAD_TO_STD * float(torch.median(size)) + 1e-300  # robust scale about 0
        weight = 1.0 / (1.0 + (size / (CAUCHY_TUNING * scale)) ** 2)  # Cauchy IRLS weights
    if not all(bool(torch.isfinite(p).all()) for p in g.parameters()):
        g.load_state_dict(backup)
    return model


# --------------------------------------------------------------------------- after EM
@dataclass
class SimulationCheck:
    """The comparison of the EM fit's noise-free simulation with the first stage's.

    Attributes
    ----------
    before, after : float
        Robust scale of the training free-run errors after the first stage and after EM.
    outcome : {"kept", "worse", "interrupted"}
        ``"kept"``: the fit simulates as its first stage did (a simulation model: EM kept ``f`` and
        ``g``), or within ``SIMULATION_TOLERANCE`` of it; ``"worse"``: EM moved a simulation model's
        ``f`` and ``g`` (``focus="prediction"``) so that it simulates worse than that;
        ``"interrupted"``: Ctrl-C stopped EM.
    """

    before: float
    after: float
    outcome: str = "kept"


def free_run_scale(outputs: torch.Tensor, data: SequenceBatch) -> float:
    """Robust scale (1.4826 MAD about 0) of the free run's output errors on the observed samples."""
    yt = torch.cat(data.unpad(data.y)).cpu().numpy()
    err = (yt - torch.cat(data.unpad(outputs)).cpu().numpy())[np.isfinite(yt)]
    return float(robust_scale(err, axis=None, center=0.0)) if err.size else math.nan


def check_simulation(
    start: Start, best, free_run_outputs: torch.Tensor, data: SequenceBatch
) -> SimulationCheck:
    """Compare the EM fit ``best`` (an ``EMResult``; ``free_run_outputs``: its noise-free outputs)
    with the kept first stage's simulation (``start.first_stage`` records both scales): outcome
    ``"worse"`` when EM moved ``f`` and ``g`` of a simulation model (``focus="prediction"``) so that
    it simulates more than ``SIMULATION_TOLERANCE`` worse, ``"interrupted"`` after a Ctrl-C."""
    before = free_run_scale(start.staged_run[1], data)
    after = free_run_scale(free_run_outputs, data)
    start.first_stage.free_run_scale_before_em = before
    start.first_stage.free_run_scale_after_em = after
    check = SimulationCheck(before, after)
    if best.interrupted:
        check.outcome = "interrupted"
    elif start.first_stage.explained >= SIMULATION_MODEL_R2 and not start.hold_modules:
        if np.isfinite(after) and after > SIMULATION_TOLERANCE * before:
            check.outcome = "worse"
    return check
