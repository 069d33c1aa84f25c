"""The per-step loops run in inference mode (no autograd bookkeeping); nothing they make may leave
them as an inference tensor: those cannot be saved for backward (the M-step's objectives, a user's
own autograd on ``smooth``'s output) nor modified in place outside inference mode."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import generator, inference_tensors, nonlinear_model, not_modifiable, paper_model, simulate

from torch_nssm.core.model import SequenceBatch
from torch_nssm.core.noise import StudentTPerOutputNoise
from torch_nssm.estimation.estep import EStepOptions, e_step, to_records
from torch_nssm.estimation.mstep import MStepOptions, m_step
from torch_nssm.inference.random import SequenceStreams


def _data(model, lengths, seed=0, missing=True):
    us, ys = simulate(model, lengths, np.random.default_rng(seed), outlier_rate=0.1)
    if missing and len(ys[0]) > 3:
        ys[0][3] = math.nan  # a missing output
    return SequenceBatch.from_sequences(us, ys)


CASES = [
    # (model, smoother, ess_threshold, resampling, streams, lengths)
    ("paper", "mcmc", 1.0, "systematic", False, [40, 40]),
    ("paper", "mcmc", 0.5, "systematic", True, [40, 31]),
    ("paper", "ffbsm", 1.0, "systematic", False, [40, 25]),
    ("paper", "ffbsi", 0.5, "multinomial", False, [40, 25]),
    ("nonlinear", "mcmc", 1.0, "systematic", False, [30, 22]),
    ("nonlinear", "ffbsm", 0.5, "stratified", True, [30, 30]),
    ("nonlinear", "ffbsi", 1.0, "systematic", True, [30, 22]),
    ("per-output", "mcmc", 1.0, "systematic", False, [30, 22]),
    ("gaussian", "mcmc", 1.0, "systematic", False, [40, 31]),
    ("gaussian", "ffbsm", 0.5, "residual", True, [1, 1]),  # T = 1: no transition at all
]


def _model(name):
    if name in ("paper", "gaussian"):  # the paper's model with Student-t or Gaussian noise
        return paper_model(dof=math.inf if name == "gaussian" else 3.0)
    model = nonlinear_model()
    if name == "per-output":  # a noise family with its own statistics arrays (per component)
        Rv = torch.diag(torch.diagonal(model.Rv))
        model = dataclasses.replace(model, noise=StudentTPerOutputNoise.initial(Rv, 4.0))
    return model


@pytest.mark.parametrize("name, smoother, ess, resampling, streams, lengths", CASES)
def test_e_step_outputs_are_ordinary_tensors(name, smoother, ess, resampling, streams, lengths):
    model = _model(name)
    data = _data(model, lengths)
    opts = EStepOptions(50, smoother, ess_threshold=ess, resampling=resampling)
    gen = SequenceStreams([3, 4]) if streams else generator(0)
    first = e_step(model, data, opts, gen)
    est = e_step(model, data, opts, gen, first, recycle=first)  # with recycled arrays too
    assert inference_tensors(est) == []  # (reading the fields computes the lazy ESS and log-weights)
    # autograd through the outputs: the M-step's gradient steps on f and g
    if max(lengths) > 1:  # (records of one sample have no transition to fit; fit() refuses them)
        new = m_step([model], data, est, MStepOptions()).models[0]
        assert all(torch.isfinite(p).all() for p in new.f.parameters())
    theta = torch.ones((), dtype=est.filter.particles.dtype, requires_grad=True)
    (theta * est.smoother.next_mean).sum().backward()
    assert theta.grad is not None
    assert not_modifiable(est) == []  # no view made in inference mode either (the last check: adds 0)


def test_windowed_e_step_outputs_are_ordinary_tensors():
    model = paper_model()
    data = _data(model, [120], missing=False)
    opts = EStepOptions(40, "mcmc", segment_length=40, segment_overlap=10)
    gen = generator(1)
    first = e_step(model, data, opts, gen, records=False)
    est = e_step(model, data, opts, gen, first, records=False)
    assert est.windows is not None
    assert inference_tensors(est) == []
    records = to_records(est, model, data)
    assert inference_tensors(records) == []
    m_step([model], est.windows.owned_data, est, MStepOptions())
    assert not_modifiable(records) == [] and not_modifiable(est) == []
