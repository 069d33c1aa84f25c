"""What the noise families with one scale per sample share: the squared Mahalanobis norm of the
whitened residual as the filter's statistic, the closed-form update of a full ``Rv``, and the
observed information's terms of a density that depends on the residual through that norm."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ... import _workspace
from ..._ops import small_matmul
from ..scales import LOG_CHOLESKY, cholesky_and_inverse, log_cholesky_scores
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
    """A noise model whose latent scale (if any) multiplies the whole output vector: its density
    depends on a residual ``r`` through ``delta2 = |C^-1 r|^2`` (``Rv = C C^T``) and ``log det Rv``
    (:meth:`density_of_norms`), and its latent scale's weight through ``delta2`` alone
    (:meth:`latent_weight`)."""

    WORKING = {"Rv": LOG_CHOLESKY}

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

    # ------------------------------------------------------------------ the observed information
    def density_of_norms(self, delta2: Tensor, logdet: Tensor, n_obs: Tensor) -> Tensor:
        """Log-density from the squared norms ``delta2``, ``log det`` of the observed block of ``Rv``
        and the number of observed components (broadcast together)."""
        raise NotImplementedError

    def latent_weight(self, delta2: Tensor, p: int, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Per row, ``lam = -2 d log-density / d delta2`` at the squared norms ``delta2`` of ``p``
        components, and ``weight`` ``(R, 1)`` times the scores of the parameters other than ``Rv``
        in their working coordinates (``{name: (R, k)}``)."""
        raise NotImplementedError

    def residual_log_prob(self, r: Tensor, mask: Tensor, all_observed: bool) -> Tensor:
        Rv = self.Rv
        m = mask.to(r.dtype)
        p = r.shape[-1]
        if all_observed:
            C = torch.linalg.cholesky(Rv)
            Ci = torch.linalg.solve_triangular(C, torch.eye(p, dtype=C.dtype, device=C.device), upper=False)
            z = r @ Ci.transpose(-1, -2)
            logdet = 2.0 * torch.log(torch.diagonal(C)).sum()
            n_obs = torch.full(r.shape[:-1], float(p), dtype=r.dtype, device=r.device)
        else:  # the observed block of Rv, per row
            eye = torch.eye(p, dtype=r.dtype, device=r.device)
            Rm = Rv * m.unsqueeze(-1) * m.unsqueeze(-2) + eye * (1.0 - m).unsqueeze(-1)
            C = torch.linalg.cholesky(Rm)
            z = torch.linalg.solve_triangular(C, (r * m).unsqueeze(-1), upper=False).squeeze(-1)
            logdet = 2.0 * torch.log(torch.diagonal(C, dim1=-2, dim2=-1)).sum(-1)
            n_obs = m.sum(-1)
        return self.density_of_norms((z * z).sum(-1), logdet, n_obs)

    def scores_in_closed_form(self, all_observed: bool) -> bool:
        return all_observed

    def residual_scores(self, r: Tensor, mask: Tensor, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """With ``z = C^-1 r``, ``v = Rv^-1 r`` and ``lam`` (:meth:`latent_weight`): the gradient in
        the mean is ``lam v``, in the log-Cholesky entries ``C_ii lam v_i z_i - 1`` (diagonal, log
        scale) and ``lam v_i z_j`` (``i > j``)."""
        p = r.shape[-1]
        C, Ci = cholesky_and_inverse(self.Rv)
        z = r @ Ci.mT
        v = z @ Ci
        delta2 = (z * z).sum(-1)
        lam, scores = self.latent_weight(delta2, p, weight)
        grad_mu = weight * lam.unsqueeze(-1) * v
        scores["Rv"] = weight * log_cholesky_scores(C, z, v, lam)
        return grad_mu, scores
