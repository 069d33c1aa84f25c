"""One iteration of the robust EM algorithm (paper Algorithm 1): E-step and M-step.

The E-step runs the particle filter, a particle smoother and the Student-t latent-scale
expectations; the M-step updates ``theta_f, Rw, theta_g, Rv, dof`` and the initial-state prior from
them (see :mod:`torch_nssm.mstep` for the formulas).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ._ops import squared_norm, time_blocks
from .filtering import FilterOutput, NumericalError, particle_filter
from .model import SequenceBatch, StateSpaceModel
from .mstep import (
    dof_update,
    fit_weighted_regression,
    initial_state_update,
    measurement_noise_update,
    observation_rows,
    process_noise_update,
    transition_rows,
)
from .noise import latent_scale_expectations
from .smoothing import SMOOTHERS, SmootherOutput, ffbsi, ffbsm

__all__ = ["EStepOutput", "MStepOptions", "e_step", "m_step", "SMOOTHERS"]


@dataclass
class EStepOutput:
    """Filter, smoother and latent-scale expectations at the current parameters.

    Attributes
    ----------
    filter : FilterOutput
    smoother : SmootherOutput
    e_lam, e_log_lam : Tensor, shape (T, B, L)
        ``<lam>`` and ``<log lam>`` for each particle (not used where ``y_k`` is missing).
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


def latent_scales(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput) -> tuple[Tensor, Tensor]:
    """``<lam>`` and ``<log lam>`` of every particle at every step (NOTES §1)."""
    T, B, L, nx = filt.particles.shape
    scale = filt.scale
    delta2 = filt.delta2  # the filter's residuals at the same parameters
    if delta2 is None:  # a filter output built by hand: recompute them
        with torch.no_grad():
            # Sequence-major (B, T*L, .) so that per-sequence (stacked) modules see their own rows.
            x = filt.particles.transpose(0, 1).reshape(B, T * L, nx)
            u = data.u.transpose(0, 1).unsqueeze(2).expand(B, T, L, data.u.shape[-1]).reshape(B, T * L, -1)
            g = model.g(x, u).reshape(B, T, L, -1).transpose(0, 1)
            delta2 = squared_norm(scale.whiten(data.y.unsqueeze(2) - g))
    dof = model.per_sequence("dof", B).view(1, B, 1)
    n_obs = scale.n_obs.unsqueeze(-1)
    e_lam, e_log = torch.empty_like(delta2), torch.empty_like(delta2)
    for sl in time_blocks(T, B * L):  # block by block: the temporaries stay in cache
        e_lam[sl], e_log[sl] = latent_scale_expectations(delta2[sl], n_obs[sl], dof)
    return e_lam, e_log


def e_step(
    model: StateSpaceModel,
    data: SequenceBatch,
    n_particles: int,
    *,
    smoother: str = "ffbsm",
    resampling: str = "systematic",
    ess_threshold: float = 1.0,
    chunk_size: int | None = None,
    generator: torch.Generator | None = None,
) -> EStepOutput:
    """Filter, smooth and compute the latent-scale expectations at the model's parameters."""
    filt = particle_filter(
        model, data, n_particles, resampling=resampling, ess_threshold=ess_threshold, generator=generator
    )
    if smoother == "ffbsm":
        smooth = ffbsm(model, data, filt, chunk_size=chunk_size)
    elif smoother == "ffbsi":
        smooth = ffbsi(model, data, filt, method="reject", generator=generator)
    elif smoother == "mcmc":
        smooth = ffbsi(model, data, filt, method="mcmc", generator=generator)
    else:
        raise ValueError(f"smoother must be one of {SMOOTHERS}, got {smoother!r}")
    e_lam, e_log = latent_scales(model, data, filt)
    return EStepOutput(filt, smooth, e_lam, e_log)


@dataclass
class MStepOptions:
    """Settings of the M-step.

    Attributes
    ----------
    optimizer : {"lbfgs", "adam"}
        Gradient optimiser for modules without a closed-form solve.
    max_iter : int
        LBFGS iterations (or Adam steps) per M-step and module.
    learning_rate : float
        Adam's step size.
    fit_dof : bool
        Update the DOF (ignored for Gaussian noise).
    dof_bounds : (float, float)
        Bracket of the DOF root-solve.
    batch_size : int or None
        Minibatch size of Adam (``max_iter`` is then a number of epochs, early-stopped).
    generator : torch.Generator or None
        Shuffles the minibatches (reproducible fits).
    fit_Rw, fit_Rv : bool
        Update the process-noise covariance / measurement-noise scale (else they stay fixed).
    fit_x0 : bool
        Update the initial-state prior from the smoothed first state.
    """

    optimizer: str = "lbfgs"
    max_iter: int = 20
    learning_rate: float = 1e-2
    fit_dof: bool = True
    dof_bounds: tuple[float, float] = (0.1, 1000.0)
    fit_x0: bool = True
    fit_Rw: bool = True
    fit_Rv: bool = True
    batch_size: int | None = None
    generator: torch.Generator | None = None


def m_step(
    model: StateSpaceModel, data: SequenceBatch, est: EStepOutput, options: MStepOptions
) -> StateSpaceModel:
    """Update all parameters from the E-step statistics (ECM order: f, Rw, g, Rv, dof, x0).

    The modules ``model.f`` and ``model.g`` are updated in place; the noise parameters are
    returned in a new :class:`StateSpaceModel`.

    Raises
    ------
    NumericalError
        If an update is not finite (the caller keeps the previous parameters).
    """
    fit = dict(
        optimizer=options.optimizer,
        max_iter=options.max_iter,
        learning_rate=options.learning_rate,
        batch_size=options.batch_size,
        generator=options.generator,
    )
    rows_f = transition_rows(model, data, est.filter, est.smoother)
    fit_weighted_regression(model.f, rows_f, **fit)
    Rw = process_noise_update(model.f, rows_f, est.smoother, data) if options.fit_Rw else model.Rw

    rows_g, sw, e_lam, e_log = observation_rows(
        model, data, est.filter, est.smoother, est.e_lam, est.e_log_lam
    )
    fit_weighted_regression(model.g, rows_g, **fit)
    Rv = measurement_noise_update(model.g, rows_g, data, model.Rv, sw) if options.fit_Rv else model.Rv

    dof = model.dof
    if options.fit_dof and not model.gaussian:
        n_samples = data.obs_mask.any(-1).sum().to(sw.dtype)
        dof = dof_update(sw, e_lam, e_log, n_samples, options.dof_bounds).reshape(model.dof.shape)

    x0_mean, x0_cov = model.x0_mean, model.x0_cov
    if options.fit_x0:
        x0_mean, x0_cov = initial_state_update(est.filter, est.smoother, Rw)

    new = replace(model, Rw=Rw, Rv=Rv, dof=dof, x0_mean=x0_mean, x0_cov=x0_cov)
    for name in ("Rw", "Rv", "x0_mean", "x0_cov"):
        if not bool(torch.isfinite(getattr(new, name)).all()):
            raise NumericalError(f"the M-step produced a non-finite {name}")
    for name in ("Rw", "Rv", "x0_cov"):
        if int(torch.linalg.cholesky_ex(getattr(new, name)).info.max()) != 0:
            raise NumericalError(
                f"the M-step produced a {name} that is not positive definite "
                "(the model diverged: try other initial values)"
            )
    for module, label in ((model.f, "f"), (model.g, "g")):
        for pname, p in module.named_parameters():
            if not bool(torch.isfinite(p).all()):
                raise NumericalError(f"the M-step produced a non-finite parameter {label}.{pname}")
    return new
