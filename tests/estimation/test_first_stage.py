"""The first stage: a robust simulation-error fit of f and g before EM (issue #13)."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import TANKS_START, TANKS_TRUE, make_paper_example, make_tanks, tanks_model
from torch_nssm.estimation.first_stage import simulation_error_fit
from torch_nssm.models import PaperObservation, PaperTransition


def _start(y, u):
    est = RobustNSSMEstimator(PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0])
    device = est._check_params()
    data, _ = est._batch(u, y, device, fitted=False)
    return est._initial_model(data, device), data


@pytest.mark.parametrize("windows", ["one", 50, "auto"])
def test_simulation_error_fit_recovers_the_dynamics_despite_outliers(windows):
    """Noise-free simulation of the paper's system (10 % outliers uniform in [-5, 5]): the Cauchy
    loss is not steered by the outliers, and the fitted model simulates the clean output; one
    window, fixed windows of 50 samples (multiple shooting) or the growing windows."""
    d = make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=2, Rw=1e-6)
    model, data = _start(d.y, d.u)
    if windows == "one":
        report = simulation_error_fit(model, data, horizons=None)
    elif windows == "auto":
        report = simulation_error_fit(model, data)
        assert report.stages[-1].horizon == 300 or report.horizon_limit  # reached the record or said why
        assert report.horizon == max(report.stages, key=lambda s: -s.free_run_scale).horizon
    else:
        report = simulation_error_fit(model, data, segment_length=windows)
    assert report.accepted and report.rmse_after < report.rmse_before
    assert report.n_windows == {"one": 1, 50: 6, "auto": report.n_windows}[windows]
    assert abs(model.f.a.item() - 0.9) < 0.03 and abs(model.f.b.item() - 1.0) < 0.05
    assert abs(model.g.c.item() - 1.0) < 0.05
    assert report.first_states.shape == (report.n_windows, 1)


def test_the_direct_fit_from_a_far_start_reaches_the_output_error_basin():
    """The suite's tanks (seed 1), one window over the record from the physically sized start: from
    a nearly Gauss-Newton first step (damping 1e-3) the fit ends in another basin (free-run judge
    0.78, validation RMSE 3.0 cm); damped as a far start is (COLD_DAMPING), it reaches the basin of
    scipy's output-error least squares from the same start (judge 0.0167, validation 0.21 cm)."""
    d = make_tanks(1024, random_state=1, n_validation=16)
    est = RobustNSSMEstimator(*tanks_model(TANKS_START), x0_mean=np.asarray(d.x0_guess, float).tolist())
    device = est._check_params()
    data, _ = est._batch(d.u, d.y, device, fitted=False)
    model = est._initial_model(data, device)
    report = simulation_error_fit(model, data, horizons=None)
    assert report.accepted and report.stages[0].status == "converged"
    assert report.loss_after < 0.03  # the output-error fit's judge: 0.0167
    assert abs(model.f.h1_max.item() / TANKS_TRUE["h1_max"] - 1.0) < 0.5


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


def test_initial_horizon_follows_the_outputs_correlation_time():
    """An AR(1) output with coefficient a has autocorrelation a^k: it falls below one half at
    k = log(0.5) / log(a); the first windows are twice that (spikes removed first)."""
    from torch_nssm.core.model import SequenceBatch
    from torch_nssm.estimation.first_stage import initial_horizon

    rng = np.random.default_rng(0)
    for a in (0.9, 0.99):
        y = np.zeros(20_000)
        for k in range(1, y.size):
            y[k] = a * y[k - 1] + rng.standard_normal()
        spiky = y.copy()
        spiky[rng.choice(y.size, 1000, replace=False)] += 50.0 * rng.standard_normal(1000)
        lag = np.log(0.5) / np.log(a)
        for values in (y, spiky):
            t = torch.as_tensor(values).reshape(-1, 1, 1)
            data = SequenceBatch(torch.zeros_like(t), t, torch.tensor([y.size]))
            assert 0.7 * 2 * lag < initial_horizon(data, 1) < 1.4 * 2 * lag


