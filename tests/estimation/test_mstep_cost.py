"""The M-step's and the latent scales' cheaper paths give what the general ones give: the
few-feature normal equations, the batched validity check, the latent scales written in place."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch
from torch import nn

from torch_nssm.core import parametric
from torch_nssm.core.model import StateSpaceModel
from torch_nssm.core.noise import StudentTNoise, latent_scale_expectations
from torch_nssm.core.parametric import LinearInParameters, ResidualMoments, linear_normal_equations
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.estimation.mstep import (
    Regression,
    _check,
    _closed_form,
    _evaluator,
    _Groups,
    _residuals,
    _valid,
    process_noise_update,
)

DTYPE = torch.float64


class Poly(LinearInParameters):
    """``y = t0 x + t1 x^2 + t2 u + 0.3 sin(x)``: three features, a non-zero offset, one output."""

    def __init__(self, theta=(0.5, -0.2, 1.5)):
        super().__init__()
        self.t0 = nn.Parameter(torch.tensor(theta[0], dtype=DTYPE))
        self.t1 = nn.Parameter(torch.tensor(theta[1], dtype=DTYPE))
        self.t2 = nn.Parameter(torch.tensor(theta[2], dtype=DTYPE))

    def features(self, x, u):
        Phi = torch.stack([x[..., 0], x[..., 0] ** 2, u[..., 0].expand_as(x[..., 0])], -1).unsqueeze(-2)
        return Phi, 0.3 * torch.sin(x)


def _rows(T=37, B=3, L=11, seed=0, per_component=False, broadcast_target=False):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(T, B, L, 1, generator=g, dtype=DTYPE)
    u = torch.randn(T, B, 1, generator=g, dtype=DTYPE)
    target = torch.randn(T, B, 1 if broadcast_target else L, 1, generator=g, dtype=DTYPE)
    w = torch.rand(T, B, L, generator=g, dtype=DTYPE)
    if per_component:
        w = w.unsqueeze(-1)
    C = 1.0 + torch.rand(T, B, 1, 1, generator=g, dtype=DTYPE)  # a metric that varies over time
    C[5] = 0.0  # a step without an observation
    return x, u, target, (lambda sl: w[sl]), C


@pytest.mark.parametrize("fixed", [(), ("t1",)])
@pytest.mark.parametrize("per_component", [False, True])
@pytest.mark.parametrize("broadcast_target", [False, True])
def test_few_feature_normal_equations_match_the_general_products(
    monkeypatch, fixed, per_component, broadcast_target
):
    module = Poly()
    for name in fixed:
        getattr(module, name).requires_grad_(False)
    x, u, target, weight, C = _rows(per_component=per_component, broadcast_target=broadcast_target)
    thetas = module.theta().detach().expand(x.shape[1], -1)
    # small blocks: the sums run over several of them
    monkeypatch.setattr(parametric, "time_blocks", lambda T, rows: (slice(s, s + 8) for s in range(0, T, 8)))
    G, h = linear_normal_equations(module, thetas, x, u, target, weight, C)
    monkeypatch.setattr(parametric, "FEW_FEATURES", 0)  # the batched (F, L) @ (L, F) products
    G_ref, h_ref = linear_normal_equations(module, thetas, x, u, target, weight, C)
    assert G.shape == G_ref.shape and h.shape == h_ref.shape
    torch.testing.assert_close(G, G_ref, rtol=1e-13, atol=0)
    torch.testing.assert_close(h, h_ref, rtol=1e-13, atol=0)


def test_few_feature_path_on_the_paper_modules(monkeypatch):
    x, u, target, weight, C = _rows(B=4, L=9, seed=3)
    for module in (PaperTransition(0.5, 0.5), PaperObservation(0.5)):
        thetas = module.theta().detach().expand(x.shape[1], -1)
        G, h = linear_normal_equations(module, thetas, x, u, target, weight, C[:1])
        with monkeypatch.context() as m:
            m.setattr(parametric, "FEW_FEATURES", 0)
            G_ref, h_ref = linear_normal_equations(module, thetas, x, u, target, weight, C[:1])
        torch.testing.assert_close(G, G_ref, rtol=1e-13, atol=0)
        torch.testing.assert_close(h, h_ref, rtol=1e-13, atol=0)


def _candidates(n=5):
    models = []
    for b in range(n):
        models.append(
            StateSpaceModel(
                f=PaperTransition(0.9, 1.0),
                g=PaperObservation(1.0),
                Rw=torch.eye(1, dtype=DTYPE) * (0.1 + b),
                noise=StudentTNoise.initial(torch.eye(1, dtype=DTYPE) * 0.01, 2.0 + b),
                x0_mean=torch.zeros(1, dtype=DTYPE),
                x0_cov=torch.eye(1, dtype=DTYPE),
            )
        )
    return models


def _spoil(model: StateSpaceModel, how: str) -> StateSpaceModel:
    if how == "Rw nan":
        return replace(model, Rw=torch.full((1, 1), math.nan, dtype=DTYPE))
    if how == "Rw negative":
        return replace(model, Rw=-torch.eye(1, dtype=DTYPE))
    if how == "x0_cov negative":
        return replace(model, x0_cov=-torch.eye(1, dtype=DTYPE))
    if how == "x0_mean inf":
        return replace(model, x0_mean=torch.full((1,), math.inf, dtype=DTYPE))
    if how == "parameter nan":
        with torch.no_grad():
            model.g.c.fill_(math.nan)
        return model
    if how == "dof nan":
        return replace(model, noise=model.noise.replace(dof=torch.tensor(math.nan, dtype=DTYPE)))
    if how == "Rv zero":
        return replace(model, noise=model.noise.replace(Rv=torch.zeros(1, 1, dtype=DTYPE)))
    raise ValueError(how)


@pytest.mark.parametrize(
    "how", ["Rw nan", "Rw negative", "x0_cov negative", "x0_mean inf", "parameter nan", "dof nan", "Rv zero"]
)
def test_batched_validity_agrees_with_the_check(how):
    models = _candidates()
    models[2] = _spoil(models[2], how)
    valid = _valid(
        models,
        torch.stack([m.Rw for m in models]),
        StudentTNoise.stack([m.noise for m in models]),
        torch.stack([m.x0_mean for m in models]),
        torch.stack([m.x0_cov for m in models]),
    )
    assert valid.tolist() == [_check(m) is None for m in models]
    assert valid.tolist() == [True, True, False, True, True]


@pytest.mark.parametrize("dof", [[3.0, 0.7], [math.inf, 4.0]])
def test_latent_scales_written_in_place_equal_the_returned_ones(dof):
    g = torch.Generator().manual_seed(1)
    delta2 = torch.rand(6, 2, 5, generator=g, dtype=DTYPE) * 10
    n_obs = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0, 1.0], dtype=DTYPE).view(6, 1, 1)
    nu = torch.tensor(dof, dtype=DTYPE).view(1, 2, 1)
    e_lam, e_log = latent_scale_expectations(delta2, n_obs, nu)
    out_lam, out_log = torch.empty_like(delta2), delta2.clone()  # <log lam> over delta2 itself
    res = latent_scale_expectations(out_log, n_obs, nu, out=(out_lam, out_log))
    assert res[0] is out_lam and res[1] is out_log
    assert torch.equal(out_lam, e_lam) and torch.equal(out_log, e_log)


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("fixed", [(), ("t1",)])
def test_scatter_from_the_closed_form_pass_equals_the_residuals(shared, fixed):
    x, u, target, weight, C = _rows(B=3, seed=5)
    modules = [Poly((0.5 + 0.1 * b, -0.2, 1.5)) for b in range(1 if shared else 3)]
    for m in modules:
        for name in fixed:
            getattr(m, name).requires_grad_(False)
    problem = Regression(x, u, target, weight, C)
    groups = _Groups(shared, 3)
    _, scatter = _closed_form(modules, problem, groups, scatter=True)
    assert scatter is not None and scatter.shape == (groups.n,)
    direct = torch.zeros(3, dtype=DTYPE)
    for sl, r in _residuals(_evaluator(modules, groups), problem):
        direct += (weight(sl) * r[..., 0] ** 2).sum((0, 2))
    torch.testing.assert_close(scatter, groups.pool(direct).reshape(-1), rtol=1e-12, atol=0)


def test_scatter_left_to_the_residuals_where_it_cancels():
    """A nearly perfect fit far from zero: the expanded scatter loses its digits and is refused."""
    x, u, _, weight, C = _rows(B=2, seed=6)
    module = Poly((100.0, 0.0, 50.0))
    Phi, offset = module.features(x, u.unsqueeze(2).expand(*x.shape[:-1], 1))
    target = offset + (Phi * module.theta().detach()).sum(-1) + 1e-5 * torch.randn_like(offset)
    problem = Regression(x, u, target, weight, C)
    start = [Poly((1.0, 0.0, 1.0)), Poly((1.0, 0.0, 1.0))]
    _, scatter = _closed_form(start, problem, _Groups(False, 2), scatter=True)
    assert scatter is None
    one = torch.ones((), dtype=DTYPE)
    moments = ResidualMoments(torch.eye(2, dtype=DTYPE), one.expand(2), 2 * one)
    value, reliable = moments.scatter_at(torch.tensor([1.0, 1.0], dtype=DTYPE))  # 2 - 4 + 2 = 0
    assert float(value) == 0.0 and not bool(reliable)


def test_scatter_shortcut_only_where_its_precision_allows():
    """A mild cancellation (terms ~10x the scatter) is fine in double precision and refused in
    single precision, whose rounding would show at ~1e-6 of the terms."""
    for dtype, expected in ((torch.float64, True), (torch.float32, False)):
        one = torch.ones((), dtype=dtype)
        moments = ResidualMoments(torch.eye(2, dtype=dtype), one.expand(2), 2.4 * one)
        value, reliable = moments.scatter_at(torch.tensor([1.0, 1.0], dtype=dtype))  # 2.4 - 4 + 2 = 0.4
        assert float(value) == pytest.approx(0.4, rel=1e-6) and bool(reliable) is expected, dtype


def test_process_noise_update_takes_the_given_scatter():
    class Est:
        class smoother:  # noqa: N801
            residual_scatter = torch.full((3, 1, 1), 0.5, dtype=DTYPE)

    class Data:
        n_sequences = 3
        transition_mask = torch.ones(4, 3, dtype=torch.bool)

    scatter = torch.tensor([1.5, 2.5, 3.5], dtype=DTYPE)
    Rw = process_noise_update([], None, Est, Data, shared=False, scatter=scatter)
    torch.testing.assert_close(Rw[:, 0, 0], (scatter + 0.5) / 4, rtol=1e-9, atol=0)
    Rw = process_noise_update([], None, Est, Data, shared=True, scatter=scatter[:1])
    torch.testing.assert_close(Rw[0, 0], (scatter[0] + 1.5) / 12, rtol=1e-9, atol=0)
