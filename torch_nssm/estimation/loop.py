"""The EM loop: one driver for a single fit and for many independent fits.

``run_em(models, data, options)`` iterates E-step and M-step for one or several *groups* of
sequences: a single fit is one group whose sequences share the parameters (``shared=True``), and
a Monte Carlo study is one group per sequence (``shared=False``), whose E-steps run as one batch.
The driver owns what every fit needs: the particle schedule, convergence per group, the rollback
of an update whose E-step fails, the history of every parameter, Polyak averaging of the last
iterates and the final E-step, and a clean stop on Ctrl-C.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..core.model import SequenceBatch, StateSpaceModel
from ..inference.filtering import NumericalError, particle_filter
from ..inference.random import SequenceStreams
from .acceleration import acceleration_for
from .convergence import has_converged
from .estep import EStepOptions, EStepOutput, e_step, to_records
from .independent import stack_models
from .mstep import MStepOptions, m_step
from .snapshot import restore, snapshot

__all__ = ["EMOptions", "EMResult", "EStepCache", "run_em"]


@dataclass
class EMOptions:
    """Settings of the EM loop.

    Attributes
    ----------
    n_iter : int
        Maximum number of EM iterations.
    tol : float
        Convergence threshold on the change of the log-likelihood estimate per observation and
        iteration over the window in which every parameter's drift is tested
        (:func:`.convergence.has_converged`; 0: run all ``n_iter``).
    n_particles_final : int or None
        Grow the particle count geometrically from ``estep.n_particles`` to this at ``n_iter``.
    average_last : int
        Average the last ``average_last`` iterates (if > 1) before the final E-step.
    acceleration : {None, "squarem", "newton"}
        ``"squarem"``: squared extrapolation of the noise parameters (single fits).  ``"newton"``:
        also Newton-type steps for ``f``'s and ``g``'s parameters from the observed
        information, until a step is within one standard error, then squared extrapolation of
        the noise parameters (:mod:`.acceleration`; single fits with an exact E-step only).
    estep, mstep : EStepOptions, MStepOptions
    progress : str or None
        Description of a progress bar (``None``: no bar).
    """

    n_iter: int = 100
    tol: float = 1e-3
    n_particles_final: int | None = None
    average_last: int = 0
    acceleration: str | None = None
    estep: EStepOptions = field(default_factory=EStepOptions)
    mstep: MStepOptions = field(default_factory=MStepOptions)
    progress: str | None = None

    def n_particles(self, iteration: int | None) -> int:
        """Particle count at EM ``iteration`` (``None``: after fitting)."""
        L0, L1 = self.estep.n_particles, self.n_particles_final
        if L1 is None:
            return L0
        if iteration is None or self.n_iter == 0:
            return L1
        frac = min(iteration, self.n_iter) / self.n_iter
        return int(round(L0 * (L1 / L0) ** frac))


@dataclass
class EMResult:
    """The outcome of EM for one group.

    Attributes
    ----------
    model : StateSpaceModel
        The last good parameters (averaged if asked).
    estep : EStepOutput or None
        The E-step at ``model`` (``None`` if EM could not start).
    history : dict of str to list
        Every parameter and the log-likelihood estimate at every iteration (index 0: the start),
        and ``"rejected.f"``/``"rejected.g"``: whether the M-step leading to that iterate undid
        that module's step (its loss got worse or non-finite).
    n_done : int
        Completed iterations.
    converged : bool
    error : str or None
        Why EM stopped early (a numerical failure), else ``None``.
    interrupted : bool
        Stopped by Ctrl-C (``KeyboardInterrupt``) after ``n_done`` iterations.
    halted : str or None
        Why EM stopped at a good iterate before converging (the log-likelihood estimate fell far
        more than its Monte Carlo error after an M-step, which was undone), else ``None``.
    """

    model: StateSpaceModel
    estep: EStepOutput | None
    history: dict
    n_done: int = 0
    converged: bool = False
    error: str | None = None
    interrupted: bool = False
    halted: str | None = None

    @property
    def log_likelihood(self) -> float:
        return -math.inf if self.estep is None else float(self.estep.log_likelihood.sum())


def record(history: dict, model: StateSpaceModel, log_likelihood: float) -> None:
    """Append the model's parameters and the log-likelihood estimate to ``history``."""
    for key in ("rejected.f", "rejected.g", "accelerated"):  # flags of the M-step that led here
        if key == "accelerated" and key not in history:
            continue
        flags = history[key]
        if len(flags) < len(history["log_likelihood"]) + 1:
            flags.append(False)
    history["log_likelihood"].append(log_likelihood)
    for label, module in (("f", model.f), ("g", model.g)):
        for name, p in module.named_parameters():
            history[f"{label}.{name}"].append(p.detach().cpu().numpy().copy())
    history["Rw"].append(model.Rw.detach().cpu().numpy())
    for name, value in model.noise.parameters().items():
        history[name].append(value.detach().cpu().numpy() if value.dim() else float(value))
    history["x0_mean"].append(model.x0_mean.detach().cpu().numpy())


