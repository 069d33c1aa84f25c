"""Continuous-time transitions: integrators against exact solutions, the closed-form (linear in the
parameters) forms against the integrators and the M-step's dispatch, neural ODEs, and the README's
pendulum fitted from its simulated record."""

from __future__ import annotations

import copy
import pickle
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.linalg import expm
from sklearn.base import clone
from torch import nn

from torch_nssm import ContinuousTimeTransition, LinearInParameters, RobustNSSMEstimator
from torch_nssm._ops import broadcast_leading
from torch_nssm.blocks import LinearContinuousTimeTransition, MLPDerivative, distill
from torch_nssm.blocks.linear import LinearObservation
from torch_nssm.datasets import ManipulatorConstants
from torch_nssm.estimation import mstep
from torch_nssm.estimation.first_stage import first_stage_applies
from torch_nssm.models import ManipulatorTransition

DT = torch.float64
A = np.array([[0.0, 1.0], [-4.0, -0.4]])  # a damped oscillator
B = np.array([[0.0], [2.0]])


class LinearODE(nn.Module):
    """``dx/dt = A x + B u``."""

    def __init__(self):
        super().__init__()
        self.A = nn.Parameter(torch.tensor(A, dtype=DT))
        self.B = nn.Parameter(torch.tensor(B, dtype=DT))

    def forward(self, x, u):
        return x @ self.A.T + u @ self.B.T


class PendulumLIP(LinearInParameters):
    """``d angle/dt = omega``, ``d omega/dt = -w2 sin(angle) - c omega + b u``: linear in (w2, c, b)."""

    def __init__(self, w2=4.0, c=0.3, b=2.0):
        super().__init__()
        self.w2, self.c, self.b = (nn.Parameter(torch.tensor(v, dtype=DT)) for v in (w2, c, b))

    def features(self, x, u):
        x, u = broadcast_leading(x, u)
        angle, omega = x[..., 0], x[..., 1]
        zero = torch.zeros_like(angle)
        Phi = torch.stack(
            [torch.stack([zero, zero, zero], -1), torch.stack([-torch.sin(angle), -omega, u[..., 0]], -1)], -2
        )
        return Phi, torch.stack([omega, zero], -1)


