"""Standard errors by Louis' identity against exact references (torch_nssm.estimation.uncertainty).

The reference is the inverse of the numerical Hessian of the exact Kalman log-likelihood
(tests/reference.py), on the same working scale as the particle information (the entries of ``A``,
``B`` and the log-Cholesky factors of ``Rw`` and ``Rv``): the observed information on two scales
differs by a term in the score away from the maximum, so the two are compared on one scale.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from reference import kalman_filter, simulate_linear

from torch_nssm import RobustNSSMEstimator
from torch_nssm._threads import limited_threads
from torch_nssm.blocks.linear import LinearObservation, LinearTransition
from torch_nssm.core.model import SequenceBatch
from torch_nssm.estimation import uncertainty as U
from torch_nssm.estimation.mstep import transition_regression
from torch_nssm.inference.ffbsi import backward_segments, backward_trajectories

A = np.array([[0.8, 0.2], [-0.3, 0.6]])
B = np.array([[1.0], [0.5]])
C = np.eye(2)
D = np.zeros((2, 1))
Q = np.array([[0.10, 0.03], [0.03, 0.08]])
R = np.array([[0.05, 0.01], [0.01, 0.07]])


def _chol(a: float, b: float, c: float) -> np.ndarray:
    return np.array([[np.exp(a), 0.0], [c, np.exp(b)]])


def _numerical_hessian(fn, w0: np.ndarray) -> np.ndarray:
    n = len(w0)
    h = 1e-4 * np.maximum(np.abs(w0), 0.1)
    H = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            ei, ej = np.zeros(n), np.zeros(n)
            ei[i], ej[j] = h[i], h[j]
            H[i, j] = H[j, i] = (
                fn(w0 + ei + ej) - fn(w0 + ei - ej) - fn(w0 - ei + ej) + fn(w0 - ei - ej)
            ) / (4 * h[i] * h[j])
    return H


@pytest.fixture(scope="module")
def linear_gaussian_fit():
    rng = np.random.default_rng(0)
    u = rng.standard_normal((300, 1))
    _, y = simulate_linear(A, B, C, D, Q, R, np.zeros(2), np.eye(2), u, rng)
    g = LinearObservation(2, 1, 2, C=C, fit_offset=False)
    g.C.requires_grad_(False)  # C = I fixed: A, B, Rw, Rv are then identifiable
    est = RobustNSSMEstimator(
        LinearTransition(2, 1, A=A, B=B),
        g,
        x0_mean=np.zeros(2),
        x0_cov=np.eye(2),
        Rw_init=Q,
        Rv_init=R,
        noise="gaussian",
        n_particles=1000,
        n_iter=5,
        tol=0,
        fit_x0=False,
        random_state=1,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
    return est, u, y


def _natural(w: np.ndarray):
    """``(A and B entries, Rw, Rv)`` from the working vector (log-Cholesky factors)."""
    Lw, Lv = _chol(*w[6:9]), _chol(*w[9:12])
    return w[:6], Lw @ Lw.T, Lv @ Lv.T


def _entries(w: np.ndarray) -> np.ndarray:
    a, Rw, Rv = _natural(w)
    rows, cols = np.tril_indices(2)
    return np.concatenate([a, Rw[rows, cols], Rv[rows, cols]])


@pytest.fixture(scope="module")
def exact(linear_gaussian_fit):
    """The working vector at the fit, the exact inverse Hessian of the Kalman log-likelihood there and
    the particle information (500 trajectories, fixed seed)."""
    est, u, y = linear_gaussian_fit
    Lw, Lv = np.linalg.cholesky(est.Rw_), np.linalg.cholesky(est.Rv_)
    w0 = np.concatenate(
        [
            est.f_.A.detach().numpy().ravel(),
            est.f_.B.detach().numpy().ravel(),
            [np.log(Lw[0, 0]), np.log(Lw[1, 1]), Lw[1, 0], np.log(Lv[0, 0]), np.log(Lv[1, 1]), Lv[1, 0]],
        ]
    )

    def loglik(w):
        a, Rw, Rv = _natural(w)
        A_, B_ = a[:4].reshape(2, 2), a[4:].reshape(2, 1)
        return kalman_filter(A_, B_, C, D, Rw, Rv, est.x0_mean_, est.x0_cov_, u, y).log_likelihood

    model, data = est._uncertainty_source
    e = est._e_step(model, data, est._generator(data.y.device))
    with limited_threads(1):
        unc = U.observed_information(model, data, e, generator=torch.Generator().manual_seed(0))
    return w0, np.linalg.inv(-_numerical_hessian(loglik, w0)), unc


def test_standard_errors_match_the_exact_kalman_information(linear_gaussian_fit, exact):
    """Every working-scale standard error within 15 % of the exact one (measured: within 6 %), and
    the natural-scale ones (delta method) within 15 % of the exact delta-method ones."""
    est, _, _ = linear_gaussian_fit
    w0, cov_exact, unc = exact
    assert unc.working_names[6:] == [
        "log chol(Rw)[0, 0]",
        "log chol(Rw)[1, 1]",
        "chol(Rw)[1, 0]",
        "log chol(Rv)[0, 0]",
        "log chol(Rv)[1, 1]",
        "chol(Rv)[1, 0]",
    ]
    se_exact = np.sqrt(np.diag(cov_exact))
    se_particle = np.sqrt(np.diag(np.linalg.inv(unc.information)))
    np.testing.assert_allclose(se_particle, se_exact, rtol=0.15)
    assert np.max(np.abs(se_particle / se_exact - 1)) > 1e-3  # a Monte Carlo estimate, not a copy

    # natural scale: the exact covariance mapped by a finite-difference Jacobian of the mapping
    J = np.stack([(_entries(w0 + h) - _entries(w0 - h)) / 2e-6 for h in 1e-6 * np.eye(12)], 1)
    se_nat_exact = np.sqrt(np.diag(J @ cov_exact @ J.T))
    np.testing.assert_allclose(np.sqrt(np.diag(unc.covariance)), se_nat_exact, rtol=0.15)
    assert unc.names[6:] == ["Rw[0, 0]", "Rw[1, 0]", "Rw[1, 1]", "Rv[0, 0]", "Rv[1, 0]", "Rv[1, 1]"]
    np.testing.assert_allclose(unc.estimate[6:9], est.Rw_[[0, 1, 1], [0, 0, 1]])
    np.testing.assert_allclose(unc.jacobian, J, rtol=1e-5, atol=1e-8)


def test_without_the_lag_window_the_score_variance_is_biased(linear_gaussian_fit, exact):
    """The plain covariance of whole-trajectory scores sums ``T^2`` cross terms, each with a particle
    bias of order ``1/L``: its standard errors are further from the exact ones than the windowed."""
    est, _, _ = linear_gaussian_fit
    _, cov_exact, unc = exact
    model, data = est._uncertainty_source
    e = est._e_step(model, data, est._generator(data.y.device))
    X = e.filter.particles
    with limited_threads(1):
        blocks, _ = U._blocks(model, True, True, True)
        ll = U._LogLikelihood(model, blocks)
        w0 = torch.cat([b.to_working() for b in blocks])
        # the information's own pieces of trajectories (the same seed: the same draws)
        gen = torch.Generator().manual_seed(0)
        V_window, lag, _ = U._score_variance(ll, w0, model, data, e, 500, True, gen)
        # whole trajectories for the plain covariance
        Js = backward_trajectories(model, data, e.filter, 500, generator=torch.Generator().manual_seed(0))
        rows = U._piece_rows(X, data, Js.unsqueeze(0), [0])
        s = U._row_scores(ll, w0, rows, True).view(*Js.shape, -1).permute(2, 0, 1, 3).numpy()  # (M, T, B, d)
    np.testing.assert_allclose(V_window, unc.score_variance)
    assert 1 <= lag < 50 and lag == unc.lag_window
    V_plain = np.cov(s.sum((1, 2)), rowvar=False)
    se_exact = np.sqrt(np.diag(cov_exact))
    error = {}
    for name, V in (("window", V_window), ("plain", V_plain)):
        var = np.diag(np.linalg.inv(unc.complete_information - V))  # negative: not even positive definite
        error[name] = np.max(np.where(var > 0, np.abs(np.sqrt(np.abs(var)) / se_exact - 1), np.inf))
    assert error["plain"] > 1.5 * error["window"], error


def test_expected_hessian_is_the_mstep_objective(linear_gaussian_fit):
    """The Hessian of the expected complete-data log-likelihood in the entries of ``B`` is
    ``-sum_k s_k^i u_k u_k^T (x) Rw^-1`` over the M-step's transition rows: exact for f linear."""
    est, _, _ = linear_gaussian_fit
    model, data = est._uncertainty_source
    e = est._e_step(model, data, est._generator(data.y.device))
    with limited_threads(1):
        unc = U.observed_information(
            model, data, e, n_trajectories=50, generator=torch.Generator().manual_seed(0)
        )
    reg = transition_regression(model.Rw, data, e)
    w = reg.row_weight(slice(None))  # (T-1, 1, L): s_k^i
    uu = float((w.sum(-1) * data.u[:-1, :, 0] ** 2).sum())
    np.testing.assert_allclose(unc.complete_information[4:6, 4:6], uu * np.linalg.inv(est.Rw_), rtol=1e-6)
    # Louis: information = complete-data information - score variance
    np.testing.assert_allclose(unc.information, unc.complete_information - unc.score_variance, atol=1e-9)