def averaged(model: StateSpaceModel, history: dict, k: int) -> StateSpaceModel:
    """The model at the average of the last ``k`` recorded iterates (parameters and noise)."""
    for label, module in (("f", model.f), ("g", model.g)):
        with torch.no_grad():
            for name, p in module.named_parameters():
                if p.requires_grad:
                    p.copy_(torch.as_tensor(np.mean(history[f"{label}.{name}"][-k:], axis=0)))
    mean = lambda key, like: torch.as_tensor(np.mean(history[key][-k:], axis=0)).to(like)  # noqa: E731
    noise = model.noise.replace(**{n: mean(n, v) for n, v in model.noise.parameters().items()})
    return replace(model, Rw=mean("Rw", model.Rw), noise=noise, x0_mean=mean("x0_mean", model.x0_mean))


class _Batch:
    """The active groups' models and data as one batch (the same order as the groups)."""

    def __init__(self, groups: list[int], models: list[StateSpaceModel], data: SequenceBatch, shared: bool):
        if shared:
            self.model, self.data = models[0], data
        else:
            idx = torch.tensor(groups, device=data.y.device)
            self.model = stack_models([models[g] for g in groups])
            self.data = data if len(groups) == data.n_sequences else data.select(idx)


class EStepCache:
    """The E-steps of one EM loop: the last E-step output of each group, and the one spare output
    whose arrays the next E-step overwrites (``e_step``'s ``recycle``: fresh arrays cost their
    first-touch page faults, about a third of an iteration on a CPU).

    Parameters
    ----------
    models : list of StateSpaceModel
        The loop's models, one per group (the list the loop updates).
    data, options, generator, shared
        As :func:`run_em`'s.
    run : callable
        The E-step function (:func:`~torch_nssm.estimation.estep.e_step`).
    """

    def __init__(self, models, data: SequenceBatch, options: EMOptions, generator, shared: bool, run):
        self.models, self.data, self.options = models, data, options
        self.generator, self.shared, self.run = generator, shared, run
        self.last: list[tuple[EStepOutput, int] | None] = [None] * len(models)  # (batch output, index)
        self.batch: _Batch | None = None  # the groups of the last E-step, as one batch
        self.latest: EStepOutput | None = None  # the last E-step's output
        self.spare: EStepOutput | None = None  # an E-step output nothing reads any more

    def __call__(self, groups: list[int], iteration: int | None, n_particles: int | None = None) -> None:
        """The E-step of ``groups`` at their current models (``iteration`` sets the particle count;
        ``None``: the final count; ``n_particles`` overrides it)."""
        batch = _Batch(groups, self.models, self.data, self.shared)
        n_particles = n_particles or self.options.n_particles(iteration)
        options = replace(self.options.estep, n_particles=n_particles)
        gen = self.generator.select(groups) if isinstance(self.generator, SequenceStreams) else self.generator
        old = self.output(groups[0])
        previous = old if self.shared else None
        recycle, self.spare = self.spare, None
        size = (batch.data.n_sequences, options.n_particles)
        if recycle is not None and tuple(recycle.filter.particles.shape[1:3]) != size:
            recycle = None  # other sizes: freed before this E-step, not held through it
        estep = self.run(batch.model, batch.data, options, gen, previous, records=False, recycle=recycle)
        for j, g in enumerate(groups):
            self.last[g] = (estep, j)
        if old is not None and old.windows is None and all(e is None or e[0] is not old for e in self.last):
            self.spare = old  # its arrays are overwritten by the E-step after next
        self.batch, self.latest = batch, estep

    def output(self, group: int) -> EStepOutput | None:
        """The last E-step output that covers ``group`` (a batch's; ``None`` before the first)."""
        last = self.last[group]
        return None if last is None else last[0]

    def selection(self, update: list[int], n_active: int) -> tuple[SequenceBatch, EStepOutput]:
        """The data and E-step output of the positions ``update`` among the ``n_active`` groups of
        the last E-step (what the M-step sees: a segmented E-step's windows own their samples)."""
        estep = self.latest
        if len(update) == n_active:  # the usual case: no copy of the E-step output
            return (self.batch.data if estep.windows is None else estep.windows.owned_data), estep
        sel = torch.tensor(update, device=self.data.y.device)
        return self.batch.data.select(sel), estep.select(sel)

    def result(self, group: int, model: StateSpaceModel) -> EStepOutput | None:
        """``group``'s E-step output at the end: per record, the group's own sequences."""
        if self.last[group] is None:
            return None
        estep, j = self.last[group]
        return to_records(estep, model, self.data) if self.shared else estep.select(slice(j, j + 1))


