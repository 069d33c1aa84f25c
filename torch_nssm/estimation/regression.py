"""The weighted regressions of the M-step as flattened rows, their loss, and the built-in
gradient solvers (LBFGS, Adam) for modules without a closed form.

A solver ``solver(module, params, rows, settings)`` decreases :func:`weighted_loss` of the module
over :class:`RegressionRows`; :mod:`torch_nssm.estimation.solvers` registers the solvers by name.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = [
    "RegressionRows", "SolverSettings", "SolverReport", "weighted_loss", "lbfgs", "adam", "gauss_newton",
]


@dataclass
class RegressionRows:
    """One weighted regression problem of the M-step, flattened over (time, sequence, particle).

    Attributes
    ----------
    x : Tensor, shape (n, nx)
    u : Tensor, shape (n, nu)
    target : Tensor, shape (n, d)
        NaN (or any value) where an output component is missing: the precision ignores it.
    weight : Tensor, shape (n,)
    precision : Tensor, shape (d, d) or (n, d, d)
        Metric of the residuals (zero rows/columns for missing components).
    """

    x: Tensor
    u: Tensor
    target: Tensor
    weight: Tensor
    precision: Tensor

    def subset(self, idx: Tensor) -> RegressionRows:
        precision = self.precision if self.precision.dim() == 2 else self.precision[idx]
        return RegressionRows(self.x[idx], self.u[idx], self.target[idx], self.weight[idx], precision)


@dataclass
class SolverSettings:
    """What the gradient solvers read: iterations (or epochs), step size, minibatches."""

    max_iter: int = 20
    learning_rate: float = 1e-2
    batch_size: int | None = None
    patience: int = 2
    generator: torch.Generator | None = None


@dataclass
class SolverReport:
    """The outcome of one module's update: the loss before and after, and whether it was rejected
    (the previous parameters restored because the step made the loss worse or non-finite)."""

    before: float
    after: float
    rejected: bool = False


def _residuals(module: nn.Module, rows: RegressionRows) -> Tensor:
    r = rows.target - module(rows.x, rows.u)
    return torch.where(torch.isnan(rows.target), torch.zeros_like(r), r)


def weighted_loss(module: nn.Module, rows: RegressionRows) -> Tensor:
    """``sum_n w_n r_n^T P_n r_n / sum_n w_n`` (normalised so optimiser tolerances are meaningful)."""
    r = _residuals(module, rows)
    Pr = (rows.precision @ r.unsqueeze(-1)).squeeze(-1)
    return (rows.weight * (r * Pr).sum(-1)).sum() / rows.weight.sum().clamp_min(1e-300)


class _NonFiniteLoss(ArithmeticError):
    """The weighted loss became NaN or infinite during an optimiser step."""


def lbfgs(module: nn.Module, params: list[Tensor], rows: RegressionRows, settings: SolverSettings) -> None:
    """LBFGS with a strong-Wolfe line search, ``max_iter`` iterations."""
    opt = torch.optim.LBFGS(
        params, lr=1.0, max_iter=settings.max_iter, line_search_fn="strong_wolfe",
        tolerance_grad=1e-10, tolerance_change=1e-12,
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
        # torch's line search fails obscurely on NaN losses: the caller restores the parameters
        with torch.no_grad():
            for p in params:
                p.fill_(float("nan"))


def adam(module: nn.Module, params: list[Tensor], rows: RegressionRows, settings: SolverSettings) -> None:
    """Adam: ``max_iter`` full-batch steps, or with ``batch_size`` up to ``max_iter`` epochs of
    shuffled minibatches, early-stopped after ``patience`` epochs without improvement of the full
    weighted loss (the best parameters are kept): the M-step for neural networks."""
    opt = torch.optim.Adam(params, lr=settings.learning_rate)
    if settings.batch_size is None:
        for _ in range(settings.max_iter):
            opt.zero_grad()
            weighted_loss(module, rows).backward()
            opt.step()
        return
    n = rows.weight.numel()
    with torch.no_grad():
        best = float(weighted_loss(module, rows))
    best_state, bad = copy.deepcopy(module.state_dict()), 0
    for _ in range(settings.max_iter):
        order = torch.randperm(n, generator=settings.generator).to(rows.weight.device)
        for start in range(0, n, settings.batch_size):
            opt.zero_grad()
            loss = weighted_loss(module, rows.subset(order[start : start + settings.batch_size]))
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
            if bad >= settings.patience:
                break
    module.load_state_dict(best_state)


def gauss_newton(
    module: nn.Module, params: list[Tensor], rows: RegressionRows, settings: SolverSettings
) -> None:
    """Levenberg-Marquardt on the whitened weighted residuals (:mod:`.least_squares`), at most
    ``max_iter`` Jacobians: the M-step for modules with few parameters that are not linear in them
    (a physical model: a mass that divides, a friction inside a tanh).  Each Jacobian costs a few
    evaluations of the module on the rows (finite differences, one batch), and a problem that is
    nearly quadratic in its parameters converges in a few of them where LBFGS needs tens of
    gradient evaluations."""
    from .free_parameters import FreeParameters
    from .least_squares import levenberg_marquardt

    free = FreeParameters({"m": module})
    d = rows.target.shape[-1]
    L = torch.linalg.cholesky(rows.precision + 0.0)  # P = L L^T; residual^T P residual = |r L|^2
    missing = torch.isnan(rows.target)
    target = torch.where(missing, torch.zeros_like(rows.target), rows.target)

    @torch.inference_mode()
    def residuals(thetas: Tensor, _local: Tensor) -> Tensor:
        out = free.map(lambda forward, x, u: forward("m", x, u), thetas, rows.x, rows.u)  # (S, n, d)
        r = torch.where(missing, torch.zeros_like(out), target - out)
        r = (r.unsqueeze(-2) @ L).squeeze(-2)
        return r.reshape(thetas.shape[0], 1, -1)

    weight = rows.weight.repeat_interleave(d).unsqueeze(0)
    theta = free.vector()
    local = theta.new_zeros(1, 0)
    result = levenberg_marquardt(residuals, theta, local, weight, max_iter=settings.max_iter, ftol=1e-10)
    free.assign(result.theta)
