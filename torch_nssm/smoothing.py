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

Backward simulation (FFBSi) draws ``M`` smoothed trajectories instead, in ``O(T (L + M))`` expected
time: each backward index is proposed from the filter weights and accepted with probability
``exp(-|z_x^j - z_f^i|^2 / 2) <= 1`` (rejection sampling, Douc et al. 2011), or moved by
independent Metropolis-Hastings steps started at the particle's genealogical parent (the MCMC
backward kernel of Bunch & Godsill 2013, Dau & Chopin 2022), with independent proposals
from the filter weights (one move per index by default, as in Dau & Chopin).  Pure rejection
has unbounded expected cost, so after ``max_tries`` failed proposals the remaining indices are
drawn exactly (``O(L)`` each).  The trajectories yield the same statistics as FFBSm, estimated by counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ._ops import small_matmul, squared_norm, time_blocks
from .filtering import FilterOutput
from .model import SequenceBatch, StateSpaceModel

__all__ = ["SmootherOutput", "ffbsm", "ffbsi", "smoothed_moments", "TINY_WEIGHT", "SMOOTHERS"]

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

    def select(self, index) -> SmootherOutput:
        """The smoother output of the sequences ``index``."""
        return SmootherOutput(
            self.log_weights[:, index],
            self.next_mean[:, index],
            self.transition_weights[:, index],
            self.residual_scatter[index],
        )


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
    Cinv_t = _whitening(model, B, X)
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
        zf = _whitened(model.transition(X[k], data.u[k]), Cinv_t)  # (B, L, nx)
        zx = _whitened(x_next, Cinv_t)
        a = logW[k] - 0.5 * squared_norm(zf)  # (B, L)
        # rows [w_j, w_j x_j^T] (B, 1 + nx, L): one product with the kernel gives s and m together,
        # and multiplying from the left reads K in its stored layout (no transposed copy)
        wx = torch.cat([w_next.unsqueeze(1), (w_next.unsqueeze(-1) * x_next).transpose(-1, -2)], 1)
        sm = torch.zeros(B, 1 + nx, L, dtype=X.dtype, device=X.device)
        for sl in _chunks(L, chunk_size):
            # (B, J, L_i): the softmax runs over the contiguous last dimension (i)
            K = torch.softmax(torch.baddbmm(a.unsqueeze(1), zx[:, sl], zf.transpose(-1, -2)), dim=-1)
            sm = sm + wx[:, :, sl] @ K
        s, m = sm[:, 0], sm[:, 1:].transpose(-1, -2)
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


def _whitening(model: StateSpaceModel, B: int, like: Tensor) -> Tensor:
    """Transpose of the inverse Cholesky factor of ``Rw``, shape (B, nx, nx)."""
    Cw = torch.linalg.cholesky(model.per_sequence("Rw", B))
    eye = torch.eye(Cw.shape[-1], dtype=like.dtype, device=like.device)
    return torch.linalg.solve_triangular(Cw, eye.expand_as(Cw), upper=False).transpose(-1, -2)


def _whitened(x: Tensor, Cinv_t: Tensor) -> Tensor:
    """``x @ Cinv_t`` for ``x`` ``(B, L, nx)`` and ``Cinv_t`` ``(B, nx, nx)``, elementwise."""
    return small_matmul(x.unsqueeze(-2), Cinv_t.unsqueeze(-3)).squeeze(-2)


def _cdf(log_weights: Tensor) -> Tensor:
    """Cumulative weights along the last dimension (any leading shape)."""
    return torch.cumsum(torch.softmax(log_weights, dim=-1), dim=-1)


def _draw_cdf(cdf: Tensor, n: int, generator) -> Tensor:
    """``n`` i.i.d. indices per row of a cumulative-weight table ``(B, L)`` (inverse CDF)."""
    u = torch.rand(cdf.shape[0], n, dtype=cdf.dtype, device=cdf.device, generator=generator)
    return torch.searchsorted(cdf, u * cdf[:, -1:]).clamp_(max=cdf.shape[-1] - 1)


def _draw(log_weights: Tensor, n: int, generator) -> Tensor:
    """``n`` i.i.d. indices per row of the normalised log-weights ``(B, L)`` (inverse CDF)."""
    return _draw_cdf(_cdf(log_weights), n, generator)


