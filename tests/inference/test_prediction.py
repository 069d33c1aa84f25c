"""The prediction loops (free run, simulation, divergence) against the plain per-step recursion.

:func:`torch_nssm.inference.prediction._run` evaluates ``f`` through the particle filter's evaluator
(parameters gathered once) and stacks blocks of steps into its output; the values must be those of
one ``model.transition`` call a step, to the last bit (the same arithmetic), across block borders.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from conftest import nonlinear_model, paper_model

from torch_nssm.core.parametric import LinearInParameters
from torch_nssm.inference import prediction
from torch_nssm.inference.filtering import sample_initial_state
from torch_nssm.models import PaperObservation, PaperTransition

DTYPE = torch.float64


class TwoStateF(LinearInParameters):
    """``f(x, u) = [a0 x0 + a1 x1, a2 x0 + a3 u]`` through ``features`` (the base class's evaluation)."""

    def __init__(self):
        super().__init__()
        self.A = torch.nn.Parameter(torch.tensor([0.5, 0.1, -0.2, 0.6], dtype=DTYPE))

    def features(self, x, u):
        z = torch.zeros_like(x[..., :1])
        rows = [torch.cat([x, z, z], -1), torch.cat([z, z, x[..., :1], u], -1)]
        return torch.stack(rows, -2), torch.zeros_like(x)


def _models():
    paper = paper_model()
    return {
        "paper-closed-form": dataclasses.replace(
            paper, f=PaperTransition(0.93, 1.1), g=PaperObservation(0.8)
        ),
        "paper-plain-module": paper,
        "nonlinear-2-state": nonlinear_model(),
        "linear-in-parameters-2-state": dataclasses.replace(nonlinear_model(), f=TwoStateF()),
    }


def _reference_states(model, x, u, chol_w_t=None, generator=None):
    """``x_{k+1} = model.transition(x_k, u_k)`` (+ one normal draw a step), one step at a time."""
    states = []
    for k in range(u.shape[0]):
        states.append(x)
        if k + 1 < u.shape[0]:
            mean = model.transition(x, u[k])
            if chol_w_t is not None:
                mean = mean + torch.randn(x.shape, dtype=x.dtype, generator=generator) @ chol_w_t
            x = mean
    return torch.stack(states)


@pytest.fixture(autouse=True)
def _small_blocks(monkeypatch):
    monkeypatch.setattr(prediction, "BLOCK", 7)  # T = 30 crosses four block borders


def _inputs(T=30, B=3):
    return torch.randn(T, B, 1, dtype=DTYPE, generator=torch.Generator().manual_seed(T + B))


@pytest.mark.parametrize("name", list(_models()))
@pytest.mark.parametrize("T", [1, 7, 30])
def test_free_run_is_the_per_step_recursion(name, T):
    model = _models()[name]
    u = _inputs(T)
    with torch.no_grad():
        ref = _reference_states(model, model.per_sequence("x0_mean", 3).unsqueeze(1), u)[:, :, 0]
        states, outputs = prediction.free_run(model, u)
        assert torch.equal(states, ref)
        assert torch.equal(outputs, model.g(ref, u))


@pytest.mark.parametrize("name", ["paper-closed-form", "nonlinear-2-state"])
def test_simulate_is_the_per_step_recursion(name):
    model = _models()[name]
    u = _inputs()
    gen = torch.Generator().manual_seed(5)
    states, outputs = prediction.simulate(model, u, 4, gen)
    gen = torch.Generator().manual_seed(5)
    with torch.no_grad():
        chol_w_t = torch.linalg.cholesky(model.per_sequence("Rw", 3)).transpose(-1, -2)
        ref = _reference_states(model, sample_initial_state(model, 3, 4, gen), u, chol_w_t, gen)
        mean = model.observation(ref, u)
        ref_outputs = mean + model.noise.sample(mean.shape[:-1], generator=gen)
    assert torch.equal(states, ref)
    assert torch.equal(outputs, ref_outputs)


def test_k_step_ahead_prior_is_the_per_step_recursion():
    """Horizons beyond the record: every prediction is the prior propagated with process noise."""
    model = _models()["paper-closed-form"]
    u = _inputs(12)
    particles = torch.zeros(12, 3, 5, 1, dtype=DTYPE)  # only its shape is read for h >= T
    filt = type("F", (), {"particles": particles})()
    pred = prediction.k_step_ahead(model, u, filt, 20, torch.Generator().manual_seed(2))
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        chol_w_t = torch.linalg.cholesky(model.per_sequence("Rw", 3)).transpose(-1, -2)
        x = _reference_states(model, sample_initial_state(model, 3, 5, gen), u, chol_w_t, gen)
        ref = torch.stack([model.observation(x[t], u[t]).mean(-2) for t in range(12)])
    assert torch.equal(pred, ref)


def test_divergence_stops_at_the_first_step_outside_across_blocks():
    """``x_{k+1} = 1.5 x_k + u_k`` from 1 with u = 0 leaves |x| <= 1.5^k - 1/2 first at step k."""
    model = dataclasses.replace(_models()["paper-closed-form"], x0_mean=torch.ones(1, dtype=DTYPE))
    model.f.a.data.fill_(1.5)
    u = torch.zeros(40, 1, 1, dtype=DTYPE)
    for k in (1, 6, 7, 8, 20):  # inside the first block, at its end, at the next one's start, later
        assert prediction.divergence(model, u, 1.5**k - 0.5) == k
    assert prediction.divergence(model, u, 1.5**20 - 0.5, max_steps=20) is None  # step 20 not simulated
    model.f.a.data.fill_(math.nan)
    assert prediction.divergence(model, u, 1e6) == 1  # not finite


def test_outputs_are_ordinary_tensors():
    """The loop runs in inference mode; its outputs are ordinary tensors (modifiable in place, usable
    in autograd)."""
    model = _models()["nonlinear-2-state"]
    u = _inputs()
    for out in (*prediction.free_run(model, u), *prediction.simulate(model, u, 2)):
        assert not out.is_inference()
        out.add_(0.0)
    w = torch.ones((), dtype=DTYPE, requires_grad=True)
    (w * prediction.free_run(model, u)[0]).sum().backward()
    assert w.grad is not None
