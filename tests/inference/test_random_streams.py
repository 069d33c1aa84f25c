"""Per-sequence random streams: a sequence's filter and smoother results do not depend on the
sequences batched with it (padding, batch size, block layout), for every resampling scheme and
backward sampler; a plain ``torch.Generator`` keeps drawing for the whole batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import paper_model, simulate

from torch_nssm.core.model import SequenceBatch
from torch_nssm.inference.ffbsi import ffbsi
from torch_nssm.inference.filtering import particle_filter
from torch_nssm.inference.random import SequenceStreams, sequence_seeds

LENGTHS = [30, 45, 12]


@pytest.fixture(scope="module")
def data():
    us, ys = simulate(paper_model(), LENGTHS, np.random.default_rng(0), outlier_rate=0.1)
    return us, ys


def _run(us, ys, seeds, resampling, method):
    model = paper_model()
    batch = SequenceBatch.from_sequences(us, ys)
    streams = SequenceStreams(seeds)
    filt = particle_filter(model, batch, 25, resampling=resampling, generator=streams)
    smooth = ffbsi(model, batch, filt, method=method, max_tries=3, generator=streams)
    return filt, smooth


@pytest.mark.parametrize(
    "resampling, method", [("systematic", "mcmc"), ("systematic", "reject"), ("stratified", "mcmc"),
                           ("multinomial", "reject"), ("residual", "mcmc")]
)
def test_a_sequence_draws_the_same_alone_and_in_a_batch(data, resampling, method):
    us, ys = data
    seeds = sequence_seeds(11, len(LENGTHS))
    filt, smooth = _run(us, ys, seeds, resampling, method)
    for b, n in enumerate(LENGTHS):
        f1, s1 = _run([us[b]], [ys[b]], [seeds[b]], resampling, method)
        torch.testing.assert_close(filt.particles[:n, b], f1.particles[:, 0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(filt.log_likelihood[b], f1.log_likelihood[0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(smooth.log_weights[:n, b], s1.log_weights[:, 0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(
            smooth.next_mean[: n - 1, b], s1.next_mean[:, 0], rtol=1e-12, atol=1e-12
        )


def test_streams_select_shares_the_generators():
    streams = SequenceStreams(sequence_seeds(3, 4))
    sub = streams.select([2])
    a = sub.rows((5,), torch.float64)
    fresh = SequenceStreams(sequence_seeds(3, 4))
    fresh.select([0, 1, 3]).rows((5,), torch.float64)  # the others' draws do not move sequence 2's
    torch.testing.assert_close(a[0], fresh.select([2]).rows((5,), torch.float64)[0])
    b = streams.rows((5,), torch.float64)[2]  # sequence 2's stream has moved on
    assert not torch.equal(a[0], b)


def test_a_plain_generator_draws_as_before():
    """Single fits keep their numbers: one draw for the batch, as torch draws it."""
    us, ys = simulate(paper_model(), [20], np.random.default_rng(1))
    batch = SequenceBatch.from_sequences(us, ys)
    model = paper_model()
    g = torch.Generator().manual_seed(5)
    filt = particle_filter(model, batch, 10, generator=g)
    g = torch.Generator().manual_seed(5)
    eps = torch.randn(1, 10, 1, dtype=torch.float64, generator=g)
    torch.testing.assert_close(filt.particles[0], eps)  # x0 ~ N(0, 1): the first draws, unchanged
