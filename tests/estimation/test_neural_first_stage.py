"""The neural first stage: robust simulation-error training over windows (estimation.neural_first_stage)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_nssm.blocks.linear import LinearTransition
from torch_nssm.blocks.neural import MLPTransition
from torch_nssm.core.model import SequenceBatch, StateSpaceModel
from torch_nssm.estimation.neural_first_stage import (
    NeuralFirstStageOptions,
    fit_initial_states,
    holds_network,
    neural_first_stage,
    start_noise_levels,
    trimmed_rms,
)

DTYPE = torch.float64


class Identity(torch.nn.Module):
    """``y = x`` (no parameters)."""

    def forward(self, x, u):
        return x


def _plant(n: int, seed: int, outliers: float = 0.0, x0: float = 0.0):
    """``x+ = 0.6 x + 0.8 tanh(1.5 u) + w``, ``y = x + v`` (w s.d. 0.02, v s.d. 0.02), a share of
    the outputs shifted by +-(1-3): an input nonlinearity no linear model simulates."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    x = np.empty(n)
    x[0] = x0
    for k in range(n - 1):
        x[k + 1] = 0.6 * x[k] + 0.8 * np.tanh(1.5 * u[k]) + 0.02 * rng.normal()
    y = x + 0.02 * rng.normal(size=n)
    clean = y.copy()
    bad = rng.random(n) < outliers
    y[bad] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(1, 3, bad.sum())
    return u, y, x, clean


def _batch(u, y) -> SequenceBatch:
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=float).reshape(len(a), -1))  # noqa: E731
    return SequenceBatch.from_sequences([t(u)], [t(y)])


def _simulate(f, u, x0) -> np.ndarray:
    with torch.no_grad():
        x = torch.tensor([[float(x0)]], dtype=DTYPE)
        out = []
        for uk in u:
            out.append(float(x[0, 0]))
            x = f(x, torch.tensor([[uk]], dtype=DTYPE))
    return np.array(out)


FAST = NeuralFirstStageOptions(horizon=20, max_horizon=40, max_iter=60, eval_every=20)


@pytest.fixture(scope="module")
def trained():
    """An MLP and a linear model trained the same way on 400 samples with 5 % outliers."""
    u, y, _, _ = _plant(400, 0, outliers=0.05)
    data = _batch(u, y)
    out = {}
    for name, f in (
        ("mlp", MLPTransition(1, 1, hidden=(8,), random_state=0)),
        ("linear", LinearTransition(1, 1)),
    ):
        model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
        out[name] = (f, neural_first_stage(model, data, FAST))
    return out


def test_trains_a_network_that_simulates_better_than_the_best_linear_model(trained):
    u, _, x, _ = _plant(400, 1)  # a fresh validation record, from rest
    f_mlp, report = trained["mlp"]
    f_lin, report_lin = trained["linear"]
    assert report.accepted and report.improved and report_lin.accepted
    assert report.free_run_after < 0.2 * report.free_run_before
    assert report.optimizer == "lbfgs" and report.loss == "cauchy" and report.horizon == 20
    assert report.first_states.shape == (1, 1) and report.encoder is None
    assert len(report.train_losses) == len(report.validation_losses) == report.evaluations >= 2
    # the restored parameters are those of the best held-out score
    assert report.validation_losses[
        report.validation_losses.index(min(report.validation_losses))
    ] == pytest.approx(min(report.validation_losses))
    rmse = lambda f: float(np.sqrt(np.mean((_simulate(f, u, 0.0) - x) ** 2)))  # noqa: E731
    # measured: MLP 0.03-0.04, the best linear simulation 0.14 (the tanh of the input)
    assert rmse(f_mlp) < 0.4 * rmse(f_lin)
    assert rmse(f_mlp) < 0.06


