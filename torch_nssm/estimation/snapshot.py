"""A model's iterate kept aside: the model object and its modules' parameter values, to go back to
when a step is undone (the EM loop's rollback, an accelerated step that lost likelihood)."""

from __future__ import annotations

from ..core.model import StateSpaceModel
from .mstep import module_state

__all__ = ["snapshot", "restore"]


def snapshot(model: StateSpaceModel) -> tuple:
    """``model`` and the values of its modules' parameters and buffers now."""
    return model, module_state(model.f), module_state(model.g)


def restore(kept: tuple) -> StateSpaceModel:
    """The model of a :func:`snapshot`, its modules set back to the values it kept."""
    model, f_state, g_state = kept
    model.f.load_state_dict(f_state)
    model.g.load_state_dict(g_state)
    return model
