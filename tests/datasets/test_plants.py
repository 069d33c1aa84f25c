"""Tests of the suite of plants (:mod:`torch_nssm.datasets`: pendulum, tanks, axis, oscillator,
wiener_hammerstein, bouc_wen) and of the suite's output-error baseline (``benchmarks/suite``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_nssm.datasets import (
    AXIS_START,
    AXIS_TRUE,
    PENDULUM_START,
    PENDULUM_TRUE,
    AxisLinearTransition,
    PlantData,
    axis_linear_parameters,
    axis_model,
    make_axis,
    make_pendulum,
    pendulum_model,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from suite.baselines import oe_fit, simulate  # noqa: E402
from suite.plants import PLANTS  # noqa: E402

#: Short records (the generators' defaults are the suite's lengths).
SHORT = {
    "pendulum": 300, "tanks": 300, "axis": 2000, "oscillator": 300, "wiener_hammerstein": 300,
    "bouc_wen": 300,
}


def _noise_free(name: str, n: int) -> PlantData:
    """The plant's record with neither process nor measurement noise (the axis keeps its encoder:
    the controller's force depends on it, the states do not)."""
    kwargs = {"Rw": 0.0} if name == "axis" else {"Rw": 0.0, "Rv": 0.0}
    return PLANTS[name].make(n, random_state=3, n_validation=50, **kwargs)


