"""Studies: one fit per data set, the E-steps of many data sets in one batched pass.

:func:`fit_independent` checks the data sets, cuts them into chunks (one per worker), fits each
chunk as one batched EM pass (:func:`~torch_nssm.estimation.loop.run_em` with ``shared=False``)
through the driver of runs (:func:`~torch_nssm.estimation.runs.drive`), and raises the study's
warnings from its report (:func:`torch_nssm.diagnostics.fit_warnings.warn_study`).
"""

from __future__ import annotations

import numpy as np
import torch
from sklearn.base import clone
from sklearn.utils import check_random_state

from . import _parallel
from . import _validation as V
from ._parameters import check_parameters, em_options, report_settings
from ._threads import limited_threads
from .core.model import SequenceBatch
from .diagnostics.fit_warnings import warn_start, warn_study
from .estimation.loop import run_em
from .estimation.runs import FitReport, RunOutcome, drive
from .estimation.start import StartSettings, plan_start
from .inference.random import SequenceStreams, sequence_seed

__all__ = ["fit_independent"]


def fit_independent(
    estimator, u, y, *, show_progress: bool | None = None, n_jobs: int | None = None
) -> list:
    """Fit one copy of ``estimator`` to each data set, the E-steps of a chunk of data sets in one
    batched pass.

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        The settings (``f``, ``g``, initial values, ``n_iter``, ``tol``, particles, ...) used for
        every data set; it is cloned, not changed.
    u : list of array-like (N_b,) or (N_b, nu), or None
        Inputs of each data set (``None`` for systems without input).
    y : list of array-like (N_b,) or (N_b, p)
        Outputs of each data set (NaN: missing).
    show_progress : bool, optional
        Progress bar over iterations (serial runs only); defaults to ``estimator.verbose > 0``.
    n_jobs : int, optional
        Workers (joblib): the data sets are split into as many chunks, each fitted as one batched
        pass on a worker; defaults to ``estimator.n_jobs`` (``None``: 1 unless a
        ``joblib.parallel_config`` context says otherwise; ``-1``: all cores).

    Returns
    -------
    list of RobustNSSMEstimator
        Fitted estimators, one per data set, each with its own parameters, ``history_``,
        ``n_iter_`` and ``converged_`` (a data set leaves the batch once it has converged).

    Raises
    ------
    WorkerLostError
        If a worker died (a crash, a memory limit): its ``results`` hold the fits that finished
        (``None`` for the lost data sets).

    Notes
    -----
    Each data set draws its random numbers from its own stream, seeded from ``(random_state,
    index of the data set)`` (:class:`~torch_nssm.inference.random.SequenceStreams`): its fit is
    the same whatever data sets it is batched with and whatever the number of workers or chunks.
    """
    device = check_parameters(estimator)
    _check_study_settings(estimator)
    datas, y_1d = _data_sets(estimator, u, y, device)
    n_sets = len(datas)
    entropy = _entropy(estimator.random_state)
    n_jobs = estimator.n_jobs if n_jobs is None else n_jobs
    n_chunks = min(n_sets, _parallel.effective_n_jobs(n_jobs))
    chunks = [c.tolist() for c in np.array_split(np.arange(n_sets), n_chunks) if c.size]
    verbose = estimator.verbose > 0 if show_progress is None else show_progress
    tasks = [(estimator, [datas[b] for b in c], c, [y_1d[b] for b in c], entropy, device) for c in chunks]
    try:
        parts = drive(
            _fit_chunk, tasks, n_jobs, f"fit_independent on {n_sets} data sets", progress=verbose,
            stop=lambda part: False,  # one chunk when serial
        )
    except _parallel.WorkerLostError as exc:
        raise _lost_data_sets(exc, chunks, n_sets) from exc
    fits = [fit for part in parts for fit, _ in part]
    outcomes = [outcome for part in parts for _, outcome in part]
    warn_study(FitReport(outcomes, report_settings(estimator), study=True), stacklevel=2)
    return fits


def _check_study_settings(estimator) -> None:
    if estimator.segment_length not in (None, "auto"):
        raise ValueError(
            "segment_length applies to fit (one model for all records); fit_independent runs each data "
            "set whole: set segment_length=None or 'auto'"
        )
    if estimator.acceleration == "newton":
        raise ValueError(
            "acceleration='newton' applies to fit (one model); fit_independent runs plain EM: set "
            "acceleration=None (or 'squarem', which applies to single fits too and is ignored here)"
        )


