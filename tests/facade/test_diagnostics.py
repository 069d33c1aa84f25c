"""``torch_nssm.diagnostics``: residual analysis as MATLAB's ``resid`` (issue #13)."""

from __future__ import annotations

import math
import warnings
from statistics import NormalDist

import matplotlib.pyplot as plt
import numpy as np
import pytest

from torch_nssm import RobustNSSMEstimator
from torch_nssm.diagnostics import ResidualAnalysis, correlations, residual_analysis
from torch_nssm.models import PaperObservation, PaperTransition
from torch_nssm.plotting import plot_residuals

plt.switch_backend("Agg")
L = 25


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def reference(records_e, records_u, max_lag):
    """``np.correlate`` on zero-filled, centred records, summed over the records."""
    e_all = np.concatenate(records_e)
    mean = np.nanmean(e_all, axis=0)
    n = np.isfinite(e_all).sum(0)
    u_mean = np.concatenate(records_u).mean(0)
    p, nu = e_all.shape[1], records_u[0].shape[1]
    auto = np.zeros((p, max_lag + 1))
    cross = np.zeros((nu, p, 2 * max_lag + 1))
    for e, u in zip(records_e, records_u):
        e = np.nan_to_num(e - mean, nan=0.0)
        u = u - u_mean
        T = len(e)
        for j in range(p):
            full = np.correlate(e[:, j], e[:, j], "full")  # full[T - 1 + tau] = sum_k e_k e_{k - tau}
            for tau in range(max_lag + 1):
                if tau < T:
                    auto[j, tau] += full[T - 1 + tau]
            for i in range(nu):
                full = np.correlate(e[:, j], u[:, i], "full")  # full[T - 1 + tau] = sum_k e_k u_{k - tau}
                for t in range(-max_lag, max_lag + 1):
                    if abs(t) < T:
                        cross[i, j, max_lag + t] += full[T - 1 + t]
    r_uu = (np.concatenate(records_u) - u_mean).var(0)
    r_ee = auto[:, 0] / n
    return (
        auto / auto[:, :1],
        cross / n[None, :, None] / np.sqrt(r_uu[:, None, None] * r_ee[None, :, None]),
        n,
    )


def test_correlations_match_numpy_one_record():
    rng = np.random.default_rng(0)
    e = rng.normal(size=(200, 2)) + 0.3
    u = rng.normal(size=(200, 3)) - 1.0
    a = correlations(e, u, max_lag=10, level=0.95)
    auto, cross, n = reference([e], [u], 10)
    np.testing.assert_allclose(a.autocorrelation, auto, atol=1e-12)
    np.testing.assert_allclose(a.cross_correlation, cross, atol=1e-12)
    assert a.autocorrelation.shape == (2, 11) and a.cross_correlation.shape == (3, 2, 21)
    np.testing.assert_array_equal(a.lags, np.arange(11))
    np.testing.assert_array_equal(a.cross_lags, np.arange(-10, 11))
    np.testing.assert_allclose(a.band, NormalDist().inv_cdf(0.975) / math.sqrt(200))
    np.testing.assert_array_equal(a.n_samples, [200, 200])
    np.testing.assert_allclose(a.mean, e.mean(0))


def test_correlations_match_numpy_records_and_gaps():
    """Records are pooled without lagged products across their boundaries; NaN residuals count
    as zero in the products and are not counted in N."""
    rng = np.random.default_rng(1)
    es = [rng.normal(size=(n, 2)) for n in (80, 7, 50)]
    us = [rng.normal(size=(len(e), 1)) for e in es]
    es[0][[3, 10, 11], 0] = np.nan
    es[2][40, 1] = np.nan
    a = correlations(es, us, max_lag=9)
    auto, cross, n = reference(es, us, 9)
    np.testing.assert_allclose(a.autocorrelation, auto, atol=1e-12)
    np.testing.assert_allclose(a.cross_correlation, cross, atol=1e-12)
    np.testing.assert_array_equal(a.n_samples, [134, 136])
    np.testing.assert_array_equal(n, a.n_samples)
    assert isinstance(a.used, list) and not a.used[0][3, 0] and a.used[0][3, 1]
    # one long record is not the same as the records pooled
    joined = correlations(np.concatenate(es), np.concatenate(us), max_lag=9)
    assert not np.allclose(joined.autocorrelation, a.autocorrelation)


