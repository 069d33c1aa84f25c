"""Resampling schemes: unbiasedness, low-variance properties, extreme weights, ESS."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_nssm.inference.resampling import (
    RESAMPLING_SCHEMES,
    effective_sample_size,
    get_resampler,
)

DTYPE = torch.float64
SCHEMES = sorted(RESAMPLING_SCHEMES)
#: Weights with very different magnitudes, one exactly-zero particle (log-weight -1000) and two
#: particles whose expected counts ``L W`` are whole numbers.
RAW = np.array([0.31, 0.005, 0.2, 0.0, 0.1, 0.15, 0.035, 0.1, 0.05, 0.05])


def _log_weights(B: int) -> torch.Tensor:
    w = RAW / RAW.sum()
    lw = np.where(w > 0, np.log(np.where(w > 0, w, 1.0)), -1000.0)
    return torch.as_tensor(lw, dtype=DTYPE).expand(B, -1).contiguous()


def _counts(idx: torch.Tensor, L: int) -> torch.Tensor:
    ones = torch.ones_like(idx, dtype=DTYPE)
    return torch.zeros(idx.shape[0], L, dtype=DTYPE).scatter_add_(1, idx, ones)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("n", [None, 7, 23])
def test_unbiased(scheme, n):
    B, L = 40000, RAW.size
    lw = _log_weights(B)
    gen = torch.Generator().manual_seed(2024)
    idx = RESAMPLING_SCHEMES[scheme](lw, n, generator=gen)
    M = L if n is None else n
    assert idx.shape == (B, M) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < L
    counts = _counts(idx, L)
    assert torch.all(counts.sum(1) == M)
    expected = M * torch.softmax(lw[0], -1)
    mean = counts.mean(0)
    se = counts.std(0) / math.sqrt(B)
    assert torch.all((mean - expected).abs() <= 4.5 * se + 1e-12), (mean, expected, se)
    assert counts[:, 3].sum() == 0  # the zero-weight particle is never drawn


@pytest.mark.parametrize("n", [None, 7])
def test_systematic_counts_within_floor_ceil(n):
    B, L = 5000, RAW.size
    lw = _log_weights(B)
    idx = RESAMPLING_SCHEMES["systematic"](lw, n, generator=torch.Generator().manual_seed(1))
    M = L if n is None else n
    dev = _counts(idx, L) - M * torch.softmax(lw, -1)
    assert dev.abs().max() < 1.0 + 1e-9


def test_stratified_counts_within_two():
    B, L = 5000, RAW.size
    lw = _log_weights(B)
    idx = RESAMPLING_SCHEMES["stratified"](lw, generator=torch.Generator().manual_seed(1))
    dev = _counts(idx, L) - L * torch.softmax(lw, -1)
    # an interval of length L W covers at least floor(L W) - 1 whole strata and meets at most
    # ceil(L W) + 1 of them
    assert dev.abs().max() < 2.0 + 1e-9


def test_residual_counts_bounds_and_variance():
    B, L = 40000, RAW.size
    lw = _log_weights(B)
    idx = RESAMPLING_SCHEMES["residual"](lw, generator=torch.Generator().manual_seed(3))
    counts = _counts(idx, L)
    nw = L * torch.softmax(lw[0], -1)
    # 2.0 and 1.0 come out as 1.9999999999999998 and 1.0000000000000002: the scheme nudges
    floor = torch.floor(nw + 1e-9)
    n_rest = L - floor.sum()
    assert torch.all(counts >= floor)
    assert torch.all(counts <= floor + n_rest)
    # residual counts are floor + Multinomial(n_rest, r / n_rest) with r = nW - floor
    r = (nw - floor).clamp_min(0)
    var = n_rest * (r / n_rest) * (1 - r / n_rest)
    np.testing.assert_allclose(counts.var(0).numpy(), var.numpy(), rtol=0.12, atol=1e-9)


@pytest.mark.parametrize("L", [49, 98])
def test_residual_uniform_weights_keep_every_particle(L):
    lw = torch.full((200, L), -math.log(L), dtype=DTYPE)
    idx = RESAMPLING_SCHEMES["residual"](lw, generator=torch.Generator().manual_seed(0))
    assert torch.all(_counts(idx, L) == 1.0)


def test_multinomial_variance():
    B, L = 40000, RAW.size
    lw = _log_weights(B)
    idx = RESAMPLING_SCHEMES["multinomial"](lw, generator=torch.Generator().manual_seed(3))
    W = torch.softmax(lw[0], -1)
    np.testing.assert_allclose(
        _counts(idx, L).var(0).numpy(), (L * W * (1 - W)).numpy(), rtol=0.05, atol=1e-9
    )


def test_low_variance_schemes_beat_multinomial():
    B, L = 20000, RAW.size
    lw = _log_weights(B)
    var = {}
    for s in SCHEMES:
        idx = RESAMPLING_SCHEMES[s](lw, generator=torch.Generator().manual_seed(8))
        var[s] = float(_counts(idx, L).var(0).sum())
    for s in ("systematic", "stratified", "residual"):
        assert var[s] < var["multinomial"], var


@pytest.mark.parametrize("scheme", SCHEMES)
def test_extreme_log_weights(scheme):
    L = 50
    lw = torch.full((6, L), -1000.0, dtype=DTYPE)
    lw[0, 7] = 0.0  # one particle carries everything
    lw[1, 0] = 0.0
    lw[2, L - 1] = 0.0
    lw[3, [3, 40]] = 0.0  # two equal winners
    lw[4] = torch.linspace(-5000.0, 0.0, L, dtype=DTYPE)  # only the last one survives
    lw[5] = -math.log(L)  # uniform
    idx = RESAMPLING_SCHEMES[scheme](lw, generator=torch.Generator().manual_seed(0))
    assert torch.all(idx[0] == 7)
    assert torch.all(idx[1] == 0)
    assert torch.all(idx[2] == L - 1)
    assert set(idx[3].tolist()) <= {3, 40}
    assert torch.all(idx[4] == L - 1)
    assert int(idx[5].min()) >= 0 and int(idx[5].max()) < L
    if scheme in ("systematic", "residual"):
        assert sorted(idx[5].tolist()) == list(range(L))  # uniform weights: every particle once
    if scheme != "multinomial":
        assert sorted(idx[3].tolist()).count(3) == L // 2


@pytest.mark.parametrize("scheme", SCHEMES)
def test_unnormalised_and_float32_log_weights(scheme):
    """Shifted log-weights give the same distribution; float32 works."""
    lw = _log_weights(3) + 12345.0
    idx = RESAMPLING_SCHEMES[scheme](lw, generator=torch.Generator().manual_seed(0))
    assert _counts(idx, RAW.size)[:, 3].sum() == 0
    idx32 = RESAMPLING_SCHEMES[scheme](
        _log_weights(3).float(), generator=torch.Generator().manual_seed(0)
    )
    assert idx32.shape == (3, RAW.size)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_reproducible_with_generator(scheme):
    lw = _log_weights(4)
    a = RESAMPLING_SCHEMES[scheme](lw, generator=torch.Generator().manual_seed(5))
    b = RESAMPLING_SCHEMES[scheme](lw, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


def test_effective_sample_size():
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(20), size=5)
    lw = torch.as_tensor(np.log(w))
    np.testing.assert_allclose(effective_sample_size(lw).numpy(), 1.0 / (w**2).sum(1), rtol=1e-12)
    uniform = torch.full((2, 8), -math.log(8), dtype=DTYPE)
    np.testing.assert_allclose(effective_sample_size(uniform).numpy(), [8.0, 8.0], rtol=1e-12)
    degenerate = torch.tensor([[0.0, -1000.0, -2000.0]], dtype=DTYPE)
    assert effective_sample_size(degenerate).item() == pytest.approx(1.0, rel=1e-12)


def test_get_resampler():
    for name, fn in RESAMPLING_SCHEMES.items():
        assert get_resampler(name) is fn
    assert set(RESAMPLING_SCHEMES) == {"multinomial", "systematic", "stratified", "residual"}
    with pytest.raises(ValueError, match="resampling must be one of"):
        get_resampler("bogus")


@pytest.mark.parametrize("search_work", [0.0, math.inf])
@pytest.mark.parametrize("n", [None, 7, 23])
def test_systematic_search_and_scatter_paths(monkeypatch, search_work, n):
    """Both implementations of systematic resampling (binary search for small problems, scatter and
    cumulative sum for large ones) are unbiased and give the same indices."""
    from torch_nssm.inference import resampling

    B, L = 40000, RAW.size
    lw = _log_weights(B)
    monkeypatch.setattr(resampling, "SEARCH_WORK", search_work)
    idx = resampling.systematic(lw, n, generator=torch.Generator().manual_seed(7))
    M = L if n is None else n
    counts = _counts(idx, L)
    assert torch.all(counts.sum(1) == M) and counts[:, 3].sum() == 0
    expected = M * torch.softmax(lw[0], -1)
    se = counts.std(0) / math.sqrt(B)
    assert torch.all((counts.mean(0) - expected).abs() <= 4.5 * se + 1e-12)
    assert (counts - expected).abs().max() < 1.0 + 1e-9
    # same uniforms through the other path: same indices, also from unnormalised cumulative sums
    u = torch.rand(B, 1, dtype=DTYPE, generator=torch.Generator().manual_seed(8))
    cumw = torch.cumsum(torch.exp(lw - 3.0), dim=-1)
    a = resampling.systematic_from_cumsum(cumw, u, n)
    monkeypatch.setattr(resampling, "SEARCH_WORK", 0.0 if search_work else math.inf)  # the other path
    assert torch.equal(a, resampling.systematic_from_cumsum(cumw, u, n))


@pytest.mark.parametrize("B, L", [(1, 8), (3, 50), (1, 1000), (20, 100)])
def test_systematic_resampler_equals_systematic_from_cumsum(B, L):
    """The filter's reusable resampler returns exactly ``systematic_from_cumsum``'s indices, on both
    paths (search for few rows, scatter otherwise), call after call on its reused arrays."""
    from torch_nssm.inference import resampling

    rs = resampling.SystematicResampler(B, L, DTYPE)
    assert rs.search == (B * L * math.log2(L) < resampling.SEARCH_WORK)
    gen = torch.Generator().manual_seed(3)
    out = torch.empty(B, L, dtype=torch.long)
    for i in range(4):
        w = torch.exp(3.0 * torch.randn(B, L, dtype=DTYPE, generator=gen))
        w[:, i % L] = 0.0
        u = torch.rand(B, 1, dtype=DTYPE, generator=gen)
        expected = resampling.systematic_from_cumsum(torch.cumsum(w, -1), u)
        assert torch.equal(rs(w, u), expected)
        assert torch.equal(rs(w, u, out=out), expected) and torch.equal(out, expected)
