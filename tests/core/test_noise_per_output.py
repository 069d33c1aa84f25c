"""Independent Student-t noise per output (``StudentTPerOutputNoise``) against exact references:
scipy's univariate t, closed-form latent-scale moments, the per-component t MLE, and the sampler's
marginals and independence."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import DTYPE, LinearF, LinearG, generator
from scipy import integrate, optimize, special, stats

from torch_nssm import RobustNSSMEstimator
from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.core.noise import (
    NOISE_MODELS,
    StudentTNoise,
    StudentTPerOutputNoise,
    masked_scale,
    sample_student_t,
)
from torch_nssm.inference.ffbsm import ffbsm
from torch_nssm.inference.filtering import FilterOutput, particle_filter

VAR = np.array([0.5, 0.2, 1.5])
DOF = np.array([1.5, 4.0, 25.0])


def _noise(var=VAR, dof=DOF) -> StudentTPerOutputNoise:
    return StudentTPerOutputNoise(
        Rv=torch.diag(torch.as_tensor(var, dtype=DTYPE)), dof=torch.as_tensor(dof, dtype=DTYPE)
    )


def _scipy_logpdf(r: np.ndarray, var=VAR, dof=DOF) -> np.ndarray:
    """Sum over the observed (non-NaN) components of the univariate t log-densities."""
    per = stats.t.logpdf(r, df=dof, scale=np.sqrt(var))
    return np.where(np.isnan(r), 0.0, per).sum(-1)


def test_registered():
    assert NOISE_MODELS["student-t-per-output"] is StudentTPerOutputNoise
    assert StudentTPerOutputNoise.per_component


# --------------------------------------------------------------------------- log-density


def test_log_prob_is_sum_of_univariate_t():
    rng = np.random.default_rng(0)
    r = 2.0 * rng.standard_t(2, size=(200, 3))
    got = _noise().log_prob(torch.as_tensor(r)).numpy()
    np.testing.assert_allclose(got, _scipy_logpdf(r), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dof", [0.7, 3.0, 80.0])
def test_log_prob_p1_equals_joint_student_t(dof):
    rng = np.random.default_rng(1)
    r = torch.as_tensor(rng.standard_t(3, size=(50, 1)))
    Rv = torch.tensor([[0.3]], dtype=DTYPE)
    per = StudentTPerOutputNoise(Rv, torch.tensor([dof], dtype=DTYPE)).log_prob(r)
    joint = StudentTNoise(Rv, torch.tensor(dof, dtype=DTYPE)).log_prob(r)
    np.testing.assert_allclose(per.numpy(), joint.numpy(), rtol=1e-12, atol=1e-12)


def _random_mask(shape, rng) -> np.ndarray:
    mask = rng.random(shape) > 0.3
    mask[0] = True  # a fully observed step
    mask[1] = False  # a fully missing step
    return mask


def test_evaluator_const_plus_step_is_masked_log_density():
    """``const[k] + step(k, z)`` of each particle is the sum over the observed components of the
    univariate t log-densities; the statistics are the whitened squared residuals."""
    rng = np.random.default_rng(2)
    T, B, L, p = 12, 2, 5, 3
    dofs = np.stack([DOF, [0.8, 9.0, 2.0]])  # one dof vector per sequence: a batched model
    variances = np.stack([VAR, [2.0, 0.05, 0.4]])
    noise = StudentTPerOutputNoise(
        Rv=torch.diag_embed(torch.as_tensor(variances)), dof=torch.as_tensor(dofs)
    )
    mask = _random_mask((T, B, p), rng)
    scale = masked_scale(noise.per_sequence("Rv", B).unsqueeze(0), torch.as_tensor(mask))
    ev = noise.evaluator(scale, L)
    r = rng.standard_t(2, size=(T, B, L, p))
    r_masked = np.where(mask[:, :, None, :], r, np.nan)
    r0 = torch.as_tensor(np.where(mask[:, :, None, :], r, 0.0))
    zt = torch.einsum("tbij,tblj->tbli", scale.whitener(), r0)  # whitened residuals, 0 where missing
    for k in range(T):
        got = (ev.const[k].unsqueeze(-1) + ev.step(k, zt[k].clone())).numpy()
        for b in range(B):
            want = _scipy_logpdf(r_masked[k, b], variances[b], dofs[b])
            np.testing.assert_allclose(got[b], want, rtol=1e-11, atol=1e-11)
    z2 = np.where(mask[:, :, None, :], r**2 / variances[None, :, None, :], 0.0)
    np.testing.assert_allclose(ev.statistics.numpy(), z2, rtol=1e-12, atol=1e-14)


def test_particle_filter_log_likelihood_with_missing_components():
    """A (nearly) deterministic state: every particle sits on the known trajectory, so the filter's
    log-likelihood is the sum of the per-step masked log-densities."""
    rng = np.random.default_rng(3)
    T, p = 40, 3
    A, Bm = np.array([[0.9, 0.1], [-0.2, 0.7]]), np.array([[1.0], [0.3]])
    C, D = np.array([[1.0, 0.0], [0.5, -1.0], [0.2, 0.4]]), np.array([[0.0], [0.1], [0.0]])
    u = rng.normal(size=(T, 1))
    x = np.zeros((T, 2))
    x[0] = [0.5, -0.3]
    for k in range(T - 1):
        x[k + 1] = A @ x[k] + Bm @ u[k]
    g = x @ C.T + u @ D.T
    y = g + np.sqrt(VAR) * rng.standard_t(DOF, size=(T, p))
    mask = _random_mask((T, p), rng)
    y[~mask] = np.nan
    tiny = 1e-16 * np.eye(2)
    model = StateSpaceModel(
        LinearF(A, Bm), LinearG(C, D), torch.as_tensor(tiny), _noise(),
        torch.as_tensor(x[0]), torch.as_tensor(tiny),
    )
    data = SequenceBatch(
        u=torch.as_tensor(u).unsqueeze(1), y=torch.as_tensor(y).unsqueeze(1), lengths=torch.tensor([T])
    )
    filt = particle_filter(model, data, 16, generator=generator(0))
    want = _scipy_logpdf(y - g).sum()
    assert float(filt.log_likelihood[0]) == pytest.approx(want, abs=1e-6)
    # the statistics recorded by the filter are each particle's whitened squared residuals
    z2 = np.where(mask, (y - g) ** 2 / VAR, 0.0)
    want_z2 = np.broadcast_to(z2[:, None], (T, 16, p))
    np.testing.assert_allclose(filt.noise_statistics[:, 0].numpy(), want_z2, atol=1e-6)


# --------------------------------------------------------------------------- latent scales


def _posterior_moments_by_quadrature(z2: float, nu: float) -> tuple[float, float]:
    """E[lam], E[log lam] under p(lam | r) ∝ N(r; 0, s/lam) Gamma(lam; nu/2, rate nu/2), one
    component (integrated over ``t = log lam``)."""
    a, b = 0.5 * (1.0 + nu), 0.5 * (z2 + nu)
    t_star = math.log(a / b)
    shift = a * t_star - b * math.exp(t_star)

    def dens(t):
        return math.exp(a * t - b * math.exp(t) - shift)

    kw = dict(limit=400, epsabs=1e-13, epsrel=1e-10)
    lo, hi = t_star - 60.0 / min(a, 1.0), t_star + 6.0
    Z = integrate.quad(dens, lo, hi, **kw)[0]
    return (
        integrate.quad(lambda t: math.exp(t) * dens(t), lo, hi, **kw)[0] / Z,
        integrate.quad(lambda t: t * dens(t), lo, hi, **kw)[0] / Z,
    )


def test_latent_expectations_per_component():
    rng = np.random.default_rng(4)
    T, B, L, p = 6, 2, 4, 3
    dofs = np.stack([DOF, [0.6, 12.0, 3.0]])
    noise = StudentTPerOutputNoise(
        Rv=torch.diag_embed(torch.ones(B, p, dtype=DTYPE)), dof=torch.as_tensor(dofs)
    )
    z2 = rng.chisquare(1, size=(T, B, L, p)) * rng.choice([1.0, 50.0], size=(T, B, L, p))
    scale = masked_scale(noise.per_sequence("Rv", B).unsqueeze(0), torch.ones(T, B, p, dtype=torch.bool))
    sl = slice(2, 5)
    lam, log_lam = noise.latent_expectations(torch.as_tensor(z2), scale, sl)
    assert lam.shape == (3, B, L, p)
    nu = dofs[None, :, None, :]
    np.testing.assert_allclose(lam.numpy(), ((nu + 1) / (nu + z2))[sl], rtol=1e-12)
    np.testing.assert_allclose(
        log_lam.numpy(), (special.digamma((nu + 1) / 2) - np.log((nu + z2) / 2))[sl], rtol=1e-11, atol=1e-13
    )
    for b, j, v in [(0, 0, 0.0), (0, 1, 2.5), (1, 0, 40.0), (1, 1, 0.3), (1, 2, 9.0)]:
        m1, ml = _posterior_moments_by_quadrature(v, dofs[b, j])
        z = torch.zeros(1, B, 1, p, dtype=DTYPE)
        z[0, b, 0, j] = v
        e_lam, e_log = noise.latent_expectations(z, scale, slice(None))
        assert float(e_lam[0, b, 0, j]) == pytest.approx(m1, rel=1e-7)
        assert float(e_log[0, b, 0, j]) == pytest.approx(ml, rel=1e-6, abs=1e-8)


# --------------------------------------------------------------------------- the M-step update


def _t_mle(r: np.ndarray) -> tuple[float, float]:
    """Maximum-likelihood (variance, dof) of a zero-location univariate t by direct maximisation."""

    def nll(params):
        log_s2, log_nu = params
        return -stats.t.logpdf(r, df=math.exp(log_nu), scale=math.exp(0.5 * log_s2)).sum()

    x0 = [math.log(np.median(r**2)), math.log(4.0)]
    opts = dict(xatol=1e-10, fatol=1e-12, maxiter=4000)
    res = optimize.minimize(nll, x0, method="Nelder-Mead", options=opts)
    return math.exp(res.x[0]), math.exp(res.x[1])


def _em_fixed_point(noise, r, mask, n_iter=3000, tol=1e-12):
    """Iterate latent expectations -> statistics -> updated with the residuals ``r`` (T, 1, 1, p)
    of a single particle of weight 1 (known states)."""
    T, _, _, p = r.shape
    W = torch.ones(T, 1, 1, dtype=DTYPE)
    mask_t = torch.as_tensor(mask).unsqueeze(1)
    r = torch.where(mask_t.unsqueeze(2), r, torch.zeros_like(r))
    n_done = 0
    for _ in range(n_iter):
        n_done += 1
        scale = masked_scale(noise.Rv.unsqueeze(0), mask_t)
        z2 = (r.square() / torch.diagonal(noise.Rv)) * mask_t.unsqueeze(2)
        e_lam, e_log = noise.latent_expectations(z2, scale, slice(None))
        st = noise.statistics(r, W, e_lam, e_log, scale, slice(None))
        st = {k: v.sum(0) for k, v in st.items()}  # pooled over the one sequence
        new = noise.updated(st, fit_Rv=True)
        change = max(float((new.dof / noise.dof - 1).abs().max()), float((new.Rv - noise.Rv).abs().max()))
        noise = new
        if change < tol:
            break
    return noise, n_done


def test_updated_recovers_per_component_mle_with_missing_components():
    rng = np.random.default_rng(5)
    T, p = 1500, 3
    var, dof = np.array([0.5, 0.2, 1.5]), np.array([2.0, 5.0, 9.0])
    r = np.sqrt(var) * rng.standard_t(dof, size=(T, p))
    mask = rng.random((T, p)) > np.array([0.0, 0.2, 0.5])  # component 3 half missing
    noise = StudentTPerOutputNoise.initial(torch.eye(p, dtype=DTYPE), 5.0)
    noise, n_it = _em_fixed_point(noise, torch.as_tensor(r).view(T, 1, 1, p), mask)
    assert n_it < 3000
    got_var, got_dof = torch.diagonal(noise.Rv).numpy(), noise.dof.numpy()
    for j in range(p):
        rj = r[mask[:, j], j]
        mle_var, mle_dof = _t_mle(rj)
        assert got_var[j] == pytest.approx(mle_var, rel=1e-5)
        assert got_dof[j] == pytest.approx(mle_dof, rel=1e-4)
        df, _, sc = stats.t.fit(rj, floc=0)  # scipy's own fit agrees (looser: its optimiser)
        assert got_dof[j] == pytest.approx(df, rel=2e-2)
        assert got_var[j] == pytest.approx(sc**2, rel=2e-2)
    assert np.all(np.abs(np.log(got_dof / dof)) < 0.5)  # and near the truth


def test_engine_statistics_with_known_states_match_the_family():
    """Through the M-step's ``noise_statistics`` (one particle on the known states, missing
    components): the pooled statistics are the family's own formulas."""
    from conftest import make_model

    from torch_nssm.estimation.estep import EStepOutput, latent_scales
    from torch_nssm.estimation.mstep import noise_statistics

    rng = np.random.default_rng(6)
    T, B, p = 300, 2, 3
    x = rng.normal(size=(T, B, p))
    r = np.sqrt(VAR) * rng.standard_t(DOF, size=(T, B, p))
    y = x + r
    mask = rng.random((T, B, p)) > 0.25
    y[~mask] = np.nan
    base = make_model(LinearF(np.eye(p), np.zeros((p, 1))), LinearG(np.eye(p), np.zeros((p, 1))),
                      np.eye(p), np.eye(p), math.inf, np.zeros(p), np.eye(p))
    model = StateSpaceModel(base.f, base.g, base.Rw, _noise(), base.x0_mean, base.x0_cov)
    data = SequenceBatch(
        u=torch.zeros(T, B, 1, dtype=DTYPE), y=torch.as_tensor(y), lengths=torch.full((B,), T)
    )
    scale = masked_scale(model.noise.per_sequence("Rv", B).unsqueeze(0), data.obs_mask)
    zeros = torch.zeros(T, B, 1, dtype=DTYPE)
    filt = FilterOutput(torch.as_tensor(x).unsqueeze(2), zeros, torch.zeros(B, dtype=DTYPE),
                        torch.ones(T, B, dtype=DTYPE), scale, torch.zeros(T, B, 1, dtype=torch.long))
    smooth = ffbsm(model, data, filt)
    e_lam, e_log = latent_scales(model, data, filt)
    assert e_lam.shape == (T, B, 1, p)
    st = noise_statistics(model.noise, [model.g], data, EStepOutput(filt, smooth, e_lam, e_log))
    nu = DOF
    r0 = np.where(mask, r, 0.0)
    lam = (nu + 1) / (nu + r0**2 / VAR)
    elog = special.digamma((nu + 1) / 2) - np.log((nu + r0**2 / VAR) / 2)
    np.testing.assert_allclose(st["scatter"].numpy(), (mask * lam * r0**2).sum((0, 1)), rtol=1e-9)
    np.testing.assert_allclose(st["n_obs"].numpy(), mask.sum((0, 1)))
    np.testing.assert_allclose(st["dof_c"].numpy(), (mask * (elog - lam)).sum((0, 1)), rtol=1e-9)
    new = model.noise.updated(st, fit_Rv=True, fit_shape=False)
    assert torch.count_nonzero(new.Rv - torch.diag_embed(torch.diagonal(new.Rv))) == 0
    np.testing.assert_allclose(torch.diagonal(new.Rv).numpy(), st["scatter"].numpy() / mask.sum((0, 1)))


