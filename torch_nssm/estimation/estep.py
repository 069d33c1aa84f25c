"""The E-step: particle filter, particle smoother and the noise model's latent-scale expectations."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from .._ops import time_blocks
from ..core.model import SequenceBatch, StateSpaceModel
from ..inference.filtering import FilterOutput, particle_filter
from ..inference.smoothers import get_smoother
from ..inference.smoothing import SmootherOutput

__all__ = ["EStepOutput", "EStepOptions", "e_step", "latent_scales", "outlier_weights"]


@dataclass
class EStepOutput:
    """Filter, smoother and latent-scale expectations at the current parameters.

    Attributes
    ----------
    filter : FilterOutput
    smoother : SmootherOutput
    e_lam, e_log_lam : Tensor, shape (T, B, L) or (T, B, L, p)
        ``<lam>`` and ``<log lam>`` of each particle (per output component for noise families
        with one scale per component); not used where ``y_k`` is missing.
    """

    filter: FilterOutput
    smoother: SmootherOutput
    e_lam: Tensor
    e_log_lam: Tensor

    def select(self, index) -> EStepOutput:
        """The E-step output of the sequences ``index``."""
        return EStepOutput(
            self.filter.select(index),
            self.smoother.select(index),
            self.e_lam[:, index],
            self.e_log_lam[:, index],
        )

    @property
    def log_likelihood(self) -> Tensor:
        """Particle estimate of the log-likelihood of each sequence, shape (B,)."""
        return self.filter.log_likelihood


@dataclass
class EStepOptions:
    """Settings of the E-step: particles, smoother (by registry name, with its options), resampling."""

    n_particles: int = 200
    smoother: str = "ffbsm"
    smoother_options: dict[str, Any] = field(default_factory=dict)
    resampling: str = "systematic"
    ess_threshold: float = 1.0


def latent_scales(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput) -> tuple[Tensor, Tensor]:
    """``<lam>`` and ``<log lam>`` of every particle at every step (docs/method.md §1)."""
    stats = filt.noise_statistics
    if stats is None:  # a filter output built by hand: evaluate the noise on its particles
        stats = _noise_statistics(model, data, filt)
    e_lam, e_log = torch.empty_like(stats), torch.empty_like(stats)
    rows = stats[0].numel()
    for sl in time_blocks(stats.shape[0], rows):  # block by block: the temporaries stay in cache
        e_lam[sl], e_log[sl] = model.noise.latent_expectations(stats, filt.scale, sl)
    return e_lam, e_log


@torch.no_grad()
def _noise_statistics(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput) -> Tensor:
    T, B, L, _ = filt.particles.shape
    density = model.noise.evaluator(filt.scale, L)
    g = model.observation_steps(filt.particles, data.u)  # (T, B, L, p)
    r = filt.scale.fill_missing(data.y).unsqueeze(2) - g
    z = (filt.scale.whitener().unsqueeze(2) @ r.unsqueeze(-1)).squeeze(-1)
    for k in range(T):
        density.step(k, z[k])
    return density.statistics


def e_step(
    model: StateSpaceModel,
    data: SequenceBatch,
    options: EStepOptions,
    generator: torch.Generator | None = None,
) -> EStepOutput:
    """Filter, smooth and compute the latent-scale expectations at the model's parameters."""
    filt = particle_filter(
        model,
        data,
        options.n_particles,
        resampling=options.resampling,
        ess_threshold=options.ess_threshold,
        generator=generator,
    )
    smooth = _smooth(model, data, filt, options, generator)
    e_lam, e_log = latent_scales(model, data, filt)
    return EStepOutput(filt, smooth, e_lam, e_log)


def _smooth(model, data, filt, options: EStepOptions, generator) -> SmootherOutput:
    smoother = get_smoother(options.smoother)
    kwargs = dict(options.smoother_options)
    if options.smoother != "ffbsm":  # the backward samplers draw random numbers
        kwargs["generator"] = generator
    return smoother(model, data, filt, **kwargs)


def outlier_weights(log_weights: Tensor, e_lam: Tensor, data: SequenceBatch) -> list:
    """``E[lam_k | y]`` per record under the weights ``log_weights`` ``(T, B, L)``, as NumPy arrays
    ``(T_b,)`` (or ``(T_b, p)`` for per-component scales); NaN where nothing is observed."""
    w = torch.exp(log_weights)
    if e_lam.dim() == 4:  # per component
        ow = (w.unsqueeze(-1) * e_lam).sum(2)
        ow = torch.where(data.obs_mask, ow, torch.full_like(ow, math.nan))
    else:
        ow = (w * e_lam).sum(-1)
        ow = torch.where(data.obs_mask.any(-1), ow, torch.full_like(ow, math.nan))
    return [a.detach().cpu().numpy() for a in data.unpad(ow)]
