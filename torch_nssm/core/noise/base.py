"""The measurement-noise protocol and the masked scale matrix shared by every noise family.

A noise family is a frozen dataclass of tensors (its parameters, e.g. ``Rv`` and ``dof``) that
subclasses :class:`MeasurementNoise` and implements a handful of methods:

* the filter's per-step log-density (:meth:`MeasurementNoise.evaluator`), its hot loop;
* the E-step's latent-scale expectations (:meth:`~MeasurementNoise.latent_expectations`);
* the M-step's sufficient statistics and closed-form update (:meth:`~MeasurementNoise.statistics`,
  :meth:`~MeasurementNoise.updated`);
* sampling (:meth:`~MeasurementNoise.sample`) and a plain log-density (:meth:`~MeasurementNoise.log_prob`).

Parameters may carry a leading batch dimension (one model per data set in independent fits).
Missing output components are handled by masking the scale matrix (:func:`masked_scale`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

__all__ = ["MeasurementNoise", "NoiseEvaluator", "MaskedScale", "masked_scale", "step_views", "symmetric_pd"]


@dataclass
class MaskedScale:
    """Scale matrix restricted to the observed components of each sample.

    Attributes
    ----------
    chol_inv : Tensor, shape (..., p, p)
        Inverse of the lower Cholesky factor of ``M R M + (I - M)``; ``chol_inv @ r`` whitens a
        residual ``r`` that is zero where missing.
    logdet : Tensor, shape (...)
        ``log det`` of the observed block of ``R``.
    n_obs : Tensor, shape (...)
        Number of observed components.
    mask : Tensor, shape (..., p), bool
        True where the component is observed.
    """

    chol_inv: Tensor
    logdet: Tensor
    n_obs: Tensor
    mask: Tensor

    def select(self, index) -> MaskedScale:
        """The scales of the sequences ``index`` (second dimension of time-major ``(T, B, ...)``)."""
        return MaskedScale(
            self.chol_inv[:, index], self.logdet[:, index], self.n_obs[:, index], self.mask[:, index]
        )

    def whitener(self) -> Tensor:
        """``chol_inv`` with zero columns at the missing components: applied to a residual whose
        missing entries are finite (see :meth:`fill_missing`), it needs no mask."""
        return self.chol_inv * self.mask.unsqueeze(-2).to(self.chol_inv.dtype)

    def precision(self) -> Tensor:
        """``R^-1`` on the observed block, zero rows and columns at the missing components."""
        m = self.mask.to(self.chol_inv.dtype)
        return (self.chol_inv.transpose(-1, -2) @ self.chol_inv) * m.unsqueeze(-1) * m.unsqueeze(-2)

    def fill_missing(self, y: Tensor) -> Tensor:
        """Outputs ``y`` (shape of the mask) with the missing entries set to 0."""
        return torch.where(self.mask, y, torch.zeros_like(y))


def masked_scale(R: Tensor, mask: Tensor) -> MaskedScale:
    """The per-sample scale of the observed components of ``R`` ``(..., p, p)`` under ``mask``."""
    m = mask.to(R.dtype)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    Rm = R * m.unsqueeze(-1) * m.unsqueeze(-2) + eye * (1.0 - m).unsqueeze(-1)
    if R.shape[-1] == 1 and bool((Rm > 0).all()):  # one output: the 1 x 1 Cholesky factor is the
        # square root and its inverse the reciprocal, the same values as LAPACK's (4x cheaper at
        # T = 1000, B = 100: 2 vs 8.5 ms per filter pass); a scale that is not positive goes
        # through cholesky below, which raises
        chol = torch.sqrt(Rm)
        chol_inv = torch.reciprocal(chol)
    else:
        chol = torch.linalg.cholesky(Rm)
        chol_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return MaskedScale(chol_inv=chol_inv, logdet=logdet, n_obs=m.sum(-1), mask=mask)


def step_views(values: Tensor) -> Sequence[Tensor]:
    """The views ``values[k]`` of every step ``k`` of a time-major ``values``, for a loop over the
    steps (indexing a list is free, a tensor select is an operation).

    Parameters
    ----------
    values : Tensor, shape (T, ...)

    Returns
    -------
    list or tuple of Tensor
        One view repeated ``T`` times (a list) when every step holds the same values (e.g. a
        whitener or a Student-t coefficient of records without missing outputs), else
        ``values.unbind(0)``.
    """
    if same_at_every_step(values):
        return [values[0]] * values.shape[0]
    return values.unbind(0)


def same_at_every_step(values: Tensor) -> bool:
    """Whether the time-major ``values`` ``(T, ...)`` (``T > 1``) hold the same values at every step."""
    return values.shape[0] > 1 and torch.equal(values, values[:1].expand_as(values))


def symmetric_pd(S: Tensor, jitter: float = 0.0) -> Tensor:
    """The symmetric part of ``S``, plus ``jitter`` times its mean diagonal on the diagonal."""
    S = 0.5 * (S + S.transpose(-1, -2))
    if jitter > 0:
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        mean_diag = torch.diagonal(S, dim1=-2, dim2=-1).mean(-1).abs() + 1e-300
        S = S + jitter * eye * mean_diag[..., None, None]
    return S


class NoiseEvaluator:
    """The filter's view of a noise model for one pass over a batch.

    Attributes
    ----------
    const : Tensor, shape (T, B)
        The part of each step's log-density that does not depend on the particles.
    statistics : Tensor, shape (T, B, L, ...)
        Filled by :meth:`step`: what the latent-scale expectations need of each particle's residual.
    """

    const: Tensor
    statistics: Tensor

    def step(self, k: int, z: Tensor) -> Tensor:
        """Log-density minus ``const[k]`` of the whitened residuals ``z`` ``(B, L, p)`` of step
        ``k`` (zero at missing components), shape ``(B, L)``; records ``statistics[k]``.  The
        result may be modified in place by the caller, and may be an array of the evaluator's own
        that the next call overwrites."""
        raise NotImplementedError


@dataclass(frozen=True)
class MeasurementNoise:
    """Base class of the measurement-noise families (see the module docstring).

    Every family has the scale matrix ``Rv`` of shape ``(..., p, p)``; the other fields are
    family-specific parameters.  ``CORE_DIMS`` gives each field's number of non-batch dimensions.
    """

    Rv: Tensor

    #: Registry name (the estimator's ``noise=`` value).
    name: ClassVar[str] = ""
    #: Non-batch dimensions of each parameter.
    CORE_DIMS: ClassVar[dict[str, int]] = {"Rv": 2}
    #: Whether the latent scales are per output component (shape ``(..., p)``) or per sample.
    per_component: ClassVar[bool] = False

    # ------------------------------------------------------------------ construction, batching
    @classmethod
    def initial(cls, Rv: Tensor, dof: float) -> MeasurementNoise:
        """The noise model at the estimator's initial values (``dof`` ignored where unused)."""
        raise NotImplementedError

    def parameters(self) -> dict[str, Tensor]:
        """The parameters by name (the keys of ``history_``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def replace(self, **params: Any) -> MeasurementNoise:
        return dataclasses.replace(self, **params)

    def to(self, **kwargs: Any) -> MeasurementNoise:
        return self.replace(**{k: v.to(**kwargs) for k, v in self.parameters().items()})

    @property
    def n_outputs(self) -> int:
        return self.Rv.shape[-1]

    @property
    def batched(self) -> bool:
        return self.Rv.dim() > 2

    def per_sequence(self, name: str, n_sequences: int) -> Tensor:
        """Parameter ``name`` with a leading batch dimension of ``n_sequences``."""
        value = getattr(self, name)
        if value.dim() == self.CORE_DIMS[name]:
            return value.expand(n_sequences, *value.shape)
        return value

    @classmethod
    def stack(cls, noises: list[MeasurementNoise]) -> MeasurementNoise:
        """One batched noise model from unbatched ones (independent fits)."""
        names = noises[0].parameters()
        return cls(**{n: torch.stack([getattr(m, n) for m in noises]) for n in names})

    def unstack(self) -> list[MeasurementNoise]:
        """The unbatched noise models of a batched one."""
        params = self.parameters()
        return [self.replace(**{n: v[b] for n, v in params.items()}) for b in range(self.Rv.shape[0])]

    def convergence_scales(self, n_obs: int) -> dict[str, Tensor]:
        """The relative standard error of each positive parameter (complete data: the latent scales
        known) at ``n_obs`` observations, by name: EM has converged in a parameter once its changes
        are small against this (:func:`torch_nssm.estimation.convergence.has_converged`).  A
        variance estimated from ``n`` samples has relative standard error ``sqrt(2 / n)``."""
        return {"Rv": torch.full_like(self.Rv, math.sqrt(2.0 / max(n_obs, 1)))}

    def is_valid(self) -> Tensor:
        """Finite parameters and a positive-definite ``Rv``, per batch entry (shape ``(...)``)."""
        ok = torch.linalg.cholesky_ex(self.Rv).info == 0
        for name, v in self.parameters().items():
            core = self.CORE_DIMS[name]
            finite = torch.isfinite(v) | (torch.isinf(v) & (v > 0) if name == "dof" else False)
            ok = ok & (finite.flatten(v.dim() - core).all(-1) if core else finite)
        return ok

    # ------------------------------------------------------------------ the filter
    def evaluator(self, scale: MaskedScale, n_particles: int) -> NoiseEvaluator:
        """The per-step log-density of the filter for the batch whose masked scale is ``scale``."""
        raise NotImplementedError

    def log_prob(self, residual: Tensor) -> Tensor:
        """Log-density of fully observed residuals ``(..., p)`` (unbatched parameters)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ E-step and M-step
    def latent_expectations(self, statistics: Tensor, scale: MaskedScale, sl: slice) -> tuple[Tensor, Tensor]:
        """``<lam>`` and ``<log lam>`` of each particle from the filter's ``statistics`` of the
        time block ``sl`` (``scale`` is the whole pass's).  Shape ``(t, B, L)``, or
        ``(t, B, L, p)`` for per-component scales."""
        raise NotImplementedError

    def statistics(
        self, r: Tensor, W: Tensor, e_lam: Tensor, e_log_lam: Tensor, scale: MaskedScale, sl: slice
    ) -> dict[str, Tensor]:
        """The M-step's sufficient statistics of one time block, summed per sequence ``(B, ...)``.

        Parameters
        ----------
        r : Tensor, shape (t, B, L, p)
            Output residuals ``y - g(x, u)`` at the new ``theta_g``, zero where missing.
        W : Tensor, shape (t, B, L)
            Smoothing weights, zero at steps without an observation.
        e_lam, e_log_lam : Tensor
            The latent-scale expectations of the block.
        scale : MaskedScale
            The E-step's masked scale (whole pass); ``sl`` selects the block.
        """
        raise NotImplementedError

    def updated(
        self, stats: dict[str, Tensor], *, fit_Rv: bool, fit_dof: bool, dof_bounds
    ) -> MeasurementNoise:
        """The closed-form update from pooled ``stats`` (as from :meth:`statistics`, batch as
        this model's)."""
        raise NotImplementedError

    def sample(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """Draws of shape ``shape + (p,)`` (unbatched parameters)."""
        raise NotImplementedError


def gaussian_log_normaliser(n_obs: Tensor, logdet: Tensor) -> Tensor:
    """``-(p log(2 pi) + log det R) / 2``."""
    return -0.5 * (n_obs * math.log(2.0 * math.pi) + logdet)


def standard_gamma(concentration: Tensor, generator: torch.Generator | None) -> Tensor:
    """``Gamma(concentration, 1)`` draws, reproducible with ``generator`` (torch's sampler has no
    generator argument: the global stream is seeded from it and restored)."""
    if generator is None:
        return torch._standard_gamma(concentration)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device))
    device = concentration.device
    with torch.random.fork_rng(devices=[] if device.type == "cpu" else [device]):
        torch.manual_seed(seed)
        return torch._standard_gamma(concentration)
