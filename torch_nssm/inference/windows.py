"""Overlapping windows over long records: the layout of the time-parallel E-step.

A record is cut into windows that each *own* ``length`` consecutive samples and also see
``overlap`` samples before them (burn-in) and after them (look-ahead).  The windows of all records
run through the filter and smoother as one batch; each record step's results are then taken from
the window that owns it (:meth:`Windows.gather`).  The rationale and the measured approximation
are in docs/design.md ("Long records").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._ops import time_blocks
from ..core.model import SequenceBatch
from .ffbsm import TINY_WEIGHT, SmootherOutput

__all__ = ["Windows", "OwnedBatch", "cut"]


@dataclass
class OwnedBatch(SequenceBatch):
    """Windows as the M-step sees them: the outputs a window does not own are missing, and only the
    transitions from the steps it owns count (``owned`` ``(T_w, W)`` bool)."""

    owned: Tensor | None = None

    @property
    def transition_mask(self) -> Tensor:
        return self.owned[:-1] & self.step_mask[1:]


@dataclass
class Windows:
    """Windows over a batch of records, and the maps between window and record time.

    Attributes
    ----------
    data : SequenceBatch
        The windows as a batch of ``W`` sequences, time-major ``(T_w, W, ...)``.
    record : Tensor, shape (W,), long
        The record each window belongs to.
    start : Tensor, shape (W,), long
        Record time of each window's first step (its burn-in included).
    own_start, own_stop : Tensor, shape (W,), long
        Record times ``[own_start, own_stop)`` that the window owns.
    window_of, local_of : Tensor, shape (T, B), long
        The window that owns record step ``k`` of record ``b``, and that step's index in the
        window (past a record's end: its last window's last step).
    owned_data : OwnedBatch
        ``data`` restricted to what each window owns, for the M-step.
    """

    data: SequenceBatch
    record: Tensor
    start: Tensor
    own_start: Tensor
    own_stop: Tensor
    window_of: Tensor
    local_of: Tensor
    owned_data: OwnedBatch | None = None

    def __post_init__(self):
        if self.owned_data is None:
            owned = self.owned()
            y = torch.where(owned.unsqueeze(-1), self.data.y, math.nan)
            self.owned_data = OwnedBatch(self.data.u, y, self.data.lengths, owned)

    @property
    def n_windows(self) -> int:
        return self.data.n_sequences

    @property
    def first(self) -> Tensor:
        """``(W,)`` bool: the windows that start at their record's first sample (their first state
        has the model's prior)."""
        return self.start == 0

    def owned(self) -> Tensor:
        """``(T_w, W)`` bool: the window steps whose results the records keep."""
        k = torch.arange(self.data.n_steps, device=self.start.device).unsqueeze(1)
        return (k >= self.own_start - self.start) & (k < self.own_stop - self.start)

    def gather(self, values: Tensor, *, transitions: bool = False) -> Tensor:
        """Window-major ``(T_w, W, ...)`` values to record-major ``(T, B, ...)``, each step from the
        window that owns it.  ``transitions``: ``values`` are indexed by the transition
        ``k -> k+1`` (``T_w - 1`` steps), the result has ``T - 1`` steps."""
        local, window = self.local_of, self.window_of
        if transitions:
            local, window = local[:-1].clamp_max(values.shape[0] - 1), window[:-1]
        # one row copy per record step (``index_select`` on the flattened leading dimensions is a
        # contiguous copy per row; two-tensor advanced indexing is ~10x slower here)
        rows = (local * values.shape[1] + window).flatten()
        flat = values.reshape(values.shape[0] * values.shape[1], *values.shape[2:])
        return flat.index_select(0, rows).view(*local.shape, *values.shape[2:])

    def to_records(self, values: Tensor) -> Tensor:
        """Sum per-window values ``(W, ...)`` over each record's windows: ``(B, ...)``."""
        B = self.window_of.shape[1]
        out = torch.zeros(B, *values.shape[1:], dtype=values.dtype, device=values.device)
        return out.index_add_(0, self.record, values)

    def owned_scatter(self, particles: Tensor, smoother: SmootherOutput) -> Tensor:
        """The parameter-free process-noise scatter (``SmootherOutput.residual_scatter``) summed
        over the transitions each window owns only, per window ``(W, nx, nx)``.

        In the centred form of :func:`~torch_nssm.inference.ffbsm.ffbsm` (nothing of size
        ``|c|^2`` cancels): ``sum_j w_j d_j d_j^T - sum_i s_i e_i e_i^T``, ``d = x_{k+1} - c``,
        ``e = xbar_k - c``, ``c`` the smoothed mean of ``x_{k+1}``.
        """
        Tw, W, L, nx = particles.shape
        owned = self.owned_data.transition_mask  # (T_w - 1, W)
        scatter = torch.zeros(W, nx, nx, dtype=particles.dtype, device=particles.device)
        for blk in time_blocks(Tw - 1, W * L):
            nxt = slice(blk.start + 1, blk.stop + 1)
            w = smoother.weights_of(nxt)
            w = torch.where(w < TINY_WEIGHT, 0.0, w).unsqueeze(-1)  # (t, W, L, 1)
            x = particles[nxt]
            c = (w * x).sum(-2, keepdim=True) / w.sum(-2, keepdim=True).clamp_min(TINY_WEIGHT)
            d = x - c
            e = smoother.next_mean[blk] - c
            s = smoother.transition_weights[blk].unsqueeze(-1)
            block = (w * d).transpose(-1, -2) @ d - (s * e).transpose(-1, -2) @ e  # (t, W, nx, nx)
            scatter += torch.where(owned[blk].view(*owned[blk].shape, 1, 1), block, 0.0).sum(0)
        return scatter


