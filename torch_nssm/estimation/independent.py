"""Independent fits in one tensor pass: many models, one per sequence, evaluated together.

A Monte Carlo study fits one model per data set.  The E-steps of all data sets run as one batch
(the filter and smoother carry a batch dimension; ``f`` and ``g`` are evaluated for every data set
at once through :class:`StackedModule`), and each data set's M-step uses only its own statistics
(:func:`~torch_nssm.estimation.mstep.m_step` with ``shared=False``).  The loop is the same as a
single fit's (:func:`~torch_nssm.estimation.loop.run_em`).
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn
from torch.func import functional_call, stack_module_state, vmap

from ..core.model import StateSpaceModel
from ..core.parametric import LinearInParameters

__all__ = ["StackedModule", "stack_models"]


class StackedModule(nn.Module):
    """``B`` modules of the same architecture, evaluated together.

    ``forward(x, u)`` takes ``x`` of shape ``(B, ..., nx)`` and ``u`` of shape ``(B, ..., nu)`` and
    applies module ``b`` to ``x[b], u[b]`` (``torch.func.vmap`` over the stacked parameters, or one
    batched product for modules linear in their parameters).

    Parameters
    ----------
    modules : list of torch.nn.Module
        Modules with identical parameter and buffer names and shapes.
    """

    def __init__(self, modules: list[nn.Module]):
        super().__init__()
        params, buffers = stack_module_state(modules)
        self._params = {k: v.detach() for k, v in params.items()}
        self._buffers_stacked = {k: v.detach() for k, v in buffers.items()}
        # A stateless copy to call functionally (parameters are passed in at call time).
        self._template = [copy.deepcopy(modules[0])]
        self._theta = None
        if isinstance(modules[0], LinearInParameters) and not buffers:
            self._theta = torch.stack([m.theta().detach() for m in modules])  # (B, P)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        template = self._template[0]
        if self._theta is not None:  # elementwise products (LinearInParameters.predict): no tiny matmuls
            theta = self._theta.view(self._theta.shape[0], *([1] * (x.dim() - 2)), -1)  # (B, 1, ..., P)
            return template.predict(x, u, theta)

        def call(p, b, xb, ub):
            return functional_call(template, (p, b), (xb, ub))

        return vmap(call)(self._params, self._buffers_stacked, x, u)

    def frozen(self):
        """The particle filter's evaluator of one pass over particle arrays ``(B, L, nx)``: for
        modules linear in their parameters, the template's
        :meth:`~torch_nssm.LinearInParameters.frozen_predict` at the stacked parameters (their views
        taken once, not at every step); else the module."""
        if self._theta is None:
            return self
        return self._template[0].frozen_predict(self._theta.unsqueeze(1))  # (B, 1, P)


def stack_models(models: list[StateSpaceModel]) -> StateSpaceModel:
    """One model with a leading batch dimension from ``B`` models of the same architecture."""
    return StateSpaceModel(
        f=StackedModule([m.f for m in models]),
        g=StackedModule([m.g for m in models]),
        Rw=torch.stack([m.Rw for m in models]),
        noise=type(models[0].noise).stack([m.noise for m in models]),
        x0_mean=torch.stack([m.x0_mean for m in models]),
        x0_cov=torch.stack([m.x0_cov for m in models]),
    )
