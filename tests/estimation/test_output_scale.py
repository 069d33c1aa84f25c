"""A plant whose states and outputs are tiny (1e-5 of the usual units, variances ~1e-12) fits as the
same plant in the usual units: the estimates scale with the data under the default start (no
``x0_cov``: a unit prior would be 1e10 times too broad for such states).  And a fit whose every EM
run fails on a numerical error after a kept first stage keeps that start, with a warning."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import nn

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import PENDULUM_START, make_pendulum, pendulum_model
from torch_nssm.estimation import loop as loop_module

SCALE = 1e-5


class FirstOrder(nn.Module):
    """``x+ = a x + b u``."""

    def __init__(self, a: float, b: float):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(a, dtype=torch.float64))
        self.b = nn.Parameter(torch.tensor(b, dtype=torch.float64))

    def forward(self, x, u):
        return self.a * x + self.b * u


class Measured(nn.Module):
    """``y = x``."""

    def forward(self, x, u):
        return x


def _record(scale: float, n: int = 300):
    """``x+ = 0.9 x + scale u + w``, ``y = x + v`` (variances 0.01 and 0.04 times ``scale**2``)."""
    rng = np.random.default_rng(0)
    u = rng.standard_normal(n)
    w, v = 0.1 * rng.standard_normal(n), 0.2 * rng.standard_normal(n)
    x = np.zeros(n)
    for k in range(n - 1):
        x[k + 1] = 0.9 * x[k] + u[k] + w[k]
    return u, scale * x, scale * (x + v)


def _fit(scale: float):
    u, _, y = _record(scale)
    est = RobustNSSMEstimator(
        FirstOrder(0.6, 0.6 * scale), Measured(), x0_mean=[0.0], n_particles=100, n_iter=10, random_state=0
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return est.fit(u, y)


def test_tiny_states_and_outputs_give_the_same_relative_estimates():
    usual, tiny = _fit(1.0), _fit(SCALE)
    assert tiny.first_stage_.accepted and usual.first_stage_.accepted
    # the first stage's estimates (held by EM: a simulation model) agree to its finite differences'
    # resolution; the noise EM then follows its own particle path: a difference of 1e-7 in a and b
    # can flip one resampling decision, and the noise estimates differ by their Monte Carlo error
    # (0.65 % in Rw measured), not by the scale
    assert float(tiny.f_.a.detach()) == pytest.approx(float(usual.f_.a.detach()), rel=1e-5)
    assert float(tiny.f_.b.detach()) / SCALE == pytest.approx(float(usual.f_.b.detach()), rel=1e-5)
    assert float(usual.f_.a.detach()) == pytest.approx(0.9, abs=0.05)
    for name in ("Rw_", "Rv_"):
        assert np.all(np.isfinite(getattr(tiny, name)))
        assert getattr(tiny, name)[0, 0] / SCALE**2 == pytest.approx(getattr(usual, name)[0, 0], rel=2e-2)
    assert float(tiny.dof_) == pytest.approx(float(usual.dof_), rel=2e-2)


def test_em_failing_in_every_run_after_a_kept_first_stage_keeps_the_start(monkeypatch):
    d = make_pendulum(n_samples=300, outlier_fraction=0.0, random_state=0, n_validation=100)
    real = loop_module.m_step

    def ruined(models, *args, **kwargs):  # every M-step's Rw is NaN: EM's next E-step fails
        result = real(models, *args, **kwargs)
        result.models = [replace(m, Rw=m.Rw * torch.nan) for m in result.models]
        return result

    monkeypatch.setattr(loop_module, "m_step", ruined)
    f, g = pendulum_model(PENDULUM_START)
    est = RobustNSSMEstimator(f, g, x0_mean=list(d.x0_guess), n_particles=60, n_iter=5, random_state=0)
    with pytest.warns(RuntimeWarning, match="EM failed on a numerical error in every run") as caught:
        est.fit(d.u, d.y)  # no NumericalError: a fitted estimator
    assert not any("did not converge" in str(w.message) for w in caught)
    assert est.first_stage_.accepted and est.n_iter_ == 0
    assert len(est.history_["Rw"]) == 1  # the start, evaluated by one E-step
    np.testing.assert_array_equal(est.Rw_, est.history_["Rw"][0])
    for name in ("Rw_", "Rv_", "x0_mean_", "log_likelihood_", "outlier_weights_"):
        assert np.all(np.isfinite(getattr(est, name)))
    stage = {name: float(getattr(est.f_, name).detach()) for name in PENDULUM_START}
    assert stage != PENDULUM_START  # the first stage's f, not the given one
    assert np.isfinite(est.predict(d.validation.u)).all()