def cut(data: SequenceBatch, length: int, overlap: int) -> Windows:
    """Cut every record of ``data`` into windows owning ``length`` samples each, with ``overlap``
    samples of burn-in before and look-ahead after (clipped at the record's ends).

    A record no longer than ``length`` is one window (the exact single pass).
    """
    if length < 1 or overlap < 1:
        raise ValueError(f"segment_length and segment_overlap must be >= 1, got {length} and {overlap}")
    T, B = data.n_steps, data.n_sequences
    device = data.y.device
    lengths = data.lengths.tolist()
    rec, start, own0, own1, size = [], [], [], [], []
    for b, n in enumerate(lengths):
        for w in range(max(1, math.ceil(n / length))):
            a, z = w * length, min((w + 1) * length, n)
            s, e = max(0, a - overlap), min(n, z + overlap)
            rec.append(b), start.append(s), own0.append(a), own1.append(z), size.append(e - s)
    as_long = lambda v: torch.tensor(v, dtype=torch.long, device=device)  # noqa: E731
    record, start_t, own_start, own_stop, sizes = map(as_long, (rec, start, own0, own1, size))
    Tw = max(size)
    k = torch.arange(Tw, device=device).unsqueeze(1)  # (T_w, 1)
    inside = k < sizes
    t_rec = (start_t + k).clamp_max(T - 1)  # (T_w, W) record time of each window step
    u = torch.where(inside.unsqueeze(-1), data.u[t_rec, record], 0.0)
    y = torch.where(inside.unsqueeze(-1), data.y[t_rec, record], math.nan)
    window_of = torch.empty(T, B, dtype=torch.long, device=device)
    local_of = torch.empty(T, B, dtype=torch.long, device=device)
    last = {}
    for j, (b, s, a, z) in enumerate(zip(rec, start, own0, own1)):
        window_of[a:z, b] = j
        local_of[a:z, b] = torch.arange(a - s, z - s, device=device)
        last[b] = j
    for b, n in enumerate(lengths):  # the padding past a record's end: its last window's last step
        window_of[n:, b] = last[b]
        local_of[n:, b] = size[last[b]] - 1
    windows = SequenceBatch(u=u, y=y, lengths=sizes)
    return Windows(windows, record, start_t, own_start, own_stop, window_of, local_of)
