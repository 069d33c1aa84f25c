"""Independent Student-t noise per output component: ``v_j ~ St(0, Rv_jj, dof_j)``.

Each component has its own latent scale ``lam_j`` and degrees of freedom, with a diagonal ``Rv``.
A glitch in one sensor then down-weights only that sensor's sample, where the joint multivariate t
(:mod:`.student_t`) down-weights every output of the sample and lets the clean outputs' scale
shrink (docs/noise_models.md has the comparison).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .base import MaskedScale, MeasurementNoise, NoiseEvaluator, standard_gamma, step_views
from .student_t import check_dof_init, dof_relative_standard_error, latent_scale_expectations, solve_dof

__all__ = ["StudentTPerOutputNoise"]


def _log_normaliser(dof: Tensor) -> Tensor:
    """``lgamma((nu+1)/2) - lgamma(nu/2) - log(nu pi)/2`` of each component's t."""
    return torch.lgamma(0.5 * (dof + 1.0)) - torch.lgamma(0.5 * dof) - 0.5 * torch.log(dof * math.pi)


class _PerOutputEvaluator(NoiseEvaluator):
    """Records ``z_j^2`` per component in ``statistics`` ``(T, B, L, p)``."""

    def __init__(self, dof: Tensor, scale: MaskedScale, n_particles: int):
        mask = scale.mask.to(scale.logdet.dtype)  # (T, B, p)
        self.const = (mask * _log_normaliser(dof)).sum(-1) - 0.5 * scale.logdet  # dof: (1, B, p)
        T, B, p = mask.shape
        self.statistics = torch.empty(T, B, n_particles, p, dtype=mask.dtype, device=mask.device)
        self._z2 = self.statistics.unbind(0)
        self._neg_coef = step_views((-0.5 * (dof + 1.0)).expand(T, B, p).unsqueeze(-2))  # (B, 1, p)
        self._inv_nu = step_views((1.0 / dof).expand(T, B, p).unsqueeze(-2))

    def step(self, k: int, z: Tensor) -> Tensor:
        z2 = torch.mul(z, z, out=self._z2[k])
        return (torch.log1p(z2 * self._inv_nu[k]) * self._neg_coef[k]).sum(-1)


@dataclass(frozen=True)
class StudentTPerOutputNoise(MeasurementNoise):
    """``v_j ~ St(0, Rv_jj, dof_j)`` independently per output (diagonal ``Rv``, ``dof`` of shape ``(p,)``)."""

    dof: Tensor

    name = "student-t-per-output"
    CORE_DIMS = {"Rv": 2, "dof": 1}
    per_component = True

    def __post_init__(self):
        off = self.Rv - torch.diag_embed(torch.diagonal(self.Rv, dim1=-2, dim2=-1))
        if bool((off != 0).any()):  # the per-component whitening assumes a diagonal scale
            raise ValueError(
                "Rv_init must be diagonal for noise='student-t-per-output' (independent outputs), "
                f"got off-diagonal entries up to {float(off.abs().max()):.3g}"
            )

    @classmethod
    def initial(cls, Rv: Tensor, dof: float) -> StudentTPerOutputNoise:
        check_dof_init(dof)
        dof_t = torch.full(Rv.shape[-1:], float(dof), dtype=Rv.dtype, device=Rv.device)
        return cls(Rv=Rv, dof=dof_t)

    def evaluator(self, scale: MaskedScale, n_particles: int) -> _PerOutputEvaluator:
        dof = self.per_sequence("dof", scale.logdet.shape[1]).unsqueeze(0)  # (1, B, p)
        return _PerOutputEvaluator(dof, scale, n_particles)

    def log_prob(self, residual: Tensor) -> Tensor:
        var = torch.diagonal(self.Rv)
        z2 = residual.square() / var
        tail = 0.5 * (self.dof + 1) * torch.log1p(z2 / self.dof)
        per = _log_normaliser(self.dof) - 0.5 * torch.log(var) - tail
        return per.sum(-1)

    def latent_expectations(self, statistics, scale, sl):
        B = statistics.shape[1]
        dof = self.per_sequence("dof", B).view(1, B, 1, -1)
        return latent_scale_expectations(statistics[sl], torch.ones((), dtype=dof.dtype), dof)

    def statistics(self, r, W, e_lam, e_log_lam, scale, sl):
        mask = scale.mask[sl].to(r.dtype)  # (t, B, p)
        Wm = W.unsqueeze(-1) * mask.unsqueeze(2)  # (t, B, L, p): zero at missing components
        return {
            "scatter": (Wm * e_lam * r.square()).sum((0, 2)),  # (B, p)
            "n_obs": mask.sum(0),  # (B, p)
            "dof_c": (Wm * (e_log_lam - e_lam)).sum((0, 2)),
        }

    def updated(self, stats, *, fit_Rv, fit_dof, dof_bounds) -> StudentTPerOutputNoise:
        n = stats["n_obs"]
        seen = n > 0
        var = torch.diagonal(self.Rv, dim1=-2, dim2=-1)
        if fit_Rv:
            var = torch.where(seen, stats["scatter"] / n.clamp_min(1), var)
        dof = self.dof
        if fit_dof:
            new = solve_dof(stats["dof_c"] / n.clamp_min(1), *dof_bounds).to(self.dof)
            dof = torch.where(seen, new, self.dof)
        return self.replace(Rv=torch.diag_embed(var), dof=dof)

    def convergence_scales(self, n_obs: int) -> dict[str, Tensor]:
        scales = super().convergence_scales(n_obs)
        scales["dof"] = dof_relative_standard_error(self.dof, 1, n_obs)
        return scales

    def sample(self, shape, generator=None) -> Tensor:
        p = self.Rv.shape[-1]
        z = torch.randn(*shape, p, dtype=self.Rv.dtype, device=self.Rv.device, generator=generator)
        conc = (0.5 * self.dof).expand(*shape, p).contiguous()
        lam = standard_gamma(conc, generator) / (0.5 * self.dof)
        return z * torch.sqrt(torch.diagonal(self.Rv)) / torch.sqrt(lam)
