"""The library's thread policy: a fixed number of CPU threads while its methods run.

The engine runs many small per-step kernels (the particle filter's loop over time).  On a busy
2-core machine torch's default pool made a fit ~20x slower than one thread (docs/design.md,
benchmarks/threads.py), so the estimator applies ``n_threads`` (default 1) to torch's intra-op
pool and, through threadpoolctl, to the BLAS/OpenMP pools, only while its call runs, and restores
the caller's settings afterwards.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Callable, TypeVar

import torch

__all__ = ["limited_threads", "with_thread_limit"]

F = TypeVar("F", bound=Callable)


@contextlib.contextmanager
def limited_threads(n_threads: int | None):
    """Run the block with ``n_threads`` CPU threads (``None``: leave the settings alone)."""
    if n_threads is None:
        yield
        return
    if isinstance(n_threads, bool) or not isinstance(n_threads, int) or n_threads < 1:
        raise ValueError(f"n_threads must be a positive integer or None, got {n_threads!r}")
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(int(n_threads))
    try:
        with threadpool_limits(limits=int(n_threads)):
            yield
    finally:
        torch.set_num_threads(before)


def with_thread_limit(method: F) -> F:
    """Decorate an estimator method to run under its ``n_threads`` setting."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        with limited_threads(getattr(self, "n_threads", None)):
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]
