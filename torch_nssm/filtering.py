"""Bootstrap particle filter with Student-t (or Gaussian) measurement noise, batched over sequences.

All weights stay in the log domain.  The filter keeps every time step's particles and normalised
weights (before resampling), which is what the smoothers need (NOTES §2-3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ._ops import small_matmul, squared_norm
from .model import SequenceBatch, StateSpaceModel
from .noise import MaskedScale, masked_scale, student_t_log_prob
from .resampling import effective_sample_size, get_resampler

__all__ = ["FilterOutput", "particle_filter", "sample_initial_state", "NumericalError"]


class NumericalError(FloatingPointError):
    """Raised when the particle weights or the model produce non-finite values."""


@dataclass
class FilterOutput:
    """Everything the smoothers and the user need from one pass of the particle filter.

    Attributes
    ----------
    particles : Tensor, shape (T, B, L, nx)
        Particles at each time step (after propagation, before resampling).
    log_weights : Tensor, shape (T, B, L)
        Normalised log filter weights ``log W_k``.
    log_likelihood : Tensor, shape (B,)
        Particle estimate of ``log p(y_{0:T_b-1})`` of each sequence.
    ess : Tensor, shape (T, B)
        Effective sample size of the filter weights at each step.
    scale : MaskedScale
        The measurement-noise scale restricted to the observed components, per ``(T, B)``.
    ancestors : Tensor, shape (T, B, L), long
        ``ancestors[k, b, l]`` is the index at ``k - 1`` of the parent of particle ``l`` at ``k``
        (``ancestors[0]`` is the identity).
    delta2 : Tensor, shape (T, B, L), optional
        Squared whitened output residual of every particle (the E-step's latent scales reuse it).
    """

    particles: Tensor
    log_weights: Tensor
    log_likelihood: Tensor
    ess: Tensor
    scale: MaskedScale
    ancestors: Tensor
    delta2: Tensor | None = None

    def select(self, index) -> FilterOutput:
        """The filter output of the sequences ``index``."""
        return FilterOutput(
            self.particles[:, index],
            self.log_weights[:, index],
            self.log_likelihood[index],
            self.ess[:, index],
            self.scale.select(index),
            self.ancestors[:, index],
            None if self.delta2 is None else self.delta2[:, index],
        )


def _mahalanobis(model: StateSpaceModel, y0: Tensor, C: Tensor, u: Tensor, x: Tensor) -> Tensor:
    """Squared whitened residual norms ``delta2`` (B, L) of one step's outputs ``y0`` (B, p, missing
    entries 0) for particles ``x`` (B, L, nx), with the whitener ``C`` (B, p, p) of
    :meth:`MaskedScale.whitener`."""
    r = y0.unsqueeze(-2) - model.observation(x, u)  # (B, L, p)
    return squared_norm(small_matmul(C.unsqueeze(-3), r.unsqueeze(-1)).squeeze(-1))


def _log_density_terms(model: StateSpaceModel, scale: MaskedScale, B: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per-(T, B) terms of the log-density, ``logp = const - coef * log1p(delta2 / nu)`` for a t,
    ``const - delta2 / 2`` for a Gaussian (signalled by ``nu = inf``): computed once, not per step."""
    dof = model.per_sequence("dof", B).unsqueeze(0)  # (1, B)
    const = student_t_log_prob(torch.zeros_like(scale.logdet), scale.logdet, scale.n_obs, dof)
    return const, 0.5 * (dof + scale.n_obs), dof.expand_as(const)


def sample_initial_state(model: StateSpaceModel, B: int, L: int, generator=None) -> Tensor:
    """``L`` draws of the initial-state prior for each of ``B`` sequences, shape ``(B, L, nx)``."""
    m0 = model.per_sequence("x0_mean", B)
    C0 = torch.linalg.cholesky(model.per_sequence("x0_cov", B))
    eps = torch.randn(B, L, m0.shape[-1], dtype=m0.dtype, device=m0.device, generator=generator)
    return m0.unsqueeze(1) + eps @ C0.transpose(-1, -2)


