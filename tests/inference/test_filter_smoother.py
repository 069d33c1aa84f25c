"""Particle filter and FFBSm smoother against exact references.

* linear-Gaussian system: the Kalman filter / RTS smoother of ``reference.py`` (checked itself
  against the batch Gaussian formulas), with independent particle runs as the batch dimension;
* Student-t weights recomputed with scipy from the filter's own particles;
* the FFBSm recursion recomputed from docs/method.md §3 with the full ``L x L`` pairwise weights;
* padding of sequences of different lengths.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
from conftest import (
    DTYPE,
    N_STEPS,
    Paper41F,
    Paper41G,
    generator,
    make_linear_system,
    make_model,
    nonlinear_model,
    paper_model,
    replicate,
    simulate,
)
from reference import kalman_filter, pairwise_smoother, rts_smoother, simulate_linear
from scipy import stats
from scipy.special import logsumexp
from torch import nn

from torch_nssm._ops import squared_norm
from torch_nssm.core.model import SequenceBatch
from torch_nssm.core.noise import MaskedScale
from torch_nssm.inference.ffbsi import ffbsi
from torch_nssm.inference.ffbsm import _backward_kernels, ffbsm, smoothed_moments
from torch_nssm.inference.filtering import FilterOutput, NumericalError, particle_filter
from torch_nssm.inference.resampling import RESAMPLING_SCHEMES

# --------------------------------------------------------------------------- the reference itself


def _batch_gaussian(sysm, u, y):
    """Joint Gaussian of all states and outputs: exact log-likelihood and smoothed means."""
    A, B, C, D, Q, R, m0, P0 = sysm.matrices()
    N, nx = u.shape[0], A.shape[0]
    mean = np.empty((N, nx))
    mean[0] = m0
    for k in range(1, N):
        mean[k] = A @ mean[k - 1] + B @ u[k - 1]
    var = [P0]
    for _ in range(1, N):
        var.append(A @ var[-1] @ A.T + Q)
    Sx = np.zeros((N * nx, N * nx))
    for j in range(N):
        block = var[j]
        for k in range(j, N):
            Sx[k * nx : (k + 1) * nx, j * nx : (j + 1) * nx] = block
            Sx[j * nx : (j + 1) * nx, k * nx : (k + 1) * nx] = block.T
            block = A @ block
    Cb = np.kron(np.eye(N), C)
    my = Cb @ mean.reshape(-1) + (u @ D.T).reshape(-1)
    Syy = Cb @ Sx @ Cb.T + np.kron(np.eye(N), R)
    Sxy = Sx @ Cb.T
    yv = y.reshape(-1)
    obs = ~np.isnan(yv)
    ll = stats.multivariate_normal(my[obs], Syy[np.ix_(obs, obs)]).logpdf(yv[obs])
    gain = np.linalg.solve(Syy[np.ix_(obs, obs)], Sxy[:, obs].T).T
    xs = mean.reshape(-1) + gain @ (yv[obs] - my[obs])
    Ps = Sx - gain @ Sxy[:, obs].T
    covs = np.stack([Ps[k * nx : (k + 1) * nx, k * nx : (k + 1) * nx] for k in range(N)])
    return ll, xs.reshape(N, nx), covs


@pytest.mark.parametrize("missing", [False, True])
def test_reference_kalman_matches_batch_gaussian(missing):
    sysm = make_linear_system()
    rng = np.random.default_rng(4)
    u = rng.normal(size=(8, 1))
    _, y = simulate_linear(*sysm.matrices(), u, rng)
    if missing:
        y[2] = np.nan
        y[5, 0] = np.nan
        y[6, 1] = np.nan
    kf = kalman_filter(*sysm.matrices(), u, y)
    sm, sP = rts_smoother(sysm.A, kf)
    ll, xs, Ps = _batch_gaussian(sysm, u, y)
    assert kf.log_likelihood == pytest.approx(ll, rel=1e-10)
    np.testing.assert_allclose(sm, xs, atol=1e-10)
    np.testing.assert_allclose(sP, Ps, atol=1e-10)


# --------------------------------------------------------------------------- linear-Gaussian system

N_COPIES = 20  # independent particle runs of one record (the batch dimension)


def _missing_record(record):
    sysm, u, y = record
    y = y.copy()
    y[[10, 11, 12, 13, 50, 99]] = np.nan  # whole samples (including the last one)
    rng = np.random.default_rng(1)
    single = rng.choice(N_STEPS * 2, size=30, replace=False)
    y.reshape(-1)[single] = np.nan  # single components
    assert np.isnan(y).any(1).sum() > 20 and (~np.isnan(y)).any(1).sum() > 80
    return sysm, u, y


def _check_log_likelihood(ll: np.ndarray, exact: float) -> None:
    """Particle log-likelihoods of independent runs vs the exact value.

    ``p_hat`` is unbiased, so ``log p_hat`` is biased by about ``-Var/2``: correct for it, then
    demand agreement within 4 standard errors, and the raw mean within 0.01 per sample.
    """
    se = ll.std(ddof=1) / math.sqrt(ll.size)
    corrected = ll.mean() + 0.5 * ll.var(ddof=1)
    assert abs(corrected - exact) < 4 * se + 1e-3, (ll.mean(), corrected, exact, se)
    assert abs(ll.mean() - exact) < 0.01 * N_STEPS
    assert ll.std(ddof=1) < 2.0  # the estimator is not degenerate


@pytest.mark.parametrize(
    ("scheme", "ess_threshold", "L"),
    [("systematic", 1.0, 500)] + [(s, 0.5, 250) for s in sorted(RESAMPLING_SCHEMES)],
)
def test_log_likelihood_matches_kalman(record, scheme, ess_threshold, L):
    sysm, u, y = record
    exact = kalman_filter(*sysm.matrices(), u, y).log_likelihood
    filt = particle_filter(
        sysm.model(),
        replicate(u, y, N_COPIES),
        L,
        resampling=scheme,
        ess_threshold=ess_threshold,
        generator=generator(11),
    )
    _check_log_likelihood(filt.log_likelihood.numpy(), exact)
    if ess_threshold < 1:  # some steps carried their weights over
        assert (filt.ess < 0.999 * L).any()


def test_log_likelihood_with_missing_data(record):
    sysm, u, y = _missing_record(record)
    exact = kalman_filter(*sysm.matrices(), u, y).log_likelihood
    full = kalman_filter(*record[0].matrices(), record[1], record[2]).log_likelihood
    assert abs(exact - full) > 10  # the missing values matter
    filt = particle_filter(sysm.model(), replicate(u, y, N_COPIES), 300, generator=generator(12))
    _check_log_likelihood(filt.log_likelihood.numpy(), exact)
    # an all-missing step leaves the weights as they were (uniform after resampling)
    np.testing.assert_allclose(filt.ess[11].numpy(), 300.0, rtol=1e-9)


def _check_moments(mean, cov, ref_mean, ref_cov, tol_mean=0.075, tol_cov=0.025):
    """Particle moments of independent runs ``(T, B, nx)`` vs exact ones ``(T, nx)``.

    The across-run average must be unbiased (RMS error comparable to its standard error; the
    particle methods' O(1/L) bias is ~0.002 here, against a standard error of ~0.01), close in
    absolute terms, and every single run must be close too.  Observed on the seeds used: RMS ratio
    1.2-1.3, averaged max error 0.05, single-run max error 0.25, covariance error 0.014.
    """
    mean, cov = mean.numpy(), cov.numpy()
    B = mean.shape[1]
    avg = mean.mean(1)
    se = mean.std(1, ddof=1) / math.sqrt(B)
    rms_err = np.sqrt(((avg - ref_mean) ** 2).mean())
    rms_se = np.sqrt((se**2).mean())
    assert rms_err < 1.6 * rms_se, (rms_err, rms_se)
    assert np.abs(avg - ref_mean).max() < tol_mean
    assert np.abs(mean - ref_mean[:, None]).max() < 0.4  # every single run
    cov_err = cov.mean(1) - ref_cov
    assert np.abs(cov_err).max() < tol_cov, np.abs(cov_err).max()
    # time-averaged covariances agree to 10 %
    np.testing.assert_allclose(cov.mean((0, 1)), ref_cov.mean(0), rtol=0.1, atol=2e-3)


@pytest.fixture(scope="module")
def smoothed_run(record):
    sysm, u, y = record
    model = sysm.model()
    data = replicate(u, y, 16)
    filt = particle_filter(model, data, 250, generator=generator(21))
    smooth = ffbsm(model, data, filt)
    return filt, smooth


def test_filtered_moments_match_kalman(record, smoothed_run):
    sysm, u, y = record
    kf = kalman_filter(*sysm.matrices(), u, y)
    filt, _ = smoothed_run
    mean, cov = smoothed_moments(filt.particles, filt.log_weights)
    _check_moments(mean, cov, kf.filtered_mean, kf.filtered_cov)


def test_smoothed_moments_match_rts(record, smoothed_run):
    sysm, u, y = record
    sm, sP = rts_smoother(sysm.A, kalman_filter(*sysm.matrices(), u, y))
    filt, smooth = smoothed_run
    mean, cov = smoothed_moments(filt.particles, smooth.log_weights)
    _check_moments(mean, cov, sm, sP)
    # the smoother is informative: it beats the filter on the (exact) smoothed means
    fmean, _ = smoothed_moments(filt.particles, filt.log_weights)
    assert (
        np.abs(mean.numpy() - sm[:, None]).mean() < 0.7 * np.abs(fmean.numpy() - sm[:, None]).mean()
    )


@pytest.mark.parametrize("method", ["reject", "mcmc"])
def test_ffbsi_smoothed_moments_match_rts(record, smoothed_run, method):
    """Backward simulation (O(N L)) estimates the same smoothed moments, with more noise."""
    sysm, u, y = record
    sm, sP = rts_smoother(sysm.A, kalman_filter(*sysm.matrices(), u, y))
    filt, _ = smoothed_run
    data = replicate(u, y, filt.particles.shape[1])
    smooth = ffbsi(sysm.model(), data, filt, method=method, generator=generator(23))
    mean, cov = smoothed_moments(filt.particles, smooth.log_weights)
    _check_moments(mean, cov, sm, sP)
    np.testing.assert_allclose(smooth.transition_weights.sum(-1).numpy(), 1.0, atol=1e-10)


def test_mcmc_smoother_after_adaptive_resampling_matches_rts(record):
    """With ``ess_threshold < 1`` the filter keeps its particles at some steps (the MCMC moves then
    weigh their uniform proposals by ``W``) and resamples at others (proposals from the ancestry):
    the smoothed moments still match RTS."""
    sysm, u, y = record
    sm, sP = rts_smoother(sysm.A, kalman_filter(*sysm.matrices(), u, y))
    model = sysm.model()
    data = replicate(u, y, 16)
    filt = particle_filter(model, data, 250, ess_threshold=0.5, generator=generator(31))
    kept = (~filt.resampled[1:]).float().mean().item()
    assert 0.2 < kept < 0.95, kept  # both kinds of steps occur
    smooth = ffbsi(model, data, filt, method="mcmc", generator=generator(32))
    mean, cov = smoothed_moments(filt.particles, smooth.log_weights)
    _check_moments(mean, cov, sm, sP)


def test_smoothed_moments_with_missing_data(record):
    sysm, u, y = _missing_record(record)
    sm, sP = rts_smoother(sysm.A, kalman_filter(*sysm.matrices(), u, y))
    model = sysm.model()
    data = replicate(u, y, 16)
    filt = particle_filter(model, data, 200, generator=generator(22))
    smooth = ffbsm(model, data, filt)
    mean, cov = smoothed_moments(filt.particles, smooth.log_weights)
    _check_moments(mean, cov, sm, sP)


def test_smoother_last_step_equals_filter(smoothed_run):
    filt, smooth = smoothed_run
    assert torch.equal(smooth.log_weights[-1], filt.log_weights[-1])
    np.testing.assert_allclose(torch.logsumexp(smooth.log_weights, -1).numpy(), 0.0, atol=1e-10)
    np.testing.assert_allclose(smooth.transition_weights.sum(-1).numpy(), 1.0, atol=1e-10)


# --------------------------------------------------------------------------- Student-t weights


@pytest.mark.parametrize("dof", [0.7, 3.0, math.inf])
def test_filter_weights_are_student_t_densities(dof):
    """Recompute every step's weights and the log-likelihood from the filter's own particles."""
    rng = np.random.default_rng(3)
    T, B, L = 12, 3, 40
    u = torch.as_tensor(rng.normal(size=(T, B, 1)))
    y = torch.as_tensor(rng.normal(size=(T, B, 2)) + 3.0 * (rng.random((T, B, 2)) < 0.2))
    y[2, 0] = math.nan
    y[4, 1, 0] = math.nan
    y[7, 2, 1] = math.nan
    data = SequenceBatch(u=u, y=y, lengths=torch.full((B,), T))
    model = nonlinear_model(dof)
    filt = particle_filter(model, data, L, generator=generator(5))
    X = filt.particles
    R = model.Rv.numpy()
    ll = np.zeros(B)
    for k in range(T):
        for b in range(B):
            yk = y[k, b].numpy()
            obs = ~np.isnan(yk)
            if not obs.any():
                logp = np.zeros(L)
            else:
                mu = model.g(X[k, b], u[k, b].expand(L, 1)).detach().numpy()[:, obs]
                sub = R[np.ix_(obs, obs)]
                if math.isinf(dof):
                    logp = np.array([stats.multivariate_normal(m, sub).logpdf(yk[obs]) for m in mu])
                else:
                    logp = np.array(
                        [stats.multivariate_t(m, sub, df=dof).logpdf(yk[obs]) for m in mu]
                    )
            # resampling at every step: the particles carry uniform weights into step k, except
            # after an all-missing step, whose (uniform) weights are carried over unchanged
            prev = np.full(L, -math.log(L)) if k == 0 else filt.log_weights[k - 1, b].numpy()
            if k > 0 and filt.ess[k - 1, b] < L - 1e-6:
                prev = np.full(L, -math.log(L))
            logits = prev + logp
            ll[b] += logsumexp(logits)
            np.testing.assert_allclose(
                filt.log_weights[k, b].numpy(), logits - logsumexp(logits), atol=1e-9
            )
            assert filt.ess[k, b].item() == pytest.approx(
                1 / np.exp(2 * (logits - logsumexp(logits))).sum()
            )
    np.testing.assert_allclose(filt.log_likelihood.numpy(), ll, rtol=1e-10)


def test_filter_is_reproducible_and_rows_are_independent():
    rng = np.random.default_rng(8)
    u = torch.as_tensor(rng.normal(size=(15, 3, 1)))
    y = torch.as_tensor(rng.normal(size=(15, 3, 2)))
    data = SequenceBatch(u=u, y=y, lengths=torch.full((3,), 15))
    model = nonlinear_model(3.0)
    a = particle_filter(model, data, 30, generator=generator(1))
    b = particle_filter(model, data, 30, generator=generator(1))
    assert torch.equal(a.particles, b.particles) and torch.equal(a.log_likelihood, b.log_likelihood)
    # change row 2's data: rows 0 and 1 see the same random numbers and must not change
    y2 = y.clone()
    y2[:, 2] += 1.0
    c = particle_filter(model, replace(data, y=y2), 30, generator=generator(1))
    assert torch.equal(a.particles[:, :2], c.particles[:, :2])
    assert torch.equal(a.log_likelihood[:2], c.log_likelihood[:2])
    assert not torch.equal(a.log_likelihood[2], c.log_likelihood[2])


class NaNAfter(nn.Module):
    def forward(self, x, u):
        return torch.where(x.abs() > 5.0, torch.full_like(x, math.nan), 2.0 * x + u)


def test_filter_raises_on_non_finite_model():
    t = lambda a: torch.as_tensor(a, dtype=DTYPE)  # noqa: E731
    model = make_model(NaNAfter(), Paper41G(), t([[0.01]]), t([[0.1]]), 4.0, t([1.0]), t([[0.01]]))
    data = SequenceBatch(
        u=torch.zeros(10, 1, 1, dtype=DTYPE),
        y=torch.zeros(10, 1, 1, dtype=DTYPE),
        lengths=torch.tensor([10]),
    )
    with pytest.raises(NumericalError, match="time step"):
        particle_filter(model, data, 20, generator=generator(0))


# --------------------------------------------------------------------------- FFBSm identities


@pytest.fixture(scope="module", params=["paper41", "nonlinear2d"])
def ffbsm_case(request):
    """Filter + FFBSm on 3 sequences (lengths 30, 22, 30) with 10 % outliers, one missing sample."""
    rng = np.random.default_rng(17)
    model = paper_model(3.0) if request.param == "paper41" else nonlinear_model(3.0)
    us, ys = simulate(model, [30, 22, 30], rng, outlier_rate=0.1)
    ys[0][4] = math.nan
    data = SequenceBatch.from_sequences(us, ys)
    filt = particle_filter(model, data, 50, generator=generator(2))
    smooth = ffbsm(model, data, filt, kernel_dtype=torch.float64)  # the algebra, to rounding
    ref = pairwise_smoother(
        model.f, model.Rw, data.u, data.lengths.tolist(), filt.particles, filt.log_weights
    )
    return model, data, filt, smooth, ref


def test_ffbsm_marginal_weights(ffbsm_case):
    _, data, _, smooth, ref = ffbsm_case
    for b, (logWs, pairs) in enumerate(ref):
        n = logWs.shape[0]
        np.testing.assert_allclose(
            np.exp(smooth.log_weights[:n, b].numpy()), np.exp(logWs), atol=1e-12
        )
        big = logWs > -200
        np.testing.assert_allclose(smooth.log_weights[:n, b].numpy()[big], logWs[big], atol=1e-8)
        for k, P in enumerate(pairs):
            # sum_j W^{ij} = W_{k|N}^i and sum_i W^{ij} = W_{k+1|N}^j
            np.testing.assert_allclose(P.sum(1), np.exp(logWs[k]), atol=1e-12)
            np.testing.assert_allclose(P.sum(0), np.exp(logWs[k + 1]), atol=1e-12)
            np.testing.assert_allclose(
                smooth.transition_weights[k, b].numpy(), P.sum(1), atol=1e-12
            )
        assert torch.all(smooth.transition_weights[n - 1 :, b] == 0)


def test_ffbsm_next_mean_and_scatter(ffbsm_case):
    _, data, filt, smooth, ref = ffbsm_case
    for b, (logWs, pairs) in enumerate(ref):
        n = logWs.shape[0]
        X = filt.particles[:n, b].numpy()
        nx = X.shape[-1]
        scatter = np.zeros((nx, nx))
        for k, P in enumerate(pairs):
            s = P.sum(1)
            m = P @ X[k + 1]  # (i, nx)
            pos = s > 1e-100
            np.testing.assert_allclose(
                smooth.next_mean[k, b].numpy()[pos], m[pos] / s[pos, None], rtol=1e-8, atol=1e-10
            )
            S = np.einsum("ij,jp,jq->pq", P, X[k + 1], X[k + 1])
            scatter += S - np.einsum("ip,iq->pq", m[pos], m[pos] / s[pos, None])
        np.testing.assert_allclose(
            smooth.residual_scatter[b].numpy(), scatter, rtol=1e-8, atol=1e-12
        )


def test_ffbsm_process_scatter_identity(ffbsm_case):
    """sum_ij W^{ij} (x^j - f^i)(x^j - f^i)^T
    = bracket + sum_i s^i (xbar^i - f^i)(xbar^i - f^i)^T (docs/method.md §7)."""
    model, data, filt, smooth, ref = ffbsm_case
    for b, (_, pairs) in enumerate(ref):
        direct = 0.0
        via_stats = smooth.residual_scatter[b].numpy().copy()
        for k, P in enumerate(pairs):
            L = P.shape[0]
            fx = model.f(filt.particles[k, b], data.u[k, b].expand(L, -1)).detach().numpy()
            d = filt.particles[k + 1, b].numpy()[None, :, :] - fx[:, None, :]
            direct = direct + np.einsum("ij,ijp,ijq->pq", P, d, d)
            r = smooth.next_mean[k, b].numpy() - fx
            via_stats += np.einsum("i,ip,iq->pq", smooth.transition_weights[k, b].numpy(), r, r)
        np.testing.assert_allclose(via_stats, direct, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("chunk_size", [7, 49])
def test_ffbsm_chunked_equals_unchunked(ffbsm_case, chunk_size):
    model, data, filt, smooth, _ = ffbsm_case
    other = ffbsm(model, data, filt, chunk_size=chunk_size, kernel_dtype=torch.float64)
    for name in ("log_weights", "next_mean", "transition_weights", "residual_scatter"):
        a, b = getattr(smooth, name), getattr(other, name)
        np.testing.assert_allclose(
            torch.nan_to_num(b, neginf=-1e300).numpy(),
            torch.nan_to_num(a, neginf=-1e300).numpy(),
            rtol=1e-10,
            atol=1e-12,
        )


def test_ffbsm_single_precision_kernel_matches_double(ffbsm_case):
    """The default single-precision kernel: the same statistics to ~1e-6 (Monte Carlo error here is
    ~1e-1)."""
    model, data, filt, smooth, _ = ffbsm_case
    fast = ffbsm(model, data, filt)
    w64, w32 = torch.exp(smooth.log_weights), torch.exp(fast.log_weights)
    torch.testing.assert_close(w32, w64, rtol=0, atol=2e-6)
    torch.testing.assert_close(fast.transition_weights, smooth.transition_weights, rtol=0, atol=2e-6)
    big = smooth.transition_weights > 1e-3
    torch.testing.assert_close(fast.next_mean[big], smooth.next_mean[big], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast.residual_scatter, smooth.residual_scatter, rtol=1e-5, atol=1e-6)


def test_ffbsm_single_precision_far_from_the_origin():
    """States near 1000 with process noise s.d. 0.03: whitened states ~3e4, whose squares no
    single-precision exponent could hold; centring each step keeps the kernel exact to ~1e-6."""
    rng = np.random.default_rng(8)
    model = replace(paper_model(3.0), Rw=torch.tensor([[1e-3]], dtype=DTYPE))
    model.f.a.data.fill_(1.0)  # a random walk near 1000
    model = replace(
        model, x0_mean=torch.tensor([1000.0], dtype=DTYPE), x0_cov=torch.tensor([[0.01]], dtype=DTYPE)
    )
    us, ys = simulate(model, [40, 40], rng)
    data = SequenceBatch.from_sequences([0.01 * u for u in us], ys)
    filt = particle_filter(model, data, 80, generator=generator(9))
    exact = ffbsm(model, data, filt, kernel_dtype=torch.float64)
    fast = ffbsm(model, data, filt)
    ref = pairwise_smoother(
        model.f, model.Rw, data.u, data.lengths.tolist(), filt.particles, filt.log_weights
    )
    for b, (logWs, _) in enumerate(ref):
        np.testing.assert_allclose(np.exp(exact.log_weights[:, b].numpy()), np.exp(logWs), atol=1e-10)
    torch.testing.assert_close(torch.exp(fast.log_weights), torch.exp(exact.log_weights), rtol=0, atol=1e-5)
    torch.testing.assert_close(fast.next_mean, exact.next_mean, rtol=1e-9, atol=1e-4)
    torch.testing.assert_close(fast.residual_scatter, exact.residual_scatter, rtol=1e-4, atol=1e-8)


@pytest.mark.parametrize("kdtype", [torch.float32, torch.float64])
def test_backward_kernel_rows_recomputed_where_the_bound_underflows(kdtype):
    """Rows shifted by an upper bound of their maximum; a row far below its bound (no prediction
    comes near that particle, or the near ones have tiny weights) is recomputed exactly."""
    g = torch.Generator().manual_seed(6)
    B, L, J, nx = 3, 40, 25, 2
    logW = torch.log_softmax(3.0 * torch.randn(B, L, dtype=DTYPE, generator=g), -1)
    zf = torch.randn(B, L, nx, dtype=DTYPE, generator=g)
    zx = torch.randn(B, J, nx, dtype=DTYPE, generator=g)
    zx[0, 3] += 30.0  # about 450 nats below its bound: all of its row underflows
    zx[2, 7] -= 16.0  # about 130 nats below: in single precision only
    a = logW - 0.5 * squared_norm(zf)
    ref = torch.softmax(a.unsqueeze(-2) + zx @ zf.mT, dim=-1)
    E, inv_d = _backward_kernels(a, zf, zx, logW, kdtype)
    K = (E * inv_d.unsqueeze(-1)).to(DTYPE)
    assert torch.isfinite(K).all()
    tol = 1e-6 if kdtype == torch.float32 else 1e-12
    torch.testing.assert_close(K, ref, rtol=0, atol=tol)
    torch.testing.assert_close(K.sum(-1), torch.ones(B, J, dtype=DTYPE), rtol=0, atol=10 * tol)


# --------------------------------------------------------------------------- padding


def _slice_filter(filt: FilterOutput, b: int, n: int) -> FilterOutput:
    """Sequence ``b`` of a filter output, cut to its first ``n`` steps."""
    sel = filt.select(slice(b, b + 1))
    cut = {}
    for field in fields(sel):
        value = getattr(sel, field.name)
        if field.name == "log_likelihood" or value is None:
            continue
        if isinstance(value, MaskedScale):
            value = MaskedScale(*(getattr(value, f.name)[:n] for f in fields(value)))
        else:
            value = value[:n]
        cut[field.name] = value
    return replace(sel, **cut)


def test_padding_is_inert(record):
    sysm, u, y = record
    model = sysm.model()
    ut, yt = torch.as_tensor(u), torch.as_tensor(y)
    rng = np.random.default_rng(5)
    y_other = torch.as_tensor(y + rng.normal(size=y.shape))
    n_short = 40
    padded = SequenceBatch.from_sequences([ut[:60], ut[:n_short]], [yt[:60], y_other[:n_short]])
    assert padded.lengths.tolist() == [60, n_short] and padded.n_steps == 60
    assert torch.isnan(padded.y[n_short:, 1]).all()
    full = SequenceBatch.from_sequences([ut[:60], ut[:60]], [yt[:60], y_other[:60]])
    # arbitrary inputs in the padding change nothing inside the sequences
    garbage = replace(padded, u=padded.u.clone())
    garbage.u[n_short:, 1] = 7.0

    runs = {}
    for name, data in (("padded", padded), ("full", full), ("garbage", garbage)):
        filt = particle_filter(model, data, 60, generator=generator(3))
        runs[name] = (data, filt, ffbsm(model, data, filt, chunk_size=13, kernel_dtype=torch.float64))
    (_, fp, sp), (_, ff, sf), (_, fg, sg) = runs["padded"], runs["full"], runs["garbage"]
    # the same random numbers: row 0 identical, row 1 identical up to its end
    assert torch.equal(fp.particles[:, 0], ff.particles[:, 0])
    assert torch.equal(fp.log_likelihood[0], ff.log_likelihood[0])
    assert torch.equal(sp.log_weights[:, 0], sf.log_weights[:, 0])
    assert torch.equal(sp.residual_scatter[0], sf.residual_scatter[0])
    assert torch.equal(fp.particles[:n_short, 1], ff.particles[:n_short, 1])
    assert torch.equal(fp.log_weights[:n_short, 1], ff.log_weights[:n_short, 1])
    # garbage in the padding: the same answers inside the sequence
    assert torch.equal(fp.log_likelihood, fg.log_likelihood)
    assert torch.equal(sp.log_weights[:n_short, 1], sg.log_weights[:n_short, 1])
    for name in ("next_mean", "transition_weights"):  # transitions 0 .. n_short - 2
        assert torch.equal(getattr(sp, name)[: n_short - 1, 1], getattr(sg, name)[: n_short - 1, 1])
    torch.testing.assert_close(sp.residual_scatter, sg.residual_scatter, rtol=1e-12, atol=1e-12)
    # the short row smooths as if it were run alone on its n_short samples
    alone = SequenceBatch.from_sequences([ut[:n_short]], [y_other[:n_short]])
    s_alone = ffbsm(model, alone, _slice_filter(fp, 1, n_short), kernel_dtype=torch.float64)
    torch.testing.assert_close(
        sp.log_weights[:n_short, 1:2], s_alone.log_weights, rtol=1e-12, atol=1e-12
    )
    torch.testing.assert_close(
        sp.next_mean[: n_short - 1, 1:2], s_alone.next_mean, rtol=1e-12, atol=1e-12
    )
    torch.testing.assert_close(
        sp.transition_weights[: n_short - 1, 1:2],
        s_alone.transition_weights,
        rtol=1e-12,
        atol=1e-12,
    )
    torch.testing.assert_close(
        sp.residual_scatter[1:2], s_alone.residual_scatter, rtol=1e-10, atol=1e-12
    )
    assert torch.all(sp.transition_weights[n_short - 1 :, 1] == 0)
    assert torch.equal(sp.log_weights[n_short - 1 :, 1], fp.log_weights[n_short - 1 :, 1])


def test_sequences_of_different_lengths_match_kalman(record):
    sysm, u, y = record
    n_short = 60
    ut, yt = torch.as_tensor(u), torch.as_tensor(y)
    us = [ut] * 10 + [ut[:n_short]] * 10
    ys = [yt] * 10 + [yt[:n_short]] * 10
    data = SequenceBatch.from_sequences(us, ys)
    filt = particle_filter(sysm.model(), data, 250, generator=generator(9))
    ll = filt.log_likelihood.numpy()
    _check_log_likelihood(ll[:10], kalman_filter(*sysm.matrices(), u, y).log_likelihood)
    _check_log_likelihood(
        ll[10:], kalman_filter(*sysm.matrices(), u[:n_short], y[:n_short]).log_likelihood
    )


def test_ffbsm_single_precision_kernel_with_huge_whitened_distances():
    """A first-state prior far broader than the process noise (prior s.d. 1, process s.d. 1e-5: the
    whitened distances of the first transition reach ~1e5): the single-precision kernel's exponent
    overflows there, and those rows are recomputed exactly (finite, the double-precision kernel's
    statistics)."""
    rng = np.random.default_rng(3)
    model = make_model(Paper41F(), Paper41G(), [[1e-10]], [[0.1]], 3.0, [0.0], [[1.0]])
    us, ys = simulate(replace(model, Rw=model.Rw * 1e8), [20], rng)  # outputs with some motion
    data = SequenceBatch.from_sequences(us, ys)
    filt = particle_filter(model, data, 100, generator=generator(5))
    exact = ffbsm(model, data, filt, kernel_dtype=torch.float64)
    fast = ffbsm(model, data, filt)
    assert torch.isfinite(fast.residual_scatter).all() and torch.isfinite(fast.transition_weights).all()
    torch.testing.assert_close(fast.transition_weights, exact.transition_weights, rtol=0, atol=2e-6)
    torch.testing.assert_close(fast.residual_scatter, exact.residual_scatter, rtol=1e-4, atol=0)
