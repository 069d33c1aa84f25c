"""Working scales of the parameters: unconstrained coordinates for the observed information and for
the squared extrapolation of the noise parameters.

A :class:`WorkingScale` maps a parameter's natural value (a covariance, a positive number, ...) to
the coordinates in which its standard errors are computed (normal approximations are better
there) and back, names those coordinates, and gives the coordinates in which
:class:`~torch_nssm.estimation.acceleration.NoiseExtrapolation` jumps.  The noise families declare
one per parameter (``MeasurementNoise.WORKING``); a family with a parameter on another domain
defines its own scale next to it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "WorkingScale",
    "PLAIN",
    "LOG",
    "LOG_DIAGONAL",
    "LOG_CHOLESKY",
    "cholesky_and_inverse",
    "log_cholesky_scores",
]


def _label(index: tuple[int, ...]) -> str:
    return f"[{', '.join(map(str, index))}]"


def _flat_index(value: Tensor) -> list[tuple[int, ...]]:
    shape = tuple(value.shape)
    return [tuple(int(j) for j in np.unravel_index(i, shape)) for i in range(value.numel())]


class WorkingScale:
    """How a parameter is put on its working scale.  The default is the identity (``PLAIN``)."""

    #: Short name (``repr``).
    kind = "plain"
    #: Whether the parameter is a symmetric matrix whose natural entries are its lower triangle
    #: (an off-diagonal entry's value belongs in both its places).
    symmetric = False

    def __repr__(self) -> str:
        return self.kind.upper()

    def n_working(self, value: Tensor) -> int:
        """Number of working coordinates of ``value``."""
        return value.numel()

    def to_working(self, value: Tensor) -> Tensor:
        """The working coordinates of ``value``, flat."""
        return value.reshape(-1)

    def from_working(self, w: Tensor, value: Tensor) -> Tensor:
        """The natural value at working coordinates ``w`` (``value``: the parameter, for its shape)."""
        return w.reshape(value.shape)

    def natural_entries(self, value: Tensor) -> Tensor:
        """The free entries on the natural scale, flat."""
        return value.reshape(-1)

    def entry_index(self, value: Tensor) -> list[tuple[int, ...]]:
        """Index into the parameter's array of each natural entry."""
        return _flat_index(value)

    def working_names(self, key: str, value: Tensor) -> list[str]:
        """Names of the working coordinates of parameter ``key``."""
        return [key if value.dim() == 0 else key + _label(i) for i in self.entry_index(value)]

    def log_scale(self, value: Tensor) -> list[bool]:
        """Which natural entries are positive by construction (their intervals are formed on the log
        scale)."""
        return [False] * len(self.entry_index(value))

    def extrapolation(self, a: np.ndarray) -> np.ndarray | None:
        """Coordinates of the natural value ``a`` for the squared extrapolation (``None``: not
        extrapolated)."""
        return None

    def from_extrapolation(self, c: np.ndarray, bounds: tuple[float, float] | None) -> np.ndarray:
        """The natural value at extrapolation coordinates ``c``, within ``bounds`` where given."""
        raise NotImplementedError


class _Log(WorkingScale):
    """Positive entries by their logarithm (degrees of freedom, a scale)."""

    kind = "log"

    def to_working(self, value: Tensor) -> Tensor:
        return torch.log(value).reshape(-1)

    def from_working(self, w: Tensor, value: Tensor) -> Tensor:
        return torch.exp(w).reshape(value.shape)

    def working_names(self, key: str, value: Tensor) -> list[str]:
        suffix = (lambda i: "") if value.dim() == 0 else _label  # noqa: E731
        return [f"log {key}{suffix(i)}" for i in self.entry_index(value)]

    def log_scale(self, value: Tensor) -> list[bool]:
        return [True] * len(self.entry_index(value))

    def extrapolation(self, a: np.ndarray) -> np.ndarray | None:
        return np.log(a) if np.all(a > 0) else None

    def from_extrapolation(self, c: np.ndarray, bounds: tuple[float, float] | None) -> np.ndarray:
        return np.exp(c) if bounds is None else np.clip(np.exp(c), *bounds)


class _Covariance(WorkingScale):
    """What the two covariance scales share: symmetric positive-definite matrices, extrapolated by
    their matrix logarithm (which does not depend on the order of the components, so a jump is the
    same whichever comes first)."""

    symmetric = True

    def extrapolation(self, a: np.ndarray) -> np.ndarray | None:
        return _sym_log(a)

    def from_extrapolation(self, c: np.ndarray, bounds: tuple[float, float] | None) -> np.ndarray:
        return _sym_exp(c)


