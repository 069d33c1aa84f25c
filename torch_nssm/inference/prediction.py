"""Prediction and simulation with a state-space model: free run, k-step-ahead, sampled trajectories.

Time convention (docs/method.md §7): ``y_k`` observes ``x_k`` and the mean of ``x_{k+1}`` is
``f(x_k, u_k)``.  All functions work on time-major batches ``(T, B, ...)`` of padded sequences (see
:class:`~torch_nssm.core.model.SequenceBatch`); values past a sequence's end are meaningless and are cut
off by the caller.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.model import StateSpaceModel
from .filtering import FilterOutput, sample_initial_state

__all__ = ["free_run", "k_step_ahead", "simulate", "divergence", "first_divergent_step"]


def _step(model: StateSpaceModel, x: Tensor, u: Tensor, chol_w: Tensor, generator) -> Tensor:
    """``f(x, u) + w`` for particles ``x`` ``(..., B, L, nx)`` and inputs ``u`` ``(..., B, nu)``."""
    noise = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
    return model.transition(x, u) + noise @ chol_w.transpose(-1, -2)


@torch.no_grad()
def free_run(model: StateSpaceModel, u: Tensor) -> tuple[Tensor, Tensor]:
    """Noise-free simulation from the prior mean: ``x_0 = x0_mean``, ``x_{k+1} = f(x_k, u_k)``.

    Parameters
    ----------
    model : StateSpaceModel
    u : Tensor, shape (T, B, nu)
        Inputs of ``B`` sequences.

    Returns
    -------
    states : Tensor, shape (T, B, nx)
    outputs : Tensor, shape (T, B, p)
        ``g(x_k, u_k)``.
    """
    T, B, _ = u.shape
    x = model.per_sequence("x0_mean", B).unsqueeze(1)  # (B, 1, nx)
    states = torch.empty(T, B, x.shape[-1], dtype=x.dtype, device=x.device)
    for k in range(T):
        states[k] = x[:, 0]
        if k + 1 < T:
            x = model.transition(x, u[k])
    return states, model.g(states, u)


@torch.no_grad()
def divergence(model: StateSpaceModel, u: Tensor, limit: float, max_steps: int = 1000) -> int | None:
    """The first step at which the noise-free simulation from ``x0_mean`` leaves ``|x| <= limit``
    or stops being finite (``None`` if it stays inside for ``min(T, max_steps)`` steps)."""
    return first_divergent_step(free_run(model, u[:max_steps])[0], limit)


def first_divergent_step(states: Tensor, limit: float) -> int | None:
    """The first step of simulated ``states`` ``(T, ...)`` outside ``|x| <= limit`` or not finite."""
    bad = ~torch.isfinite(states) | (states.abs() > limit)
    steps = torch.nonzero(bad.flatten(1).any(-1)).flatten()
    return int(steps[0]) if steps.numel() else None


@torch.no_grad()
def k_step_ahead(
    model: StateSpaceModel,
    u: Tensor,
    filt: FilterOutput,
    horizon: int,
    generator: torch.Generator | None = None,
) -> Tensor:
    """``E[g(x_t, u_t) | y_{0:t-horizon}]`` for every ``t``, from the particle filter's output.

    The filter's particles and weights at ``s = t - horizon`` are propagated ``horizon`` steps
    through ``f`` *with* process noise (Monte Carlo, so the prediction is the conditional mean
    even for a nonlinear ``f``), and ``g`` is averaged over them with the filter weights.  For
    ``t < horizon`` no output has been seen yet and the prediction comes from the initial-state
    prior propagated ``t`` steps the same way.  ``horizon=0`` gives the filtered output
    ``E[g(x_t, u_t) | y_{0:t}]``.

    Parameters
    ----------
    model : StateSpaceModel
    u : Tensor, shape (T, B, nu)
    filt : FilterOutput
        The filter run on the same sequences (particles ``(T, B, L, nx)``).
    horizon : int
        Number of steps ahead, ``>= 0``.
    generator : torch.Generator, optional
        Source of the process noise.

    Returns
    -------
    Tensor, shape (T, B, p)
    """
    T, B, L, nx = filt.particles.shape
    chol_w = torch.linalg.cholesky(model.per_sequence("Rw", B))  # (B, nx, nx)
    h = min(horizon, T)
    parts = []
    # t < horizon: the prior, propagated t steps (one pass over the first h steps)
    x = sample_initial_state(model, B, L, generator)
    for t in range(h):
        parts.append(model.observation(x, u[t]).mean(-2))
        if t + 1 < h:
            x = _step(model, x, u[t], chol_w, generator)
    prior = torch.stack(parts) if parts else None
    if h == T:
        return prior
    # t >= horizon: from the filter at s = t - horizon, all s at once
    n = T - h
    x = filt.particles[:n]  # (n, B, L, nx)
    for j in range(h):
        x = _step(model, x, u[j : j + n], chol_w, generator)
    w = torch.softmax(filt.log_weights[:n], dim=-1).unsqueeze(-1)  # (n, B, L, 1)
    pred = (w * model.observation(x, u[h:])).sum(-2)
    return pred if prior is None else torch.cat([prior, pred])


@torch.no_grad()
def simulate(
    model: StateSpaceModel, u: Tensor, n_samples: int, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Sample state and output trajectories, process and measurement noise included.

    ``x_0 ~ N(x0_mean, x0_cov)``, ``x_{k+1} = f(x_k, u_k) + w_k``, ``y_k = g(x_k, u_k) + v_k`` with
    ``w ~ N(0, Rw)`` and ``v`` drawn from the model's measurement noise.

    Parameters
    ----------
    model : StateSpaceModel
        With shared (not per-sequence) noise parameters.
    u : Tensor, shape (T, B, nu)
    n_samples : int
        Trajectories per sequence.
    generator : torch.Generator, optional

    Returns
    -------
    states : Tensor, shape (T, B, n_samples, nx)
    outputs : Tensor, shape (T, B, n_samples, p)
    """
    T, B, _ = u.shape
    chol_w = torch.linalg.cholesky(model.per_sequence("Rw", B))
    x = sample_initial_state(model, B, n_samples, generator)
    states = torch.empty(T, *x.shape, dtype=x.dtype, device=x.device)
    for k in range(T):
        states[k] = x
        if k + 1 < T:
            x = _step(model, x, u[k], chol_w, generator)
    mean = model.observation(states, u)
    return states, mean + model.noise.sample(mean.shape[:-1], generator=generator)
