"""Tests of the starts of networks (distilled, simulation) and the linear blocks
(:mod:`torch_nssm.blocks`)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from torch_nssm import RobustNSSMEstimator, distilled_start
from torch_nssm.blocks.linear import LinearObservation, LinearTransition
from torch_nssm.blocks.neural import GreyBoxTransition, MLPObservation, MLPTransition
from torch_nssm.blocks.starts import DistilledStartInfo, distill
from torch_nssm.datasets import make_paper_example
from torch_nssm.models import PaperObservation, PaperTransition, true_model

torch.set_num_threads(1)
DTYPE = torch.float64


@pytest.fixture(scope="module")
def data():
    return make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=0)


def _neural_estimator(n_iter: int) -> RobustNSSMEstimator:
    return RobustNSSMEstimator(
        MLPTransition(1, 1, hidden=(16,), random_state=0),
        PaperObservation(0.5),
        x0_mean=[0.0],
        optimizer="adam",
        max_iter_mstep=50,
        learning_rate=1e-2,
        n_particles=100,
        n_iter=n_iter,
        tol=0,
        random_state=0,
    )


def _corr(pred, data) -> float:
    clean = ~data.outlier_mask
    return float(np.corrcoef(np.ravel(pred)[clean], data.y_clean[clean, 0])[0, 1])


# ---------------------------------------------------------------------- linear modules
def test_linear_transition_and_observation_match_matrices():
    gen = torch.Generator().manual_seed(0)
    A = torch.randn(3, 3, generator=gen, dtype=DTYPE)
    B = torch.randn(3, 2, generator=gen, dtype=DTYPE)
    f = LinearTransition(3, 2, A=A, B=B)
    x = torch.randn(4, 5, 3, generator=gen, dtype=DTYPE)
    u = torch.randn(4, 5, 2, generator=gen, dtype=DTYPE)
    torch.testing.assert_close(f(x, u), x @ A.T + u @ B.T)
    C = torch.randn(2, 3, generator=gen, dtype=DTYPE)
    D = torch.randn(2, 2, generator=gen, dtype=DTYPE)
    g = LinearObservation(3, 2, 2, C=C, D=D, d=[0.5, -1.0])
    torch.testing.assert_close(g(x, u), x @ C.T + u @ D.T + torch.tensor([0.5, -1.0], dtype=DTYPE))
    # without input, and with a bias
    f0 = LinearTransition(2, 0, A=0.7, bias=True)
    torch.testing.assert_close(f0(x[..., :2], u[..., :0]), 0.7 * x[..., :2])


def test_linear_transition_closed_form_recovers_matrices():
    gen = torch.Generator().manual_seed(1)
    A = torch.tensor([[0.8, 0.2], [-0.3, 0.5]], dtype=DTYPE)
    B = torch.tensor([[1.0], [-0.5]], dtype=DTYPE)
    x = torch.randn(200, 2, generator=gen, dtype=DTYPE)
    u = torch.randn(200, 1, generator=gen, dtype=DTYPE)
    f = LinearTransition(2, 1)
    f.solve_weighted_least_squares(x, u, x @ A.T + u @ B.T, torch.ones(200, dtype=DTYPE))
    torch.testing.assert_close(f.A.detach(), A)
    torch.testing.assert_close(f.B.detach(), B)
    # the feed-through of the observation is held fixed unless asked for
    g = LinearObservation(2, 1, 1)
    y = x[:, :1] * 2.0 + u * 3.0 + 1.0
    g.solve_weighted_least_squares(x, u, y, torch.ones(200, dtype=DTYPE))
    assert g.D.item() == 0.0
    g = LinearObservation(2, 1, 1, feedthrough=True)
    g.solve_weighted_least_squares(x, u, y, torch.ones(200, dtype=DTYPE))
    torch.testing.assert_close(g(x, u), y)


def test_linear_observation_offset_can_be_held_fixed(data):
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(200, 2, generator=gen, dtype=DTYPE)
    u = torch.randn(200, 1, generator=gen, dtype=DTYPE)
    y = x[:, :1] * 2.0 + 1.0
    w = torch.ones(200, dtype=DTYPE)
    g = LinearObservation(2, 1, 1, fit_offset=False)
    assert not g.d.requires_grad and g.C.requires_grad
    assert "fit_offset=False" in repr(g)
    g.solve_weighted_least_squares(x, u, y, w)
    assert g.d.item() == 0.0  # held, the rest fitted: C[0, 0] absorbs what it can
    g = LinearObservation(2, 1, 1, d=0.25, fit_offset=False)
    g.solve_weighted_least_squares(x, u, y, w)
    assert g.d.item() == 0.25
    g = LinearObservation(2, 1, 1)  # default: the offset is estimated
    g.solve_weighted_least_squares(x, u, y, w)
    torch.testing.assert_close(g.d.detach(), torch.tensor([1.0], dtype=DTYPE))
    # through an EM fit: the fitted copy keeps d = 0, the default moves it
    y_shifted = data.y[:120] + 2.0
    fitted = {}
    for fit_offset in (False, True):
        est = RobustNSSMEstimator(
            LinearTransition(1, 1), LinearObservation(1, 1, 1, fit_offset=fit_offset), x0_mean=[0.0],
            n_particles=20, n_iter=2, tol=0, random_state=0,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted[fit_offset] = est.fit(data.u[:120], y_shifted).g_
    assert fitted[False].d.item() == 0.0 and not fitted[False].d.requires_grad
    assert fitted[True].d.item() != 0.0


def test_linear_modules_reject_bad_shapes():
    with pytest.raises(ValueError, match="A must have shape"):
        LinearTransition(2, 1, A=np.ones((3, 3)))
    with pytest.raises(ValueError, match="B must be finite"):
        LinearTransition(1, 1, B=[[np.nan]])
    with pytest.raises(ValueError, match="C must have shape"):
        LinearObservation(2, 1, 1, C=np.ones((2, 2)))
    with pytest.raises(ValueError, match="nx"):
        LinearTransition(0, 1)


# ---------------------------------------------------------------------- distill
def test_distill_imitates_reference():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(400, 2, generator=gen, dtype=DTYPE)
    u = torch.randn(400, 1, generator=gen, dtype=DTYPE)
    ref = LinearTransition(2, 1, A=[[0.9, 0.1], [-0.2, 0.7]], B=[[1.0], [0.3]])
    f = MLPTransition(2, 1, hidden=(16,), random_state=0).fit_normalisation(x, u, x_next=ref(x, u).detach())
    before = ((f(x, u) - ref(x, u)) ** 2).mean().item()
    err = distill(f, ref, x, u, baseline=x)
    after = ((f(x, u) - ref(x, u)) ** 2).mean().item()
    assert err < 0.02
    assert after < 1e-3 * before
    # the reference is not changed
    torch.testing.assert_close(ref.A.detach(), torch.tensor([[0.9, 0.1], [-0.2, 0.7]], dtype=DTYPE))


def test_distill_errors():
    f = MLPTransition(1, 1, hidden=(4,))
    ref = LinearTransition(1, 1)
    x = np.zeros((5, 1))
    with pytest.raises(TypeError, match="reference"):
        distill(f, lambda x, u: x, x, x)
    with pytest.raises(ValueError, match="u must have shape"):
        distill(f, ref, x, np.zeros((4, 1)))
    with pytest.raises(ValueError, match="same shape"):
        distill(f, LinearObservation(1, 1, 2), x, x)
    with pytest.raises(ValueError, match="requires_grad"):
        distill(f.requires_grad_(False), ref, x, x)
    with pytest.raises(ValueError, match="max_iter"):
        distill(MLPTransition(1, 1), ref, x, x, max_iter=0)


# ---------------------------------------------------------------------- distilled_start
def test_distilled_start_beats_cold_start(data):
    """§4.1 data, 10 % outliers: 8 EM iterations of a residual MLP, warm versus cold.

    Measured (N = 300, L = 100, seeds 0): log-likelihood -290 warm vs -393 cold; free-run
    correlation with the clean outputs 0.78 warm, 0.27 cold, 0.76 for the true model.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(_neural_estimator(8), data.u, data.y, return_info=True)
        assert isinstance(info, DistilledStartInfo)
        assert (info.f_action, info.g_action) == ("distilled", "fitted")
        assert info.f_error < 0.05  # the MLP imitates the fitted linear model
        # a distilled network keeps the estimator's first stage ("auto": trained by simulation
        # error from this start); here EM alone from the distilled network is what is measured
        assert warm.first_stage == "auto"
        est_warm = warm.set_params(first_stage=None).fit(data.u, data.y)
        est_cold = _neural_estimator(8).set_params(first_stage=None).fit(data.u, data.y)  # the identity
        f, g = true_model(data)
        est_true = RobustNSSMEstimator(f, g, x0_mean=[0.0], n_iter=0, random_state=0).fit(data.u, data.y)
    ll_warm = est_warm.history_["log_likelihood"]
    ll_cold = est_cold.history_["log_likelihood"]
    # the warm fit starts near where the linear reference ended, and ends far above the cold one
    assert ll_warm[0] > ll_cold[0] + 300
    assert np.mean(ll_warm[-3:]) > np.mean(ll_cold[-3:]) + 50
    assert np.mean(ll_warm[-3:]) >= info.reference.log_likelihood_ - 10
    c_warm, c_cold = _corr(est_warm.predict(data.u), data), _corr(est_cold.predict(data.u), data)
    c_true = _corr(est_true.predict(data.u), data)
    assert c_warm > c_cold + 0.3
    assert c_warm > 0.9 * c_true