def test_backward_trajectories_follow_the_smoothing_marginals():
    """Trajectory counts match the exact FFBSm marginal smoothing weights (within 5 binomial s.e. over
    1,800 (time, particle) cells; measured max 3.2-3.6, as the library's FFBSi)."""
    from torch_nssm.core.model import StateSpaceModel
    from torch_nssm.core.noise import GaussianNoise
    from torch_nssm.datasets.paper import PaperObservation, PaperTransition
    from torch_nssm.estimation.estep import EStepOptions, e_step

    rng = np.random.default_rng(3)
    u = torch.as_tensor(rng.standard_normal((60, 1)))
    y = torch.as_tensor(
        np.cos(np.cumsum(rng.standard_normal(60)))[:, None] + 0.3 * rng.standard_normal((60, 1))
    )
    data = SequenceBatch.from_sequences([u], [y])
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    model = StateSpaceModel(
        PaperTransition(0.9, 1.0),
        PaperObservation(1.0),
        t([[0.1]]),
        GaussianNoise(t([[0.1]])),
        t([0.0]),
        t([[1.0]]),
    )
    gen = torch.Generator().manual_seed(0)
    est = e_step(
        model, data, EStepOptions(n_particles=30, smoother_options={"kernel_dtype": torch.float64}), gen
    )
    M = 20000
    Js = backward_trajectories(model, data, est.filter, M, max_tries=2, generator=gen)[:, 0]  # (T, M)
    counts = torch.zeros(60, 30, dtype=torch.float64).scatter_add_(
        1, Js, torch.ones(60, M, dtype=torch.float64)
    )
    p = torch.exp(est.smoother.log_weights[:, 0])
    z = torch.where(p > 1e-3, (counts / M - p) / torch.sqrt(p * (1 - p) / M), 0.0)  # tiny p: no normal limit
    assert float(z.abs().max()) < 5.0
    # pairs (k, k+1) follow the pairwise weights: the mean of x_{k+1} given x_k = i is xbar_k^i
    X = est.filter.particles[:, 0, :, 0]
    nxt = torch.gather(X[1:], 1, Js[1:])
    m = torch.zeros(59, 30, dtype=torch.float64).scatter_add_(1, Js[:-1], nxt)
    seen = counts[:-1] > 500
    xbar = m[seen] / counts[:-1][seen]
    np.testing.assert_allclose(xbar.numpy(), est.smoother.next_mean[:, 0, :, 0][seen].numpy(), atol=0.05)