@dataclass
class _Groups:
    """What the loop knows of each group: its model, history, log-likelihood estimates, completed
    iterations, convergence and error, and which groups are still iterating."""

    models: list[StateSpaceModel]
    shared: bool
    n_obs: list[int]
    histories: list = field(default_factory=list)
    lls: list = field(default_factory=list)
    n_done: list = field(default_factory=list)
    done: list = field(default_factory=list)
    errors: list = field(default_factory=list)
    active: list = field(default_factory=list)
    snapshots: dict = field(default_factory=dict)  # the iterates before the running M-step
    interrupted: bool = False
    halted: dict = field(default_factory=dict)  # group -> why it stopped at its previous iterate

    @classmethod
    def start(cls, models: list[StateSpaceModel], data: SequenceBatch, shared: bool) -> _Groups:
        n = len(models)
        observed = data.obs_mask.any(-1).sum(0).tolist()
        return cls(
            list(models),
            shared,
            [sum(observed)] if shared else observed,
            histories=[defaultdict(list) for _ in range(n)],
            lls=[[] for _ in range(n)],
            n_done=[0] * n,
            done=[False] * n,
            errors=[None] * n,
            active=list(range(n)),
        )

    def record(self, estep: EStepCache, it: int, options: EMOptions) -> list[int]:
        """Record the active groups' iterates and their E-step's log-likelihood; the positions (in
        ``active``) of the groups that go on: not converged and ``it < n_iter``."""
        if not self.active:
            return []
        batch_lls = estep.latest.log_likelihood.tolist()
        update = []
        for j, g in enumerate(self.active):
            ll = sum(batch_lls) if self.shared else batch_lls[j]
            record(self.histories[g], self.models[g], ll)
            self.lls[g].append(ll)
            scales = self.models[g].noise.convergence_scales(self.n_obs[g])
            scales = {k: v.detach().cpu().numpy() for k, v in scales.items()}
            scales["Rw"] = np.full(self.models[g].Rw.shape, math.sqrt(2.0 / max(self.n_obs[g], 1)))
            if has_converged(self.histories[g], self.n_obs[g], options.tol, max(options.tol, 1e-4), scales):
                self.done[g] = True
            elif it < options.n_iter:
                update.append(j)
        return update

    def stop(self, groups: list[int], message: str, *, back: bool = True) -> None:
        """``groups`` stop with an error (``back``: at the iterate before the running M-step)."""
        for g in groups:
            if back:
                self.models[g] = restore(self.snapshots[g])
            self.errors[g] = message

    def undo_unfinished(self) -> None:
        """Ctrl-C: every group keeps its last completed iteration (an interrupted M-step is undone)."""
        self.interrupted = True
        for g in range(len(self.models)):
            if g in self.snapshots and self.n_done[g] < len(self.lls[g]):
                self.models[g] = restore(self.snapshots[g])

    def results(self, estep: EStepCache) -> list[EMResult]:
        out = []
        for g, model in enumerate(self.models):
            history = dict(self.histories[g])
            for key in ("rejected.f", "rejected.g", "accelerated"):  # an interrupt or error can leave a
                if key in history or key != "accelerated":  # flag without its iterate
                    history[key] = history.get(key, [])[: len(history.get("log_likelihood", []))]
            n_done, done, error = self.n_done[g], self.done[g], self.errors[g]
            interrupted = self.interrupted
            result = EMResult(model, estep.result(g, model), history, n_done, done, error, interrupted)
            result.halted = self.halted.get(g)
            out.append(result)
        return out


