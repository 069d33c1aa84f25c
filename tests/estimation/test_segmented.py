"""The time-parallel E-step (``segment_length``): window layout, exactness of the per-window M-step,
and the approximation against exact references (Kalman / RTS, the unsegmented fit)."""

from __future__ import annotations

import copy
import math
import warnings

import numpy as np
import pytest
import torch
from conftest import DTYPE, generator, make_linear_system, nonlinear_model, simulate
from reference import kalman_filter, rts_smoother, simulate_linear

from torch_nssm import RobustNSSMEstimator, fit_independent
from torch_nssm.core.model import SequenceBatch
from torch_nssm.datasets import make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.estimation.estep import EStepOptions, e_step, to_records
from torch_nssm.estimation.mstep import MStepOptions, m_step
from torch_nssm.inference.windows import cut


def _batch(us, ys) -> SequenceBatch:
    return SequenceBatch.from_sequences(
        [torch.as_tensor(u, dtype=DTYPE) for u in us], [torch.as_tensor(y, dtype=DTYPE) for y in ys]
    )


# --------------------------------------------------------------------------- the layout


@pytest.mark.parametrize("length, overlap", [(5, 2), (4, 7), (30, 3)])
def test_windows_own_every_step_once_and_see_their_context(length, overlap):
    rng = np.random.default_rng(0)
    lengths = [23, 17, 4]
    data = _batch([rng.normal(size=(n, 1)) for n in lengths], [rng.normal(size=(n, 2)) for n in lengths])
    w = cut(data, length, overlap)
    owned = w.owned()
    for b, n in enumerate(lengths):
        mine = (w.record == b).nonzero().flatten().tolist()
        covered = []
        for j in mine:
            a, z, s = int(w.own_start[j]), int(w.own_stop[j]), int(w.start[j])
            covered += list(range(a, z))
            assert s == max(0, a - overlap)  # burn-in, clipped at the record's start
            assert s + int(w.data.lengths[j]) == min(n, z + overlap)  # look-ahead, clipped at its end
            assert owned[:, j].sum() == z - a
            # the window's samples are the record's
            k = torch.arange(int(w.data.lengths[j]))
            torch.testing.assert_close(w.data.y[k, j], data.y[s + k, b])
            torch.testing.assert_close(w.data.u[k, j], data.u[s + k, b])
        assert covered == list(range(n))  # every step owned exactly once, in order
    # gather is the inverse of cutting on the records' steps
    back = w.gather(w.data.y)
    inside = data.step_mask
    torch.testing.assert_close(back[inside], data.y[inside])
    # the M-step's view: outputs outside the owned steps are missing, transitions counted once
    od = w.owned_data
    assert int(od.obs_mask.any(-1).sum()) == sum(lengths)
    assert int(od.transition_mask.sum()) == sum(n - 1 for n in lengths)


def test_invalid_windows_are_refused():
    data = _batch([np.zeros((10, 1))], [np.zeros((10, 1))])
    with pytest.raises(ValueError, match="segment_overlap"):
        cut(data, 5, 0)


# --------------------------------------------------------------------------- exactness of the M-step


