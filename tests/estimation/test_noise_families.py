"""Joint vs per-output Student-t noise on a 2-output system whose glitches hit output 1 only
(issue #11): the joint t down-weights both outputs of a glitch sample and lets the clean output's
scale collapse; the per-output t down-weights the glitching sensor alone.

Plus the estimator surface with ``noise="student-t-per-output"``: outlier weights per component,
smoothing, simulation, pickling, independent fits and missing components.
"""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from scipy import stats

from torch_nssm import RobustNSSMEstimator, fit_independent
from torch_nssm.blocks.linear import LinearObservation, LinearTransition
from torch_nssm.datasets.two_sensors import TWO_SENSOR_RV, make_two_sensor_example

RV_TRUE = TWO_SENSOR_RV


def glitch_record(n: int, seed: int, rate: float = 0.1):
    """Inputs, outputs and the glitch mask of :func:`make_two_sensor_example`."""
    d = make_two_sensor_example(n, glitch_fraction=rate, random_state=seed)
    return d.u, d.y, d.outlier_mask


def estimator(noise: str, **kw) -> RobustNSSMEstimator:
    """Linear f and g (closed-form M-step); C = I fixed, so the states are the outputs' means."""
    g = LinearObservation(2, 1, 2)
    g.C.requires_grad_(False)
    params = dict(
        x0_mean=np.zeros(2), Rv_init=np.diag([0.2, 0.2]), dof_init=10.0, noise=noise,
        n_particles=100, n_iter=30, tol=0.0, random_state=0,
    )
    params.update(kw)
    return RobustNSSMEstimator(LinearTransition(2, 1), g, **params)


@pytest.fixture(scope="module")
def record():
    return glitch_record(300, seed=0)


@pytest.fixture(scope="module")
def joint(record):
    u, y, _ = record
    return estimator("student-t").fit(u, y)


@pytest.fixture(scope="module")
def per_output(record):
    u, y, _ = record
    return estimator("student-t-per-output").fit(u, y)


def _rv22_history(est) -> np.ndarray:
    return np.array([r[1, 1] for r in est.history_["Rv"]])


def test_per_output_keeps_the_clean_output(per_output, record):
    _, _, glitch = record
    est = per_output
    assert est.Rv_.shape == (2, 2) and est.Rv_[0, 1] == 0.0 and est.Rv_[1, 0] == 0.0
    assert est.dof_.shape == (2,)
    assert 0.06 < est.Rv_[1, 1] < 0.15  # clean output: near the truth 0.1
    assert est.dof_[1] > 10.0  # ... and near-Gaussian
    assert est.dof_[0] < 3.0  # the glitching output is heavy-tailed
    w = est.outlier_weights_
    assert w.shape == (300, 2)
    assert np.median(w[glitch, 0]) < 0.05  # glitches down-weighted on output 1 ...
    assert w[glitch, 1].min() > 0.5 and w[glitch, 1].mean() > 0.9  # ... not on output 2
    assert (w[~glitch, 1] < 0.5).sum() <= 3
    assert est.history_["dof"].shape == (31, 2)


def test_joint_t_down_weights_both_outputs_and_shrinks_the_clean_scale(joint, per_output, record):
    _, _, glitch = record
    est = joint
    assert np.ndim(est.dof_) == 0 and est.dof_ < 2.0
    w = est.outlier_weights_
    assert w.shape == (300,)  # one weight for both outputs
    assert np.median(w[glitch]) < 0.05  # output 2 of the glitch samples is thrown away too
    assert (w[~glitch] < 0.5).sum() >= 15  # and many clean samples with it
    rv22 = _rv22_history(est)
    assert rv22[-1] < 0.3 * RV_TRUE  # the clean output's scale collapsed ...
    assert rv22[-1] < rv22[-10]  # ... and is still falling
    assert per_output.Rv_[1, 1] > 4.0 * est.Rv_[1, 1]


def test_smooth_simulate_and_pickle(per_output, record):
    u, y, glitch = record
    est = per_output
    sm = est.smooth(u, y)
    assert sm.mean.shape == (300, 2) and sm.outlier_weights.shape == (300, 2)
    assert np.median(sm.outlier_weights[glitch, 0]) < 0.1 < sm.outlier_weights[glitch, 1].min()
    # simulated measurement noise (y - C x - d with C = I, D = 0): t per output, the fitted dof
    x, ys = est.simulate(u, n_samples=20, random_state=1)
    v = (ys - x - est.g_.d.detach().numpy()).reshape(-1, 2)
    for j in range(2):
        z = v[:, j] / math.sqrt(est.Rv_[j, j])
        assert stats.kstest(z, stats.t(df=est.dof_[j]).cdf).pvalue > 1e-3
    tail = (np.abs(v) / np.sqrt(np.diag(est.Rv_)) > 6).mean(0)
    assert tail[0] > 0.05 > 0.005 > tail[1]  # heavy tails on output 1 only
    loaded = pickle.loads(pickle.dumps(est))
    np.testing.assert_array_equal(loaded.dof_, est.dof_)
    np.testing.assert_array_equal(loaded.outlier_weights_, est.outlier_weights_)
    assert loaded.log_likelihood(u, y) == est.log_likelihood(u, y)