def _paper_estep(noise: str = "student-t", p: int = 1, n: int = 80, missing: bool = False, seed: int = 3):
    """A small model of the paper's kind (``p`` outputs) and one E-step of simulated data."""
    from torch_nssm.blocks.linear import LinearObservation
    from torch_nssm.core.model import StateSpaceModel
    from torch_nssm.core.noise import noise_spec
    from torch_nssm.datasets.paper import PaperObservation, PaperTransition
    from torch_nssm.estimation.estep import EStepOptions, e_step

    rng = np.random.default_rng(seed)
    u = torch.as_tensor(rng.standard_normal((n, 1)))
    x = np.cumsum(0.3 * rng.standard_normal(n))
    y = np.cos(x)[:, None] * np.linspace(1.0, 0.5, p) + 0.3 * rng.standard_t(3, (n, p))
    if missing:
        y[rng.random((n, p)) < 0.2] = np.nan
    data = SequenceBatch.from_sequences([u], [torch.as_tensor(y)])
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    g = PaperObservation(1.0) if p == 1 else LinearObservation(1, 1, p, C=np.linspace(1.0, 0.5, p)[:, None])
    Rv = t(np.diag(np.full(p, 0.1)) + 0.02 * (noise != "student-t-per-output") * (1 - np.eye(p)))
    model = StateSpaceModel(
        PaperTransition(0.9, 1.0), g, t([[0.1]]), noise_spec(noise, dof_init=4.0).initial(Rv), t([0.0]),
        t([[1.0]]),
    )
    est = e_step(model, data, EStepOptions(n_particles=50), torch.Generator().manual_seed(0))
    return model, data, est