def _states(f, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    ut = torch.as_tensor(u)
    x = torch.as_tensor(x0)
    out = [x]
    with torch.no_grad():
        for k in range(len(u) - 1):
            x = f(x, ut[k])
            out.append(x)
    return torch.stack(out).numpy()


@pytest.mark.parametrize("name", list(PLANTS))
def test_user_model_reproduces_the_noise_free_record(name):
    """The f / g a user writes, at the true parameters, reproduce the generator's noise-free states and
    outputs from the record's first state (to rounding)."""
    data = _noise_free(name, SHORT[name])
    f, g = PLANTS[name].model(None)
    x = _states(f, data.u, data.x0)
    scale = np.abs(data.x).max(axis=0)
    np.testing.assert_allclose(x, data.x, rtol=0, atol=1e-10 * scale.max() + 1e-300)
    np.testing.assert_allclose(x / scale, data.x / scale, rtol=0, atol=1e-10)
    y = g(torch.as_tensor(x), torch.as_tensor(data.u)).detach().numpy()
    np.testing.assert_allclose(y, data.y_true, rtol=1e-12, atol=1e-12 * np.abs(data.y_true).max())
    if name != "axis":  # without measurement noise the record is its noise-free measurement
        np.testing.assert_array_equal(data.y, data.y_clean)
        np.testing.assert_allclose(data.y, data.y_true, rtol=0, atol=0)
    # the suite's simulation helper gives the same outputs
    y_sim = simulate(f, g, data.u, data.x0)
    np.testing.assert_allclose(y_sim, data.y_true, rtol=1e-12, atol=1e-12 * scale.max())


@pytest.mark.parametrize("name", list(PLANTS))
def test_generators_are_deterministic_and_records_consistent(name):
    plant = PLANTS[name]
    n = SHORT[name]
    a = plant.make(n, outlier_fraction=0.05, random_state=7, n_validation=200)
    b = plant.make(n, outlier_fraction=0.05, random_state=7, n_validation=200)
    c = plant.make(n, outlier_fraction=0.05, random_state=8, n_validation=200)
    clean = plant.make(n, outlier_fraction=0.0, random_state=7, n_validation=200)
    for field in ("u", "y", "x", "y_clean", "y_true", "outlier_mask", "x0_guess"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        np.testing.assert_array_equal(getattr(a.validation, field), getattr(b.validation, field))
    assert not np.array_equal(a.u, c.u)
    # shapes, finiteness
    assert isinstance(a, PlantData) and isinstance(a.validation, PlantData)
    assert a.validation.validation is None
    for d in (a, a.validation):
        assert d.y.shape == d.y_clean.shape == d.y_true.shape == (d.n_samples, 1)
        assert d.x0.shape == d.x0_guess.shape == (d.nx,)
        np.testing.assert_array_equal(d.x0, d.x[0])
        assert all(np.all(np.isfinite(v)) for v in (d.u, d.y, d.x, d.y_true))
    # outliers: exactly round(fraction * N), and only there does y differ from y_clean
    assert a.outlier_mask.sum() == round(0.05 * n) == a.params["n_outliers"]
    np.testing.assert_array_equal((a.y != a.y_clean).any(-1), a.outlier_mask)
    assert np.all(np.abs(a.y - a.y_clean)[a.outlier_mask] >= 2.0 * a.y_clean.std() - 1e-12)
    # the clean part and the validation record do not depend on the outliers
    np.testing.assert_array_equal(a.y_clean, clean.y_clean)
    np.testing.assert_array_equal(a.validation.y, clean.validation.y)
    assert not clean.outlier_mask.any() and not a.validation.outlier_mask.any()
    # the validation record is another input realisation of the same plant
    m = min(n, 200)
    assert not np.allclose(a.u[:m], a.validation.u[:m])
    assert a.validation.params == {**a.params, "x0": a.validation.params["x0"], "n_outliers": 0,
                                   "outlier_fraction": 0.0}


@pytest.mark.parametrize("name", list(PLANTS))
def test_starts_are_physically_sized_and_simulate(name):
    """Every start parameter is 30-50 % off the truth, and the start's free run stays finite."""
    plant = PLANTS[name]
    assert set(plant.start) == set(plant.true)
    for k, v in plant.true.items():
        assert 0.3 - 1e-9 <= abs(plant.start[k] / v - 1.0) <= 0.5 + 1e-9, k
    data = plant.make(SHORT[name], random_state=0, n_validation=50)
    f, g = plant.model(plant.start)
    assert np.all(np.isfinite(simulate(f, g, data.u, data.x0_guess)))
    assert {k for k, p in list(f.named_parameters()) + list(g.named_parameters())} == set(plant.true)


def test_axis_linear_form_equals_the_physical_form():
    torch.manual_seed(0)
    x = torch.randn(64, 2, dtype=torch.float64) * torch.tensor([0.05, 0.3], dtype=torch.float64)
    u = torch.randn(64, 1, dtype=torch.float64) * 20.0
    for params in (AXIS_TRUE, AXIS_START):
        f, _ = axis_model(params)
        lin, _ = axis_model(params, linear=True)
        assert isinstance(lin, AxisLinearTransition)
        with torch.no_grad():
            np.testing.assert_allclose(lin(x, u).numpy(), f(x, u).numpy(), rtol=1e-13, atol=1e-15)
            Phi, offset = lin.features(x, u)
            theta = torch.tensor(list(axis_linear_parameters(params).values()), dtype=torch.float64)
            by_features = (offset + Phi @ theta).numpy()
            np.testing.assert_allclose(by_features, f(x, u).numpy(), rtol=1e-13, atol=1e-15)
    data = make_axis(2000, random_state=1, n_validation=50)
    f, g = axis_model()
    lin, _ = axis_model(linear=True)
    y_lin, y = simulate(lin, g, data.u, data.x0), simulate(f, g, data.u, data.x0)
    np.testing.assert_allclose(y_lin, y, rtol=0, atol=1e-12)


def test_oe_baseline_recovers_the_pendulum():
    """scipy's OE least squares from the physically sized start recovers the true parameters and the
    first state on a short clean pendulum record without process noise."""
    data = make_pendulum(300, random_state=0, n_validation=50, Rw=0.0)
    f, g = pendulum_model(PENDULUM_START)
    res = oe_fit(f, g, data.u, data.y, data.x0_guess)
    assert res["status"] > 0 and not res["budget_exceeded"]
    for k, v in PENDULUM_TRUE.items():
        assert getattr(res["f"], k).item() == pytest.approx(v, rel=5e-3), k
    np.testing.assert_allclose(res["x0"], data.x0, atol=5e-3)
    # the residuals are the measurement noise (s.d. 0.01 rad)
    assert np.sqrt(2 * res["cost"] / data.n_samples) == pytest.approx(0.01, rel=0.15)


def test_pendulum_friction_is_the_gap_in_the_users_model():
    """``make_pendulum(friction=...)`` simulates RK4 of the pendulum plus the pivot's dry friction:
    one step of the user's ``f`` at the truth misses it, ``PendulumTransition(friction=...)``
    reproduces the states; ``friction=0`` is the plain record."""
    from torch_nssm.datasets.pendulum import PendulumTransition

    data = make_pendulum(300, random_state=0, n_validation=50, Rw=0.0, friction=1.0)
    x, u = torch.as_tensor(data.x), torch.as_tensor(data.u)
    f, _ = pendulum_model()
    with torch.no_grad():
        plain = (f(x[:-1], u[:-1]) - x[1:]).abs().max().item()
        exact = (PendulumTransition(friction=1.0)(x[:-1], u[:-1]) - x[1:]).abs().max().item()
    assert exact < 1e-12 < 1e-3 < plain
    plain_record = make_pendulum(50, random_state=1)
    np.testing.assert_array_equal(make_pendulum(50, random_state=1, friction=0.0).y, plain_record.y)
    with pytest.raises(ValueError, match="friction"):
        make_pendulum(100, friction=-1.0)


def test_generators_reject_bad_settings():
    with pytest.raises(ValueError, match="outlier_fraction"):
        make_pendulum(100, outlier_fraction=1.5)
    with pytest.raises(ValueError, match="n_validation"):
        make_pendulum(100, n_validation=0)
    with pytest.raises(ValueError, match="Rw"):
        make_pendulum(100, Rw=[-1.0, 0.0])
    with pytest.raises(ValueError, match="unknown keys"):
        make_pendulum(100, params={"length": 1.0})
    with pytest.raises(ValueError, match="quantum"):
        make_axis(100, quantum=-1.0)
