"""The paper's systems as ready ``f`` / ``g`` modules.

Each module is called ``f(x, u)`` / ``g(x, u)`` with ``x`` of shape ``(..., nx)`` and ``u`` of
shape ``(..., nu)`` (leading dimensions broadcast) and returns the mean of the next state
``(..., nx)`` or of the output ``(..., p)``.  The modules that have parameters derive from
:class:`~torch_nssm.parametric.LinearInParameters`, so the EM engine updates them in closed
form (paper eqs. 44-45, 48).  Parameters are 0-dimensional ``nn.Parameter`` s (``float64`` by
default); ``.to()`` converts them and the constant buffers together.

:func:`true_model` builds ``(f, g)`` at the true parameters of a
:class:`~torch_nssm.datasets.SimulatedData`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._ops import broadcast_leading
from .core.parametric import LinearInParameters
from .datasets import MANIPULATOR_DT, ManipulatorConstants, SimulatedData

__all__ = [
    "PaperTransition",
    "PaperObservation",
    "ManipulatorTransition",
    "ManipulatorObservation",
    "true_model",
]


def _scalar_parameter(value: float | Tensor, dtype: torch.dtype, device) -> nn.Parameter:
    t = torch.as_tensor(value, dtype=dtype, device=device).detach().clone().reshape(())
    return nn.Parameter(t)


class PaperTransition(LinearInParameters):
    """``f(x, u) = a x + b u`` (Section 4.1; ``nx = nu = 1``), linear in ``theta = (a, b)``.

    Parameters
    ----------
    a, b : float or Tensor
        Initial values (default: the paper's true values 0.9 and 1).
    dtype : torch.dtype
        Parameter dtype.
    device : torch.device or str, optional
    """

    nx = 1
    nu = 1

    def __init__(
        self,
        a: float | Tensor = 0.9,
        b: float | Tensor = 1.0,
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.a = _scalar_parameter(a, dtype, device)
        self.b = _scalar_parameter(b, dtype, device)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi = [[x, u]]`` of shape ``(..., 1, 2)`` and a zero offset ``(..., 1)``."""
        x, u = broadcast_leading(x, u)
        Phi = torch.stack([x[..., 0], u[..., 0]], dim=-1).unsqueeze(-2)
        return Phi, torch.zeros_like(x)

    def extra_repr(self) -> str:
        return f"a={self.a.item():.6g}, b={self.b.item():.6g}"


class PaperObservation(LinearInParameters):
    """``g(x, u) = c cos(x)`` (Section 4.1; ``p = 1``), linear in ``theta = (c,)``; ``u`` unused.

    Parameters
    ----------
    c : float or Tensor
        Initial value (default: the paper's true value 1).
    dtype : torch.dtype
        Parameter dtype.
    device : torch.device or str, optional
    """

    nx = 1
    ny = 1

    def __init__(
        self,
        c: float | Tensor = 1.0,
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.c = _scalar_parameter(c, dtype, device)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi = [[cos x]]`` of shape ``(..., 1, 1)`` and a zero offset ``(..., 1)``."""
        return torch.cos(x).unsqueeze(-1), torch.zeros_like(x)

    def extra_repr(self) -> str:
        return f"c={self.c.item():.6g}"


class ManipulatorTransition(LinearInParameters):
    """Forward-Euler step of the two-link manipulator (eq. 54), linear in ``(theta1, theta2)``.

    State ``x = [dphi1, dphi2, phi1, phi2]``, input ``u = [F(t_k)]`` (the force, N).  With
    ``M^-1 E``, ``M^-1 K0``, ``M^-1 K1`` from :class:`~torch_nssm.datasets.ManipulatorConstants`
    (``K(t) = K0 + F(t) K1``)::

        dphi_{k+1} = dphi_k + dt (-M^-1 E dphi_k - M^-1 (K0 + F_k K1) phi_k)     (offset)
        phi_{k+1}  = phi_k  + dt diag(theta1, theta2) dphi_k                     (Phi @ theta)

    It reproduces :func:`~torch_nssm.datasets.make_manipulator` exactly when built with the same
    ``dt`` and ``constants``.

    Parameters
    ----------
    theta1, theta2 : float or Tensor
        Initial values (default: the true values 1, 1).
    dt : float
        Euler step, s (default :data:`~torch_nssm.datasets.MANIPULATOR_DT`).
    constants : ManipulatorConstants, optional
        Physical constants (default: the module constants of :mod:`torch_nssm.datasets`).
    dtype : torch.dtype
        Dtype of the parameters and buffers.
    device : torch.device or str, optional
    """

    nx = 4
    nu = 1

    def __init__(
        self,
        theta1: float | Tensor = 1.0,
        theta2: float | Tensor = 1.0,
        *,
        dt: float = MANIPULATOR_DT,
        constants: ManipulatorConstants | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.theta1 = _scalar_parameter(theta1, dtype, device)
        self.theta2 = _scalar_parameter(theta2, dtype, device)
        self.dt = float(dt)
        self.constants = constants if constants is not None else ManipulatorConstants()
        MinvE, MinvK0, MinvK1 = self.constants.continuous_blocks()
        for name, mat in (("MinvE", MinvE), ("MinvK0", MinvK0), ("MinvK1", MinvK1)):
            self.register_buffer(name, torch.as_tensor(mat, dtype=dtype, device=device).clone())

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` of shape ``(..., 4, 2)`` (``dt dphi_i`` at row ``2 + i``, column ``i``), offset
        ``(..., 4)``."""
        x, u = broadcast_leading(x, u)
        vel, ang = x[..., :2], x[..., 2:]
        force = u[..., :1]
        acc = -(vel @ self.MinvE.T) - (ang @ self.MinvK0.T) - force * (ang @ self.MinvK1.T)
        offset = torch.cat([vel + self.dt * acc, ang], dim=-1)
        Phi = x.new_zeros(x.shape[:-1] + (4, 2))
        Phi[..., 2, 0] = self.dt * vel[..., 0]
        Phi[..., 3, 1] = self.dt * vel[..., 1]
        return Phi, offset

    def extra_repr(self) -> str:
        return f"theta1={self.theta1.item():.6g}, theta2={self.theta2.item():.6g}, dt={self.dt:g}"


class ManipulatorObservation(nn.Module):
    """``g(x, u) = [phi1, phi2]`` (eq. 55): the two angles; no parameters, ``u`` unused.

    A plain ``nn.Module`` (``LinearInParameters`` needs at least one parameter); the EM engine
    skips the M-step of a module without free parameters.
    """

    nx = 4
    ny = 2

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., 2:4]


def true_model(data: SimulatedData, *, dtype: torch.dtype = torch.float64) -> tuple[nn.Module, nn.Module]:
    """The ``(f, g)`` modules of a simulated data set, at its true parameters.

    Parameters
    ----------
    data : SimulatedData
        From :func:`~torch_nssm.datasets.make_paper_example`,
        :func:`~torch_nssm.datasets.make_gopaluni_example`,
        :func:`~torch_nssm.datasets.make_huang_example` or
        :func:`~torch_nssm.datasets.make_manipulator`.
    dtype : torch.dtype
        Dtype of the modules.

    Returns
    -------
    f, g : nn.Module

    Raises
    ------
    ValueError
        For an unknown ``data.name``.
    """
    p = data.params
    if data.name in ("paper_example", "gopaluni_example", "huang_example"):
        return PaperTransition(p["a"], p["b"], dtype=dtype), PaperObservation(p["c"], dtype=dtype)
    if data.name == "manipulator":
        constants = ManipulatorConstants(**p["constants"])
        f = ManipulatorTransition(p["theta1"], p["theta2"], dt=p["dt"], constants=constants, dtype=dtype)
        return f, ManipulatorObservation()
    raise ValueError(f"true_model: unknown data set name {data.name!r}")
