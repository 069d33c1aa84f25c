"""The EM loop driven directly (:func:`torch_nssm.estimation.loop.run_em`) on the small
linear-Gaussian system: the log-likelihood rises, undone M-steps are flagged, Ctrl-C keeps the last
completed iterate, ``n_iter=0`` evaluates the start, the E-step cache recycles the output from two
iterations back, and the acceleration's hooks run in their order."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import DTYPE, LinearF, LinearG, noise_model
from torch import nn

from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.estimation import loop as loop_module
from torch_nssm.estimation.acceleration import Acceleration
from torch_nssm.estimation.estep import EStepOptions
from torch_nssm.estimation.loop import EMOptions, run_em


def start_model(system, f: nn.Module | None = None) -> StateSpaceModel:
    """The system's structure from a poor start: ``A`` halved, noise covariances tripled."""
    t = lambda a: torch.as_tensor(a, dtype=DTYPE)  # noqa: E731
    return StateSpaceModel(
        f=f if f is not None else LinearF(0.5 * system.A, system.B),
        g=LinearG(system.C, system.D),
        Rw=t(3.0 * system.Q),
        noise=noise_model(3.0 * system.R),
        x0_mean=t(system.m0),
        x0_cov=t(system.P0),
    )


def batch(record) -> SequenceBatch:
    _, u, y = record
    return SequenceBatch.from_sequences([torch.as_tensor(u, dtype=DTYPE)], [torch.as_tensor(y, dtype=DTYPE)])


def options(n_iter: int, **kw) -> EMOptions:
    return EMOptions(n_iter=n_iter, tol=0.0, estep=EStepOptions(n_particles=100), **kw)


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_log_likelihood_rises_on_average(record):
    system = record[0]
    (result,) = run_em([start_model(system)], batch(record), options(12), gen())
    ll = np.asarray(result.history["log_likelihood"])
    assert ll.shape == (13,) and result.n_done == 12 and not result.converged
    assert result.error is None and not result.interrupted
    assert ll[-4:].mean() > ll[:4].mean() + 5.0  # from a poor start EM climbs
    assert np.mean(np.diff(ll)) > 0
    # no final E-step without averaging or a final particle count: the fit's E-step is the last iterate's
    assert result.log_likelihood == ll[-1]
    assert [len(result.history[k]) for k in ("f.A", "Rw", "Rv", "rejected.f", "rejected.g")] == [13] * 5
    assert not any(result.history["rejected.f"]) and "accelerated" not in result.history
    np.testing.assert_array_equal(result.model.f.A.detach().numpy(), result.history["f.A"][-1])


class NaNAbove(nn.Module):
    """``x A^T + u B^T`` with ``A`` fixed, NaN once ``B[0, 0]`` exceeds 0.75: every step from 0.5
    towards the system's 1.0 fails, and the M-step undoes it."""

    def __init__(self, A, B):
        super().__init__()
        self.A = nn.Parameter(torch.as_tensor(A, dtype=DTYPE).clone(), requires_grad=False)
        self.B = nn.Parameter(torch.as_tensor(B, dtype=DTYPE).clone())

    def forward(self, x, u):
        out = x @ self.A.T + u @ self.B.T
        return torch.where(self.B[0, 0] > 0.75, torch.full_like(out, math.nan), out)


def test_undone_m_steps_are_flagged(record):
    system = record[0]
    f = NaNAbove(system.A, 0.5 * system.B)
    (result,) = run_em([start_model(system, f)], batch(record), options(3), gen())
    flags = result.history["rejected.f"]
    assert flags == [False, True, True, True] and not any(result.history["rejected.g"])
    B = np.asarray(result.history["f.B"])
    np.testing.assert_array_equal(B, np.broadcast_to(B[0], B.shape))  # the parameters did not move
    assert result.error is None and result.n_done == 3