def test_robust_loss_ignores_outliers_squared_loss_does_not():
    """A linear model trained by simulation error: with 10 % gross outliers the Cauchy loss lands
    where the clean data's fit does, least squares does not."""
    rng = np.random.default_rng(3)
    n = 600
    u = rng.normal(size=n)
    x = np.zeros(n)
    for k in range(n - 1):
        x[k + 1] = 0.8 * x[k] + 0.5 * u[k]
    y = x + 0.01 * rng.normal(size=n)
    y_bad = y.copy()
    bad = rng.random(n) < 0.1
    y_bad[bad] += 5.0 * rng.choice([-1.0, 1.0], bad.sum())
    options = dict(horizon=25, max_horizon=50, max_iter=60, validation_fraction=0.0)
    fits = {}
    for label, yy, loss in (
        ("clean", y, "cauchy"),
        ("robust", y_bad, "cauchy"),
        ("squared", y_bad, "squared"),
    ):
        f = LinearTransition(1, 1)
        model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
        report = neural_first_stage(model, _batch(u, yy), NeuralFirstStageOptions(loss=loss, **options))
        assert report.accepted
        fits[label] = np.array([f.A.item(), f.B.item()])
    np.testing.assert_allclose(fits["clean"], [0.8, 0.5], atol=0.01)
    np.testing.assert_allclose(fits["robust"], [0.8, 0.5], atol=0.01)
    assert np.abs(fits["squared"] - [0.8, 0.5]).max() > 0.03


