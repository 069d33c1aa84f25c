"""Running independent tasks (restarts, chunks of data sets) through joblib.

joblib picks the backend: its default process pool (loky) for ``n_jobs > 1``, or whatever the
caller chose with ``joblib.parallel_config`` (``backend="dask"`` runs on a ``dask.distributed``
cluster, with no change to the library).  The library builds no scheduler of its own: this
module only runs the tasks, forwards the warnings the workers raised, and turns a worker lost in
the middle (a crash, an out-of-memory kill) into :class:`WorkerLostError`, which keeps the results
that had come back (docs/design.md, "Many fits on many machines").
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Sequence
from typing import Any, Callable

__all__ = ["WorkerLostError", "effective_n_jobs", "run_tasks", "collect_warnings"]


class WorkerLostError(RuntimeError):
    """A worker process died (or was killed) before it returned its task's result.

    Attributes
    ----------
    results : list
        The result of every task, ``None`` for those that did not come back.
    lost : list of int
        The tasks whose results were lost.
    """

    def __init__(self, message: str, results: list, lost: list[int]):
        super().__init__(message)
        self.results = results
        self.lost = lost


#: Exceptions (by class name) that mean "the worker died", not "the task raised": loky's and
#: dask.distributed's (a task whose workers died ``allowed-failures`` times).
_WORKER_DEATHS = ("TerminatedWorkerError", "KilledWorker", "BrokenProcessPool", "CommClosedError")


def effective_n_jobs(n_jobs: int | None) -> int:
    """The number of workers ``n_jobs`` means under the active joblib configuration (``None``: 1
    unless a ``joblib.parallel_config`` says otherwise; ``-1``: all)."""
    import joblib

    return max(1, int(joblib.effective_n_jobs(n_jobs)))


def collect_warnings(fn: Callable, *args) -> tuple[Any, list]:
    """``fn(*args)`` and the warnings it raised, as ``(message, category)`` pairs (a worker's
    warnings do not reach the caller's process: they travel back with the result)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = fn(*args)
    return result, [(str(w.message), w.category) for w in caught]


def _indexed(i: int, fn: Callable, args: tuple):
    return i, collect_warnings(fn, *args)


def run_tasks(fn: Callable, tasks: Sequence[tuple], n_jobs: int | None, what: str) -> list:
    """``[fn(*task) for task in tasks]`` through joblib, in parallel; the workers' warnings are
    raised again here.

    Raises
    ------
    WorkerLostError
        If a worker died: it holds the results that came back (the others are ``None``).  Errors
        raised by ``fn`` itself propagate unchanged.
    """
    import joblib

    results: list = [None] * len(tasks)
    done = [False] * len(tasks)
    caught: list = []
    client = _dask_client()
    try:
        if client is not None:
            outcomes = _run_on_dask(client, tasks, fn)
        else:
            parallel = joblib.Parallel(n_jobs=n_jobs, return_as="generator_unordered")
            outcomes = parallel(joblib.delayed(_indexed)(i, fn, task) for i, task in enumerate(tasks))
        for i, (result, task_warnings) in outcomes:
            results[i], done[i] = result, True
            caught.extend(task_warnings)
    except Exception as exc:
        if type(exc).__name__ not in _WORKER_DEATHS:
            raise
        lost = [i for i, ok in enumerate(done) if not ok]
        raise WorkerLostError(
            f"a worker died while running {what} ({type(exc).__name__}: {exc}); {len(tasks) - len(lost)} "
            f"of {len(tasks)} tasks had finished and are kept in this error's `results`. A worker dies "
            "when its process crashes or runs out of memory: check the workers' logs, give them more "
            "memory, or run the lost part again",
            results,
            lost,
        ) from exc
    for message, category in caught:
        warnings.warn(message, category, stacklevel=3)
    return results


def _dask_client():
    """The ``dask.distributed`` client of the active joblib backend (``parallel_config(backend="dask")``),
    else ``None``."""
    from joblib.parallel import get_active_backend

    backend = get_active_backend()[0]
    return getattr(backend, "client", None) if type(backend).__name__ == "DaskDistributedBackend" else None


def _run_on_dask(client, tasks: Sequence[tuple], fn: Callable):
    """The tasks as futures of the joblib backend's own client, yielded as they finish.

    joblib's dask backend waits forever when a worker dies (the scheduler's ``KilledWorker`` never
    reaches joblib's callbacks; joblib 1.6): submitting to its client directly delivers the error,
    and lets every other task finish before :class:`WorkerLostError` is raised.
    """
    from distributed import as_completed

    futures = [client.submit(_indexed_on_dask, i, fn, task, pure=False) for i, task in enumerate(tasks)]
    death = None
    try:
        for future in as_completed(futures):
            try:
                yield future.result()
            except Exception as exc:
                if type(exc).__name__ not in _WORKER_DEATHS:
                    raise
                death = death or exc
    finally:
        for future in futures:
            future.cancel()
    if death is not None:
        raise death


_allocator_tuned = False


def _tune_allocator() -> None:
    """Undo, in a Dask worker, the nanny's ``MALLOC_TRIM_THRESHOLD_=65536``.

    Setting any glibc malloc threshold disables its dynamic mmap threshold, which stays at 128 KiB:
    every tensor above that (the filter's and smoother's per-step and per-block arrays) is then a
    fresh ``mmap`` whose pages fault in on first touch.  Measured: a 50-record Table 1 E-step took
    1.30 s instead of 0.72 s.  The thresholds are set where the dynamic ones end up; done once per
    worker process, only where the variable is set (Linux, glibc).
    """
    global _allocator_tuned
    if _allocator_tuned or "MALLOC_TRIM_THRESHOLD_" not in os.environ or not sys.platform.startswith("linux"):
        return
    _allocator_tuned = True
    from ._workspace import set_malloc_thresholds

    set_malloc_thresholds()


def _indexed_on_dask(i: int, fn: Callable, args: tuple):
    _tune_allocator()
    return _indexed(i, fn, args)
