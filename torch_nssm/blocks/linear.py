"""Linear ``f`` / ``g`` blocks, linear in their parameters (closed-form M-steps).

:class:`LinearTransition` and :class:`LinearObservation` are the reference models of
:func:`~torch_nssm.blocks.starts.distilled_start` and a fast first model of any system.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Union

import numpy as np
import torch
from torch import Tensor, nn

from .. import _validation as V
from .._ops import broadcast_leading, small_matmul
from ..core.parametric import LinearInParameters

__all__ = ["LinearTransition", "LinearObservation"]

ArrayLike = Union[Tensor, np.ndarray, Sequence, float, None]


def _matrix(
    value: ArrayLike, shape: tuple[int, int], name: str, default: np.ndarray, dtype, device
) -> Tensor:
    arr = default if value is None else V.check_matrix_array(value, name, shape)
    return torch.as_tensor(np.array(arr, dtype=np.float64), dtype=dtype, device=device)


def _kron_rows(z: Tensor, d: int) -> Tensor:
    """``Phi`` of shape ``(..., d, d * m)`` with ``Phi[..., i, i * m + j] = z[..., j]``, so that
    ``Phi @ M.reshape(-1) = z @ M.T`` for a ``(d, m)`` matrix ``M`` (row-major flattening)."""
    eye = torch.eye(d, dtype=z.dtype, device=z.device)
    m = z.shape[-1]
    return (eye[:, :, None] * z[..., None, None, :]).reshape(*z.shape[:-1], d, d * m)


def _affine(theta: Tensor, d: int, nx: int, nu: int, offset: bool) -> Callable[[Tensor, Tensor], Tensor]:
    """``(x, u) -> M x + N u (+ c)`` for ``theta = (M, N[, c])`` flattened row-major, ``(..., P)``
    broadcast against the rows' leading dimensions (tiny matrices: elementwise products)."""
    M = theta[..., : d * nx].unflatten(-1, (d, nx))
    N = theta[..., d * nx : d * (nx + nu)].unflatten(-1, (d, nu)) if nu else None
    c = theta[..., d * (nx + nu) : d * (nx + nu + 1)] if offset else None

    def affine(x: Tensor, u: Tensor) -> Tensor:
        out = small_matmul(M, x.unsqueeze(-1)).squeeze(-1)
        if N is not None:
            out = out + small_matmul(N, u.unsqueeze(-1)).squeeze(-1)
        return out if c is None else out + c

    return affine


class LinearTransition(LinearInParameters):
    """Linear transition ``f(x, u) = A x + B u (+ c)``: the default reference model of ``distilled_start``.

    Linear in ``theta = (A, B[, c])``, so the EM engine updates it in closed form (fast).

    Parameters
    ----------
    nx : int
        State dimension.
    nu : int
        Input dimension (0 for a system without input).
    A : array-like of shape (nx, nx) or float, optional
        Initial state matrix (a scalar means ``A * I``); default ``0.5 I``.
    B : array-like of shape (nx, nu) or float, optional
        Initial input matrix (a scalar fills it); default ``0.5`` everywhere.
    bias : bool, default=False
        Add a free offset ``c`` (initially 0).
    dtype : torch.dtype, default=torch.float64
    device : torch.device or str, optional

    Attributes
    ----------
    A, B : nn.Parameter
    c : nn.Parameter, only with ``bias=True``
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        *,
        A: ArrayLike = None,
        B: ArrayLike = None,
        bias: bool = False,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.nx = V.check_positive(nx, "nx", integer=True, minimum=1, inclusive=True)
        self.nu = V.check_positive(nu, "nu", integer=True, minimum=0, inclusive=True)
        kw = dict(dtype=dtype, device=device)
        self.A = nn.Parameter(_matrix(A, (nx, nx), "A", 0.5 * np.eye(nx), **kw))
        self.B = nn.Parameter(_matrix(B, (nx, nu), "B", np.full((nx, nu), 0.5), **kw))
        self.bias = bool(bias)
        if self.bias:
            self.c = nn.Parameter(torch.zeros(nx, **kw))

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        # the same function as features() @ theta, without building the Kronecker features (the
        # particle filter calls f at every step; the M-step's normal equations use features())
        out = x @ self.A.T + u @ self.B.T
        return out + self.c if self.bias else out

    def frozen_predict(self, theta: Tensor) -> Callable[[Tensor, Tensor], Tensor]:
        """``A x + B u (+ c)`` at ``theta`` ``(..., P)`` (e.g. one row per stacked sequence), its
        matrices taken once per pass: :meth:`predict` would build the Kronecker features at every
        filter step."""
        return _affine(theta, self.nx, self.nx, self.nu, self.bias)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` of shape ``(..., nx, P)`` over ``(A, B[, c])`` and a zero offset ``(..., nx)``."""
        x, u = broadcast_leading(x, u)
        blocks = [_kron_rows(x, self.nx), _kron_rows(u, self.nx)]
        if self.bias:
            blocks.append(torch.eye(self.nx, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], -1, -1))
        return torch.cat(blocks, dim=-1), torch.zeros_like(x)

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}, bias={self.bias}"


