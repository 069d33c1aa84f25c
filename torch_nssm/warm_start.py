"""Public path of the warm start: a re-export of :mod:`torch_nssm.blocks.warm_start` (with the
linear reference blocks of :mod:`torch_nssm.blocks.linear`)."""

from .blocks.warm_start import *  # noqa: F403
from .blocks.warm_start import __all__  # noqa: F401