def exact_step(Ts: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The exact zero-order-hold step of ``dx/dt = A x + B u``: ``expm([[A, B], [0, 0]] Ts)``."""
    M = np.zeros((3, 3))
    M[:2, :2], M[:2, 2:] = A, B
    E = expm(M * Ts)
    return x @ E[:2, :2].T + u @ E[:2, 2:].T


def step_errors(method: str, substeps: list[int], Ts: float = 1.0, **kw) -> np.ndarray:
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(6, 2)), rng.normal(size=(6, 1))
    exact = exact_step(Ts, x, u)
    errors = []
    for n in substeps:
        f = ContinuousTimeTransition(LinearODE(), Ts, method, substeps=n, **kw)
        with torch.no_grad():
            out = f(torch.tensor(x, dtype=DT), torch.tensor(u, dtype=DT)).numpy()
        errors.append(np.abs(out - exact).max())
    return np.array(errors)


@pytest.mark.parametrize(
    "method, kw, low, high",
    [("rk4", {}, 3.7, 4.3), ("euler", {}, 0.8, 1.2), ("semi-implicit", {"velocities": [1]}, 0.8, 1.2)],
)
def test_order_against_the_matrix_exponential(method, kw, low, high):
    """Over one sample Ts = 1 taken in n steps of h = 1 / n, the error is O(h^order)."""
    substeps = [8, 16, 32, 64]
    errors = step_errors(method, substeps, **kw)
    slope = -np.polyfit(np.log(substeps), np.log(errors), 1)[0]
    assert low <= slope <= high, (slope, errors)
    if method == "rk4":
        assert errors[-1] < 1e-7


def test_rk4_against_solve_ivp_on_a_nonlinear_ode_batched():
    """Van der Pol with a forcing input, on a batch of particles (..., nx) with their own inputs."""

    class VanDerPol(nn.Module):
        def __init__(self):
            super().__init__()
            self.mu = nn.Parameter(torch.tensor(1.5, dtype=DT))

        def forward(self, x, u):
            p, v = x[..., 0], x[..., 1]
            return torch.stack([v, self.mu * (1 - p**2) * v - p + u[..., 0]], -1)

    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(3, 4, 2)), rng.normal(size=(3, 4, 1))
    Ts = 0.5
    f = ContinuousTimeTransition(VanDerPol(), Ts, substeps=25)
    with torch.no_grad():
        out = f(torch.tensor(x, dtype=DT), torch.tensor(u, dtype=DT)).numpy()
    for i in np.ndindex(3, 4):
        def rhs(t, s, uk=u[i][0]):
            return [s[1], 1.5 * (1 - s[0] ** 2) * s[1] - s[0] + uk]

        ref = solve_ivp(rhs, (0.0, Ts), x[i], method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
        np.testing.assert_allclose(out[i], ref, atol=2e-8)


def test_the_closed_form_is_chosen_where_it_applies():
    def make(**kw):
        return ContinuousTimeTransition(PendulumLIP(), 0.05, **kw)

    linear = [make(method="euler"), make(method="semi-implicit", velocities=[1])]
    generic = [
        make(),  # rk4
        make(method="euler", substeps=2),
        make(method="euler", closed_form=False),
        ContinuousTimeTransition(LinearODE(), 0.05, "euler"),  # rhs not LinearInParameters
    ]
    assert all(isinstance(f, LinearContinuousTimeTransition) for f in linear)
    assert not any(isinstance(f, LinearInParameters) for f in generic)
    assert all(isinstance(f, ContinuousTimeTransition) for f in linear + generic)
    f = linear[1]
    for copied in (copy.deepcopy(f), pickle.loads(pickle.dumps(f))):
        assert type(copied) is LinearContinuousTimeTransition and copied.velocities == (1,)
    # the estimated parameters are rhs's; Ts is neither a parameter nor a buffer
    assert [n for n, _ in f.named_parameters()] == ["rhs.w2", "rhs.c", "rhs.b"]
    assert not list(f.buffers()) and isinstance(f.Ts, float)
    torch.testing.assert_close(f.theta(), f.rhs.theta())
    est = RobustNSSMEstimator(f, LinearObservation(2, 1, 1))
    assert est.get_params()["f__rhs.w2"] == 4.0
    other = clone(est).set_params(**{"f__rhs.w2": 3.5})
    assert type(other.f) is LinearContinuousTimeTransition and other.f.rhs.w2.item() == 3.5
    assert f.rhs.w2.item() == 4.0


@pytest.mark.parametrize("method, kw", [("euler", {}), ("semi-implicit", {"velocities": [1]})])
def test_linear_form_equals_the_integrator(method, kw):
    f = ContinuousTimeTransition(PendulumLIP(), 0.1, method, **kw)
    generic = ContinuousTimeTransition(PendulumLIP(), 0.1, method, closed_form=False, **kw)
    x = torch.randn(5, 7, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    u = torch.randn(5, 7, 1, dtype=DT, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        Phi, offset = f.features(x, u)
        for theta in (f.theta(), torch.tensor([1.0, -0.5, 3.0], dtype=DT)):
            generic.rhs.set_theta(theta)
            torch.testing.assert_close(offset + Phi @ theta, generic(x, u), rtol=1e-13, atol=1e-13)
            torch.testing.assert_close(f.predict(x, u, theta), generic(x, u), rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(f.frozen()(x, u), f(x, u), rtol=1e-14, atol=1e-14)


def test_euler_of_the_manipulator_ode_is_the_manipulator_transition():
    """The library's discretised manipulator (forward Euler) is the Euler wrapper of its ODE."""
    constants = ManipulatorConstants()
    MinvE, MinvK0, MinvK1 = (torch.as_tensor(m, dtype=DT) for m in constants.continuous_blocks())

    class ManipulatorODE(LinearInParameters):
        """x = [dphi1, dphi2, phi1, phi2]: d dphi/dt = acc (offset), d phi_i/dt = theta_i dphi_i."""

        def __init__(self):
            super().__init__()
            self.theta1 = nn.Parameter(torch.tensor(0.7, dtype=DT))
            self.theta2 = nn.Parameter(torch.tensor(1.3, dtype=DT))

        def features(self, x, u):
            x, u = broadcast_leading(x, u)
            vel, ang = x[..., :2], x[..., 2:]
            acc = -(vel @ MinvE.T) - (ang @ MinvK0.T) - u[..., :1] * (ang @ MinvK1.T)
            Phi = x.new_zeros(x.shape[:-1] + (4, 2))
            Phi[..., 2, 0], Phi[..., 3, 1] = vel[..., 0], vel[..., 1]
            return Phi, torch.cat([acc, torch.zeros_like(ang)], -1)

    dt = 0.01
    f = ContinuousTimeTransition(ManipulatorODE(), dt, "euler")
    ref = ManipulatorTransition(0.7, 1.3, dt=dt, constants=constants)
    x = torch.randn(9, 4, dtype=DT, generator=torch.Generator().manual_seed(2))
    u = torch.randn(9, 1, dtype=DT, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        for got, want in zip(f.features(x, u), ref.features(x, u)):
            torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(f(x, u), ref(x, u), rtol=1e-14, atol=1e-14)
    # semi-implicit Euler: the velocity rows hold no parameter, so it is linear too
    semi = ContinuousTimeTransition(ManipulatorODE(), dt, "semi-implicit", velocities=[0, 1])
    assert isinstance(semi, LinearInParameters)
    Phi, offset = semi.features(x, u)
    torch.testing.assert_close(offset + Phi @ semi.theta(), semi(x, u).detach(), rtol=1e-13, atol=1e-13)


def test_semi_implicit_closed_form_says_when_rhs_does_not_fit_it():
    class Bilinear(LinearInParameters):
        """d q/dt = a v^2 (not affine in v), d v/dt = b u."""

        def __init__(self):
            super().__init__()
            self.a = nn.Parameter(torch.tensor(0.5, dtype=DT))
            self.b = nn.Parameter(torch.tensor(2.0, dtype=DT))

        def features(self, x, u):
            x, u = broadcast_leading(x, u)
            zero = torch.zeros_like(x[..., 0])
            Phi = torch.stack(
                [torch.stack([x[..., 1] ** 2, zero], -1), torch.stack([zero, u[..., 0]], -1)], -2
            )
            return Phi, torch.zeros_like(x)

    f = ContinuousTimeTransition(Bilinear(), 0.1, "semi-implicit", velocities=[1])
    x, u = torch.ones(4, 2, dtype=DT), torch.ones(4, 1, dtype=DT)
    with pytest.raises(ValueError, match="closed_form=False"):
        f.features(x, u)
    generic = ContinuousTimeTransition(Bilinear(), 0.1, "semi-implicit", velocities=[1], closed_form=False)
    assert generic(x, u).shape == (4, 2)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="velocities"):
        ContinuousTimeTransition(PendulumLIP(), 0.1, "semi-implicit")
    with pytest.raises(ValueError, match="velocities applies"):
        ContinuousTimeTransition(LinearODE(), 0.1, "rk4", velocities=[1])
    with pytest.raises(ValueError, match="Ts"):
        ContinuousTimeTransition(LinearODE(), 0.0)
    with pytest.raises(ValueError, match="method"):
        ContinuousTimeTransition(LinearODE(), 0.1, "rk45")
    with pytest.raises(ValueError, match="substeps"):
        ContinuousTimeTransition(LinearODE(), 0.1, substeps=0)
    with pytest.raises(TypeError, match="rhs"):
        ContinuousTimeTransition(lambda x, u: x, 0.1)
    f = ContinuousTimeTransition(LinearODE(), 0.1, "semi-implicit", velocities=[2])
    with pytest.raises(ValueError, match="beyond the state dimension"):
        f(torch.zeros(3, 2, dtype=DT), torch.zeros(3, 1, dtype=DT))


def _m_step_solvers(monkeypatch) -> list[str]:
    """Record which M-step each module of a fit takes ("closed" or "gradient")."""
    calls: list[str] = []
    closed, gradient = mstep._closed_form, mstep.fit_weighted_regression

    def closed_spy(modules, *args, **kwargs):
        calls.append("closed")
        return closed(modules, *args, **kwargs)

    def gradient_spy(module, *args, **kwargs):
        calls.append("gradient")
        return gradient(module, *args, **kwargs)

    monkeypatch.setattr(mstep, "_closed_form", closed_spy)
    monkeypatch.setattr(mstep, "fit_weighted_regression", gradient_spy)
    return calls


def test_the_m_step_dispatch_and_its_solution(monkeypatch):
    """The Euler form takes the closed-form M-step; its solution is the weighted least-squares one
    that the gradient solver finds for the same transition without the closed form."""
    calls = _m_step_solvers(monkeypatch)
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, size=(120, 1))
    y = np.sin(np.arange(120) / 8.0)[:, None] + 0.05 * rng.normal(size=(120, 1))
    solutions = {}
    for closed_form in (True, False):
        f = ContinuousTimeTransition(PendulumLIP(w2=3.0, c=0.5, b=1.0), 0.1, "euler", closed_form=closed_form)
        g = LinearObservation(2, 1, 1, C=[[1.0, 0.0]], fit_offset=False).requires_grad_(False)
        est = RobustNSSMEstimator(
            f, g, x0_mean=[0.0, 0.0], n_particles=30, n_iter=1, first_stage=None, fit_Rw=True,
            max_iter_mstep=200, random_state=0,
        )
        calls.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(u, y)
        assert calls[0] == ("closed" if closed_form else "gradient")  # f's update (g has no free parameter)
        assert isinstance(est.f_, LinearContinuousTimeTransition) == closed_form
        solutions[closed_form] = est.f_.rhs.theta().detach().numpy()
    np.testing.assert_allclose(solutions[True], solutions[False], rtol=1e-5)


