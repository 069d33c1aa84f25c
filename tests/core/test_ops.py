"""The elementwise tiny-matrix helpers and the MCMC backward kernel's building blocks."""

import math

import numpy as np
import pytest
import torch

from torch_nssm._ops import broadcast_leading, linear_combination, small_matmul, squared_norm, time_blocks
from torch_nssm.inference.ffbsi import _mcmc_block
from torch_nssm.inference.resampling import _GUIDE_MIN_DRAWS, cumulative_weights, inverse_cdf, systematic


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


def _mh_law(start: int, q: np.ndarray, pi: np.ndarray, steps: int) -> np.ndarray:
    """Exact law after ``steps`` independent Metropolis-Hastings moves from ``start`` (proposal
    ``q``, target ``pi``), by the chain's transition matrix."""
    L = q.size
    with np.errstate(divide="ignore", invalid="ignore"):  # q = 0: never proposed (P = 0 there)
        ratio = np.divide.outer(q, q) * np.divide.outer(pi, pi).T  # [a, b]: pi_b q_a / (pi_a q_b)
    P = q[None, :] * np.minimum(1.0, np.nan_to_num(ratio, nan=0.0, posinf=1.0))
    P[np.arange(L), np.arange(L)] = 0.0
    P[np.arange(L), np.arange(L)] = 1.0 - P.sum(1)
    law = np.zeros(L)
    law[start] = 1.0
    for _ in range(steps):
        law = law @ P
    return law


@pytest.mark.parametrize("resampled", [True, False])
@pytest.mark.parametrize("streams", [False, True])
@pytest.mark.parametrize("steps", [1, 3])
def test_mcmc_backward_moves_have_the_exact_law(resampled, streams, steps):
    """The MCMC backward pass's indices after ``steps`` moves are distributed exactly as the
    Metropolis-Hastings chain from the genealogical parent with proposals from the ancestry
    (``c_i / L``) targeting ``c_i exp(-|z_x - z_f^i|^2 / 2)`` after a resampling and
    ``W_i exp(...)`` where the step kept its particles (``c = 1``); many moves reach the target."""
    L, M = 10, 40000
    g = torch.Generator().manual_seed(4)
    log_w = torch.log_softmax(2.0 * torch.randn(1, 1, L, dtype=torch.float64, generator=g), -1)
    if resampled:  # systematic resampling of W: some particles have no child, some several
        anc = systematic(log_w[0], generator=g).unsqueeze(0)
    else:
        anc = torch.arange(L).view(1, 1, L)
    ancestors = torch.cat([torch.arange(L).view(1, 1, L), anc])
    zf = torch.randn(1, 1, L, 1, dtype=torch.float64, generator=g)
    zx = torch.randn(1, 1, L, 1, dtype=torch.float64, generator=g)
    j0 = 3  # every trajectory passes through particle 3 at k + 1
    Js = torch.full((2, 1, M), j0, dtype=torch.long)
    draws = torch.rand(1, 1, 2 * steps * M, dtype=torch.float64, generator=g) if streams else None
    record = torch.tensor([[False], [resampled]])  # (T, B): the filter's record of resampling
    _mcmc_block(Js, slice(0, 1), zf, zx, ancestors, record, log_w, torch.ones(1, 1, dtype=torch.bool),
                [True], steps, g, draws, None)
    c = np.bincount(anc.view(-1).numpy(), minlength=L).astype(float)
    prior = c if resampled else torch.exp(log_w).view(-1).numpy()
    pi = prior * np.exp(-0.5 * (zx[0, 0, j0, 0].item() - zf[0, 0, :, 0].numpy()) ** 2)
    pi /= pi.sum()
    law = _mh_law(int(anc.view(-1)[j0]), c / L, pi, steps)
    freq = np.bincount(Js[0, 0].numpy(), minlength=L) / M
    se = np.sqrt(law * (1 - law) / M)
    assert np.all(np.abs(freq - law) < 5 * se + 1e-12), (freq, law)
    assert np.all(freq[c == 0] == 0)  # childless particles are never proposed after a resampling
    # the chain converges to its target
    assert np.abs(_mh_law(int(anc.view(-1)[j0]), c / L, pi, 200) - pi).max() < 1e-6


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