@pytest.mark.parametrize(
    "noise,p,missing",
    [
        ("gaussian", 2, False),
        ("student-t", 1, False),
        ("student-t", 2, False),
        ("student-t-per-output", 2, True),
    ],
)
def test_closed_form_scores_and_hessian_match_autograd(noise, p, missing):
    """The per-step scores in closed form equal reverse-mode autograd of each row's log-density, and
    the expected Hessian from the moments (Gaussian parts) and the closed-form Student-t terms equals
    the autograd Hessian of ``Q`` (forced by treating the modules as general)."""
    model, data, est = _paper_estep(noise, p, missing=missing)
    all_observed = bool(data.obs_mask[data.obs_mask.any(-1)].all())
    blocks, _ = U._blocks(model, True, True, True)
    ll = U._LogLikelihood(model, blocks)
    w0 = torch.cat([b.to_working() for b in blocks])
    T = data.y.shape[0]
    starts, length, _ = U._pieces(T, 6, 24)
    Js = backward_segments(
        model, data, est.filter, 7, starts, length, log_weights=est.smoother.log_weights,
        generator=torch.Generator().manual_seed(0),
    )
    rows = U._piece_rows(est.filter.particles, data, Js, starts)
    fast = U._closed_form_scores(ll, w0, rows)
    reference = U._row_scores_autograd(ll, w0, rows, all_observed)
    np.testing.assert_allclose(fast.numpy(), reference.numpy(), rtol=1e-9, atol=1e-9)

    unc = U.observed_information(
        model, data, est, n_trajectories=20, generator=torch.Generator().manual_seed(0)
    )
    original = U._linear_in_parameters
    try:
        U._linear_in_parameters = lambda module: False  # the general path: autograd Hessians
        general = U.observed_information(
            model, data, est, n_trajectories=20, generator=torch.Generator().manual_seed(0)
        )
    finally:
        U._linear_in_parameters = original
    np.testing.assert_allclose(unc.complete_information, general.complete_information, rtol=1e-9, atol=1e-8)
    # the scores of a module without the linear form come from forward mode: the same information
    np.testing.assert_allclose(unc.score_variance, general.score_variance, rtol=1e-9, atol=1e-8)


def test_windowed_covariance_of_pieces_equals_that_of_whole_trajectories():
    """Pieces that own consecutive steps and run ``margin`` steps past them give the same lag-windowed
    covariance as whole trajectories (the same scores cut into pieces), the record's last piece
    ending at its last step."""
    rng = np.random.default_rng(0)
    M, T, d, lag = 40, 103, 3, 4
    whole = torch.as_tensor(rng.standard_normal((M, T, 1, d))).cumsum(1) * 0.3  # correlated in time
    whole = whole + torch.as_tensor(rng.standard_normal((M, T, 1, d)))
    starts, length, own = U._pieces(T, 6, 20)
    assert length == 26 and starts[-1] == T - length and own.sum() == T and own.any(0).all() is not None
    idx = torch.as_tensor(starts).unsqueeze(1) + torch.arange(length)  # (G, n)
    pieces = whole[:, idx].permute(1, 2, 3, 0, 4)  # (G, n, B, M, d)
    V_pieces, _, mean_pieces = U._windowed_covariance(pieces, torch.as_tensor(own), lag=lag)
    V_whole, _, mean_whole = U._windowed_covariance(
        whole.permute(1, 2, 0, 3).unsqueeze(0), torch.ones(1, T, dtype=torch.bool), lag=lag
    )
    np.testing.assert_allclose(V_pieces, V_whole, rtol=1e-10)
    np.testing.assert_allclose(mean_pieces, mean_whole, rtol=1e-10)
    # brute force: sum over |k - j| <= lag of the centred cross products
    c = (whole - whole.mean(0, keepdim=True))[:, :, 0].numpy()
    brute = sum(
        np.einsum("mi,mj->ij", c[:, k], c[:, j])
        for k in range(T)
        for j in range(max(0, k - lag), min(T, k + lag + 1))
    ) / (M - 1)
    np.testing.assert_allclose(V_whole, brute, rtol=1e-10)