def test_updated_keeps_unobserved_component_and_flags():
    noise = _noise()
    st = {
        "scatter": torch.tensor([2.0, 0.0, 6.0], dtype=DTYPE),
        "n_obs": torch.tensor([4.0, 0.0, 3.0], dtype=DTYPE),
        "dof_c": torch.tensor([-5.0, 0.0, -3.3], dtype=DTYPE),
    }
    new = noise.updated(st, fit_Rv=True)
    np.testing.assert_allclose(torch.diagonal(new.Rv).numpy(), [0.5, VAR[1], 2.0])
    assert float(new.dof[1]) == DOF[1]  # never observed: unchanged
    same = noise.updated(st, fit_Rv=False, fit_shape=False)
    assert torch.equal(same.Rv, noise.Rv) and torch.equal(same.dof, noise.dof)


# --------------------------------------------------------------------------- sampling


def test_sample_marginals_reproducibility_and_independence():
    noise = _noise()
    n = 20000
    v = noise.sample((n,), generator=generator(7)).numpy()
    assert v.shape == (n, 3)
    for j in range(3):
        assert stats.kstest(v[:, j], stats.t(df=DOF[j], scale=math.sqrt(VAR[j])).cdf).pvalue > 1e-3
    again = noise.sample((n,), generator=generator(7)).numpy()
    np.testing.assert_array_equal(v, again)
    assert not np.array_equal(v, noise.sample((n,), generator=generator(8)).numpy())
    # independent latent scales: the magnitudes of the components are uncorrelated (a joint t with
    # the same diagonal scale couples them through its shared scale)
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        assert abs(stats.spearmanr(v[:, i], v[:, j]).statistic) < 0.03
        assert abs(stats.spearmanr(np.abs(v[:, i]), np.abs(v[:, j])).statistic) < 0.03
    joint = sample_student_t((n,), torch.linalg.cholesky(noise.Rv), 1.5, generator(7)).numpy()
    assert stats.spearmanr(np.abs(joint[:, 0]), np.abs(joint[:, 1])).statistic > 0.1


