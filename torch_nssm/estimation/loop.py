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
from ..inference.filtering import NumericalError
from ..inference.random import SequenceStreams
from .acceleration import MAX_FACTOR, NoiseExtrapolation, information_at, newton_step, newton_tolerance
from .estep import EStepOptions, EStepOutput, e_step, to_records
from .independent import stack_models
from .mstep import MStepOptions, m_step, module_state

__all__ = ["EMOptions", "EMResult", "run_em", "CONVERGENCE_WINDOW"]

#: Convergence compares the mean log-likelihood estimate of the last CONVERGENCE_WINDOW iterations
#: with that of the window before: single particle estimates are too noisy to compare.
CONVERGENCE_WINDOW = 5


@dataclass
class EMOptions:
    """Settings of the EM loop.

    Attributes
    ----------
    n_iter : int
        Maximum number of EM iterations.
    tol : float
        Convergence threshold on the change of the per-observation log-likelihood, averaged over
        windows of :data:`CONVERGENCE_WINDOW` iterations (0: run all ``n_iter``).
    n_particles_final : int or None
        Grow the particle count geometrically from ``estep.n_particles`` to this at ``n_iter``.
    average_last : int
        Average the last ``average_last`` iterates (if > 1) before the final E-step.
    acceleration : {None, "newton"}
        ``"newton"``: Newton-type steps for ``f``'s and ``g``'s parameters from the observed
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
    """

    model: StateSpaceModel
    estep: EStepOutput | None
    history: dict
    n_done: int = 0
    converged: bool = False
    error: str | None = None
    interrupted: bool = False

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


def converged(lls: list[float], n_obs: int, tol: float) -> bool:
    """Whether the windowed mean log-likelihood changed by less than ``tol`` per observation."""
    w = CONVERGENCE_WINDOW
    if tol <= 0 or len(lls) < 2 * w:
        return False
    recent, before = np.mean(lls[-w:]), np.mean(lls[-2 * w : -w])
    return abs(recent - before) / max(n_obs, 1) < tol


class _Batch:
    """The active groups' models and data as one batch (the same order as the groups)."""

    def __init__(self, groups: list[int], models: list[StateSpaceModel], data: SequenceBatch, shared: bool):
        if shared:
            self.model, self.data = models[0], data
        else:
            idx = torch.tensor(groups, device=data.y.device)
            self.model = stack_models([models[g] for g in groups])
            self.data = data if len(groups) == data.n_sequences else data.select(idx)


def _snapshot(model: StateSpaceModel):
    return model, module_state(model.f), module_state(model.g)