def _log_kernel(zf: Tensor, idx: Tensor, zx_traj: Tensor) -> Tensor:
    """``-|z_x^j - z_f^i|^2 / 2`` for candidate ancestors ``idx`` (B, M) of trajectories (B, M, nx)."""
    d = zx_traj - torch.gather(zf, 1, idx.unsqueeze(-1).expand(*idx.shape, zf.shape[-1]))
    return -0.5 * squared_norm(d)


def _proposals(log_weights: Tensor, n: int, steps: int, generator) -> Tensor:
    """``steps`` sets of ``n`` i.i.d. proposals per row from the filter weights ``(B, L)``: ``(B, steps, n)``.

    Independent draws matter: a cheaper systematic sample read from a random offset has the right
    marginals, but couples the proposals of different trajectories and steps so strongly that an
    average over trajectories is far noisier (tried: after two moves from exact draws, a histogram
    of 40,000 trajectories was off by up to 16 standard errors).
    """
    B = log_weights.shape[0]
    return _draw(log_weights, n * steps, generator).view(B, steps, n)


def _independent_mh(J: Tensor, zf: Tensor, zx: Tensor, props: Tensor, log_us: Tensor) -> Tensor:
    """Independent Metropolis-Hastings moves of backward indices ``J`` ``(B, M)``.

    The target of trajectory ``m`` is the backward kernel ``pi(i) ~ W_i exp(-|z_x^m - z_f^i|^2 / 2)``;
    ``props`` ``(B, S, M)`` are ``S`` proposals per trajectory drawn from ``W`` (so the acceptance
    ratio is the ratio of the transition densities); ``log_us`` ``(B, S, M)`` are log-uniforms.
    Each move leaves ``pi`` invariant.
    """
    log_t = _log_kernel(zf, J, zx)
    for step in range(props.shape[1]):
        prop = props[:, step]
        log_t_prop = _log_kernel(zf, prop, zx)
        accept = log_us[:, step] < log_t_prop - log_t
        J = torch.where(accept, prop, J)
        log_t = torch.where(accept, log_t_prop, log_t)
    return J


@torch.no_grad()
def ffbsi(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    *,
    n_trajectories: int | None = None,
    method: str = "reject",
    max_tries: int = 10,
    mcmc_steps: int = 1,
    generator: torch.Generator | None = None,
) -> SmootherOutput:
    """Backward-simulation particle smoother (FFBSi), ``O(T (L + M))`` per pass.

    Parameters
    ----------
    model, data, filt
        As for :func:`ffbsm`.
    n_trajectories : int, optional
        Number ``M`` of smoothed trajectories; the number of particles by default.
    method : {"reject", "mcmc"}
        ``"reject"``: rejection sampling with an exact fallback after ``max_tries`` failed
        proposals (exact draws from the backward kernel).  ``"mcmc"``: ``mcmc_steps`` independent
        Metropolis-Hastings moves from the genealogical parent, with independent proposals
        from the filter weights (each move leaves the backward kernel invariant; cheapest).
    max_tries : int
        Rejection proposals per index before the exact fallback.
    mcmc_steps : int
        Metropolis-Hastings moves per index.
    generator : torch.Generator, optional

    Returns
    -------
    SmootherOutput
        Statistics estimated from the trajectories: ``W_{k|N}^i`` is the fraction of trajectories
        through particle ``i`` at time ``k``.
    """
    if method not in ("reject", "mcmc"):
        raise ValueError(f"method must be 'reject' or 'mcmc', got {method!r}")
    X, logW = filt.particles, filt.log_weights
    T, B, L, nx = X.shape
    M = L if n_trajectories is None else int(n_trajectories)
    Cinv_t = _whitening(model, B, X)
    trans = data.transition_mask
    dtype, device = X.dtype, X.device

    cdfs = _cdf(logW) if method == "reject" else None  # (T, B, L), once for all steps

    def draw_filter(k: int) -> Tensor:  # M i.i.d. indices from the filter weights at step k
        return _draw_cdf(cdfs[k], M, generator) if cdfs is not None else _draw(logW[k], M, generator)

    all_valid = trans.all(-1).tolist()
    Js = torch.empty(T, B, M, dtype=torch.long, device=device)  # the trajectories' indices
    Js[T - 1] = draw_filter(T - 1)
    for k in range(T - 2, -1, -1):
        J_next = Js[k + 1]
        x_next = torch.gather(X[k + 1], 1, J_next.unsqueeze(-1).expand(B, M, nx))  # (B, M, nx)
        zf = _whitened(model.transition(X[k], data.u[k]), Cinv_t)
        zx = _whitened(x_next, Cinv_t)
        if method == "reject":
            J = torch.zeros(B, M, dtype=torch.long, device=device)
            pending = torch.ones(B, M, dtype=torch.bool, device=device)
            for _ in range(max_tries):
                prop = _draw_cdf(cdfs[k], M, generator)
                log_u = torch.log(torch.rand(B, M, dtype=dtype, device=device, generator=generator))
                accept = pending & (log_u < _log_kernel(zf, prop, zx))
                J = torch.where(accept, prop, J)
                pending = pending & ~accept
                if not bool(pending.any()):
                    break
            if bool(pending.any()):
                b_idx, m_idx = torch.nonzero(pending, as_tuple=True)
                d = zx[b_idx, m_idx].unsqueeze(1) - zf[b_idx]  # (P, L, nx)
                logits = logW[k][b_idx] - 0.5 * squared_norm(d)
                J[b_idx, m_idx] = _draw(logits, 1, generator)[:, 0]
        else:
            props = _proposals(logW[k], M, mcmc_steps, generator)
            log_us = torch.log(torch.rand(B, mcmc_steps, M, dtype=dtype, device=device, generator=generator))
            J = _independent_mh(torch.gather(filt.ancestors[k + 1], 1, J_next), zf, zx, props, log_us)
        if not all_valid[k]:
            # Rows past a sequence's end restart from the filter (their transitions are masked out).
            J = torch.where(trans[k].unsqueeze(-1), J, draw_filter(k))
        Js[k] = J
    return _trajectory_statistics(X, logW, Js, trans)


