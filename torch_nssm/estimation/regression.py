"""The weighted regressions of the M-step as flattened rows, their loss, and the built-in
solvers (LBFGS, Adam, Gauss-Newton) for modules without a closed form.

A solver ``solver(module, params, rows, settings)`` decreases :func:`weighted_loss` of the module
over :class:`RegressionRows`; :mod:`torch_nssm.estimation.solvers` registers the solvers by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

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
    """What the gradient solvers read: iterations (or epochs), step size, minibatches, and
    ``memory``: what a solver carries from one M-step to the next (copies made by
    ``dataclasses.replace`` share it; ``adam`` keeps there the step size that last made progress for
    each module)."""

    max_iter: int = 20
    learning_rate: float = 1e-2
    batch_size: int | None = None
    patience: int = 2
    generator: torch.Generator | None = None
    memory: dict = field(default_factory=dict)


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


#: Rows up to which ``adam`` without ``batch_size`` takes full-batch steps; above, it takes steps on
#: minibatches of :data:`AUTO_BATCH_ROWS` rows.
FULL_BATCH_ROWS = 2**16
AUTO_BATCH_ROWS = 2**13
#: Rows above which ``adam`` judges its iterates on a fixed draw of this many rows (the final iterate
#: is then checked on all rows).
CHECK_ROWS = 2**16
#: Minibatch steps between two judgements when ``adam`` draws the minibatches itself.
AUTO_CHECK_STEPS = 10
#: Judgements in a row without a better iterate after which ``adam`` stops (each halves the step
#: size).
MAX_HALVINGS = 14


def _set_vector(params: list[Tensor], vector: Tensor) -> None:
    """Copy a flat vector into the parameters (``vector_to_parameters`` would make them views of it)."""
    first = 0
    for p in params:
        p.copy_(vector[first : first + p.numel()].view_as(p))
        first += p.numel()


def _weighted_draw(rows: RegressionRows, size: int, generator) -> RegressionRows:
    """``size`` rows drawn with probability proportional to their weight, with unit weights: an
    unbiased estimate of the weighted loss (the smoothing weights of a time step sum to one, so most
    of the ``N L`` rows carry little of it and a uniform draw would waste the batch)."""
    probabilities = rows.weight.detach().clamp_min(0).double().cpu()
    index = torch.multinomial(probabilities, size, replacement=True, generator=generator)
    drawn = rows.subset(index.to(rows.weight.device))
    drawn.weight = torch.ones_like(drawn.weight)
    return drawn


def adam(module: nn.Module, params: list[Tensor], rows: RegressionRows, settings: SolverSettings) -> None:
    """Adam that keeps the best iterate of the weighted loss and backtracks: the M-step for networks.

    Steps: ``max_iter`` full-batch steps (up to :data:`FULL_BATCH_ROWS` rows), or ``max_iter`` steps
    on minibatches of :data:`AUTO_BATCH_ROWS` rows drawn with probability proportional to their
    weight (more rows), or with ``batch_size`` up to ``max_iter`` epochs of shuffled minibatches.
    The loss is judged after every full-batch step, every :data:`AUTO_CHECK_STEPS` minibatch steps
    or every epoch, and after every step until an iterate beats the start, on all rows (up to
    :data:`CHECK_ROWS`) or on a fixed weighted draw of :data:`CHECK_ROWS` of them.  A judgement
    that is not better than the best so far (or not finite) restores the best iterate, halves the
    step size and restarts Adam's moments; :data:`MAX_HALVINGS` such judgements in a row (at least
    ``patience``) stop the solver.  The first step size is ``learning_rate``, or twice the one that
    last made progress for this module (``settings.memory``; at most ``learning_rate``): a network
    near its optimum needs steps near 1e-4, where an untrained one takes 1e-2.

    It ends at the best iterate (checked on all rows when a draw judged), so a minibatch's noise or
    a too large step never makes the M-step worse.  When nothing beat the start it keeps the start
    if every iterate tried had a finite loss and the step size went down to ``2**-MAX_HALVINGS``
    times its first value (a stationary point: a null step), and otherwise ends at the last iterate
    tried (a failure, which the caller rejects).
    """
    n = rows.weight.numel()
    gen = settings.generator
    check = rows if n <= CHECK_ROWS else _weighted_draw(rows, CHECK_ROWS, gen)
    if settings.batch_size is not None:
        batch, per_check = settings.batch_size, None  # one judgement per epoch
    elif n > FULL_BATCH_ROWS:
        batch, per_check = AUTO_BATCH_ROWS, AUTO_CHECK_STEPS
    else:
        batch, per_check = None, 1
    key = ("adam", id(module))
    lr = min(settings.learning_rate, 2.0 * settings.memory.get(key, settings.learning_rate))
    opt = torch.optim.Adam(params, lr=lr)
    with torch.no_grad():
        best = float(weighted_loss(module, check))
    start = torch.nn.utils.parameters_to_vector(params).detach().clone()
    best_vector, improved, fails, finite = start.clone(), False, 0, True
    limit = max(settings.patience, MAX_HALVINGS)
    tried = start  # the last iterate judged worse (left in place when nothing beat the start)

    def judge() -> bool:
        """Keep the current iterate if it is the best so far; else back to the best with half the
        step size.  Whether the solver stops."""
        nonlocal best, best_vector, improved, fails, finite, lr, opt, tried
        with torch.no_grad():
            current = float(weighted_loss(module, check))
        if current < best:  # also False for NaN
            best, improved, fails = current, True, 0
            best_vector = torch.nn.utils.parameters_to_vector(params).detach().clone()
            settings.memory[key] = lr
            return False
        fails += 1
        finite = finite and math.isfinite(current)
        if fails >= limit:
            return True
        tried = torch.nn.utils.parameters_to_vector(params).detach().clone()
        with torch.no_grad():
            _set_vector(params, best_vector)
        lr *= 0.5
        opt = torch.optim.Adam(params, lr=lr)
        return False

    def step(subset: RegressionRows) -> None:
        opt.zero_grad()
        loss = weighted_loss(module, subset)
        if bool(torch.isfinite(loss)):
            loss.backward()
            opt.step()

    k = 0
    for epoch in range(settings.max_iter):
        if batch is None or per_check is not None:  # one step
            step(rows if batch is None else _weighted_draw(rows, batch, gen))
            k += 1
            due = not improved or k % per_check == 0 or epoch + 1 == settings.max_iter
        else:  # one epoch of shuffled minibatches
            order = torch.randperm(n, generator=gen).to(rows.weight.device)
            stopped = False
            for first in range(0, n, batch):
                step(rows.subset(order[first : first + batch]))
                if not improved and judge():
                    stopped = True
                    break
            if stopped:
                break
            due = improved
        if due and judge():
            break
    with torch.no_grad():
        if improved and check is not rows:  # judged on a draw: the best iterate against all rows
            _set_vector(params, start)
            before = float(weighted_loss(module, rows))
            _set_vector(params, best_vector)
            improved = float(weighted_loss(module, rows)) < before
        stationary = fails >= limit and finite
        _set_vector(params, best_vector if improved else start if stationary else tried)


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