def run_em(
    models: list[StateSpaceModel],
    data: SequenceBatch,
    options: EMOptions,
    generator: torch.Generator | SequenceStreams | None = None,
    *,
    shared: bool = True,
) -> list[EMResult]:
    """Run EM from ``models`` until convergence, ``n_iter`` iterations, an error or Ctrl-C.

    Parameters
    ----------
    models : list of StateSpaceModel
        The starting model of each group: one (``shared=True``: all sequences of ``data`` share
        it) or one per sequence (independent fits, E-steps batched).  Their modules are updated
        in place.
    data : SequenceBatch
    options : EMOptions
    generator : torch.Generator or SequenceStreams, optional
        The particle methods' random numbers: one generator, or one stream per group
        (``shared=False``: each group's draws then depend on its own stream alone).

    Returns
    -------
    list of EMResult
        One per group; a group stopped by an error or an interrupt keeps its last good model.
    """
    groups = _Groups.start(models, data, shared)
    estep = EStepCache(groups.models, data, options, generator, shared, e_step)
    # acceleration: single fits; Newton steps need the exact E-step (the information)
    exact = shared and (options.estep.segment_length is None or options.acceleration == "squarem")
    acceleration = acceleration_for(
        options.acceleration if exact else None,
        n_obs=groups.n_obs[0],
        history=groups.histories[0],
    )
    bar = _progress_bar(options.n_iter, options.progress)
    try:
        failure = _attempt(estep, groups.active, 0)
        if failure is None:
            acceleration.start(groups.models[0])
        else:
            message = f"EM could not start: the E-step failed at the initial parameters: {failure}"
            groups.stop(groups.active, message, back=False)
            groups.active = []
        for it in range(options.n_iter + 1):
            update = groups.record(estep, it, options)  # the groups that go on
            if not update:
                break
            _iterate(groups, update, it, estep, acceleration, options, generator)
            bar.update(1)
            _show(bar, groups, estep)
    except KeyboardInterrupt:
        groups.undo_unfinished()
    finally:
        bar.close()
    if not groups.interrupted:
        _finish(groups, options, estep)
    return groups.results(estep)


def _iterate(
    groups: _Groups, update: list[int], it: int, estep: EStepCache, acceleration, options, generator
) -> None:
    """EM iteration ``it + 1`` of the active groups at positions ``update``: the M-step, the
    acceleration's step, the E-step at the new iterates; a group whose M-step or E-step fails stops
    at its last iterate."""
    ids = [groups.active[j] for j in update]
    groups.snapshots = {g: snapshot(groups.models[g]) for g in ids}
    sub_data, sub_estep = estep.selection(update, len(groups.active))
    acceleration.before_mstep(groups.models[0], sub_data, sub_estep, generator)
    still, rejected = _m_step(groups, ids, sub_data, sub_estep, options, generator, it)
    if still:
        stepped = groups.models[0]  # the M-step floored its own noise update
        groups.models[0] = acceleration.after_mstep(stepped, rejected)
        if groups.models[0] is not stepped and options.mstep.Rv_floor is not None and options.mstep.fit_Rv:
            floored = groups.models[0].noise.floored(options.mstep.Rv_floor)  # an extrapolated noise
            groups.models[0] = replace(groups.models[0], noise=floored)
        failure = _attempt(estep, still, it + 1)
        undo = acceleration.after_estep(groups.lls[0][-1], estep.latest if failure is None else None)
        if undo is not None:  # the accelerated step lost likelihood or failed: the M-step's instead
            groups.models[0] = undo
            failure = _attempt(estep, still, it + 1)
        if failure is not None:
            groups.stop(still, f"EM stopped at iteration {it + 1}: {failure}")
            still = []
    still = _halt_on_collapse(groups, still, it, estep)
    for g in still:
        groups.n_done[g] += 1
    groups.active = still