@pytest.mark.parametrize("dof", [4.0, math.inf])
def test_per_window_m_step_equals_the_records_m_step(dof):
    """The M-step on the per-window output (owned steps only) equals the M-step on the same E-step
    stitched into records: ownership, the process scatter, the counts and the first state."""
    model = nonlinear_model(dof)
    rng = np.random.default_rng(1)
    us, ys = simulate(model, [300, 170], rng, outlier_rate=0.05)
    ys[0][10:14, 1] = math.nan  # gaps
    data = SequenceBatch.from_sequences(us, ys)
    opts = EStepOptions(n_particles=40, smoother="mcmc", segment_length=60, segment_overlap=15)
    est_w = e_step(model, data, opts, generator(0), records=False)
    assert est_w.windows is not None
    est_r = to_records(est_w, model, data)
    assert est_r.filter.particles.shape[:2] == (data.n_steps, data.n_sequences)
    torch.testing.assert_close(est_r.log_likelihood.sum(), est_w.log_likelihood.sum())
    mopts = MStepOptions()
    a = m_step([copy.deepcopy(model)], est_w.windows.owned_data, est_w, mopts).models[0]
    b = m_step([copy.deepcopy(model)], data, est_r, mopts).models[0]
    for name in ("Rw", "x0_mean", "x0_cov"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(a.noise.Rv, b.noise.Rv, rtol=1e-9, atol=1e-12)
    if math.isfinite(dof):
        torch.testing.assert_close(a.noise.dof, b.noise.dof, rtol=1e-7, atol=1e-9)
    for pa, pb in zip(
        list(a.f.parameters()) + list(a.g.parameters()), list(b.f.parameters()) + list(b.g.parameters())
    ):
        torch.testing.assert_close(pa, pb, rtol=1e-6, atol=1e-8)


# --------------------------------------------------------------------------- the approximation


@pytest.fixture(scope="module")
def long_linear_record():
    sysm = make_linear_system()
    rng = np.random.default_rng(0)
    n = 20_000
    u = rng.normal(size=(n, 1))
    _, y = simulate_linear(*sysm.matrices(), u, rng)
    kf = kalman_filter(*sysm.matrices(), u, y)
    sm, _ = rts_smoother(sysm.A, kf)
    return sysm, _batch([u], [y]), kf.log_likelihood, sm


def test_segmented_e_step_matches_kalman_and_rts_within_monte_carlo_error(long_linear_record):
    """N = 20,000: the segmented E-step's log-likelihood error (against Kalman) and smoothed-mean
    error (against RTS) are those of the exact single pass, within its Monte Carlo spread."""
    sysm, data, ll_exact, sm_exact = long_linear_record
    model = sysm.model()

    def run(segment_length, seed, previous=None):
        opts = EStepOptions(n_particles=100, segment_length=segment_length, segment_overlap=50)
        est = e_step(model, data, opts, generator(seed), previous)
        w = torch.softmax(est.smoother.log_weights[:, 0], -1).unsqueeze(-1)
        mean = (w * est.filter.particles[:, 0]).sum(1).numpy()
        err = float(np.sqrt(np.mean((mean - sm_exact) ** 2)))
        return float(est.log_likelihood.sum()) - ll_exact, err, est

    exact = np.array([run(None, s)[:2] for s in range(3)])
    seg, previous = [], None
    for s in range(3):  # the first from the warm-up pass, then from the previous E-step
        ll_err, err, previous = run(1000, 10 + s, previous)
        seg.append((ll_err, err))
    seg = np.array(seg)
    spread = max(exact[:, 0].std(ddof=1), seg[:, 0].std(ddof=1), 5.0)
    assert abs(seg[:, 0].mean() - exact[:, 0].mean()) < 4 * spread
    assert seg[:, 1].max() < 1.1 * exact[:, 1].max()


def _paper_fit(y, u, seed, segment_length=None):
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5, dtype=torch.float64),
        PaperObservation(0.5, dtype=torch.float64),
        x0_mean=[0.0],
        noise="student-t",
        n_particles=50,
        n_iter=20,
        tol=0.0,
        smoother="mcmc",
        segment_length=segment_length,
        segment_overlap=50,
        random_state=seed,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
    h = est.history_
    theta = np.array([np.mean(np.asarray(h[k][-5:], dtype=float)) for k in ("f.a", "f.b", "g.c")])
    return est, theta


@pytest.mark.slow  # ~35 s: the E-step's agreement with Kalman/RTS stays in the default run
def test_segmented_fit_equals_the_exact_fit_within_monte_carlo_error():
    """The paper's example (N = 3,000, 10 % outliers): a, b, c of the segmented fit (windows of 500)
    agree with those of the exact single pass within the spread over seeds."""
    data = make_paper_example(n_samples=3000, noise="student-t", random_state=3)
    exact = np.array([_paper_fit(data.y, data.u, s)[1] for s in (0, 1)])
    seg_fits = [_paper_fit(data.y, data.u, s, segment_length=500) for s in (0, 1)]
    seg = np.array([t for _, t in seg_fits])
    spread = np.maximum(np.abs(exact[0] - exact[1]), 0.01)
    assert np.all(np.abs(seg.mean(0) - exact.mean(0)) < 3 * spread), (seg, exact)
    assert np.all(np.abs(seg.mean(0) - [0.9, 1.0, 1.0]) < 0.06)
    # the fitted estimator's record-level outputs have the records' shapes
    est = seg_fits[0][0]
    assert est.outlier_weights_.shape == (3000,)
    assert np.isfinite(est.score(data.u, data.y))
    smoothed = est.smooth(data.u, data.y)
    assert smoothed.mean.shape == (3000, 1)
    assert np.sqrt(np.mean((smoothed.mean[:, 0] - data.x[:, 0]) ** 2)) < 0.5


