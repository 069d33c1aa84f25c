"""Deprecated: :mod:`torch_nssm.blocks.starts` (``warm_start_estimator`` is
:func:`~torch_nssm.blocks.starts.distilled_start`, ``simulation_warm_start`` is
:func:`~torch_nssm.blocks.starts.simulation_start`)."""

from .._deprecation import module_getattr

#: old name in this module -> its name in the starts module (also :mod:`torch_nssm.warm_start`'s)
RENAMED = {
    "warm_start_estimator": "distilled_start",
    "simulation_warm_start": "simulation_start",
    "WarmStartInfo": "DistilledStartInfo",
    "distill": "distill",
    "LinearTransition": "LinearTransition",
    "LinearObservation": "LinearObservation",
}
__getattr__ = module_getattr(__name__, {o: ("torch_nssm.blocks.starts", n) for o, n in RENAMED.items()})
