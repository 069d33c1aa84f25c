"""Robust Levenberg-Marquardt with per-window parameters, and the free-parameter vector."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torch_nssm.estimation.free_parameters import FreeParameters
from torch_nssm.estimation.least_squares import _jacobian, levenberg_marquardt, robust_loss

D = torch.float64


def _linear_problem(seed=0, W=6, m=40, P=3, q=2):
    """Rows ``r_w = y_w - A_w theta - B_w z_w``: a linear least-squares problem with shared and
    per-window unknowns, whose exact solution is a dense ``lstsq``."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(W, m, P, generator=g, dtype=D)
    B = torch.randn(W, m, q, generator=g, dtype=D)
    theta_true = torch.randn(P, generator=g, dtype=D)
    z_true = torch.randn(W, q, generator=g, dtype=D)
    y = A @ theta_true + (B @ z_true.unsqueeze(-1)).squeeze(-1)
    y = y + 0.01 * torch.randn(W, m, generator=g, dtype=D)

    def residuals(thetas, zs):
        return y - torch.einsum("wmp,sp->swm", A, thetas) - torch.einsum("wmq,swq->swm", B, zs)

    dense = torch.zeros(W * m, P + W * q, dtype=D)
    for w in range(W):
        dense[w * m : (w + 1) * m, :P] = A[w]
        dense[w * m : (w + 1) * m, P + w * q : P + (w + 1) * q] = B[w]
    exact = torch.linalg.lstsq(dense, y.reshape(-1, 1)).solution.flatten()
    return residuals, exact[:P], exact[P:].reshape(W, q), (W, m, P, q)


def test_levenberg_marquardt_solves_a_linear_problem_with_window_blocks_exactly():
    residuals, theta_exact, z_exact, (W, m, P, q) = _linear_problem()
    weight = torch.ones(W, m, dtype=D)
    zeros = torch.zeros(W, q, dtype=D)
    res = levenberg_marquardt(residuals, torch.zeros(P, dtype=D), zeros, weight, ftol=1e-14)
    assert res.status in ("converged", "max_iter")
    torch.testing.assert_close(res.theta, theta_exact, atol=1e-7, rtol=0)
    torch.testing.assert_close(res.local, z_exact, atol=1e-7, rtol=0)
    assert res.objective < res.initial_objective


def test_zero_weights_drop_rows_and_no_local_parameters_work():
    residuals, _, _, (W, m, P, q) = _linear_problem(seed=1, q=0)
    weight = torch.ones(W, m, dtype=D)
    weight[:, ::2] = 0.0  # every other row does not count
    zeros = torch.zeros(W, 0, dtype=D)
    res = levenberg_marquardt(residuals, torch.zeros(P, dtype=D), zeros, weight, ftol=1e-14)
    r = residuals(res.theta.unsqueeze(0), torch.zeros(1, W, 0, dtype=D))[0]
    # the normal equations of the weighted rows hold at the solution
    A = -torch.stack([_jacobian(residuals, res.theta, torch.zeros(W, 0, dtype=D))[1]])[0]
    grad = torch.einsum("wmp,wm->p", A * weight.unsqueeze(-1), r)
    assert float(grad.abs().max()) < 1e-6


def test_cauchy_loss_is_not_steered_by_gross_outliers():
    g = torch.Generator().manual_seed(3)
    x = torch.linspace(-1, 1, 200, dtype=D)
    y = 2.0 * x + 0.5 + 0.05 * torch.randn(200, generator=g, dtype=D)
    y[::10] += 20.0  # 10 % gross outliers, all on one side

    def residuals(thetas, _z):
        return ((y - thetas[:, :1] * x - thetas[:, 1:]) / 0.05).unsqueeze(1)

    weight = torch.ones(1, 200, dtype=D)
    z = torch.zeros(1, 0, dtype=D)
    plain = levenberg_marquardt(residuals, torch.zeros(2, dtype=D), z, weight, loss="linear")
    robust = levenberg_marquardt(residuals, plain.theta, z, weight, loss="cauchy")
    assert abs(float(plain.theta[1]) - 0.5) > 1.0  # least squares follows the outliers
    torch.testing.assert_close(robust.theta, torch.tensor([2.0, 0.5], dtype=D), atol=0.03, rtol=0)


def test_robust_losses_match_their_definitions():
    s = torch.tensor([0.0, 1.0, 100.0], dtype=D)
    rho, drho = robust_loss(s, "cauchy")
    c2 = 2.385**2
    torch.testing.assert_close(rho, c2 * torch.log1p(s / c2))
    torch.testing.assert_close(drho, 1 / (1 + s / c2))
    rho, drho = robust_loss(s, "soft_l1")
    torch.testing.assert_close(rho, 2 * (torch.sqrt(1 + s) - 1))
    with pytest.raises(ValueError, match="loss"):
        robust_loss(s, "huber")