def _restore(snapshot) -> StateSpaceModel:
    model, f_state, g_state = snapshot
    model.f.load_state_dict(f_state)
    model.g.load_state_dict(g_state)
    return model


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
    n_groups = len(models)
    models = list(models)
    histories = [defaultdict(list) for _ in range(n_groups)]
    lls: list[list[float]] = [[] for _ in range(n_groups)]
    n_done = [0] * n_groups
    done = [False] * n_groups
    errors: list[str | None] = [None] * n_groups
    last: list[tuple[EStepOutput, int] | None] = [None] * n_groups
    observed = data.obs_mask.any(-1).sum(0).tolist()
    n_obs = [sum(observed)] if shared else observed
    interrupted = False

    spare: list[EStepOutput | None] = [None]  # an E-step output nothing reads any more

    def estep(groups: list[int], iteration: int | None) -> _Batch:
        batch = _Batch(groups, models, data, shared)
        est_options = replace(options.estep, n_particles=options.n_particles(iteration))
        gen = generator.select(groups) if isinstance(generator, SequenceStreams) else generator
        previous = last[groups[0]][0] if shared and last[groups[0]] is not None else None
        old = last[groups[0]][0] if last[groups[0]] is not None else None
        recycle, spare[0] = spare[0], None
        size = (batch.data.n_sequences, est_options.n_particles)
        if recycle is not None and tuple(recycle.filter.particles.shape[1:3]) != size:
            recycle = None  # other sizes: freed before this E-step, not held through it
        est = e_step(batch.model, batch.data, est_options, gen, previous, records=False, recycle=recycle)
        for j, g in enumerate(groups):
            last[g] = (est, j)
        if old is not None and old.windows is None and all(e is None or e[0] is not old for e in last):
            spare[0] = old  # its arrays are overwritten by the E-step after next (e_step's recycle)
        return batch

    active = list(range(n_groups))
    snapshots: dict[int, tuple] = {}
    accelerating = options.acceleration == "newton" and shared and options.estep.segment_length is None
    previous_step, max_factor = None, MAX_FACTOR  # the last Newton step taken, the cap of the next
    extrapolation = NoiseExtrapolation(options.mstep.dof_bounds, n_obs[0]) if accelerating else None
    if accelerating:
        histories[0]["accelerated"] = []
    bar = _progress_bar(options.n_iter, options.progress)
    try:
        try:
            batch = estep(active, 0)
        except (NumericalError, torch.linalg.LinAlgError) as exc:
            for g in active:
                errors[g] = f"EM could not start: the E-step failed at the initial parameters: {exc}"
            active = []
        if extrapolation is not None and active:
            extrapolation.start(models[0])
        for it in range(options.n_iter + 1):
            if not active:
                break
            est = last[active[0]][0]
            batch_lls = est.log_likelihood.tolist()
            update = []
            for j, g in enumerate(active):
                ll = sum(batch_lls) if shared else batch_lls[j]
                record(histories[g], models[g], ll)
                lls[g].append(ll)
                import os
                if os.environ.get("NSSM_CONV") == "new":
                    from .convergence import has_converged
                    stop = has_converged(histories[g], n_obs[g], options.tol)
                else:
                    stop = converged(lls[g], n_obs[g], options.tol)
                if stop:
                    done[g] = True
                elif it < options.n_iter:
                    update.append(j)
            if not update:
                break
            snapshots = {active[j]: _snapshot(models[active[j]]) for j in update}
            ids = [active[j] for j in update]
            if len(update) == len(active):  # the usual case: no copy of the E-step output
                sub_data, sub_est = batch.data if est.windows is None else est.windows.owned_data, est
            else:
                sel = torch.tensor(update, device=data.y.device)
                sub_data, sub_est = batch.data.select(sel), est.select(sel)
            at = None
            if accelerating:  # the information at the current parameters, before the M-step moves them
                try:
                    at = information_at(models[0], sub_data, sub_est, generator)
                except (RuntimeError, ValueError, NotImplementedError, torch.linalg.LinAlgError):
                    at = None
                accelerating = at is not None
            m_options = options.mstep
            if isinstance(generator, SequenceStreams):  # each data set's minibatches from its stream
                solver = replace(m_options.solver, generator=generator.select(ids))
                m_options = replace(m_options, solver=solver)
            result = m_step([models[g] for g in ids], sub_data, sub_est, m_options, shared=shared)
            still = []
            for g, new, error, report in zip(ids, result.models, result.errors, result.reports):
                if error is not None:
                    errors[g] = f"EM stopped at iteration {it + 1}: {error}"
                    continue
                for label in ("f", "g"):  # index it + 1: the iterate this M-step produced
                    histories[g][f"rejected.{label}"].append(bool(report[label].rejected))
                models[g] = new
                still.append(g)
            em_iterate = None  # while an accelerated step replaces the M-step's: the M-step's iterate
            if extrapolation is not None and still:  # (single fits with acceleration="newton")
                rejected = any(report[label].rejected for report in result.reports for label in ("f", "g"))
                if at is not None and not rejected:
                    snapshot = _snapshot(models[0])
                    step = newton_step(at, models[0], previous_step, max_factor)
                    if step.reason == "reversed":  # the last Newton step overshot: shorter ones from now
                        max_factor /= 2.0
                    accelerating = not step.done and max_factor >= 2.0
                    if step.taken:
                        em_iterate, previous_step = snapshot, step.delta
                # the measurement noise jumps from the start, the process noise once the Newton
                # steps end (its jumps moved their maximum)
                extrapolated = extrapolation.propose(models[0], rejected, ("Rw",) if accelerating else ())
                if extrapolated is not None:
                    em_iterate = _snapshot(models[0]) if em_iterate is None else em_iterate
                    models[0] = extrapolated
                histories[0]["accelerated"].append(em_iterate is not None)
            if still:
                try:
                    batch = estep(still, it + 1)
                    lost = em_iterate is not None and (
                        lls[0][-1] - float(last[0][0].log_likelihood.sum()) > newton_tolerance(n_obs[0])
                    )
                except (NumericalError, torch.linalg.LinAlgError) as exc:
                    batch, failure, lost = None, str(exc), em_iterate is not None
                if lost:  # the accelerated step lost likelihood or failed: the M-step's instead
                    models[0], accelerating = _restore(em_iterate), False  # Newton: EM from here
                    histories[0]["accelerated"][-1] = False
                    if extrapolation is not None:  # the noise: shorter jumps, a new cycle at the M-step's
                        extrapolation.undone(models[0])
                    try:
                        batch = estep(still, it + 1)
                    except (NumericalError, torch.linalg.LinAlgError) as exc:
                        batch, failure = None, str(exc)
                if batch is None:
                    for g in still:
                        models[g] = _restore(snapshots[g])
                        errors[g] = f"EM stopped at iteration {it + 1}: {failure}"
                    still = []
            for g in still:
                n_done[g] += 1
            active = still
            bar.update(1)
            if shared and active:
                ll = float(last[0][0].log_likelihood.sum())
                postfix = {"loglik": f"{ll / max(n_obs[0], 1):.4f}/obs"}
                dof = getattr(models[0].noise, "dof", None)
                if dof is not None and dof.dim() == 0:
                    postfix["dof"] = f"{float(dof):.3g}"
                bar.set_postfix(postfix)
    except KeyboardInterrupt:
        # Ctrl-C: every group keeps its last completed iteration (an interrupted M-step is undone)
        interrupted = True
        for g in range(n_groups):
            if g in snapshots and n_done[g] < len(lls[g]):
                models[g] = _restore(snapshots[g])
    finally:
        bar.close()
    if not interrupted:
        _finish(models, histories, n_done, errors, last, options, estep)
    results = []
    for g in range(n_groups):
        est = None
        if last[g] is not None:
            batch_est, j = last[g]
            est = to_records(batch_est, models[g], data) if shared else batch_est.select(slice(j, j + 1))
        history = dict(histories[g])
        for key in ("rejected.f", "rejected.g", "accelerated"):  # an interrupt or error can leave a
            if key in history or key != "accelerated":  # flag without its iterate
                history[key] = history.get(key, [])[: len(history.get("log_likelihood", []))]
        results.append(EMResult(models[g], est, history, n_done[g], done[g], errors[g], interrupted))
    return results


def _finish(models, histories, n_done, errors, last, options: EMOptions, estep) -> None:
    """Average the last iterates and/or run the final E-step at the final particle count."""
    K = options.average_last
    final = [
        g
        for g in range(len(models))
        if errors[g] is None and ((K > 1 and n_done[g] >= K) or (options.n_particles_final and n_done[g]))
    ]
    if not final:
        return
    for g in final:
        if K > 1 and n_done[g] >= K:
            models[g] = averaged(models[g], histories[g], K)
    estep(final, None)


def _progress_bar(total: int, desc: str | None):
    """A tqdm bar (a notebook widget where available); imported only when shown."""
    from tqdm import tqdm

    if desc is None:
        return tqdm(total=total, disable=True)
    from tqdm.auto import tqdm as auto_tqdm  # warns in kernels without ipywidgets: only if asked

    return auto_tqdm(total=total, desc=desc, leave=True)
