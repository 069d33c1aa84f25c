"""Ready-made building blocks for ``f`` and ``g``, and the warm start of neural models.

* :mod:`~torch_nssm.blocks.neural` -- :class:`MLPTransition`, :class:`MLPObservation`,
  :class:`GreyBoxTransition`, :class:`MLPDerivative`.
* :mod:`~torch_nssm.blocks.linear` -- :class:`LinearTransition`, :class:`LinearObservation`.
* :mod:`~torch_nssm.blocks.continuous` -- :class:`ContinuousTimeTransition` (a transition from an
  ODE ``dx/dt = F(x, u)`` and a sample time), :class:`LinearContinuousTimeTransition`;
  :class:`MLPDerivative` (in :mod:`~torch_nssm.blocks.neural`) is a neural ``F``.
* :mod:`~torch_nssm.blocks.warm_start` -- :func:`simulation_warm_start` (networks trained by
  simulation error first), :func:`warm_start_estimator`, :func:`distill`, :class:`WarmStartInfo`.

The public paths :mod:`torch_nssm.neural` and :mod:`torch_nssm.warm_start` re-export them.
"""

from .continuous import ContinuousTimeTransition, LinearContinuousTimeTransition
from .linear import LinearObservation, LinearTransition
from .neural import ACTIVATIONS, GreyBoxTransition, MLPDerivative, MLPObservation, MLPTransition
from .warm_start import WarmStartInfo, distill, simulation_warm_start, warm_start_estimator

__all__ = [
    "MLPTransition",
    "MLPObservation",
    "GreyBoxTransition",
    "MLPDerivative",
    "ACTIVATIONS",
    "ContinuousTimeTransition",
    "LinearContinuousTimeTransition",
    "LinearTransition",
    "LinearObservation",
    "warm_start_estimator",
    "simulation_warm_start",
    "distill",
    "WarmStartInfo",
]
