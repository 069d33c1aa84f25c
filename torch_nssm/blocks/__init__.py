"""Ready-made building blocks for ``f`` and ``g``, and the starts of neural models.

* :mod:`~torch_nssm.blocks.neural` -- :class:`MLPTransition`, :class:`MLPObservation`,
  :class:`GreyBoxTransition`, :class:`MLPDerivative`.
* :mod:`~torch_nssm.blocks.linear` -- :class:`LinearTransition`, :class:`LinearObservation`.
* :mod:`~torch_nssm.blocks.continuous` -- :class:`ContinuousTimeTransition` (a transition from an
  ODE ``dx/dt = F(x, u)`` and a sample time), :class:`LinearContinuousTimeTransition`;
  :class:`MLPDerivative` (in :mod:`~torch_nssm.blocks.neural`) is a neural ``F``.
* :mod:`~torch_nssm.blocks.starts` -- :func:`simulation_start` (networks trained by
  simulation error first), :func:`distilled_start`, :func:`distill`, :class:`DistilledStartInfo`.

The public paths :mod:`torch_nssm.neural` and :mod:`torch_nssm.starts` re-export them.
"""

from .._deprecation import module_getattr
from .continuous import ContinuousTimeTransition, LinearContinuousTimeTransition
from .linear import LinearObservation, LinearTransition
from .neural import ACTIVATIONS, GreyBoxTransition, MLPDerivative, MLPObservation, MLPTransition
from .starts import DistilledStartInfo, distill, distilled_start, simulation_start

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
    "distilled_start",
    "simulation_start",
    "distill",
    "DistilledStartInfo",
]

#: the names of the starts before they were renamed, for one release
__getattr__ = module_getattr(
    __name__,
    {
        "warm_start_estimator": ("torch_nssm.blocks", "distilled_start"),
        "simulation_warm_start": ("torch_nssm.blocks", "simulation_start"),
        "WarmStartInfo": ("torch_nssm.blocks", "DistilledStartInfo"),
    },
)
