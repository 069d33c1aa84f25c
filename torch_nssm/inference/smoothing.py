"""Deprecated: the marginal smoother is :mod:`torch_nssm.inference.ffbsm`, backward simulation
:mod:`torch_nssm.inference.ffbsi`."""

from .._deprecation import module_getattr

_FFBSM, _FFBSI = "torch_nssm.inference.ffbsm", "torch_nssm.inference.ffbsi"
__getattr__ = module_getattr(
    __name__,
    {
        "SmootherOutput": (_FFBSM, "SmootherOutput"),
        "ffbsm": (_FFBSM, "ffbsm"),
        "smoothed_moments": (_FFBSM, "smoothed_moments"),
        "TINY_WEIGHT": (_FFBSM, "TINY_WEIGHT"),
        "ffbsi": (_FFBSI, "ffbsi"),
        "backward_trajectories": (_FFBSI, "backward_trajectories"),
        "backward_segments": (_FFBSI, "backward_segments"),
    },
)
