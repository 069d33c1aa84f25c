"""The exact fallback draw of the backward sampler (torch_nssm.inference.ffbsi._exact_backward)
against the backward kernel computed directly, in both of its layouts of the pairs' tables and in its
direct form (one table per index, one state)."""

from __future__ import annotations

import pytest
import torch

from torch_nssm.inference import ffbsi
from torch_nssm.inference.ffbsi import _exact_backward


def _kernel(zf: torch.Tensor, lw: torch.Tensor, zx: torch.Tensor, row: int, nxt: int) -> torch.Tensor:
    """``W_i exp(-|z_x^j - z_f^i|^2 / 2)`` normalised over ``i``, for one row and next particle."""
    logits = lw[row] - 0.5 * ((zx[row, nxt] - zf[row]) ** 2).sum(-1)
    return torch.softmax(logits, 0)


@pytest.mark.parametrize(
    "crowded, nx, direct", [(False, 2, False), (True, 2, False), (False, 1, False), (False, 1, True)]
)
def test_exact_backward_draws_follow_the_backward_kernel(crowded, nx, direct, monkeypatch):
    """Every (row, next particle) pair's draws follow its kernel within 5 binomial standard errors
    per particle (cells with probability above 1e-3), with the pairs spread over the rows (one
    padded batched product) or crowded in one row of many (the rows' predictions gathered), or, for
    one state, each index's table built directly; particles of zero filter weight are never drawn."""
    monkeypatch.setattr(ffbsi, "_EXACT_DIRECT_MAX", 1 << 30 if direct else 0)
    gen = torch.Generator().manual_seed(0)
    R, L, n = (12, 40, 4000)
    zf = torch.randn(R, L, nx, dtype=torch.float64, generator=gen) * 1.5
    zx = torch.randn(R, L, nx, dtype=torch.float64, generator=gen) * 1.5
    lw = torch.randn(R, L, dtype=torch.float64, generator=gen) * 2.0
    lw[:, ::9] = -torch.inf  # particles without filter weight: never drawn (no NaN from the padding)
    lw = torch.log_softmax(lw, -1)
    if crowded:  # all pairs in row 5: R * C > 4 U
        pairs = [(5, j) for j in (0, 3, 7, 11)]
    else:
        pairs = [(r, (3 * r) % L) for r in range(R)] + [(0, 9), (4, 1)]
    rows = torch.tensor([r for r, _ in pairs for _ in range(n)])
    nxt = torch.tensor([j for _, j in pairs for _ in range(n)])
    perm = torch.randperm(rows.numel(), generator=gen)  # the indices in no particular order
    rows, nxt = rows[perm], nxt[perm]
    J = _exact_backward(zf, lw, zx, rows, nxt, gen)
    assert J.shape == rows.shape and int(J.min()) >= 0 and int(J.max()) < L
    for r, j in pairs:
        draws = J[(rows == r) & (nxt == j)]
        p = _kernel(zf, lw, zx, r, j)
        freq = torch.bincount(draws, minlength=L).double() / draws.numel()
        z = torch.where(p > 1e-3, (freq - p) / torch.sqrt(p * (1 - p) / draws.numel()), 0.0)
        assert float(z.abs().max()) < 5.0, (r, j)
        assert bool((freq[p < 1e-12] == 0).all()) and bool((freq[::9] == 0).all())  # nor without mass
