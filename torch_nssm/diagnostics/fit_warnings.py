"""Every warning of a fit or a study, written from the report of its EM runs.

The estimation code records what happened (:class:`~torch_nssm.estimation.start.Start`,
:class:`~torch_nssm.estimation.runs.FitReport`); this module says it in words, in one place and one
order: the start (:func:`start_messages`: a first stage that did not help, a start whose
simulation diverges), then a fit's runs and result (:func:`fit_messages`: unstable restarts,
discarded runs, the simulation check, rejected M-steps, a noise model that absorbs the data, a
model that explains nothing, interruption or no convergence), or a study's
(:func:`warn_study`).  ``*_messages`` return ``(message, category)`` pairs; ``warn_*`` raise them.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator

from sklearn.exceptions import ConvergenceWarning

from ..estimation.start import JITTER_DRAWS, SimulationCheck, Start
from ..inference.filtering import NumericalError

__all__ = [
    "EXPLAINED_FLOOR",
    "error_message",
    "fit_messages",
    "rejection_message",
    "start_messages",
    "warn_fit",
    "warn_start",
    "warn_study",
]

#: Below this robust R² of the smoothed outputs against ``y``, a fit is reported as explaining nothing.
EXPLAINED_FLOOR = 0.05

Messages = Iterator[tuple[str, type[Warning]]]


def _emit(messages: Iterable[tuple[str, type[Warning]]], stacklevel: int) -> None:
    """Raise ``messages``; ``stacklevel`` counts from the caller of the ``warn_*`` function."""
    for message, category in messages:
        warnings.warn(message, category, stacklevel=stacklevel + 2)


# --------------------------------------------------------------------------- the start
def start_messages(start: Start) -> Messages:
    """A first stage (``first_stage="simulation"``) that did not improve the start; a start whose
    noise-free simulation diverges."""
    if start.first_stage_unimproved:
        yield (
            "the first stage (robust simulation-error fit) did not improve the start; EM starts "
            "from the given values",
            RuntimeWarning,
        )
    if start.divergent_step is not None:
        yield (
            f"the noise-free simulation of f from x0_mean diverges at step {start.divergent_step} with "
            "the initial parameters (the state leaves every finite bound): start from values for "
            "which f is stable, or EM may fail with non-finite updates",
            RuntimeWarning,
        )


def warn_start(start: Start, stacklevel: int = 1) -> None:
    """Raise :func:`start_messages` (``stacklevel`` as for ``warnings.warn`` in the caller)."""
    _emit(start_messages(start), stacklevel)


# --------------------------------------------------------------------------- a fit
def fit_messages(report) -> Messages:
    """The warnings of a fit's :class:`~torch_nssm.estimation.runs.FitReport`, in order; the parts
    of a report that a failed fit did not reach (no kept run, no simulation check) say nothing."""
    for outcome in report.outcomes:
        if not outcome.stable_start:
            yield (
                f"no jittered restart (init_jitter={report.start.init_jitter}) gave a stable simulation of "
                f"f in {JITTER_DRAWS} draws; lower init_jitter",
                RuntimeWarning,
            )
    if report.kept is None:
        return
    failed = report.failed
    if report.fallback is not None:
        yield (
            f"EM failed on a numerical error in every run ({report.fallback}); the estimator keeps the "
            "start: the first stage's f and g (robust simulation-error fit) with the starting noise "
            "parameters (Rw_, Rv_ and the noise family's, not estimated), evaluated by one E-step. Its "
            "simulations and predictions are the first stage's; to estimate the noise, refit with "
            "other Rw_init / Rv_init, more particles, or first_stage=None",
            RuntimeWarning,
        )
    elif failed:
        yield (
            f"{len(failed)} of {len(report.outcomes)} EM runs stopped on a numerical error and "
            f"were discarded (first: {failed[0].error})",
            RuntimeWarning,
        )
    if report.simulation is not None:
        yield from simulation_messages(report.simulation)
    message = rejection_message(report.kept.rejections, **_advice_settings(report.settings))
    if message:
        yield message, RuntimeWarning
    if report.absorption:
        yield report.absorption, RuntimeWarning
    yield from explained_messages(report.explained, report.simulated)
    if report.fallback is None:  # no EM iteration of the kept model to say how it ended
        yield from ending_messages(report.kept, report.settings, report.start)


def warn_fit(report, stacklevel: int = 1) -> None:
    """Raise :func:`fit_messages` (``stacklevel`` as for ``warnings.warn`` in the caller)."""
    _emit(fit_messages(report), stacklevel)


def simulation_messages(check: SimulationCheck) -> Messages:
    """EM moved a simulation model's ``f`` and ``g`` (``focus="prediction"``) so that it simulates
    much worse than its first stage."""
    if check.outcome == "worse":
        yield (
            f"EM moved f and g so that the model simulates the training record worse than its first stage "
            f"did (robust scale of the free-run errors {check.after:.4g} against {check.before:.4g}): the "
            "states follow y through the process noise. That suits a model for filtering and prediction "
            "(focus='prediction'); focus='simulation' keeps the first stage's f and g",
            RuntimeWarning,
        )


def _advice_settings(settings: dict) -> dict:
    return {"optimizer": settings["optimizer"], "learning_rate": settings["learning_rate"]}


def rejection_message(rejections: list, optimizer: str, learning_rate: float) -> str | None:
    """Words for the M-step updates that were undone (``rejections``: :class:`~torch_nssm.estimation.
    runs.Rejection` s; ``None`` if there were none)."""
    parts = []
    for r in rejections:
        shown = ", ".join(r.names[:6]) + (", ..." if len(r.names) > 6 else "")
        parts.append(f"{r.label} ({r.kind}: {shown}) at {r.n} of {r.of} iterations")
    if not parts:
        return None
    if optimizer == "adam":
        advice = (
            f"lower learning_rate (now {learning_rate}), raise max_iter_mstep, or try "
            "optimizer='lbfgs'"
        )
    else:
        advice = (
            "the weighted loss got worse or non-finite at every step tried: check that the module "
            "returns finite values near the current parameters, or start from other values"
        )
    return (
        "the M-step update was rejected (the step was undone and the parameters did not move) "
        f"for {'; '.join(parts)}; history_['rejected.f'] / ['rejected.g'] mark the iterations. "
        f"To fix: {advice}."
    )


def explained_messages(explained: float, simulated: float) -> Messages:
    """A fit whose simulation, or whose smoothed outputs, explain none of ``y`` (robust R²)."""
    if explained >= EXPLAINED_FLOOR and simulated < 0.0:
        yield (
            f"the model's noise-free simulation explains none of y (robust R² of the free run "
            f"{simulated:.2f}, of the smoothed outputs {explained:.2f}): the states follow y through "
            "the process noise, not through f; f and g may sit in a wrong basin (check the scale of "
            "g's output against y's, try other initial values or n_init > 1), or the model is a "
            "tracking model rather than a simulation model (focus='prediction' or fit_Rw=True let "
            "the process noise grow; focus='simulation' with the first stage holds it)",
            RuntimeWarning,
        )
    if explained < EXPLAINED_FLOOR:
        yield (
            f"the model explains almost none of the variance of y (robust R² of the smoothed outputs "
            f"{explained:.3f}): the fit may sit where the modelled output g(x, u) is nearly constant "
            "and the noise explains the data; check the scale of the modelled output against y's "
            "(the states f produces and, where g has free parameters, g's), try other initial "
            "values, or n_init > 1",
            RuntimeWarning,
        )


def ending_messages(kept, settings: dict, start: Start | None = None) -> Messages:
    """How EM ended: interrupted by Ctrl-C (in the first stage or in EM), or not converged in
    ``n_iter`` iterations."""
    n_iter, tol = settings["n_iter"], settings["tol"]
    if start is not None and start.interrupted:
        report = start.first_stage
        where = f"windows of {report.horizon} samples" if report.accepted else "none: the given values"
        yield (
            "fit interrupted (KeyboardInterrupt) during the first stage: no EM iteration ran; the fitted "
            f"attributes hold its best stage completed ({where}) with the starting noise parameters",
            RuntimeWarning,
        )
    elif kept.halted:
        yield f"EM stopped early: {kept.halted}", RuntimeWarning
    elif kept.interrupted:
        yield (
            f"fit interrupted (KeyboardInterrupt) after {kept.n_done} EM iterations: the fitted "
            "attributes hold the last completed iteration",
            RuntimeWarning,
        )
    elif not kept.converged and tol > 0 and n_iter > 0:
        yield (
            f"EM did not converge in n_iter={n_iter} iterations (tol={tol}); "
            "raise n_iter or tol, or average the last iterates",
            ConvergenceWarning,
        )


def error_message(outcome) -> str:
    """The :class:`~torch_nssm.NumericalError` of a fit none of whose runs finished."""
    if not outcome.fitted or outcome.n_done == 0 and outcome.error and "could not start" in outcome.error:
        return outcome.error
    return (
        f"{outcome.error}. The fitted attributes hold the last good parameters (after iteration "
        f"{outcome.n_done})."
    )


# --------------------------------------------------------------------------- a study
def warn_study(report, stacklevel: int = 1) -> None:
    """Raise the warnings of a study (:func:`torch_nssm.fit_independent`): each data set's error,
    then the rejected M-steps and how EM ended over all data sets.

    Raises
    ------
    NumericalError
        For the first data set with nothing fitted (its EM could not start).
    """
    for b, outcome in enumerate(report.outcomes):
        if outcome.error is not None:
            _emit([(f"data set {b}: {outcome.error}", UserWarning)], stacklevel)
        if not outcome.fitted:
            raise NumericalError(f"data set {b}: {outcome.error}")
    _emit(study_messages(report), stacklevel)


def study_messages(report) -> Messages:
    """A study's rejected M-steps (how many fits, the first one's words) and how EM ended."""
    settings, n_sets = report.settings, len(report.outcomes)
    rejected = [o for o in report.outcomes if o.rejections]
    if rejected:
        first = rejection_message(rejected[0].rejections, **_advice_settings(settings))
        yield f"{len(rejected)} of {n_sets} fits had rejected M-steps; the first: {first}", RuntimeWarning
    n_unconverged = sum(not o.converged for o in report.outcomes)
    if report.interrupted:
        yield (
            "fit_independent interrupted (KeyboardInterrupt): each fit holds its last completed iteration",
            RuntimeWarning,
        )
    elif n_unconverged and settings["tol"] > 0 and settings["n_iter"] > 0:
        yield (
            f"{n_unconverged} of {n_sets} fits did not converge in n_iter={settings['n_iter']} iterations",
            ConvergenceWarning,
        )
