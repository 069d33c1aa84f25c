"""Resampling schemes for particle filters, batched over independent rows.

Every scheme takes normalised *log*-weights of shape ``(B, L)`` (one row per sequence) and returns
ancestor indices of shape ``(B, M)`` such that the expected number of copies of particle ``i`` is
``M * W_i`` (unbiasedness).  Systematic, stratified and residual resampling have lower variance than
multinomial (Douc, Cappé & Moulines 2005); systematic is the default.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from . import random as _random

__all__ = [
    "RESAMPLING_SCHEMES",
    "effective_sample_size",
    "cumulative_weights",
    "inverse_cdf",
    "multinomial",
    "systematic",
    "systematic_from_cumsum",
    "systematic_grid",
    "SystematicResampler",
    "stratified",
    "residual",
    "get_resampler",
]


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """ESS ``1 / sum_i W_i^2`` of normalised log-weights along the last dimension."""
    return torch.exp(-torch.logsumexp(2.0 * log_weights, dim=-1))


def cumulative_weights(log_weights: Tensor) -> Tensor:
    """Cumulative weights along the last dimension (any leading shape), ending at exactly 1."""
    cdf = torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1)
    return cdf / cdf[..., -1:]


#: Below this many draws per call the guide table's dozen operations cost more than they save.
_GUIDE_MIN_DRAWS = 4096


def inverse_cdf(cdf: Tensor, u: Tensor) -> Tensor:
    """Inverse-CDF indices ``#{i < L-1: cdf_i <= u}`` for uniforms ``u`` ``(R, n)`` and rows of a
    cumulative-weight table ``cdf`` ``(R, L)`` (ending at 1): ``n`` i.i.d. draws per row.

    Equal to ``searchsorted(cdf, u, right=True)`` and ~3x cheaper on a CPU (its binary search
    costs 70-100 ns a draw at L = 1000-3000).  A guide table (Chen & Asau 1974) gives, for the
    bucket ``floor(L u)`` of each uniform, the first index that can hold it and the bucket's end;
    four vectorised steps forward finish almost every draw, and the few left (buckets crowded
    with tiny weights) are finished by a binary search between those two bounds.  Calls with
    fewer than :data:`_GUIDE_MIN_DRAWS` draws (a rejection sampler's tries, one resampling) use
    ``searchsorted``.
    """
    R, L = cdf.shape
    if u.numel() < _GUIDE_MIN_DRAWS:
        return torch.searchsorted(cdf, u.contiguous(), right=True).clamp_(max=L - 1)
    key = (cdf[:, :-1] * L).long().clamp_(max=L - 1)  # bucket of each boundary
    lo = torch.zeros(R, L + 1, dtype=torch.long, device=cdf.device)
    lo = lo.scatter_add_(1, key + 1, torch.ones_like(key)).cumsum_(1)  # boundaries before bucket b
    bucket = (u * L).long().clamp_(max=L - 1)  # u * L rounds to L for u within 2^-53 of 1
    idx = (lo.gather(1, bucket) - 1).clamp_(min=0)  # one back: robust to rounding
    for _ in range(4):
        idx += cdf.gather(1, idx) <= u
    r, c = torch.nonzero(cdf.gather(1, idx) <= u, as_tuple=True)
    if r.numel():  # binary search in [idx, end of the bucket]: cdf[first] <= u < cdf[last]
        first = idx[r, c]
        last = (lo[r, bucket[r, c] + 1] + 1).clamp_(max=L - 1)
        flat, base, v = cdf.reshape(-1), r * L, u[r, c]
        for _ in range(int(last.sub(first).max()).bit_length()):
            mid = (first + last) // 2
            below = flat[base + mid] <= v
            first = torch.where(below, mid + 1, first)
            last = torch.where(below, last, mid)
        idx[r, c] = first
    return idx


def multinomial(
    log_weights: Tensor, n: int | None = None, generator: _random.Randomness = None
) -> Tensor:
    """Multinomial resampling: ``n`` i.i.d. draws from the weights of each row."""
    n = log_weights.shape[-1] if n is None else n
    w = torch.softmax(log_weights, dim=-1)
    return _random.multinomial(w, n, generator)


def systematic(log_weights: Tensor, n: int | None = None, generator: _random.Randomness = None) -> Tensor:
    """Systematic resampling: one uniform ``u`` per row, positions ``(j + 1 - u) / n``."""
    B, L = log_weights.shape
    u = _random.uniform(generator, (B, 1), log_weights.dtype, log_weights.device)
    return systematic_from_cumsum(torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1), u, n)


#: :class:`SystematicResampler` binary-searches the positions while ``rows * n * log2(L)``
#: is below this and scatters otherwise.  Measured on one CPU thread with fresh weights at every
#: call (the search's branches are then unpredictable; repeating one input flatters it 3-4x): the
#: search is faster for one row of up to ~300 particles (10 vs 18 us), 2x slower for 1000.
SEARCH_WORK = 4000


def systematic_grid(B: int, n: int, dtype: torch.dtype, device: torch.device | str | None = None) -> Tensor:
    """The integers ``1, ..., n`` that :class:`SystematicResampler` searches for, shape ``(B, n)``."""
    return torch.arange(1, n + 1, dtype=dtype, device=device).expand(B, n).contiguous()


def systematic_from_cumsum(
    cumw: Tensor, u: Tensor, n: int | None = None, *, out: Tensor | None = None
) -> Tensor:
    """Systematic resampling from cumulative sums of (unnormalised, non-negative) weights.

    Position ``j = 0, ..., n - 1`` is ``p_j = (j + 1 - u) / n`` (the offset ``1 - u`` is uniform
    on ``(0, 1]``, which saves computing ``1 - u``) and goes to the particle ``i`` with ``cdf_{i-1}
    <= p_j < cdf_i``, ``cdf = cumw / cumw[:, -1]``; the indices come sorted.  One call of a
    :class:`SystematicResampler` (which the particle filter keeps for all its steps).

    Parameters
    ----------
    cumw : Tensor, shape (B, L)
        ``cumsum(W, -1)`` of weights ``W >= 0`` of any (positive) total.
    u : Tensor, shape (B, 1)
        One uniform draw in ``[0, 1)`` per row.
    n : int, optional
        Number of draws (default ``L``).
    out : Tensor, shape (B, n), long, optional
        Where to write the indices.

    Returns
    -------
    Tensor, shape (B, n), long
        Ancestor indices in ``[0, L)``.
    """
    B, L = cumw.shape
    resampler = SystematicResampler(B, L, cumw.dtype, cumw.device, n=n)
    resampler.cumw.copy_(cumw)
    return resampler.from_cumsum(u, out)


class SystematicResampler:
    """Systematic resampling of ``B`` rows of ``L`` weights into ``n`` draws (default ``L``),
    called many times (the particle filter's every step) with its work arrays and their views made
    once: about six operations fewer per call than making them each time (three slices, three
    allocations; measured at one sequence, where each costs ~0.5-1 us of dispatch).

    A call takes the weights themselves (it writes their cumulative sums into its own array
    ``cumw``; :meth:`from_cumsum` starts from sums already there) and returns the indices in
    ``out`` or, without it, in an array of the resampler's own that the next call overwrites.

    Parameters
    ----------
    B, L : int
        Rows and weights per row.
    dtype : torch.dtype
        Dtype of the weights.
    device : torch.device or str, optional
    n : int, optional
        Draws per row (default ``L``).
    """

    def __init__(
        self,
        B: int,
        L: int,
        dtype: torch.dtype,
        device: torch.device | str | None = None,
        n: int | None = None,
    ):
        n = L if n is None else n
        self.L, self.n = L, n
        self.cumw = torch.empty(B, L, dtype=dtype, device=device)
        self._total = self.cumw[:, -1:]
        self.search = B * n * math.log2(max(L, 2)) < SEARCH_WORK
        self._own = torch.empty(B, n, dtype=torch.long, device=device)
        if self.search:
            self._grid = systematic_grid(B, n, dtype, device)
        else:
            self._head = self.cumw[:, :-1]
            self._ones = torch.ones(B, L - 1, dtype=torch.long, device=device)
            self._below = torch.empty(B, L - 1, dtype=torch.long, device=device)
            self._marks = torch.empty(B, n + 1, dtype=torch.long, device=device)
            self._counted = self._marks[:, :n]

    def __call__(self, weights: Tensor, u: Tensor, out: Tensor | None = None) -> Tensor:
        """Ancestor indices ``(B, n)`` for non-negative ``weights`` ``(B, L)`` and one uniform per row
        ``u`` ``(B, 1)`` (into ``out`` if given).  The reciprocals of the rows' totals, which a call
        computes anyway, are left in :attr:`inv_total` (the particle filter's likelihood terms take
        them instead of summing the weights again)."""
        torch.cumsum(weights, dim=-1, out=self.cumw)
        return self.from_cumsum(u, out)

    def from_cumsum(self, u: Tensor, out: Tensor | None = None) -> Tensor:
        """Ancestor indices ``(B, n)`` from the cumulative sums in ``cumw`` (see
        :func:`systematic_from_cumsum`)."""
        L, n, out = self.L, self.n, self._own if out is None else out
        self.inv_total = inv_total = torch.reciprocal(self._total)  # (B, 1), a new tensor each call
        if self.search:
            # index of position j = #{i: cdf_i <= p_j} = #{i: n cdf_i + u <= j + 1}; positions past
            # the end (rounding) go to L - 1
            positions = torch.addcmul(u, self.cumw, inv_total, value=n)
            idx = torch.searchsorted(positions, self._grid, right=True, out=out)
            return idx.clamp_(max=L - 1)
        # particle i gets below_i - below_{i-1} positions, below_i = #{j: p_j < cdf_i} = floor(n
        # cdf_i + u) (the conversion truncates, and n cdf + u >= 0): mark each below_i (i < L - 1)
        # and count the marks up to j (one scatter and one cumulative sum).  The clamp also maps NaN
        # weights (undefined integer conversion) to a valid index.
        below = self._below.copy_(torch.addcmul(u, self._head, inv_total, value=n)).clamp_(0, n)  # as .long()
        self._marks.zero_()
        self._marks.scatter_add_(1, below, self._ones)
        return torch.cumsum(self._counted, dim=1, out=out)


def stratified(log_weights: Tensor, n: int | None = None, generator: _random.Randomness = None) -> Tensor:
    """Stratified resampling: one uniform per stratum ``[j/n, (j+1)/n)``."""
    B, L = log_weights.shape
    n = L if n is None else n
    u = _random.uniform(generator, (B, n), log_weights.dtype, log_weights.device)
    j = torch.arange(n, dtype=log_weights.dtype, device=log_weights.device)
    return inverse_cdf(cumulative_weights(log_weights), (j + u) / n)


def residual(log_weights: Tensor, n: int | None = None, generator: _random.Randomness = None) -> Tensor:
    """Residual resampling: ``floor(n W_i)`` deterministic copies, the rest multinomially."""
    B, L = log_weights.shape
    n = L if n is None else n
    w = torch.softmax(log_weights, dim=-1)
    # n * W can round to 0.999... for exactly representable copy counts: nudge before the floor
    # (the total stays <= n while n * 1e-9 < 1).
    counts = torch.floor(n * w + 1e-9)
    n_rest = n - counts.sum(-1)  # (B,)
    rest = (n * w - counts).clamp_min(0.0)
    rest = torch.where(rest.sum(-1, keepdim=True) > 0, rest, torch.ones_like(rest))
    draws = _random.multinomial(rest, n, generator)  # (B, n)
    use = torch.arange(n, device=w.device).unsqueeze(0) < n_rest.unsqueeze(-1)
    counts = counts.scatter_add(-1, draws, use.to(counts.dtype))
    ends = torch.cumsum(counts, dim=-1)
    j = torch.arange(n, dtype=ends.dtype, device=w.device).expand(B, n)
    idx = torch.searchsorted(ends, j.contiguous(), right=True)
    return idx.clamp_(max=L - 1)


Resampler = Callable[..., Tensor]

RESAMPLING_SCHEMES: dict[str, Resampler] = {
    "multinomial": multinomial,
    "systematic": systematic,
    "stratified": stratified,
    "residual": residual,
}


def get_resampler(name: str) -> Resampler:
    """Look up a resampling scheme by name (``multinomial``, ``systematic``, ``stratified``,
    ``residual``)."""
    try:
        return RESAMPLING_SCHEMES[name]
    except KeyError:
        raise ValueError(f"resampling must be one of {sorted(RESAMPLING_SCHEMES)}, got {name!r}") from None
