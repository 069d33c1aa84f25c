"""Recycled E-step arrays (torch_nssm._workspace): the same output, written into the old arrays."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import paper_model, simulate

from torch_nssm.core.model import SequenceBatch
from torch_nssm.estimation.estep import EStepOptions, _arrays, e_step

FIELDS = ("log_weights", "next_mean", "transition_weights", "residual_scatter", "weights")


@pytest.mark.parametrize("smoother", ["mcmc", "ffbsm"])
def test_a_recycled_e_step_equals_a_fresh_one_in_the_old_arrays(smoother):
    model = paper_model()
    us, ys = simulate(model, [60, 45], np.random.default_rng(3), outlier_rate=0.1)
    data = SequenceBatch.from_sequences(us, ys)
    options = EStepOptions(n_particles=40, smoother=smoother)
    old = e_step(model, data, options, torch.Generator().manual_seed(1))
    fresh = e_step(model, data, options, torch.Generator().manual_seed(2))
    pointers = {t.data_ptr() for t in _arrays(old) if t is not None}
    again = e_step(model, data, options, torch.Generator().manual_seed(2), recycle=old)
    for name in ("particles", "log_weights", "ancestors", "log_likelihood", "ess"):
        assert torch.equal(getattr(again.filter, name), getattr(fresh.filter, name)), name
    for name in FIELDS:
        a, b = getattr(again.smoother, name), getattr(fresh.smoother, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert torch.equal(a, b), name
    assert torch.equal(again.e_lam, fresh.e_lam) and torch.equal(again.e_log_lam, fresh.e_log_lam)
    # the filter's and the smoother's outputs live in the old arrays
    assert again.filter.particles.data_ptr() in pointers
    assert again.filter.log_weights.data_ptr() in pointers
    if smoother == "mcmc":  # the trajectory smoothers' statistics (FFBSm allocates its own)
        assert again.smoother.weights.data_ptr() in pointers
        assert again.smoother.next_mean.data_ptr() in pointers
