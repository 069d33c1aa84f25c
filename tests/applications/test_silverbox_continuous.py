"""The continuous-time Duffing oscillator of the Silverbox example (``examples/silverbox/models.py``,
``DuffingODE``) and the comparison script's simulator (``examples/silverbox/continuous_time.py``).

No data needed: the models against each other and against the library's transitions.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_nssm import ContinuousTimeTransition, LinearInParameters

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "examples"))

from silverbox.continuous_time import TS_MS, _simulate, transition  # noqa: E402
from silverbox.study import DuffingTransition  # noqa: E402

DT = torch.float64
COEF = dict(k1=-0.3, d=-0.05, b=0.1, k2=0.02, k3=-0.1, c=0.01, e=0.0)


def test_semi_implicit_euler_of_the_ode_is_the_discrete_duffing():
    """One semi-implicit Euler step of DuffingODE.from_discrete(coef, Ts) is DuffingTransition(coef)
    with e = 0, the discrete velocity being Ts times dy/dt."""
    f = transition("semi-implicit", COEF)
    assert isinstance(f, LinearInParameters)  # the closed-form M-step
    x = torch.randn(6, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    u = torch.randn(6, 1, dtype=DT, generator=torch.Generator().manual_seed(1))
    scale = torch.tensor([1.0, TS_MS], dtype=DT)
    with torch.no_grad():
        discrete = DuffingTransition(**COEF)(x, u)
        torch.testing.assert_close(f(x / scale, u) * scale, discrete, rtol=1e-13, atol=1e-14)
        Phi, offset = f.features(x, u)
        torch.testing.assert_close(offset + Phi @ f.theta(), f(x, u), rtol=1e-13, atol=1e-14)
    ode = f.rhs
    ph = ode.physical()
    assert ph["m"] == pytest.approx(1 / ode.b.item())
    assert ph["f0_hz"] == pytest.approx(1e3 * np.sqrt(ode.k_m.item()) / (2 * np.pi))
    # forward is features @ theta
    with torch.no_grad():
        Phi, offset = ode.features(x, u)
        torch.testing.assert_close(ode(x, u), offset + Phi @ ode.theta(), rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("model", ["discrete", "semi-implicit", "rk4"])
def test_the_scripts_simulator_is_the_modules_free_run(model):
    f = transition(model, COEF)
    theta = (f if model == "discrete" else f.rhs).theta().detach().numpy()
    u = np.random.default_rng(0).normal(size=60)
    x0 = np.array([0.1, 0.02])
    state = torch.tensor(x0, dtype=DT).unsqueeze(0)
    ys = []
    with torch.no_grad():
        for uk in u:
            ys.append(state[0, 0].item())
            state = f(state, torch.tensor([[uk]], dtype=DT))
    np.testing.assert_allclose(_simulate(model, theta, x0, u), ys, rtol=1e-12, atol=1e-14)
    assert isinstance(f, ContinuousTimeTransition) == (model != "discrete")