def test_stages_stop_where_the_simulation_diverges():
    d = make_paper_example(n_samples=400, random_state=0, Rw=1e-6)
    model, data = _start(d.y, d.u)
    with torch.no_grad():
        model.f.a.fill_(10.0)  # the simulation overflows after about 300 steps
    model.f.a.requires_grad_(False)
    report = simulation_error_fit(model, data, horizons=[10, 40, 400])
    assert [s.horizon for s in report.stages] == [10, 40, 400]
    assert report.stages[-1].status == "diverged"
    assert "diverges over windows of 400 samples" in report.horizon_limit
    assert report.horizon in (10, 40)


class _Interrupting(PaperTransition):
    """Raises KeyboardInterrupt (as Ctrl-C) after a number of calls."""

    calls = 0
    limit = 10**9

    def forward(self, x, u):
        type(self).calls += 1
        if type(self).calls > type(self).limit:
            type(self).limit = 10**9  # one Ctrl-C
            raise KeyboardInterrupt
        return super().forward(x, u)


def test_ctrl_c_in_the_first_stage_keeps_its_best_stage_and_no_em_runs():
    d = make_paper_example(n_samples=300, outlier_fraction=0.05, random_state=1, Rw=1e-6)
    f = _Interrupting(0.5, 0.5)
    _Interrupting.calls, _Interrupting.limit = 0, 10**9
    est = RobustNSSMEstimator(f, PaperObservation(0.5), x0_mean=[0.0], n_particles=50, random_state=0)
    model, data = _start(d.y, d.u)
    full = simulation_error_fit(replace_modules(model, _Interrupting(0.5, 0.5)), data)
    calls_per_run = _Interrupting.calls
    # interrupt well into the run: after the first stages, before the last
    _Interrupting.calls, _Interrupting.limit = 0, int(0.6 * calls_per_run)
    with pytest.warns(RuntimeWarning, match="interrupted .* during the first stage"):
        est.fit(d.u, d.y)
    _Interrupting.limit = 10**9
    assert est.first_stage_.interrupted and est.n_iter_ == 0
    assert len(est.first_stage_.stages) < len(full.stages) + 1
    assert np.isfinite(est.log_likelihood_)


def replace_modules(model, f):
    from dataclasses import replace

    return replace(model, f=f)


@pytest.mark.filterwarnings("ignore:only 300 observed samples")
def test_a_grey_box_fits_its_physical_part_first_with_the_network_held():
    """``physical_part_first``: a GreyBoxTransition's physical parameters (30-50 % off) are fitted by
    the physical first stage while the correction's layers are held (unchanged, their
    ``requires_grad`` restored); a network without physical parameters, or a grey box observed
    through a network, gets ``None``."""
    from torch_nssm.datasets import PENDULUM_START, PENDULUM_TRUE, make_pendulum, pendulum_model
    from torch_nssm.estimation.start import physical_part_first
    from torch_nssm.neural import GreyBoxTransition, MLPObservation, MLPTransition

    d = make_pendulum(300, random_state=0, n_validation=10, Rw=0.0)
    f_phys, g = pendulum_model(PENDULUM_START)
    grey = GreyBoxTransition(f_phys, 2, 1, hidden=(8,), random_state=0)
    before = [p.detach().clone() for p in grey.net.parameters()]
    est = RobustNSSMEstimator(grey, g, x0_mean=[0.0, 0.0])
    device = est._check_params()
    data, _ = est._batch(d.u, d.y, device, fitted=False)
    model = est._initial_model(data, device)
    report = physical_part_first(model, data)
    assert report is not None and report.accepted
    for k, v in PENDULUM_TRUE.items():
        assert getattr(model.f.physical, k).item() == pytest.approx(v, rel=0.02), k
    for p, p0 in zip(model.f.net.parameters(), before):
        assert p.requires_grad and torch.equal(p, p0)
    net_model = RobustNSSMEstimator(MLPTransition(2, 1, hidden=(8,)), g, x0_mean=[0.0, 0.0])._initial_model(
        data, device
    )
    assert physical_part_first(net_model, data) is None
    neural_g = RobustNSSMEstimator(
        GreyBoxTransition(pendulum_model(PENDULUM_START)[0], 2, 1, hidden=(8,)), MLPObservation(2, 1, 1),
        x0_mean=[0.0, 0.0],
    )._initial_model(data, device)
    assert physical_part_first(neural_g, data) is None  # no physical g to fit f's physics through


