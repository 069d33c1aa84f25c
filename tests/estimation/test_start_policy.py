"""How a fit starts and what it keeps: a simulation model holds its process noise, a prediction
model estimates it, a process noise not given is sized from the data, EM cannot spoil a
simulation model's simulation, and an iteration whose likelihood collapses is undone."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import (
    PENDULUM_START,
    PENDULUM_TRUE,
    make_paper_example,
    make_pendulum,
    pendulum_model,
)
from torch_nssm.estimation import loop as loop_module
from torch_nssm.estimation.loop import EMOptions, run_em
from torch_nssm.estimation.start import (
    PROCESS_NOISE_SHARE,
    UNEXPLAINED_SHARE,
    Start,
    check_simulation,
    scaled_process_noise,
)
from torch_nssm.models import PaperObservation, PaperTransition


@pytest.fixture(scope="module")
def pendulum():
    return make_pendulum(n_samples=400, outlier_fraction=0.03, random_state=0, n_validation=400)


def _fit(d, **kw):
    f, g = pendulum_model(PENDULUM_START)
    options = dict(x0_mean=list(d.x0_guess), n_particles=60, n_iter=8, random_state=0)
    options.update(kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RobustNSSMEstimator(f, g, **options).fit(d.u, d.y)


def _moved(history, name):
    values = np.asarray(history[name], dtype=float)
    return not np.all(values == values[0])


def test_a_simulation_model_keeps_its_f_and_g_and_estimates_the_noise(pendulum):
    est = _fit(pendulum)
    assert est.first_stage_.accepted and est.first_stage_.explained >= 0.9
    assert est.simulation_model_ and est.fit_Rw_
    assert not any(_moved(est.history_, f"f.{name}") for name in PENDULUM_TRUE)  # the first stage's f
    assert _moved(est.history_, "Rw") and _moved(est.history_, "Rv")
    # the measurement noise starts at the first stage's output errors, not at 2 % of y's variance
    assert est.history_["Rv"][0][0, 0] < 0.01 * np.var(pendulum.y)
    for name, true in PENDULUM_TRUE.items():
        assert abs(float(getattr(est.f_, name).detach()) / true - 1) < 0.1
    # the free run is the first stage's, from its first state; the prior's spread about that
    # state is EM's, far narrower than the states' spread over the record (the start's)
    assert est.first_stage_.free_run_scale_after_em == est.first_stage_.free_run_scale_before_em
    assert not _moved(est.history_, "x0_mean")
    states = est.smooth(pendulum.u, pendulum.y).mean
    assert np.all(np.diag(est.x0_cov_) < 0.05 * states.var(0))


def test_a_prediction_model_moves_f_and_g(pendulum):
    est = _fit(pendulum, focus="prediction")
    assert not est.simulation_model_ and est.fit_Rw_
    assert any(_moved(est.history_, f"f.{name}") for name in PENDULUM_TRUE)


def test_a_process_noise_not_given_is_sized_from_the_states_steps():
    d = make_paper_example(n_samples=200, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_iter=0, first_stage=None
        ).fit(d.u, d.y)
    model = est._fitted_model(torch.device("cpu"))
    model = replace(model, Rw=torch.eye(1, dtype=torch.float64))
    data, _ = est._batch(d.u, d.y, torch.device("cpu"), fitted=True)
    from torch_nssm.inference.prediction import free_run

    x = free_run(model, data.u)[0][:, 0, 0]
    expected = PROCESS_NOISE_SHARE * torch.var(x[1:] - x[:-1])
    torch.testing.assert_close(scaled_process_noise(model, data)[0, 0], expected)
    fitted = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_iter=1, first_stage=None,
        n_particles=30, random_state=0,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fitted.fit(d.u, d.y)
    # no first stage kept: the states must follow y through the process noise, a whole step's
    # variance (at least the general default 0.1)
    whole_step = max(float(expected) * UNEXPLAINED_SHARE / PROCESS_NOISE_SHARE, 0.1)
    assert fitted.history_["Rw"][0][0, 0] == pytest.approx(whole_step, rel=1e-9)
    given = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_iter=1, first_stage=None,
        n_particles=30, random_state=0, Rw_init=0.1,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        given.fit(d.u, d.y)
    assert given.history_["Rw"][0][0, 0] == 0.1


def test_the_simulation_check_says_when_em_moved_a_simulation_model_to_simulate_worse():
    d = make_paper_example(n_samples=150, random_state=0, Rw=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = RobustNSSMEstimator(PaperTransition(0.9, 1.0), PaperObservation(1.0), x0_mean=[0.0], n_iter=0)
        est.fit(d.u, d.y)
    staged = est._fitted_model(torch.device("cpu"))
    data, _ = est._batch(d.u, d.y, torch.device("cpu"), fitted=True)
    from torch_nssm.estimation.first_stage import FirstStageReport
    from torch_nssm.inference.prediction import free_run

    start = Start(staged, seeds=[0], limit=math.inf, init_jitter=1.0)
    start.first_stage = FirstStageReport(1.0, 1.0, 1.0, 1.0, True, 1, explained=0.95)
    start.staged, start.staged_run = staged, free_run(staged, data.u)
    worse = replace(staged, f=PaperTransition(0.5, 1.0).double())

    class Run:
        interrupted = False

    check = check_simulation(start, Run(), free_run(worse, data.u)[1], data)
    assert check.outcome == "worse" and check.after > check.before
    start.hold_modules = True  # a simulation model's EM does not move f and g: nothing to say
    assert check_simulation(start, Run(), free_run(worse, data.u)[1], data).outcome == "kept"
    Run.interrupted = True
    assert check_simulation(start, Run(), free_run(worse, data.u)[1], data).outcome == "interrupted"


def _paper_em_start():
    """The paper's example (N = 200) as EM's start: its model and data, no iteration run."""
    d = make_paper_example(n_samples=200, random_state=0)
    est = RobustNSSMEstimator(
        PaperTransition(0.9, 1.0), PaperObservation(1.0), x0_mean=[0.0], n_iter=0, first_stage=None
    ).fit(d.u, d.y)
    return est._fitted_model(torch.device("cpu")), est._batch(d.u, d.y, torch.device("cpu"), fitted=True)[0]


def test_an_iteration_whose_likelihood_collapses_is_undone_and_em_stops(monkeypatch):
    model, data = _paper_em_start()
    real = loop_module.m_step
    calls = {"n": 0}

    def sabotaged(models, *args, **kwargs):
        result = real(models, *args, **kwargs)
        calls["n"] += 1
        if calls["n"] == 3:  # the third M-step ruins g: the likelihood collapses
            with torch.no_grad():
                result.models[0].g.c.fill_(1e-3)
        return result

    monkeypatch.setattr(loop_module, "m_step", sabotaged)
    options = EMOptions(n_iter=10, tol=0.0)
    options.estep.n_particles = 50
    result = run_em([model], data, options, torch.Generator().manual_seed(0))[0]
    assert result.halted and "fell from" in result.halted
    assert result.n_done == 2 and not result.converged
    assert float(result.model.g.c) > 0.5  # the iterate before the ruinous M-step
    assert len(result.history["log_likelihood"]) == 3
    assert result.log_likelihood == pytest.approx(result.history["log_likelihood"][-1], abs=50)


def test_a_fall_of_the_estimate_alone_is_measured_again_and_em_goes_on(monkeypatch):
    """A log-likelihood estimate that falls by Monte Carlo error alone (here: made to fall) is
    measured again with more particles at both iterates; the iterate stands, its E-step (which the
    next M-step reads) runs again with those particles, and EM goes on."""
    model, data = _paper_em_start()
    real = loop_module.e_step
    particles = []

    def unlucky(model, data, options, *args, **kwargs):
        out = real(model, data, options, *args, **kwargs)
        particles.append(options.n_particles)
        if len(particles) == 3:  # the E-step after the second M-step: an estimate far too low
            out.filter.log_likelihood.sub_(1e4)
        return out

    monkeypatch.setattr(loop_module, "e_step", unlucky)
    options = EMOptions(n_iter=5, tol=0.0)
    options.estep.n_particles = 50
    result = run_em([model], data, options, torch.Generator().manual_seed(0))[0]
    assert result.halted is None and result.n_done == 5
    factor = loop_module.COLLAPSE_RECHECK_FACTOR
    assert particles[:4] == [50, 50, 50, factor * 50] and particles[4:] == [50] * 3
    lls = result.history["log_likelihood"]
    assert abs(lls[2] - lls[1]) < 100  # the estimate of the E-step run again


def test_the_measurement_noise_stays_above_the_rounding_of_an_output_on_a_grid():
    """An output recorded on a grid of step q (an encoder) has a measurement-noise variance of at
    least q**2 / 12, the rounding's own: EM's update is floored there, a start below it raised."""
    from torch_nssm.core.noise import StudentTNoise
    from torch_nssm.estimation.start import measurement_floor

    noise = StudentTNoise.initial(torch.tensor([[1e-6, 0.0], [0.0, 4.0]], dtype=torch.float64), 5.0)
    raised = noise.floored(torch.tensor([1e-2, 1.0], dtype=torch.float64))
    assert torch.allclose(raised.Rv, torch.tensor([[1e-2, 0.0], [0.0, 4.0]], dtype=torch.float64))
    assert noise.floored(torch.zeros(2, dtype=torch.float64)) is noise
    d = make_paper_example(n_samples=200, outlier_fraction=0.0, random_state=0)
    q = 0.1
    y = q * np.round(np.asarray(d.y) / q)
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=40, n_iter=2,
        random_state=0, Rv_init=[[1e-6]],
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(d.u, y)
    assert est.Rv_[0, 0] >= q**2 / 12 * (1 - 1e-9)
    batch = est._batch(d.u, d.y, torch.device("cpu"), fitted=True)[0]
    assert measurement_floor(batch) is None  # continuous data: no floor
