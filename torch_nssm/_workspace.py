"""Recycled output arrays: an E-step writes into the arrays of a previous, discarded E-step.

Each EM iteration writes about a dozen fresh ``(T, B, L)`` arrays (particles, weights, ancestors,
smoothing statistics, latent scales).  Large CPU allocations come straight from the operating
system, so every iteration pays first-touch page faults on all of them: measured at the Table 1
size (B = 100, N = 1000, L = 100, one thread) about a third of an EM iteration's CPU
time, the same whether torch asks for transparent huge pages or not.  The EM loop hands the
previous E-step's output to the next E-step when nothing reads it any more
(:func:`torch_nssm.estimation.estep.e_step`'s ``recycle``); the allocation sites below take their
arrays from it (same shape, dtype and device) instead of allocating.

The allocation sites call :func:`empty`; outside :func:`recycling` it is ``torch.empty``.

The smaller per-block temporaries (a few MB per block of time steps, thousands per E-step) are
not recycled: :func:`tune_allocator` keeps glibc from handing their memory back to the operating
system between blocks instead.
"""

from __future__ import annotations

import contextvars
import ctypes
import os
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

__all__ = ["empty", "recycling", "tune_allocator"]

_active: contextvars.ContextVar[dict | None] = contextvars.ContextVar("torch_nssm_workspace", default=None)


def _key(shape, dtype: torch.dtype, device) -> tuple:
    return tuple(int(n) for n in shape), dtype, torch.device(device)


def empty(shape, dtype: torch.dtype, device) -> Tensor:
    """An uninitialised tensor: a recycled one of the same shape, dtype and device if
    :func:`recycling` offers one, else ``torch.empty``.  Always an ordinary tensor, also when
    called in inference mode (where the per-step loops run): what it makes are outputs, which
    autograd may meet later (the M-step's objectives)."""
    free = _active.get()
    if free:
        stack = free.get(_key(shape, dtype, device))
        if stack:
            return stack.pop()
    with torch.inference_mode(False):
        return torch.empty(shape, dtype=dtype, device=device)


@contextmanager
def recycling(tensors: Iterable[Tensor | None]) -> Iterator[None]:
    """Let :func:`empty` hand out ``tensors`` (whose values are then overwritten) while the context
    is active.  Only whole, contiguous tensors on the CPU are taken (a view would overwrite the
    array it belongs to; other devices have caching allocators that already reuse memory)."""
    free: dict = {}
    seen: set = set()
    for t in tensors:
        if t is None or t.device.type != "cpu" or t._base is not None or not t.is_contiguous():
            continue
        ptr = t.data_ptr()
        if ptr in seen or t.numel() == 0:
            continue
        seen.add(ptr)
        free.setdefault(_key(t.shape, t.dtype, t.device), []).append(t)
    token = _active.set(free)
    try:
        yield
    finally:
        _active.reset(token)


#: glibc's ``mallopt`` parameter numbers, and the thresholds :func:`tune_allocator` sets: the
#: largest values glibc's dynamic thresholds can reach on 64-bit systems.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD, _TRIM_THRESHOLD = 32 << 20, 64 << 20
_allocator_tuned = False


def tune_allocator() -> None:
    """Keep freed CPU memory in the process between the E-step's blocks (Linux, glibc; once per
    process).

    glibc hands the top of its heap back to the operating system whenever more than its trim
    threshold is free there; the threshold follows the largest block freed so far (a few MB in an
    E-step), so every block of time steps of the filter's and the smoothers' passes frees its
    temporaries, the heap is trimmed, and the next block faults the same memory in again, page by
    page.  Measured at the Table 1 size (B = 100, N = 1000, L = 100, MCMC smoother, one thread):
    ~220,000 page faults per backward pass, and 1.47-1.55 against 1.13-1.26 CPU s
    per EM iteration with the thresholds set.  This sets the mmap threshold to 32 MiB and the trim
    threshold to 64 MiB (where the dynamic ones end for large blocks): at most 64 MiB of freed
    memory stays with the process.  Nothing is changed when any ``MALLOC_*`` environment variable
    is set (the user's or a Dask nanny's choice; see ``_parallel._tune_allocator``) or when
    ``TORCH_NSSM_TUNE_MALLOC=0``.
    """
    global _allocator_tuned
    if _allocator_tuned:
        return
    _allocator_tuned = True
    if not sys.platform.startswith("linux") or os.environ.get("TORCH_NSSM_TUNE_MALLOC", "1") == "0":
        return
    if any(k.startswith("MALLOC_") for k in os.environ):
        return
    set_malloc_thresholds()


def set_malloc_thresholds() -> None:
    """Set glibc's mmap and trim thresholds to 32 and 64 MiB (nothing where libc is not glibc)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)
    except (OSError, AttributeError):  # not glibc
        pass