#: An iteration whose log-likelihood estimate falls by more than this per observation (and by more
#: than COLLAPSE_MIN) is undone and ends EM: EM does not lower the likelihood, and a particle
#: estimate's Monte Carlo error is a few units; such a fall means a degenerate filter (a noise
#: parameter shrinking towards zero) or an M-step that should not have been taken.
COLLAPSE_PER_OBS = 0.5
COLLAPSE_MIN = 100.0

#: A single fit's fall is first measured again: both iterates' log-likelihood by one filter pass of
#: this many times the E-step's particles (the same random numbers for both).  Where the filter is
#: barely adequate, the estimate at the E-step's count swings far more than its usual few units:
#: the suite's axis (25,000 samples, encoder-limited output) at one iterate gave 210,998 and
#: 259,034 with 200 particles and two seeds, 262,821 and 262,396 with 800, and its "collapse" from
#: 251,027 to 212,781 was an iterate 6,000 units *better* at 800 particles.  A filter pass costs a
#: fraction of the E-step (the smoother's work grows with the square of the particles): 5.5 s at
#: 800 particles against an E-step of 11.8 s at 200 there.
COLLAPSE_RECHECK_FACTOR = 4


def _halt_on_collapse(groups: _Groups, still: list[int], it: int, estep: EStepCache) -> list[int]:
    """The groups of ``still`` whose new log-likelihood estimate did not collapse; the others get
    their previous iterate back (and its E-step) and stop, with the reason in ``groups.halted``.
    A single fit's fall is measured again with more particles (:data:`COLLAPSE_RECHECK_FACTOR`)
    before it counts; where that acquits the iterate, its E-step (the outlying estimate, whose
    smoother the next M-step would read) is run again with those particles."""
    if not still:
        return still
    lls = estep.latest.log_likelihood.tolist()
    fallen, acquitted, n_recheck = [], [], None
    for j, g in enumerate(still):
        ll = sum(lls) if groups.shared else lls[j]
        drop = groups.lls[g][-1] - ll
        limit = max(COLLAPSE_PER_OBS * groups.n_obs[g], COLLAPSE_MIN)
        again = ""
        if drop > limit and groups.shared and estep.options.estep.segment_length is None:
            n_recheck = COLLAPSE_RECHECK_FACTOR * estep.options.n_particles(it + 1)
            drop = _remeasured_fall(groups.snapshots[g], groups.models[g], estep, n_recheck, seed=it + 1)
            again = f"; measured again with {n_recheck} particles: a fall of {drop:.6g}"
            if drop <= limit:
                acquitted.append(g)
        if drop > limit:
            fallen.append(g)
            groups.halted[g] = (
                f"the log-likelihood estimate fell from {groups.lls[g][-1]:.6g} to {ll:.6g} at iteration "
                f"{it + 1}{again} "
                "(far more than its Monte Carlo error: the particle filter degenerates, e.g. as a noise "
                "parameter shrinks, or the M-step went wrong), so that iteration was undone and EM stopped "
                f"at iteration {it}"
            )
    if acquitted:
        # the iterate is fine, its E-step's estimate is the outlier: a particle filter's log-likelihood
        # has heavy tails, and an M-step after such an E-step undoes the noise model (the suite's tanks:
        # dof 7.5 -> 3.0 on clean data, ~20 iterations to recover; benchmarks/README.md, "When EM
        # stops").  Its E-step again, with the particles that acquitted it: what the next M-step reads
        failure = _attempt(estep, acquitted, it + 1, n_particles=n_recheck)
        if failure is not None:
            groups.stop(acquitted, f"EM stopped at iteration {it + 1}: {failure}")
            still = [g for g in still if g not in acquitted]
    if not fallen:
        return still
    for g in fallen:
        groups.models[g] = restore(groups.snapshots[g])
        for key in ("rejected.f", "rejected.g"):  # the flags of the undone M-step
            if len(groups.histories[g][key]) > len(groups.lls[g]) - 1:
                groups.histories[g][key].pop()
    _attempt(estep, fallen, it)
    return [g for g in still if g not in fallen]


