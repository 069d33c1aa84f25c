"""Student-t noise: log-density, latent-scale posterior moments, DOF equation, sampler."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate, optimize, special, stats

from torch_nssm.core.noise import (
    dof_equation,
    latent_scale_expectations,
    masked_scale,
    sample_student_t,
    solve_dof,
    student_t_log_prob,
)

DTYPE = torch.float64


def _random_spd(p: int, rng: np.random.Generator) -> np.ndarray:
    M = rng.normal(size=(p, p))
    return M @ M.T + 0.3 * np.eye(p)


def _whiten(sc, resid: torch.Tensor) -> torch.Tensor:
    """Whitened residuals ``(..., L, p)`` under the masked scale (NaN where missing)."""
    r = torch.where(sc.mask.unsqueeze(-2), resid, torch.zeros_like(resid))
    return r @ sc.whitener().transpose(-1, -2)


def _engine_logpdf(y: np.ndarray, mu: np.ndarray, R: np.ndarray, dof: float) -> np.ndarray:
    """Log-density of rows ``y`` (NaN = missing): ``masked_scale`` + ``student_t_log_prob``."""
    yt = torch.as_tensor(y, dtype=DTYPE)
    mask = ~torch.isnan(yt)
    sc = masked_scale(torch.as_tensor(R, dtype=DTYPE), mask)  # (n, p, p) etc.
    resid = (yt - torch.as_tensor(mu, dtype=DTYPE)).unsqueeze(-2)  # (n, 1, p)
    z = _whiten(sc, resid).squeeze(-2)
    delta2 = (z * z).sum(-1)
    return student_t_log_prob(delta2, sc.logdet, sc.n_obs, torch.tensor(dof, dtype=DTYPE)).numpy()


@pytest.mark.parametrize("p", [1, 2, 3])
@pytest.mark.parametrize("dof", [0.5, 1.0, 4.0, 30.0])
def test_student_t_log_prob_matches_scipy(p, dof):
    rng = np.random.default_rng(10 * p + int(dof * 2))
    R = _random_spd(p, rng)
    mu = rng.normal(size=p)
    y = mu + 2.0 * rng.standard_t(3, size=(50, p))
    got = _engine_logpdf(y, mu, R, dof)
    want = stats.multivariate_t(loc=mu, shape=R, df=dof).logpdf(y)
    np.testing.assert_allclose(got, np.atleast_1d(want), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("p", [1, 2, 3])
def test_gaussian_log_prob_matches_scipy(p):
    rng = np.random.default_rng(p)
    R = _random_spd(p, rng)
    mu = rng.normal(size=p)
    y = mu + rng.normal(size=(40, p))
    got = _engine_logpdf(y, mu, R, math.inf)
    want = stats.multivariate_normal(mean=mu, cov=R).logpdf(y)
    np.testing.assert_allclose(got, np.atleast_1d(want), rtol=1e-10, atol=1e-10)


def test_mixed_dof_broadcast():
    """A tensor of DOFs with finite and infinite entries picks the right density per element."""
    rng = np.random.default_rng(3)
    R = _random_spd(2, rng)
    y = rng.normal(size=(2, 2))
    sc = masked_scale(torch.as_tensor(R), torch.ones(2, 2, dtype=torch.bool))
    z = _whiten(sc, torch.as_tensor(y).unsqueeze(-2)).squeeze(-2)
    delta2 = (z * z).sum(-1)
    got = student_t_log_prob(
        delta2, sc.logdet, sc.n_obs, torch.tensor([3.0, math.inf], dtype=DTYPE)
    )
    want = [
        stats.multivariate_t(loc=np.zeros(2), shape=R, df=3.0).logpdf(y[0]),
        stats.multivariate_normal(mean=np.zeros(2), cov=R).logpdf(y[1]),
    ]
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10)


@pytest.mark.parametrize("dof", [1.0, 5.0, math.inf])
def test_masked_density_is_marginal_of_observed_components(dof):
    rng = np.random.default_rng(7)
    p = 3
    R = _random_spd(p, rng)
    mu = rng.normal(size=p)
    patterns = [
        [True, True, True],
        [True, False, True],
        [False, True, False],
        [False, False, True],
        [False, False, False],
    ]
    rows = []
    for pat in patterns:
        yk = mu + rng.normal(size=p)
        yk[~np.array(pat)] = np.nan
        rows.append(yk)
    y = np.array(rows)
    got = _engine_logpdf(y, mu, R, dof)
    for i, pat in enumerate(patterns):
        obs = np.array(pat)
        if not obs.any():
            assert got[i] == 0.0
            continue
        sub_R = R[np.ix_(obs, obs)]
        if math.isinf(dof):
            want = stats.multivariate_normal(mean=mu[obs], cov=sub_R).logpdf(y[i, obs])
        else:
            want = stats.multivariate_t(loc=mu[obs], shape=sub_R, df=dof).logpdf(y[i, obs])
        np.testing.assert_allclose(got[i], want, rtol=1e-10, err_msg=f"pattern {pat}")


def test_masked_scale_fields():
    rng = np.random.default_rng(11)
    R = _random_spd(3, rng)
    mask = torch.tensor([[True, False, True], [False, False, False]])
    sc = masked_scale(torch.as_tensor(R), mask)
    obs = np.array([True, False, True])
    np.testing.assert_allclose(sc.logdet[0].item(), np.linalg.slogdet(R[np.ix_(obs, obs)])[1])
    assert sc.logdet[1].item() == pytest.approx(0.0, abs=1e-14)
    assert sc.n_obs.tolist() == [2.0, 0.0]
    # chol_inv^T chol_inv restricted to the observed block is the inverse of the observed block
    Pm = (sc.chol_inv[0].T @ sc.chol_inv[0]).numpy()
    np.testing.assert_allclose(Pm[np.ix_(obs, obs)], np.linalg.inv(R[np.ix_(obs, obs)]), rtol=1e-10)


def test_masked_scale_one_output_equals_cholesky():
    """One output: the square-root path gives LAPACK's Cholesky factor, inverse and log-determinant
    bit for bit (with missing samples and a batch of scales); a scale that is not positive still
    raises as ``torch.linalg.cholesky`` does."""
    gen = torch.Generator().manual_seed(4)
    R = 10.0 ** (4.0 * torch.rand(1, 7, 1, 1, dtype=DTYPE, generator=gen) - 3.0)
    mask = torch.rand(50, 7, 1, generator=gen) > 0.2
    sc = masked_scale(R, mask)
    m = mask.to(DTYPE)
    Rm = R * m.unsqueeze(-1) * m.unsqueeze(-2) + (1.0 - m).unsqueeze(-1)
    chol = torch.linalg.cholesky(Rm)
    eye = torch.ones(1, 1, dtype=DTYPE).expand_as(chol)
    assert torch.equal(sc.chol_inv, torch.linalg.solve_triangular(chol, eye, upper=False))
    assert torch.equal(sc.logdet, 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1))
    with pytest.raises(torch.linalg.LinAlgError):
        masked_scale(-R, mask)


# --------------------------------------------------------------------------- latent scale moments


def _gamma_posterior_moments_by_quadrature(delta2: float, p: int, nu: float) -> tuple[float, float]:
    """E[lam] and E[log lam] under p(lam | y) ∝ N(y; 0, R/lam) Gamma(lam; nu/2, rate nu/2).

    Integrated over ``t = log lam`` (smooth, no endpoint singularity): the unnormalised density of
    ``t`` is ``lam^{p/2} exp(-lam delta2/2) lam^{nu/2-1} exp(-nu lam/2) * lam``.
    """
    a = 0.5 * (p + nu)  # exponent of lam after the Jacobian
    b = 0.5 * (delta2 + nu)
    t_star = np.log(a / b)  # the mode in t
    shift = a * t_star - b * np.exp(t_star)

    def dens(t):
        return np.exp(a * t - b * np.exp(t) - shift)

    kw = dict(limit=400, epsabs=1e-13, epsrel=1e-10)
    lo, hi = t_star - 60.0 / min(a, 1.0), t_star + 6.0
    Z = integrate.quad(dens, lo, hi, **kw)[0]
    m1 = integrate.quad(lambda t: np.exp(t) * dens(t), lo, hi, **kw)[0]
    ml = integrate.quad(lambda t: t * dens(t), lo, hi, **kw)[0]
    return m1 / Z, ml / Z


@pytest.mark.parametrize("nu", [0.5, 1.0, 4.0, 30.0])
@pytest.mark.parametrize("p", [1, 2, 3])
def test_latent_scale_expectations_match_quadrature(nu, p):
    delta2 = np.array([0.0, 0.3, 2.0, 25.0])
    lam, log_lam = latent_scale_expectations(
        torch.as_tensor(delta2), torch.tensor(float(p), dtype=DTYPE), torch.tensor(nu, dtype=DTYPE)
    )
    for i, d2 in enumerate(delta2):
        m1, ml = _gamma_posterior_moments_by_quadrature(d2, p, nu)
        assert lam[i].item() == pytest.approx(m1, rel=1e-7)
        assert log_lam[i].item() == pytest.approx(ml, rel=1e-6, abs=1e-8)
        # and the closed forms of the Gamma((nu+p)/2, rate (nu+d2)/2) posterior
        a, b = 0.5 * (nu + p), 0.5 * (nu + d2)
        assert lam[i].item() == pytest.approx(stats.gamma(a, scale=1 / b).mean(), rel=1e-12)
        assert log_lam[i].item() == pytest.approx(
            special.digamma(a) - np.log(b), rel=1e-12, abs=1e-14
        )


def test_latent_scale_expectations_gaussian_and_broadcast():
    delta2 = torch.tensor([[0.5, 100.0], [3.0, 0.0]], dtype=DTYPE)
    dof = torch.tensor([[math.inf], [2.0]], dtype=DTYPE)
    lam, log_lam = latent_scale_expectations(delta2, torch.tensor(2.0, dtype=DTYPE), dof)
    assert torch.equal(lam[0], torch.ones(2, dtype=DTYPE))
    assert torch.equal(log_lam[0], torch.zeros(2, dtype=DTYPE))
    np.testing.assert_allclose(lam[1].numpy(), [4.0 / 5.0, 4.0 / 2.0])
    # an outlier gets a small weight
    lam_t, _ = latent_scale_expectations(torch.tensor([0.1, 1e4], dtype=DTYPE), 1.0, 3.0)
    assert lam_t[1] < 1e-3 < 1.0 < lam_t[0]


# --------------------------------------------------------------------------- DOF equation


@pytest.mark.parametrize("c", [-1.001, -1.05, -1.2, -1.5, -2.0, -3.0])
def test_solve_dof_matches_brentq(c):
    def h(nu):
        return 1.0 + np.log(nu / 2) - special.digamma(nu / 2) + c

    want = optimize.brentq(h, 1e-3, 1e6, xtol=1e-14, rtol=1e-14)
    got = solve_dof(torch.tensor(c, dtype=DTYPE), dof_min=1e-3, dof_max=1e6).item()
    assert got == pytest.approx(want, rel=1e-9)
    assert dof_equation(torch.tensor(got, dtype=DTYPE), torch.tensor(c, dtype=DTYPE)).abs() < 1e-9


def test_solve_dof_batched_and_clipped():
    c = torch.tensor([-0.5, -1.0 + 1e-9, -1.3, -50.0], dtype=DTYPE)
    got = solve_dof(c, dof_min=0.1, dof_max=1000.0)
    assert got.dtype == torch.float64 and got.shape == c.shape
    assert got[0].item() == pytest.approx(1000.0, rel=1e-9)  # c > -1: no root, h > 0 everywhere
    assert got[1].item() == pytest.approx(1000.0, rel=1e-9)  # root far beyond the bracket
    single = solve_dof(c[2], dof_min=0.1, dof_max=1000.0)
    assert got[2].item() == pytest.approx(single.item(), rel=1e-12)
    assert got[3].item() == pytest.approx(0.1, rel=1e-9)  # root below the bracket
    with pytest.raises(ValueError):
        solve_dof(c, dof_min=2.0, dof_max=1.0)


def test_solve_dof_float32_input():
    got = solve_dof(torch.tensor(-1.2, dtype=torch.float32))
    want = optimize.brentq(
        lambda nu: 1.0 + np.log(nu / 2) - special.digamma(nu / 2) - 1.2, 0.1, 1000
    )
    assert got.dtype == torch.float64
    assert got.item() == pytest.approx(want, rel=1e-6)


# --------------------------------------------------------------------------- sampler


@pytest.mark.parametrize("dof", [1.0, 3.5, math.inf])
def test_sample_student_t_marginals_ks(dof):
    R = np.array([[2.0, 0.6], [0.6, 0.5]])
    chol = torch.linalg.cholesky(torch.as_tensor(R))
    gen = torch.Generator().manual_seed(123)
    x = sample_student_t((20000,), chol, dof, generator=gen).numpy()
    assert x.shape == (20000, 2)
    for i in range(2):
        sd = math.sqrt(R[i, i])
        dist = stats.norm(scale=sd) if math.isinf(dof) else stats.t(df=dof, scale=sd)
        assert stats.kstest(x[:, i], dist.cdf).pvalue > 1e-3
    # a projection tests the joint scale matrix: a^T v ~ t(dof, scale sqrt(a^T R a))
    a = np.array([1.0, -2.0])
    sd = math.sqrt(a @ R @ a)
    dist = stats.norm(scale=sd) if math.isinf(dof) else stats.t(df=dof, scale=sd)
    assert stats.kstest(x @ a, dist.cdf).pvalue > 1e-3


def test_sample_student_t_mahalanobis_distribution():
    """delta2 / p of a p-variate t is F(p, nu): a check of the shared latent scale per draw."""
    R = np.array([[1.0, 0.3, 0.0], [0.3, 0.8, 0.2], [0.0, 0.2, 0.5]])
    chol = torch.linalg.cholesky(torch.as_tensor(R))
    gen = torch.Generator().manual_seed(5)
    x = sample_student_t((20000,), chol, 4.0, generator=gen).numpy()
    d2 = np.einsum("ni,ij,nj->n", x, np.linalg.inv(R), x)
    assert stats.kstest(d2 / 3, stats.f(3, 4.0).cdf).pvalue > 1e-3


def test_sample_student_t_reproducible_with_generator():
    chol = torch.eye(2, dtype=DTYPE)
    a = sample_student_t((100,), chol, 3.0, generator=torch.Generator().manual_seed(9))
    b = sample_student_t((100,), chol, 3.0, generator=torch.Generator().manual_seed(9))
    assert torch.equal(a, b)
    state = torch.random.get_rng_state()
    sample_student_t((10,), chol, 3.0, generator=torch.Generator().manual_seed(9))
    assert torch.equal(state, torch.random.get_rng_state())  # the global stream is untouched
