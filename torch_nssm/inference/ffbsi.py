"""Backward simulation (FFBSi): smoothed trajectories drawn backwards through the filter's
particles, the statistics of the EM M-step estimated by counts (docs/method.md §3-4), and pieces of
trajectories for the standard errors.

Backward simulation draws ``M`` smoothed trajectories, in ``O(T (L + M))`` expected
time: each backward index is proposed from the filter weights and accepted with probability
``exp(-|z_x^j - z_f^i|^2 / 2) <= 1`` (rejection sampling, Douc et al. 2011), or moved by
independent Metropolis-Hastings steps started at the particle's genealogical parent (the MCMC
backward kernel of Bunch & Godsill 2013, Dau & Chopin 2022), with independent proposals
from the resampling ancestry (one move per index by default, as in Dau & Chopin).  Pure rejection
has unbounded expected cost, so after ``max_tries`` failed proposals the remaining indices are
drawn exactly (``O(L)`` each).  The trajectories yield the same statistics as FFBSm
(:mod:`torch_nssm.inference.ffbsm`), estimated by counts.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import _workspace
from .._ops import squared_norm, time_blocks
from ..core.model import SequenceBatch, StateSpaceModel
from .ffbsm import SmootherOutput, whitened, whitened_steps, whitening
from .filtering import FilterOutput
from .random import Randomness, SequenceStreams
from .resampling import cumulative_weights, inverse_cdf

__all__ = ["ffbsi", "backward_trajectories", "backward_segments"]


def _draw(log_weights: Tensor, n: int, generator) -> Tensor:
    """``n`` i.i.d. indices per row of the log-weights ``(..., L)``: ``(..., n)``."""
    lead, L = log_weights.shape[:-1], log_weights.shape[-1]
    cdf = cumulative_weights(log_weights).reshape(-1, L)
    u = torch.rand(cdf.shape[0], n, dtype=cdf.dtype, device=cdf.device, generator=generator)
    return inverse_cdf(cdf, u).view(*lead, n)


def _sq_dist(zf: Tensor, idx: Tensor, zx_traj: Tensor) -> Tensor:
    """``|z_x^m - z_f^{idx_m}|^2`` for candidate ancestors ``idx`` (B, M) of trajectories (B, M, nx)."""
    if zf.shape[-1] == 1:
        d = zx_traj[..., 0] - torch.gather(zf[..., 0], 1, idx)
        return d * d
    return squared_norm(zx_traj - torch.gather(zf, 1, idx.unsqueeze(-1).expand(*idx.shape, zf.shape[-1])))


def _log_kernel(zf: Tensor, idx: Tensor, zx_traj: Tensor) -> Tensor:
    """``-|z_x^j - z_f^i|^2 / 2`` for candidate ancestors ``idx`` (B, M) of trajectories (B, M, nx)."""
    return -0.5 * _sq_dist(zf, idx, zx_traj)


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
    generator: Randomness = None,
) -> SmootherOutput:
    """Backward-simulation particle smoother (FFBSi), ``O(T (L + M))`` per pass.

    Everything that does not depend on the trajectories drawn so far (``f`` at all particles, the
    whitening, the MCMC proposals and uniforms) is computed for blocks of time steps before the
    backward loop, which keeps about a dozen small operations per step.

    Parameters
    ----------
    model, data, filt
        As for :func:`ffbsm`.
    n_trajectories : int, optional
        Number ``M`` of smoothed trajectories; the number of particles by default.
    method : {"reject", "mcmc"}
        ``"reject"``: rejection sampling with an exact fallback after ``max_tries`` failed
        proposals (exact draws from the backward kernel; its data-dependent number of tries costs
        a host synchronisation per step on a GPU).  ``"mcmc"``: ``mcmc_steps`` independent
        Metropolis-Hastings moves from the genealogical parent, with independent proposals
        from the filter weights (each move leaves the backward kernel invariant; cheapest).
    max_tries : int
        Rejection proposals per index before the exact fallback.
    mcmc_steps : int
        Metropolis-Hastings moves per index.
    generator : torch.Generator or SequenceStreams, optional
        With per-sequence streams (:mod:`torch_nssm.inference.random`) each sequence's backward
        pass starts at its own last step and draws, per step, a fixed number of uniforms in
        reverse time order (rejection: its whole ``max_tries`` budget), whatever its batch.

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
    Cinv_t = whitening(model, B, X)
    trans = data.transition_mask
    dtype, device = X.dtype, X.device
    all_valid = trans.all(-1).tolist()

    blocks = list(time_blocks(T - 1, B * max(L, M * mcmc_steps)))
    # the statistics are taken block by block as the pass goes (the indices of one block kept,
    # not all T steps'), where the blocks are the statistics' own
    rolling = bool(blocks) and max(L, M * mcmc_steps) == max(L, M)
    stats = _TrajectoryStatistics(X, logW, trans, M) if rolling else None
    size = blocks[0].stop - blocks[0].start if rolling else T - 1
    Js = torch.empty(size + 1, B, M, dtype=torch.long, device=device)  # indices: one block's, or all
    streams = generator if isinstance(generator, SequenceStreams) else None
    if streams is None:
        Js[-1] = _draw(logW[T - 1], M, generator)
    else:  # each sequence starts at its own last step; the rows past it restart from there
        last = data.lengths - 1
        logW_last = logW[last, torch.arange(B, device=device)]  # (B, L)
        J_last = inverse_cdf(cumulative_weights(logW_last), streams.rows((M,), dtype))
        Js[-1] = J_last
        limits = [n - 1 for n in data.lengths.tolist()]  # steps with a transition
        n_mcmc, n_reject = M * mcmc_steps, (2 * max_tries + 1) * M
    with torch.inference_mode():  # writes only into ``Js`` and the statistics' outputs
        for blk in reversed(blocks):
            t = blk.stop - blk.start
            if rolling:  # row i: step blk.start + i; the last row is the later block's first
                if t < size or blk.stop < T - 1:
                    Js[t] = Js[0] if blk.stop < T - 1 else Js[-1]
                Jb = Js[: t + 1]
            else:
                Jb = Js[blk.start : blk.stop + 1]
            zf, zx, _ = whitened_steps(model, data, X, logW, Cinv_t, blk, centred=False)
            if streams is not None:  # (B, t, ...), row j: step blk.stop - 1 - j
                n_draws = 2 * n_mcmc if method == "mcmc" else n_reject
                kind = _UNIFORM_DTYPE if method == "mcmc" else dtype
                draws = streams.steps(blk.start, blk.stop, limits, (n_draws,), kind, reverse=True)
            if method == "mcmc":
                pre = (draws, J_last) if streams is not None else (None, None)
                A, kept = filt.ancestors, filt.resampled
                _mcmc_block(Jb, blk, zf, zx, A, kept, logW, trans, all_valid, mcmc_steps, generator, *pre)
            else:
                cdfs = cumulative_weights(logW[blk])  # (t, B, L)
                for k in range(blk.stop - 1, blk.start - 1, -1):
                    i = k - blk.start
                    J_next = Jb[i + 1]
                    if nx == 1:
                        x_next = torch.gather(zx[i, ..., 0], 1, J_next).unsqueeze(-1)  # (B, M, 1)
                    else:
                        x_next = torch.gather(zx[i], 1, J_next.unsqueeze(-1).expand(B, M, nx))  # (B, M, nx)
                    pre = None if streams is None else draws[:, blk.stop - 1 - k]
                    J = _reject(zf[i], x_next, logW[k], cdfs[i], max_tries, generator, pre)
                    if not all_valid[k]:
                        # Rows past a sequence's end restart from the filter (transitions masked out).
                        if streams is not None:
                            restart = J_last
                        else:
                            u = torch.rand(B, M, dtype=dtype, device=device, generator=generator)
                            restart = inverse_cdf(cdfs[i], u)
                        J = torch.where(trans[k].unsqueeze(-1), J, restart)
                    Jb[i] = J
            if rolling:
                stats.add(blk, Jb[:t], Jb[1:])
    if rolling:
        return stats.finish()
    return _trajectory_statistics(X, logW, Js, trans)


