"""The elementwise tiny-matrix helpers and the MCMC backward kernel's building blocks."""

import math

import numpy as np
import pytest
import torch

from torch_nssm._ops import broadcast_leading, linear_combination, small_matmul, squared_norm, time_blocks
from torch_nssm.inference.resampling import _GUIDE_MIN_DRAWS, cumulative_weights, inverse_cdf
from torch_nssm.inference.smoothing import _independent_mh, _log_kernel, _proposals


@pytest.mark.parametrize(
    "shape_a, shape_b", [((5, 3, 2, 4), (5, 3, 4, 6)), ((5, 1, 2, 4), (3, 4, 1)), ((7, 1, 1), (7, 1, 1))]
)
def test_small_matmul_matches_matmul(shape_a, shape_b):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(*shape_a, dtype=torch.float64, generator=g)
    b = torch.randn(*shape_b, dtype=torch.float64, generator=g)
    torch.testing.assert_close(small_matmul(a, b), a @ b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("P", [1, 3, 8, 12])
def test_linear_combination_and_squared_norm(P):
    g = torch.Generator().manual_seed(1)
    Phi = torch.randn(4, 6, P, dtype=torch.float64, generator=g)
    theta = torch.randn(4, 1, P, dtype=torch.float64, generator=g)
    torch.testing.assert_close(linear_combination(Phi, theta), (Phi * theta).sum(-1))
    torch.testing.assert_close(squared_norm(Phi), (Phi * Phi).sum(-1))


def test_broadcast_leading_and_time_blocks():
    x, u = broadcast_leading(torch.zeros(3, 1, 2), torch.zeros(1, 4, 5))
    assert x.shape == (3, 4, 2) and u.shape == (3, 4, 5)
    blocks = list(time_blocks(10, 30, max_rows=100))
    assert [b.start for b in blocks] == [0, 3, 6, 9] and blocks[-1].stop == 10
    assert len(list(time_blocks(5, 10**9))) == 5  # at least one step per block


def _weights(L=12, seed=2):
    g = torch.Generator().manual_seed(seed)
    return torch.log_softmax(2.0 * torch.randn(1, L, dtype=torch.float64, generator=g), -1)


def test_mcmc_proposals_are_distributed_as_the_weights_at_every_position():
    """Each proposal (whatever trajectory it is offered to) is a draw from W."""
    log_w = _weights()
    W = torch.exp(log_w)[0].numpy()
    n, reps = 8, 20000
    g = torch.Generator().manual_seed(3)
    props = _proposals(log_w.expand(reps, -1), n, 2, g)  # (reps, 2, n)
    for step in range(2):
        for pos in (0, n // 2, n - 1):
            freq = np.bincount(props[:, step, pos].numpy(), minlength=W.size) / reps
            se = np.sqrt(W * (1 - W) / reps)
            assert np.all(np.abs(freq - W) < 5 * se + 1e-12)


def test_independent_mh_leaves_the_backward_kernel_invariant_and_converges():
    """Exact draws from pi(i) ~ W_i exp(-|zx - zf_i|^2 / 2) stay exact; a bad start converges."""
    L, M = 12, 40000
    log_w = _weights(L)
    g = torch.Generator().manual_seed(4)
    zf = torch.randn(1, L, 1, dtype=torch.float64, generator=g)
    zx = torch.full((1, M, 1), 0.3, dtype=torch.float64)
    log_pi = log_w[0] - 0.5 * (0.3 - zf[0, :, 0]) ** 2
    pi = torch.softmax(log_pi, -1).numpy()
    exact = torch.multinomial(torch.tensor(pi), M, replacement=True, generator=g).unsqueeze(0)
    se = np.sqrt(pi * (1 - pi) / M)
    for start, steps in ((exact, 2), (torch.zeros(1, M, dtype=torch.long), 30)):
        props = _proposals(log_w, M, steps, g)
        log_us = torch.log(torch.rand(1, steps, M, dtype=torch.float64, generator=g))
        J = _independent_mh(start, zf, zx, props, log_us)
        freq = np.bincount(J[0].numpy(), minlength=L) / M
        assert np.all(np.abs(freq - pi) < 5 * se + 1e-12), (freq, pi)
    assert _log_kernel(zf, torch.zeros(1, 1, dtype=torch.long), zx[:, :1]).item() == pytest.approx(
        -0.5 * (0.3 - zf[0, 0, 0].item()) ** 2, abs=1e-12
    )
    assert math.isfinite(float(log_pi.sum()))


@pytest.mark.parametrize("case", ["spread", "degenerate", "zeros"])
def test_guide_table_draws_equal_the_binary_search(case):
    """The guide-table inverse CDF returns exactly ``searchsorted(cdf, u, right=True)``, also where
    crowded buckets (many tiny or zero weights) need its fallback search."""
    g = torch.Generator().manual_seed(7)
    R, L, n = 64, 300, 500
    log_w = torch.randn(R, L, dtype=torch.float64, generator=g)
    if case == "degenerate":  # a few particles hold nearly all the weight
        log_w = 40.0 * log_w
    if case == "zeros":  # zero weights: flat stretches of the cdf
        log_w[:, ::3] = -math.inf
        log_w[:5, 2:] = -math.inf  # all the weight on particle 1
    cdf = cumulative_weights(log_w)
    u = torch.rand(R, n, dtype=torch.float64, generator=g)
    u[:, :3] = torch.tensor([0.0, 0.5, 1.0 - 2.0**-53], dtype=torch.float64)
    ref = torch.searchsorted(cdf, u, right=True).clamp_(max=L - 1)
    assert u.numel() >= _GUIDE_MIN_DRAWS  # the guide-table path
    assert torch.equal(inverse_cdf(cdf, u), ref)