def test_interrupt_keeps_the_last_completed_iterate(record, monkeypatch):
    real = loop_module.e_step
    calls = {"n": 0}

    def interrupting(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:  # the E-step after the third M-step
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(loop_module, "e_step", interrupting)
    (result,) = run_em([start_model(record[0])], batch(record), options(10), gen())
    assert result.interrupted and result.n_done == 2 and result.error is None
    assert len(result.history["log_likelihood"]) == 3 and len(result.history["rejected.f"]) == 3
    # the model is the last completed iterate, not the interrupted M-step's
    np.testing.assert_array_equal(result.model.f.A.detach().numpy(), result.history["f.A"][-1])
    np.testing.assert_array_equal(result.model.Rw.numpy(), result.history["Rw"][-1])
    assert result.log_likelihood == result.history["log_likelihood"][-1]


def test_zero_iterations_evaluate_the_start(record):
    model = start_model(record[0])
    A = model.f.A.detach().clone()
    (result,) = run_em([model], batch(record), options(0), gen())
    assert result.n_done == 0 and len(result.history["log_likelihood"]) == 1
    assert result.history["rejected.f"] == [False] and np.isfinite(result.log_likelihood)
    assert torch.equal(result.model.f.A.detach(), A) and torch.equal(result.model.Rw, model.Rw)


def test_e_step_cache_recycles_the_output_from_two_iterations_back(record, monkeypatch):
    real = loop_module.e_step
    outputs, recycled = [], []

    def spy(*args, recycle=None, **kwargs):
        recycled.append(recycle)
        outputs.append(real(*args, recycle=recycle, **kwargs))
        return outputs[-1]

    monkeypatch.setattr(loop_module, "e_step", spy)
    run_em([start_model(record[0])], batch(record), options(4), gen())
    assert len(outputs) == 5
    assert recycled[:2] == [None, None]
    assert all(recycled[k] is outputs[k - 2] for k in range(2, 5))


class Spy(Acceleration):
    """Plain EM that logs the hooks; its first E-step after an M-step is undone once (the loop must
    then run the E-step of the model it returns)."""

    def __init__(self):
        self.calls: list[str] = []
        self.kept = None

    def start(self, model):
        self.calls.append("start")

    def before_mstep(self, model, data, estep, generator):
        self.calls.append("before_mstep")

    def after_mstep(self, model, rejected):
        self.calls.append("after_mstep")
        self.kept = model
        return model

    def after_estep(self, log_likelihood, estep):
        self.calls.append("after_estep")
        if self.calls.count("after_estep") == 1:
            return self.kept
        return None


def test_acceleration_hooks_run_in_order(record, monkeypatch):
    spy = Spy()
    monkeypatch.setattr(loop_module, "acceleration_for", lambda *args, **kwargs: spy)
    n_esteps = {"n": 0}
    real = loop_module.e_step

    def count(*args, **kwargs):
        n_esteps["n"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(loop_module, "e_step", count)
    (result,) = run_em([start_model(record[0])], batch(record), options(2), gen())
    assert spy.calls == ["start"] + ["before_mstep", "after_mstep", "after_estep"] * 2
    assert n_esteps["n"] == 1 + 2 + 1  # the first iteration's E-step ran again at the returned model
    assert result.n_done == 2


@pytest.mark.parametrize("shared", [True, False])
def test_groups_of_independent_fits(record, shared):
    """Two copies of the record as two groups (``shared=False``) run the same EM as each alone
    with the same stream; as one group they share the parameters."""
    from torch_nssm.inference.random import SequenceStreams

    _, u, y = record
    ut, yt = torch.as_tensor(u, dtype=DTYPE), torch.as_tensor(y, dtype=DTYPE)
    data = SequenceBatch.from_sequences([ut, ut], [yt, yt])
    system = record[0]
    if shared:
        (result,) = run_em([start_model(system)], data, options(2), gen())
        assert result.n_done == 2 and result.estep.log_likelihood.shape == (2,)
        return
    streams = SequenceStreams([11, 12], torch.device("cpu"))
    both = run_em([start_model(system), start_model(system)], data, options(2), streams, shared=False)
    one = SequenceBatch.from_sequences([ut], [yt])
    second = SequenceStreams([12], torch.device("cpu"))
    alone = run_em([start_model(system)], one, options(2), second, shared=False)
    lls = [r.history["log_likelihood"] for r in (both[1], alone[0])]
    np.testing.assert_allclose(lls[0], lls[1], rtol=1e-12)
    assert both[0].history["log_likelihood"] != both[1].history["log_likelihood"]
