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

__all__ = [
    "RESAMPLING_SCHEMES",
    "effective_sample_size",
    "multinomial",
    "systematic",
    "systematic_from_cumsum",
    "systematic_grid",
    "stratified",
    "residual",
    "get_resampler",
]


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """ESS ``1 / sum_i W_i^2`` of normalised log-weights along the last dimension."""
    return torch.exp(-torch.logsumexp(2.0 * log_weights, dim=-1))


def _inverse_cdf(log_weights: Tensor, positions: Tensor) -> Tensor:
    """Indices ``i`` with ``cdf[i-1] <= positions < cdf[i]`` (positions sorted in ``[0, 1)``)."""
    cdf = torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1)
    cdf = cdf / cdf[..., -1:]  # exact 1 at the end despite rounding
    idx = torch.searchsorted(cdf, positions.contiguous(), right=True)
    return idx.clamp_(max=log_weights.shape[-1] - 1)


def multinomial(
    log_weights: Tensor, n: int | None = None, generator: torch.Generator | None = None
) -> Tensor:
    """Multinomial resampling: ``n`` i.i.d. draws from the weights of each row."""
    n = log_weights.shape[-1] if n is None else n
    w = torch.softmax(log_weights, dim=-1)
    return torch.multinomial(w, n, replacement=True, generator=generator)


def systematic(log_weights: Tensor, n: int | None = None, generator: torch.Generator | None = None) -> Tensor:
    """Systematic resampling: one uniform ``u`` per row, positions ``(j + 1 - u) / n``."""
    B, L = log_weights.shape
    u = torch.rand(B, 1, dtype=log_weights.dtype, device=log_weights.device, generator=generator)
    return systematic_from_cumsum(torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1), u, n)


#: :func:`systematic_from_cumsum` binary-searches the positions while ``rows * n * log2(L)``
#: is below this and scatters otherwise.  Measured on one CPU thread with fresh weights at every
#: call (the search's branches are then unpredictable; repeating one input flatters it 3-4x): the
#: search is faster for one row of up to ~300 particles (10 vs 18 us), 2x slower for 1000.
SEARCH_WORK = 4000


def systematic_grid(B: int, n: int, dtype: torch.dtype, device: torch.device | str | None = None) -> Tensor:
    """The integers ``1, ..., n`` that :func:`systematic_from_cumsum` searches for, shape ``(B, n)``."""
    return torch.arange(1, n + 1, dtype=dtype, device=device).expand(B, n).contiguous()


def systematic_from_cumsum(
    cumw: Tensor,
    u: Tensor,
    n: int | None = None,
    *,
    out: Tensor | None = None,
    grid: Tensor | None = None,
    ones: Tensor | None = None,
) -> Tensor:
    """Systematic resampling from cumulative sums of (unnormalised, non-negative) weights.

    Position ``j = 0, ..., n - 1`` is ``p_j = (j + 1 - u) / n`` (the offset ``1 - u`` is uniform
    on ``(0, 1]``, which saves computing ``1 - u``) and goes to the particle ``i`` with ``cdf_{i-1}
    <= p_j < cdf_i``, ``cdf = cumw / cumw[:, -1]``; the indices come sorted.  Few operations per
    call: the particle filter calls it at every time step, where per-operation overhead dominates
    for one sequence.

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
    grid : Tensor, optional
        :func:`systematic_grid` ``(B, n)`` (made here if omitted); callers that resample many times
        pass it to save its construction.
    ones : Tensor, shape (B, L - 1), long, optional
        ``torch.ones`` (made here if omitted and needed), likewise.

    Returns
    -------
    Tensor, shape (B, n), long
        Ancestor indices in ``[0, L)``.
    """
    B, L = cumw.shape
    n = L if n is None else n
    inv_total = torch.reciprocal(cumw[:, -1:])
    if B * n * math.log2(max(L, 2)) < SEARCH_WORK:
        # index of position j = #{i: cdf_i <= p_j} = #{i: n cdf_i + u <= j + 1}; positions past the
        # end (rounding) go to L - 1
        if grid is None:
            grid = systematic_grid(B, n, cumw.dtype, cumw.device)
        idx = torch.searchsorted(torch.addcmul(u, cumw, inv_total, value=n), grid, right=True, out=out)
        return idx.clamp_(max=L - 1)
    # particle i gets below_i - below_{i-1} positions, below_i = #{j: p_j < cdf_i} = floor(n cdf_i +
    # u) (the conversion truncates, and n cdf + u >= 0): mark each below_i (i < L - 1) and count the
    # marks up to j (one scatter and one cumulative sum).  The clamp also maps NaN weights
    # (undefined integer conversion) to a valid index.
    below = torch.addcmul(u, cumw[:, :-1], inv_total, value=n).long().clamp_(0, n)
    if ones is None:
        ones = torch.ones(B, L - 1, dtype=torch.long, device=cumw.device)
    marks = torch.zeros(B, n + 1, dtype=torch.long, device=cumw.device)
    marks.scatter_add_(1, below, ones)
    return torch.cumsum(marks[:, :n], dim=1, out=out)


def stratified(log_weights: Tensor, n: int | None = None, generator: torch.Generator | None = None) -> Tensor:
    """Stratified resampling: one uniform per stratum ``[j/n, (j+1)/n)``."""
    B, L = log_weights.shape
    n = L if n is None else n
    u = torch.rand(B, n, dtype=log_weights.dtype, device=log_weights.device, generator=generator)
    j = torch.arange(n, dtype=log_weights.dtype, device=log_weights.device)
    return _inverse_cdf(log_weights, (j + u) / n)


def residual(log_weights: Tensor, n: int | None = None, generator: torch.Generator | None = None) -> Tensor:
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
    draws = torch.multinomial(rest, n, replacement=True, generator=generator)  # (B, n)
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