#: The MCMC backward pass's uniforms are drawn in single precision: a double costs ~3x as much
#: (6 vs 2 ns a number on one CPU thread, the pass's largest cost at the Table 1 size), and 24-bit
#: uniforms pick among ``L < 2^24`` particles and set an acceptance probability to ``2^-24``.
_UNIFORM_DTYPE = torch.float32


@torch.inference_mode()  # writes only into ``Js``: see particle_filter's loop
def _mcmc_block(
    Js: Tensor,
    blk: slice,
    zf: Tensor,
    zx: Tensor,
    ancestors: Tensor,
    resampled: Tensor | None,
    logW: Tensor,
    trans: Tensor,
    all_valid: list,
    steps: int,
    generator,
    draws: Tensor | None,
    J_last: Tensor | None,
) -> None:
    """The MCMC backward pass over the steps ``blk`` (in reverse): ``Js`` ``(t + 1, B, M)`` holds the
    indices of the steps ``blk.start ... blk.stop`` (the last given, the others written).

    Each index starts at its genealogical parent and makes ``steps`` independent
    Metropolis-Hastings moves with proposals from the resampling ancestry: the parent
    ``A_{k+1}[U]`` of a uniformly chosen particle at ``k + 1``.  After a resampling at ``k + 1``
    the filter at ``k`` is represented by the resampled particles (equal weights: particle ``i``
    counted ``c_i`` times, its number of children), from which the particles at ``k + 1`` were
    drawn; the backward kernel of that representation, ``pi(i) ~ c_i exp(-|z_x - z_f^i|^2 / 2)``,
    has the proposal ``c_i / L`` as its prior part, so a move is accepted with the ratio of the
    transition densities alone, ``2 log u < d_J - d_{i'}`` with ``d = |z_x - z_f|^2``.  Where a
    step did not resample (the filter's ``resampled`` false, ``ess_threshold < 1``) the filter's
    weights ``W`` enter the ratio, ``2 log u - 2 log W_{i'} < (d_J - 2 log W_J) - d_{i'}`` (uniform
    proposals).  Either way each move leaves the backward kernel of the filter's particle
    approximation invariant, and a proposal costs a uniform and a lookup, not an inverse-CDF draw.

    Everything that does not depend on the trajectories is made for the whole block before its loop
    (:func:`_block_uniforms`, :func:`_block_lookups`): the proposals, their whitened predictions
    ``z_f`` (``cand``), the thresholds and, for every particle ``j`` at ``k + 1``, the squared
    distance ``d0_j`` to its genealogical parent's prediction, so that a trajectory's start is one
    lookup. Per step: three lookups by the trajectories' indices at ``k + 1`` (``z_x``, the parent,
    ``d0``) and the test. ``draws`` (per-sequence streams): the block's uniforms ``(B, t, 2 S M)``
    in reverse time (row ``j``: step ``blk.stop - 1 - j``), each row's ``S M`` proposal uniforms
    then ``S M`` acceptance uniforms; padded rows restart at ``J_last``. Without streams they are
    drawn from ``generator`` in time order.
    """
    t = blk.stop - blk.start
    B, L, nx = zf.shape[1:]
    M = Js.shape[-1]
    A_next = ancestors[blk.start + 1 : blk.stop + 1]  # (t, B, L): parents of the particles at k + 1
    pick, u = _block_uniforms(draws, generator, t, B, L, steps, M, zf.device)
    THR, PROPS, CAND, W2, A, D0, ZX = _block_lookups(blk, zf, zx, A_next, resampled, logW, pick, u, steps)
    JS = Js.unbind(0)
    last = steps - 1
    if nx == 1 and steps == 1 and all(all_valid[blk.start : blk.stop]):
        # the common case (one state, one move, no padding) as a loop of its seven operations and
        # nothing else, the gathered rows updated in place (no allocation): 1-2 us a step less
        # than the general loop below, whose per-step branches are Python
        THR1, PROPS1, CAND1 = THR[0], PROPS[0], CAND[0]
        for i in range(t - 1, -1, -1):
            J_next = JS[i + 1]
            diff = torch.gather(ZX[i], 1, J_next).sub_(CAND1[i])
            keep = torch.gather(D0[i], 1, J_next).addcmul_(diff, diff, value=-1.0)  # d - (x - c)^2
            torch.where(THR1[i] < keep, PROPS1[i], torch.gather(A[i], 1, J_next), out=JS[i])
        return
    for k in range(blk.stop - 1, blk.start - 1, -1):
        i = k - blk.start
        J_next = JS[i + 1]
        J = torch.gather(A[i], 1, J_next)  # the genealogical parents
        d = torch.gather(D0[i], 1, J_next)  # their squared distances (less 2 log W where not resampled)
        if nx == 1:
            x_next = torch.gather(ZX[i], 1, J_next)  # (B, M)
        else:
            x_next = torch.gather(ZX[i], 1, J_next.unsqueeze(-1).expand(B, M, nx))  # (B, M, nx)
        for s in range(steps):
            if nx == 1 and s == last:  # d - (x - c)^2 in one multiply-add (an operation fewer a step)
                diff = x_next - CAND[s][i]
                accept = THR[s][i] < torch.addcmul(d, diff, diff, value=-1.0)
            elif nx == 1:
                d_prop = x_next - CAND[s][i]
                d_prop = d_prop * d_prop
                accept = THR[s][i] < d - d_prop
            else:
                d_prop = squared_norm(x_next - CAND[s][i])
                accept = THR[s][i] < d - d_prop
            out = JS[i] if s == last and all_valid[k] else None  # the last move writes the result
            J = torch.where(accept, PROPS[s][i], J, out=out)
            if s < last:
                d = torch.where(accept, d_prop if W2 is None else d_prop - W2[s][i], d)
        if not all_valid[k]:
            # Rows past a sequence's end restart from the filter (their transitions are masked out):
            # an i.i.d. draw from the filter weights, or each sequence's draw at its last step (streams).
            restart = _draw(logW[k], M, generator) if draws is None else J_last
            torch.where(trans[k].unsqueeze(-1), J, restart, out=JS[i])


