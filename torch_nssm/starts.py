"""Starts of neural and grey-box models (a re-export of :mod:`torch_nssm.blocks.starts`, with the
linear reference blocks of :mod:`torch_nssm.blocks.linear`): :func:`simulation_start` and
:func:`distilled_start`."""

from .blocks.starts import *  # noqa: F403
from .blocks.starts import __all__  # noqa: F401
