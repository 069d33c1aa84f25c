"""Ready-made ``f`` / ``g`` modules of the paper's systems, and :func:`true_model`.

The classes are defined next to their data generators (:mod:`torch_nssm.datasets.paper`,
:mod:`torch_nssm.datasets.manipulator`) and collected here.  Each is called ``f(x, u)`` /
``g(x, u)`` with ``x`` of shape ``(..., nx)`` and ``u`` of shape ``(..., nu)`` and returns the
mean of the next state or of the output; those with parameters derive from
:class:`~torch_nssm.LinearInParameters` (closed-form M-steps).
"""

from __future__ import annotations

import torch
from torch import nn

from .datasets._base import SimulatedData
from .datasets.manipulator import ManipulatorConstants, ManipulatorObservation, ManipulatorTransition
from .datasets.paper import PaperObservation, PaperTransition

__all__ = [
    "PaperTransition",
    "PaperObservation",
    "ManipulatorTransition",
    "ManipulatorObservation",
    "true_model",
]


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