class LinearObservation(LinearInParameters):
    """Linear observation ``g(x, u) = C x + D u + d``: the reference of an MLP observation.

    Parameters
    ----------
    nx : int
        State dimension.
    nu : int
        Input dimension (0 for a system without input, or when ``g`` ignores ``u``).
    p : int
        Number of outputs.
    C : array-like of shape (p, nx) or float, optional
        Initial output matrix; default ones on the diagonal ``C[i, i]`` and zeros elsewhere.
    D : array-like of shape (p, nu) or float, optional
        Initial feed-through; default zeros.
    d : array-like of shape (p,) or float, optional
        Initial offset; default zeros.
    feedthrough : bool, default=False
        Estimate ``D`` (otherwise it is held fixed at its initial value).
    fit_offset : bool, default=True
        Estimate ``d``; ``False`` holds it at its initial value (zero by default), e.g. for
        outputs known to be centred.
    dtype : torch.dtype, default=torch.float64
    device : torch.device or str, optional
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        p: int,
        *,
        C: ArrayLike = None,
        D: ArrayLike = None,
        d: ArrayLike = None,
        feedthrough: bool = False,
        fit_offset: bool = True,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.nx = V.check_positive(nx, "nx", integer=True, minimum=1, inclusive=True)
        self.nu = V.check_positive(nu, "nu", integer=True, minimum=0, inclusive=True)
        self.p = V.check_positive(p, "p", integer=True, minimum=1, inclusive=True)
        kw = dict(dtype=dtype, device=device)
        self.C = nn.Parameter(_matrix(C, (p, nx), "C", np.eye(p, nx), **kw))
        self.D = nn.Parameter(
            _matrix(D, (p, nu), "D", np.zeros((p, nu)), **kw), requires_grad=bool(feedthrough)
        )
        off = np.zeros(p) if d is None else V.check_vector_array(d, "d", p)
        self.d = nn.Parameter(torch.as_tensor(off, **kw), requires_grad=bool(fit_offset))

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        # features() @ theta without the Kronecker features, as LinearTransition.forward
        return x @ self.C.T + u @ self.D.T + self.d

    def frozen_predict(self, theta: Tensor) -> Callable[[Tensor, Tensor], Tensor]:
        """``C x + D u + d`` at ``theta`` ``(..., P)``, its matrices taken once per pass (as
        :meth:`LinearTransition.frozen_predict`)."""
        return _affine(theta, self.p, self.nx, self.nu, True)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` of shape ``(..., p, P)`` over ``(C, D, d)`` and a zero offset ``(..., p)``."""
        x, u = broadcast_leading(x, u)
        eye = torch.eye(self.p, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], -1, -1)
        Phi = torch.cat([_kron_rows(x, self.p), _kron_rows(u, self.p), eye], dim=-1)
        return Phi, x.new_zeros(*x.shape[:-1], self.p)

    def extra_repr(self) -> str:
        return (
            f"nx={self.nx}, nu={self.nu}, p={self.p}, feedthrough={self.D.requires_grad}, "
            f"fit_offset={self.d.requires_grad}"
        )
