"""Gaussian measurement noise ``v ~ N(0, Rv)``: the non-robust baseline (Gopaluni 2008)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .base import MaskedScale, NoiseSpec, gaussian_log_normaliser, masked_scale, random_source
from .joint import JointScaleNoise, SquaredNormEvaluator

__all__ = ["Gaussian", "GaussianNoise"]


@dataclass(frozen=True)
class Gaussian(NoiseSpec):
    """Gaussian measurement noise ``v ~ N(0, Rv)``: the non-robust baseline (``noise="gaussian"``).

    It has no parameter besides ``Rv``, so it ignores the estimator's ``dof_init``, ``fit_dof`` and
    ``dof_bounds``.
    """

    name = "gaussian"


class _GaussianEvaluator(SquaredNormEvaluator):
    """``-|z|^2 / 2``.  Records nothing in ``statistics`` (which the E-step keeps as storage): the
    latent scales of Gaussian noise are 1 whatever the residuals, and with one output the
    log-density is then one multiply-add a step instead of two operations."""

    def __init__(self, const: Tensor, n_particles: int):
        super().__init__(const, n_particles, records=False)
        self._zero = torch.zeros((), dtype=const.dtype, device=const.device)

    def step(self, k: int, z: Tensor) -> Tensor:
        if z.shape[-1] == 1:
            torch.addcmul(self._zero, z, z, value=-0.5, out=self._logits_col)
        else:
            torch.sum(z * z, dim=-1, keepdim=True, out=self._logits_col).mul_(-0.5)
        return self._logits


@dataclass(frozen=True)
class GaussianNoise(JointScaleNoise):
    """``v ~ N(0, Rv)``: every latent scale is 1, so no sample is down-weighted."""

    name = "gaussian"
    SPEC = Gaussian

    def attributes(self):
        """``Rv``, and ``dof = inf`` (the Student-t limit), so that Gaussian and robust fits compare
        attribute by attribute."""
        return {**super().attributes(), "dof": math.inf}

    def evaluator(self, scale: MaskedScale, n_particles: int) -> _GaussianEvaluator:
        return _GaussianEvaluator(gaussian_log_normaliser(scale.n_obs, scale.logdet), n_particles)

    def log_prob(self, residual: Tensor) -> Tensor:
        mask = torch.ones(residual.shape[-1:], dtype=torch.bool, device=residual.device)
        s = masked_scale(self.Rv, mask)
        z = residual @ s.chol_inv.transpose(-1, -2)
        return gaussian_log_normaliser(s.n_obs, s.logdet) - 0.5 * (z * z).sum(-1)

    def latent_expectations(self, statistics, scale, sl):
        ones = torch.ones((), dtype=statistics.dtype, device=statistics.device)
        shape = statistics[sl].shape
        return ones.expand(shape), torch.zeros_like(ones).expand(shape)

    def updated(self, stats, *, fit_Rv=True, fit_shape=True) -> GaussianNoise:
        return self.replace(Rv=self._updated_scale(stats, fit_Rv))

    def sample(self, shape, generator=None) -> Tensor:
        return random_source(generator, self.Rv).gaussian(shape, self.Rv)

    # ------------------------------------------------------------------ the observed information
    @property
    def is_gaussian(self) -> bool:
        return True

    def density_of_norms(self, delta2, logdet, n_obs) -> Tensor:
        return -0.5 * (n_obs * math.log(2 * math.pi) + logdet + delta2)

    def latent_weight(self, delta2, p, weight):
        return torch.ones_like(delta2), {}