def _trajectory_statistics(X: Tensor, logW: Tensor, Js: Tensor, trans: Tensor) -> SmootherOutput:
    """The smoother output from the trajectories' indices ``Js`` ``(T, B, M)``, by counts.

    Computed after the backward pass, for blocks of time steps at once (a dozen operations per
    block instead of per step; the blocks keep the temporaries in cache).
    """
    T, B, L, nx = X.shape
    M = Js.shape[-1]
    log_ws = logW.clone()
    next_mean = torch.empty(T - 1, B, L, nx, dtype=X.dtype, device=X.device)
    trans_w = torch.empty(T - 1, B, L, dtype=X.dtype, device=X.device)
    scatter = torch.zeros(B, nx, nx, dtype=X.dtype, device=X.device)
    for sl in time_blocks(T - 1, B * max(L, M)):
        t = sl.stop - sl.start
        J, valid = Js[sl], trans[sl]  # (t, B, M), (t, B)
        J_next = Js[sl.start + 1 : sl.stop + 1]
        x_next = torch.gather(
            X[sl.start + 1 : sl.stop + 1], 2, J_next.unsqueeze(-1).expand(t, B, M, nx)
        )  # (t, B, M, nx)
        s = torch.zeros(t, B, L, dtype=X.dtype, device=X.device).scatter_add_(
            2, J, torch.full((1, 1, 1), 1.0 / M, dtype=X.dtype, device=X.device).expand(t, B, M)
        )
        m = torch.zeros(t, B, L, nx, dtype=X.dtype, device=X.device).scatter_add_(
            2, J.unsqueeze(-1).expand(t, B, M, nx), x_next / M
        )
        pos = s > 0
        xbar = torch.where(pos.unsqueeze(-1), m / torch.where(pos, s, 1.0).unsqueeze(-1), X[sl])
        S_next = (x_next.transpose(-1, -2) @ x_next) / M  # (t, B, nx, nx)
        MmT = (s.unsqueeze(-1) * xbar).transpose(-1, -2) @ xbar
        scatter += torch.where(valid.view(t, B, 1, 1), S_next - MmT, torch.zeros_like(S_next)).sum(0)
        log_ws[sl] = torch.where(valid.unsqueeze(-1), torch.log(s), logW[sl])
        next_mean[sl] = xbar
        trans_w[sl] = torch.where(valid.unsqueeze(-1), s, torch.zeros_like(s))
    return SmootherOutput(log_ws, next_mean, trans_w, scatter)


#: The smoothers of the E-step, by name.
SMOOTHERS = ("ffbsm", "ffbsi", "mcmc")
