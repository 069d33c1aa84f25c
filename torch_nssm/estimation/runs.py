"""The driver of EM runs and the report of what they did.

:func:`drive` runs independent tasks (a fit's restarts, a study's chunks of data sets) here one
after another, stopping at a Ctrl-C, or on joblib workers (:mod:`torch_nssm._parallel`).
:class:`EMRunner` is one EM run of a fit from its planned start (:mod:`.start`), and
:func:`fit_runs` runs all of a fit's restarts through :func:`drive`.  What the runs did is a
:class:`FitReport` (runs, errors, rejected M-steps, interruption, convergence, the first stage, the
simulation check, the explained fractions): :mod:`torch_nssm.diagnostics.fit_warnings` writes
every warning of a fit or a study from it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from .. import _parallel
from .._threads import limited_threads
from ..core.model import SequenceBatch
from ..inference import prediction
from ..metrics import robust_r2_score
from .loop import EMOptions, EMResult, run_em
from .start import SimulationCheck, Start, check_simulation

__all__ = [
    "EMRunner",
    "FitReport",
    "Rejection",
    "RunOutcome",
    "drive",
    "explained_fractions",
    "first_stage_fallback",
    "fit_runs",
    "rejections_of",
]


def drive(
    fn: Callable, tasks: list[tuple], n_jobs: int | None, what: str, *, progress: bool, stop: Callable
) -> list:
    """``[fn(*task, progress=...) for task in tasks]``: here, one after another (with ``progress``;
    ``stop(result)`` true ends the job there: a Ctrl-C), or on ``min(len(tasks), n_jobs)`` joblib
    workers when that is more than one (no progress bars; the workers' warnings raised here)."""
    if min(len(tasks), _parallel.effective_n_jobs(n_jobs)) > 1:
        return _parallel.run_tasks(functools.partial(fn, progress=False), tasks, n_jobs, what)
    results = []
    for task in tasks:
        results.append(fn(*task, progress=progress))
        if stop(results[-1]):
            break
    return results


@dataclass
class EMRunner:
    """One EM run of a fit from its planned :class:`~.start.Start`, here or on a worker.

    Attributes
    ----------
    make_options : callable
        ``make_options(description, fit_Rw=None)``: the EM loop's options (``fit_Rw`` overrides the
        estimator's).
    n_threads : int or None
        CPU threads while the run works.
    n_init : int
        Number of runs (the progress bar's "run r/n").
    device : torch.device
    fit_Rw : bool or None
        Overrides the estimator's ``fit_Rw`` in every run (``warm_start=True`` continues the fit's).
    hold_modules : bool
        EM keeps ``f``'s and ``g``'s parameters and the first state's prior (a simulation model's
        runs: those of the first stage).
    """

    make_options: Callable[..., EMOptions]
    n_threads: int | None
    n_init: int
    device: torch.device
    fit_Rw: bool | None = None
    hold_modules: bool = False

    def __call__(
        self, start: Start, data: SequenceBatch, r: int, *, progress: bool = True, fit_Rw: bool | None = None
    ) -> tuple[EMResult, bool]:
        """Run ``r``'s EM result and whether its start's simulation stayed bounded (``fit_Rw``:
        this run's override)."""
        with limited_threads(self.n_threads):
            model, generator, stable = start.run_start(r, data, self.device)
            desc = "robust EM" if self.n_init == 1 else f"robust EM (run {r + 1}/{self.n_init})"
            options = self.make_options(desc, fit_Rw=self.fit_Rw if fit_Rw is None else fit_Rw)
            if self.hold_modules:  # a simulation model: its f, g and first state are the first stage's
                options.mstep.fit_modules = False
                # the prior's spread about that state is EM's: the spread of the states over the
                # whole record, the start's, is far wider than what the record leaves open
                options.mstep.fit_x0 = "cov" if options.mstep.fit_x0 else False
            options.mstep.Rv_floor = start.Rv_floor
            if not progress:
                options.progress = None
            return run_em([model], data, options, generator)[0], stable

    def without_iterations(self) -> EMRunner:
        """This runner with ``n_iter=0``: each run is the E-step at its start."""

        def make_options(*args, **kwargs) -> EMOptions:
            options = self.make_options(*args, **kwargs)
            options.n_iter = 0
            return options

        return dataclasses.replace(self, make_options=make_options)



def fit_runs(runner: EMRunner, start: Start, data: SequenceBatch, n_jobs: int | None) -> list[tuple]:
    """All of a fit's EM runs from ``start``, each ``(EMResult, start was stable)``: run ``r``
    depends on ``(random_state, r)`` only, here or on a worker."""
    n_runs = len(start.seeds)
    tasks = [(start, data, r) for r in range(n_runs)]
    return drive(
        runner, tasks, n_jobs, f"{n_runs} EM restarts", progress=True, stop=lambda run: run[0].interrupted
    )


def first_stage_fallback(runner: EMRunner, start: Start, data: SequenceBatch) -> EMResult | None:
    """The fit's start evaluated by one E-step, for a fit whose every EM run failed on a numerical
    error after a kept first stage: run 0's start (the first stage's ``f`` and ``g`` with the
    start's noise parameters), ``None`` when there is no kept first stage or its E-step fails too."""
    if start.staged is None:
        return None
    only = dataclasses.replace(start, seeds=start.seeds[:1])
    result = runner.without_iterations()(only, data, 0, progress=False)[0]
    return result if result.error is None and result.estep is not None else None


def best_run(runs: list[tuple], report: FitReport, fallback: Callable[[], EMResult | None] | None = None):
    """The kept run of a fit: the one with the highest final log-likelihood among those without an
    error; when every run failed on a numerical error after a kept first stage, the start evaluated
    by ``fallback()`` (:func:`first_stage_fallback`; ``report.fallback`` then names the error);
    ``None`` when no run finished and there is no such start.  Raises ``KeyboardInterrupt`` when
    Ctrl-C came before anything was fitted."""
    if runs[-1][0].interrupted and runs[-1][0].estep is None and len(runs) == 1:
        raise KeyboardInterrupt  # nothing was fitted yet
    good = report.good()
    if good:
        return runs[max(good, key=lambda i: report.outcomes[i].log_likelihood)][0]
    kept = fallback() if fallback is not None and not runs[0][0].interrupted else None
    if kept is not None:
        report.fallback = report.outcomes[0].error
    return kept


def last_good_run(runs: list[tuple]) -> EMResult | None:
    """Of runs that all failed, the one whose last good parameters have the highest log-likelihood
    (``None``: no run has any)."""
    candidates = [run for run, _ in runs if run.estep is not None]
    return max(candidates, key=lambda run: run.log_likelihood) if candidates else None


def kept_outputs(start: Start, best: EMResult, data: SequenceBatch, report: FitReport) -> torch.Tensor:
    """The kept run's noise-free outputs ``(T, B, p)``; after a kept first stage, the comparison of
    the two simulations goes in ``report.simulation``."""
    outputs = prediction.free_run(best.model, data.u)[1]
    if start.staged is not None:
        report.simulation = check_simulation(start, best, outputs, data)
    return outputs


# --------------------------------------------------------------------------- the report
@dataclass
class Rejection:
    """A module whose M-step updates were undone in ``n`` of ``of`` iterations."""

    label: str
    kind: str
    names: list[str]
    n: int
    of: int


def rejections_of(result: EMResult) -> list[Rejection]:
    """The modules of ``result`` whose M-step updates were undone (``history["rejected.f"]`` ...)."""
    out = []
    for label, module in (("f", result.model.f), ("g", result.model.g)):
        flags = result.history.get(f"rejected.{label}", [])[1:]
        n = int(np.sum(flags))
        if n:
            names = [name for name, p in module.named_parameters() if p.requires_grad]
            out.append(Rejection(label, type(module).__name__, names, n, len(flags)))
    return out


@dataclass
class RunOutcome:
    """What one EM run did (a fit's restart or a study's data set), small enough to cross processes.

    Attributes
    ----------
    error : str or None
        Why it stopped early (a numerical failure).
    fitted : bool
        It has an E-step at its parameters (something to store).
    converged, interrupted : bool
    n_done : int
    log_likelihood : float
        ``-inf`` without an E-step.
    rejections : list of Rejection
    stable_start : bool
        Its start's noise-free simulation stayed bounded (False: no jittered draw did).
    halted : str or None
        Why EM stopped at a good iterate before converging (:attr:`~.loop.EMResult.halted`).
    """

    error: str | None
    fitted: bool
    converged: bool
    interrupted: bool
    n_done: int
    log_likelihood: float
    rejections: list[Rejection] = field(default_factory=list)
    stable_start: bool = True
    halted: str | None = None

    @classmethod
    def of(cls, result: EMResult, stable_start: bool = True) -> RunOutcome:
        return cls(
            result.error,
            result.estep is not None,
            result.converged,
            result.interrupted,
            result.n_done,
            result.log_likelihood,
            rejections_of(result),
            stable_start,
            result.halted,
        )


@dataclass
class FitReport:
    """What a fit's (or a study's) EM runs did; the warnings are written from it.

    Attributes
    ----------
    outcomes : list of RunOutcome
        One per EM run: each restart of a fit, each data set of a study.
    settings : dict
        ``n_iter``, ``tol``, ``optimizer``, ``learning_rate`` (the words of the warnings).
    study : bool
        The runs are a study's data sets (:func:`torch_nssm.fit_independent`).
    kept : RunOutcome or None
        The fit's kept run (after the simulation check: possibly the re-run with ``Rw`` held).
    start : Start or None
        The fit's start: the first stage, the divergence of the start's simulation.
    simulation : SimulationCheck or None
        The comparison of the fit's simulation with the first stage's.
    explained, simulated : float
        Robust R² of the kept fit's smoothed outputs and of its noise-free simulation.
    absorption : str or None
        The noise family's words when it absorbs much of the data (model error taken for noise).
    outlier_weights
        The fitted outlier weights.
    fallback : str or None
        Every EM run failed on a numerical error (this is the first run's) and the fit keeps its
        start after a kept first stage (:func:`first_stage_fallback`); ``None`` otherwise.
    """

    outcomes: list[RunOutcome]
    settings: dict
    study: bool = False
    kept: RunOutcome | None = None
    start: Start | None = None
    simulation: SimulationCheck | None = None
    explained: float = math.nan
    simulated: float = math.nan
    absorption: str | None = None
    outlier_weights: Any = None
    fallback: str | None = None

    @property
    def interrupted(self) -> bool:
        """Ctrl-C stopped the fit (the kept run) or the study."""
        if self.kept is not None:
            return self.kept.interrupted
        return bool(self.outcomes) and self.outcomes[0].interrupted

    @property
    def failed(self) -> list[RunOutcome]:
        """The runs stopped by a numerical error."""
        return [o for o in self.outcomes if o.error is not None]

    def good(self) -> list[int]:
        """Indices of the runs without an error that have an E-step (candidates to keep)."""
        return [i for i, o in enumerate(self.outcomes) if o.error is None and o.fitted]

    def describe_kept(self, result: EMResult, data: SequenceBatch, outputs: torch.Tensor, weights):
        """Record the kept run (``outputs``: its noise-free outputs), how much of ``y`` it explains,
        its outlier ``weights`` and whether its noise absorbs the data."""
        self.kept = RunOutcome.of(result)
        self.explained, self.simulated = explained_fractions(result, data, outputs)
        self.outlier_weights = weights
        self.absorption = result.model.noise.absorption_message(weights)

    def init_log_likelihoods(self) -> np.ndarray:
        """Final log-likelihood estimate of each run (``-inf`` for a run stopped by an error)."""
        return np.array([o.log_likelihood if o.error is None else -np.inf for o in self.outcomes])


@torch.no_grad()
def explained_fractions(result: EMResult, data: SequenceBatch, free_run_outputs: torch.Tensor) -> tuple:
    """Robust R² against ``y`` of the smoothed outputs ``sum_l W_{k|N}^l g(x_k^l, u_k)`` and of the
    noise-free simulation (NaN scores count as explained: nothing to report)."""
    estep = result.estep
    g = result.model.observation_steps(estep.filter.particles, data.u)  # (T, B, L, p)
    w = torch.softmax(estep.smoother.log_weights, dim=-1).unsqueeze(-1)
    yt = torch.cat(data.unpad(data.y)).cpu().numpy()
    scores = []
    for y_hat in ((w * g).sum(2), free_run_outputs):
        score = robust_r2_score(yt, torch.cat(data.unpad(y_hat)).cpu().numpy())
        scores.append(score if np.isfinite(score) else 1.0)
    return scores[0], scores[1]