def test_white_noise_passes():
    rng = np.random.default_rng(3)
    u = rng.normal(size=(500, 1))
    a = correlations(rng.normal(size=(500, 1)), u, max_lag=L, level=0.999)
    assert not a.outside_auto.any() and not a.outside_cross.any()
    assert a.white.all() and a.independent.all()
    assert "whiteness and independence tests passed" in a.summary()


def test_ar1_residuals_flag_lag_1():
    rng = np.random.default_rng(4)
    w = rng.normal(size=500)
    e = np.empty(500)
    e[0] = w[0]
    for k in range(1, 500):
        e[k] = 0.6 * e[k - 1] + w[k]
    a = correlations(e, rng.normal(size=500), max_lag=L)
    assert a.outside_auto[0, 1] and not a.white[0]
    assert abs(a.autocorrelation[0, 1] - 0.6) < 0.1
    assert "output 0: residuals not white (lags 1, 2" in a.summary()
    assert "the model misses dynamics" in a.summary()


def test_filtered_input_flags_cross_correlation():
    """e_k = 0.5 u_{k-2} + noise: past inputs at lag 2, and no other lag at the 99.9 % level."""
    rng = np.random.default_rng(5)
    u = rng.normal(size=500)
    e = rng.normal(size=500)
    e[2:] += 0.5 * u[:-2]
    a = correlations(e, u, max_lag=L, level=0.999)
    assert a.cross_lags[a.outside_cross[0, 0]].tolist() == [2]
    assert abs(a.cross_correlation[0, 0, L + 2] - 0.5 / math.sqrt(1.25)) < 0.1
    assert a.white[0]
    assert "input 0 -> output 0: residuals correlated with past inputs at lag" in a.summary()
    assert "the input path is misspecified" in a.summary()


def test_offset_is_reported():
    rng = np.random.default_rng(6)
    a = correlations(rng.normal(size=300) + 0.5, rng.normal(size=300), max_lag=5)
    assert a.mean_significant[0] and "misses an offset" in a.summary()


def test_correlations_check_arguments():
    e = np.zeros((10, 1))
    with pytest.raises(ValueError, match="level"):
        correlations(e, level=1.0)
    with pytest.raises(ValueError, match="max_lag"):
        correlations(e, max_lag=-1)
    with pytest.raises(ValueError, match="same length"):
        correlations(e, np.zeros((9, 1)))
    with pytest.raises(ValueError, match="too few"):
        correlations(np.full((10, 1), np.nan))
    a = correlations(np.random.default_rng(0).normal(size=(40, 2)), None, max_lag=3)
    assert a.cross_correlation.shape == (0, 2, 7)


# --- end to end: the paper's system (Section 4.1) with 10 % outliers --------------------------------


