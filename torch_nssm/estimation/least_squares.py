"""Robust Levenberg-Marquardt for residuals with shared and per-window parameters.

The problems of the first stage (multiple shooting: parameters ``theta`` shared by every window,
a first state per window) and of the Gauss-Newton M-step (``theta`` alone) are weighted nonlinear
least squares over a residual array ``r`` of shape ``(W, m)``: ``W`` windows of ``m`` rows, the
rows of window ``w`` depending on ``theta`` ``(P,)`` and on the window's own ``local[w]`` ``(q,)``.
The normal equations then have a block-arrow structure, and the window blocks are eliminated by
their Schur complement (as in bundle adjustment): a step costs ``O(W m (P + q)^2 + W q^3 + P^3)``,
never a dense ``(P + W q)``-square system.

The Jacobian comes from one-sided finite differences evaluated as one batch of ``P + q + 1``
parameter sets (``residuals`` takes the batch), which costs a few evaluations where forward-mode
differentiation through a simulation loop costs 15-20.  Robust losses are handled by iteratively
reweighted Gauss-Newton: each step uses the weights ``rho'(r^2)`` at the current residuals, and a
step is kept only when the robust objective itself decreases (Nielsen's damping update).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

__all__ = ["LOSSES", "LeastSquaresResult", "robust_loss", "levenberg_marquardt"]

#: ``rho(s)`` of the squared scaled residual ``s`` and its derivative ``rho'(s)``.  ``cauchy`` with
#: ``c = CAUCHY_C``: 95 % efficiency at the normal, and a far outlier's weight goes to zero.
CAUCHY_C = 2.385
LOSSES = ("linear", "cauchy", "soft_l1")


def robust_loss(s: Tensor, loss: str) -> tuple[Tensor, Tensor]:
    """``rho(s)`` and ``rho'(s)`` of squared residuals ``s`` (in units of the residuals' scale)."""
    if loss == "linear":
        return s, torch.ones_like(s)
    if loss == "cauchy":
        c2 = CAUCHY_C**2
        return c2 * torch.log1p(s / c2), 1.0 / (1.0 + s / c2)
    if loss == "soft_l1":
        t = torch.sqrt(1.0 + s)
        return 2.0 * (t - 1.0), 1.0 / t
    raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")


@dataclass
class LeastSquaresResult:
    """The outcome of :func:`levenberg_marquardt`.

    Attributes
    ----------
    theta : Tensor, shape (P,)
    local : Tensor, shape (W, q)
    objective : float
        ``sum w rho(r^2) / sum w`` at the result.
    initial_objective : float
    n_iter : int
        Jacobians computed.
    n_evaluations : int
        Residual evaluations (a Jacobian counts ``P + q + 1``).
    status : str
        Why it stopped: ``"converged"``, ``"max_iter"``, ``"no_progress"`` (no step along the
        damped directions decreased the objective) or ``"not_finite"`` (the start's residuals are
        not finite).
    """

    theta: Tensor
    local: Tensor
    objective: float
    initial_objective: float
    n_iter: int
    n_evaluations: int
    status: str


Residuals = Callable[[Tensor, Tensor], Tensor]


def _objective(r: Tensor, weight: Tensor, total: Tensor, loss: str) -> float:
    rho, _ = robust_loss(r * r, loss)
    value = float((weight * rho).sum() / total)
    return value if math.isfinite(value) else math.inf


def _fd_steps(v: Tensor) -> Tensor:
    return math.sqrt(torch.finfo(v.dtype).eps) * torch.clamp(v.abs(), min=1e-2)


def _jacobian(residuals: Residuals, theta: Tensor, local: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals ``(W, m)`` at the point and their Jacobians ``(W, m, P)``, ``(W, m, q)`` by one-sided
    differences, all ``P + q + 1`` evaluations as one batch.  Local direction ``j`` moves entry ``j``
    of every window's local parameters at once (windows do not see each other's)."""
    P, (W, q) = theta.numel(), local.shape
    h_theta = _fd_steps(theta)
    h_local = _fd_steps(local).amax(0) if W else torch.zeros(q, dtype=local.dtype, device=local.device)
    thetas = theta.expand(1 + P + q, P).clone()
    locals_ = local.expand(1 + P + q, W, q).clone()
    idx = torch.arange(P, device=theta.device)
    thetas[1 + idx, idx] += h_theta
    for j in range(q):
        locals_[1 + P + j, :, j] += h_local[j]
    r = residuals(thetas, locals_)  # (1 + P + q, W, m)
    base = r[0]
    Jg = ((r[1 : 1 + P] - base) / h_theta.view(-1, 1, 1)).permute(1, 2, 0)
    Jl = ((r[1 + P :] - base) / h_local.view(-1, 1, 1)).permute(1, 2, 0)
    # a perturbed evaluation that left the finite range carries no usable slope
    return base, torch.nan_to_num(Jg, nan=0.0, posinf=0.0, neginf=0.0), torch.nan_to_num(
        Jl, nan=0.0, posinf=0.0, neginf=0.0
    )


def _damped(M: Tensor, lam: float) -> Tensor:
    """``M + lam * diag(M)`` (Marquardt's scaling), the diagonal floored relative to its largest."""
    d = torch.diagonal(M, dim1=-2, dim2=-1)
    floor = 1e-12 * d.amax(-1, keepdim=True).clamp_min(1e-300)
    return M + torch.diag_embed(lam * torch.maximum(d, floor) + floor)


