"""M-step: noise covariances, weighted regressions (closed form, LBFGS, Adam, rollback), DOF."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import (
    DTYPE,
    LinearF,
    LinearG,
    NonlinearF,
    generator,
    make_linear_system,
    make_model,
    nonlinear_model,
    simulate,
    simulate_t_outputs,
)
from reference import pairwise_smoother, simulate_linear
from scipy import optimize, special, stats
from torch import nn

from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.core.noise import GaussianNoise, masked_scale, solve_dof
from torch_nssm.core.parametric import LinearInParameters
from torch_nssm.estimation.estep import EStepOptions, EStepOutput, e_step, latent_scales
from torch_nssm.estimation.mstep import (
    initial_state_update,
    noise_statistics,
    observation_regression,
    process_noise_update,
    transition_regression,
)
from torch_nssm.estimation.solvers import (
    RegressionRows,
    SolverSettings,
    fit_weighted_regression,
    weighted_loss,
)
from torch_nssm.inference.ffbsm import ffbsm
from torch_nssm.inference.filtering import FilterOutput


class LinearFLip(LinearInParameters):
    """``x A^T + u B^T`` as a module linear in its parameters (closed-form M-step)."""

    def __init__(self, A, B):
        super().__init__()
        self.A = nn.Parameter(torch.as_tensor(np.asarray(A), dtype=DTYPE).clone())
        self.B = nn.Parameter(torch.as_tensor(np.asarray(B), dtype=DTYPE).clone())

    def features(self, x, u):
        d = self.A.shape[0]
        eye = torch.eye(d, dtype=x.dtype)
        phi_a = torch.einsum("dc,...e->...dce", eye, x).reshape(*x.shape[:-1], d, -1)
        phi_b = torch.einsum("dc,...e->...dce", eye, u).reshape(*u.shape[:-1], d, -1)
        Phi = torch.cat([phi_a, phi_b], -1)
        return Phi, torch.zeros(*x.shape[:-1], d, dtype=x.dtype)


def _params(module: nn.Module) -> np.ndarray:
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()]).numpy()


# --------------------------------------------------------------------------- E-step fixtures


@pytest.fixture(scope="module")
def nonlinear_estep():
    """E-step of the nonlinear 2-state model on 2 sequences of different lengths (FFBSm)."""
    rng = np.random.default_rng(31)
    model = nonlinear_model(4.0)
    us, ys = simulate(model, [40, 31], rng, outlier_rate=0.1)
    ys[1][[3, 7]] = math.nan
    ys[0][5, 1] = math.nan
    data = SequenceBatch.from_sequences(us, ys)
    est = e_step(model, data, EStepOptions(40), generator(4))
    return model, data, est


@pytest.fixture(scope="module")
def linear_estep():
    """E-step of the linear system with Student-t noise (dof 5), missing components."""
    sysm = make_linear_system()
    rng = np.random.default_rng(32)
    us, ys = [], []
    for n in (120, 90):
        u = rng.normal(size=(n, 1))
        _, y = simulate_linear(*sysm.matrices(), u, rng)
        y.reshape(-1)[rng.choice(2 * n, size=n // 5, replace=False)] = np.nan
        y[rng.choice(n, size=5, replace=False)] = np.nan
        us.append(torch.as_tensor(u))
        ys.append(torch.as_tensor(y))
    data = SequenceBatch.from_sequences(us, ys)
    model = sysm.model(5.0)
    est = e_step(model, data, EStepOptions(60), generator(6))
    return sysm, model, data, est


# --------------------------------------------------------------------------- process noise


@pytest.mark.parametrize("theta", ["e-step", "perturbed"])
def test_process_noise_update_equals_pairwise_formula(nonlinear_estep, theta):
    """Rw = 1/(N-1) sum_k sum_ij W^{ij} (x^j - f^i)(x^j - f^i)^T, at any theta_f (docs/method.md §5, §7)."""
    model, data, est = nonlinear_estep
    f = model.f if theta == "e-step" else NonlinearF(a=0.6, b=1.3, c=-0.2)
    filt = est.filter
    ref = pairwise_smoother(
        model.f, model.Rw, data.u, data.lengths.tolist(), filt.particles, filt.log_weights
    )
    direct = np.zeros((2, 2))
    for b, (_, pairs) in enumerate(ref):
        for k, P in enumerate(pairs):
            L = P.shape[0]
            with torch.no_grad():
                fx = f(filt.particles[k, b], data.u[k, b].expand(L, -1)).numpy()
            d = filt.particles[k + 1, b].numpy()[None] - fx[:, None]
            direct += np.einsum("ij,ijp,ijq->pq", P, d, d)
    direct /= sum(n - 1 for n in data.lengths.tolist())
    Rw = process_noise_update([f], transition_regression(model.Rw, data, est), est, data)
    np.testing.assert_allclose(Rw.numpy(), direct, rtol=1e-7)
    # dropping the theta-free bracket would underestimate Rw (the bug docs/method.md §7 warns about)
    assert np.all(
        np.linalg.eigvalsh(
            direct
            - (
                Rw.numpy()
                - est.smoother.residual_scatter.sum(0).numpy() / sum(n - 1 for n in data.lengths.tolist())
            )
        )
        > 0
    )


def test_transition_rows(nonlinear_estep):
    model, data, est = nonlinear_estep
    rows = transition_regression(model.Rw, data, est).rows(slice(None))
    np.testing.assert_allclose(rows.precision.numpy(), np.linalg.inv(model.Rw.numpy()), rtol=1e-12)
    # total weight: one per transition inside the sequences
    assert rows.weight.sum().item() == pytest.approx(sum(n - 1 for n in data.lengths.tolist()), rel=1e-9)
    assert rows.x.shape[0] == rows.target.shape[0] == rows.u.shape[0] == rows.weight.shape[0]


# --------------------------------------------------------------------------- regressions


def _gradient_norm(module: nn.Module, rows: RegressionRows) -> float:
    module.zero_grad()
    loss = weighted_loss(module, rows)
    loss.backward()
    g = torch.cat([p.grad.reshape(-1) for p in module.parameters()])
    module.zero_grad()
    return float(g.abs().max())


def _normal_equations(rows: RegressionRows, nx: int, nu: int, d: int) -> np.ndarray:
    """Independent numpy minimiser of sum_n w_n r_n^T P_n r_n for out = x A^T + u B^T."""
    x, u = rows.x.numpy(), rows.u.numpy()
    t = np.nan_to_num(rows.target.numpy())
    w = rows.weight.numpy()
    P = np.broadcast_to(rows.precision.numpy(), (x.shape[0], d, d))
    n = x.shape[0]
    Phi = np.zeros((n, d, d * nx + d * nu))
    for i in range(d):
        Phi[:, i, i * nx : (i + 1) * nx] = x
        Phi[:, i, d * nx + i * nu : d * nx + (i + 1) * nu] = u
    G = np.einsum("n,ndf,nde,neg->fg", w, Phi, P, Phi)
    h = np.einsum("n,ndf,nde,ne->f", w, Phi, P, t)
    return np.linalg.solve(G, h)


@pytest.mark.parametrize("which", ["f", "g"])
def test_closed_form_and_lbfgs_reach_the_same_minimiser(linear_estep, which):
    sysm, model, data, est = linear_estep
    if which == "f":
        rows = transition_regression(model.Rw, data, est).rows(slice(None))
        start = (sysm.A + 0.3, sysm.B - 0.5)
    else:
        rows = observation_regression(data, est).rows(slice(None))
        missing = torch.diagonal(rows.precision, dim1=-2, dim2=-1) == 0
        assert rows.precision.dim() == 3 and missing.any()  # per-row metrics
        start = (sysm.C - 0.4, sysm.D + 0.5)
    closed = LinearFLip(*start)
    plain = LinearF(*start) if which == "f" else LinearG(*start)
    loss_closed = fit_weighted_regression(closed, rows).after
    loss_lbfgs = fit_weighted_regression(plain, rows, "lbfgs", SolverSettings(max_iter=200)).after
    want = _normal_equations(rows, 2, 1, 2)
    np.testing.assert_allclose(_params(closed), want, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(_params(plain), want, rtol=1e-5, atol=1e-6)
    assert loss_lbfgs == pytest.approx(loss_closed, rel=1e-8)
    with torch.no_grad():
        assert float(weighted_loss(closed, rows)) == pytest.approx(loss_closed, rel=1e-12)
    assert _gradient_norm(closed, rows) < 1e-8
    # and the minimiser is near the truth (the E-step ran at the true parameters)
    truth = np.concatenate([M.reshape(-1) for M in ((sysm.A, sysm.B) if which == "f" else (sysm.C, sysm.D))])
    assert np.abs(want - truth).max() < 0.25


def test_weighted_loss_formula():
    rng = np.random.default_rng(0)
    n = 30
    x = torch.as_tensor(rng.normal(size=(n, 2)))
    u = torch.as_tensor(rng.normal(size=(n, 1)))
    target = torch.as_tensor(rng.normal(size=(n, 2)))
    target[3, 1] = math.nan
    w = torch.as_tensor(rng.random(n))
    M = rng.normal(size=(n, 2, 2))
    P = torch.as_tensor(M @ M.transpose(0, 2, 1) + np.eye(2))
    P[3, 1, :] = 0.0
    P[3, :, 1] = 0.0
    rows = RegressionRows(x, u, target, w, P)
    g = LinearG(np.array([[1.0, 0.5], [0.2, -1.0]]), np.array([[0.3], [0.0]]))
    with torch.no_grad():
        r = np.nan_to_num(target.numpy() - g(x, u).numpy())
    want = np.einsum("n,ni,nij,nj->", w.numpy(), r, P.numpy(), r) / w.numpy().sum()
    with torch.no_grad():
        assert float(weighted_loss(g, rows)) == pytest.approx(want, rel=1e-12)


def test_adam_decreases_the_loss(linear_estep):
    sysm, model, data, est = linear_estep
    rows = transition_regression(model.Rw, data, est).rows(slice(None))
    f = LinearF(sysm.A + 0.3, sysm.B - 0.5)
    with torch.no_grad():
        before = float(weighted_loss(f, rows))
    after = fit_weighted_regression(f, rows, "adam", SolverSettings(max_iter=30, learning_rate=0.02)).after
    assert after < 0.8 * before
    with torch.no_grad():
        assert float(weighted_loss(f, rows)) == pytest.approx(after, rel=1e-12)
    assert all(p.grad is None for p in f.parameters())
    with pytest.raises(ValueError, match="optimizer"):
        fit_weighted_regression(f, rows, optimizer="sgd")


class Fragile(nn.Module):
    """``out = a x``; the forward pass returns NaN once ``a`` exceeds 0.5 (a model that breaks)."""

    def __init__(self, a: float):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(a, dtype=DTYPE))

    def forward(self, x, u):
        out = self.a * x
        return torch.where(self.a > 0.5, torch.full_like(out, math.nan), out)


def _scalar_rows(slope: float = 1.0, n: int = 200) -> RegressionRows:
    rng = np.random.default_rng(2)
    x = torch.as_tensor(rng.normal(size=(n, 1)))
    return RegressionRows(
        x=x,
        u=torch.zeros(n, 1, dtype=DTYPE),
        target=slope * x + 0.1 * torch.as_tensor(rng.normal(size=(n, 1))),
        weight=torch.ones(n, dtype=DTYPE),
        precision=torch.eye(1, dtype=DTYPE),
    )


def test_nan_step_is_rolled_back_adam():
    rows = _scalar_rows(1.0)  # the minimiser a = 1 lies where the module returns NaN
    # at the edge every step goes into NaN: the update is rejected and a stays
    m = Fragile(0.5)
    with torch.no_grad():
        before = float(weighted_loss(m, rows))
    report = fit_weighted_regression(m, rows, "adam", SolverSettings(max_iter=5, learning_rate=0.3))
    assert m.a.item() == 0.5
    assert report.after == before and report.rejected
    # inside, Adam backs off from the NaN step (0.4 + 0.3) with smaller steps and improves within
    # a <= 0.5 (as LBFGS does), never leaving a NaN model
    m = Fragile(0.4)
    with torch.no_grad():
        before = float(weighted_loss(m, rows))
    report = fit_weighted_regression(m, rows, "adam", SolverSettings(max_iter=5, learning_rate=0.3))
    assert 0.4 < m.a.item() <= 0.5 and not report.rejected
    assert math.isfinite(report.after) and report.after < before


def test_nan_step_is_rolled_back_lbfgs():
    rows = _scalar_rows(1.0)
    m = Fragile(0.4)
    with torch.no_grad():
        before = float(weighted_loss(m, rows))
    out = fit_weighted_regression(m, rows, "lbfgs", SolverSettings(max_iter=20)).after
    # LBFGS may improve inside a <= 0.5 but must never leave a NaN model behind
    assert math.isfinite(out) and out <= before
    assert m.a.item() <= 0.5
    with torch.no_grad():
        assert float(weighted_loss(m, rows)) == pytest.approx(out, rel=1e-12)


def test_worse_step_is_rolled_back():
    rows = _scalar_rows(1.0)
    m = LinearF(np.array([[0.95]]), np.array([[0.0]]))
    with torch.no_grad():
        before = float(weighted_loss(m, rows))
    state = {k: v.clone() for k, v in m.state_dict().items()}
    report = fit_weighted_regression(m, rows, "adam", SolverSettings(max_iter=1, learning_rate=10.0))
    assert report.after == before and report.rejected
    for k, v in m.state_dict().items():
        assert torch.equal(v, state[k])


def test_no_free_parameters_or_rows():
    rows = _scalar_rows(1.0)
    m = LinearF(np.array([[0.5]]), np.array([[0.0]]))
    for p in m.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        before = float(weighted_loss(m, rows))
    assert fit_weighted_regression(m, rows).after == pytest.approx(before)
    assert m.A.item() == 0.5
    empty = RegressionRows(rows.x[:0], rows.u[:0], rows.target[:0], rows.weight[:0], rows.precision)
    m.A.requires_grad_(True)
    assert fit_weighted_regression(m, empty).after == 0.0


# --------------------------------------------------------------------------- known-state E-steps


def _known_states(model: StateSpaceModel, data: SequenceBatch, x: torch.Tensor):
    """Filter/smoother outputs of one particle per step sitting on the known states ``x``."""
    T, B, nx = x.shape
    particles = x.unsqueeze(2)  # (T, B, 1, nx)
    zeros = torch.zeros(T, B, 1, dtype=DTYPE)
    scale = masked_scale(model.noise.per_sequence("Rv", B).unsqueeze(0), data.obs_mask)
    filt = FilterOutput(
        particles=particles,
        log_weights=zeros,
        log_likelihood=torch.zeros(B, dtype=DTYPE),
        ess=torch.ones(T, B, dtype=DTYPE),
        scale=scale,
        ancestors=torch.zeros(T, B, 1, dtype=torch.long),
    )
    smooth = ffbsm(model, data, filt)
    return filt, smooth


def test_dof_update_recovers_known_dof():
    """Pure Student-t noise with known R: iterating the DOF update reaches the t MLE of dof."""
    rng = np.random.default_rng(41)
    true_dof, T, B = 4.0, 1500, 2
    R = np.array([[0.5, 0.2], [0.2, 0.3]])
    x, y = simulate_t_outputs(R, true_dof, T, B, rng)
    y[rng.random((T, B)) < 0.05] = math.nan
    y.reshape(-1)[rng.choice(y.size, size=y.size // 10, replace=False)] = math.nan
    data = SequenceBatch(
        u=torch.zeros(T, B, 1, dtype=DTYPE), y=torch.as_tensor(y), lengths=torch.full((B,), T)
    )
    model = make_model(
        LinearF(np.eye(2), np.zeros((2, 1))), LinearG(np.eye(2), np.zeros((2, 1))), np.eye(2), R, 20.0,
        np.zeros(2), np.eye(2),
    )
    filt, smooth = _known_states(model, data, torch.as_tensor(x))
    noise = model.noise
    dof = noise.dof
    for _ in range(300):
        noise = noise.replace(dof=dof)
        e_lam, e_log = latent_scales(replace(model, noise=noise), data, filt)
        suff = noise_statistics(noise, [model.g], data, EStepOutput(filt, smooth, e_lam, e_log))
        new = noise.updated(suff, fit_Rv=False).dof
        if abs(float(new - dof)) < 1e-10:
            break
        dof = new
    # the EM fixed point is the maximum-likelihood dof of the residuals (R known)
    resid = (y - x).reshape(-1, 2)
    groups = []  # residuals grouped by their pattern of observed components
    for pattern in ([True, True], [True, False], [False, True]):
        m = np.array(pattern)
        sel = (~np.isnan(resid) == m).all(1)
        groups.append((resid[sel][:, m], m))

    def nll(log_nu):
        nu = math.exp(log_nu)
        return -sum(
            stats.multivariate_t(np.zeros(m.sum()), R[np.ix_(m, m)], df=nu).logpdf(r).sum() for r, m in groups
        )

    mle = math.exp(
        optimize.minimize_scalar(nll, bounds=(0.0, 4.0), method="bounded", options={"xatol": 1e-7}).x
    )
    assert float(dof) == pytest.approx(mle, rel=1e-6)
    assert abs(float(dof) - true_dof) < 0.8


def test_dof_update_gaussian_data_hits_upper_bound():
    rng = np.random.default_rng(42)
    T = 2000
    d2 = torch.as_tensor(rng.chisquare(1, size=T))  # Gaussian residuals, p = 1
    dof = torch.tensor(10.0, dtype=DTYPE)
    from torch_nssm.core.noise import latent_scale_expectations

    for _ in range(200):
        lam, log_lam = latent_scale_expectations(d2, torch.tensor(1.0, dtype=DTYPE), dof)
        dof = solve_dof((log_lam - lam).sum() / T, 0.1, 200.0)
    assert float(dof) > 30.0


def test_latent_scales_with_missing_components(linear_estep):
    """<lam> and <log lam> of every particle use the observed components only (docs/method.md §1)."""
    sysm, model, data, est = linear_estep
    T, B, L, _ = est.filter.particles.shape
    nu = float(model.noise.dof)
    with torch.no_grad():
        g = model.g(est.filter.particles, data.u.unsqueeze(2).expand(T, B, L, 1)).numpy()
    r = data.y.numpy()[:, :, None, :] - g  # (T, B, L, p)
    obs = ~np.isnan(data.y.numpy())  # (T, B, p)
    R = model.Rv.numpy()
    n_partial = 0
    for t in range(T):
        for b in range(B):
            m = obs[t, b]
            if not m.any():
                continue
            n_partial += int(not m.all())
            ro = r[t, b][:, m]
            d2 = np.einsum("li,ij,lj->l", ro, np.linalg.inv(R[np.ix_(m, m)]), ro)
            p = m.sum()
            np.testing.assert_allclose(est.e_lam[t, b].numpy(), (nu + p) / (nu + d2), rtol=1e-10)
            np.testing.assert_allclose(
                est.e_log_lam[t, b].numpy(),
                special.digamma((nu + p) / 2) - np.log((nu + d2) / 2),
                rtol=1e-10,
                atol=1e-12,
            )
    assert n_partial > 20


def test_measurement_noise_update_with_missing_components(linear_estep):
    """Rv = 1/N_obs sum_k sum_l [W <lam> rhat rhat^T + W (R_mm - R_mo R_oo^-1 R_om)], with the
    missing part of each residual completed by its conditional mean under the old R."""
    sysm, model, data, est = linear_estep
    stats = noise_statistics(model.noise, [model.g], data, est)
    Rv = model.noise.updated(stats, fit_Rv=True, fit_shape=False).Rv.numpy()
    T, B, L, _ = est.filter.particles.shape
    with torch.no_grad():
        g = model.g(est.filter.particles, data.u.unsqueeze(2).expand(T, B, L, 1)).numpy()
    R = model.Rv.numpy()
    r = data.y.numpy()[:, :, None, :] - g  # (T, B, L, p), NaN where missing
    W = np.exp(est.smoother.log_weights.numpy())
    lam = est.e_lam.numpy()
    num = np.zeros((2, 2))
    n_obs = 0
    n_partial = 0
    for t in range(T):
        for b in range(B):
            o = ~np.isnan(data.y.numpy()[t, b])
            if not o.any():
                continue
            n_obs += 1
            m = ~o
            n_partial += m.any()
            for l in range(L):
                rr = np.zeros(2)
                rr[o] = r[t, b, l, o]
                C = np.zeros((2, 2))
                if m.any():
                    Roo_inv = np.linalg.inv(R[np.ix_(o, o)])
                    rr[m] = R[np.ix_(m, o)] @ Roo_inv @ r[t, b, l, o]
                    C[np.ix_(m, m)] = R[np.ix_(m, m)] - R[np.ix_(m, o)] @ Roo_inv @ R[np.ix_(o, m)]
                num += W[t, b, l] * (lam[t, b, l] * np.outer(rr, rr) + C)
    np.testing.assert_allclose(Rv, num / n_obs, rtol=1e-7)
    assert n_partial > 0  # some samples really are partly missing


def test_measurement_noise_update_recovers_R_with_known_states():
    rng = np.random.default_rng(43)
    T, B = 3000, 1
    R = np.array([[0.5, 0.2], [0.2, 0.3]])
    x, y = simulate_t_outputs(R, math.inf, T, B, rng)
    y.reshape(-1)[rng.choice(y.size, size=y.size // 4, replace=False)] = np.nan
    data = SequenceBatch(u=torch.zeros(T, B, 1, dtype=DTYPE), y=torch.as_tensor(y), lengths=torch.tensor([T]))
    model = make_model(
        LinearF(np.eye(2), np.zeros((2, 1))), LinearG(np.eye(2), np.zeros((2, 1))), np.eye(2), np.eye(2),
        math.inf, np.zeros(2), np.eye(2),
    )
    for _ in range(50):  # EM for incomplete data: iterate the update to its fixed point
        filt, smooth = _known_states(model, data, torch.as_tensor(x))
        e_lam, e_log = latent_scales(model, data, filt)
        assert torch.all(e_lam == 1.0)
        stats = noise_statistics(model.noise, [model.g], data, EStepOutput(filt, smooth, e_lam, e_log))
        Rv = model.noise.updated(stats, fit_Rv=True, fit_shape=False).Rv
        model = replace(model, noise=GaussianNoise(Rv))
    np.testing.assert_allclose(Rv.numpy(), R, atol=0.04)


def test_measurement_noise_update_is_positive_definite():
    """Component 1 alone on 100 samples, component 2 alone on 100, both on 4 (residuals 3, 3)."""
    T = 204
    y = np.full((T, 1, 2), np.nan)
    y[:100, 0, 0] = np.where(np.arange(100) % 2, 1.0, -1.0)
    y[100:200, 0, 1] = np.where(np.arange(100) % 2, 1.0, -1.0)
    y[200:, 0, :] = 3.0
    data = SequenceBatch(u=torch.zeros(T, 1, 1, dtype=DTYPE), y=torch.as_tensor(y), lengths=torch.tensor([T]))
    model = make_model(
        LinearF(np.eye(2), np.zeros((2, 1))), LinearG(np.eye(2), np.zeros((2, 1))), np.eye(2), np.eye(2),
        math.inf, np.zeros(2), np.eye(2),
    )
    filt, smooth = _known_states(model, data, torch.zeros(T, 1, 2, dtype=DTYPE))  # residuals = y
    e_lam, e_log = latent_scales(model, data, filt)
    stats = noise_statistics(model.noise, [model.g], data, EStepOutput(filt, smooth, e_lam, e_log))
    Rv = model.noise.updated(stats, fit_Rv=True, fit_shape=False).Rv
    assert torch.linalg.eigvalsh(Rv).min() > 0  # pairwise deletion gave eigenvalues (-7.7, 10.3)


def test_observation_rows_when_particles_equal_outputs():
    sysm = make_linear_system()
    rng = np.random.default_rng(0)
    u = rng.normal(size=(20, 1))
    _, y = simulate_linear(*sysm.matrices(), u, rng)
    data = SequenceBatch.from_sequences([torch.as_tensor(u)], [torch.as_tensor(y)])
    model = sysm.model(5.0)
    est = e_step(model, data, EStepOptions(2), generator(0))  # L = 2 = p
    rows = observation_regression(data, est).rows(slice(None))
    assert rows.target.shape == (rows.x.shape[0], 2)
    assert rows.weight.shape == (rows.x.shape[0],)
    assert rows.precision.shape in ((2, 2), (rows.x.shape[0], 2, 2))


def test_initial_state_update(nonlinear_estep):
    model, data, est = nonlinear_estep
    floor = 0.01 * torch.eye(2, dtype=DTYPE)
    mean, cov = initial_state_update(est, floor)
    w = np.exp(est.smoother.log_weights[0].numpy())  # (B, L)
    x = est.filter.particles[0].numpy()  # (B, L, nx)
    means = np.einsum("bl,blp->bp", w, x)
    want_mean = means.mean(0)
    d = x - want_mean
    want_cov = np.einsum("bl,blp,blq->pq", w, d, d) / x.shape[0] + floor.numpy()
    np.testing.assert_allclose(mean.numpy(), want_mean, rtol=1e-10)
    np.testing.assert_allclose(cov.numpy(), want_cov, rtol=1e-10)


def test_initial_state_update_about_a_held_mean(nonlinear_estep):
    """A simulation model's first state is held: the covariance is the second moment about it."""
    model, data, est = nonlinear_estep
    floor = 0.01 * torch.eye(2, dtype=DTYPE)
    held = torch.tensor([0.3, -0.2], dtype=DTYPE)
    mean, cov = initial_state_update(est, floor, mean=held)
    w = np.exp(est.smoother.log_weights[0].numpy())  # (B, L)
    d = est.filter.particles[0].numpy() - held.numpy()
    want_cov = np.einsum("bl,blp,blq->pq", w, d, d) / d.shape[0] + floor.numpy()
    np.testing.assert_array_equal(mean.numpy(), held.numpy())
    np.testing.assert_allclose(cov.numpy(), want_cov, rtol=1e-10)
    free = initial_state_update(est, floor)[1]
    # wider than about the smoothed mean, by the held mean's offset
    assert np.all(np.linalg.eigvalsh(cov.numpy() - free.numpy()) > -1e-12)


