"""The first stage: a robust simulation-error fit of f and g before EM (issue #13)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.estimation.first_stage import simulation_error_fit
from torch_nssm.models import PaperObservation, PaperTransition


def _start(y, u):
    est = RobustNSSMEstimator(PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0])
    device = est._check_params()
    data, _ = est._batch(u, y, device, fitted=False)
    return est._initial_model(data, device), data


@pytest.mark.parametrize("segment_length", [None, 50])
def test_simulation_error_fit_recovers_the_dynamics_despite_outliers(segment_length):
    """Noise-free simulation of the paper's system (10 % outliers uniform in [-5, 5]): the Cauchy
    loss is not steered by the outliers, and the fitted model simulates the clean output."""
    d = make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=2, Rw=1e-6)
    model, data = _start(d.y, d.u)
    report = simulation_error_fit(model, data, segment_length=segment_length)
    assert report.accepted and report.rmse_after < report.rmse_before
    assert report.n_windows == (1 if segment_length is None else 6)
    assert abs(model.f.a.item() - 0.9) < 0.03 and abs(model.f.b.item() - 1.0) < 0.05
    assert abs(model.g.c.item() - 1.0) < 0.05
    assert report.first_states.shape == (report.n_windows, 1)


def test_a_first_stage_that_cannot_improve_is_not_kept():
    d = make_paper_example(n_samples=60, random_state=0)
    model, data = _start(d.y, d.u)
    for p in list(model.f.parameters()) + list(model.g.parameters()):
        p.requires_grad_(False)
    report = simulation_error_fit(model, data)
    assert not report.accepted and report.first_states is None
    assert model.f.a.item() == 0.5


def test_first_stage_moves_em_out_of_the_wrong_basin():
    """y scaled by 0.1 from a = b = c = 0.5: plain EM ends at a ~ 1, b ~ 0 (log-likelihood ~200
    lower); with first_stage="simulation" one run reaches the right basin, and so does the default
    ("auto": the first stage's simulation explains enough of y to be kept)."""
    d = make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=0)
    y = 0.1 * np.asarray(d.y)
    kw = dict(x0_mean=[0.0], n_particles=100, n_iter=30, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), first_stage=None, **kw
        ).fit(d.u, y)
        staged = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), first_stage="simulation", **kw
        ).fit(d.u, y)
        default = RobustNSSMEstimator(PaperTransition(0.5, 0.5), PaperObservation(0.5), **kw).fit(d.u, y)
    assert staged.first_stage_.accepted and staged.first_stage_.rmse_after < staged.first_stage_.rmse_before
    assert staged.f_.b.item() > 0.8 and abs(staged.g_.c.item() - 0.1) < 0.02
    assert staged.log_likelihood_ > plain.log_likelihood_ + 50.0
    assert default.first_stage_.accepted and default.first_stage_.explained >= 0.5
    assert default.log_likelihood_ == pytest.approx(staged.log_likelihood_)
    bad = RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], first_stage="ls")
    with pytest.raises(ValueError, match="first_stage"):
        bad.fit(d.u, y)
    assert isinstance(staged.first_stage_.first_states, torch.Tensor)


def test_fit_independent_runs_the_first_stage_per_data_set():
    from torch_nssm import fit_independent

    sets = [make_paper_example(n_samples=150, random_state=s) for s in (3, 4)]
    proto = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=40, n_iter=3,
        random_state=0, first_stage="simulation",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = fit_independent(proto, [d.u for d in sets], [d.y for d in sets])
    assert all(f.first_stage_.accepted for f in fits)
    assert fits[0].first_stage_.rmse_after != fits[1].first_stage_.rmse_after