def _block_uniforms(draws: Tensor | None, generator, t: int, B: int, L: int, steps: int, M: int, device):
    """The MCMC block's random numbers, time-major: the proposals' uniform picks among the ``L``
    particles ``(t, B, S M)`` and the acceptance uniforms ``(t, B, S, M)``, from ``draws`` (see
    :func:`_mcmc_block`) or drawn from ``generator``."""
    n = steps * M
    if draws is None:
        pick = torch.randint(L, (t, B, n), device=device, generator=generator)
        u = torch.rand(t, B, steps, M, dtype=_UNIFORM_DTYPE, device=device, generator=generator)
    else:  # from the draws' layout (B, t, ...) in reversed time to time-major (t, B, ...)
        d = draws.view(B, t, 2, n)
        pick = d[:, :, 0].mul(L).long().clamp_(max=L - 1).transpose(0, 1).flip(0)
        u = d[:, :, 1].reshape(B, t, steps, M).transpose(0, 1).flip(0)
    return pick, u


def _block_lookups(
    blk: slice, zf: Tensor, zx: Tensor, A_next: Tensor, resampled: Tensor | None, logW: Tensor,
    pick: Tensor, u: Tensor, steps: int,
) -> tuple:
    """What the MCMC block's loop looks up, as lists of views made once: per move ``s`` and step
    ``i`` the thresholds ``THR[s][i]``, proposals ``PROPS[s][i]``, their predictions ``CAND[s][i]``
    ``(B, M, ...)`` and, where the filter's weights enter and there are several moves, the
    proposals' ``2 log W`` ``W2[s][i]`` (else ``W2`` is ``None``); per step the parents ``A[i]``,
    the squared distances to them ``D0[i]`` ``(B, L)`` and the whitened states ``ZX[i]``."""
    t = blk.stop - blk.start
    B, L, nx = zf.shape[1:]
    M = u.shape[-1]
    n = steps * M
    props = torch.gather(A_next, 2, pick)  # (t, B, S M)
    thr = torch.log(u).to(zf.dtype).mul_(2.0)  # accept where 2 log u < d - d'
    log_w2 = None
    # the steps that kept their particles (the filter's ``resampled``; None: none)
    kept = None if resampled is None else ~resampled[blk.start + 1 : blk.stop + 1].unsqueeze(-1)
    if kept is not None and bool(kept.any()):  # there the weights W enter: 2 log W, 0 after a resampling
        log_w2 = torch.where(kept, logW[blk], 0.0).mul_(2.0)
        thr -= torch.gather(log_w2, 2, props).view(t, B, steps, M)
    props = props.view(t, B, steps, M)
    if nx == 1:
        zf1, zx1 = zf[..., 0], zx[..., 0]
        cand = torch.gather(zf1, 2, props.view(t, B, n)).view(t, B, steps, M)
        d0 = zx1 - torch.gather(zf1, 2, A_next)
        d0 = d0 * d0
    else:
        cand = torch.gather(zf, 2, props.view(t, B, n, 1).expand(t, B, n, nx)).view(t, B, steps, M, nx)
        d0 = squared_norm(zx - torch.gather(zf, 2, A_next.unsqueeze(-1).expand(t, B, L, nx)))
    if log_w2 is not None:
        d0 -= torch.gather(log_w2, 2, A_next)
        w2_props = torch.gather(log_w2, 2, props.view(t, B, n)).view(t, B, steps, M) if steps > 1 else None
    # every step's views made once per block (a list lookup is free; indexing a tensor with
    # ``[i, :, s]`` costs a few microseconds of Python and view operations, at one record as much
    # as an operation on its 1,000 trajectories)
    by_move = lambda x: [v.unbind(0) for v in x.unbind(2)]  # noqa: E731  [s][i]: (B, M, ...)
    W2 = by_move(w2_props) if log_w2 is not None and steps > 1 else None
    ZX = zx1.unbind(0) if nx == 1 else zx.unbind(0)
    return by_move(thr), by_move(props), by_move(cand), W2, A_next.unbind(0), d0.unbind(0), ZX