def _grey_pendulum() -> RobustNSSMEstimator:
    """A grey box of the pendulum at its start parameters (an 8-unit correction), 2 EM iterations."""
    from torch_nssm.datasets import PENDULUM_START, pendulum_model
    from torch_nssm.neural import GreyBoxTransition

    grey = GreyBoxTransition(pendulum_model(PENDULUM_START)[0], 2, 1, hidden=(8,), random_state=0)
    return RobustNSSMEstimator(grey, pendulum_model()[1], x0_mean=[0.0, 0.0], n_iter=2, n_particles=50,
                               random_state=0)


@pytest.mark.filterwarnings("ignore:only 300 observed samples")
def test_a_grey_box_whose_network_does_not_improve_starts_em_at_its_physical_fit(monkeypatch):
    """Where the neural first stage does not improve on the physical part's fit (forced here: its
    modules restored, ``accepted=False``), ``simulation_start`` says so and starts EM at the
    physical fit, and ``fit`` keeps the physical stage's report as ``first_stage_``."""
    import dataclasses

    import torch_nssm.estimation.start as start_module
    from torch_nssm import simulation_start
    from torch_nssm.datasets import PENDULUM_TRUE, make_pendulum
    from torch_nssm.estimation.first_stage import FirstStageReport

    real = start_module.neural_first_stage

    def unimproved(model, data, options=None, *, generator=None):
        kept = [copy.deepcopy(m.state_dict()) for m in (model.f, model.g)]
        report = real(model, data, dataclasses.replace(options, max_iter=5), generator=generator)
        for m, state in zip((model.f, model.g), kept):
            m.load_state_dict(state)
        report.accepted = False
        return report

    monkeypatch.setattr(start_module, "neural_first_stage", unimproved)
    d = make_pendulum(300, random_state=0, n_validation=10, Rw=0.0)

    with pytest.warns(RuntimeWarning, match="physical part's fit"):
        started = simulation_start(_grey_pendulum(), d.u, d.y)
    assert started.f.physical.g_over_l.item() == pytest.approx(PENDULUM_TRUE["g_over_l"], rel=0.02)
    assert started.fit_Rw is False and started.first_stage is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted = _grey_pendulum().fit(d.u, d.y)
    assert isinstance(fitted.first_stage_, FirstStageReport) and fitted.first_stage_.accepted
    assert fitted.f_.physical.g_over_l.item() == pytest.approx(PENDULUM_TRUE["g_over_l"], rel=0.02)


@pytest.mark.filterwarnings("ignore:only 300 observed samples")
@pytest.mark.filterwarnings("ignore:the model's noise-free simulation explains")
def test_ctrl_c_in_a_grey_box_physical_stage_ends_the_first_stage(monkeypatch):
    """Ctrl-C during a grey box's physical stage (its report ``interrupted``): the network is not
    trained after it, ``fit`` ends with the first stage's message and ``simulation_start`` raises
    ``KeyboardInterrupt``."""
    import torch_nssm.estimation.start as start_module
    from torch_nssm import simulation_start
    from torch_nssm.datasets import make_pendulum

    real = start_module.simulation_error_fit

    def interrupted(model, data, **kw):
        report = real(model, data, horizons=[50], max_iter=3)
        report.interrupted = True
        return report

    def untouched(*args, **kw):
        raise AssertionError("the network trained after Ctrl-C")

    monkeypatch.setattr(start_module, "simulation_error_fit", interrupted)
    monkeypatch.setattr(start_module, "neural_first_stage", untouched)
    d = make_pendulum(300, random_state=0, n_validation=10, Rw=0.0)

    with pytest.warns(RuntimeWarning, match="interrupted"):
        fitted = _grey_pendulum().fit(d.u, d.y)
    assert fitted.first_stage_.interrupted
    with pytest.raises(KeyboardInterrupt):
        simulation_start(_grey_pendulum(), d.u, d.y)
