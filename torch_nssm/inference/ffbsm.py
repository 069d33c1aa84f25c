"""Forward-filtering backward-smoothing (FFBSm): the marginal particle smoother and the
statistics every smoother returns (:class:`SmootherOutput`), for the EM M-step (docs/method.md §3-4).

The exact forward-filtering backward-smoothing (FFBSm) recursion uses the full ``L x L`` pairwise
weights (not the paper's diagonal eq. 24), but never stores them: with ``C = chol(Q)``,
``z_f^i = C^-1 f(x_k^i, u_k)`` and ``z_x^j = C^-1 x_{k+1}^j``, the backward kernel

    K^{ij} = softmax_i(log W_k^i - |z_f^i|^2 / 2 + z_x^j . z_f^i)

is built from one batched matmul (the part that depends on ``j`` only cancels), the pairwise
weights are ``W^{ij} = K^{ij} W_{k+1|N}^j`` and everything the M-step needs is a mat-vec:

    W_{k|N}^i = sum_j K^{ij} W_{k+1|N}^j
    m_k^i     = sum_j K^{ij} W_{k+1|N}^j x_{k+1}^j

The kernels depend on the filter alone: they are built for blocks of time steps (or chunks of rows
of one step's) of at most :data:`KERNEL_BLOCK` entries, in single precision by default, and the
backward recursion is one small product per step; memory is ``O(KERNEL_BLOCK)`` beyond the
``(T, B, L)`` statistics.

Backward simulation (FFBSi) is in :mod:`torch_nssm.inference.ffbsi`; both return a
:class:`SmootherOutput`, the statistics every smoother gives the M-step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .. import _workspace
from .._ops import inverse_cholesky, small_matmul, squared_norm, time_blocks
from ..core.model import SequenceBatch, StateSpaceModel
from .filtering import FilterOutput

__all__ = [
    "SmootherOutput",
    "ffbsm",
    "smoothed_moments",
    "TINY_WEIGHT",
]

#: Smoothing weights below this are set to zero: products of such weights are denormal numbers,
#: which slow CPU mat-vecs about 17x (docs/method.md §7), and they carry no information.
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
        ``sum_k [S_{k+1} - sum_i m_k^i m_k^i^T / s_k^i]`` (docs/method.md §7: it must not be dropped).
    weights : Tensor, shape (T, B, L), optional
        ``exp(log_weights)``, where the smoother has it exactly at no cost (the trajectory
        smoothers: counts over ``M``); the M-step reads it instead of taking ``exp`` of the
        log-weights twice per pass (``exp`` of the many ``-inf`` is ~3x slower than of a finite
        value on a CPU).  ``None``: take ``exp(log_weights)``.  Where a smoother gives only the
        weights (``log_weights`` passed as ``None``), ``log_weights`` is their ``log``, taken when
        first read: the EM loop reads only the weights, and a ``(T, B, L)`` array written per
        E-step costs ~25 ms of memory traffic alone at the Table 1 size.
    """

    log_weights: Tensor | None  # a property over ``_log_weights`` (below the class)
    next_mean: Tensor
    transition_weights: Tensor
    residual_scatter: Tensor
    weights: Tensor | None = None

    def weights_of(self, index) -> Tensor:
        """``W_{k|N}`` of the steps ``index`` (an int or a slice): ``weights[index]`` where the
        smoother has them (a view: not to be modified in place), else ``exp`` of the log-weights
        (so that reading the weights never computes the lazy log-weights of every step)."""
        return self.weights[index] if self.weights is not None else torch.exp(self.log_weights[index])

    def select(self, index) -> SmootherOutput:
        """The smoother output of the sequences ``index``."""
        return SmootherOutput(
            None if self._log_weights is None else self._log_weights[:, index],
            self.next_mean[:, index],
            self.transition_weights[:, index],
            self.residual_scatter[index],
            None if self.weights is None else self.weights[:, index],
        )


def _lazy_log_weights(self: SmootherOutput) -> Tensor:
    if self._log_weights is None:
        self._log_weights = torch.log(self.weights)
    return self._log_weights


def _set_log_weights(self: SmootherOutput, value: Tensor | None) -> None:
    self._log_weights = value


