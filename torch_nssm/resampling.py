"""Resampling schemes for particle filters, batched over independent rows.

Every scheme takes normalised *log*-weights of shape ``(B, L)`` (one row per sequence) and returns
ancestor indices of shape ``(B, M)`` such that the expected number of copies of particle ``i`` is
``M * W_i`` (unbiasedness).  Systematic, stratified and residual resampling have lower variance than
multinomial (Douc, Cappé & Moulines 2005); systematic is the default.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

__all__ = [
    "RESAMPLING_SCHEMES",
    "effective_sample_size",
    "multinomial",
    "systematic",
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
    """Systematic resampling: one uniform per row, positions ``(j + U) / n``.

    Particle ``i`` gets the positions in ``[cdf_{i-1}, cdf_i)``, i.e. ``floor(n cdf_i - U + 1) -
    floor(n cdf_{i-1} - U + 1)`` of them; the indices come sorted, as the inverse-CDF method
    would give them, from one scatter and one cumulative sum (no search).
    """
    B, L = log_weights.shape
    n = L if n is None else n
    u = torch.rand(B, 1, dtype=log_weights.dtype, device=log_weights.device, generator=generator)
    cdf = torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1)
    cdf = cdf / cdf[:, -1:]
    below = torch.floor(n * cdf - u + 1.0).nan_to_num_(0.0).clamp_(0, n)  # #{j: (j + u)/n < cdf_i}
    # Position j belongs to the particle i with below_{i-1} <= j < below_i, i.e. its index is the
    # number of i' < L - 1 with below_i' <= j: one scatter and one cumulative sum, no search.
    marks = torch.zeros(B, n + 1, dtype=torch.long, device=log_weights.device)
    marks.scatter_add_(1, below[:, :-1].long(), torch.ones(B, L - 1, dtype=torch.long, device=marks.device))
    return torch.cumsum(marks[:, :n], dim=1)


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
