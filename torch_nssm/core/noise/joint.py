"""What the noise families with one scale per sample share: the squared Mahalanobis norm of the
whitened residual as the filter's statistic, and the closed-form update of a full ``Rv``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ... import _workspace
from ..._ops import small_matmul
from .base import MaskedScale, MeasurementNoise, NoiseEvaluator, symmetric_pd

__all__ = ["JointScaleNoise", "SquaredNormEvaluator"]


class SquaredNormEvaluator(NoiseEvaluator):
    """Records ``delta2 = |z|^2`` of every particle in ``statistics`` ``(T, B, L)``."""

    def __init__(self, const: Tensor, n_particles: int, records: bool = True):
        T, B = const.shape
        self.const = const
        self.statistics = _workspace.empty((T, B, n_particles), const.dtype, const.device)
        # views of every step, made once (indexing a list is free, a tensor select costs ~0.3 us,
        # as much as a small operation), shaped (B, L, 1) like the residuals; none where nothing is
        # recorded (``records=False``: ``statistics`` is only storage)
        self._delta2 = self.statistics.unsqueeze(-1).unbind(0) if records else ()
        self._logits = torch.empty(B, n_particles, dtype=const.dtype, device=const.device)  # step's result
        self._logits_col = self._logits.unsqueeze(-1)  # written through this (B, L, 1) view

    def squared_norm(self, k: int, z: Tensor) -> Tensor:
        """``|z|^2`` of the residuals ``z`` ``(B, L, p)`` of step ``k``, recorded: ``(B, L, 1)``."""
        if z.shape[-1] == 1:
            return torch.mul(z, z, out=self._delta2[k])
        return torch.sum(z * z, dim=-1, keepdim=True, out=self._delta2[k])


@dataclass(frozen=True)
class JointScaleNoise(MeasurementNoise):
    """A noise model whose latent scale (if any) multiplies the whole output vector."""

    def statistics(self, r, W, e_lam, e_log_lam, scale: MaskedScale, sl: slice) -> dict[str, Tensor]:
        # E[lam r r^T | r_o] = <lam> rhat rhat^T + (R_mm - R_mo R_oo^-1 R_om): the missing part of
        # each residual is completed by its conditional expectation given the observed part
        # (standard EM for incomplete multivariate data, docs/method.md §4); zero without gaps.
        B, p = r.shape[1], r.shape[-1]
        Wl = W * e_lam
        mass = W.sum(-1)  # (t, B): 1 on observed steps, 0 elsewhere
        stats = {"n_obs": scale.mask[sl].any(-1).sum(0).to(r.dtype)}
        if p == 1:
            stats["scatter"] = (Wl * r[..., 0].square()).sum((0, 2)).view(B, 1, 1)
        else:
            R = self.per_sequence("Rv", B).unsqueeze(0)  # (1, B, p, p)
            K = R @ scale.precision()[sl]  # identity on the observed block, R_mo R_oo^-1 below
            rhat = small_matmul(K.unsqueeze(2), r.unsqueeze(-1)).squeeze(-1)  # (t, B, L, p)
            S = ((Wl.unsqueeze(-1) * rhat).transpose(-1, -2) @ rhat).sum(0)
            stats["scatter"] = S + torch.einsum("tb,tbpq->bpq", mass, R - K @ R)
        return stats

    def _updated_scale(self, stats: dict[str, Tensor], fit_Rv: bool) -> Tensor:
        if not fit_Rv:
            return self.Rv
        n = stats["n_obs"].clamp_min(1)
        return symmetric_pd(stats["scatter"] / n[..., None, None], 1e-10).reshape(self.Rv.shape)