def _data_sets(estimator, u, y, device: torch.device) -> tuple[list[SequenceBatch], list[bool]]:
    """Each data set as a batch of one record, and whether its ``y`` was 1-D."""
    if not V.is_sequence_list(y):
        raise ValueError("y must be a list of data sets (one array per data set)")
    n_sets = len(y)
    us = [None] * n_sets if u is None else list(u)
    if len(us) != n_sets:
        raise ValueError(f"u and y must hold the same number of data sets, got {len(us)} and {n_sets}")
    datas = []
    for b in range(n_sets):
        ub, yb, _ = V.as_sequence_list(us[b], y[b], dtype=estimator.dtype, device=device)
        datas.append(SequenceBatch.from_sequences(ub, yb))
    return datas, [np.ndim(y[b]) == 1 for b in range(n_sets)]


def _lost_data_sets(exc: _parallel.WorkerLostError, chunks: list[list[int]], n_sets: int):
    """The error of a worker lost in a study: the finished fits by data set, the lost ones named."""
    fits: list = [None] * n_sets
    for c, part in zip(chunks, exc.results):
        for b, (fit, _) in zip(c, part or []):
            fits[b] = fit
    lost = [b for i in exc.lost for b in chunks[i]]
    return _parallel.WorkerLostError(
        f"{exc} (data sets {_ranges(lost)} are lost; the {n_sets - len(lost)} finished fits are in "
        "this error's `results`, None for the lost ones; each data set's fit depends on its "
        "random_state and its index only, so a rerun of the whole study gives the same fits)",
        fits,
        lost,
    )


def _fit_chunk(
    estimator,
    datas: list[SequenceBatch],
    indices: list[int],
    y_1d: list[bool],
    entropy: int,
    device: torch.device,
    *,
    progress: bool,
) -> list[tuple]:
    """Fit the data sets ``indices`` (``datas``) as one batched EM pass (on a worker or here).

    Returns, per data set, ``(fitted estimator, RunOutcome)``: the caller raises the warnings and
    errors of the whole study.
    """
    with limited_threads(estimator.n_threads):
        estimators = [_copy_for(estimator, b) for b in indices]
        models = [_start(est_b, data_b, device) for est_b, data_b in zip(estimators, datas)]
        all_data = SequenceBatch.from_sequences([d.u[:, 0] for d in datas], [d.y[:, 0] for d in datas])
        n = len(indices)
        options = em_options(estimator, f"robust EM x{n}")
        options.estep.segment_length = None  # whole data sets, batched ("auto" included)
        options.progress = f"robust EM x{n}" if progress else None
        streams = SequenceStreams([sequence_seed(entropy, b) for b in indices], device)
        options.mstep.solver.generator = streams  # each data set's minibatch orders from its stream
        results = run_em(models, all_data, options, streams, shared=False)
    outcomes = []
    for j, (est_b, run) in enumerate(zip(estimators, results)):
        est_b.segment_length_ = None
        if run.estep is not None:
            # the stored E-step is padded like the batch (lengths kept)
            est_b._store(
                run.model, run.history, run.estep, all_data.select(slice(j, j + 1)), False, run.n_done,
                run.converged, y_1d=y_1d[j],
            )
        outcomes.append((est_b, RunOutcome.of(run)))
    return outcomes


def _copy_for(estimator, b: int):
    """The unfitted copy of ``estimator`` for data set ``b`` (an int ``random_state`` plus ``b``)."""
    est_b = clone(estimator)
    if isinstance(estimator.random_state, (int, np.integer)):
        est_b.random_state = int(estimator.random_state) + b
    return est_b


def _start(est_b, data_b: SequenceBatch, device: torch.device):
    """Data set ``b``'s start: its initial model, after the first stage when that runs (per data
    set, before the batched EM; ``first_stage_`` reports it)."""
    model = est_b._initial_model(data_b, device)
    settings = StartSettings(est_b.first_stage, est_b.n_iter, 1, est_b.init_jitter, est_b.random_state)
    start = plan_start(model, data_b, settings, restarts=False)
    if start.first_stage is not None:
        est_b.first_stage_ = start.first_stage
    warn_start(start, stacklevel=4)
    return start.model


def _ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5]`` as ``"0-2, 5"``."""
    parts, start = [], None
    for i, b in enumerate(indices):
        if start is None:
            start = b
        if i + 1 == len(indices) or indices[i + 1] != b + 1:
            parts.append(str(start) if start == b else f"{start}-{b}")
            start = None
    return ", ".join(parts)


def _entropy(random_state) -> int:
    """One integer that seeds a whole study (drawn once, in the caller's process)."""
    if random_state is None:
        return int(np.random.SeedSequence().entropy % (2**63))
    if isinstance(random_state, (int, np.integer)):
        return int(random_state)
    return int(check_random_state(random_state).randint(0, 2**31 - 1))