def simulate_paper_system(n, seed, u_mean=0.157, u_std=0.5):
    """``x+ = 0.9 x + u + w``, ``y = cos x + v`` (variances 0.1), 10 % U[-5, 5] outliers.

    Unlike ``make_paper_example``, the input has a mean that puts the state around pi / 2, where
    cos is monotone: around x = 0 (a zero-mean input) an input effect on y enters through
    -sin(x) u, whose *linear* correlation with u averages out, so no linear residual test can
    see a missing input path there.
    """
    rng = np.random.default_rng(seed)
    u = u_mean + u_std * rng.standard_normal(n)
    x = np.empty(n)
    x[0] = u_mean / 0.1 + rng.standard_normal()
    for k in range(n - 1):
        x[k + 1] = 0.9 * x[k] + u[k] + math.sqrt(0.1) * rng.standard_normal()
    y = np.cos(x) + math.sqrt(0.1) * rng.standard_normal(n)
    idx = rng.choice(n, n // 10, replace=False)
    y[idx] += rng.uniform(-5.0, 5.0, idx.size)
    return u[:, None], y[:, None]


@pytest.fixture(scope="module")
def paper_fits():
    u, y = simulate_paper_system(300, seed=0)
    kw = dict(x0_mean=[math.pi / 2], n_particles=80, n_iter=15, random_state=0)
    with warnings.catch_warnings():  # convergence or not is not what these tests are about
        warnings.simplefilter("ignore")
        right = RobustNSSMEstimator(PaperTransition(0.5, 0.5), PaperObservation(0.5), **kw).fit(u, y)
        f = PaperTransition(0.5, 0.0)
        f.b.requires_grad_(False)  # no input path
        wrong = RobustNSSMEstimator(f, PaperObservation(0.5), **kw).fit(u, y)
    assert wrong.f_.b.item() == 0.0
    return u, y, right, wrong


def test_true_structure_passes(paper_fits):
    u, y, right, _ = paper_fits
    a = residual_analysis(right, u, y, random_state=0)
    assert isinstance(a, ResidualAnalysis)
    assert a.robust == "excluded outlier weight < 0.2"
    assert 20 <= a.n_excluded[0] <= 40  # 30 outliers injected
    assert a.n_samples[0] + a.n_excluded[0] == 300
    assert a.residuals.shape == (300, 1) and a.used.sum() == a.n_samples[0]
    assert not a.outside_auto[0, 1:6].any()  # the small lags: no missing dynamics
    assert not a.outside_cross[0, 0, L : L + 6].any()  # nor a missing input path
    assert a.outside_auto.sum() + a.outside_cross.sum() <= 2  # "mostly": the band holds per lag
    print(a.summary())


def test_missing_input_path_is_flagged(paper_fits):
    u, y, right, wrong = paper_fits
    a = residual_analysis(wrong, u, y, random_state=0)
    good = residual_analysis(right, u, y, random_state=0)
    assert a.outside_cross[0, 0, L + 1]  # y_k misses u_{k-1}
    assert abs(a.cross_correlation[0, 0, L + 1]) > 1.5 * a.band[0]
    assert abs(good.cross_correlation[0, 0, L + 1]) < good.band[0]
    assert "input 0 -> output 0: residuals correlated with past inputs at lag" in a.summary()
    assert "the input path is misspecified" in a.summary()
    print(a.summary())


def test_robust_false_and_records(paper_fits):
    u, y, right, _ = paper_fits
    a = residual_analysis(right, u, y, robust=False, max_lag=5, random_state=0)
    assert a.robust == "none" and a.n_samples[0] == 300 and a.n_excluded[0] == 0
    y2 = y.copy()
    y2[[5, 6, 7]] = np.nan
    b = residual_analysis(right, [u[:150], u[150:]], [y2[:150], y2[150:]], max_lag=5, random_state=0)
    assert isinstance(b.residuals, list) and len(b.residuals) == 2 and b.residuals[0].shape == (150, 1)
    assert np.isnan(b.residuals[0][5:8]).all() and not b.used[0][5:8].any()
    assert b.n_samples[0] + b.n_excluded[0] == 297
    c = residual_analysis(right, u[:, 0], y[:, 0], max_lag=5, random_state=0)
    assert c.residuals.shape == (300,)


def test_plot_residuals(paper_fits):
    u, y, _, wrong = paper_fits
    a = residual_analysis(wrong, u, y, max_lag=10, random_state=0)
    axes = plot_residuals(a)
    assert axes.shape == (1, 2)
    auto_ax, cross_ax = axes[0]
    assert "autocorrelation" in auto_ax.get_title() and "input 0 -> output 0" in cross_ax.get_title()
    lines = cross_ax.get_lines()
    xs = np.concatenate([ln.get_xdata() for ln in lines if ln.get_marker() == "o"])
    assert sorted(xs.tolist()) == list(range(-10, 11))
    red = [ln for ln in lines if ln.get_label() == "outside"]
    assert red and 1 in red[0].get_xdata()
    fig, grid = plt.subplots(2, 2)
    out = plot_residuals(a, ax=grid[0])
    assert out[0, 0] is grid[0, 0]
    with pytest.raises(ValueError, match="Axes for 2 panels"):
        plot_residuals(a, ax=grid.ravel())
    with pytest.raises(TypeError, match="ResidualAnalysis"):
        plot_residuals({"lags": []})


def test_the_estimator_method_is_the_function():
    """``est.residual_analysis(u, y)`` is :func:`residual_analysis` of the estimator."""
    import warnings

    from torch_nssm import RobustNSSMEstimator
    from torch_nssm.datasets import make_paper_example
    from torch_nssm.diagnostics import residual_analysis
    from torch_nssm.models import PaperObservation, PaperTransition

    d = make_paper_example(n_samples=150, outlier_fraction=0.1, random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=40, n_iter=3,
            random_state=0,
        ).fit(d.u, d.y)
    a = est.residual_analysis(d.u, d.y, max_lag=10, random_state=1)
    b = residual_analysis(est, d.u, d.y, max_lag=10, random_state=1)
    np.testing.assert_allclose(a.autocorrelation, b.autocorrelation)
    assert a.summary() == b.summary()