# Installed after the dataclass is made, so that ``log_weights`` stays its first field (positional
# and keyword construction, ``dataclasses.replace``) while reading it takes the log of ``weights``
# when only those were given.
SmootherOutput.log_weights = property(
    _lazy_log_weights, _set_log_weights, doc="Log marginal smoothing weights ``(T, B, L)``."
)


def _chunks(n: int, size: int):
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


#: Entries of the ``L x L`` backward kernel processed at once (the kernels of several time steps,
#: or a chunk of rows of one step's): 1 million, 4 MB in single precision, which stays in cache
#: (measured on a 2-core CPU: blocks of 4 million entries were 1.6-2x slower per entry).
KERNEL_BLOCK = 1 << 20

_LOG2E = 1.4426950408889634
#: A kernel row whose sum (relative to the row's upper bound) is below this lost its precision to
#: underflow and is recomputed exactly (2^-96: its largest entry is ~30 binary orders above the
#: single-precision denormals).
_ROW_SUM_FLOOR = 2.0**-96


@torch.no_grad()
def ffbsm(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    *,
    chunk_size: int | None = None,
    kernel_dtype: torch.dtype | None = torch.float32,
) -> SmootherOutput:
    """Forward-filtering backward-smoothing (marginal and pairwise), exact, ``O(T L^2)``.

    The backward kernels ``K_k`` depend on the filter alone, so they are built for blocks of time
    steps at once (see :func:`_backward_kernels`); the backward recursion is one small matrix
    product per step, and everything derived from ``s`` and ``m`` (``xbar``, the process scatter)
    is computed after it, for all steps together.

    Parameters
    ----------
    model : StateSpaceModel
        The model the filter ran with (its ``f`` and ``Rw`` define the backward kernel).
    data : SequenceBatch
    filt : FilterOutput
    chunk_size : int, optional
        Number of ``x_{k+1}`` particles (kernel rows) processed at once; by default the kernels of
        as many steps, or as many rows of one step's kernel, as fit in :data:`KERNEL_BLOCK`
        entries.
    kernel_dtype : torch.dtype, optional
        Precision of the ``L x L`` kernel and of its products (``None``: the particles' dtype).
        Single precision (the default) halves the memory traffic of the dominant ``O(L^2)`` work;
        the states are centred on each step's filter mean before whitening, so the exponents
        carry no cancellation from large state values, and every statistic derived from the
        products is accumulated in the particles' dtype; a block of steps whose whitened
        distances exceed :data:`SINGLE_KERNEL_LIMIT` gets its kernel in the particles' dtype.
        Relative rounding ~1e-7, far below the Monte Carlo error ``O(1/sqrt(L))``
        (tests/inference/test_filter_smoother.py compares both).

    Returns
    -------
    SmootherOutput
    """
    X, logW = filt.particles, filt.log_weights
    T, B, L, nx = X.shape
    dtype, device = X.dtype, X.device
    kdtype = dtype if kernel_dtype is None else kernel_dtype
    rows = min(L, chunk_size or max(1, KERNEL_BLOCK // max(1, B * L)))
    whole = rows >= L  # whole kernels of one or more steps per block, else chunks of rows
    Cinv_t = whitening(model, B, X)
    trans = data.transition_mask  # (T-1, B)

    log_ws = _workspace.empty(logW.shape, logW.dtype, logW.device)  # every entry written below
    log_ws[T - 1] = logW[T - 1]
    # [s, m^T] of every step (T-1, B, 1 + nx, L), m about the step's centre c (centres)
    sm_all = torch.empty(T - 1, B, 1 + nx, L, dtype=kdtype, device=device)
    centres = torch.empty(T - 1, B, 1, nx, dtype=dtype, device=device)
    entries = B * L * (L * min(T - 1, max(1, KERNEL_BLOCK // (B * L * L))) if whole else rows)
    workspace = torch.empty(entries, dtype=kdtype, device=device)  # every block's E, reused
    with torch.inference_mode():  # writes only into ``centres``, ``sm_all`` and ``log_ws``
        for blk in reversed(list(time_blocks(T - 1, B * L * L if whole else KERNEL_BLOCK, KERNEL_BLOCK))):
            zf, zx, centre = whitened_steps(model, data, X, logW, Cinv_t, blk)
            centres[blk] = centre
            a = logW[blk] - 0.5 * squared_norm(zf)  # (t, B, L)
            # rows [w_j, w_j (x_j - c)^T]: one product with the kernel gives s and m together, and
            # multiplying from the left reads K in its stored layout (no transposed copy)
            kd = kdtype if _fits_kernel_dtype(zf, zx, kdtype, dtype) else dtype  # this block's precision
            if kd != sm_all.dtype and kd == dtype:  # s and m too: the process scatter subtracts them
                sm_all = sm_all.to(dtype)  # from the next states' scatter, nearly equal here
            space = workspace if kd == kdtype else None
            dx = (X[blk.start + 1 : blk.stop + 1] - centre).to(kd).transpose(-1, -2)  # (t, B, nx, L)
            if whole:
                # (t, B, L, L), (t, B, L)
                K, inv_d = _backward_kernels(a, zf, zx, logW[blk], kd, space)
            for k in range(blk.stop - 1, blk.start - 1, -1):
                i = k - blk.start
                w = torch.exp(log_ws[k + 1])
                w = torch.where(w < TINY_WEIGHT, 0.0, w).to(kd).unsqueeze(1)  # (B, 1, L)
                wx = torch.cat([w, w * dx[i]], 1)  # (B, 1 + nx, L)
                if whole and kd == sm_all.dtype:
                    torch.bmm(wx * inv_d[i].unsqueeze(1), K[i], out=sm_all[k])
                elif whole:
                    sm_all[k] = torch.bmm(wx * inv_d[i].unsqueeze(1), K[i])
                else:
                    sm = torch.zeros(B, 1 + nx, L, dtype=kd, device=device)
                    for sl in _chunks(L, rows):
                        Kc, inv_dc = _backward_kernels(a[i], zf[i], zx[i][:, sl], logW[k], kd, space)
                        sm = torch.baddbmm(sm, wx[:, :, sl] * inv_dc.unsqueeze(1), Kc)
                    sm_all[k] = sm
                log_s = torch.log(sm_all[k, :, 0].to(dtype))
                log_s = log_s - torch.logsumexp(log_s, dim=-1, keepdim=True)  # guard rounding drift
                log_ws[k] = torch.where(trans[k].unsqueeze(-1), log_s, logW[k])
    return _pairwise_statistics(data, X, log_ws, sm_all, centres)


#: Largest squared whitened norm of a block's predictions and next states for a single-precision
#: kernel: its exponent's terms reach that size, and their rounding (~6e-8 of them) stays below
#: ~1e-2 in a log-weight.  A block beyond it (a first-state prior far broader than the process
#: noise, a process noise far smaller than the states' spread) gets its kernel in the particles'
#: precision: a whitened distance of 1e4 (squared 1e8) makes single-precision weights meaningless.
SINGLE_KERNEL_LIMIT = 2.0**16


def _fits_kernel_dtype(zf: Tensor, zx: Tensor, kdtype: torch.dtype, dtype: torch.dtype) -> bool:
    """Whether a block's kernel may be computed in ``kdtype`` (always when it is the particles'
    ``dtype``; a single-precision one within :data:`SINGLE_KERNEL_LIMIT`)."""
    if kdtype == dtype or torch.finfo(kdtype).bits >= 64:
        return True
    big = torch.maximum(squared_norm(zf).amax(), squared_norm(zx).amax())
    return bool(big <= SINGLE_KERNEL_LIMIT)


def _backward_kernels(
    a: Tensor, zf: Tensor, zx: Tensor, logW: Tensor, kdtype: torch.dtype, workspace: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Backward kernels ``K^{ji} = softmax_i(a_i + z_x^j . z_f^i)`` as unnormalised rows and their
    inverse row sums: ``E`` ``(..., J, L)`` and ``1 / sum_i E^{ji}`` ``(..., J)``, so that
    ``K = E / sum_i E`` (the division is applied to the small left factor of the next product).

    On the CPU the rows are shifted by an upper bound of their maximum instead of the maximum
    itself (no extra pass over ``E``): ``a_i + z_x^j . z_f^i <= max_i log W_i + |z_x^j|^2 / 2``,
    and the whole exponent is one matrix product with two extra columns, in base 2 (``exp2`` is
    ~4x cheaper than ``exp`` in single precision).  A row whose sum falls below
    :data:`_ROW_SUM_FLOOR` (all of it far below the bound: rare, a particle no prediction
    reaches) is recomputed exactly with the row maximum, and so is a row whose sum is not finite
    (the rounding of a single-precision exponent of huge whitened distances overflows).  On other
    devices (GPUs, where the passes are cheap and a data-dependent fix-up would cost a host
    synchronisation) it is the softmax itself.

    Parameters
    ----------
    a : Tensor, shape (..., L)
        ``log W_k^i - |z_f^i|^2 / 2`` (particles' dtype).
    zf : Tensor, shape (..., L, nx)
    zx : Tensor, shape (..., J, nx)
    logW : Tensor, shape (..., L)
        The filter's log-weights (for the bound).
    kdtype : torch.dtype
    workspace : Tensor, optional
        A flat buffer of at least ``J * L`` times the batch entries that ``E`` is written into
        (CPU): a fresh 4 MB ``E`` per step cost more in page faults than its matrix product.
    """
    if zf.device.type != "cpu":
        logits = torch.baddbmm(
            a.reshape(-1, 1, a.shape[-1]).to(kdtype),
            zx.reshape(-1, *zx.shape[-2:]).to(kdtype),
            zf.reshape(-1, *zf.shape[-2:]).to(kdtype).mT,
        )
        K = torch.softmax(logits, dim=-1).view(*zx.shape[:-1], a.shape[-1])
        return K, torch.ones(K.shape[:-1], dtype=kdtype, device=K.device)
    bound = logW.amax(-1, keepdim=True) + 0.5 * squared_norm(zx)  # (..., J)
    ones_f = torch.ones_like(a).unsqueeze(-2)
    ones_x = torch.ones_like(bound).unsqueeze(-1)
    left = torch.cat([zx * _LOG2E, -_LOG2E * bound.unsqueeze(-1), ones_x], -1).to(kdtype)  # (..., J, nx+2)
    # (..., nx+2, L), built in this layout: a product with a transposed view is 3.5x slower
    right = torch.cat([zf.mT, ones_f, _LOG2E * a.unsqueeze(-2)], -2).to(kdtype)
    left, right = left.reshape(-1, *left.shape[-2:]), right.reshape(-1, *right.shape[-2:])
    out = None
    if workspace is not None:
        n_rows, n_cols = left.shape[0] * left.shape[1], right.shape[2]
        out = workspace[: n_rows * n_cols].view(left.shape[0], -1, n_cols)
    E = torch.exp2_(torch.bmm(left, right, out=out)).view(*zx.shape[:-1], a.shape[-1])
    d = E.sum(-1)
    # a row far below its bound (underflow), or above it: the single-precision exponent carries a
    # rounding error of ~1e-7 times its terms, which at whitened distances of ~1e4 and more (a broad
    # first-state prior against a small process noise) exceeds the exponent range and gives inf
    low = torch.nonzero((~((d >= _ROW_SUM_FLOOR) & torch.isfinite(d))).view(-1)).squeeze(-1)  # flat rows
    if low.numel():
        J, L = zx.shape[-2], a.shape[-1]
        batch = low // J  # the kernel (step, sequence) each row belongs to
        logits = a.reshape(-1, L)[batch] + (
            zf.reshape(-1, L, zf.shape[-1])[batch] @ zx.reshape(-1, zx.shape[-1])[low].unsqueeze(-1)
        ).squeeze(-1)
        E.view(-1, L)[low] = torch.softmax(logits, dim=-1).to(kdtype)  # in full precision
        d.view(-1)[low] = 1.0
    return E, 1.0 / d


def whitened_steps(
    model: StateSpaceModel,
    data: SequenceBatch,
    X: Tensor,
    logW: Tensor,
    Cinv_t: Tensor,
    blk: slice,
    centred: bool = True,
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Whitened predictions ``z_f = C^-1 (f(x_k^i) - c)`` and next states ``z_x = C^-1 (x_{k+1}^j -
    c)`` of the steps ``blk`` (t, B, L, nx each), and ``c`` (t, B, 1, nx).

    With ``centred``, ``c_k`` is the filter mean of ``x_{k+1}``: differences ``z_x - z_f`` are
    unchanged by the common shift, and the centring keeps FFBSm's expanded exponent
    ``z_x . z_f - |z_f|^2 / 2`` free of cancellation when states are far from 0.  The trajectory
    smoothers use only the differences and skip it (``c = None``).
    """
    X_next = X[blk.start + 1 : blk.stop + 1]
    fx = model.transition_steps(X[blk], data.u[blk])
    if not centred:
        return whitened(fx, Cinv_t), whitened(X_next, Cinv_t), None
    w = torch.softmax(logW[blk.start + 1 : blk.stop + 1], dim=-1).unsqueeze(-1)
    c = (w * X_next).sum(-2, keepdim=True)
    return whitened(fx - c, Cinv_t), whitened(X_next - c, Cinv_t), c


def _pairwise_statistics(
    data: SequenceBatch, X: Tensor, log_ws: Tensor, sm_all: Tensor, centres: Tensor
) -> SmootherOutput:
    """``xbar``, the transition weights and the process scatter from FFBSm's ``s`` and ``m``.

    ``m`` is about the centre ``c_k`` of each step (:func:`whitened_steps`); the scatter is
    computed in centred form, ``sum_j w_j d_j d_j^T - sum_i s_i e_i e_i^T`` with ``d = x - c``,
    ``e = xbar - c`` (the same quantity: ``sum_i K^{ij} = 1``), so nothing of size ``|c|^2``
    cancels.  Done for blocks of steps after the backward pass.
    """
    T, B, L, nx = X.shape
    dtype = X.dtype
    trans = data.transition_mask
    next_mean = _workspace.empty((T - 1, B, L, nx), dtype, X.device)  # every block written below
    trans_w = _workspace.empty((T - 1, B, L), dtype, X.device)
    scatter = torch.zeros(B, nx, nx, dtype=dtype, device=X.device)
    for blk in time_blocks(T - 1, B * L):
        nxt = slice(blk.start + 1, blk.stop + 1)
        valid = trans[blk]  # (t, B)
        centre = centres[blk]  # (t, B, 1, nx)
        sm = sm_all[blk].to(dtype)
        s, e = sm[:, :, 0], sm[:, :, 1:].transpose(-1, -2)  # (t, B, L), (t, B, L, nx)
        pos = s > 0
        e = torch.where(pos.unsqueeze(-1), e / torch.where(pos, s, 1.0).unsqueeze(-1), X[blk] - centre)
        s = s / s.sum(-1, keepdim=True)  # sums to 1 like W_{k|N} (the kernel's rounding aside)
        w_next = torch.exp(log_ws[nxt])
        w_next = torch.where(w_next < TINY_WEIGHT, 0.0, w_next).unsqueeze(-1)
        d = X[nxt] - centre
        S_next = (w_next * d).transpose(-1, -2) @ d  # (t, B, nx, nx)
        MmT = (s.unsqueeze(-1) * e).transpose(-1, -2) @ e
        scatter += torch.where(valid.view(*valid.shape, 1, 1), S_next - MmT, 0.0).sum(0)
        next_mean[blk] = e + centre
        trans_w[blk] = torch.where(valid.unsqueeze(-1), s, 0.0)
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


def whitening(model: StateSpaceModel, B: int, like: Tensor) -> Tensor:
    """Transpose of the inverse Cholesky factor of ``Rw``, shape (B, nx, nx)."""
    return inverse_cholesky(model.per_sequence("Rw", B).to(like.dtype)).transpose(-1, -2)


def whitened(x: Tensor, Cinv_t: Tensor) -> Tensor:
    """``x @ Cinv_t`` for ``x`` ``(..., B, L, nx)`` and ``Cinv_t`` ``(B, nx, nx)``, elementwise."""
    return small_matmul(x.unsqueeze(-2), Cinv_t.unsqueeze(-3)).squeeze(-2)
