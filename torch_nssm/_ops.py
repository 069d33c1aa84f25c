"""Elementwise forms of tiny linear-algebra operations on huge batches.

The engine works on millions of rows with 1-4 components each.  A reduction or matrix product
over such a tiny last dimension is dominated by per-element overhead in PyTorch's CPU kernels
(``(Phi * theta).sum(-1)`` with two terms is 6x slower than two multiply-adds); these
helpers spell the small dimension out instead.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "squared_norm",
    "linear_combination",
    "small_matmul",
    "broadcast_leading",
    "time_blocks",
    "inverse_cholesky",
]

#: Rows (time steps x sequences x particles) per block of the whole-record passes that follow the
#: filter and smoother (latent scales, M-step sums): each block's temporaries stay in cache, where
#: streaming whole ``(T, B, L)`` arrays through memory once per operation is 2-5x
#: slower on a 2-core CPU.
BLOCK_ROWS = 1 << 17

#: Up to this many terms, a reduction over the last dimension is unrolled into multiply-adds.
_UNROLL = 8


def squared_norm(z: Tensor) -> Tensor:
    """``(z * z).sum(-1)``."""
    return linear_combination(z, z)


def linear_combination(Phi: Tensor, theta: Tensor) -> Tensor:
    """``(Phi * theta).sum(-1)`` with broadcasting: ``Phi`` ``(..., P)``, ``theta`` ``(..., P)``."""
    P = Phi.shape[-1]
    if 0 < P <= _UNROLL:
        out = Phi[..., 0] * theta[..., 0]
        for i in range(1, P):
            out = out + Phi[..., i] * theta[..., i]
        return out
    return (Phi * theta).sum(-1)


def small_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for huge batches of tiny matrices ``(..., n, k) @ (..., k, m)``, elementwise."""
    return linear_combination(a.unsqueeze(-1).transpose(-1, -2), b.transpose(-1, -2).unsqueeze(-3))


def broadcast_leading(x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Expand ``x`` ``(..., nx)`` and ``u`` ``(..., nu)`` to common leading dimensions (views)."""
    if x.shape[:-1] == u.shape[:-1]:  # the usual case; torch.broadcast_shapes costs ~0.1 ms
        return x, u
    lead = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    return x.expand(lead + x.shape[-1:]), u.expand(lead + u.shape[-1:])


def time_blocks(T: int, rows_per_step: int, max_rows: int = BLOCK_ROWS):
    """Slices of consecutive time steps holding about ``max_rows`` rows each (at least one step)."""
    step = max(1, max_rows // max(1, rows_per_step))
    for start in range(0, T, step):
        yield slice(start, min(start + step, T))


def inverse_cholesky(S: Tensor) -> Tensor:
    """``C`` with ``C^T C = S^-1``: the inverse of the lower Cholesky factor of ``S`` ``(..., n, n)``."""
    chol = torch.linalg.cholesky(S)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device).expand_as(chol)
    return torch.linalg.solve_triangular(chol, eye, upper=False)
