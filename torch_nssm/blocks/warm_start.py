"""Deprecated: :mod:`torch_nssm.blocks.starts` (``warm_start_estimator`` is
:func:`~torch_nssm.blocks.starts.distilled_start`, ``simulation_warm_start`` is
:func:`~torch_nssm.blocks.starts.simulation_start`)."""

from .._deprecation import module_getattr

_STARTS = "torch_nssm.blocks.starts"
_ALIASES = {
    "warm_start_estimator": (_STARTS, "distilled_start"),
    "simulation_warm_start": (_STARTS, "simulation_start"),
    "WarmStartInfo": (_STARTS, "DistilledStartInfo"),
    "distill": (_STARTS, "distill"),
    "LinearTransition": (_STARTS, "LinearTransition"),
    "LinearObservation": (_STARTS, "LinearObservation"),
}
__getattr__ = module_getattr(__name__, _ALIASES)
