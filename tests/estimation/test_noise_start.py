"""A simulation model's starting process noise: the walk up the ladder of scales, against the exact
log-likelihood of a linear-Gaussian model (Kalman filter)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import DTYPE, make_linear_system
from reference import kalman_filter, simulate_linear

from torch_nssm.core.model import SequenceBatch
from torch_nssm.estimation import noise_start
from torch_nssm.estimation.noise_start import LADDER_TOP, likeliest_process_noise


@pytest.fixture(scope="module")
def system_and_data():
    sysm = make_linear_system()
    rng = np.random.default_rng(1)
    u = rng.normal(size=(300, 1))
    _, y = simulate_linear(*sysm.matrices(), u, rng)
    data = SequenceBatch.from_sequences([torch.as_tensor(u, dtype=DTYPE)], [torch.as_tensor(y, dtype=DTYPE)])
    return sysm, u, y, data


def _exact(sysm, u, y, Q) -> float:
    A, B, C, D, _, R, m0, P0 = sysm.matrices()
    return kalman_filter(A, B, C, D, Q, R, m0, P0, u, y).log_likelihood


def _exact_walk(sysm, u, y, Q0) -> int:
    k = 0
    while k < LADDER_TOP and _exact(sysm, u, y, Q0 * 10.0 ** (k + 1)) > _exact(sysm, u, y, Q0 * 10.0**k):
        k += 1
    return k


@pytest.mark.parametrize("scale", [1e-3, 1e-2])
def test_a_start_too_small_is_raised_where_the_exact_likelihood_says(system_and_data, scale):
    sysm, u, y, data = system_and_data
    model = sysm.model()
    Q0 = sysm.Q * scale
    Rw, ladder = likeliest_process_noise(replace(model, Rw=torch.as_tensor(Q0, dtype=DTYPE)), data, seed=0)
    k = _exact_walk(sysm, u, y, Q0)
    assert k >= 1  # the exact likelihood grows from the start: the walk must go up
    assert ladder.factor == 10.0**k
    torch.testing.assert_close(Rw, torch.as_tensor(Q0 * 10.0**k, dtype=DTYPE))
    for j, score in ladder.log_likelihoods.items():  # each rung: the mean of the replicas' estimates,
        exact = _exact(sysm, u, y, Q0 * 10.0**j)  # the log of an unbiased estimate: biased low
        assert exact - 15.0 < score < exact + 2.0


def test_a_start_above_the_likeliest_scale_is_kept(system_and_data):
    sysm, u, y, data = system_and_data
    model = replace(sysm.model(), Rw=torch.as_tensor(sysm.Q * 3.0, dtype=DTYPE))
    assert _exact(sysm, u, y, sysm.Q * 30.0) < _exact(sysm, u, y, sysm.Q * 3.0)
    Rw, ladder = likeliest_process_noise(model, data, seed=0)
    assert ladder.factor == 1.0 and list(ladder.log_likelihoods) == [0, 1]
    torch.testing.assert_close(Rw, model.Rw)


def test_a_degenerate_rung_ranks_below_a_steady_one(system_and_data, monkeypatch):
    """The score is the mean over replicas: one collapsed replica (a degenerate filter) pulls a
    rung down, even when the others are the best estimates of all."""
    sysm, u, y, data = system_and_data
    model = replace(sysm.model(), Rw=torch.as_tensor(sysm.Q * 1e-2, dtype=DTYPE))
    real = noise_start.particle_filter

    def filter_with_a_collapse(m, batch, n_particles, generator):
        out = real(m, batch, n_particles, generator=generator)
        if float(m.Rw[0, 0] / model.Rw[0, 0]) > 5.0:  # rung 1: one replica collapses, the others gain 50
            ll = out.log_likelihood + 50.0
            ll[0] = -1e4
            out = replace(out, log_likelihood=ll)
        return out

    monkeypatch.setattr(noise_start, "particle_filter", filter_with_a_collapse)
    _, ladder = likeliest_process_noise(model, data, seed=0)
    assert ladder.factor == 1.0 and ladder.log_likelihoods[1] < ladder.log_likelihoods[0]


def test_one_model_per_record_scores_the_same_rungs(system_and_data):
    """Independent fits (``Rw`` with a batch dimension) run the replicas one after another."""
    sysm, u, y, data = system_and_data
    Q0 = torch.as_tensor(sysm.Q * 1e-3, dtype=DTYPE)
    two = SequenceBatch(data.u.repeat(1, 2, 1), data.y.repeat(1, 2, 1), data.lengths.repeat(2))
    shared = replace(sysm.model(), Rw=Q0)
    batched = replace(shared, Rw=Q0.expand(2, *Q0.shape).clone())
    _, a = likeliest_process_noise(shared, two, seed=0)
    Rw, b = likeliest_process_noise(batched, two, seed=0)
    assert a.factor == b.factor and Rw.shape == (2, 2, 2)
    for k in a.log_likelihoods:
        assert a.log_likelihoods[k] == pytest.approx(b.log_likelihoods[k], abs=10.0)
