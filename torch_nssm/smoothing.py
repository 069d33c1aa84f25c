"""Particle smoothers producing the sufficient statistics of the EM M-step (NOTES §3-4).

The exact forward-filtering backward-smoothing (FFBSm) recursion uses the full ``L x L`` pairwise
weights (not the paper's diagonal eq. 24), but never stores them: with ``C = chol(Q)``,
``z_f^i = C^-1 f(x_k^i, u_k)`` and ``z_x^j = C^-1 x_{k+1}^j``, the backward kernel

    K^{ij} = softmax_i(log W_k^i - |z_f^i|^2 / 2 + z_x^j . z_f^i)

is built from one batched matmul (the part that depends on ``j`` only cancels), the pairwise
weights are ``W^{ij} = K^{ij} W_{k+1|N}^j`` and everything the M-step needs is a mat-vec:

    W_{k|N}^i = sum_j K^{ij} W_{k+1|N}^j
    m_k^i     = sum_j K^{ij} W_{k+1|N}^j x_{k+1}^j

The ``j`` dimension is processed in chunks, so memory is ``O(B * L * chunk)`` per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .filtering import FilterOutput
from .model import SequenceBatch, StateSpaceModel

__all__ = ["SmootherOutput", "ffbsm", "smoothed_moments", "TINY_WEIGHT"]

#: Smoothing weights below this are set to zero: products of such weights are denormal numbers,
#: which slow CPU mat-vecs about 17x (NOTES §7), and they carry no information.
TINY_WEIGHT = 1e-150


@dataclass
class SmootherOutput:
    """Smoothing weights and transition statistics of one E-step.

    Attributes
    ----------
    log_weights : Tensor, shape (T, B, L)
        Log marginal smoothing weights ``log W_{k|N}`` of the filter particles.
    next_mean : Tensor, shape (T-1, B, L, nx)
        ``xbar_k^i = m_k^i / s_k^i``: the smoothed mean of ``x_{k+1}`` given ``x_k = x_k^i``.
    transition_weights : Tensor, shape (T-1, B, L)
        ``s_k^i = W_{k|N}^i`` where the transition ``k -> k+1`` exists, else 0.
    residual_scatter : Tensor, shape (B, nx, nx)
        The parameter-free part of the process-noise scatter,
        ``sum_k [S_{k+1} - sum_i m_k^i m_k^i^T / s_k^i]`` (NOTES §7: it must not be dropped).
    """

    log_weights: Tensor
    next_mean: Tensor
    transition_weights: Tensor
    residual_scatter: Tensor


def _chunks(n: int, size: int):
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


@torch.no_grad()
def ffbsm(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    *,
    chunk_size: int | None = None,
) -> SmootherOutput:
    """Forward-filtering backward-smoothing (marginal and pairwise), exact, ``O(T L^2)``.

    Parameters
    ----------
    model : StateSpaceModel
        The model the filter ran with (its ``f`` and ``Rw`` define the backward kernel).
    data : SequenceBatch
    filt : FilterOutput
    chunk_size : int, optional
        Number of ``x_{k+1}`` particles processed at once; default keeps the per-step work matrix
        ``B * L * chunk`` under about 4 million entries (32 MB in float64).

    Returns
    -------
    SmootherOutput
    """
    X, logW = filt.particles, filt.log_weights
    T, B, L, nx = X.shape
    if chunk_size is None:
        chunk_size = max(1, min(L, 4_000_000 // max(1, B * L)))
    Cw = torch.linalg.cholesky(model.per_sequence("Rw", B))
    eye = torch.eye(nx, dtype=X.dtype, device=X.device)
    Cinv_t = torch.linalg.solve_triangular(Cw, eye.expand_as(Cw), upper=False).transpose(-1, -2)
    trans = data.transition_mask  # (T-1, B)

    log_ws = torch.empty_like(logW)
    log_ws[T - 1] = logW[T - 1]
    next_mean = torch.empty(T - 1, B, L, nx, dtype=X.dtype, device=X.device)
    trans_w = torch.zeros(T - 1, B, L, dtype=X.dtype, device=X.device)
    scatter = torch.zeros(B, nx, nx, dtype=X.dtype, device=X.device)

    for k in range(T - 2, -1, -1):
        x_next = X[k + 1]
        w_next = torch.exp(log_ws[k + 1])
        w_next = torch.where(w_next < TINY_WEIGHT, torch.zeros_like(w_next), w_next)
        zf = model.transition(X[k], data.u[k]) @ Cinv_t  # (B, L, nx)
        zx = x_next @ Cinv_t
        a = logW[k] - 0.5 * (zf * zf).sum(-1)  # (B, L)
        s = torch.zeros(B, L, dtype=X.dtype, device=X.device)
        m = torch.zeros(B, L, nx, dtype=X.dtype, device=X.device)
        for sl in _chunks(L, chunk_size):
            logits = a.unsqueeze(-1) + zf @ zx[:, sl].transpose(-1, -2)  # (B, L_i, J)
            K = torch.softmax(logits, dim=1)
            wj = w_next[:, sl]
            s = s + (K @ wj.unsqueeze(-1)).squeeze(-1)
            m = m + K @ (wj.unsqueeze(-1) * x_next[:, sl])
        valid = trans[k]  # (B,)
        pos = s > 0
        xbar = torch.where(pos.unsqueeze(-1), m / torch.where(pos, s, 1.0).unsqueeze(-1), X[k])
        S_next = torch.einsum("bj,bjp,bjq->bpq", w_next, x_next, x_next)
        MmT = torch.einsum("bi,bip,biq->bpq", s, xbar, xbar)
        scatter = scatter + torch.where(valid.view(B, 1, 1), S_next - MmT, torch.zeros_like(S_next))
        log_s = torch.log(s)
        log_s = log_s - torch.logsumexp(log_s, dim=-1, keepdim=True)  # guard rounding drift
        log_ws[k] = torch.where(valid.unsqueeze(-1), log_s, logW[k])
        next_mean[k] = xbar
        trans_w[k] = torch.where(valid.unsqueeze(-1), s, torch.zeros_like(s))
    return SmootherOutput(log_ws, next_mean, trans_w, scatter)


def smoothed_moments(particles: Tensor, log_weights: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted mean ``(..., nx)`` and covariance ``(..., nx, nx)`` over the particle dimension.

    Parameters
    ----------
    particles : Tensor, shape (..., L, nx)
    log_weights : Tensor, shape (..., L)
        Normalised log-weights.
    """
    w = torch.softmax(log_weights, dim=-1).unsqueeze(-1)
    mean = (w * particles).sum(-2)
    d = particles - mean.unsqueeze(-2)
    cov = (w * d).transpose(-1, -2) @ d
    return mean, cov
