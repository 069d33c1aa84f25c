"""Tests of the ready-made model modules against the generators of torch_nssm.datasets."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from torch_nssm.core.parametric import LinearInParameters
from torch_nssm.datasets import (
    ManipulatorConstants,
    make_gopaluni_example,
    make_huang_example,
    make_manipulator,
    make_paper_example,
    manipulator_transition_matrix,
)
from torch_nssm.models import (
    ManipulatorObservation,
    ManipulatorTransition,
    PaperObservation,
    PaperTransition,
    true_model,
)

DTYPE = torch.float64


def _t(a):
    return torch.as_tensor(np.asarray(a), dtype=DTYPE)


# ------------------------------------------------------------------------------------------
# Contract: shapes, parameters, dtype
# ------------------------------------------------------------------------------------------


def test_paper_modules_shapes_and_parameters():
    f, g = PaperTransition(0.3, -0.4), PaperObservation(2.0)
    assert isinstance(f, LinearInParameters) and isinstance(g, LinearInParameters)
    assert [n for n, _ in f.named_parameters()] == ["a", "b"]
    assert [n for n, _ in g.named_parameters()] == ["c"]
    torch.testing.assert_close(f.theta(), _t([0.3, -0.4]))
    x, u = torch.randn(7, 5, 1, dtype=DTYPE), torch.randn(7, 5, 1, dtype=DTYPE)
    fx, gx = f(x, u), g(x, u)
    assert fx.shape == (7, 5, 1) and gx.shape == (7, 5, 1)
    torch.testing.assert_close(fx, 0.3 * x - 0.4 * u)
    torch.testing.assert_close(gx, 2.0 * torch.cos(x))
    # leading dims broadcast: particles (L, 1) with one input (1,)
    torch.testing.assert_close(f(x[0], u[0, 0]), 0.3 * x[0] - 0.4 * u[0, 0])
    Phi, off = f.features(x, u)
    assert Phi.shape == (7, 5, 1, 2) and off.shape == (7, 5, 1)


def test_manipulator_modules_shapes_and_parameters():
    f, g = ManipulatorTransition(0.8, 1.2), ManipulatorObservation()
    assert isinstance(f, LinearInParameters)
    assert [n for n, _ in f.named_parameters()] == ["theta1", "theta2"]
    assert list(g.parameters()) == []
    x, u = torch.randn(3, 6, 4, dtype=DTYPE), torch.randn(3, 6, 1, dtype=DTYPE)
    assert f(x, u).shape == (3, 6, 4)
    torch.testing.assert_close(g(x, u), x[..., 2:])
    Phi, off = f.features(x, u)
    assert Phi.shape == (3, 6, 4, 2) and off.shape == (3, 6, 4)
    # the parameterless observation also accepts an empty input (nu = 0) and any leading dims
    assert g(torch.zeros(4, dtype=DTYPE), torch.zeros(0, dtype=DTYPE)).shape == (2,)


def test_dtype_and_to():
    f = PaperTransition(0.5, 0.5, dtype=torch.float32)
    assert f.a.dtype == torch.float32
    m = ManipulatorTransition(dtype=torch.float32)
    assert all(b.dtype == torch.float32 for b in m.buffers())
    m = m.to(torch.float64)
    assert m.theta1.dtype == torch.float64 and m.MinvE.dtype == torch.float64
    x, u = torch.randn(5, 4, dtype=DTYPE), torch.randn(5, 1, dtype=DTYPE)
    assert m(x, u).dtype == torch.float64


def test_gradients_flow():
    f = ManipulatorTransition(0.9, 1.1)
    x, u = torch.randn(10, 4, dtype=DTYPE), torch.randn(10, 1, dtype=DTYPE)
    f(x, u).pow(2).sum().backward()
    assert f.theta1.grad is not None and f.theta2.grad is not None
    g = PaperObservation(0.5)
    g(torch.randn(10, 1, dtype=DTYPE), torch.zeros(10, 1, dtype=DTYPE)).sum().backward()
    assert g.c.grad is not None


# ------------------------------------------------------------------------------------------
# The modules reproduce the generators' mean dynamics exactly
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        lambda: make_paper_example(
            Rw=0.0, Rv=0.0, outlier_fraction=0.0, a=0.7, b=-1.3, c=2.1, random_state=0
        ),
        lambda: make_huang_example(Rw=0.0, Rv=0.0, random_state=0),
        lambda: make_manipulator(
            Rw=0.0, Rv=0.0, outlier_fraction=0.0, theta=(0.8, 1.1), random_state=0
        ),
        lambda: make_manipulator(
            Rw=0.0,
            Rv=0.0,
            outlier_fraction=0.0,
            dt=0.1,
            constants=ManipulatorConstants(k1=12.0, d1=4.0, d2=1.0, alpha10=0.1),
            random_state=1,
        ),
    ],
)
def test_true_model_matches_noise_free_generator(make):
    """With the noise switched off the recorded states obey x_{k+1} = f(x_k, u_k), y_k = g(x_k)."""
    d = make()
    f, g = true_model(d)
    x, u = _t(d.x), _t(d.u)
    with torch.no_grad():
        torch.testing.assert_close(f(x[:-1], u[:-1]), x[1:], rtol=0, atol=1e-12)
        torch.testing.assert_close(g(x, u), _t(d.y_clean), rtol=0, atol=1e-12)
        # and a free simulation with the modules from x_0 reproduces the whole record
        xs = [x[0]]
        for k in range(d.n_samples - 1):
            xs.append(f(xs[-1], u[k]))
        torch.testing.assert_close(torch.stack(xs), x, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "gen", [make_paper_example, make_gopaluni_example, make_huang_example, make_manipulator]
)
def test_true_model_residuals_have_noise_statistics(gen):
    """With noise on, x_{k+1} - f(x_k, u_k) is white with covariance Rw (sampling error)."""
    d = gen(n_samples=4000, random_state=9)
    f, g = true_model(d)
    x, u = _t(d.x), _t(d.u)
    with torch.no_grad():
        w = (x[1:] - f(x[:-1], u[:-1])).numpy()
    Rw = np.asarray(d.params["Rw"])
    n = w.shape[0]
    for i in range(d.nx):
        assert abs(w[:, i].var() - Rw[i, i]) < 5 * Rw[i, i] * math.sqrt(2 / n)
        assert abs(w[:, i].mean()) < 5 * math.sqrt(Rw[i, i] / n)


def test_manipulator_module_matches_transition_matrix():
    f = ManipulatorTransition(0.7, 1.4, dt=0.1)
    x = torch.randn(8, 4, dtype=DTYPE)
    F = torch.linspace(-10, 10, 8, dtype=DTYPE).unsqueeze(-1)
    T = _t(manipulator_transition_matrix(F.numpy()[:, 0], dt=0.1, theta=(0.7, 1.4)))
    with torch.no_grad():
        torch.testing.assert_close(f(x, F), (T @ x.unsqueeze(-1)).squeeze(-1), rtol=0, atol=1e-13)


def test_true_model_unknown_name():
    d = make_paper_example(n_samples=5, random_state=0)
    bad = type(d)(d.u, d.y, d.x, d.y_clean, d.outlier_mask, d.params, "nonsense")
    with pytest.raises(ValueError, match="nonsense"):
        true_model(bad)


# ------------------------------------------------------------------------------------------
# Closed-form weighted least squares (paper eqs. 44-45, 48)
# ------------------------------------------------------------------------------------------


def _fit_f(f, d, weight=None):
    x, u = _t(d.x), _t(d.u)
    w = torch.ones(d.n_samples - 1, dtype=DTYPE) if weight is None else weight
    f.solve_weighted_least_squares(x[:-1], u[:-1], x[1:], w)
    return f


def test_wls_recovers_paper_parameters_noise_free():
    d = make_paper_example(
        Rw=0.0, Rv=0.0, outlier_fraction=0.0, a=0.9, b=1.0, c=1.0, random_state=1
    )
    f = _fit_f(PaperTransition(0.2, 0.2), d)
    assert f.a.item() == pytest.approx(0.9, abs=1e-9) and f.b.item() == pytest.approx(1.0, abs=1e-9)
    g = PaperObservation(0.2)
    g.solve_weighted_least_squares(_t(d.x), _t(d.u), _t(d.y), torch.ones(d.n_samples, dtype=DTYPE))
    assert g.c.item() == pytest.approx(1.0, abs=1e-9)


def test_wls_recovers_paper_parameters_noisy():
    d = make_paper_example(random_state=2)  # Rw = Rv = 0.1, 10% outliers in y
    f = _fit_f(PaperTransition(0.2, 0.2), d)
    # standard errors: a ~ 0.006, b ~ 0.014
    assert abs(f.a.item() - 0.9) < 0.04 and abs(f.b.item() - 1.0) < 0.07
    x, u = _t(d.x), _t(d.u)
    # outliers down-weighted to zero (the role of <lambda_k>): c as from clean data
    g = PaperObservation(0.2)
    weight = _t(~d.outlier_mask)
    g.solve_weighted_least_squares(x, u, _t(d.y), weight)
    assert abs(g.c.item() - 1.0) < 0.06
    keep = torch.as_tensor(~d.outlier_mask)
    g_clean = PaperObservation(0.2)
    g_clean.solve_weighted_least_squares(
        x[keep], u[keep], _t(d.y_clean)[keep], torch.ones(int(keep.sum()), dtype=DTYPE)
    )
    assert g.c.item() == pytest.approx(g_clean.c.item(), abs=1e-12)


def test_wls_matches_paper_formulas():
    """Eqs. (44)-(45) at the fixed point and eq. (48), with arbitrary weights."""
    d = make_paper_example(n_samples=300, random_state=4)
    rng = np.random.default_rng(0)
    wts = rng.uniform(0.0, 2.0, size=d.n_samples)
    x, u, y = d.x[:, 0], d.u[:, 0], d.y[:, 0]
    f = _fit_f(PaperTransition(0.0, 0.0), d, weight=_t(wts[:-1]))
    a, b = f.a.item(), f.b.item()
    w1, x0, x1, u0 = wts[:-1], x[:-1], x[1:], u[:-1]
    assert a == pytest.approx(np.sum(w1 * (x1 - b * u0) * x0) / np.sum(w1 * x0**2), rel=1e-9)
    assert b == pytest.approx(np.sum(w1 * (x1 - a * x0) * u0) / np.sum(w1 * u0**2), rel=1e-9)
    g = PaperObservation(0.0)
    g.solve_weighted_least_squares(_t(d.x), _t(d.u), _t(d.y), _t(wts))
    c_ref = np.sum(wts * y * np.cos(x)) / np.sum(wts * np.cos(x) ** 2)
    assert g.c.item() == pytest.approx(c_ref, rel=1e-9)


def test_wls_respects_fixed_parameter():
    d = make_paper_example(Rw=0.0, Rv=0.0, outlier_fraction=0.0, random_state=3)
    f = PaperTransition(0.5, 0.2)
    f.a.requires_grad_(False)
    _fit_f(f, d)
    assert f.a.item() == 0.5  # untouched
    x, u = d.x[:, 0], d.u[:, 0]
    b_ref = np.sum((x[1:] - 0.5 * x[:-1]) * u[:-1]) / np.sum(u[:-1] ** 2)
    assert f.b.item() == pytest.approx(b_ref, rel=1e-9)
    # all fixed: nothing moves
    g = PaperObservation(0.3)
    g.c.requires_grad_(False)
    g.solve_weighted_least_squares(_t(d.x), _t(d.u), _t(d.y), torch.ones(d.n_samples, dtype=DTYPE))
    assert g.c.item() == 0.3


def test_wls_recovers_manipulator_theta():
    # noise-free: exact
    d0 = make_manipulator(Rw=0.0, Rv=0.0, outlier_fraction=0.0, theta=(0.9, 1.15), random_state=5)
    f = _fit_f(ManipulatorTransition(0.5, 0.5), d0)
    assert f.theta1.item() == pytest.approx(0.9, abs=1e-8)
    assert f.theta2.item() == pytest.approx(1.15, abs=1e-8)
    # noisy, with the Rw^-1 metric of the M-step (docs/method.md §4-5)
    d = make_manipulator(random_state=6)
    prec = torch.linalg.inv(_t(d.params["Rw"]))
    f = ManipulatorTransition(0.5, 0.5)
    x, u = _t(d.x), _t(d.u)
    f.solve_weighted_least_squares(
        x[:-1], u[:-1], x[1:], torch.ones(d.n_samples - 1, dtype=DTYPE), prec
    )
    assert abs(f.theta1.item() - 1.0) < 0.06 and abs(f.theta2.item() - 1.0) < 0.04
    # one fixed
    f = ManipulatorTransition(0.5, 0.5)
    f.theta1.requires_grad_(False)
    f.solve_weighted_least_squares(
        x[:-1], u[:-1], x[1:], torch.ones(d.n_samples - 1, dtype=DTYPE), prec
    )
    assert f.theta1.item() == 0.5 and abs(f.theta2.item() - 1.0) < 0.04


def test_parameterless_observation_module():
    g = ManipulatorObservation()
    assert isinstance(g, nn.Module) and sum(p.numel() for p in g.parameters()) == 0
    assert g.to(torch.float32) is g  # no state to convert
    x = torch.randn(2, 3, 4, dtype=DTYPE)
    torch.testing.assert_close(g(x, torch.zeros(2, 3, 1, dtype=DTYPE)), x[..., 2:])


def _assert_frozen_equals_forward(module, x, u):
    """``module.frozen()`` at every step of inputs ``u`` ``(T, B, nu)``, through its ``step_inputs``
    where it has them (what the particle filter passes), equals ``forward`` bit for bit."""
    frozen = module.frozen()
    steps = frozen.step_inputs(u) if hasattr(frozen, "step_inputs") else None
    for k in range(u.shape[0]):
        expected = module(x, u[k].unsqueeze(-2).expand(*x.shape[:-1], u.shape[-1]))
        got = frozen(x, steps[k] if steps is not None else u[k].unsqueeze(-2).expand_as(expected))
        assert torch.equal(got, expected)


def test_frozen_paper_and_stacked_modules_equal_forward():
    """The paper's f and g, alone and stacked (one parameter vector per sequence), evaluate the
    same values through their per-pass evaluators as through ``forward``."""
    from torch_nssm.estimation.independent import StackedModule

    x = torch.randn(3, 7, 1, dtype=torch.float64)
    u = torch.randn(4, 3, 1, dtype=torch.float64)
    fs = [PaperTransition(0.9 - 0.1 * i, 0.7 + 0.2 * i) for i in range(3)]
    gs = [PaperObservation(1.0 + 0.3 * i) for i in range(3)]
    for module in (fs[1], gs[2], StackedModule(fs), StackedModule(gs)):
        frozen = module.frozen()
        assert frozen is not module and hasattr(frozen, "step_inputs")
        _assert_frozen_equals_forward(module, x, u)


@pytest.mark.parametrize("bias, nu", [(False, 2), (True, 1), (True, 0)])
def test_stacked_linear_blocks_evaluate_without_their_features(bias, nu):
    """Stacked ``LinearTransition`` / ``LinearObservation`` (``fit_independent``): the per-pass
    evaluator takes each sequence's matrices once and equals ``forward`` (and ``predict``, which
    builds the Kronecker features) to rounding."""
    from torch_nssm.blocks.linear import LinearObservation, LinearTransition
    from torch_nssm.estimation.independent import StackedModule

    g = torch.Generator().manual_seed(5)
    B, L, nx, p = 3, 6, 2, 3
    rand = lambda *shape: torch.randn(*shape, dtype=DTYPE, generator=g)  # noqa: E731
    fs = [LinearTransition(nx, nu, A=rand(nx, nx), B=rand(nx, nu).numpy(), bias=bias) for _ in range(B)]
    gs = [
        LinearObservation(nx, nu, p, C=rand(p, nx), D=rand(p, nu).numpy(), d=rand(p).numpy(),
                          feedthrough=True)
        for _ in range(B)
    ]
    if bias:
        for f in fs:
            f.c.data = rand(nx)
    x, u = rand(B, L, nx), rand(B, L, nu)
    for modules in (fs, gs):
        stacked = StackedModule(modules)
        frozen = stacked.frozen()
        expected = torch.stack([m(x[b], u[b]) for b, m in enumerate(modules)])
        torch.testing.assert_close(frozen(x, u), expected, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(stacked(x, u), expected, rtol=1e-12, atol=1e-12)
        theta = modules[0].theta()
        torch.testing.assert_close(modules[0].frozen_predict(theta)(x[0], u[0]),
                                   modules[0].predict(x[0], u[0], theta), rtol=1e-12, atol=1e-12)


def test_frozen_evaluator_equals_forward_and_respects_overrides():
    """``frozen()`` (the filter's per-pass evaluator) computes ``forward`` with the parameters as
    they were when it was made; a subclass with its own ``forward`` or a hook gets the module."""
    f = PaperTransition(0.9, 0.7)
    x = torch.randn(3, 7, 1, dtype=torch.float64)  # (B, L, nx) particles
    u = torch.randn(5, 3, 1, dtype=torch.float64)  # (T, B, nu) inputs of a pass
    _assert_frozen_equals_forward(f, x, u)

    class Scaled(PaperTransition):
        def forward(self, x, u):
            return 2.0 * super().forward(x, u)

    scaled = Scaled(0.9, 1.0)
    assert scaled.frozen() is scaled
    f.register_forward_hook(lambda module, args, out: out + 1.0)
    assert f.frozen() is f