def test_finite_difference_jacobian_matches_autograd():
    x = torch.linspace(0, 2, 30, dtype=D)

    def residuals(thetas, zs):  # (S, P), (S, W=2, q=1)
        core = torch.sin(thetas[:, :1] * x) * thetas[:, 1:2]  # (S, 30)
        return torch.stack([core + zs[:, 0, :1] ** 2, core - zs[:, 1, :1]], dim=1)

    theta = torch.tensor([1.3, 0.7], dtype=D)
    z = torch.tensor([[0.4], [-0.2]], dtype=D)
    r, Jg, Jl = _jacobian(residuals, theta, z)
    jacobian = torch.autograd.functional.jacobian
    exact_g = jacobian(lambda t: residuals(t.unsqueeze(0), z.unsqueeze(0))[0], theta)
    exact_l = jacobian(lambda zz: residuals(theta.unsqueeze(0), zz.unsqueeze(0))[0], z)
    torch.testing.assert_close(Jg, exact_g, atol=1e-6, rtol=1e-6)
    # each window sees only its own local parameters: the diagonal blocks
    torch.testing.assert_close(Jl[0, :, 0], exact_l[0, :, 0, 0], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(Jl[1, :, 0], exact_l[1, :, 1, 0], atol=1e-6, rtol=1e-6)


class _Affine(nn.Module):
    def __init__(self):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(2.0, dtype=D))
        self.B = nn.Parameter(torch.tensor([[1.0, 0.5], [0.0, -1.0]], dtype=D))
        self.held = nn.Parameter(torch.tensor(3.0, dtype=D), requires_grad=False)

    def forward(self, x, u):
        return self.a * x @ self.B.T + self.held * u


class _NotBatchable(_Affine):
    def forward(self, x, u):
        if float(self.a.item()) > 0:  # data-dependent Python control flow: vmap refuses it
            return self.a * x + u
        return x


def test_free_parameters_round_trip_and_batched_calls():
    m = _Affine()
    fp = FreeParameters({"f": m})
    assert fp.size == 5 and fp.names == ["f.a", "f.B[0, 0]", "f.B[0, 1]", "f.B[1, 0]", "f.B[1, 1]"]
    v = fp.vector()
    thetas = torch.stack([v, v + 1.0, 2.0 * v])
    x = torch.randn(7, 2, dtype=D)
    u = torch.randn(7, 1, dtype=D)
    out = fp.map(lambda forward, xx, uu: forward("f", xx, uu), thetas, x, u)
    for s in range(3):
        fp.assign(thetas[s])
        with torch.no_grad():
            torch.testing.assert_close(out[s], m(x, u))
    fp.assign(v)
    torch.testing.assert_close(fp.vector(), v)
    assert m.held.item() == 3.0


def test_free_parameters_fall_back_to_one_call_per_vector():
    m = _NotBatchable()
    fp = FreeParameters({"f": m})
    thetas = fp.vector().expand(2, -1).clone()
    thetas[1, 0] = -1.0
    x, u = torch.ones(3, 2, dtype=D), torch.ones(3, 2, dtype=D)
    out = fp.map(lambda forward, xx, uu: forward("f", xx, uu), thetas, x, u)
    torch.testing.assert_close(out[0], 2.0 * x + u)
    torch.testing.assert_close(out[1], x)


@pytest.mark.parametrize("shared", [False, True])
def test_free_parameters_bind_f_and_g_for_a_whole_simulation(shared):
    """A simulation through ``forward("f")`` and ``forward("g")`` at each vector equals the modules
    run at that vector, whether the modules share a parameter (bound per call) or not (bound once)."""
    f, g = _Affine(), _Affine()
    if shared:
        g.a = f.a
    fp = FreeParameters({"f": f, "g": g})
    assert (fp._bound is None) == shared
    v = fp.vector()
    thetas = torch.stack([v, v + 0.5])
    x0, u = torch.randn(2, dtype=D), 0.1 * torch.randn(6, 1, dtype=D)

    def simulate(forward, x, uu):
        ys = []
        for k in range(uu.shape[0]):
            ys.append(forward("g", x, uu[k]))
            x = forward("f", x, uu[k])
        return torch.stack(ys)

    out = fp.map(simulate, thetas, x0, u)
    for s in range(2):
        fp.assign(thetas[s])
        with torch.no_grad():
            torch.testing.assert_close(out[s], simulate(lambda label, *a: {"f": f, "g": g}[label](*a), x0, u))


