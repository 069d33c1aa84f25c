"""Deprecated: :mod:`torch_nssm.starts` (``warm_start_estimator`` is
:func:`~torch_nssm.starts.distilled_start`, ``simulation_warm_start`` is
:func:`~torch_nssm.starts.simulation_start`)."""

from ._deprecation import module_getattr

_STARTS = "torch_nssm.starts"
_ALIASES = {
    "warm_start_estimator": (_STARTS, "distilled_start"),
    "simulation_warm_start": (_STARTS, "simulation_start"),
    "WarmStartInfo": (_STARTS, "DistilledStartInfo"),
    "distill": (_STARTS, "distill"),
    "LinearTransition": (_STARTS, "LinearTransition"),
    "LinearObservation": (_STARTS, "LinearObservation"),
}
__getattr__ = module_getattr(__name__, _ALIASES)