def _remeasured_fall(
    kept: tuple, model: StateSpaceModel, estep: EStepCache, n_particles: int, seed: int
) -> float:
    """How far the log-likelihood falls from the iterate ``kept`` (a snapshot) to ``model``, each by
    one pass of the E-step's filter with ``n_particles`` from ``seed`` (its own generator: the fit's
    random stream is not touched); ``inf`` where a pass fails."""
    options = estep.options.estep

    def log_likelihood(m: StateSpaceModel) -> float:
        generator = torch.Generator(device=estep.data.y.device).manual_seed(seed)
        try:
            out = particle_filter(
                m, estep.data, n_particles, resampling=options.resampling,
                ess_threshold=options.ess_threshold, generator=generator,
            )  # fmt: skip
        except (NumericalError, torch.linalg.LinAlgError):
            return math.nan
        return float(out.log_likelihood.sum())

    new = log_likelihood(model)
    current = snapshot(model)  # the kept iterate shares the modules: set back, measured, undone
    try:
        old = log_likelihood(restore(kept))
    finally:
        restore(current)
    drop = old - new
    return drop if math.isfinite(drop) else math.inf


def _m_step(groups: _Groups, ids: list[int], data, estep, options: EMOptions, generator, it: int) -> tuple:
    """The M-step of the groups ``ids``: the groups it updated, and whether it undid a module's step."""
    m_options = options.mstep
    if isinstance(generator, SequenceStreams):  # each data set's minibatches from its stream
        m_options = replace(m_options, solver=replace(m_options.solver, generator=generator.select(ids)))
    result = m_step([groups.models[g] for g in ids], data, estep, m_options, shared=groups.shared)
    still, rejected = [], False
    for g, new, error, report in zip(ids, result.models, result.errors, result.reports):
        if error is not None:
            groups.errors[g] = f"EM stopped at iteration {it + 1}: {error}"
            continue
        for label in ("f", "g"):  # index it + 1: the iterate this M-step produced
            groups.histories[g][f"rejected.{label}"].append(bool(report[label].rejected))
            rejected = rejected or bool(report[label].rejected)
        groups.models[g] = new
        still.append(g)
    return still, rejected


def _attempt(
    estep: EStepCache, groups: list[int], iteration: int | None, n_particles: int | None = None
) -> str | None:
    """Run the E-step of ``groups``; why it failed (``None`` if it did not)."""
    try:
        estep(groups, iteration, n_particles)
    except (NumericalError, torch.linalg.LinAlgError) as exc:
        return str(exc)
    return None


def _show(bar, groups: _Groups, estep: EStepCache) -> None:
    """The progress bar: log-likelihood per observation, and the noise family's scalar parameters."""
    if groups.shared and groups.active:
        ll = float(estep.latest.log_likelihood.sum())
        postfix = {"loglik": f"{ll / max(groups.n_obs[0], 1):.4f}/obs"}
        for name, value in groups.models[0].noise.parameters().items():  # its scalar parameters
            if value.dim() == 0:
                postfix[name] = f"{float(value):.3g}"
        bar.set_postfix(postfix)


def _finish(groups: _Groups, options: EMOptions, estep: EStepCache) -> None:
    """Average the last iterates and/or run the final E-step at the final particle count."""
    K = options.average_last
    final = [
        g
        for g in range(len(groups.models))
        if groups.errors[g] is None
        and ((K > 1 and groups.n_done[g] >= K) or (options.n_particles_final and groups.n_done[g]))
    ]
    if not final:
        return
    for g in final:
        if K > 1 and groups.n_done[g] >= K:
            groups.models[g] = averaged(groups.models[g], groups.histories[g], K)
    estep(final, None)


def _progress_bar(total: int, desc: str | None):
    """A tqdm bar (a notebook widget where available); imported only when shown."""
    from tqdm import tqdm

    if desc is None:
        return tqdm(total=total, disable=True)
    from tqdm.auto import tqdm as auto_tqdm  # warns in kernels without ipywidgets: only if asked

    return auto_tqdm(total=total, desc=desc, leave=True)
