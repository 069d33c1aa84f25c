"""Deprecated: :mod:`torch_nssm.starts` (``warm_start_estimator`` is
:func:`~torch_nssm.starts.distilled_start`, ``simulation_warm_start`` is
:func:`~torch_nssm.starts.simulation_start`)."""

from ._deprecation import module_getattr
from .blocks.warm_start import RENAMED

__getattr__ = module_getattr(__name__, {old: ("torch_nssm.starts", new) for old, new in RENAMED.items()})
