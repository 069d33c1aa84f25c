"""The smoothers by name: ``SMOOTHERS`` maps the estimator's ``smoother=`` to a function
``smoother(model, data, filt, **options) -> SmootherOutput``.

A new smoother is a function in a file of its own (importing ``SmootherOutput`` from
:mod:`torch_nssm.inference.ffbsm`) plus one line here; its keyword-only options are reachable
from the estimator as ``smoother_options``.
"""

from __future__ import annotations

import inspect
from typing import Callable

from ..core.model import SequenceBatch, StateSpaceModel
from .ffbsi import ffbsi
from .ffbsm import SmootherOutput, ffbsm
from .filtering import FilterOutput

__all__ = ["SMOOTHERS", "get_smoother", "smoother_options"]


def _mcmc(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput, **options) -> SmootherOutput:
    """:func:`ffbsi` with Metropolis-Hastings backward moves (``method="mcmc"``)."""
    return ffbsi(model, data, filt, method="mcmc", **options)


def _rejection(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput, **options) -> SmootherOutput:
    """:func:`ffbsi` with rejection sampling and an exact fallback (``method="reject"``)."""
    return ffbsi(model, data, filt, method="reject", **options)


Smoother = Callable[..., SmootherOutput]

#: The estimator's ``smoother=`` choices: ``smoother(model, data, filt, **options)``; the options
#: (``smoother_options=``) are the keyword arguments of the function (``generator`` is passed to
#: those that take it).
SMOOTHERS: dict[str, Smoother] = {
    "ffbsm": ffbsm,
    "ffbsi": _rejection,
    "mcmc": _mcmc,
}

#: Options of each smoother that the estimator sets itself.
_RESERVED = ("model", "data", "filt", "generator", "method")


def smoother_options(name: str) -> tuple[str, ...]:
    """The keyword options a user may pass to smoother ``name``."""
    fn = ffbsi if name in ("ffbsi", "mcmc") else get_smoother(name)
    params = inspect.signature(fn).parameters.values()
    return tuple(p.name for p in params if p.kind is p.KEYWORD_ONLY and p.name not in _RESERVED)


def get_smoother(name: str) -> Smoother:
    """The smoother registered as ``name``."""
    try:
        return SMOOTHERS[name]
    except KeyError:
        raise ValueError(f"smoother must be one of {sorted(SMOOTHERS)}, got {name!r}") from None
