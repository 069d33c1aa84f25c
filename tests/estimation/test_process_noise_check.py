"""The check that the fitted process noise carries model error (estimation.process_noise_check)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import DTYPE, LinearF, LinearG

from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.core.noise import GaussianNoise
from torch_nssm.estimation.process_noise_check import WANDER_RATIO, process_noise_check


def _record(a: float, q: float, r: float, n: int, seed: int):
    """``x+ = a x + u + w`` (``w ~ N(0, q)``), ``y = x + v`` (``v ~ N(0, r)``) from ``x0 = 0``."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    x = np.zeros(n)
    for k in range(n - 1):
        x[k + 1] = a * x[k] + u[k] + np.sqrt(q) * rng.normal()
    y = x + np.sqrt(r) * rng.normal(size=n)
    t = lambda v: torch.as_tensor(v.reshape(n, 1))  # noqa: E731
    return SequenceBatch.from_sequences([t(u)], [t(y)])


def _model(a: float, q: float, r: float) -> StateSpaceModel:
    return StateSpaceModel(
        LinearF(np.array([[a]]), np.array([[1.0]])),
        LinearG(np.array([[1.0]]), np.array([[0.0]])),
        torch.tensor([[q]], dtype=DTYPE),
        GaussianNoise(torch.tensor([[r]], dtype=DTYPE)),
        torch.zeros(1, dtype=DTYPE),
        torch.eye(1, dtype=DTYPE),
    )


def test_wander_matches_the_stationary_variance():
    """For ``x+ = a x + w`` the output's deviation from the noise-free run settles at variance
    ``q / (1 - a^2)``; over a long record the robust scale of the wander is its s.d."""
    a, q = 0.5, 0.04
    data = _record(a, q, 1e-4, 4000, 0)
    check = process_noise_check(
        _model(a, q, 1e-4), data, n_trajectories=64, generator=torch.Generator().manual_seed(0)
    )
    assert check.wander == pytest.approx(np.sqrt(q / (1 - a**2)), rel=0.05)


def test_consistent_process_noise_passes_inflated_fails():
    a, q, r = 0.9, 0.01, 0.01
    data = _record(a, q, r, 2000, 1)
    gen = torch.Generator().manual_seed(0)
    right = process_noise_check(_model(a, q, r), data, generator=gen)
    # the truth: the free run's errors are the wander plus the measurement noise
    assert right.ratio < 1.0 and not right.absorbs and right.message is None
    # a process noise 100 times the truth predicts wander 10 times larger than the simulation's errors
    wrong = process_noise_check(_model(a, 100 * q, r), data, generator=gen)
    assert wrong.ratio > WANDER_RATIO and wrong.absorbs
    assert "process noise carries model error" in wrong.message and "fit_Rw=False" in wrong.message


def test_bad_settings():
    data = _record(0.5, 0.01, 0.01, 50, 0)
    with pytest.raises(ValueError, match="threshold"):
        process_noise_check(_model(0.5, 0.01, 0.01), data, threshold=0.0)
    with pytest.raises(ValueError, match="n_trajectories"):
        process_noise_check(_model(0.5, 0.01, 0.01), data, n_trajectories=1)
