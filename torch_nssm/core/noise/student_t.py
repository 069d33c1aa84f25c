"""Multivariate Student-t measurement noise ``v ~ St(0, Rv, dof)``, the robust model of the paper.

``v`` is the Gaussian scale mixture ``v | lam ~ N(0, Rv / lam)``, ``lam ~ Gamma(dof/2, rate=dof/2)``:
one latent scale per sample, whose posterior given a residual with squared Mahalanobis norm
``delta2`` over ``p`` observed components is ``Gamma((dof + p)/2, rate=(dof + delta2)/2)``; its
moments weight the M-step (docs/method.md §1, §5).
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
from ..scales import LOG, LOG_CHOLESKY
from .base import (
    DOWNWEIGHTED_SHARE,
    MaskedScale,
    NoiseSpec,
    absorbed_in_runs,
    core_outlier_threshold,
    downweighted_share,
    masked_scale,
    random_source,
    same_at_every_step,
    step_views,
)
from .joint import JointScaleNoise, SquaredNormEvaluator

__all__ = [
    "StudentT",
    "StudentTNoise",
    "student_t_log_prob",
    "latent_scale_expectations",
    "dof_equation",
    "solve_dof",
    "sample_student_t",
    "dof_score",
    "absorbing_message",
]


def student_t_log_prob(delta2: Tensor, logdet: Tensor, n_obs: Tensor, dof: Tensor) -> Tensor:
    """Log-density of a multivariate Student-t (Gaussian where ``dof`` is infinite).

    ``lgamma((nu+p)/2) - lgamma(nu/2) - p/2 log(nu pi) - 1/2 log det R - (nu+p)/2 log(1 + delta2/nu)``
    from the squared Mahalanobis norms ``delta2``, ``log det R`` and the number ``p`` of observed
    components (broadcast together).
    """
    dof = torch.as_tensor(dof, dtype=delta2.dtype, device=delta2.device)
    gauss = -0.5 * (n_obs * math.log(2.0 * math.pi) + logdet + delta2)
    if torch.isinf(dof).all():
        return gauss
    nu = torch.where(torch.isinf(dof), torch.ones_like(dof), dof)
    half = 0.5 * (nu + n_obs)
    t = (
        torch.lgamma(half)
        - torch.lgamma(0.5 * nu)
        - 0.5 * n_obs * torch.log(nu * math.pi)
        - 0.5 * logdet
        - half * torch.log1p(delta2 / nu)
    )
    return torch.where(torch.isinf(dof), gauss, t)


def latent_scale_expectations(
    delta2: Tensor, n_obs: Tensor, dof: Tensor, out: tuple[Tensor, Tensor] | None = None
) -> tuple[Tensor, Tensor]:
    """``<lam> = (nu + p) / (nu + delta2)`` and ``<log lam> = psi((nu+p)/2) - log((nu + delta2)/2)``
    (paper eqs. 27-28); ``1`` and ``0`` where ``dof`` is infinite.

    ``out``: two arrays of the broadcast shape to write ``<lam>`` and ``<log lam>`` into (the same
    values; the second may be ``delta2`` itself, which is then overwritten): five passes over the
    rows and no temporaries of their size, instead of seven passes of which two are the copies.
    """
    dof = torch.as_tensor(dof, dtype=delta2.dtype, device=delta2.device)
    inf = torch.isinf(dof)
    nu = torch.where(inf, torch.ones_like(dof), dof)
    # digamma on the (usually much smaller) broadcast of nu and p only, not per residual
    psi = torch.digamma(0.5 * (nu + n_obs))
    if out is None:
        denominator = nu + delta2
        e_lam = (nu + n_obs) / denominator
        e_log = psi - torch.log(0.5 * denominator)
    else:
        e_lam, e_log = out
        denominator = torch.add(nu, delta2, out=e_lam)  # delta2 read here, and only here
        e_log = torch.log(torch.mul(denominator, 0.5, out=e_log), out=e_log)
        e_log = torch.sub(psi, e_log, out=e_log)
        e_lam = torch.div(nu + n_obs, denominator, out=e_lam)
    if not bool(inf.any()):
        return e_lam, e_log
    if out is not None:
        return e_lam.masked_fill_(inf, 1.0), e_log.masked_fill_(inf, 0.0)
    return (
        torch.where(inf, torch.ones_like(e_lam), e_lam),
        torch.where(inf, torch.zeros_like(e_log), e_log),
    )


def dof_equation(nu: Tensor, c: Tensor) -> Tensor:
    """``h(nu) = 1 + log(nu/2) - psi(nu/2) + c`` (paper eq. 38); decreasing in ``nu``."""
    return 1.0 + torch.log(0.5 * nu) - torch.digamma(0.5 * nu) + c


def solve_dof(c: Tensor, dof_min: float = 0.1, dof_max: float = 1000.0, n_bisect: int = 100) -> Tensor:
    """Root of ``h(nu) = 0`` in ``[dof_min, dof_max]`` (clipped to the bracket), element-wise, float64.

    ``c = mean(<log lam> - <lam>) <= -1`` guarantees a root on ``(0, inf)``.  Bisection on
    ``log nu`` (100 steps: full float64 precision).
    """
    if not 0 < dof_min < dof_max:
        raise ValueError(f"dof bounds must satisfy 0 < dof_min < dof_max, got ({dof_min}, {dof_max})")
    c = torch.as_tensor(c, dtype=torch.float64)
    lo = torch.full_like(c, math.log(dof_min))
    hi = torch.full_like(c, math.log(dof_max))
    for _ in range(n_bisect):
        mid = 0.5 * (lo + hi)
        positive = dof_equation(torch.exp(mid), c) > 0
        lo = torch.where(positive, mid, lo)
        hi = torch.where(positive, hi, mid)
    return torch.exp(0.5 * (lo + hi))


def dof_relative_standard_error(dof: Tensor, p: int, n_obs: int) -> Tensor:
    """``se(dof) / dof`` from the Fisher information of the degrees of freedom of ``n_obs``
    ``p``-variate t samples with a known scale (Lange, Little & Taylor 1989):
    ``I = psi'(v/2)/4 - psi'((v+p)/2)/4 - p (v+p+4) / (2 v (v+p) (v+p+2))``."""
    v = dof.clamp_min(1e-6)
    info = (
        0.25 * (torch.special.polygamma(1, v / 2) - torch.special.polygamma(1, (v + p) / 2))
        - p * (v + p + 4) / (2 * v * (v + p) * (v + p + 2))
    )
    return 1.0 / (v * torch.sqrt(info.clamp_min(1e-300) * max(n_obs, 1)))


def sample_student_t(shape: tuple[int, ...], chol: Tensor, dof: Tensor | float, generator=None) -> Tensor:
    """Draws ``shape + (p,)`` of ``St(0, chol chol^T, dof)`` (Gaussian for infinite ``dof``)."""
    draws = random_source(generator, chol)
    z = draws.standard_normal((*shape, chol.shape[-1])) @ chol.transpose(-1, -2)
    return _scale_mixture(z, dof, draws)


def _scale_mixture(z: Tensor, dof: Tensor | float, draws) -> Tensor:
    """Gaussian draws ``z`` ``(..., p)`` over the square roots of ``Gamma(dof/2, rate=dof/2)`` draws,
    one per row: Student-t draws (``z`` itself for infinite ``dof``)."""
    dof = float(dof)
    if math.isinf(dof):
        return z
    conc = torch.full(z.shape[:-1], 0.5 * dof, dtype=z.dtype, device=z.device)
    return draws.scale_mixture(z, conc, 0.5 * dof)


def dof_score(nu: Tensor, delta2: Tensor, p: float) -> Tensor:
    """``d/d log nu`` of the Student-t log-density with ``p`` components at squared distance
    ``delta2``."""
    return (
        0.5 * nu * (torch.digamma(0.5 * (nu + p)) - torch.digamma(0.5 * nu) - torch.log1p(delta2 / nu))
        - 0.5 * p + 0.5 * (nu + p) * delta2 / (nu + delta2)
    )


def check_dof(dof, name: str = "dof_init") -> None:
    """Degrees of freedom (a number or an array of them) must be positive and finite; ``name``: the
    argument that gave them."""
    values = np.asarray(dof, dtype=float)
    if not np.all((values > 0) & (values < math.inf)):
        raise ValueError(
            f"{name} must be positive and finite for Student-t noise, got {dof!r} "
            "(use noise='gaussian' for the Gaussian limit)"
        )


def check_bounds(bounds, name: str = "dof_bounds") -> tuple[float, float]:
    """A bracket ``(low, high)`` with ``0 < low < high``, as floats."""
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a pair (low, high), got {bounds!r}") from exc
    if not 0 < lo < hi:
        raise ValueError(f"{name} must satisfy 0 < low < high, got {bounds!r}")
    return lo, hi


#: A fitted dof below this (tails heavier than Cauchy's) is reported after the fit, as are more
#: than DOWNWEIGHTED_SHARE of the samples with an outlier weight below 0.5: the noise model may be
#: absorbing model error (genuinely Cauchy noise down-weights about a third of the samples).
DOF_FLOOR = 1.0


def absorbing_message(dof, weights) -> str | None:
    """Words for a Student-t fit whose noise model explains too much (``None`` if it does not):
    ``dof`` (one or one per output) below :data:`DOF_FLOOR` or too many down-weighted samples, and
    the down-weighted samples in runs (:func:`absorbed_in_runs`).  A low dof with isolated
    down-weighted samples is what gross, isolated glitches give (a Student-t fits a clean bulk with
    far spikes by a dof near 1): nothing to report."""
    share = downweighted_share(weights)
    low = np.min(np.atleast_1d(dof)) < DOF_FLOOR
    if not low and share <= DOWNWEIGHTED_SHARE:
        return None
    if not absorbed_in_runs(weights):
        return None
    return (
        f"the measurement noise absorbs much of the data: dof {np.round(np.atleast_1d(dof), 2).tolist()}, "
        f"{100 * share:.0f} % of the samples have an outlier weight below 0.5. Unless the sensor "
        "noise really is that heavy-tailed, the noise model is absorbing what f and g cannot explain "
        "(model error, not outliers): check the residuals (torch_nssm.diagnostics), raise the lower "
        "dof bound (dof_bounds=(2.0, 1000.0)) or hold it (fit_dof=False), or improve the model"
    )


@dataclass(frozen=True)
class StudentT(NoiseSpec):
    """Multivariate Student-t measurement noise ``v ~ St(0, Rv, dof)`` (``noise="student-t"``): one
    latent scale per sample, shared by all outputs.

    Parameters
    ----------
    dof : float, default=5.0
        Initial degrees of freedom (positive and finite).
    fit_dof : bool, default=True
        Estimate the degrees of freedom; if False they stay at ``dof``.
    dof_bounds : (float, float), default=(0.1, 1000.0)
        Bracket of the degrees-of-freedom root-solve (and of their extrapolation).
    """

    dof: float = 5.0
    fit_dof: bool = True
    dof_bounds: tuple[float, float] = (0.1, 1000.0)

    name = "student-t"

    def __post_init__(self):
        V.check_positive(self.dof, "dof")
        check_dof(self.dof, "dof")
        object.__setattr__(self, "dof", float(self.dof))
        object.__setattr__(self, "fit_dof", bool(self.fit_dof))
        object.__setattr__(self, "dof_bounds", check_bounds(self.dof_bounds))

    @classmethod
    def from_shortcuts(cls, dof_init=5.0, fit_dof=True, dof_bounds=(0.1, 1000.0), **ignored: Any) -> StudentT:
        V.check_positive(dof_init, "dof_init")
        check_dof(dof_init, "dof_init")
        return cls(dof=float(dof_init), fit_dof=bool(fit_dof), dof_bounds=check_bounds(dof_bounds))

    def initial(self, Rv: Tensor) -> StudentTNoise:
        return StudentTNoise.initial(Rv, self.dof, spec=self)

    def starting_at(self, noise: StudentTNoise) -> StudentT:
        return dataclasses.replace(self, dof=float(noise.dof))

    def initial_shortcuts(self) -> dict[str, Any]:
        return {"dof_init": self.dof}


class _StudentTEvaluator(SquaredNormEvaluator):
    """The filter's fused log-density: ``-(nu + p)/2 log1p(delta2 / nu)`` with the per-``(T, B)``
    coefficients split into per-step views once per pass."""

    def __init__(self, dof: Tensor, scale: MaskedScale, n_particles: int):
        logdet, n_obs = scale.logdet, scale.n_obs
        if same_at_every_step(logdet) and same_at_every_step(n_obs):  # nothing missing: one step's
            # constants, expanded (the lgamma of every (T, B) entry cost ~3 ms at T = 1000, B = 100)
            const = student_t_log_prob(torch.zeros_like(logdet[:1]), logdet[:1], n_obs[:1], dof)
            const = const.expand_as(logdet)
        else:
            const = student_t_log_prob(torch.zeros_like(logdet), logdet, n_obs, dof)
        super().__init__(const, n_particles)
        self._neg_coef = step_views((-0.5 * (dof + scale.n_obs))[..., None, None])  # (B, 1, 1) per step
        self._inv_nu = step_views((1.0 / dof).expand_as(const)[..., None, None])

    def step(self, k: int, z: Tensor) -> Tensor:
        delta2 = self.squared_norm(k, z)  # (B, L, 1)
        torch.log1p_(torch.mul(delta2, self._inv_nu[k], out=self._logits_col)).mul_(self._neg_coef[k])
        return self._logits


@dataclass(frozen=True)
class StudentTNoise(JointScaleNoise):
    """``v ~ St(0, Rv, dof)``: one latent scale per sample, shared by all output components."""

    dof: Tensor

    name = "student-t"
    SPEC = StudentT
    CORE_DIMS = {"Rv": 2, "dof": 0}
    WORKING = {"Rv": LOG_CHOLESKY, "dof": LOG}

    @classmethod
    def initial(cls, Rv: Tensor, dof: float, spec: StudentT | None = None) -> StudentTNoise:
        """The noise of scale ``Rv`` with ``dof`` degrees of freedom (positive and finite)."""
        check_dof(dof)
        return cls(Rv=Rv, dof=torch.tensor(float(dof), dtype=Rv.dtype, device=Rv.device), spec=spec)

    def admissible(self, name: str, value: Tensor) -> Tensor:
        """Finite, and ``dof = inf`` (the Gaussian limit)."""
        finite = torch.isfinite(value)
        return finite | (torch.isinf(value) & (value > 0)) if name == "dof" else finite

    def absorption_message(self, weights) -> str | None:
        return absorbing_message(self.attributes()["dof"], weights)

    def outlier_threshold(self, weights=None) -> np.ndarray:
        return core_outlier_threshold(self.attributes()["dof"], self.n_outputs, weights)

    def evaluator(self, scale: MaskedScale, n_particles: int) -> _StudentTEvaluator:
        dof = self.per_sequence("dof", scale.logdet.shape[1]).unsqueeze(0)  # (1, B)
        return _StudentTEvaluator(dof, scale, n_particles)

    def log_prob(self, residual: Tensor) -> Tensor:
        mask = torch.ones(residual.shape[-1:], dtype=torch.bool, device=residual.device)
        s = masked_scale(self.Rv, mask)
        z = residual @ s.chol_inv.transpose(-1, -2)
        return student_t_log_prob((z * z).sum(-1), s.logdet, s.n_obs, self.dof)

    def latent_expectations(self, statistics, scale, sl, out=None):
        """As :meth:`MeasurementNoise.latent_expectations`; ``out``: the block's arrays to write
        into (:func:`latent_scale_expectations`)."""
        B = statistics.shape[1]
        dof = self.per_sequence("dof", B).view(1, B, 1)
        return latent_scale_expectations(statistics[sl], scale.n_obs[sl].unsqueeze(-1), dof, out)

    def statistics(self, r, W, e_lam, e_log_lam, scale, sl):
        stats = super().statistics(r, W, e_lam, e_log_lam, scale, sl)
        stats["dof_c"] = (W * (e_log_lam - e_lam)).sum((0, 2))
        return stats

    def updated(self, stats, *, fit_Rv=True, fit_shape=True) -> StudentTNoise:
        dof = self.dof
        if fit_shape and self.spec.fit_dof:
            c = stats["dof_c"] / stats["n_obs"].clamp_min(1)
            dof = solve_dof(c, *self.spec.dof_bounds).to(self.dof).reshape(self.dof.shape)
        return self.replace(Rv=self._updated_scale(stats, fit_Rv), dof=dof)

    def sample(self, shape, generator=None) -> Tensor:
        draws = random_source(generator, self.Rv)
        return _scale_mixture(draws.gaussian(shape, self.Rv), self.dof, draws)

    # ------------------------------------------------------------------ the observed information
    def estimated(self, fit_Rv=True, fit_shape=True) -> list[str]:
        """``Rv`` if ``fit_Rv``; ``dof`` if ``fit_shape``, the specification's ``fit_dof`` and finite."""
        names = ["Rv"] if fit_Rv else []
        if fit_shape and self.spec.fit_dof and bool(torch.isfinite(self.dof).all()):
            names.append("dof")
        return names

    def bounds(self, name: str) -> tuple[float, float] | None:
        return self.spec.dof_bounds if name == "dof" else None

    @property
    def is_gaussian(self) -> bool:
        """Infinite degrees of freedom."""
        return not bool(torch.isfinite(self.dof).all())

    def density_of_norms(self, delta2, logdet, n_obs) -> Tensor:
        if self.is_gaussian:
            return -0.5 * (n_obs * math.log(2 * math.pi) + logdet + delta2)
        dof = self.dof
        half = 0.5 * (dof + n_obs)
        return (
            torch.lgamma(half) - torch.lgamma(0.5 * dof) - 0.5 * n_obs * torch.log(dof * math.pi)
            - 0.5 * logdet - half * torch.log1p(delta2 / dof)
        )

    def latent_weight(self, delta2, p, weight):
        """``lam = (nu + p) / (nu + delta2)``; the score in ``log nu`` is :func:`dof_score`."""
        if self.is_gaussian:
            return torch.ones_like(delta2), {}
        nu = self.dof
        lam = (nu + p) / (nu + delta2)
        return lam, {"dof": weight * dof_score(nu, delta2, float(p)).unsqueeze(-1)}

    @property
    def elliptical(self) -> bool:
        return not self.is_gaussian

    def elliptical_terms(self, q, p, names=()):
        """``h(q) = c(nu) - (nu + p) / 2 log(1 + q / nu)``: ``lam = (nu + p) / (nu + q)``,
        ``h_qq = (nu + p) / (2 (nu + q)^2)``, and in ``log nu`` the cross term
        ``-nu (q - p) / (2 (nu + q)^2)`` and the second derivative ``nu l_nu + nu^2 l_nunu``."""
        if self.is_gaussian:
            return None
        nu = self.dof
        lam = (nu + p) / (nu + q)
        h_qq = (nu + p) / (2.0 * (nu + q) ** 2)
        shape = {}
        if "dof" in names:
            cross = -nu * (q - p) / (2.0 * (nu + q) ** 2)
            l_nu = (
                0.5 * torch.digamma(0.5 * (nu + p)) - 0.5 * torch.digamma(0.5 * nu) - 0.5 * p / nu
                - 0.5 * torch.log1p(q / nu) + 0.5 * (nu + p) * q / (nu * (nu + q))
            )
            l_nunu = (
                0.25 * torch.polygamma(1, 0.5 * (nu + p)) - 0.25 * torch.polygamma(1, 0.5 * nu)
                + 0.5 * p / nu**2
                + 0.5 * q / (nu * (nu + q))
                + 0.5 * q * (nu * (nu + q) - (nu + p) * (2.0 * nu + q)) / (nu**2 * (nu + q) ** 2)
            )
            shape["dof"] = (cross, nu * l_nu + nu**2 * l_nunu)
        return lam, h_qq, shape

    def convergence_scales(self, n_obs: int) -> dict[str, Tensor]:
        scales = super().convergence_scales(n_obs)
        scales["dof"] = dof_relative_standard_error(self.dof, self.Rv.shape[-1], n_obs)
        return scales
