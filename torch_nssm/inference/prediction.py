"""Prediction and simulation with a state-space model: free run, k-step-ahead, sampled trajectories.

Time convention (docs/method.md §7): ``y_k`` observes ``x_k`` and the mean of ``x_{k+1}`` is
``f(x_k, u_k)``.  All functions work on time-major batches ``(T, B, ...)`` of padded sequences (see
:class:`~torch_nssm.core.model.SequenceBatch`); values past a sequence's end are meaningless and are cut
off by the caller.

The per-step loops (:func:`_run`) evaluate ``f`` through the evaluator the particle filter uses
(parameters gathered once per run), in inference mode, and stack a block of steps' states into the
output at once: a step of the paper's model costs one tensor operation.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.model import StateSpaceModel
from .filtering import FilterOutput, _frozen, _step_inputs, sample_initial_state

__all__ = ["free_run", "k_step_ahead", "simulate", "divergence", "first_divergent_step"]

#: Steps per block of the per-step loops: each block's states are stacked into the output at once and
#: its per-step input views made at once (the views of a whole record would cost ~600 bytes a step).
BLOCK = 1024


def _run(
    model: StateSpaceModel,
    x: Tensor,
    u: Tensor,
    chol_w_t: Tensor | None = None,
    generator: torch.Generator | None = None,
    limit: float | None = None,
) -> tuple[Tensor, int | None]:
    """States ``(T, B, L, nx)`` of ``x_{k+1} = f(x_k, u_k)`` from ``x_0 = x`` ``(B, L, nx)``.

    With ``chol_w_t``, ``eps_k @ chol_w_t`` (``eps_k ~ N(0, I)``, one draw from ``generator`` a step)
    is added at each step.  With ``limit``, the run stops at the block of steps where the states
    first leave ``|x| <= limit`` or stop being finite, and that step (:func:`first_divergent_step`) is
    returned (the later states are left unset); else ``None``.

    ``f`` is evaluated through its :func:`~torch_nssm.inference.filtering._frozen` evaluator (e.g.
    :meth:`~torch_nssm.LinearInParameters.frozen`: the parameters gathered once, not at every step)
    with the per-step inputs the particle filter passes it (the inputs expanded to ``(B, L, nu)``, or
    the evaluator's own ``step_inputs``): the values of ``model.transition``.  The steps run in
    inference mode (no autograd bookkeeping) and write into the output only through one stack per
    block, so the output is an ordinary tensor.
    """
    T, L = u.shape[0], x.shape[-2]
    states = torch.empty(T, *x.shape, dtype=x.dtype, device=x.device)
    f = _frozen(model.f)
    with torch.inference_mode():
        for s, e in _blocks(T):
            U = _step_inputs(f, u[s:e], L)
            xs = [x]
            if chol_w_t is None:  # the free run: nothing but the evaluator's call
                for k in range(e - s - 1):
                    x = f(x, U[k])
                    xs.append(x)
            else:
                for k in range(e - s - 1):
                    x = _noisy(f(x, U[k]), chol_w_t, generator)
                    xs.append(x)
            torch.stack(xs, out=states[s:e])
            if limit is not None:
                step = first_divergent_step(states[s:e], limit)
                if step is not None:
                    return states, s + step
            if e < T:
                x = f(x, U[-1]) if chol_w_t is None else _noisy(f(x, U[-1]), chol_w_t, generator)
    return states, None


def _noisy(mean: Tensor, chol_w_t: Tensor, generator: torch.Generator | None) -> Tensor:
    """``mean + eps @ chol_w_t`` with ``eps ~ N(0, I)`` of ``mean``'s shape."""
    eps = torch.randn(mean.shape, dtype=mean.dtype, device=mean.device, generator=generator)
    return mean + eps @ chol_w_t


def _blocks(T: int):
    """``(start, stop)`` of the blocks of :data:`BLOCK` steps covering ``range(T)``."""
    return ((s, min(s + BLOCK, T)) for s in range(0, T, BLOCK))


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
        ``g(x_k, u_k)``, evaluated once over all steps.
    """
    x0 = model.per_sequence("x0_mean", u.shape[1]).unsqueeze(1)  # (B, 1, nx)
    states = _run(model, x0, u)[0][:, :, 0]
    return states, model.g(states, u)


@torch.no_grad()
def divergence(model: StateSpaceModel, u: Tensor, limit: float, max_steps: int = 1000) -> int | None:
    """The first step at which the noise-free simulation from ``x0_mean`` leaves ``|x| <= limit``
    or stops being finite (``None`` if it stays inside for ``min(T, max_steps)`` steps).

    The simulation stops in the block of steps where it leaves; ``g`` is not evaluated."""
    x0 = model.per_sequence("x0_mean", u.shape[1]).unsqueeze(1)
    return _run(model, x0, u[:max_steps], limit=limit)[1]


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
    chol_w_t = torch.linalg.cholesky(model.per_sequence("Rw", B)).transpose(-1, -2)  # (B, nx, nx)
    h = min(horizon, T)
    prior = None
    if h > 0:  # t < horizon: the prior, propagated t steps (one pass over the first h steps)
        x = _run(model, sample_initial_state(model, B, L, generator), u[:h], chol_w_t, generator)[0]
        prior = torch.stack([model.observation(x[t], u[t]).mean(-2) for t in range(h)])
    if h == T:
        return prior
    # t >= horizon: from the filter at s = t - horizon, all s at once
    n = T - h
    x = filt.particles[:n]  # (n, B, L, nx)
    for j in range(h):
        x = _noisy(model.transition(x, u[j : j + n]), chol_w_t, generator)
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
    B = u.shape[1]
    chol_w_t = torch.linalg.cholesky(model.per_sequence("Rw", B)).transpose(-1, -2)  # (B, nx, nx)
    states = _run(model, sample_initial_state(model, B, n_samples, generator), u, chol_w_t, generator)[0]
    mean = model.observation(states, u)
    return states, mean + model.noise.sample(mean.shape[:-1], generator=generator)