@torch.no_grad()
def particle_filter(
    model: StateSpaceModel,
    data: SequenceBatch,
    n_particles: int,
    *,
    resampling: str = "systematic",
    ess_threshold: float = 1.0,
    generator: torch.Generator | None = None,
) -> FilterOutput:
    """Run the bootstrap particle filter over a batch of sequences.

    Parameters
    ----------
    model : StateSpaceModel
    data : SequenceBatch
    n_particles : int
        Number of particles ``L``.
    resampling : str
        ``"systematic"`` (default), ``"stratified"``, ``"residual"`` or ``"multinomial"``.
    ess_threshold : float
        Resample a sequence when its ESS falls below ``ess_threshold * L``; ``1.0`` resamples at
        every step, ``0.0`` never.
    generator : torch.Generator, optional
        Source of randomness (for reproducible runs).

    Returns
    -------
    FilterOutput

    Raises
    ------
    NumericalError
        If the model or the weights produce non-finite values (e.g. ``f`` or ``g`` return NaN).
    """
    resample = get_resampler(resampling)
    T, B = data.n_steps, data.n_sequences
    L = n_particles
    scale = masked_scale(model.per_sequence("Rv", B).unsqueeze(0), data.obs_mask)
    Cw = torch.linalg.cholesky(model.per_sequence("Rw", B))
    x = sample_initial_state(model, B, L, generator)
    nx = x.shape[-1]
    particles = torch.empty(T, B, L, nx, dtype=x.dtype, device=x.device)
    log_weights = torch.empty(T, B, L, dtype=x.dtype, device=x.device)
    ancestors = torch.empty(T, B, L, dtype=torch.long, device=x.device)
    log_lik = torch.zeros(B, dtype=x.dtype, device=x.device)
    log_w = torch.full((B, L), -math.log(L), dtype=x.dtype, device=x.device)
    arange = torch.arange(L, device=x.device).expand(B, L)
    ancestors[0] = arange
    const, coef, nu = _log_density_terms(model, scale, B)
    gaussian = bool(torch.isinf(nu).all())
    always = ess_threshold >= 1.0
    log_uniform = torch.full((B, L), -math.log(L), dtype=x.dtype, device=x.device)
    # All process-noise draws at once, shaped by chol(Rw) elementwise (tiny matrices).  Standard
    # normals are drawn in single precision (2x faster than double on CPU; the 24-bit draws are
    # more than enough for Monte Carlo noise) and used in the model's dtype.
    noise_dtype = torch.float32 if x.dtype == torch.float64 else x.dtype
    noise = torch.randn(max(T - 1, 0), B, L, nx, dtype=noise_dtype, device=x.device, generator=generator)
    noise = noise.to(x.dtype)
    if nx == 1:
        noise = noise * Cw.view(B, 1, 1)
    else:
        noise = (noise.unsqueeze(-2) * Cw.unsqueeze(-3)).sum(-1)  # noise @ Cw^T
    delta2_all = torch.empty(T, B, L, dtype=x.dtype, device=x.device)
    ess = torch.empty(T, B, dtype=x.dtype, device=x.device)
    y0, C = scale.fill_missing(data.y), scale.whitener()  # no masking per step
    for k in range(T):
        if k > 0:
            if always:
                anc = resample(log_w, generator=generator)
                log_w = log_uniform
            else:
                do = (effective_sample_size(log_w) < ess_threshold * L).unsqueeze(-1)  # (B, 1)
                anc = torch.where(do, resample(log_w, generator=generator), arange)
                log_w = torch.where(do, log_uniform, log_w)
            ancestors[k] = anc
            x = torch.gather(x, 1, anc.unsqueeze(-1).expand(B, L, nx))
            x = model.transition(x, data.u[k - 1]) + noise[k - 1]
        delta2 = _mahalanobis(model, y0[k], C[k], data.u[k], x)
        delta2_all[k] = delta2
        if gaussian:
            logp = const[k].unsqueeze(-1) - 0.5 * delta2
        else:
            logp = const[k].unsqueeze(-1) - coef[k].unsqueeze(-1) * torch.log1p(delta2 / nu[k].unsqueeze(-1))
        logits = log_w + logp
        lse = torch.logsumexp(logits, dim=-1)
        log_lik = log_lik + lse
        log_w = logits - lse.unsqueeze(-1)
        particles[k] = x
        log_weights[k] = log_w
        ess[k] = effective_sample_size(log_w)
    if not torch.isfinite(log_lik).all():
        bad = (~torch.isfinite(log_weights).any(-1)) | (~torch.isfinite(particles).all(-1).all(-1))
        steps = torch.nonzero(bad.any(-1)).flatten().tolist()
        where = f"first at time step {steps[0]}" if steps else "at an unknown step"
        raise NumericalError(
            "particle filter produced non-finite weights or states "
            f"({where}); check that f and g return finite values at the current parameters"
        )
    return FilterOutput(particles, log_weights, log_lik, ess, scale, ancestors, delta2_all)
