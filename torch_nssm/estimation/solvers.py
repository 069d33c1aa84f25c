"""Gradient solvers of the M-step for modules without a closed form: one function each, one line
each in :data:`SOLVERS`.

A solver decreases :func:`weighted_loss` of a module over flattened :class:`RegressionRows`.
:func:`fit_weighted_regression` wraps the chosen one: it calls a module's own
``solve_weighted_least_squares`` where it has one, and restores the previous parameters when the
loss got worse or non-finite, so an M-step never harms (a generalised EM step).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

__all__ = [
    "RegressionRows",
    "SolverSettings",
    "SolverReport",
    "SOLVERS",
    "get_solver",
    "weighted_loss",
    "fit_weighted_regression",
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


Solver = Callable[[nn.Module, list, RegressionRows, SolverSettings], None]

#: The estimator's ``optimizer=`` choices for modules without a closed-form M-step.
SOLVERS: dict[str, Solver] = {
    "lbfgs": lbfgs,
    "adam": adam,
}


def get_solver(name: str) -> Solver:
    """The gradient solver registered as ``name``."""
    try:
        return SOLVERS[name]
    except KeyError:
        raise ValueError(f"optimizer must be one of {sorted(SOLVERS)}, got {name!r}") from None


def fit_weighted_regression(
    module: nn.Module, rows: RegressionRows, optimizer: str = "lbfgs", settings: SolverSettings | None = None
) -> SolverReport:
    """Update the free parameters of ``module`` to decrease :func:`weighted_loss` over ``rows``.

    Uses the module's ``solve_weighted_least_squares(x, u, target, weight, precision)`` when it has
    one, else the solver ``optimizer``.  A step that makes the loss worse or non-finite is undone.
    """
    settings = settings or SolverSettings()
    params = [p for p in module.parameters() if p.requires_grad]
    if not params or rows.weight.numel() == 0:
        with torch.no_grad():
            loss = float(weighted_loss(module, rows)) if rows.weight.numel() else 0.0
        return SolverReport(loss, loss)
    backup = copy.deepcopy(module.state_dict())
    with torch.no_grad():
        before = float(weighted_loss(module, rows))
    if hasattr(module, "solve_weighted_least_squares"):
        module.solve_weighted_least_squares(rows.x, rows.u, rows.target, rows.weight, rows.precision)
    else:
        get_solver(optimizer)(module, params, rows, settings)
    for p in params:
        p.grad = None
    with torch.no_grad():
        after = float(weighted_loss(module, rows))
    if not after <= before:  # also catches NaN
        module.load_state_dict(backup)
        return SolverReport(before, before, rejected=True)
    return SolverReport(before, after)
