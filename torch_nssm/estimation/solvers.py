"""The M-step's gradient solvers by name, and the wrapper that makes every step safe.

``SOLVERS`` maps the estimator's ``optimizer=`` to ``solver(module, params, rows, settings)``
(:mod:`torch_nssm.estimation.regression` has the built-in ones and the row format).  A new solver
is a function in a file of its own plus one line here.  :func:`fit_weighted_regression` calls the
module's own ``solve_weighted_least_squares`` where it has one, else the chosen solver, and undoes
a step that made the loss worse or non-finite (a generalised EM step never harms); its report
says whether it did.
"""

from __future__ import annotations

import copy
from typing import Callable

import torch
from torch import nn

from .regression import RegressionRows, SolverReport, SolverSettings, adam, gauss_newton, lbfgs, weighted_loss

__all__ = [
    "SOLVERS",
    "get_solver",
    "fit_weighted_regression",
    "RegressionRows",
    "SolverSettings",
    "SolverReport",
    "weighted_loss",
]


Solver = Callable[[nn.Module, list, RegressionRows, SolverSettings], None]

#: The estimator's ``optimizer=`` choices for modules without a closed-form M-step.
SOLVERS: dict[str, Solver] = {
    "lbfgs": lbfgs,
    "adam": adam,
    "gauss-newton": gauss_newton,
}


#: ``optimizer="auto"`` takes Gauss-Newton for modules with at most this many free parameters (a
#: physical model), LBFGS for more (a network: its Jacobian would cost one evaluation a parameter).
GAUSS_NEWTON_MAX_PARAMETERS = 64


def auto_solver(module: nn.Module) -> str:
    """The solver ``optimizer="auto"`` takes for ``module``."""
    n = sum(p.numel() for p in module.parameters() if p.requires_grad)
    return "gauss-newton" if n <= GAUSS_NEWTON_MAX_PARAMETERS else "lbfgs"


def get_solver(name: str) -> Solver:
    """The gradient solver registered as ``name``."""
    try:
        return SOLVERS[name]
    except KeyError:
        raise ValueError(f"optimizer must be one of {sorted([*SOLVERS, 'auto'])}, got {name!r}") from None


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
        get_solver(auto_solver(module) if optimizer == "auto" else optimizer)(module, params, rows, settings)
    for p in params:
        p.grad = None
    with torch.no_grad():
        after = float(weighted_loss(module, rows))
    if not after <= before:  # also catches NaN
        module.load_state_dict(backup)
        return SolverReport(before, before, rejected=True)
    return SolverReport(before, after)
