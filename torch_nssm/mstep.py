"""The M-step of the robust EM algorithm (paper eqs. 31-38; NOTES §4-5, §7).

The smoother's sufficient statistics turn each parameter update into a weighted regression with
``N * L`` rows (never ``N * L^2``):

* ``theta_f``: inputs ``(x_k^i, u_k)``, target ``xbar_k^i``, weight ``s_k^i``, metric ``Rw_old^-1``
  (an ECM step); then ``Rw`` in closed form with the parameter-free scatter kept.
* ``theta_g``: inputs ``(x_k^l, u_k)``, target ``y_k``, weight ``W_{k|N}^l <lam>_k^l``, metric
  ``Rv_old^-1`` restricted to the observed components; then ``Rv`` in closed form.
* the DOF by a bracketed root-solve of eq. 38 in float64;
* the initial state's mean and covariance from the smoothed first state.

A module that offers ``solve_weighted_least_squares`` (see :mod:`torch_nssm.parametric`) gets its
closed-form solution; any other module is fitted by LBFGS (default) or a few Adam steps.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .filtering import FilterOutput
from .model import SequenceBatch, StateSpaceModel
from .noise import solve_dof
from .smoothing import SmootherOutput

__all__ = [
    "RegressionRows",
    "transition_rows",
    "observation_rows",
    "fit_weighted_regression",
    "weighted_loss",
    "process_noise_update",
    "measurement_noise_update",
    "dof_update",
    "weighted_scatter",
    "initial_state_update",
    "OPTIMIZERS",
]

OPTIMIZERS = ("lbfgs", "adam")

#: Rows whose smoothing weight is below this (weights sum to one at each time step) do not enter
#: the regressions: they change the objective by less than a part in 1e12 and cost as much as any.
ROW_WEIGHT_CUTOFF = 1e-12


@dataclass
class RegressionRows:
    """One weighted regression problem of the M-step, flattened over (time, sequence, particle).

    Attributes
    ----------
    x : Tensor, shape (n, nx)
    u : Tensor, shape (n, nu)
    target : Tensor, shape (n, d)
        NaN where an output component is missing.
    weight : Tensor, shape (n,)
    precision : Tensor, shape (d, d) or (n, d, d)
        Metric of the residuals (zero rows/columns for missing components).
    """

    x: Tensor
    u: Tensor
    target: Tensor
    weight: Tensor
    precision: Tensor


def _flatten_rows(keep: Tensor, per_particle: list[Tensor], per_step: list[Tensor]) -> list[Tensor]:
    """Select the rows ``keep`` (``(T, B, L)``) of per-particle arrays ``(T, B, L, ...)`` and of
    per-step arrays ``(T, B, ...)`` (repeated over the particles), in that order."""
    T, B, L = keep.shape
    out = [a[keep] for a in per_particle]
    out += [a.unsqueeze(2).expand(T, B, L, *a.shape[2:])[keep] for a in per_step]
    return out


def transition_rows(
    model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput, smooth: SmootherOutput
) -> RegressionRows:
    """Rows of the ``theta_f`` regression (NOTES §4): ``(x_k^i, u_k) -> xbar_k^i``, weight ``s_k^i``."""
    w = smooth.transition_weights
    keep = w > ROW_WEIGHT_CUTOFF
    x, target, weight, u = _flatten_rows(keep, [filt.particles[:-1], smooth.next_mean, w], [data.u[:-1]])
    return RegressionRows(x, u, target, weight, torch.linalg.inv(_shared(model.Rw)))


def observation_rows(
    model: StateSpaceModel,
    data: SequenceBatch,
    filt: FilterOutput,
    smooth: SmootherOutput,
    e_lam: Tensor,
    e_log_lam: Tensor,
) -> tuple[RegressionRows, Tensor, Tensor, Tensor]:
    """Rows of the ``theta_g`` regression, with the latent-scale expectations of each row.

    Parameters
    ----------
    e_lam, e_log_lam : Tensor, shape (T, B, L)
        ``<lam>`` and ``<log lam>`` of each particle at the E-step parameters.

    Returns
    -------
    rows : RegressionRows
        Weight ``W_{k|N}^l <lam>_k^l`` and metric ``Rv_old^-1`` on the observed components.
    smoothing_weight, e_lam, e_log_lam : Tensor, shape (n,)
        ``W_{k|N}^l``, ``<lam>`` and ``<log lam>`` of the same rows (for the DOF update).
    """
    W = torch.exp(smooth.log_weights)
    observed = data.obs_mask.any(-1)  # (T, B)
    keep = (W > ROW_WEIGHT_CUTOFF) & observed.unsqueeze(-1)
    scale = filt.scale
    x, sw, lam, log_lam, u, y, chol_inv, mask = _flatten_rows(
        keep, [filt.particles, W, e_lam, e_log_lam], [data.u, data.y, scale.chol_inv, scale.mask]
    )
    m = mask.to(x.dtype)
    precision = (chol_inv.transpose(-1, -2) @ chol_inv) * m.unsqueeze(-1) * m.unsqueeze(-2)
    return RegressionRows(x, u, y, sw * lam, precision), sw, lam, log_lam


def _shared(value: Tensor) -> Tensor:
    return value if value.dim() == 2 else value[0]


def _residuals(module: nn.Module, rows: RegressionRows) -> Tensor:
    r = rows.target - module(rows.x, rows.u)
    return torch.where(torch.isnan(rows.target), torch.zeros_like(r), r)


def weighted_loss(module: nn.Module, rows: RegressionRows) -> Tensor:
    """``sum_n w_n r_n^T P_n r_n / sum_n w_n`` (normalised so optimiser tolerances are meaningful)."""
    r = _residuals(module, rows)
    Pr = (rows.precision @ r.unsqueeze(-1)).squeeze(-1)
    return (rows.weight * (r * Pr).sum(-1)).sum() / rows.weight.sum().clamp_min(1e-300)


def fit_weighted_regression(
    module: nn.Module,
    rows: RegressionRows,
    *,
    optimizer: str = "lbfgs",
    max_iter: int = 20,
    learning_rate: float = 1e-2,
    batch_size: int | None = None,
    patience: int = 2,
    generator: torch.Generator | None = None,
) -> float:
    """Update the free parameters of ``module`` to decrease :func:`weighted_loss`.

    Uses the module's ``solve_weighted_least_squares`` when it has one; otherwise LBFGS (strong
    Wolfe line search, ``max_iter`` iterations) or Adam: ``max_iter`` full-batch steps, or, with
    ``batch_size``, up to ``max_iter`` epochs of minibatch steps over the shuffled rows with early
    stopping (the full weighted loss is checked after each epoch; training stops after
    ``patience`` epochs without improvement and the best parameters are kept) — the M-step for
    neural networks, a generalised EM step.  If the loss got worse or non-finite the previous
    parameters are restored (NOTES §7), so the step never harms.

    Returns
    -------
    float
        The weighted loss after the update.
    """
    params = [p for p in module.parameters() if p.requires_grad]
    if not params or rows.weight.numel() == 0:
        with torch.no_grad():
            return float(weighted_loss(module, rows)) if rows.weight.numel() else 0.0
    backup = copy.deepcopy(module.state_dict())
    with torch.no_grad():
        before = float(weighted_loss(module, rows))
    if hasattr(module, "solve_weighted_least_squares"):
        module.solve_weighted_least_squares(rows.x, rows.u, rows.target, rows.weight, rows.precision)
    elif optimizer == "lbfgs":
        opt = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=max_iter,
            line_search_fn="strong_wolfe",
            tolerance_grad=1e-10,
            tolerance_change=1e-12,
        )

        def closure():
            opt.zero_grad()
            loss = weighted_loss(module, rows)
            if not bool(torch.isfinite(loss)):
                raise _NonFiniteLoss
            loss.backward()
            return loss

        try:
            opt.step(closure)
        except (_NonFiniteLoss, IndexError, RuntimeError):
            # torch's line search fails obscurely on NaN losses: keep the previous parameters.
            module.load_state_dict(backup)
            for p in params:
                p.grad = None
            return before
    elif optimizer == "adam" and batch_size is not None:
        _minibatch_adam(module, params, rows, max_iter, learning_rate, batch_size, patience, generator)
    elif optimizer == "adam":
        opt = torch.optim.Adam(params, lr=learning_rate)
        for _ in range(max_iter):
            opt.zero_grad()
            loss = weighted_loss(module, rows)
            loss.backward()
            opt.step()
    else:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")
    for p in params:
        p.grad = None
    with torch.no_grad():
        after = float(weighted_loss(module, rows))
    if not after <= before:  # also catches NaN
        module.load_state_dict(backup)
        return before
    return after


def _row_subset(rows: RegressionRows, idx: Tensor) -> RegressionRows:
    precision = rows.precision if rows.precision.dim() == 2 else rows.precision[idx]
    return RegressionRows(rows.x[idx], rows.u[idx], rows.target[idx], rows.weight[idx], precision)


def _minibatch_adam(module, params, rows, epochs, lr, batch_size, patience, generator) -> None:
    """Adam over shuffled minibatches of the rows, early-stopped on the full weighted loss."""
    opt = torch.optim.Adam(params, lr=lr)
    n = rows.weight.numel()
    with torch.no_grad():
        best = float(weighted_loss(module, rows))
    best_state, bad = copy.deepcopy(module.state_dict()), 0
    for _ in range(epochs):
        order = torch.randperm(n, generator=generator).to(rows.weight.device)
        for start in range(0, n, batch_size):
            batch = _row_subset(rows, order[start : start + batch_size])
            opt.zero_grad()
            loss = weighted_loss(module, batch)
            if not bool(torch.isfinite(loss)):
                break
            loss.backward()
            opt.step()
        with torch.no_grad():
            current = float(weighted_loss(module, rows))
        if current < best:
            best, best_state, bad = current, copy.deepcopy(module.state_dict()), 0
        else:
            bad += 1
            if bad >= patience:
                break
    module.load_state_dict(best_state)


class _NonFiniteLoss(ArithmeticError):
    """The weighted loss became NaN or infinite during an optimiser step."""


def weighted_scatter(module: nn.Module, rows: RegressionRows) -> Tensor:
    """``sum_n w_n r_n r_n^T`` of the residuals at the module's current parameters."""
    with torch.no_grad():
        r = _residuals(module, rows)
        return torch.einsum("n,np,nq->pq", rows.weight, r, r)