def _reject(
    zf: Tensor, zx: Tensor, logW: Tensor, cdf: Tensor, max_tries: int, generator, pre: Tensor | None = None
) -> Tensor:
    """Backward indices ``(B, M)`` drawn exactly from the backward kernels of trajectories ``zx``
    ``(B, M, nx)``: proposals from the filter weights (``cdf`` ``(B, L)``) accepted with probability
    ``exp(-|z_x - z_f|^2 / 2) <= 1``; after ``max_tries`` failures, the exact ``O(L)`` draw.
    ``pre`` ``(B, (2 max_tries + 1) M)``: the uniforms of every try and of the fallback, drawn up
    front (per-sequence streams), else they are drawn from ``generator`` as needed."""
    B, M = zx.shape[:2]
    J = torch.zeros(B, M, dtype=torch.long, device=zx.device)
    pending = torch.ones(B, M, dtype=torch.bool, device=zx.device)
    for j in range(max_tries):
        if pre is None:
            u = torch.rand(2, B, M, dtype=zx.dtype, device=zx.device, generator=generator)
        else:
            u = pre[:, 2 * j * M : 2 * (j + 1) * M].reshape(B, 2, M).transpose(0, 1)
        prop = inverse_cdf(cdf, u[0])
        accept = pending & (torch.log(u[1]) < _log_kernel(zf, prop, zx))
        J = torch.where(accept, prop, J)
        pending = pending & ~accept
        if not bool(pending.any()):
            return J
    b_idx, m_idx = torch.nonzero(pending, as_tuple=True)
    d = zx[b_idx, m_idx].unsqueeze(1) - zf[b_idx]  # (P, L, nx)
    logits = logW[b_idx] - 0.5 * squared_norm(d)
    if pre is None:
        J[b_idx, m_idx] = _draw(logits, 1, generator)[:, 0]
    else:
        u = pre[:, 2 * max_tries * M :][b_idx, m_idx].unsqueeze(-1)
        J[b_idx, m_idx] = inverse_cdf(cumulative_weights(logits), u.contiguous())[:, 0]
    return J


def _trajectory_statistics(X: Tensor, logW: Tensor, Js: Tensor, trans: Tensor) -> SmootherOutput:
    """The smoother output from the trajectories' indices ``Js`` ``(T, B, M)``, by counts.

    Computed after the backward pass, for blocks of time steps at once (a dozen operations per
    block instead of per step; the blocks keep the temporaries in cache).  Each particle's count
    ``c`` (trajectories through it) and the sum ``q`` of its trajectories' next states give
    ``s = c / M``, ``xbar = q / c`` and ``sum_i s_i xbar_i xbar_i^T = sum_i q_i xbar_i^T / M``.
    Only ``s`` is written (``log s`` is taken if the output's ``log_weights`` are read; with every
    transition valid the transition weights are a view of it), and the particles no trajectory
    visits (``c = 0``, where ``xbar`` is the particle itself) are selected by ``(1 - c)^+``
    arithmetic instead of ``torch.where`` (~3 ns an entry with a random mask, one CPU thread).
    """
    stats = _TrajectoryStatistics(X, logW, trans, Js.shape[-1])
    for sl in time_blocks(X.shape[0] - 1, X.shape[1] * max(X.shape[2], Js.shape[-1])):
        stats.add(sl, Js[sl], Js[sl.start + 1 : sl.stop + 1])
    return stats.finish()


