"""A first stage before EM: fit ``f`` and ``g`` to the record by robust simulation error.

EM from a poor start converges slowly, or into the wrong basin, when the process noise can explain
what ``f`` gets wrong (issue #13, docs/design.md).  This stage minimises a robust (Cauchy) loss of
the *noise-free simulation*'s output errors over the free parameters of ``f`` and ``g`` and each
record's first state: the output-error fit an engineer tries first, here with a loss that
outliers do not steer.  Long or unstable records are cut into windows of ``segment_length``
samples, each with its own free initial state (multiple shooting).  EM then starts there and
estimates the noise, the outlier weights and the final parameters.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._stats import MAD_TO_STD
from ..core.model import SequenceBatch, StateSpaceModel
from ..inference.prediction import free_run

__all__ = ["FirstStageReport", "first_stage_applies", "held_process_noise", "simulation_error_fit"]


@dataclass
class FirstStageReport:
    """What the first stage did.

    Attributes
    ----------
    rmse_before, rmse_after : float
        Root mean square of the simulation's output errors over the observed samples (outliers
        included) at the start and at the result.
    loss_before, loss_after : float
        The robust loss minimised (mean Cauchy loss of the scaled errors).
    accepted : bool
        Whether the result was kept (the loss decreased and everything stayed finite).
    n_windows : int
        Number of simulation windows (1 per record without ``segment_length``).
    first_states : Tensor or None
        The fitted first state of each window ``(n_windows, nx)`` (``None`` if not accepted).
    free_run_scale_before_em, free_run_scale_after_em : float
        Set by the estimator: the robust scale (1.4826 MAD about 0) of the training record's
        free-run output errors of the first stage's model and of the EM fit.
    explained : float
        Set by the estimator: robust R² of the first stage's free run against ``y``
        (``first_stage="auto"`` keeps the result only when it is at least 0.5).
    """

    rmse_before: float
    rmse_after: float
    loss_before: float
    loss_after: float
    accepted: bool
    n_windows: int
    first_states: Tensor | None = None
    free_run_scale_before_em: float = math.nan
    free_run_scale_after_em: float = math.nan
    explained: float = math.nan


#: Layers that mark a network: ``first_stage="auto"`` leaves models holding them to
#: :func:`torch_nssm.warm_start_estimator` (a simulation-error fit of an untrained network from a
#: random start is a training problem of its own, not a quick first stage).
NETWORK_LAYERS: tuple[type, ...] = (
    torch.nn.Linear,
    torch.nn.Bilinear,
    torch.nn.RNNBase,
    torch.nn.modules.conv._ConvNd,
)


def first_stage_applies(model: StateSpaceModel) -> bool:
    """Whether ``first_stage="auto"`` runs the first stage for ``model``.

    It does for physical and grey-box models: ``f`` or ``g`` has free parameters and neither holds a
    network layer (:data:`NETWORK_LAYERS`).
    """
    modules = (model.f, model.g)
    if not any(p.requires_grad for m in modules for p in m.parameters()):
        return False
    return not any(isinstance(sub, NETWORK_LAYERS) for m in modules for sub in m.modules())


def held_process_noise(states: Tensor, data: SequenceBatch, relative: float = 1e-6) -> Tensor:
    """A small process-noise covariance for a simulation model: ``relative`` times the variance of
    each state along a noise-free simulation ``states`` ``(T, B, nx)`` of ``data`` (diagonal),
    floored at ``relative`` times the largest of them (and at ``1e-300``) so that no state is
    noise-free."""
    x = torch.cat(data.unpad(states.detach()))  # (n, nx)
    var = x.var(0) if x.shape[0] > 1 else torch.ones_like(x[0])
    var = torch.where(torch.isfinite(var), var, torch.ones_like(var))
    floor = torch.clamp(var.max() * relative, min=1e-300)
    return torch.diag(torch.clamp(relative * var, min=floor))


def _window_starts(data: SequenceBatch, segment_length: int | None) -> list[tuple[int, int, int]]:
    """``(record, start, stop)`` of each window (windows shorter than 2 samples are dropped)."""
    out = []
    for b, n in enumerate(data.lengths.tolist()):
        step = n if segment_length is None else segment_length
        out += [(b, s, min(s + step, n)) for s in range(0, n, step) if min(s + step, n) - s >= 2]
    return out


def _simulate(model: StateSpaceModel, x0: Tensor, u: Tensor) -> Tensor:
    """Outputs ``(T, B, p)`` of the noise-free simulation from ``x0`` ``(B, nx)``."""
    x = x0.unsqueeze(1)  # (B, 1, nx)
    outputs = []
    for k in range(u.shape[0]):
        outputs.append(model.observation(x, u[k])[:, 0])
        if k + 1 < u.shape[0]:
            x = model.transition(x, u[k])
    return torch.stack(outputs)


def simulation_error_fit(
    model: StateSpaceModel,
    data: SequenceBatch,
    *,
    max_iter: int = 100,
    segment_length: int | None = None,
) -> FirstStageReport:
    """Fit ``model.f``, ``model.g`` (in place) and the first states by robust simulation error.

    Parameters
    ----------
    model : StateSpaceModel
        The start; its modules' free parameters are updated in place if the fit is accepted.
    data : SequenceBatch
    max_iter : int
        LBFGS iterations.
    segment_length : int, optional
        Cut the records into windows of this many samples, each with a free first state (for long
        records or unstable simulations); one window per record if omitted.

    Returns
    -------
    FirstStageReport
        With the fitted first state of every window (``first_states``); ``model.x0_mean`` is
        not changed.
    """
    spans = _window_starts(data, segment_length)
    windows = SequenceBatch.from_sequences(
        [data.u[s:e, b] for b, s, e in spans], [data.y[s:e, b] for b, s, e in spans]
    )
    with torch.no_grad():  # each window starts where the start model's simulation of its record is
        states, _ = free_run(model, data.u)
    x0 = torch.stack([states[s, b] for b, s, _ in spans]).requires_grad_(True)
    mask = windows.obs_mask
    y = torch.where(mask, windows.y, torch.zeros_like(windows.y))
    params = [p for m in (model.f, model.g) for p in m.parameters() if p.requires_grad] + [x0]
    backup = (copy.deepcopy(model.f.state_dict()), copy.deepcopy(model.g.state_dict()))

    def errors() -> Tensor:
        return torch.where(mask, y - _simulate(model, x0, windows.u), torch.zeros_like(y))

    with torch.no_grad():
        e0 = errors()
    n_obs = mask.sum().clamp_min(1)
    finite0 = bool(torch.isfinite(e0).all())
    rmse_before = float(torch.sqrt((e0**2).sum() / n_obs)) if finite0 else math.inf
    # the scale of the Cauchy loss: a robust spread of the starting errors, per output (fixed)
    scale = None
    if finite0:
        spreads = [
            MAD_TO_STD * torch.median(e0[..., j][mask[..., j]].abs()) if bool(mask[..., j].any())
            else e0.new_ones(())
            for j in range(e0.shape[-1])
        ]
        scale = torch.stack(spreads).clamp_min(1e-12)

    def loss_of(e: Tensor) -> Tensor:
        return (torch.log1p((e / scale) ** 2) * mask).sum() / n_obs

    if not finite0 or not params[:-1]:
        return FirstStageReport(rmse_before, rmse_before, math.nan, math.nan, False, windows.n_sequences)
    with torch.no_grad():
        loss_before = float(loss_of(e0))
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")

    penalty = torch.tensor(1e6 * (1.0 + abs(loss_before)), dtype=e0.dtype, device=e0.device)

    def closure():
        opt.zero_grad()
        loss = loss_of(errors())
        if not bool(torch.isfinite(loss)):
            # a step into a diverging simulation: a huge finite loss makes the line search back off
            return penalty
        loss.backward()
        for p in params:
            if p.grad is not None and not bool(torch.isfinite(p.grad).all()):
                p.grad = torch.zeros_like(p)
                return penalty
        return loss

    try:
        opt.step(closure)
        with torch.no_grad():
            e1 = errors()
            loss_after = float(loss_of(e1))
        accepted = math.isfinite(loss_after) and loss_after < loss_before
    except (FloatingPointError, RuntimeError, IndexError):
        accepted, loss_after, e1 = False, math.nan, e0
    for p in params:
        p.grad = None
    if not accepted:
        model.f.load_state_dict(backup[0])
        model.g.load_state_dict(backup[1])
        n = windows.n_sequences
        return FirstStageReport(rmse_before, rmse_before, loss_before, loss_before, False, n)
    rmse_after = float(torch.sqrt((e1**2).sum() / n_obs))
    return FirstStageReport(
        rmse_before, rmse_after, loss_before, loss_after, True, windows.n_sequences, x0.detach()
    )