def test_backward_segments_follow_the_smoothing_distribution():
    """Pieces started from the FFBSm marginals at their last step: their counts follow the marginal
    smoothing weights and their pairs the pairwise ones (the mean of ``x_{k+1}`` given ``x_k`` is
    ``xbar_k``; within 5 standard errors in every cell), with every rejection round used
    (``max_tries`` above the first round's) and with the exact draws alone (``max_tries=1`` with a
    low acceptance leaves many)."""
    model, data, est = _paper_estep("gaussian", 1, n=60, seed=3)
    X = est.filter.particles[:, 0, :, 0]
    p = torch.exp(est.smoother.log_weights[:, 0])
    M = 20000
    for tries in (13, 1):
        Js = backward_segments(
            model, data, est.filter, M, [0, 20, 35], 25, log_weights=est.smoother.log_weights,
            max_tries=tries, generator=torch.Generator().manual_seed(1),
        )[:, :, 0]  # (G, n, M)
        for g, a in enumerate((0, 20, 35)):
            J = Js[g]
            ones = torch.ones(25, M, dtype=torch.float64)
            counts = torch.zeros(25, 50, dtype=torch.float64).scatter_add_(1, J, ones)
            q = p[a : a + 25]
            z = torch.where(q > 1e-3, (counts / M - q) / torch.sqrt(q * (1 - q) / M), 0.0)
            assert float(z.abs().max()) < 5.0, (tries, g)
            nxt = torch.gather(X[a + 1 : a + 25], 1, J[1:])
            m = torch.zeros(24, 50, dtype=torch.float64).scatter_add_(1, J[:-1], nxt)
            m2 = torch.zeros(24, 50, dtype=torch.float64).scatter_add_(1, J[:-1], nxt * nxt)
            c = counts[:-1]
            spread = m2 / c.clamp(min=1) - (m / c.clamp(min=1)) ** 2
            seen = (c > 500) & (spread > 1e-8)  # next states all one particle: nothing to test
            mean = m[seen] / c[seen]
            se = torch.sqrt(spread[seen] / c[seen])
            xbar = est.smoother.next_mean[a : a + 24, 0, :, 0][seen]
            assert float(((mean - xbar) / se).abs().max()) < 5.0, (tries, g)
    with pytest.raises(ValueError, match="log_weights"):
        backward_segments(model, data, est.filter, 5, [0], 10)


def test_a_linear_in_parameters_module_whose_forward_differs_takes_the_general_path():
    """A ``LinearInParameters`` subclass whose ``forward`` is not ``offset + Phi theta`` (here shifted)
    gets the autograd Hessian and scores, not its features' closed forms: the same information as
    with every module treated as general."""
    from torch_nssm.datasets.paper import PaperObservation

    class Shifted(PaperObservation):
        def forward(self, x, u):
            return super().forward(x, u) + 0.1

    model, data, est = _paper_estep("student-t", 1, n=60)
    model = type(model)(model.f, Shifted(1.0), model.Rw, model.noise, model.x0_mean, model.x0_cov)
    gen = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    unc = U.observed_information(model, data, est, n_trajectories=20, generator=gen())
    original = U._linear_in_parameters
    try:
        U._linear_in_parameters = lambda module: False
        general = U.observed_information(model, data, est, n_trajectories=20, generator=gen())
    finally:
        U._linear_in_parameters = original
    np.testing.assert_allclose(unc.complete_information, general.complete_information, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(unc.score_variance, general.score_variance, rtol=1e-9, atol=1e-8)
