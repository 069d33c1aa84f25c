"""``fit_percent`` and ``RobustNSSMEstimator.compare`` (MATLAB's ``compare``), and ``plot_compare``."""

from __future__ import annotations

import warnings

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from sklearn.metrics import r2_score

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.evaluation import CompareResult
from torch_nssm.metrics import fit_percent
from torch_nssm.models import PaperObservation, PaperTransition
from torch_nssm.plotting import plot_compare

plt.switch_backend("Agg")


@pytest.fixture(scope="module")
def fitted():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    train = make_paper_example(n_samples=200, outlier_fraction=0.1, random_state=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=60,
            n_iter=8, tol=0.0, random_state=0,
        ).fit(train.u, train.y)
    torch.set_num_threads(n)
    # a new record of the same plant, with outliers
    return est, make_paper_example(n_samples=150, outlier_fraction=0.1, random_state=7)


def test_fit_percent_by_hand_and_missing_values():
    # ||y - yhat|| = 1, ||y - mean y|| = sqrt(5)
    by_hand = 100 * (1 - 1 / 5**0.5)
    np.testing.assert_allclose(fit_percent([1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 5.0]), [by_hand])
    y = np.array([[1.0, 2.0], [2.0, np.nan], [3.0, 1.0], [4.0, 0.0]])
    pred = np.array([[1.0, 2.0], [2.0, 50.0], [3.0, 1.0], [4.0, 1.0]])
    # output 0 perfect; output 1 on its observed samples [2, 1, 0] (mean 1): 100 (1 - 1 / sqrt(2))
    np.testing.assert_allclose(fit_percent(y, pred), [100.0, 100 * (1 - 1 / 2**0.5)])
    assert np.isnan(fit_percent([1.0, 1.0, 1.0], [1.0, 2.0, 3.0])[0])  # no spread: undefined
    with pytest.raises(ValueError, match="same shape"):
        fit_percent(np.ones(4), np.ones(5))


def test_fit_percent_is_a_function_of_r2():
    rng = np.random.default_rng(0)
    y = rng.normal(size=(300, 3))
    pred = y + rng.normal(scale=[0.1, 0.5, 2.0], size=(300, 3))
    r2 = r2_score(y, pred, multioutput="raw_values")
    np.testing.assert_allclose(fit_percent(y, pred), 100 * (1 - np.sqrt(1 - r2)), rtol=1e-12)
    assert fit_percent(y, pred)[2] < 0  # worse than the mean


def test_compare_is_predict_and_fit_percent(fitted):
    est, data = fitted
    result = est.compare(data.u, data.y)
    assert isinstance(result, CompareResult) and result.horizon is None and result.robust == "none"
    pred = est.predict(data.u)
    np.testing.assert_array_equal(result.y_pred, pred)
    np.testing.assert_allclose(result.fit, fit_percent(data.y, pred))
    k_step = est.compare(data.u, data.y, horizon=1, random_state=3)
    np.testing.assert_allclose(k_step.y_pred, est.predict(data.u, data.y, horizon=1, random_state=3))
    np.testing.assert_allclose(k_step.fit, fit_percent(data.y, k_step.y_pred))
    assert k_step.fit[0] > result.fit[0]  # the one-step predictions follow the measured outputs
    assert str(result) == f"free-run simulation: fit {result.fit[0]:.1f} %"
    assert str(k_step).startswith("1-step-ahead prediction: fit")


def test_robust_compare_leaves_out_the_outliers(fitted):
    est, data = fitted
    plain = est.compare(data.u, data.y, random_state=0)
    robust = est.compare(data.u, data.y, robust=True, random_state=0)
    left_out = robust.excluded.reshape(-1)
    assert robust.robust == f"smoothed outlier weight < {float(est.outlier_threshold_):.2g}"
    assert 0.0 < est.outlier_threshold_ < 0.5  # dof 1.4: a weight below 0.5 is a residual of 1.8 scales
    # the left-out samples are the glitches: 8 of the 15 injected outliers (the others, drawn
    # uniformly in [-5, 5], lie within the noise's spread of the output) and none of the regular
    # samples (the core of the fitted Student-t of dof 1.4 widened to the samples' bulk; its own
    # core left out 10 of the 15 and 1 regular sample, for a robust fit of 14.2 against 16.5 %)
    assert left_out[data.outlier_mask].mean() >= 0.5
    assert left_out[~data.outlier_mask].mean() <= 0.02
    kept = np.where(robust.excluded, np.nan, data.y)
    np.testing.assert_allclose(robust.fit, fit_percent(kept, plain.y_pred))
    assert robust.fit[0] > plain.fit[0] + 2.0  # 16.5 against 9.4 %
    assert "left out" in str(robust)


def test_compare_of_records(fitted):
    est, data = fitted
    other = make_paper_example(n_samples=80, outlier_fraction=0.0, random_state=8)
    result = est.compare([data.u, other.u], [data.y, other.y])
    assert result.fit.shape == (2, 1) and isinstance(result.y_pred, list)
    np.testing.assert_allclose(result.fit[1], est.compare(other.u, other.y).fit)
    assert str(result).splitlines()[1].startswith("record 1, free-run simulation: fit")


def test_plot_compare(fitted):
    est, data = fitted
    result = est.compare(data.u, data.y, robust=True)
    axes = plot_compare(result, data.y)
    assert axes.shape == (1,)
    measured, predicted, left_out = axes[0].get_lines()
    np.testing.assert_allclose(measured.get_ydata(), data.y[:, 0])
    np.testing.assert_allclose(predicted.get_ydata(), result.y_pred.reshape(-1))
    assert len(left_out.get_xdata()) == int(result.excluded.sum())
    labels = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert labels[1] == f"simulated: fit {result.fit[0]:.1f} %"
    with pytest.raises(TypeError, match="CompareResult"):
        plot_compare(result.fit, data.y)
    with pytest.raises(ValueError, match="shape"):
        plot_compare(result, data.y[:-1])
    plt.close("all")