def test_adam_path_trains_with_an_encoder():
    u, y, _, _ = _plant(300, 0)
    f = MLPTransition(1, 1, hidden=(8,), random_state=0)
    model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
    options = NeuralFirstStageOptions(
        optimizer="adam",
        horizon=20,
        encoder_lags=5,
        encoder_hidden=(16,),
        batch_size=32,
        max_iter=150,
        eval_every=25,
        learning_rate=1e-2,
    )
    first = neural_first_stage(model, _batch(u, y), options, generator=torch.Generator().manual_seed(0))
    assert first.accepted and first.free_run_after < 0.5 * first.free_run_before
    assert first.encoder is not None and first.iterations <= 150 and first.evaluations >= 2
    state = {k: v.clone() for k, v in f.state_dict().items()}
    # reproducible with the same generator
    f2 = MLPTransition(1, 1, hidden=(8,), random_state=0)
    model2 = StateSpaceModel(f2, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
    neural_first_stage(model2, _batch(u, y), options, generator=torch.Generator().manual_seed(0))
    assert all(torch.equal(v, f2.state_dict()[k]) for k, v in state.items())


def test_not_improving_restores_the_modules():
    """A start that already simulates the record (the truth, noise-free data) cannot be improved:
    the modules come back unchanged and the report says so."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=200)
    f = LinearTransition(1, 1, A=[[0.5]], B=[[1.0]])
    x = _simulate(f, u, 0.0)
    model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
    before = {k: v.clone() for k, v in f.state_dict().items()}
    report = neural_first_stage(model, _batch(u, x), NeuralFirstStageOptions(horizon=20, max_iter=10))
    assert not report.accepted and not report.improved
    assert report.free_run_before == pytest.approx(0.0, abs=1e-12)
    assert all(torch.equal(v, f.state_dict()[k]) for k, v in before.items())


def test_first_states_noise_levels_and_helpers():
    u, y, x, clean = _plant(300, 2, x0=1.5)
    f = LinearTransition(1, 1, A=[[0.6]], B=[[0.8]])
    model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
    x0 = fit_initial_states(model, _batch(u, y))
    assert x0.shape == (1, 1) and abs(float(x0[0, 0]) - 1.5) < 0.1
    Rw, Rv = start_noise_levels(model, _batch(u, y), x0)
    assert Rw.shape == (1, 1) and Rv.shape == (1, 1) and float(Rw) > 0 and float(Rv) > 0
    # the trimmed RMS: the largest 10 % left out, NaN ignored, inf propagated
    e = torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 100.0, math.nan], dtype=DTYPE)
    assert trimmed_rms(e) == pytest.approx(1.0)
    assert trimmed_rms(torch.tensor([1.0, math.inf])) == math.inf
    assert math.isnan(trimmed_rms(torch.tensor([math.nan])))
    mlp = StateSpaceModel(MLPTransition(1, 1, hidden=(4,)), Identity(), None, None, torch.zeros(1), None)
    assert holds_network(mlp) and not holds_network(model)


@pytest.mark.parametrize(
    "options, match",
    [
        (dict(optimizer="sgd"), "optimizer"),
        (dict(loss="huber"), "loss"),
        (dict(horizon=1), "horizon"),
        (dict(validation_fraction=1.0), "validation_fraction"),
        (dict(max_iter=0), "max_iter"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(max_seconds=-1.0), "max_seconds"),
        (dict(weight_decay=-1e-3), "weight_decay"),
        (dict(weight_decay=math.nan), "weight_decay"),
        (dict(weight_decay=math.inf), "weight_decay"),
        (dict(weight_decay="1e-3"), "weight_decay"),
    ],
)
def test_bad_options_are_named(options, match):
    with pytest.raises(ValueError, match=match):
        NeuralFirstStageOptions(**options).check()


def test_adam_needs_records_longer_than_a_window():
    u, y, _, _ = _plant(30, 0)
    model = StateSpaceModel(
        MLPTransition(1, 1, hidden=(4,)), Identity(), None, None, torch.zeros(1, dtype=DTYPE), None
    )
    with pytest.raises(ValueError, match="too short"):
        neural_first_stage(
            model, _batch(u, y), NeuralFirstStageOptions(optimizer="adam", horizon=20, encoder_lags=20)
        )


def test_default_iteration_cap_depends_on_a_held_out_part(monkeypatch):
    """Without ``max_iter`` each LBFGS phase stops at ``LBFGS_MAX_ITER`` iterations when a held-out
    part scores the early stop, and at ``LBFGS_MAX_ITER_NO_HOLDOUT`` when nothing is held out."""
    from torch_nssm.estimation import neural_first_stage as nfs

    monkeypatch.setattr(nfs, "LBFGS_MAX_ITER", 12)
    monkeypatch.setattr(nfs, "LBFGS_MAX_ITER_NO_HOLDOUT", 6)
    u, y, _, _ = _plant(300, 3)
    data = _batch(u, y)
    base = dict(horizon=20, max_horizon=40, eval_every=3, patience=100)  # two phases, no early stop
    for fraction, cap in ((0.2, 12), (0.0, 6)):
        model = StateSpaceModel(
            MLPTransition(1, 1, hidden=(4,), random_state=0), Identity(), None, None, torch.zeros(1), None
        )
        options = NeuralFirstStageOptions(validation_fraction=fraction, **base)
        report = neural_first_stage(model, data, options)
        assert report.stop_reason == "max_iter"
        assert report.iterations == 2 * cap  # each of the two phases runs to its cap


class Position(torch.nn.Module):
    """``y = x[0]``: the first state measured (no parameters)."""

    def forward(self, x, u):
        return x[..., :1]


def _oscillator(n: int, seed: int):
    """A lightly damped oscillator, 10 samples per period, state ``[position, velocity]`` (the velocity's
    spread about 100 times the position's, as in mm and mm/s at 150 Hz), position measured."""
    rng = np.random.default_rng(seed)
    dt, w, zeta = 1.0 / 150.0, 2 * math.pi * 15.0, 0.05
    u = rng.normal(size=n)
    x = np.zeros((n, 2))
    for k in range(n - 1):
        vel = x[k, 1] + dt * (-(w**2) * x[k, 0] - 2 * zeta * w * x[k, 1] + 1000.0 * u[k])
        x[k + 1] = [x[k, 0] + dt * vel, vel]
    return u, x[:, 0] + 0.01 * rng.normal(size=n), x


def test_lbfgs_windows_states_move_in_the_networks_state_units():
    """Measuring the velocity in units 1024 times smaller (its normalisation scaled alike) trains the
    same network: the windows' first states are free in units of the network's ``x_scale``, so LBFGS
    takes the same steps; in raw units the rescaled state's curvature changes 2**20-fold."""
    u, y, x = _oscillator(300, 0)
    data = _batch(u, y)
    spread, step = x.std(0), np.diff(x, axis=0).std(0)
    options = NeuralFirstStageOptions(horizon=20, max_horizon=20, max_iter=40, eval_every=20)
    runs = []
    for c in (1.0, 1024.0):  # a power of 2: the rescaled arithmetic is exact
        units = np.array([1.0, c])
        f = MLPTransition(
            2, 1, hidden=(8,), x_mean=0.0, x_scale=spread * units, out_scale=step * units, random_state=0
        )
        model = StateSpaceModel(f, Position(), None, None, torch.zeros(2, dtype=DTYPE), None)
        report = neural_first_stage(model, data, options)
        runs.append((f, report, units))
    (f1, r1, _), (f2, r2, units) = runs
    assert r1.iterations == r2.iterations > 0
    np.testing.assert_allclose(r2.free_run_after, r1.free_run_after, rtol=1e-9)
    for a, b in zip(f1.parameters(), f2.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    scaled = r1.first_states * torch.as_tensor(units)
    torch.testing.assert_close(r2.first_states, scaled, rtol=1e-9, atol=1e-12)


def test_phases_double_past_four_horizons_only_while_the_held_out_score_improves():
    """By default the LBFGS phases' windows double to ``4 * horizon``, then on while the last phase
    improved the held-out score, up to the longest training part; ``max_horizon`` fixes them; with
    nothing held out they stop at ``4 * horizon``."""
    from torch_nssm.estimation.neural_first_stage import _next_horizon, _Problem

    u, y, _, _ = _plant(1000, 0)
    data = _batch(u, y)
    model = StateSpaceModel(
        MLPTransition(1, 1, hidden=(4,), random_state=0), Identity(), None, None, torch.zeros(1), None
    )
    opt = NeuralFirstStageOptions(horizon=20)  # 150 samples held out: a training part of 850
    problem = _Problem(model, data, opt)
    assert [_next_horizon(opt, problem, H, False) for H in (20, 40, 80)] == [40, 80, None]
    assert [_next_horizon(opt, problem, H, True) for H in (80, 160, 320, 640)] == [160, 320, 640, None]
    fixed = NeuralFirstStageOptions(horizon=20, max_horizon=40)
    assert _next_horizon(fixed, problem, 20, False) == 40
    assert _next_horizon(fixed, problem, 40, True) is None
    no_holdout = NeuralFirstStageOptions(horizon=20, validation_fraction=0.0)
    problem = _Problem(model, data, no_holdout)
    assert _next_horizon(no_holdout, problem, 40, False) == 80
    assert _next_horizon(no_holdout, problem, 80, True) is None


def test_phases_are_more_patient_where_the_held_out_part_is_short():
    """The LBFGS phases' default patience is 20 held-out evaluations where the held-out parts hold
    fewer than 10,000 samples (a short held-out part is a weak guide of progress), 6 where they
    hold more or where nothing is held out; ``patience`` overrides it, and a short record's phase
    ends 20 evaluations after its best score."""
    from torch_nssm.estimation.neural_first_stage import _lbfgs_patience, _Problem

    model = StateSpaceModel(
        MLPTransition(1, 1, hidden=(4,), random_state=0), Identity(), None, None, torch.zeros(1), None
    )
    opt = NeuralFirstStageOptions(horizon=20)
    short = _Problem(model, _batch(*_plant(1000, 0)[:2]), opt)  # 150 samples held out
    assert _lbfgs_patience(short) == 20
    long = _Problem(model, _batch(*_plant(70_000, 0)[:2]), opt)  # 10,500 held out
    assert _lbfgs_patience(long) == 6
    none = _Problem(model, _batch(*_plant(1000, 0)[:2]), NeuralFirstStageOptions(validation_fraction=0))
    assert _lbfgs_patience(none) == 6

    data = _batch(*_plant(600, 0)[:2])  # one phase of 20-sample windows, 90 samples held out
    for patience, expected in ((None, 20), (3, 3)):
        model = StateSpaceModel(
            MLPTransition(1, 1, hidden=(8,), random_state=0), Identity(), None, None, torch.zeros(1), None
        )
        options = NeuralFirstStageOptions(horizon=20, max_horizon=20, patience=patience)
        report = neural_first_stage(model, data, options)
        scores = report.validation_losses
        assert report.stop_reason == "patience"
        assert len(scores) - 1 - scores.index(min(scores)) == expected


@pytest.mark.parametrize("optimizer", ["lbfgs", "adam"])
def test_weight_decay_shrinks_the_networks_weights(optimizer):
    """``weight_decay`` adds an L2 penalty on the linear layers' weights: the same training ends
    with smaller weights and a network that still simulates the record better than its start."""
    from torch_nssm.estimation.neural_first_stage import _weight_penalty

    u, y, _, _ = _plant(400, 0)
    data = _batch(u, y)
    opt = dict(optimizer=optimizer, horizon=20, max_iter=60, eval_every=20, encoder_lags=5)
    if optimizer == "lbfgs":
        opt["max_horizon"] = 40
    weights, reports = {}, {}
    for decay in (0.0, 0.05):
        f = MLPTransition(1, 1, hidden=(8,), random_state=0)
        model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
        reports[decay] = neural_first_stage(model, data, NeuralFirstStageOptions(**opt, weight_decay=decay))
        with torch.no_grad():
            weights[decay] = float(_weight_penalty((f,), 1.0))
    assert weights[0.05] < 0.8 * weights[0.0]
    assert reports[0.05].accepted and reports[0.05].free_run_after < reports[0.05].free_run_before


def test_the_kept_iterate_weighs_the_whole_records_free_run():
    """With whole-record free-run scores the kept iterate has the best held-out score among the
    evaluations whose free run is within ``FREE_RUN_SLACK`` of the best one (checked against a
    brute-force choice after every evaluation, NaN scores included), unless its held-out score is
    more than ``HELD_OUT_GUARD`` times the best; without them, the best held-out score; the early
    stop's best score follows the held-out score alone."""
    from torch_nssm.estimation.neural_first_stage import FREE_RUN_SLACK, HELD_OUT_GUARD, _Best

    rng = np.random.default_rng(0)
    net = torch.nn.Linear(1, 1)
    for trial in range(20):
        with_free = trial % 4 != 3
        best, seen = _Best((net,)), []
        for it in range(1, 41):
            held, free = rng.lognormal(0.0, 0.5, size=2)
            if rng.random() < 0.1:
                held = math.nan
            if rng.random() < 0.1:
                free = math.inf
            with torch.no_grad():
                net.bias.fill_(float(it))  # the snapshot names its iteration
            best.record(0.0, held, it, free if with_free else None)
            seen.append((it, held, free))
            held_best = [s for s in seen if math.isfinite(s[1])]
            expected = min(held_best, key=lambda s: s[1])[0] if held_best else 0
            both = [s for s in held_best if math.isfinite(s[2])]
            if with_free and both:
                floor = min(s[2] for s in both)
                pick = min([s for s in both if s[2] <= FREE_RUN_SLACK * floor], key=lambda s: s[1])
                if pick[1] <= HELD_OUT_GUARD * min(s[1] for s in held_best):
                    expected = pick[0]
            assert best.kept_iteration == expected
            assert best.score == (min(s[1] for s in held_best) if held_best else math.inf)
        best.restore()
        assert float(net.bias.detach()) == best.kept_iteration
        assert len(best.free_runs) == (40 if with_free else 0)


def test_short_held_out_parts_keep_by_the_free_run_too(trained):
    """A short record's report scores the whole free run at every evaluation, and the parameters
    kept are the rule's choice: their free run (``free_run_after``) is that evaluation's."""
    from torch_nssm.estimation.neural_first_stage import (
        FREE_RUN_SLACK,
        HELD_OUT_GUARD,
        _robust_center_scale,
    )

    report = trained["mlp"][1]
    assert len(report.free_runs) == report.evaluations == len(report.validation_losses)
    floor = min(report.free_runs)
    eligible = [i for i, w in enumerate(report.free_runs) if w <= FREE_RUN_SLACK * floor]
    kept = min(eligible, key=lambda i: report.validation_losses[i])
    if report.validation_losses[kept] > HELD_OUT_GUARD * min(report.validation_losses):
        kept = int(np.argmin(report.validation_losses))
    u, y, _, _ = _plant(400, 0, outliers=0.05)
    _, scale = _robust_center_scale(torch.as_tensor(y, dtype=DTYPE).reshape(-1, 1))
    assert report.free_run_after == pytest.approx(report.free_runs[kept] * float(scale), rel=1e-9)


def test_the_kept_iterates_free_run_runs_long_records_in_stretches():
    """The free-run score is the whole records' free run from the first windows' states where the
    records are shorter than ``FREE_RUN_SPAN`` (equal to ``_Problem.record_errors``'s), and on
    longer ones the stretches' free runs from the windows that start them, run side by side
    (equal to running each stretch alone), the held-out end in each record's last stretch."""
    from torch_nssm.estimation.neural_first_stage import FREE_RUN_SPAN, _Problem, _simulate, _Tiling

    f = MLPTransition(1, 1, hidden=(8,), random_state=0)
    model = StateSpaceModel(f, Identity(), None, None, torch.zeros(1, dtype=DTYPE), None)
    rng = np.random.default_rng(1)

    def batch(lengths):
        us = [torch.as_tensor(rng.normal(size=(n, 1))) for n in lengths]
        ys = [torch.as_tensor(rng.normal(size=(n, 1))) for n in lengths]
        ys[0][5] = math.nan  # a missing output
        return SequenceBatch.from_sequences(us, ys)

    for lengths, H in (([2000, 1500], 50), ([2000], 1600), ([9000, 3000], 50), ([9000, 3000], 1600)):
        problem = _Problem(model, batch(lengths), NeuralFirstStageOptions())
        tiling = _Tiling(problem, H, torch.ones(1, dtype=DTYPE))
        tiling.start_at(torch.as_tensor(rng.normal(size=(len(tiling.spans), 1))))
        score = tiling.free_run(f, model.g)
        span = H * max(1, FREE_RUN_SPAN // H)
        errors = []
        for i, (b, k) in enumerate(tiling.spans):
            if k % span:
                continue
            n, end = int(problem.lengths[b]), int(problem.lengths[b] - problem.n_val[b])
            stop = n if k + span >= end else k + span
            y_hat, _ = _simulate(f, model.g, tiling.x[i : i + 1], problem.u[k:stop, b].unsqueeze(0))
            e, mask = problem.errors(problem.y[k:stop, b], y_hat[0])
            errors.append(torch.where(mask, e, torch.full_like(e, math.nan)))
        assert score == pytest.approx(trimmed_rms(torch.cat(errors)), rel=1e-12)
        whole = trimmed_rms(problem.record_errors(f, model.g, tiling.x[tiling.first]))
        if max(lengths) <= FREE_RUN_SPAN:
            assert score == pytest.approx(whole, rel=1e-12)
        else:
            assert len(errors) > len(lengths) and score != pytest.approx(whole, rel=1e-3)