def process_noise_update(
    f: nn.Module, rows: RegressionRows, smooth: SmootherOutput, data: SequenceBatch, jitter: float = 1e-10
) -> Tensor:
    """Closed-form ``Rw`` (eq. 31, NOTES §7) at the current ``theta_f``, shared by all sequences."""
    scatter = weighted_scatter(f, rows) + smooth.residual_scatter.sum(0)
    n = data.transition_mask.sum().clamp_min(1).to(scatter.dtype)
    return _symmetric_pd(scatter / n, jitter)


def measurement_noise_update(
    g: nn.Module,
    rows: RegressionRows,
    data: SequenceBatch,
    Rv_old: Tensor,
    smoothing_weight: Tensor,
    jitter: float = 1e-10,
) -> Tensor:
    """Closed-form ``Rv`` (eq. 32) at the current ``theta_g``, averaged over the observed samples.

    With several outputs and some components missing, the missing part of each residual is
    completed by its conditional expectation given the observed part (under ``Rv_old``), and the
    conditional covariance is added: ``E[lam r r^T | r_o] = <lam> rhat rhat^T + (R_mm - R_mo
    R_oo^-1 R_om)``, the standard EM for incomplete multivariate t data.  The result is positive
    definite whenever ``Rv_old`` is.

    Parameters
    ----------
    rows : RegressionRows
        Observation rows (weight ``W <lam>``, precision ``Rv_old^-1`` on the observed block).
    Rv_old : Tensor, shape (p, p)
        The scale matrix of the E-step.
    smoothing_weight : Tensor, shape (n,)
        ``W_{k|N}^l`` of the rows.
    """
    with torch.no_grad():
        r = _residuals(g, rows)
        R = _shared(Rv_old)
        K = R @ rows.precision  # identity on the observed block, R_mo R_oo^-1 below it
        rhat = (K @ r.unsqueeze(-1)).squeeze(-1)
        cond_cov = R - K @ R  # zero unless a component is missing
        num = torch.einsum("n,np,nq->pq", rows.weight, rhat, rhat)
        num = num + torch.einsum("n,npq->pq", smoothing_weight, cond_cov)
    n = data.obs_mask.any(-1).sum().clamp_min(1).to(num.dtype)
    return _symmetric_pd(num / n, jitter)