class _LogDiagonal(_Covariance):
    """A diagonal covariance by the logarithms of its variances."""

    kind = "logdiag"

    def n_working(self, value: Tensor) -> int:
        return value.shape[-1]

    def to_working(self, value: Tensor) -> Tensor:
        return torch.log(torch.diagonal(value))

    def from_working(self, w: Tensor, value: Tensor) -> Tensor:
        return torch.diag_embed(torch.exp(w))

    def natural_entries(self, value: Tensor) -> Tensor:
        return torch.diagonal(value)

    def entry_index(self, value: Tensor) -> list[tuple[int, ...]]:
        return [(i, i) for i in range(value.shape[0])]

    def working_names(self, key: str, value: Tensor) -> list[str]:
        return [f"log {key}{_label(i)}" for i in self.entry_index(value)]

    def log_scale(self, value: Tensor) -> list[bool]:
        return [True] * value.shape[0]


class _LogCholesky(_Covariance):
    """A full covariance ``C C^T`` by its log-Cholesky factor: ``log C_ii``, then the strict lower
    triangle of ``C``."""

    kind = "cholesky"

    def n_working(self, value: Tensor) -> int:
        n = value.shape[-1]
        return n * (n + 1) // 2

    def to_working(self, value: Tensor) -> Tensor:
        C = torch.linalg.cholesky(value)
        rows, cols = torch.tril_indices(value.shape[0], value.shape[0], -1)
        return torch.cat([torch.log(torch.diagonal(C)), C[rows, cols]])

    def from_working(self, w: Tensor, value: Tensor) -> Tensor:
        n = value.shape[0]
        rows, cols = torch.tril_indices(n, n, -1)
        C = torch.diag_embed(torch.exp(w[:n]))
        if rows.numel():
            C = C.index_put((rows, cols), w[n:])
        return C @ C.transpose(-1, -2)

    def natural_entries(self, value: Tensor) -> Tensor:
        rows, cols = torch.tril_indices(value.shape[0], value.shape[0])
        return value[rows, cols]

    def entry_index(self, value: Tensor) -> list[tuple[int, ...]]:
        rows, cols = torch.tril_indices(value.shape[0], value.shape[0])
        return list(zip(rows.tolist(), cols.tolist()))

    def working_names(self, key: str, value: Tensor) -> list[str]:
        n = value.shape[0]
        rows, cols = torch.tril_indices(n, n, -1)
        return [f"log chol({key})[{i}, {i}]" for i in range(n)] + [
            f"chol({key})[{i}, {j}]" for i, j in zip(rows.tolist(), cols.tolist())
        ]

    def log_scale(self, value: Tensor) -> list[bool]:
        return [i[0] == i[1] for i in self.entry_index(value)]


#: Real entries as they are (the modules' parameters).
PLAIN = WorkingScale()
#: Positive entries by their logarithm.
LOG = _Log()
#: A diagonal covariance by the logarithms of its variances.
LOG_DIAGONAL = _LogDiagonal()
#: A full covariance by its log-Cholesky factor.
LOG_CHOLESKY = _LogCholesky()


def _sym_log(a: np.ndarray) -> np.ndarray | None:
    """Matrix logarithm of a symmetric positive-definite matrix (``None`` if it is not one)."""
    e, v = np.linalg.eigh(a)
    if not np.all(np.isfinite(e)) or e.min() <= 0:
        return None
    return (v * np.log(e)) @ v.T


def _sym_exp(a: np.ndarray) -> np.ndarray:
    """Matrix exponential of a symmetric matrix (symmetrised first)."""
    e, v = np.linalg.eigh((a + a.T) / 2)
    return (v * np.exp(e)) @ v.T


def cholesky_and_inverse(S: Tensor) -> tuple[Tensor, Tensor]:
    """The lower Cholesky factor ``C`` of ``S`` and its inverse."""
    C = torch.linalg.cholesky(S)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    return C, torch.linalg.solve_triangular(C, eye, upper=False)


def log_cholesky_scores(C: Tensor, z: Tensor, v: Tensor, lam: Tensor | float) -> Tensor:
    """Gradient of ``-lam |C^-1 r|^2 / 2 - log det C`` (``lam`` at the row's value, which is exact
    for a Gaussian scale mixture's marginal density) in the log-Cholesky working entries of
    ``C C^T`` (``log C_ii``, then the strict lower triangle): rows ``(R, n(n+1)/2)`` from
    ``z = C^-1 r`` and ``v = C^-T z``."""
    n = C.shape[-1]
    lv = lam.unsqueeze(-1) * v if isinstance(lam, Tensor) else lam * v
    out = torch.empty(v.shape[0], n * (n + 1) // 2, dtype=v.dtype, device=v.device)
    out[:, :n] = lv * z * torch.diagonal(C) - 1.0  # C_ii (lam v_i z_i) - 1
    rows, cols = torch.tril_indices(n, n, -1).tolist()
    for k, (i, j) in enumerate(zip(rows, cols)):
        out[:, n + k] = lv[:, i] * z[:, j]
    return out