def test_segmented_fit_of_several_records_of_different_lengths():
    data = [make_paper_example(n_samples=n, random_state=i) for i, n in enumerate((1500, 700, 90))]
    u, y = [d.u for d in data], [d.y for d in data]
    est, theta = _paper_fit(y, u, 0, segment_length=400)
    ref, theta_ref = _paper_fit(y, u, 0)
    assert np.all(np.abs(theta - theta_ref) < 0.08)
    assert [np.asarray(w).shape[0] for w in est.outlier_weights_] == [1500, 700, 90]
    # the per-record log-likelihood of the last E-step is close to the exact pass's
    assert abs(est.log_likelihood(u, y) - ref.log_likelihood(u, y)) < 0.02 * abs(ref.log_likelihood(u, y))


def test_segment_length_is_checked_and_refused_for_independent_fits():
    est = RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], segment_length=0)
    with pytest.raises(ValueError, match="segment_length"):
        est.fit(np.zeros(50), np.zeros(50))
    est.set_params(segment_length=20)
    with pytest.raises(ValueError, match="segment_length"):
        fit_independent(est, [np.zeros(50)] * 2, [np.zeros(50)] * 2)


def test_segmented_smoothing_of_a_new_record_with_its_own_first_state():
    """``smooth(..., x0=...)`` gives each record its own prior; the windows take their record's."""
    data = make_paper_example(n_samples=1200, random_state=5)
    est, _ = _paper_fit(data.y, data.u, 0, segment_length=300)
    new = make_paper_example(n_samples=900, random_state=6)
    for x0 in (None, [float(new.x[0, 0])], "estimate"):
        sm = est.smooth(new.u, new.y, x0=x0)
        assert sm.mean.shape == (900, 1) and np.all(np.isfinite(sm.mean))
        assert np.sqrt(np.mean((sm.mean[:, 0] - new.x[:, 0]) ** 2)) < 0.6
    two = est.smooth([new.u, data.u], [new.y, data.y], x0=[[float(new.x[0, 0])], [float(data.x[0, 0])]])
    assert [s.mean.shape for s in two] == [(900, 1), (1200, 1)]


def test_auto_cuts_records_of_ten_windows_of_ten_overlaps():
    from torch_nssm.estimation.estep import auto_segment_length

    assert auto_segment_length(9_999, 100) is None
    assert auto_segment_length(10_000, 100) == 1000
    assert auto_segment_length(4_999, 50) is None and auto_segment_length(5_000, 50) == 500


def test_segment_length_auto_cuts_a_long_record_and_says_so():
    """The default ``segment_length="auto"``: a record of 10,000 samples runs the time-parallel
    E-step with windows of 1,000 (``segment_length_``), the same fit as ``segment_length=1000``;
    a shorter record, ``None`` or ``acceleration="newton"`` keep the exact pass."""
    from sklearn.base import clone

    from torch_nssm._parameters import resolved_segment_length

    data = make_paper_example(n_samples=10_000, random_state=2)
    short = make_paper_example(n_samples=600, random_state=2)

    def fitted(u, y, **kw):
        est = RobustNSSMEstimator(
            PaperTransition(), PaperObservation(), x0_mean=[0.0], n_particles=20, n_iter=2, tol=0,
            first_stage=None, random_state=0, **kw,
        )  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return est.fit(u, y)

    auto = fitted(data.u, data.y)
    assert RobustNSSMEstimator(PaperTransition(), PaperObservation()).segment_length == "auto"
    assert auto.segment_length_ == 1000
    explicit = fitted(data.u, data.y, segment_length=1000)
    np.testing.assert_array_equal(auto.history_["log_likelihood"], explicit.history_["log_likelihood"])
    exact = fitted(short.u, short.y)
    assert exact.segment_length_ is None
    again = fitted(short.u, short.y, segment_length=None)
    np.testing.assert_array_equal(exact.history_["log_likelihood"], again.history_["log_likelihood"])
    est = RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0], segment_length="yes")
    with pytest.raises(ValueError, match="segment_length must be a positive integer, 'auto' or None"):
        est.fit(short.u, short.y)
    # Newton steps need the exact pass: "auto" gives it to them
    newton = RobustNSSMEstimator(PaperTransition(), PaperObservation(), acceleration="newton")
    batch = _batch([data.u], [data.y])
    assert resolved_segment_length(newton, batch) is None
    assert resolved_segment_length(clone(newton).set_params(acceleration=None), batch) == 1000