def test_distilled_start_sets_initial_values_and_leaves_estimator_alone(data):
    est = _neural_estimator(3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(est, data.u, data.y, n_iter=5, n_jitter=1, return_info=True)
    ref = info.reference
    np.testing.assert_allclose(warm.Rw_init, ref.Rw_)
    np.testing.assert_allclose(warm.Rv_init, ref.Rv_)
    np.testing.assert_allclose(warm.x0_mean, ref.x0_mean_)
    assert warm.dof_init == pytest.approx(ref.dof_)
    assert info.n_rows == 2 * 300
    # the normalisation buffers come from the smoothed states
    sm = ref.smooth(data.u, data.y).mean
    assert warm.f.x_mean.item() == pytest.approx(sm[:-1].mean(), rel=1e-6)
    assert warm.f.u_scale.item() == pytest.approx(data.u[:-1].std(), rel=1e-6)
    # the MLP now follows the linear model on the smoothed states
    x = torch.as_tensor(sm, dtype=DTYPE)
    u = torch.as_tensor(data.u, dtype=DTYPE)
    with torch.no_grad():
        gap = (warm.f(x, u) - ref.f_(x, u)).abs().max().item()
        spread = (ref.f_(x, u) - x).std().item()
    assert gap < 0.1 * spread
    # the user's estimator and modules are untouched: its MLP is still near the identity
    assert est.Rw_init is None and est.x0_cov is None
    with torch.no_grad():
        assert (est.f(x, u) - x).abs().max().item() < 1e-2
    assert warm.g is not est.g and warm.g.c.item() == pytest.approx(ref.g_.c.item())


def test_distilled_start_greybox_takes_physical_parameters(data):
    physical = PaperTransition(a=0.5, b=0.5)
    est = RobustNSSMEstimator(
        GreyBoxTransition(physical, 1, 1, hidden=(8,), random_state=0),
        PaperObservation(0.5),
        x0_mean=[0.0],
        n_particles=100,
        n_iter=2,
        random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(est, data.u, data.y, n_iter=10, return_info=True)
    assert info.f_action == "physical" and info.f_error is None
    assert warm.first_stage is None  # the grey box's start is done: EM refines it
    a, b = warm.f.physical.a.item(), warm.f.physical.b.item()
    assert a == pytest.approx(info.reference.f_.a.item())
    assert abs(a - 0.9) < 0.15 and abs(abs(b) - 1.0) < 0.2  # the fitted physics, not the guess
    x = torch.linspace(-3, 3, 7, dtype=DTYPE).unsqueeze(-1)
    u = torch.zeros(7, 1, dtype=DTYPE)
    with torch.no_grad():
        torch.testing.assert_close(warm.f.correction(x, u), torch.zeros_like(x))
    assert physical.a.item() == 0.5  # the user's physical module is not changed


def test_distilled_start_mlp_observation(data):
    """An MLP observation gets a linear reference and imitates it; its output scale is set."""
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5),
        MLPObservation(1, 0, 1, hidden=(8,), random_state=0),
        x0_mean=[0.0],
        n_particles=50,
        n_iter=2,
        random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(est, data.u, data.y, n_iter=3, return_info=True)
    assert (info.f_action, info.g_action) == ("fitted", "distilled")
    assert warm.first_stage is None  # only a distilled f is trained again by the first stage
    assert isinstance(info.reference.g, LinearObservation)
    assert info.g_error < 0.05
    assert warm.g.y_mean.item() == pytest.approx(np.median(data.y), abs=1e-2)  # torch: lower median
    assert isinstance(warm.f, PaperTransition) and warm.f.a.item() == pytest.approx(
        info.reference.f_.a.item()
    )


def test_distilled_start_errors(data):
    est = _neural_estimator(1)
    with pytest.raises(TypeError, match="estimator must be a RobustNSSMEstimator"):
        distilled_start("not an estimator", data.u, data.y)
    with pytest.raises(TypeError, match="reference_f"):
        distilled_start(est, data.u, data.y, reference_f=lambda x, u: x)
    with pytest.raises(ValueError, match="n_iter"):
        distilled_start(est, data.u, data.y, n_iter=0)
    with pytest.raises(ValueError, match="noise"):
        distilled_start(est, data.u, data.y, noise="cauchy")
    with pytest.raises(ValueError, match="n_jitter"):
        distilled_start(est, data.u, data.y, n_jitter=-1)
    with pytest.raises(ValueError, match="x0_mean"):
        distilled_start(est.set_params(x0_mean=None), data.u, data.y)
    with pytest.raises(ValueError, match="same number of records"):
        distilled_start(_neural_estimator(1), [data.u, data.u], [data.y])


def test_linear_blocks_forward_equals_features_times_theta():
    """LinearTransition/LinearObservation evaluate x A^T + u B^T (+ c) directly (the filter calls them
    at every step); that is the function features() @ theta that the closed-form M-step fits."""
    from torch_nssm.core.parametric import LinearInParameters
    from torch_nssm.starts import LinearObservation, LinearTransition

    gen = torch.Generator().manual_seed(0)
    modules = [
        LinearTransition(2, 1, bias=True),
        LinearTransition(3, 0),
        LinearObservation(2, 1, 3, feedthrough=True, d=[0.1, 0.2, 0.3]),
    ]
    for m in modules:
        with torch.no_grad():
            for p in m.parameters():
                p.add_(torch.randn(p.shape, generator=gen, dtype=p.dtype))
        x = torch.randn(4, 6, m.nx, generator=gen, dtype=DTYPE)
        u = torch.randn(4, 6, m.nu, generator=gen, dtype=DTYPE)
        with torch.no_grad():
            torch.testing.assert_close(m(x, u), LinearInParameters.forward(m, x, u), rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------- simulation_start
class _Position(torch.nn.Module):
    """``y = x`` (no parameters)."""

    def forward(self, x, u):
        return x


def _tanh_plant(n: int, seed: int, outliers: float = 0.0):
    """``x+ = 0.6 x + 0.8 tanh(1.5 u) + w`` (s.d. 0.02) from rest, ``y = x + v`` (s.d. 0.02), a share of
    the outputs shifted by +-(1-3)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    x = np.zeros(n)
    for k in range(n - 1):
        x[k + 1] = 0.6 * x[k] + 0.8 * np.tanh(1.5 * u[k]) + 0.02 * rng.normal()
    y = x + 0.02 * rng.normal(size=n)
    bad = rng.random(n) < outliers
    y[bad] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(1, 3, bad.sum())
    return u, y, x


def test_simulation_warm_start_then_em_beats_the_linear_reference():
    from torch_nssm import simulation_start
    from torch_nssm.estimation.neural_first_stage import NeuralFirstStageOptions

    u, y, _ = _tanh_plant(300, 0, outliers=0.05)
    est = RobustNSSMEstimator(
        MLPTransition(1, 1, hidden=(8,), random_state=0), _Position(), x0_mean=[0.0], optimizer="adam",
        max_iter_mstep=20, n_particles=50, n_iter=4, tol=0, random_state=0,
    )
    options = NeuralFirstStageOptions(horizon=20, max_horizon=40, max_iter=60, eval_every=20)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 300 samples for 33 parameters: said, and meant here
        warm, report = simulation_start(est, u, y, options=options, return_report=True)
    assert isinstance(warm, RobustNSSMEstimator) and warm is not est and not hasattr(warm, "f_")
    assert report.accepted and warm.first_stage is None
    assert not torch.equal(warm.f.net[-1].weight, est.f.net[-1].weight)  # trained; est is untouched
    assert warm.Rw_init.shape == (1, 1) and warm.Rv_init.shape == (1, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm.fit(u, y)
        linear = RobustNSSMEstimator(
            LinearTransition(1, 1), _Position(), x0_mean=[0.0], n_particles=50, n_iter=10, random_state=0
        ).fit(u, y)
    # the M-step of the trained network is never undone
    assert not warm.history_["rejected.f"].any()
    u_val, _, x_val = _tanh_plant(400, 1)
    rmse = lambda e: float(np.sqrt(np.mean((np.ravel(e.predict(u_val, x0=[0.0])) - x_val) ** 2)))  # noqa: E731
    # measured: 0.03 against the best linear model's 0.14
    assert rmse(warm) < 0.4 * rmse(linear)


def test_simulation_warm_start_checks_its_arguments():
    from torch_nssm import simulation_start

    u, y, _ = _tanh_plant(100, 0)
    with pytest.raises(TypeError, match="estimator"):
        simulation_start("not an estimator", u, y)
    est = RobustNSSMEstimator(MLPTransition(1, 1, hidden=(4,)), _Position(), x0_mean=[0.0])
    with pytest.raises(TypeError, match="options"):
        simulation_start(est, u, y, options={"horizon": 10})
    with pytest.raises(ValueError, match="x0_mean"):
        simulation_start(RobustNSSMEstimator(MLPTransition(1, 1), _Position()), u, y)


def test_first_stage_auto_trains_a_network_by_simulation_error():
    """One first stage for networks: ``first_stage="auto"`` runs inside ``fit`` the stage that
    ``simulation_start`` runs outside it, and the start policy treats it as a physical one."""
    from sklearn.base import clone

    from torch_nssm.estimation.neural_first_stage import NeuralFirstStageReport

    u, y, _ = _tanh_plant(200, 0, outliers=0.05)
    est = RobustNSSMEstimator(
        MLPTransition(1, 1, hidden=(8,), random_state=0), _Position(), x0_mean=[0.0], optimizer="adam",
        max_iter_mstep=20, n_particles=50, n_iter=2, tol=0, random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = clone(est).fit(u, y)
    stage = fitted.first_stage_
    assert isinstance(stage, NeuralFirstStageReport) and stage.accepted
    assert stage.explained > 0.9 and fitted.simulation_model_  # the start policy's simulation model
    assert not torch.equal(fitted.f_.net[-1].weight, fitted.f.net[-1].weight)  # f was trained, in a copy
    u_val, _, x_val = _tanh_plant(400, 1)
    rmse = float(np.sqrt(np.mean((np.ravel(fitted.predict(u_val, x0=[0.0])) - x_val) ** 2)))
    assert rmse < 0.08  # the untrained network (the random walk) is near 1
