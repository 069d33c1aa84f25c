"""Independent Student-t noise per output component: ``v_j ~ St(0, Rv_jj, dof_j)``.

Each component has its own latent scale ``lam_j`` and degrees of freedom, with a diagonal ``Rv``.
A glitch in one sensor then down-weights only that sensor's sample, where the joint multivariate t
(:mod:`.student_t`) down-weights every output of the sample and lets the clean outputs' scale
shrink (docs/noise_models.md has the comparison).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ... import _validation as V
from ..scales import LOG, LOG_DIAGONAL
from .base import (
    MaskedScale,
    MeasurementNoise,
    NoiseEvaluator,
    NoiseSpec,
    core_outlier_threshold,
    random_source,
    step_views,
)
from .student_t import (
    absorbing_message,
    check_bounds,
    check_dof,
    dof_relative_standard_error,
    dof_score,
    latent_scale_expectations,
    solve_dof,
)

__all__ = ["StudentTPerOutput", "StudentTPerOutputNoise"]


def _check_dofs(dof, name: str) -> float | tuple[float, ...]:
    """One positive finite number, or a sequence of them (one per output), as floats."""
    if np.ndim(dof) == 0:
        V.check_positive(dof, name)
        check_dof(dof, name)
        return float(dof)
    try:
        values = tuple(float(d) for d in np.asarray(dof, dtype=float).reshape(-1))
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a number or one number per output, got {dof!r}") from exc
    check_dof(values, name)
    return values


@dataclass(frozen=True)
class StudentTPerOutput(NoiseSpec):
    """Independent Student-t noise per output ``v_j ~ St(0, Rv_jj, dof_j)``
    (``noise="student-t-per-output"``): one latent scale and one ``dof`` per output, diagonal ``Rv``.

    Parameters
    ----------
    dof : float or sequence of float, default=5.0
        Initial degrees of freedom: one for every output, or one per output.
    fit_dof : bool, default=True
        Estimate the degrees of freedom; if False they stay at ``dof``.
    dof_bounds : (float, float), default=(0.1, 1000.0)
        Bracket of the degrees-of-freedom root-solves (and of their extrapolation).
    """

    dof: float | tuple[float, ...] = 5.0
    fit_dof: bool = True
    dof_bounds: tuple[float, float] = (0.1, 1000.0)

    name = "student-t-per-output"

    def __post_init__(self):
        object.__setattr__(self, "dof", _check_dofs(self.dof, "dof"))
        object.__setattr__(self, "fit_dof", bool(self.fit_dof))
        object.__setattr__(self, "dof_bounds", check_bounds(self.dof_bounds))

    @classmethod
    def from_shortcuts(
        cls, dof_init=5.0, fit_dof=True, dof_bounds=(0.1, 1000.0), **ignored: Any
    ) -> StudentTPerOutput:
        dof = _check_dofs(dof_init, "dof_init")
        return cls(dof=dof, fit_dof=bool(fit_dof), dof_bounds=check_bounds(dof_bounds))

    def initial(self, Rv: Tensor) -> StudentTPerOutputNoise:
        return StudentTPerOutputNoise.initial(Rv, self.dof, spec=self)

    def starting_at(self, noise: StudentTPerOutputNoise) -> StudentTPerOutput:
        return dataclasses.replace(self, dof=tuple(float(d) for d in noise.dof.reshape(-1)))

    def initial_shortcuts(self) -> dict[str, Any]:
        return {"dof_init": self.dof if isinstance(self.dof, float) else np.asarray(self.dof)}


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
    SPEC = StudentTPerOutput
    CORE_DIMS = {"Rv": 2, "dof": 1}
    WORKING = {"Rv": LOG_DIAGONAL, "dof": LOG}
    per_component = True

    def __post_init__(self):
        super().__post_init__()
        off = self.Rv - torch.diag_embed(torch.diagonal(self.Rv, dim1=-2, dim2=-1))
        if bool((off != 0).any()):  # the per-component whitening assumes a diagonal scale
            raise ValueError(
                "Rv_init must be diagonal for noise='student-t-per-output' (independent outputs), "
                f"got off-diagonal entries up to {float(off.abs().max()):.3g}"
            )

    @classmethod
    def initial(cls, Rv: Tensor, dof, spec: StudentTPerOutput | None = None) -> StudentTPerOutputNoise:
        """The noise of (diagonal) scale ``Rv`` with ``dof`` degrees of freedom: one number for every
        output or one per output (positive and finite)."""
        check_dof(dof)
        p = Rv.shape[-1]
        if np.ndim(dof) == 0:
            dof_t = torch.full(Rv.shape[-1:], float(dof), dtype=Rv.dtype, device=Rv.device)
        elif np.size(dof) == p:
            dof_t = torch.as_tensor(np.asarray(dof, dtype=float).reshape(p), dtype=Rv.dtype, device=Rv.device)
        else:
            raise ValueError(f"dof_init must be one number or {p} (one per output), got {np.size(dof)}")
        return cls(Rv=Rv, dof=dof_t, spec=spec)

    def admissible(self, name: str, value: Tensor) -> Tensor:
        """Finite, and ``dof = inf`` (the Gaussian limit)."""
        finite = torch.isfinite(value)
        return finite | (torch.isinf(value) & (value > 0)) if name == "dof" else finite

    def absorption_message(self, weights) -> str | None:
        return absorbing_message(self.attributes()["dof"], weights)

    def outlier_threshold(self, weights=None) -> np.ndarray:
        return core_outlier_threshold(self.attributes()["dof"], 1, weights)  # one per output

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

    def updated(self, stats, *, fit_Rv=True, fit_shape=True) -> StudentTPerOutputNoise:
        n = stats["n_obs"]
        seen = n > 0
        var = torch.diagonal(self.Rv, dim1=-2, dim2=-1)
        if fit_Rv:
            var = torch.where(seen, stats["scatter"] / n.clamp_min(1), var)
        dof = self.dof
        if fit_shape and self.spec.fit_dof:
            new = solve_dof(stats["dof_c"] / n.clamp_min(1), *self.spec.dof_bounds).to(self.dof)
            dof = torch.where(seen, new, self.dof)
        return self.replace(Rv=torch.diag_embed(var), dof=dof)

    def convergence_scales(self, n_obs: int) -> dict[str, Tensor]:
        scales = super().convergence_scales(n_obs)
        scales["dof"] = dof_relative_standard_error(self.dof, 1, n_obs)
        return scales

    def sample(self, shape, generator=None) -> Tensor:
        draws = random_source(generator, self.Rv)
        p = self.Rv.shape[-1]
        z = draws.standard_normal((*shape, p))
        conc = (0.5 * self.dof).expand(*shape, p).contiguous()
        return draws.scale_mixture(z * torch.sqrt(torch.diagonal(self.Rv)), conc, 0.5 * self.dof)

    # ------------------------------------------------------------------ the observed information
    def estimated(self, fit_Rv=True, fit_shape=True) -> list[str]:
        """``Rv`` if ``fit_Rv``; ``dof`` if ``fit_shape``, the specification's ``fit_dof`` and finite."""
        names = ["Rv"] if fit_Rv else []
        if fit_shape and self.spec.fit_dof and bool(torch.isfinite(self.dof).all()):
            names.append("dof")
        return names

    def bounds(self, name: str) -> tuple[float, float] | None:
        return self.spec.dof_bounds if name == "dof" else None

    def residual_log_prob(self, r, mask, all_observed) -> Tensor:
        m = mask.to(r.dtype)
        dof = self.dof
        var = torch.diagonal(self.Rv)
        half = 0.5 * (dof + 1.0)
        per = (
            torch.lgamma(half) - torch.lgamma(0.5 * dof) - 0.5 * torch.log(dof * math.pi)
            - 0.5 * torch.log(var) - half * torch.log1p(r * r / (var * dof))
        )
        return (per * m).sum(-1)

    def scores_in_closed_form(self, all_observed: bool) -> bool:
        return True

    def residual_scores(self, r, mask, weight):
        """Per component ``j`` with ``d2 = r_j^2 / Rv_jj`` and ``lam = (nu_j + 1) / (nu_j + d2)``: the
        gradient in the mean is ``lam r_j / Rv_jj``, in ``log Rv_jj`` ``(lam d2 - 1) / 2``, in
        ``log nu_j`` :func:`~.student_t.dof_score`."""
        m = weight * mask.to(r.dtype)
        var = torch.diagonal(self.Rv)
        nu = self.dof.expand(var.shape)
        d2 = r * r / var
        lam = (nu + 1.0) / (nu + d2)
        grad_mu = m * lam * r / var
        per = m * dof_score(nu, d2, 1.0)
        scores = {
            "Rv": m * (0.5 * lam * d2 - 0.5),
            "dof": per if self.dof.numel() == var.numel() else per.sum(-1, keepdim=True),
        }
        return grad_mu, scores
