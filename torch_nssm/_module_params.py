"""scikit-learn parameters of the modules: ``f__a`` / ``g__C`` name the initial values of ``f``'s
and ``g``'s parameters (``get_params``, ``set_params``, ``clone``, ``GridSearchCV``), and fitted
modules pickle on the CPU.

:class:`ModuleParams` is a mixin of :class:`~torch_nssm.RobustNSSMEstimator` (before
``BaseEstimator`` in its bases).
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

__all__ = ["ModuleParams"]


class ModuleParams:
    """``get_params``/``set_params`` with the parameters of the modules ``f`` and ``g``, and a
    ``__getstate__`` that saves the fitted modules on the CPU."""

    def get_params(self, deep: bool = True) -> dict:
        """The estimator's parameters; with ``deep``, also the initial values of ``f``'s and ``g``'s
        parameters as ``f__<name>`` / ``g__<name>`` (floats or arrays), for ``set_params``,
        ``GridSearchCV`` and ``clone``."""
        params = super().get_params(deep=False)
        if deep:
            for label in ("f", "g"):
                module = params.get(label)
                if isinstance(module, nn.Module):
                    for name, p in module.named_parameters():
                        value = p.detach().cpu().numpy().copy()
                        params[f"{label}__{name}"] = float(value) if value.ndim == 0 else value
        return params

    def set_params(self, **params):
        """Set parameters; ``f__a=0.3`` sets the initial value of ``f``'s parameter ``a`` (on a copy
        of ``f``: the module passed in is not changed)."""
        nested = {k: params.pop(k) for k in list(params) if k.startswith(("f__", "g__"))}
        super().set_params(**params)
        copied = set()
        for key, value in nested.items():
            label, name = key.split("__", 1)
            module = getattr(self, label)
            if not isinstance(module, nn.Module):
                raise ValueError(f"Invalid parameter {key!r}: {label} is not a torch.nn.Module")
            if label not in copied:
                module = copy.deepcopy(module)
                setattr(self, label, module)
                copied.add(label)
            named = dict(module.named_parameters())
            if name not in named:
                raise ValueError(f"Invalid parameter {key!r}: {label} has parameters {sorted(named)}")
            target = named[name]
            try:
                new = torch.as_tensor(np.asarray(value, dtype=float), dtype=target.dtype).to(target.device)
                new = new.expand_as(target) if new.dim() == 0 else new.reshape(target.shape)
            except (TypeError, ValueError, RuntimeError) as exc:
                shape = tuple(target.shape)
                raise ValueError(f"{key} must be a number or an array of shape {shape}") from exc
            with torch.no_grad():
                target.copy_(new)
        return self

    def __getstate__(self):
        state = super().__getstate__()
        for name in ("f_", "g_"):  # save the fitted modules on the CPU: they load anywhere
            module = state.get(name)
            if isinstance(module, nn.Module) and any(
                t.device.type != "cpu" for t in list(module.parameters()) + list(module.buffers())
            ):
                state[name] = copy.deepcopy(module).to("cpu")
        return state
