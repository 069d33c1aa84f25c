"""The free parameters of ``f`` and ``g`` as one flat vector, and the modules evaluated at many
values of it at once.

The least-squares solvers (:mod:`torch_nssm.estimation.least_squares`) work on a vector ``theta``
of the free (``requires_grad``) parameters of one or more modules.  :class:`FreeParameters` maps
between that vector and the modules, and :meth:`FreeParameters.map` evaluates the modules at a
*batch* of parameter vectors through :func:`torch.func.vmap` over
:func:`torch.func.functional_call` (about 2-3 module calls' cost for a handful of vectors: the
finite-difference Jacobians of the solvers cost a few simulations, where forward-mode
differentiation through a simulation loop costs 15-20).  A module that ``vmap`` cannot run
(data-dependent Python control flow, ``.item()``) is evaluated once per vector instead.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor, nn
from torch.func import functional_call, vmap

__all__ = ["FreeParameters"]


class FreeParameters:
    """The free parameters of named modules, flattened in a fixed order.

    Parameters
    ----------
    modules : dict of str to nn.Module
        E.g. ``{"f": f, "g": g}``; the vector holds each module's parameters with
        ``requires_grad=True`` in :meth:`torch.nn.Module.named_parameters` order.
    """

    def __init__(self, modules: dict[str, nn.Module]):
        self.modules = modules
        self.entries: list[tuple[str, str, torch.Size, int]] = []  # (module, name, shape, offset)
        offset = 0
        for label, module in modules.items():
            for name, p in module.named_parameters():
                if p.requires_grad:
                    self.entries.append((label, name, p.shape, offset))
                    offset += p.numel()
        self.size = offset
        self._vectorised = True
        params = [p for m in modules.values() for p in m.parameters()]
        # one functional_call binds every module's parameters for a whole ``fn`` (a simulation's
        # loop over time) instead of one per module call: the rebinding cost 0.1 ms a step, a sixth
        # of the pendulum's first stage.  Modules that share a parameter keep one binding per call.
        self._bound = _Bound(modules) if len({id(p) for p in params}) == len(params) else None

    @property
    def names(self) -> list[str]:
        """``"f.a"``-style name of each entry of the vector (a matrix gives ``"g.C[0, 1]"``...)."""
        out = []
        for label, name, shape, _ in self.entries:
            if len(shape) == 0:
                out.append(f"{label}.{name}")
            else:
                for idx in torch.cartesian_prod(*[torch.arange(s) for s in shape]).reshape(-1, len(shape)):
                    out.append(f"{label}.{name}[{', '.join(str(int(i)) for i in idx)}]")
        return out

    def _parameter(self, label: str, name: str) -> Tensor:
        return dict(self.modules[label].named_parameters())[name]

    def vector(self) -> Tensor:
        """The current values as one detached vector ``(P,)``."""
        parts = [self._parameter(label, name).detach().reshape(-1) for label, name, _, _ in self.entries]
        if not parts:
            ref = next(iter(m for m in self.modules.values()), None)
            p = next(iter(ref.parameters()), None) if ref is not None else None
            kw = dict(dtype=p.dtype, device=p.device) if p is not None else {}
            return torch.zeros(0, **kw)
        return torch.cat(parts)

    @torch.no_grad()
    def assign(self, theta: Tensor) -> None:
        """Write ``theta`` ``(P,)`` into the modules."""
        for label, name, shape, offset in self.entries:
            n = max(1, int(torch.Size(shape).numel()))
            self._parameter(label, name).copy_(theta[offset : offset + n].reshape(shape))

    def batched(self, label: str, thetas: Tensor) -> dict[str, Tensor]:
        """Module ``label``'s free parameters for a batch of vectors ``(S, P)``: ``{name: (S, *shape)}``."""
        S = thetas.shape[0]
        return {
            name: thetas[:, offset : offset + max(1, int(torch.Size(shape).numel()))].reshape(S, *shape)
            for lab, name, shape, offset in self.entries
            if lab == label
        }

    def map(
        self, fn: Callable[..., Tensor], thetas: Tensor, *args: Tensor, batched: tuple[bool, ...] = ()
    ) -> Tensor:
        """``fn(forward, *args)`` at each parameter vector of ``thetas`` ``(S, P)``, stacked ``(S, ...)``
        (a tuple of such when ``fn`` returns a tuple).

        ``forward(label, *inputs)`` calls module ``label`` with its free parameters at that vector
        (the other parameters and buffers as they are).  ``batched[i]``: argument ``i`` carries the
        batch of ``S`` as its first dimension (default: no argument does).
        """
        flags = tuple(batched) + (False,) * (len(args) - len(batched))
        params = {label: self.batched(label, thetas) for label in self.modules}

        def one(p: dict[str, dict[str, Tensor]], *a: Tensor) -> Tensor:
            if self._bound is not None:
                flat = {f"held.{label}.{name}": v for label, d in p.items() for name, v in d.items()}
                return functional_call(self._bound, flat, (fn, *a))

            def forward(label: str, *inputs: Tensor) -> Tensor:
                return functional_call(self.modules[label], p[label], inputs)

            return fn(forward, *a)

        if self._vectorised:
            try:
                return vmap(one, in_dims=(0, *(0 if b else None for b in flags)))(params, *args)
            except (RuntimeError, NotImplementedError, ValueError, TypeError):
                # data-dependent control flow, or an operation without a batching rule: one by one
                self._vectorised = False
        out = []
        for s in range(thetas.shape[0]):
            p = {label: {k: v[s] for k, v in d.items()} for label, d in params.items()}
            out.append(one(p, *(a[s] if b else a for a, b in zip(args, flags))))
        if isinstance(out[0], tuple):
            return tuple(torch.stack(parts) for parts in zip(*out))
        return torch.stack(out)


class _Bound(nn.Module):
    """Named modules under one parent: ``_Bound(modules)(fn, *args)`` is ``fn(forward, *args)`` with
    ``forward(label, *inputs)`` calling module ``label`` as it is bound (by ``functional_call``)."""

    def __init__(self, modules: dict[str, nn.Module]):
        super().__init__()
        self.held = nn.ModuleDict(modules)

    def forward(self, fn: Callable[..., Tensor], *args: Tensor) -> Tensor:
        return fn(lambda label, *inputs: self.held[label](*inputs), *args)