class _TrajectoryStatistics:
    """:func:`_trajectory_statistics` block by block: :meth:`add` takes the indices of a block of
    steps and of the steps after them, as soon as the backward pass has drawn them (so that the
    pass keeps one block of indices instead of all ``(T, B, M)``: that array's first-touch page
    faults were ~20,000 per E-step at the Table 1 size); :meth:`finish` sums the blocks'
    scatters in time order (the same sums, bit for bit, as one pass over the blocks)."""

    def __init__(self, X: Tensor, logW: Tensor, trans: Tensor, M: int):
        T, B, L, nx = X.shape
        dtype, device = X.dtype, X.device
        self.X, self.logW, self.trans, self.M = X, logW, trans, M
        self.all_valid = bool(trans.all())
        self.ws = _workspace.empty((T, B, L), dtype, device)
        torch.exp(logW[-1], out=self.ws[-1])
        self.next_mean = _workspace.empty((T - 1, B, L, nx), dtype, device)
        # with every transition valid the transition weights are the weights of the steps before
        # the last: one array (a view) instead of two equal ones
        self.trans_w = self.ws[:-1] if self.all_valid else _workspace.empty((T - 1, B, L), dtype, device)
        self.one = torch.ones((1, 1, 1), dtype=dtype, device=device)
        self.parts: list[tuple[int, Tensor]] = []

    @torch.inference_mode()  # writes into the outputs (made outside it) and keeps a sum
    def add(self, sl: slice, J: Tensor, J_next: Tensor) -> None:
        """The statistics of the steps ``sl`` from their indices ``J`` ``(t, B, M)`` and those of
        the steps ``sl.start + 1 ... sl.stop`` (``J_next``)."""
        X, logW, M = self.X, self.logW, self.M
        _, B, L, nx = X.shape
        dtype, device = X.dtype, X.device
        ws, next_mean, trans_w = self.ws, self.next_mean, self.trans_w
        t = sl.stop - sl.start
        valid = self.trans[sl]  # (t, B)
        X_next, X_here = X[sl.start + 1 : sl.stop + 1], X[sl]
        masked = not (self.all_valid or bool(valid.all()))
        # written straight into the outputs where nothing is masked (no copies of the block)
        c = torch.zeros(t, B, L, dtype=dtype, device=device) if masked else trans_w[sl].zero_()
        c.scatter_add_(2, J, self.one.expand(t, B, M))
        unvisited = torch.rsub(c, 1.0).clamp_(min=0.0)  # 1 where c = 0, else 0 (c is an integer)
        xbar = torch.empty(t, B, L, nx, dtype=dtype, device=device) if masked else next_mean[sl]
        if nx == 1:
            x_next = torch.gather(X_next[..., 0], 2, J_next)  # (t, B, M)
            q = torch.zeros(t, B, L, dtype=dtype, device=device).scatter_add_(2, J, x_next)
            torch.addcmul(q, X_here[..., 0], unvisited, out=xbar[..., 0])
            xbar[..., 0].div_(unvisited.add_(c))  # c + (c = 0): max(c, 1)
            step_scatter = (x_next.square().sum(-1) - (q * xbar[..., 0]).sum(-1)).view(t, B, 1, 1) / M
        else:
            x_next = torch.gather(X_next, 2, J_next.unsqueeze(-1).expand(t, B, M, nx))  # (t, B, M, nx)
            q = torch.zeros(t, B, L, nx, dtype=dtype, device=device)
            q.scatter_add_(2, J.unsqueeze(-1).expand(t, B, M, nx), x_next)
            torch.addcmul(q, X_here, unvisited.unsqueeze(-1), out=xbar)
            xbar.div_(unvisited.add_(c).unsqueeze(-1))
            step_scatter = (x_next.transpose(-1, -2) @ x_next - q.transpose(-1, -2) @ xbar) / M
        s = c.mul_(1.0 / M)
        if not masked:
            self.parts.append((sl.start, step_scatter.sum(0)))
            if not self.all_valid:  # else ``trans_w`` is a view of ``ws``: written already
                ws[sl] = s
        else:
            self.parts.append((sl.start, torch.where(valid.view(t, B, 1, 1), step_scatter, 0.0).sum(0)))
            ws[sl] = torch.where(valid.unsqueeze(-1), s, torch.exp(logW[sl]))
            trans_w[sl] = torch.where(valid.unsqueeze(-1), s, 0.0)
            next_mean[sl] = xbar

    def finish(self) -> SmootherOutput:
        """The smoother output (every step added)."""
        _, B, _, nx = self.X.shape
        scatter = torch.zeros(B, nx, nx, dtype=self.X.dtype, device=self.X.device)
        for _, part in sorted(self.parts, key=lambda p: p[0]):
            scatter += part
        return SmootherOutput(None, self.next_mean, self.trans_w, scatter, self.ws)


