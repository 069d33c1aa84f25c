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
differentiation through a simulation loop costs 15-20; with ``speculative`` each trial point is
evaluated in the batch of its own Jacobian, so an accepted step costs one pass of a simulation
loop instead of two.  Robust losses are handled by iteratively
reweighted Gauss-Newton: each step uses the weights ``rho'(r^2)`` at the current residuals, and a
step is kept only when the robust objective itself decreases (Nielsen's damping update).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

__all__ = ["LOSSES", "Links", "LeastSquaresResult", "robust_loss", "levenberg_marquardt"]

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
        Iterations (steps tried from a new point; ``max_iter`` bounds them).
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


Residuals = Callable[[Tensor, Tensor], "Tensor | tuple[Tensor, Tensor]"]


@dataclass
class Links:
    """Soft continuity between consecutive windows (multiple shooting): window ``w``'s simulated
    state after its last sample should equal window ``w + 1``'s first state.  Each linked pair adds
    ``q`` residuals ``(end_w - local_{w+1}) / scale`` to the objective (not robustified).

    Attributes
    ----------
    linked : Tensor of bool, shape (W - 1,)
        Whether window ``w`` continues into window ``w + 1`` (the same record).
    scale : Tensor, shape (q,)
        The mismatch of each state that costs as much as one scaled output residual.
    """

    linked: Tensor
    scale: Tensor


def _objective(r: Tensor, weight: Tensor, total: Tensor, loss: str, link_r: Tensor | None = None) -> float:
    rho, _ = robust_loss(r * r, loss)
    value = (weight * rho).sum()
    if link_r is not None:
        value = value + (link_r * link_r).sum()
    value = float(value / total)
    return value if math.isfinite(value) else math.inf


def _fd_steps(v: Tensor) -> Tensor:
    return math.sqrt(torch.finfo(v.dtype).eps) * torch.clamp(v.abs(), min=1e-2)


def _split(out) -> tuple[Tensor, Tensor | None]:
    return out if isinstance(out, tuple) else (out, None)


def _link_residuals(ends: Tensor | None, local: Tensor, links: Links | None) -> Tensor | None:
    """``(end_w - local_{w+1}) / scale`` where linked, 0 elsewhere, shape ``(W - 1, q)``."""
    if links is None or ends is None:
        return None
    e = (ends[..., :-1, :] - local[..., 1:, :]) / links.scale
    return torch.where(links.linked.unsqueeze(-1), e, torch.zeros_like(e))


def _fd(values: Tensor, base: Tensor, h: Tensor) -> Tensor:
    """Finite-difference columns ``(values - base) / h`` moved last, non-finite slopes set to 0 (a
    perturbed evaluation that left the finite range carries no usable slope)."""
    J = ((values - base) / h.view(-1, *([1] * base.dim()))).movedim(0, -1)
    return torch.nan_to_num(J, nan=0.0, posinf=0.0, neginf=0.0)


def _jacobian(residuals: Residuals, theta: Tensor, local: Tensor):
    """Residuals ``(W, m)`` at the point and their Jacobians ``(W, m, P)``, ``(W, m, q)`` by one-sided
    differences, all ``P + q + 1`` evaluations as one batch; with window end states, also those and
    their Jacobians ``(W, q, P)``, ``(W, q, q)``.  Local direction ``j`` moves entry ``j`` of every
    window's local parameters at once (windows do not see each other's)."""
    P, (W, q) = theta.numel(), local.shape
    h_theta = _fd_steps(theta)
    h_local = _fd_steps(local).amax(0) if W else torch.zeros(q, dtype=local.dtype, device=local.device)
    thetas = theta.expand(1 + P + q, P).clone()
    locals_ = local.expand(1 + P + q, W, q).clone()
    idx = torch.arange(P, device=theta.device)
    thetas[1 + idx, idx] += h_theta
    for j in range(q):
        locals_[1 + P + j, :, j] += h_local[j]
    r, ends = _split(residuals(thetas, locals_))  # (1 + P + q, W, m), (1 + P + q, W, q)
    out = [r[0], _fd(r[1 : 1 + P], r[0], h_theta), _fd(r[1 + P :], r[0], h_local)]
    if ends is not None:
        out += [ends[0], _fd(ends[1 : 1 + P], ends[0], h_theta), _fd(ends[1 + P :], ends[0], h_local)]
    return out


def _damped(M: Tensor, lam: float) -> Tensor:
    """``M + lam * diag(M)`` (Marquardt's scaling), the diagonal floored relative to its largest."""
    d = torch.diagonal(M, dim1=-2, dim2=-1)
    floor = 1e-12 * d.amax(-1, keepdim=True).clamp_min(1e-300)
    return M + torch.diag_embed(lam * torch.maximum(d, floor) + floor)


@dataclass
class _Normal:
    """The Gauss-Newton normal equations in block-arrow form: shared block ``A``, ``a``; window
    blocks ``C``, ``c``; couplings ``B`` (shared-window) and ``O`` (window ``w`` with ``w + 1``)."""

    A: Tensor
    a: Tensor
    B: Tensor
    C: Tensor
    c: Tensor
    O: Tensor | None


def _normal_equations(J: list, r: Tensor, omega: Tensor, link_r, links: Links | None, total) -> _Normal:
    _, Jg, Jl = J[:3]
    wJg = omega.unsqueeze(-1) * Jg
    wJl = omega.unsqueeze(-1) * Jl
    A = torch.einsum("wmp,wmk->pk", wJg, Jg)
    a = torch.einsum("wmp,wm->p", wJg, r)
    B = torch.einsum("wmp,wmk->wpk", wJg, Jl)
    C = torch.einsum("wmp,wmk->wpk", wJl, Jl)
    c = torch.einsum("wmq,wm->wq", wJl, r)
    O = None
    if link_r is not None:
        mask = links.linked.to(r.dtype).view(-1, 1, 1) / total
        Eg = J[4][:-1] / links.scale.view(-1, 1) * mask  # (W-1, q, P), scaled by 1/total
        Ez = J[5][:-1] / links.scale.view(-1, 1)  # (W-1, q, q)
        inv_s = (1.0 / links.scale).expand_as(link_r)
        A = A + torch.einsum("kqp,kqr->pr", J[4][:-1] / links.scale.view(-1, 1), Eg)
        a = a + torch.einsum("kqp,kq->p", Eg, link_r)
        B = B.clone()
        B[:-1] += torch.einsum("kqp,kqr->kpr", Eg, Ez)
        B[1:] -= Eg.transpose(-1, -2) * inv_s.unsqueeze(-2)
        C = C.clone()
        C[:-1] += torch.einsum("kqp,kqr->kpr", Ez * mask, Ez)
        C[1:] += torch.diag_embed(inv_s * inv_s) * mask
        O = -(Ez * mask).transpose(-1, -2) * inv_s.unsqueeze(-2)  # (W-1, q, q): d^2/dz_w dz_{w+1}
        c = c.clone()
        c[:-1] += torch.einsum("kqp,kq->kp", Ez * mask, link_r)
        c[1:] -= link_r * inv_s * mask.view(-1, 1)
    return _Normal(A, a, B, C, c, O)


def _solve_windows(C: Tensor, O: Tensor | None, R: Tensor) -> Tensor:
    """``T^-1 R`` for the window blocks ``T`` (block diagonal ``C``, or block tridiagonal with ``O``
    above the diagonal), ``R`` ``(W, q, k)``."""
    if O is None:
        return torch.linalg.solve(C, R)
    import numpy as np
    from scipy.linalg import solveh_banded

    W, q, k = R.shape
    Cn, On = C.detach().cpu().numpy(), O.detach().cpu().numpy()
    ab = np.zeros((2 * q, W * q))
    a_idx, b_idx = np.meshgrid(np.arange(q), np.arange(q), indexing="ij")
    lower = a_idx >= b_idx
    w = np.arange(W)[:, None, None]
    rows, cols = (w * q + a_idx)[:, lower], (w * q + b_idx)[:, lower]
    ab[rows - cols, cols] = Cn[:, lower]
    w = np.arange(W - 1)[:, None, None]
    rows, cols = (w + 1) * q + a_idx, w * q + b_idx  # the block below the diagonal: O_w^T
    ab[(rows - cols).ravel(), cols.ravel()] = On.transpose(0, 2, 1).ravel()
    x = solveh_banded(ab, R.detach().cpu().numpy().reshape(W * q, k), lower=True)
    return torch.as_tensor(x.reshape(W, q, k), dtype=R.dtype, device=R.device)


def _step(
    J: list, r: Tensor, omega: Tensor, link_r, links, total, lam: float
) -> tuple[Tensor, Tensor, float]:
    """The damped Gauss-Newton step ``(dtheta, dlocal)`` by the Schur complement of the window
    blocks, and the decrease of the local quadratic model it predicts."""
    _, Jg, Jl = J[:3]
    P, q = Jg.shape[-1], Jl.shape[-1]
    N = _normal_equations(J, r, omega, link_r, links, total)
    W = N.C.shape[0]
    if q:
        Cd = _damped(N.C, lam)
        X = _solve_windows(Cd, N.O, torch.cat([N.B.transpose(-1, -2), N.c.unsqueeze(-1)], -1))
        TinvBt, Tinvc = X[..., :P], X[..., P]  # (W, q, P), (W, q)
        S = _damped(N.A, lam) - torch.einsum("wqp,wqk->pk", N.B.transpose(-1, -2), TinvBt) if P else N.A
        rhs = N.a - torch.einsum("wpq,wq->p", N.B, Tinvc) if P else N.a
    else:
        S, rhs = _damped(N.A, lam), N.a
    dg = -torch.linalg.solve(S, rhs) if P else rhs.new_zeros(0)
    dl = -(Tinvc + torch.einsum("wqp,p->wq", TinvBt, dg)) if q else Jl.new_zeros(W, 0)
    # predicted decrease of 1/2 (sum omega (r + J d)^2 + sum (e + E d)^2 / total)
    Jd = Jg @ dg if P else torch.zeros_like(r)
    if q:
        Jd = Jd + (Jl @ dl.unsqueeze(-1)).squeeze(-1)
    predicted = -(omega * (r * Jd + 0.5 * Jd * Jd)).sum()
    if link_r is not None:
        Ed = J[4][:-1] @ dg + (J[5][:-1] @ dl[:-1].unsqueeze(-1)).squeeze(-1) - dl[1:]
        Ed = torch.where(links.linked.unsqueeze(-1), Ed / links.scale, torch.zeros_like(Ed))
        predicted = predicted - (link_r * Ed + 0.5 * Ed * Ed).sum() / total
    return dg, dl, float(predicted)


#: The small-decrease and small-step stops of :func:`levenberg_marquardt` count once a step has been
#: accepted at a damping no larger than this (a nearly Gauss-Newton step): a run started heavily
#: damped (a far start) otherwise stops after its first, deliberately short step.
SETTLED_DAMPING = 1e-2


def levenberg_marquardt(
    residuals: Residuals,
    theta: Tensor,
    local: Tensor,
    weight: Tensor,
    *,
    loss: str = "linear",
    links: Links | None = None,
    max_iter: int = 50,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    damping: float = 1e-3,
    speculative: bool = False,
) -> LeastSquaresResult:
    """Minimise ``sum w rho(r^2)`` (plus the continuity residuals of ``links``) over ``theta``
    (shared) and ``local`` (per window).

    Parameters
    ----------
    residuals : callable
        ``residuals(thetas (S, P), locals (S, W, q)) -> (S, W, m)``: the scaled residuals at ``S``
        points at once (NaN or inf where an evaluation left the finite range); with ``links``, a
        pair ``(residuals, ends)``, ``ends`` ``(S, W, q)`` each window's state after its last sample.
    theta : Tensor, shape (P,)
    local : Tensor, shape (W, q)
        ``q`` may be 0.
    weight : Tensor, shape (W, m)
        Fixed row weights (0 for rows that do not count, e.g. missing outputs).
    loss : {"linear", "cauchy", "soft_l1"}
    links : Links, optional
        Soft continuity between consecutive windows.
    max_iter : int
        Iterations at most (one Jacobian each; with ``speculative``, one for each trial point).
    ftol, xtol : float
        Stop when an accepted step lowers the objective by less than ``ftol`` relatively, or
        moves every variable by less than ``xtol`` relatively.
    damping : float
        The first step's damping ``lambda`` (Marquardt's scaling: ``lambda`` times the diagonal of
        the normal equations is added to them).  Small (1e-3): the first step is nearly
        Gauss-Newton's, right for a start near the minimum (the M-step); about 1 for a start far
        from it, where a full Gauss-Newton step can jump into another basin (the ``ftol`` and
        ``xtol`` stops then wait until the damping has come down to :data:`SETTLED_DAMPING`).
    speculative : bool
        Evaluate each trial point's Jacobian with its residuals, in one batch, so that an accepted
        step (most are) needs no further pass for the next Jacobian.  Worth it where an evaluation's
        cost is its sequential steps rather than its batch's width (a simulation over a window);
        a rejected trial wastes ``P + q`` evaluations.

    Returns
    -------
    LeastSquaresResult
    """
    total = weight.sum().clamp_min(1e-300)

    def evaluate(th: Tensor, lo: Tensor) -> tuple[list | None, float, int]:
        """The objective at a point, with the point's Jacobian when ``speculative`` (in one batch);
        also how many evaluations that took."""
        if speculative:
            J = _jacobian(residuals, th, lo)
            link_r = _link_residuals(J[3] if len(J) > 3 else None, lo, links)
            return J, _objective(J[0], weight, total, loss, link_r), per_jacobian
        r, ends = _split(residuals(th.unsqueeze(0), lo.unsqueeze(0)))
        link_r = _link_residuals(None if ends is None else ends[0], lo, links)
        return None, _objective(r[0], weight, total, loss, link_r), 1

    per_jacobian = theta.numel() + local.shape[-1] + 1
    J, F, n_eval = evaluate(theta, local)
    F0 = F
    if not math.isfinite(F):
        return LeastSquaresResult(theta, local, F, F0, 0, n_eval, "not_finite")
    lam, nu = float(damping), 2.0
    # a heavily damped step makes little progress by design: the small-step stops count once a step
    # has been taken at nearly Gauss-Newton damping (from the start when the first step is one)
    settled = lam <= SETTLED_DAMPING
    status, n_iter = "max_iter", 0
    while n_iter < max_iter:
        if J is None:
            J = _jacobian(residuals, theta, local)
            n_eval += per_jacobian
        r = J[0]
        link_r = _link_residuals(J[3] if len(J) > 3 else None, local, links)
        n_iter += 1
        _, drho = robust_loss(r * r, loss)
        omega = weight * drho / total
        r0 = torch.where(weight > 0, r, torch.zeros_like(r))
        accepted, first_prediction = False, None
        for _ in range(30):  # raise the damping until a step lowers the objective
            dg, dl, predicted = _step(J, r0, omega, link_r, links, total, lam)
            first_prediction = predicted if first_prediction is None else first_prediction
            new_theta, new_local = theta + dg, local + dl
            J_new, F_new, n = evaluate(new_theta, new_local)
            n_eval += n
            gain = (F - F_new) / (2.0 * predicted) if predicted > 0 else -1.0
            if math.isfinite(F_new) and F_new < F:
                accepted = True
                settled = settled or lam <= SETTLED_DAMPING
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3) if gain > 0 else 1.0
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                break
        if not accepted:
            # at a minimum the quadratic model promises nothing: that is convergence
            status = "converged" if 2.0 * first_prediction <= ftol * max(abs(F), 1e-300) else "no_progress"
            break
        small_f = (F - F_new) <= ftol * max(abs(F), 1e-300)
        scale = torch.cat([theta.abs().reshape(-1), local.abs().reshape(-1)]).clamp_min(1e-8)
        small_x = bool((torch.cat([dg.reshape(-1), dl.reshape(-1)]).abs() <= xtol * scale).all())
        theta, local, F, J = new_theta, new_local, F_new, J_new
        if settled and (small_f or small_x):
            status = "converged"
            break
    return LeastSquaresResult(theta, local, F, F0, n_iter, n_eval, status)