def _observed_precision(R: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-row inverse of R on the observed block of each target row, zero elsewhere."""
    o = (~torch.isnan(target)).to(R.dtype)
    eye = torch.eye(R.shape[0], dtype=R.dtype)
    Rm = R * o[:, :, None] * o[:, None, :] + eye * (1 - o)[:, :, None]
    return torch.linalg.inv(Rm) * o[:, :, None] * o[:, None, :]


class _Affine(torch.nn.Module):
    """A plain module (no closed form): out = w * x + v * u."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(0.0, dtype=DTYPE))
        self.v = torch.nn.Parameter(torch.tensor(0.0, dtype=DTYPE))

    def forward(self, x, u):
        return self.w * x + self.v * u


def test_minibatch_adam_early_stopping_reaches_the_minimiser():
    rng = np.random.default_rng(5)
    n = 4000
    x = torch.as_tensor(rng.standard_normal((n, 1)))
    u = torch.as_tensor(rng.standard_normal((n, 1)))
    target = 0.7 * x - 0.4 * u + 0.05 * torch.as_tensor(rng.standard_normal((n, 1)))
    weight = torch.as_tensor(rng.uniform(0.1, 1.0, n))
    rows = RegressionRows(x, u, target, weight, torch.eye(1, dtype=DTYPE))
    results = []
    for _ in range(2):
        module = _Affine()
        settings = SolverSettings(
            max_iter=60, learning_rate=0.05, batch_size=256, generator=torch.Generator().manual_seed(0)
        )
        loss = fit_weighted_regression(module, rows, "adam", settings).after
        results.append((module.w.item(), module.v.item(), loss))
    assert results[0] == results[1]  # reproducible with a seeded generator
    w, v, loss = results[0]
    assert abs(w - 0.7) < 0.01 and abs(v + 0.4) < 0.01
    assert loss < 0.05**2 * 1.2


def _affine_rows(n: int, seed: int = 5) -> RegressionRows:
    rng = np.random.default_rng(seed)
    x = torch.as_tensor(rng.standard_normal((n, 1)))
    u = torch.as_tensor(rng.standard_normal((n, 1)))
    target = 0.7 * x - 0.4 * u + 0.05 * torch.as_tensor(rng.standard_normal((n, 1)))
    weight = torch.as_tensor(rng.uniform(0.1, 1.0, n))
    return RegressionRows(x, u, target, weight, torch.eye(1, dtype=DTYPE))


def _weighted_least_squares(rows: RegressionRows) -> np.ndarray:
    X = torch.cat([rows.x, rows.u], 1).numpy()
    w = np.sqrt(rows.weight.numpy())[:, None]
    return np.linalg.lstsq(X * w, rows.target.numpy() * w, rcond=None)[0][:, 0]


def test_adam_at_the_minimiser_takes_a_null_step_not_a_rejected_one():
    """At the exact minimiser every Adam step is worse: the solver halves its step size down to
    2^-14 of it and keeps the start (a stationary point), which the caller does not reject."""
    rows = _affine_rows(500)
    w, v = _weighted_least_squares(rows)
    module = _Affine()
    with torch.no_grad():
        module.w.fill_(float(w))
        module.v.fill_(float(v))
    report = fit_weighted_regression(module, rows, "adam", SolverSettings(max_iter=50, learning_rate=1e-2))
    # (numpy's minimiser and torch's loss may differ in the last bit: a step of 1e-6 can win by that)
    assert not report.rejected and report.after == pytest.approx(report.before, rel=1e-12)
    assert abs(module.w.item() - w) < 1e-5 and abs(module.v.item() - v) < 1e-5


def test_adam_near_the_minimiser_finds_its_step_size():
    """Slightly off the minimiser a step of 1e-2 is far too large; the backtracking finds the step
    size that improves (the first stage leaves networks there) and remembers it for the next call."""
    rows = _affine_rows(500)
    w, v = _weighted_least_squares(rows)
    module = _Affine()
    with torch.no_grad():
        module.w.fill_(float(w) + 1e-3)
        module.v.fill_(float(v) - 1e-3)
    settings = SolverSettings(max_iter=50, learning_rate=1e-2)
    report = fit_weighted_regression(module, rows, "adam", settings)
    assert not report.rejected and report.after < report.before
    remembered = settings.memory[("adam", id(module))]
    assert remembered < 1e-2 / 4  # the step size that made progress
    assert abs(module.w.item() - w) < 1e-3 and abs(module.v.item() - v) < 1e-3


def test_adam_draws_weighted_minibatches_for_many_rows():
    """Above FULL_BATCH_ROWS rows Adam steps on weighted draws of rows and judges on a weighted
    draw; the final iterate is checked against all rows, so the report is never a rejection."""
    from torch_nssm.estimation.regression import FULL_BATCH_ROWS

    rows = _affine_rows(FULL_BATCH_ROWS + 5000)
    w, v = _weighted_least_squares(rows)
    module = _Affine()
    settings = SolverSettings(max_iter=150, learning_rate=0.05, generator=torch.Generator().manual_seed(0))
    report = fit_weighted_regression(module, rows, "adam", settings)
    assert not report.rejected and report.after < 0.05 * report.before
    assert abs(module.w.item() - w) < 0.01 and abs(module.v.item() - v) < 0.01