@torch.no_grad()
def backward_trajectories(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    n_trajectories: int,
    *,
    max_tries: int = 8,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Indices of ``M`` trajectories drawn from the particle approximation of the joint smoothing
    distribution ``p(x_{0:T-1} | y)`` (backward simulation, Godsill, Doucet & West 2004).

    Each backward index is drawn exactly from the backward kernel
    ``W_k^i N(x_{k+1}^j; f(x_k^i, u_k), Rw)`` by rejection: ``max_tries`` proposals from the filter
    weights, all drawn and tested at once (a handful of operations per step), the first accepted
    one kept; an index with none accepted is drawn exactly (``O(L)``).  The trajectories are
    independent draws, in ``O(T (L + M max_tries))`` time.  Where a sequence has ended (padding) the
    index restarts from the filter.  :func:`backward_segments` draws pieces of trajectories.

    Parameters
    ----------
    model, data, filt
        As for :func:`ffbsm`.
    n_trajectories : int
        Number ``M`` of trajectories.
    max_tries : int
        Rejection proposals per index before the exact draw.
    generator : torch.Generator, optional

    Returns
    -------
    Tensor, shape (T, B, M), long
        ``J[k, b, m]``: the particle of sequence ``b`` at time ``k`` on trajectory ``m``.
    """
    T = filt.particles.shape[0]
    return backward_segments(
        model, data, filt, n_trajectories, [0], T, max_tries=max_tries, generator=generator
    )[0]


@torch.no_grad()
def backward_segments(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    n_trajectories: int,
    starts,
    length: int,
    *,
    log_weights: Tensor | None = None,
    max_tries: int = 8,
    generator: torch.Generator | None = None,
) -> Tensor:
    """``M`` draws of the pieces ``x_{a:a+length-1}`` of smoothed trajectories, for each start ``a``
    in ``starts``, all pieces drawn backward together (one loop of ``length`` steps, not ``T``).

    The joint smoothing distribution of a piece is ``p(x_b | y) prod_{k=a}^{b-1} p(x_k | x_{k+1},
    y_{0:k})`` (``b = a + length - 1``): its last index is drawn from the marginal smoothing weights
    ``log_weights[b]`` (an E-step's ``W_{b|N}``; FFBSm's are the exact marginals of the particle
    approximation), the others by backward simulation exactly as :func:`backward_trajectories`
    (rejection with ``max_tries`` proposals from the filter weights, then the exact ``O(L)`` draw).
    A piece ending at ``T - 1`` starts from the filter weights, which are the smoothing weights there.

    Parameters
    ----------
    model, data, filt
        As for :func:`ffbsm`.
    n_trajectories : int
        Number ``M`` of draws per piece.
    starts : sequence of int
        First step of each piece; ``start + length <= T``.
    length : int
    log_weights : Tensor, shape (T, B, L), optional
        Marginal smoothing log-weights for the pieces' last steps (required unless every piece ends
        at ``T - 1``).
    max_tries : int
    generator : torch.Generator, optional

    Returns
    -------
    Tensor, shape (len(starts), length, B, M), long
        ``J[s, i, b, m]``: the particle of sequence ``b`` at time ``starts[s] + i`` on draw ``m``.
    """
    X, logW = filt.particles, filt.log_weights
    T, B, L, nx = X.shape
    M, S, n = int(n_trajectories), max(1, int(max_tries)), int(length)
    device = X.device
    first = torch.as_tensor(list(starts), dtype=torch.long, device=device)
    G = first.numel()
    if G == 0 or n < 1 or int(first.min()) < 0 or int(first.max()) + n > T:
        raise ValueError(f"pieces of length {n} at {list(starts)} do not fit in {T} steps")
    if S > 53:
        raise ValueError(f"max_tries must be at most 53, got {max_tries}")
    ends = first + n - 1
    if log_weights is None:
        if bool((ends != T - 1).any()):
            raise ValueError(
                "log_weights (the marginal smoothing weights) are needed for pieces ending before T - 1"
            )
        log_weights = logW
    Js = torch.empty(G, n, B, M, dtype=torch.long, device=device)  # ordinary: made outside the region
    # the loop in inference mode (no autograd bookkeeping on its ~50 small operations a step, most
    # of the sampler's time at M = 200); it only writes into Js and nothing it makes escapes
    with torch.inference_mode():
        _backward_segments_loop(
            Js, model, data, X, logW, log_weights, first, ends, S, L, nx, generator
        )
    return Js


def _backward_segments_loop(
    Js: Tensor, model, data, X, logW, log_weights, first, ends, S: int, L: int, nx: int, generator
) -> None:
    """The draws of :func:`backward_segments`, written into ``Js`` ``(G, n, B, M)``."""
    G, n, B, M = Js.shape
    device = X.device
    Cinv_t = whitening(model, B, X)
    trans = data.transition_mask
    GB = G * B
    J_next = _draw(log_weights[ends], M, generator)  # (G, B, M)
    Js[:, n - 1] = J_next
    J_next = J_next.view(GB, M)
    # the tries come in rounds: S1 for every index, drawn for blocks of steps before the loop, then
    # rounds of twice as many as the last for the indices none of the earlier ones accepted, drawn
    # in the loop (with acceptance rates about 0.4-0.5 the first round leaves a tenth; a try costs
    # ~100x less than an exact O(L) draw)
    S1 = min(S, _FIRST_TRIES)
    S2 = S - S1
    bits = torch.pow(2.0, torch.arange(S - 1, -1, -1, dtype=torch.float64, device=device))  # exact in float64
    rows_offset = torch.arange(GB, dtype=X.dtype, device=device).unsqueeze(-1)  # (GB, 1)
    table = _first_try_table(S1, device)
    for blk in reversed(list(time_blocks(n - 1, GB * max(L, M * S1)))):
        t = blk.stop - blk.start
        times = (first.unsqueeze(0) + torch.arange(blk.start, blk.stop, device=device).unsqueeze(1)).view(-1)
        # the steps of every piece, piece-major within a local step: (t, G * B, ...)
        fx = model.transition_steps(X[times], data.u[times])  # (t * G, B, L, nx)
        # reshape, not view: a module's transition_steps may return another memory layout (the
        # default goes through (B, t, ...) and back), which the elementwise whitening keeps
        zf = whitened(fx, Cinv_t).reshape(t, GB, L, nx)
        zx = whitened(X[times + 1], Cinv_t).reshape(t, GB, L, nx)
        lw = logW[times].view(t, GB, L)
        valid = trans[times].view(t, GB)
        any_invalid = (~valid).any(-1).tolist()
        cdf = cumulative_weights(lw)  # (t, GB, L)
        u = torch.rand(t * GB, M * S1, dtype=X.dtype, device=device, generator=generator)
        props = inverse_cdf(cdf.view(t * GB, L), u).view(t, GB, M * S1)  # proposals from the filter weights
        # accepted where |zx - zf|^2 < -2 log u: the thresholds for the whole block at once, from
        # single-precision uniforms as the MCMC pass's (_UNIFORM_DTYPE: an acceptance probability
        # set to 2^-24; half the cost of the doubles and their logarithms)
        limit = torch.rand(t, GB, M, S1, dtype=_UNIFORM_DTYPE, device=device, generator=generator)
        limit = limit.log_().mul_(-2.0)
        # the proposals' whitened predictions, gathered for the whole block at once
        if nx == 1:
            cand = torch.gather(zf[..., 0], 2, props).view(t, GB, M, S1)
        else:
            cand = torch.gather(zf, 2, props.unsqueeze(-1).expand(t, GB, M * S1, nx)).view(t, GB, M, S1, nx)
        props = props.view(t, GB, M, S1)
        # the rows' cumulative weights shifted by the row number: one increasing table, so that one
        # searchsorted draws for indices of any rows (the second round)
        flat_cdf = (cdf + rows_offset).view(t, GB * L) if S2 else None
        for i in range(t - 1, -1, -1):
            if nx == 1:
                x_next = torch.gather(zx[i, ..., 0], 1, J_next).unsqueeze(-1)  # (GB, M, 1)
                d = cand[i] - x_next
                accept = d.mul_(d).lt_(limit[i])  # (GB, M, S1), as 0 / 1
            else:
                x_next = torch.gather(zx[i], 1, J_next.unsqueeze(-1).expand(GB, M, nx))  # (GB, M, nx)
                accept = squared_norm(x_next.unsqueeze(-2) - cand[i]).lt_(limit[i])
            J, none = _first_accepted(props[i], accept, bits[-S1:], table)
            b_idx, m_idx = torch.nonzero(none, as_tuple=True)
            if b_idx.numel():
                # where the first round left most indices, the tries accept so rarely (a tiny process
                # noise) that the rounds are wasted: the exact draws at once
                left = S2 if b_idx.numel() <= _ROUNDS_MAX_LEFT * GB * M else 0
                S_r = S1
                if left:
                    zf_i = zf[i].reshape(GB * L, nx)
                    xn = x_next[b_idx, m_idx]  # (P, nx)
                while left and b_idx.numel():  # further rounds of tries, for these indices only
                    S_r = min(left, 2 * S_r)  # doubling: the indices left accept less often
                    left -= S_r
                    P = b_idx.numel()
                    u = torch.rand(2, P, S_r, dtype=X.dtype, device=device, generator=generator)
                    row = b_idx.unsqueeze(-1)
                    pos = torch.searchsorted(flat_cdf[i], u[0] + row.to(X.dtype), right=True)
                    prop = (pos - row * L).clamp_(0, L - 1)
                    c = zf_i[row * L + prop]  # (P, S_r, nx)
                    accept = 2.0 * torch.log(u[1]) < -squared_norm(xn.unsqueeze(1) - c)
                    J2, none2 = _first_accepted(prop, accept, bits[-S_r:])
                    J[b_idx, m_idx] = J2
                    q = torch.nonzero(none2).squeeze(-1)
                    b_idx, m_idx, xn = b_idx[q], m_idx[q], xn[q]
                if b_idx.numel():  # exact draws from the backward kernel
                    nxt = J_next[b_idx, m_idx]
                    J[b_idx, m_idx] = _exact_backward(zf[i], lw[i], zx[i], b_idx, nxt, generator)
            if any_invalid[i]:  # past a sequence's end: restart from the filter
                J = torch.where(valid[i].unsqueeze(-1), J, props[i, :, :, 0])
            Js[:, blk.start + i] = J.view(G, B, M)
            J_next = J


#: Rejection tries drawn for every index of :func:`backward_segments` before its loop; the rest of
#: ``max_tries`` are drawn in the loop, in rounds of twice as many each, for the indices not
#: settled yet.
_FIRST_TRIES = 4

#: The further rounds of tries of :func:`backward_segments` are skipped at a step where the first
#: round left more than this share of the indices (its acceptance below ~16 % a try): the manipulator's
#: tiny process noise leaves ~95 %, the test models ~15 %.
_ROUNDS_MAX_LEFT = 0.5


def _exact_backward(zf: Tensor, lw: Tensor, zx: Tensor, rows: Tensor, nxt: Tensor, generator) -> Tensor:
    """One exact draw from the backward kernel ``W_i exp(-|zx_j - zf_i|^2 / 2)`` per index, for
    indices of rows ``rows`` ``(P,)`` whose next particle is ``nxt`` ``(P,)`` (``zf``, ``zx``
    ``(R, L, nx)``, ``lw`` ``(R, L)``).

    The kernel depends on the index only through ``(row, next particle)``, and the indices left to
    the exact draw share few (measured: 263 indices, 54 distinct pairs a step on the linear test
    model, ``L = 200``): its ``O(L)`` table is built once per distinct pair, and each index draws
    from its pair's by a uniform of its own (one ``searchsorted`` over the tables laid end to end)."""
    R, L, nx = zf.shape
    P = rows.numel()
    if nx == 1 and P * L <= _EXACT_DIRECT_MAX:
        # one state and few indices: each its own O(L) table, directly (~10 operations against the
        # pairs' ~35, whose per-operation cost dominates at these sizes: 45 / 150 indices at
        # L = 200 took 43 / 107 us against 88 / 147 us; with two states the (P, L, 2) differences
        # cost more than they save: 203 against 157 us)
        d = zf[rows, :, 0] - zx[rows, nxt]
        logits = lw[rows].addcmul_(d, d, value=-0.5)
        cdf = logits.sub_(logits.amax(-1, keepdim=True)).exp_().cumsum_(-1)
        u = torch.rand(P, 1, dtype=cdf.dtype, device=cdf.device, generator=generator).mul_(cdf[:, -1:])
        return torch.searchsorted(cdf, u, right=True).clamp_(max=L - 1).squeeze(-1)
    pairs, which = torch.unique(rows * L + nxt, return_inverse=True)  # sorted: by row, then particle
    r, j = pairs // L, pairs % L
    U = pairs.numel()
    a = zx[r, j]  # (U, nx)
    # log W_i - |a - zf_i|^2 / 2 = a . zf_i + (log W_i - |zf_i|^2 / 2) - |a|^2 / 2, the last the same
    # for every i (the table is normalised): the first two by one batched product of each row's
    # pairs, padded to the most a row has and extended by a 1, against the row's predictions
    # extended by the pair-free part (no (U, L, nx) copy of them, one pass over the tables)
    base = lw - 0.5 * squared_norm(zf)  # (R, L)
    counts = torch.bincount(r, minlength=R)
    C = int(counts.max())
    if R * C <= 4 * U:
        slot = torch.arange(U, device=r.device) - (torch.cumsum(counts, 0) - counts)[r]
        A = torch.zeros(R, C, nx + 1, dtype=zf.dtype, device=zf.device)
        A[r, slot] = torch.cat([a, torch.ones_like(a[:, :1])], -1)
        logits = torch.bmm(A, torch.cat([zf, base.unsqueeze(-1)], -1).mT)[r, slot]  # (U, L)
    else:  # pairs crowded in a few of many rows: the rows' predictions gathered instead
        logits = torch.bmm(zf[r], a.unsqueeze(-1)).squeeze(-1).add_(base[r])
    # the tables' cumulative weights, normalised and laid end to end (row q in (q, q + 1]), in place
    cdf = logits.sub_(logits.amax(-1, keepdim=True)).exp_().cumsum_(-1)
    cdf.div_(cdf[:, -1:].clone())
    cdf.add_(torch.arange(U, dtype=cdf.dtype, device=cdf.device).unsqueeze(-1))
    u = torch.rand(rows.numel(), dtype=cdf.dtype, device=cdf.device, generator=generator)
    pos = torch.searchsorted(cdf.view(-1), u + which.to(cdf.dtype), right=True)
    return (pos - which * L).clamp_(0, L - 1)


