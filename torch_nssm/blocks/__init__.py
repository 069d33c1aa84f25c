"""Ready-made building blocks for ``f`` and ``g``, and the warm start of neural models.

* :mod:`~torch_nssm.blocks.neural` -- :class:`MLPTransition`, :class:`MLPObservation`,
  :class:`GreyBoxTransition`.
* :mod:`~torch_nssm.blocks.linear` -- :class:`LinearTransition`, :class:`LinearObservation`.
* :mod:`~torch_nssm.blocks.warm_start` -- :func:`simulation_warm_start` (networks trained by
  simulation error first), :func:`warm_start_estimator`, :func:`distill`, :class:`WarmStartInfo`.

The public paths :mod:`torch_nssm.neural` and :mod:`torch_nssm.warm_start` re-export them.
"""

from .linear import LinearObservation, LinearTransition
from .neural import ACTIVATIONS, GreyBoxTransition, MLPObservation, MLPTransition
from .warm_start import WarmStartInfo, distill, simulation_warm_start, warm_start_estimator

__all__ = [
    "MLPTransition",
    "MLPObservation",
    "GreyBoxTransition",
    "ACTIVATIONS",
    "LinearTransition",
    "LinearObservation",
    "warm_start_estimator",
    "simulation_warm_start",
    "distill",
    "WarmStartInfo",
]
