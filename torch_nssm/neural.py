"""Public path of the neural blocks: a re-export of :mod:`torch_nssm.blocks.neural`."""

from .blocks.neural import *  # noqa: F403
from .blocks.neural import __all__  # noqa: F401