def test_a_neural_ode_through_the_wrapper():
    """An MLP derivative starts near x' = x, is not a first-stage model (a network), takes its
    normalisation through the wrapper and learns a linear ODE's sample map."""
    mlp = MLPDerivative(2, 1, hidden=(16,), random_state=0)
    f = ContinuousTimeTransition(mlp, 0.1)
    x = torch.randn(200, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    u = torch.randn(200, 1, dtype=DT, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert float((f(x, u) - x).abs().max()) < 1e-2
    assert not first_stage_applies(SimpleNamespace(f=f, g=LinearObservation(2, 1, 1)))
    reference = ContinuousTimeTransition(LinearODE(), 0.1, substeps=4)
    with torch.no_grad():
        x_next = reference(x, u)
    f.fit_normalisation(x.numpy(), u.numpy(), x_next=x_next.numpy())
    scale = ((x_next - x) / 0.1).std(0, correction=0)
    np.testing.assert_allclose(mlp.out_scale.numpy(), scale.numpy(), rtol=1e-9)
    error = distill(f, reference, x, u, baseline=x, max_iter=300)
    assert error < 0.05  # relative RMS error of the increments
    with pytest.raises(TypeError, match="fit_normalisation"):
        reference.fit_normalisation(x.numpy())


def test_distilled_start_of_a_neural_ode():
    """distilled_start sets the MLP derivative's normalisation through the wrapper and distils
    the transition from the reference linear model."""
    from torch_nssm import distilled_start
    from torch_nssm.datasets import make_paper_example
    from torch_nssm.models import PaperObservation

    data = make_paper_example(n_samples=150, random_state=0)
    f = ContinuousTimeTransition(MLPDerivative(1, 1, hidden=(8,), random_state=0), 1.0)
    est = RobustNSSMEstimator(f, PaperObservation(1.0), x0_mean=[0.0], n_particles=30, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        warm, info = distilled_start(est, data.u, data.y, n_iter=3, distill_iter=100, return_info=True)
    assert info.f_action == "distilled" and info.f_error < 0.1
    assert warm.f.rhs.out_scale.item() != 1.0  # the increments' scale, not the default
    assert est.f.rhs.out_scale.item() == 1.0  # the user's module is not changed


# the README's example ("Continuous-time models"), as written there
class Pendulum(nn.Module):  # dx/dt = F(x, u), x = [angle, angular velocity]
    def __init__(self, w2=5.0, c=0.5, b=1.0):
        super().__init__()
        self.w2, self.c, self.b = (nn.Parameter(torch.tensor(v)) for v in (w2, c, b))

    def forward(self, x, u):
        angle, omega = x[..., 0], x[..., 1]
        return torch.stack([omega, -self.w2 * torch.sin(angle) - self.c * omega + self.b * u[..., 0]], -1)


def test_the_readme_pendulum_recovers_its_physical_parameters():
    """Simulated in continuous time (exact ODE solution, a random torque, a noisy angle sensor with
    glitches), fitted through RK4 with the estimator's defaults (fewer particles and iterations):
    each physical parameter within 3 standard errors of the truth, and the standard errors small
    enough for that to mean something (measured: within 0.83 of them on seeds 0-3)."""
    from torch_nssm.datasets import make_continuous_pendulum

    data = make_continuous_pendulum(random_state=0)  # 300 samples of the angle, Ts = 0.05 s, 2.5 % glitches
    f = ContinuousTimeTransition(Pendulum(), Ts=0.05)  # RK4 over each sample, u held
    g = LinearObservation(2, 1, 1, C=[[1.0, 0.0]], fit_offset=False).requires_grad_(False)  # y = angle
    n = torch.get_num_threads()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ConvergenceWarning after 25 iterations
        est = RobustNSSMEstimator(f, g, x0_mean=[0.0, 0.0], n_particles=50, n_iter=25, random_state=0)
        est.fit(data.u, data.y)
        se = est.standard_errors_
    assert torch.get_num_threads() == n
    for name in ("w2", "c", "b"):
        value, truth, error = getattr(est.f_.rhs, name).item(), data.params[name], se[f"f.rhs.{name}"]
        assert abs(value - truth) < 3 * error, (name, value, truth, error)
        assert error < 0.5 * truth, (name, error)
    assert se["f.rhs.w2"] < 0.1 * data.params["w2"]