def test_fit_independent_per_output():
    sets = [glitch_record(80, seed=s, rate=r) for s, r in [(10, 0.0), (11, 0.1), (12, 0.2)]]
    fits = fit_independent(
        estimator("student-t-per-output", n_particles=30, n_iter=4),
        [s[0] for s in sets], [s[1] for s in sets],
    )
    assert len(fits) == 3
    for est in fits:
        assert est.dof_.shape == (2,) and est.history_["dof"].shape == (5, 2)
        assert np.count_nonzero(est.Rv_ - np.diag(np.diag(est.Rv_))) == 0
        assert est.outlier_weights_.shape == (80, 2)
    assert len({tuple(est.dof_) for est in fits}) == 3  # each data set its own dofs
    # the glitch-free set keeps its output-1 dof highest
    assert fits[0].dof_[0] > max(fits[1].dof_[0], fits[2].dof_[0])


def test_missing_components():
    u, y, _ = glitch_record(120, seed=3)
    rng = np.random.default_rng(4)
    y = y.copy()
    y[rng.random(120) < 0.2, 1] = np.nan
    y[[5, 6], :] = np.nan
    est = estimator("student-t-per-output", n_particles=40, n_iter=4).fit(u, y)
    w = est.outlier_weights_
    np.testing.assert_array_equal(np.isnan(w), np.isnan(y))
    assert np.all(np.isfinite(est.Rv_)) and np.all(np.isfinite(est.dof_))


@pytest.mark.slow
def test_joint_vs_per_output_long_run():
    """The issue's setting: 100 EM iterations on 500 samples."""
    u, y, glitch = glitch_record(500, seed=1)
    joint = estimator("student-t", n_iter=100).fit(u, y)
    per = estimator("student-t-per-output", n_iter=100).fit(u, y)
    rv22 = _rv22_history(joint)
    assert rv22[-1] < 0.2 * RV_TRUE and rv22[-1] < rv22[-20]
    assert abs(per.Rv_[1, 1] - RV_TRUE) < 0.03 and per.dof_[1] > 10.0
    assert (per.outlier_weights_[~glitch, 1] < 0.5).sum() <= 3
    assert (joint.outlier_weights_[~glitch] < 0.5).sum() >= 25


def test_outlier_flags_follow_the_gaussian_core(record, joint, per_output):
    """``outliers_`` flags a weight below ``(dof + p) / (dof + k chi2_p(0.999))``: the weight of a
    residual that the noise's Gaussian core, widened by ``k >= 1`` to the bulk of the samples'
    distances, exceeds once in a thousand samples (joint: one threshold for both outputs; per
    output: one per output, each with p = 1)."""
    from torch_nssm.core.noise.base import bulk_spread

    _, _, glitch = record
    nu = joint.dof_
    k = bulk_spread(joint.outlier_weights_, nu, 2)
    assert k >= 1.0
    expected = (nu + 2) / (nu + k * stats.chi2.ppf(0.999, 2))
    assert joint.outlier_threshold_ == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(joint.outliers_, joint.outlier_weights_ < joint.outlier_threshold_)
    assert per_output.outlier_threshold_.shape == (2,)
    k = bulk_spread(per_output.outlier_weights_, per_output.dof_, 1)
    assert k.shape == (2,) and np.all(k >= 1.0)
    np.testing.assert_allclose(
        per_output.outlier_threshold_,
        (per_output.dof_ + 1) / (per_output.dof_ + k * stats.chi2.ppf(0.999, 1)),
        rtol=1e-12,
    )
    np.testing.assert_array_equal(
        per_output.outliers_, per_output.outlier_weights_ < per_output.outlier_threshold_[None, :]
    )
    # the glitches of output 1 are flagged there, output 2 (clean) keeps its samples
    assert per_output.outliers_[glitch, 0].mean() > 0.5
    assert per_output.outliers_[~glitch, 1].mean() < 0.02


def test_the_core_is_widened_to_the_bulk_of_the_samples():
    """Samples whose distances from a Student-t of dof 0.7 spread twice its scale (a t that gross
    outliers made heavy-tailed): the core is widened by about 4 (in squared distance), so a regular
    sample at 3.3 scales is not flagged; samples spread as the t's own core leave it at 1; per
    column, missing samples ignored."""
    from torch_nssm.core.noise.base import bulk_spread, core_outlier_threshold

    rng = np.random.default_rng(0)
    nu = 0.7
    wide = 4.0 * rng.chisquare(1, 20_000)
    own = rng.chisquare(1, 20_000) * 0.5
    w = np.stack([(nu + 1) / (nu + wide), (nu + 1) / (nu + own)], axis=1)
    w[:100, 0] = np.nan
    k = bulk_spread([w[:5000], w[5000:]], np.array([nu, nu]), 1)
    assert k[0] == pytest.approx(4.0, rel=0.05) and k[1] == 1.0
    t = core_outlier_threshold(np.array([nu, nu]), 1, [w])
    regular = (nu + 1) / (nu + 3.3**2)  # a residual of 3.3 scales
    assert regular < core_outlier_threshold(nu, 1)  # flagged by the t's own core
    assert regular > t[0]  # not by the widened one
    assert t[1] == pytest.approx(float(core_outlier_threshold(nu, 1)))


def test_gaussian_noise_flags_nothing(record):
    u, y, _ = record
    est = estimator("gaussian", n_iter=3).fit(u, y)
    assert not est.outliers_.any() and est.outlier_threshold_ == 0.5