def test_continuity_links_give_the_dense_least_squares_solution():
    """Linear windows whose end states are linked to the next window's first state: the block
    tridiagonal elimination gives the dense least-squares solution of all rows, link rows included
    (and windows of different records, not linked, stay independent)."""
    from torch_nssm.estimation.least_squares import Links

    g = torch.Generator().manual_seed(5)
    W, m, P, q = 7, 12, 2, 2
    A = torch.randn(W, m, P, generator=g, dtype=D)
    B = torch.randn(W, m, q, generator=g, dtype=D)
    F = torch.randn(W, q, P, generator=g, dtype=D)
    G = torch.randn(W, q, q, generator=g, dtype=D)
    y = torch.randn(W, m, generator=g, dtype=D)
    scale = torch.tensor([0.5, 2.0], dtype=D)
    linked = torch.tensor([True, True, False, True, True, True], dtype=torch.bool)  # two records

    def residuals(thetas, zs):
        r = y - torch.einsum("wmp,sp->swm", A, thetas) - torch.einsum("wmq,swq->swm", B, zs)
        ends = torch.einsum("wqp,sp->swq", F, thetas) + torch.einsum("wqk,swk->swq", G, zs)
        return r, ends

    rows, rhs = [], []
    for w in range(W):
        M = torch.zeros(m, P + W * q, dtype=D)
        M[:, :P] = A[w]
        M[:, P + w * q : P + (w + 1) * q] = B[w]
        rows.append(M)
        rhs.append(y[w])
    for w in range(W - 1):
        if linked[w]:
            M = torch.zeros(q, P + W * q, dtype=D)
            M[:, :P] = F[w]
            M[:, P + w * q : P + (w + 1) * q] = G[w]
            M[:, P + (w + 1) * q : P + (w + 2) * q] = -torch.eye(q, dtype=D)
            rows.append(M / scale.view(-1, 1))
            rhs.append(torch.zeros(q, dtype=D))
    # minimise |y - M_out x|^2 + |M_link x|^2: one dense least-squares problem
    exact = torch.linalg.lstsq(torch.cat(rows), torch.cat(rhs).reshape(-1, 1)).solution.flatten()
    weight = torch.ones(W, m, dtype=D)
    res = levenberg_marquardt(
        residuals, torch.zeros(P, dtype=D), torch.zeros(W, q, dtype=D), weight,
        links=Links(linked, scale), ftol=1e-15, max_iter=100,
    )
    torch.testing.assert_close(res.theta, exact[:P], atol=1e-7, rtol=0)
    torch.testing.assert_close(res.local, exact[P:].reshape(W, q), atol=1e-7, rtol=0)


@pytest.mark.parametrize("damping", [1e-3, 1.0])
def test_speculative_jacobians_take_the_same_steps_in_fewer_passes(damping):
    """With ``speculative`` each trial point's residuals come with its Jacobian in one batch: the
    same iterates (a nonlinear, robust problem with windows and links, started near and far), and
    fewer calls of ``residuals`` (the sequential passes of a simulation)."""
    from torch_nssm.estimation.least_squares import Links

    g = torch.Generator().manual_seed(7)
    W, m = 5, 30
    t = torch.arange(m, dtype=D)
    rate_true, z_true = 0.15, 1.0 + torch.rand(W, 1, generator=g, dtype=D)
    y = z_true * torch.exp(-rate_true * t) + 0.01 * torch.randn(W, m, generator=g, dtype=D)
    y[:, ::9] += 3.0  # gross outliers

    def residuals(thetas, zs):
        calls.append(thetas.shape[0])
        fit = zs * torch.exp(-thetas[:, None, :1] * t)  # (S, W, m)
        ends = zs * torch.exp(-thetas[:, None, :1] * m)
        return (y - fit) / 0.01, ends

    links = Links(torch.zeros(W - 1, dtype=torch.bool), torch.ones(1, dtype=D))
    runs = {}
    for speculative in (False, True):
        calls = []
        runs[speculative] = levenberg_marquardt(
            residuals, torch.tensor([0.5], dtype=D), torch.ones(W, 1, dtype=D), torch.ones(W, m, dtype=D),
            loss="cauchy", links=links, damping=damping, ftol=1e-12, speculative=speculative,
        ), len(calls)
    (plain, plain_calls), (fast, fast_calls) = runs[False], runs[True]
    assert plain.status == fast.status == "converged" and plain.n_iter == fast.n_iter
    torch.testing.assert_close(fast.theta, plain.theta, atol=1e-10, rtol=0)
    torch.testing.assert_close(fast.local, plain.local, atol=1e-10, rtol=0)
    assert abs(float(fast.theta[0]) - rate_true) < 0.01
    assert fast_calls < plain_calls