#: Up to this many entries (indices x particles), :func:`_exact_backward` builds one table per index
#: directly instead of one per distinct (row, next particle) pair.
_EXACT_DIRECT_MAX = 1 << 16


def _first_accepted(
    props: Tensor, accept: Tensor, bits: Tensor, table: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """The first accepted of the tries ``props`` ``(..., S)`` (``accept`` likewise), and where none was.

    The first accepted is the highest bit of ``sum_s accept_s 2^(S-1-s)`` (``bits``, float64): a
    small product and ``frexp``, ~10x cheaper than ``argmax`` on a CPU; or, with ``table`` (the
    try of each code, :func:`_first_try_table`), one lookup (two operations fewer)."""
    S = props.shape[-1]
    code = accept.to(bits.dtype) @ bits
    if table is not None:
        tried = table[code.long()]
    else:
        tried = (S - torch.frexp(code).exponent).clamp_(0, S - 1).long()
    return torch.gather(props, -1, tried.unsqueeze(-1)).squeeze(-1), code == 0


def _first_try_table(S: int, device) -> Tensor:
    """For each code ``sum_s accept_s 2^(S-1-s)`` of ``S`` tries, the first accepted (0 for none)."""
    code = torch.arange(1 << S, device=device)
    first = torch.zeros(1 << S, dtype=torch.long, device=device)
    for s in range(S - 1, -1, -1):  # the last set wins: from the last try to the first
        first[(code >> (S - 1 - s)) & 1 == 1] = s
    return first