def _step(
    Jg: Tensor, Jl: Tensor, r: Tensor, omega: Tensor, lam: float
) -> tuple[Tensor, Tensor, float]:
    """The damped Gauss-Newton step ``(dtheta, dlocal)`` by the Schur complement of the window
    blocks, and the decrease of the local quadratic model it predicts."""
    P, q = Jg.shape[-1], Jl.shape[-1]
    wJg = omega.unsqueeze(-1) * Jg
    A = torch.einsum("wmp,wmk->pk", wJg, Jg)
    a = torch.einsum("wmp,wm->p", wJg, r)
    if q:
        wJl = omega.unsqueeze(-1) * Jl
        B = torch.einsum("wmp,wmk->wpk", wJg, Jl)  # (W, P, q)
        C = torch.einsum("wmp,wmk->wpk", wJl, Jl)  # (W, q, q)
        c = torch.einsum("wmq,wm->wq", wJl, r)
        Cd = _damped(C, lam)
        CinvBt = torch.linalg.solve(Cd, B.transpose(-1, -2))  # (W, q, P)
        Cinvc = torch.linalg.solve(Cd, c.unsqueeze(-1)).squeeze(-1)  # (W, q)
        S = _damped(A, lam) - torch.einsum("wpq,wqk->pk", B, CinvBt) if P else A
        rhs = a - torch.einsum("wpq,wq->p", B, Cinvc) if P else a
    else:
        S, rhs = _damped(A, lam), a
    dg = -torch.linalg.solve(S, rhs) if P else rhs.new_zeros(0)
    dl = -(Cinvc + torch.einsum("wqp,p->wq", CinvBt, dg)) if q else Jl.new_zeros(Jl.shape[0], 0)
    # predicted decrease of 1/2 sum omega (r + J d)^2
    Jd = Jg @ dg if P else torch.zeros_like(r)
    if q:
        Jd = Jd + (Jl @ dl.unsqueeze(-1)).squeeze(-1)
    predicted = float(-(omega * (r * Jd + 0.5 * Jd * Jd)).sum())
    return dg, dl, predicted


def levenberg_marquardt(
    residuals: Residuals,
    theta: Tensor,
    local: Tensor,
    weight: Tensor,
    *,
    loss: str = "linear",
    max_iter: int = 50,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
) -> LeastSquaresResult:
    """Minimise ``sum w rho(r^2)`` over ``theta`` (shared) and ``local`` (per window).

    Parameters
    ----------
    residuals : callable
        ``residuals(thetas (S, P), locals (S, W, q)) -> (S, W, m)``: the scaled residuals at ``S``
        points at once (NaN or inf where an evaluation left the finite range).
    theta : Tensor, shape (P,)
    local : Tensor, shape (W, q)
        ``q`` may be 0.
    weight : Tensor, shape (W, m)
        Fixed row weights (0 for rows that do not count, e.g. missing outputs).
    loss : {"linear", "cauchy", "soft_l1"}
    max_iter : int
        Jacobians at most.
    ftol, xtol : float
        Stop when an accepted step lowers the objective by less than ``ftol`` relatively, or
        moves every variable by less than ``xtol`` relatively.

    Returns
    -------
    LeastSquaresResult
    """
    total = weight.sum().clamp_min(1e-300)
    n_eval = 1
    r = residuals(theta.unsqueeze(0), local.unsqueeze(0))[0]
    F = _objective(r, weight, total, loss)
    F0 = F
    if not math.isfinite(F):
        return LeastSquaresResult(theta, local, F, F0, 0, n_eval, "not_finite")
    lam, nu = 1e-3, 2.0
    status, n_iter = "max_iter", 0
    while n_iter < max_iter:
        r, Jg, Jl = _jacobian(residuals, theta, local)
        n_iter += 1
        n_eval += theta.numel() + local.shape[-1] + 1
        _, drho = robust_loss(r * r, loss)
        omega = weight * drho / total
        r0 = torch.where(weight > 0, r, torch.zeros_like(r))
        accepted = False
        for _ in range(30):  # raise the damping until a step lowers the objective
            dg, dl, predicted = _step(Jg, Jl, r0, omega, lam)
            new_theta, new_local = theta + dg, local + dl
            r_new = residuals(new_theta.unsqueeze(0), new_local.unsqueeze(0))[0]
            n_eval += 1
            F_new = _objective(r_new, weight, total, loss)
            gain = (F - F_new) / (2.0 * predicted) if predicted > 0 else -1.0
            if math.isfinite(F_new) and F_new < F:
                accepted = True
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3) if gain > 0 else 1.0
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                break
        if not accepted:
            status = "no_progress"
            break
        small_f = (F - F_new) <= ftol * max(abs(F), 1e-300)
        scale = torch.cat([theta.abs().reshape(-1), local.abs().reshape(-1)]).clamp_min(1e-8)
        small_x = bool((torch.cat([dg.reshape(-1), dl.reshape(-1)]).abs() <= xtol * scale).all())
        theta, local, F = new_theta, new_local, F_new
        if small_f or small_x:
            status = "converged"
            break
    return LeastSquaresResult(theta, local, F, F0, n_iter, n_eval, status)
