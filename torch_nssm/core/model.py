"""The state-space model and the batch of sequences the algorithms run on.

Time convention (docs/method.md §7): sample ``k`` has input ``u_k`` and output ``y_k``; ``y_k`` observes
``x_k``; the mean of ``x_{k+1}`` is ``f(x_k, u_k)``; ``x0_mean``/``x0_cov`` are the prior of the
first state, the one ``y_0`` observes.

Internally every sequence quantity is *time-major*: ``(T, B, ...)`` with ``B`` sequences padded to
the longest length ``T``.  Padded outputs are NaN (missing) and padded transitions are masked out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .noise import MeasurementNoise

__all__ = ["StateSpaceModel", "SequenceBatch"]


@dataclass
class SequenceBatch:
    """Inputs and outputs of ``B`` sequences, padded to a common length, time-major.

    Attributes
    ----------
    u : Tensor, shape (T, B, nu)
        Inputs (zeros after a sequence's end).
    y : Tensor, shape (T, B, p)
        Outputs; NaN marks a missing value (and the padding).
    lengths : Tensor, shape (B,), long
        Length of each sequence.
    """

    u: Tensor
    y: Tensor
    lengths: Tensor

    @property
    def n_steps(self) -> int:
        return self.y.shape[0]

    @property
    def n_sequences(self) -> int:
        return self.y.shape[1]

    @property
    def obs_mask(self) -> Tensor:
        """``(T, B, p)`` bool, True where an output component is observed (never in the padding)."""
        return ~torch.isnan(self.y) & self.step_mask.unsqueeze(-1)

    @property
    def step_mask(self) -> Tensor:
        """``(T, B)`` bool, True for the samples inside each sequence."""
        k = torch.arange(self.n_steps, device=self.y.device).unsqueeze(1)
        return k < self.lengths.unsqueeze(0)

    @property
    def transition_mask(self) -> Tensor:
        """``(T - 1, B)`` bool, True where the transition ``k -> k+1`` is inside the sequence."""
        return self.step_mask[1:]

    @classmethod
    def from_sequences(cls, us: list[Tensor], ys: list[Tensor]) -> SequenceBatch:
        """Pad lists of ``(T_b, nu)`` inputs and ``(T_b, p)`` outputs into one batch."""
        T = max(y.shape[0] for y in ys)
        B = len(ys)
        u0, y0 = us[0], ys[0]
        u = torch.zeros(T, B, u0.shape[-1], dtype=u0.dtype, device=u0.device)
        y = torch.full((T, B, y0.shape[-1]), math.nan, dtype=y0.dtype, device=y0.device)
        for b, (ub, yb) in enumerate(zip(us, ys)):
            u[: ub.shape[0], b] = ub
            y[: yb.shape[0], b] = yb
        lengths = torch.tensor([y.shape[0] for y in ys], device=y0.device)
        return cls(u=u, y=y, lengths=lengths)

    def select(self, index) -> SequenceBatch:
        """The sub-batch of the sequences ``index`` (a slice or index tensor)."""
        return SequenceBatch(u=self.u[:, index], y=self.y[:, index], lengths=self.lengths[index])

    def unpad(self, values: Tensor) -> list[Tensor]:
        """Split a time-major ``(T, B, ...)`` tensor into the list of per-sequence ``(T_b, ...)``."""
        return [values[: int(n), b] for b, n in enumerate(self.lengths.tolist())]


@dataclass
class StateSpaceModel:
    """``x_{k+1} = f(x_k, u_k) + w``, ``w ~ N(0, Rw)``; ``y_k = g(x_k, u_k) + v``, ``v ~ noise``.

    ``Rw``, ``x0_mean``, ``x0_cov`` and the noise's parameters are shared by all sequences, or
    carry a leading batch dimension ``B`` (one model per sequence: independent fits, where ``f``
    and ``g`` are :class:`~torch_nssm.estimation.independent.StackedModule` s).
    """

    f: nn.Module
    g: nn.Module
    Rw: Tensor
    noise: MeasurementNoise
    x0_mean: Tensor
    x0_cov: Tensor

    @property
    def state_dim(self) -> int:
        return self.x0_mean.shape[-1]

    @property
    def Rv(self) -> Tensor:
        return self.noise.Rv

    def per_sequence(self, name: str, n_sequences: int) -> Tensor:
        """``Rw``, ``x0_mean`` or ``x0_cov`` with a leading batch dimension of ``n_sequences``."""
        value = getattr(self, name)
        if value.dim() == {"Rw": 2, "x0_cov": 2, "x0_mean": 1}[name]:
            return value.expand(n_sequences, *value.shape)
        return value

    def transition(self, x: Tensor, u: Tensor) -> Tensor:
        """Mean of the next state for states ``(B, L, nx)`` and inputs ``(B, nu)``."""
        return self.f(x, u.unsqueeze(-2).expand(*x.shape[:-1], u.shape[-1]))

    def transition_steps(self, x: Tensor, u: Tensor) -> Tensor:
        """Mean of the next state for the states of several time steps at once: ``x`` ``(t, B, L,
        nx)``, inputs ``(t, B, nu)``.  ``f`` sees the sequence dimension first (``(B, t, L, nx)``),
        as batched per-sequence modules require."""
        return _steps(self.f, x, u)

    def observation(self, x: Tensor, u: Tensor) -> Tensor:
        """Mean of the output for states ``(B, L, nx)`` and inputs ``(B, nu)``."""
        return self.g(x, u.unsqueeze(-2).expand(*x.shape[:-1], u.shape[-1]))

    def observation_steps(self, x: Tensor, u: Tensor) -> Tensor:
        """:meth:`observation` for several time steps at once, as :meth:`transition_steps`."""
        return _steps(self.g, x, u)


def _steps(module: nn.Module, x: Tensor, u: Tensor) -> Tensor:
    xb = x.transpose(0, 1)
    ub = u.transpose(0, 1).unsqueeze(-2).expand(*xb.shape[:-1], u.shape[-1])
    return module(xb, ub).transpose(0, 1)