def test_sample_shape_with_leading_dims():
    v = _noise().sample((4, 5, 6), generator=generator(0))
    assert v.shape == (4, 5, 6, 3) and v.dtype == DTYPE


# --------------------------------------------------------------------------- construction


def test_initial():
    noise = StudentTPerOutputNoise.initial(torch.diag(torch.tensor([0.1, 0.3], dtype=DTYPE)), 7.0)
    assert noise.dof.shape == (2,) and torch.all(noise.dof == 7.0)
    assert bool(noise.is_valid())


def test_initial_refuses_non_diagonal_rv_and_infinite_dof():
    R = torch.tensor([[1.0, 0.2], [0.2, 1.0]], dtype=DTYPE)
    with pytest.raises(ValueError, match="Rv_init must be diagonal"):
        StudentTPerOutputNoise.initial(R, 5.0)
    for bad in (math.inf, 0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="dof_init must be positive and finite"):
            StudentTPerOutputNoise.initial(torch.eye(2, dtype=DTYPE), bad)


def test_estimator_refuses_non_diagonal_rv_init_at_fit():
    rng = np.random.default_rng(8)
    u, y = rng.normal(size=(20, 1)), rng.normal(size=(20, 2))
    kw = dict(x0_mean=np.zeros(2), noise="student-t-per-output", n_particles=10, n_iter=1)
    est = RobustNSSMEstimator(LinearF(np.eye(2), np.zeros((2, 1))), LinearG(np.eye(2), np.zeros((2, 1))),
                              Rv_init=[[1.0, 0.3], [0.3, 1.0]], **kw)
    with pytest.raises(ValueError, match="Rv_init must be diagonal"):
        est.fit(u, y)
    est = RobustNSSMEstimator(LinearF(np.eye(2), np.zeros((2, 1))), LinearG(np.eye(2), np.zeros((2, 1))),
                              dof_init=math.inf, **kw)
    with pytest.raises(ValueError, match="dof_init"):
        est.fit(u, y)
