"""Recycled output arrays: an E-step writes into the arrays of a previous, discarded E-step.

Each EM iteration writes about a dozen fresh ``(T, B, L)`` arrays (particles, weights, ancestors,
smoothing statistics, latent scales).  Large CPU allocations come straight from the operating
system, so every iteration pays first-touch page faults on all of them: measured at the Table 1
size (B = 100, N = 1000, L = 100, one thread, 2026-11-24) about a third of an EM iteration's CPU
time, the same whether torch asks for transparent huge pages or not.  The EM loop hands the
previous E-step's output to the next E-step when nothing reads it any more
(:func:`torch_nssm.estimation.estep.e_step`'s ``recycle``); the allocation sites below take their
arrays from it (same shape, dtype and device) instead of allocating.

The allocation sites call :func:`empty`; outside :func:`recycling` it is ``torch.empty``.
"""

from __future__ import annotations

import contextvars
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

__all__ = ["empty", "recycling"]

_active: contextvars.ContextVar[dict | None] = contextvars.ContextVar("torch_nssm_workspace", default=None)


def _key(shape, dtype: torch.dtype, device) -> tuple:
    return tuple(int(n) for n in shape), dtype, torch.device(device)


def empty(shape, dtype: torch.dtype, device) -> Tensor:
    """An uninitialised tensor: a recycled one of the same shape, dtype and device if
    :func:`recycling` offers one, else ``torch.empty``."""
    free = _active.get()
    if free:
        stack = free.get(_key(shape, dtype, device))
        if stack:
            return stack.pop()
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
