"""Independent fits: the grouped M-step equals the single M-step of each data set, and the EM
driver runs many groups as one batch (estimation layer)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
from conftest import DTYPE, CosineG, NonlinearF, generator, make_model

from torch_nssm import LinearInParameters
from torch_nssm.core.model import SequenceBatch
from torch_nssm.datasets import make_paper_example
from torch_nssm.estimation.estep import EStepOptions, e_step
from torch_nssm.estimation.independent import stack_models
from torch_nssm.estimation.mstep import MStepOptions, m_step
from torch_nssm.models import PaperObservation, PaperTransition


class _TwoStateF(LinearInParameters):
    """f(x, u) = [a0 x0 + a1 x1, a2 x0 + a3 u]: different regressors per row, so the metric of the
    weighted regression matters (with identical regressors GLS equals OLS row by row)."""

    def __init__(self):
        super().__init__()
        self.A = torch.nn.Parameter(torch.tensor([0.5, 0.1, -0.2, 0.6], dtype=torch.float64))

    def features(self, x, u):
        z = torch.zeros_like(x[..., :1])
        rows = [torch.cat([x, z, z], -1), torch.cat([z, z, x[..., :1], u], -1)]
        return torch.stack(rows, -2), torch.zeros_like(x)


class _TwoStateG(LinearInParameters):
    """g(x, u) = c x_0 + x_1."""

    def __init__(self):
        super().__init__()
        self.c = torch.nn.Parameter(torch.tensor(0.7, dtype=torch.float64))

    def features(self, x, u):
        return x[..., :1].unsqueeze(-1), x[..., 1:2]


class _TwoOutputG(LinearInParameters):
    """g(x, u) = [c0 x_0 + x_1, c1 x_1]: two outputs, so the measurement metric is a 2x2 matrix."""

    def __init__(self):
        super().__init__()
        self.c = torch.nn.Parameter(torch.tensor([0.7, 1.3], dtype=torch.float64))

    def features(self, x, u):
        z = torch.zeros_like(x[..., :1])
        Phi = torch.stack([torch.cat([x[..., :1], z], -1), torch.cat([z, x[..., 1:2]], -1)], -2)
        return Phi, torch.cat([x[..., 1:2], z], -1)


def _records(kind: str, rng: np.random.Generator):
    us, ys = [], []
    lengths = (110, 90)  # different lengths: padded rows must not count
    for n in lengths:
        u = rng.standard_normal(n)
        x = np.zeros((n, 2))
        for k in range(n - 1):
            x[k + 1] = [0.8 * x[k, 0] + 0.2 * x[k, 1], -0.3 * x[k, 0] + u[k]] + 0.3 * rng.standard_normal(2)
        if kind == "two-outputs":
            y = np.stack([x[:, 0] + x[:, 1], 1.2 * x[:, 1]], 1) + 0.2 * rng.standard_normal((n, 2))
            y[rng.random((n, 2)) < 0.1] = np.nan
        else:
            y = (x[:, 0] + x[:, 1] + 0.2 * rng.standard_normal(n))[:, None]
        us.append(torch.as_tensor(u[:, None]))
        ys.append(torch.as_tensor(y))
    return us, ys


def _models(kind: str, noise_dof: float):
    if kind == "paper":
        f, g, Rw, Rv, x0 = PaperTransition(0.6, 0.8), PaperObservation(0.7), [[0.1]], [[0.2]], [0.0]
        f, g = f.double(), g.double()
    elif kind == "nonlinear":  # no closed form: the gradient solver runs per data set
        f, g, x0 = NonlinearF(), CosineG(), [0.0, 0.0]
        Rw, Rv = [[0.2, 0.05], [0.05, 0.3]], [[0.1, 0.03], [0.03, 0.2]]
    else:
        g = _TwoOutputG() if kind == "two-outputs" else _TwoStateG()
        Rv = [[0.1, 0.03], [0.03, 0.2]] if kind == "two-outputs" else [[0.1]]
        f, Rw, x0 = _TwoStateF(), [[0.2, 0.15], [0.15, 0.3]], [0.0, 0.0]
    nx = len(x0)
    return [
        make_model(copy.deepcopy(f), copy.deepcopy(g), Rw, Rv, noise_dof, x0, np.eye(nx)) for _ in range(2)
    ]


def _close(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-9, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("kind", ["paper", "two-states", "two-outputs", "nonlinear"])
@pytest.mark.parametrize("dof", [4.0, math.inf])
def test_grouped_m_step_equals_the_single_m_step_of_each_data_set(kind, dof):
    """One E-step of two data sets; the independent (grouped) M-step of both equals the shared
    M-step of each data set on its own part of the same E-step."""
    rng = np.random.default_rng(3)
    if kind == "paper":
        sets = [make_paper_example(n_samples=n, random_state=s) for n, s in ((120, 3), (90, 4))]
        us = [torch.as_tensor(np.asarray(d.u, dtype=float)).reshape(-1, 1) for d in sets]
        ys = [torch.as_tensor(np.asarray(d.y, dtype=float)).reshape(-1, 1) for d in sets]
    else:
        us, ys = _records("one-output" if kind == "two-states" else "two-outputs", rng)
    data = SequenceBatch.from_sequences(us, ys)
    models = _models(kind, dof)
    est = e_step(stack_models(models), data, EStepOptions(40), generator(0))
    grouped = m_step([copy.deepcopy(m) for m in models], data, est, MStepOptions(), shared=False)
    assert grouped.errors == [None, None]
    for b in range(2):
        one = slice(b, b + 1)
        single = m_step([copy.deepcopy(models[b])], data.select(one), est.select(one), MStepOptions())
        assert single.errors == [None]
        a, s = grouped.models[b], single.models[0]
        for (name, p), (_, q) in zip(
            list(a.f.named_parameters()) + list(a.g.named_parameters()),
            list(s.f.named_parameters()) + list(s.g.named_parameters()),
        ):
            _close(p.detach(), q.detach(), name)
        for name in ("Rw", "x0_mean", "x0_cov"):
            _close(getattr(a, name), getattr(s, name), name)
        for name, v in a.noise.parameters().items():
            _close(v, getattr(s.noise, name), name)
    # the estimates of the two data sets differ: nothing was pooled across them
    assert not torch.allclose(grouped.models[0].Rw, grouped.models[1].Rw)


def test_a_refused_update_keeps_that_data_set_only():
    """A group whose update is not valid keeps its previous parameters; the others move on."""
    rng = np.random.default_rng(4)
    us, ys = _records("one-output", rng)
    data = SequenceBatch.from_sequences(us, ys)
    models = _models("two-states", 4.0)
    est = e_step(stack_models(models), data, EStepOptions(30), generator(1))
    est.e_lam[:, 1] = math.nan  # data set 1's statistics are broken
    before = [m.g.c.item() for m in models]
    out = m_step(models, data, est, MStepOptions(), shared=False)
    assert out.errors[0] is None and out.errors[1] is not None
    assert out.models[1] is models[1] and models[1].g.c.item() == before[1]
    assert out.models[0].g.c.item() != before[0]
    assert DTYPE == torch.float64