def dof_update(
    smoothing_weight: Tensor,
    e_lam: Tensor,
    e_log_lam: Tensor,
    n_samples: Tensor,
    bounds: tuple[float, float],
) -> Tensor:
    """DOF from eq. 38: root of ``h(nu) = 1 + log(nu/2) - psi(nu/2) + c`` with
    ``c = 1/N_obs sum_k sum_l W_{k|N}^l (<log lam> - <lam>)`` (expectations at the E-step)."""
    c = (smoothing_weight * (e_log_lam - e_lam)).sum() / n_samples.clamp_min(1)
    return solve_dof(c, *bounds).to(smoothing_weight.dtype)


def initial_state_update(filt: FilterOutput, smooth: SmootherOutput, floor: Tensor) -> tuple[Tensor, Tensor]:
    """Prior of the first state from its smoothed distribution, pooled over sequences.

    ``floor`` (the process-noise covariance) is *added* to the smoothed covariance: with a single
    record the maximum-likelihood prior would otherwise collapse to a point over the iterations.
    """
    w = torch.exp(smooth.log_weights[0]).unsqueeze(-1)  # (B, L, 1)
    x = filt.particles[0]  # (B, L, nx)
    means = (w * x).sum(1)  # (B, nx)
    mean = means.mean(0)
    d = x - mean
    cov = ((w * d).transpose(-1, -2) @ d).mean(0)
    return mean, _symmetric_pd(cov + floor, 0.0)


def _symmetric_pd(S: Tensor, jitter: float) -> Tensor:
    S = 0.5 * (S + S.transpose(-1, -2))
    if jitter > 0:
        S = S + jitter * torch.eye(S.shape[-1], dtype=S.dtype, device=S.device) * (
            torch.diagonal(S, dim1=-2, dim2=-1).mean().abs() + 1e-300
        )
    return S
