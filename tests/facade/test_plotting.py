"""``torch_nssm.plotting``: each function draws what it says, on the Axes it is given."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from matplotlib.collections import PathCollection, PolyCollection
from sklearn.exceptions import NotFittedError

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.models import PaperObservation, PaperTransition
from torch_nssm.plotting import plot_history, plot_outliers, plot_states

plt.switch_backend("Agg")
N = 120


@pytest.fixture(scope="module")
def fit():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    data = make_paper_example(n_samples=N, random_state=1)
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=40,
        n_iter=4, tol=0.0, random_state=0,
    ).fit(data.u, data.y)
    sm = est.smooth(data.u, data.y, return_particles=True)
    torch.set_num_threads(n)
    yield est, data, sm
    plt.close("all")


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def test_plot_history_panels(fit):
    est, data, _ = fit
    axes = plot_history(est, true_values={"f.a": 0.9, "f.b": 1.0, "g.c": 1.0, "Rw": 0.1})
    titles = [a.get_title() for a in axes]
    assert titles == ["f.a", "f.b", "g.c", "Rw", "Rv", "dof"]
    a = axes[0]
    line, truth = a.get_lines()
    np.testing.assert_allclose(line.get_ydata(), est.history_["f.a"])
    np.testing.assert_allclose(line.get_xdata(), np.arange(5))
    assert truth.get_linestyle() == "--" and truth.get_ydata()[0] == 0.9
    assert truth.get_color() == line.get_color()
    assert len(axes[4].get_lines()) == 1  # Rv: no true value given


def test_plot_history_on_one_axes_and_a_dict(fit):
    est, _, _ = fit
    fig, ax = plt.subplots()
    out = plot_history(est.history_, params=["g.c", "log_likelihood"], ax=ax)
    assert out is ax
    assert [ln.get_label() for ln in ax.get_lines()] == ["g.c", "log_likelihood"]
    assert ax.get_legend() is not None
    fig, axs = plt.subplots(1, 2)
    out = plot_history(est, params=["f.a", "dof"], ax=axs)
    assert list(out) == list(axs)


def _truth_lines(ax) -> list[float]:
    return [ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_label().endswith("(true)")]


def test_plot_history_takes_a_simulation_params_dict(fit):
    """The README's ``plot_history(est, true_values=data.params)``: plain names ``a``, ``c`` go to
    ``f.a``, ``g.c``; settings (``noise``, ``x0_mean``, ...) and ``dof = inf`` are skipped."""
    est, data, _ = fit
    assert {"a", "b", "c", "noise", "x0_mean", "outlier_range"} <= set(data.params)
    axes = plot_history(est, true_values=data.params)
    truths = {a.get_title(): _truth_lines(a) for a in axes}
    # Rv: the data's Gaussian variance is not the Student-t scale's true value (drawn, not as "true")
    assert truths == {"f.a": [0.9], "f.b": [1.0], "g.c": [1.0], "Rw": [0.1], "Rv": [], "dof": []}
    # a parameter left out of params is skipped, and a qualified name wins over a plain one
    axes = plot_history(est, params=["f.a"], true_values={"g.c": 1.0, "a": 0.5, "f.a": 0.9})
    assert _truth_lines(axes[0]) == [0.9]


def test_plot_history_matrix_entries():
    history = {
        "Rv": np.array([np.eye(2), 2 * np.eye(2), 3 * np.eye(2)]),
        "f.A": np.arange(12.0).reshape(3, 2, 2),
    }
    fig, ax = plt.subplots()
    plot_history(history, params=["Rv", "f.A"], ax=ax, true_values={"Rv": np.eye(2) * 2.5})
    labels = [ln.get_label() for ln in ax.get_lines()]
    assert labels == [
        "Rv[0, 0]", "Rv[0, 0] (true)", "Rv[0, 1]", "Rv[0, 1] (true)", "Rv[1, 1]",
        "Rv[1, 1] (true)", "f.A[0, 0]", "f.A[0, 1]", "f.A[1, 0]", "f.A[1, 1]",
    ]


def test_plot_history_errors(fit):
    est, _, _ = fit
    with pytest.raises(ValueError, match=r"params \['f.z'\] not in the history"):
        plot_history(est, params=["f.z"])
    with pytest.raises(ValueError, match=r"true_values has \['f.z'\], which are not in the history"):
        plot_history(est, true_values={"f.z": 1.0})  # a qualified name that is not there: a typo
    with pytest.raises(ValueError, match="ambiguous"):
        plot_history({"f.c": np.zeros(3), "g.c": np.ones(3)}, true_values={"c": 1.0})
    with pytest.raises(ValueError, match="must be numeric"):
        plot_history(est, true_values={"a": "0.9x"})
    with pytest.raises(NotFittedError):
        plot_history(RobustNSSMEstimator(PaperTransition(), PaperObservation(), x0_mean=[0.0]))


def test_plot_outliers_colours_by_weight(fit):
    est, data, _ = fit
    fig, ax = plt.subplots()
    out = plot_outliers(data.y, est.outlier_weights_, true_outliers=data.outlier_mask, ax=ax)
    assert out is ax
    points, circles = [c for c in ax.collections if isinstance(c, PathCollection)]
    np.testing.assert_allclose(points.get_array(), est.outlier_weights_)  # not clipped at 1
    np.testing.assert_allclose(points.get_offsets()[:, 1], data.y[:, 0])
    assert len(circles.get_offsets()) == data.outlier_mask.sum()
    assert len(fig.axes) == 2  # with a colour bar
    # the flagged samples are drawn in the colour of a low weight
    cmap = points.get_cmap()
    colours = points.to_rgba(points.get_array())
    low = np.argmin(est.outlier_weights_)
    np.testing.assert_allclose(colours[low], cmap(float(np.clip(est.outlier_weights_[low], 0, 1))))


def test_plot_outliers_colour_bar_spans_the_weights(fit):
    """A regular sample's weight ``E[lam | y] = (dof + p) / (dof + delta^2)`` exceeds 1 for a small
    residual: the colour bar runs to the largest weight (not 1), its middle colour at the 0.5 that
    flags an outlier."""
    est, data, _ = fit
    w = est.outlier_weights_
    assert w.max() > 1.0  # the weights this test is about
    assert w.max() <= (est.dof_ + 1) / est.dof_ + 1e-12  # the bound the docstring states
    fig, ax = plt.subplots()
    points = plot_outliers(data.y, w, ax=ax).collections[0]
    assert points.norm.vmin == 0.0 and points.norm.vmax == pytest.approx(w.max())
    assert points.norm(0.5) == pytest.approx(0.5)
    colorbar = fig.axes[1]
    assert colorbar.get_ylim() == pytest.approx((0.0, w.max()))  # the bar shows every weight
    # weights at most 1 keep the bar at 1
    assert plot_outliers(data.y, np.clip(w, 0, 0.9)).collections[0].norm.vmax == 1.0


def test_plot_history_titles_clear_the_row_above(fit):
    """The bottom row's titles (Rw, Rv, dof) do not sit under the top row's x labels and ticks."""
    est, _, _ = fit
    axes = plot_history(est)
    fig = axes[0].figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for above, below in zip(axes[:3], axes[3:]):
        title = below.title.get_window_extent(renderer)
        assert below.get_title()
        for artist in (above.xaxis.label, *above.get_xticklabels()):
            box = artist.get_window_extent(renderer)
            assert title.y1 < box.y0 or not box.width, (below.get_title(), title, box)


def test_plot_parameters_titles_clear_the_row_above(fit):
    from torch_nssm.plotting import plot_parameters

    est, _, _ = fit
    axes = plot_parameters(est)
    fig = axes[0].figure
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for above, below in zip(axes[:3], axes[3:]):
        title = below.title.get_window_extent(renderer)
        for artist in above.get_xticklabels():
            assert title.y1 < artist.get_window_extent(renderer).y0


def test_a_gaussian_variance_is_not_marked_as_a_student_t_scales_truth(fit):
    """Gaussian data (``data.params["noise"] == "gaussian"``) beside a Student-t fit: ``Rv`` of the
    data is a variance, the fit's a scale; it is drawn and labelled as the data's variance, not
    as the true value.  The model's own parameters keep their "true" marks."""
    from torch_nssm.plotting import plot_parameters

    est, data, _ = fit
    assert data.params["noise"] == "gaussian" and np.isfinite(est.dof_)
    axes = dict(zip(["f.a", "f.b", "g.c", "Rw", "Rv", "dof"], plot_parameters(est, true_values=data.params)))
    marks = lambda a: [ln.get_label() for ln in a.get_lines() if not ln.get_label().startswith("_")]  # noqa: E731
    labels = {k: marks(a) for k, a in axes.items()}
    assert labels["f.a"] == ["true"] and labels["Rw"] == ["true"]
    assert labels["Rv"] == ["data's Gaussian variance"]
    assert axes["Rv"].get_legend() is not None
    history_axes = plot_history(est, true_values=data.params)
    rv = [ln for ln in history_axes[4].get_lines() if ln.get_label().startswith("Rv (")]
    assert [ln.get_label() for ln in rv] == ["Rv (data's Gaussian variance)"]
    assert rv[0].get_linestyle() == ":"
    # Student-t data with a Student-t fit: the scale is the true value
    params = dict(data.params, noise="student-t")
    assert marks(plot_parameters(est, true_values=params)[4]) == ["true"]


def test_plot_outliers_missing_and_errors():
    y = np.array([0.0, 1.0, np.nan, 2.0])
    w = np.array([1.0, 0.1, np.nan, 1.2])
    ax = plot_outliers(y, w)
    pts = [c for c in ax.collections if isinstance(c, PathCollection)]
    assert len(pts[0].get_offsets()) == 3  # the NaN weight drawn apart, in grey
    with pytest.raises(ValueError, match="outlier_weights must have 4 entries"):
        plot_outliers(y, w[:3])
    with pytest.raises(ValueError, match="true_outliers must have 4 entries"):
        plot_outliers(y, w, true_outliers=[True])


def test_plot_states_band_and_truth(fit):
    _, data, sm = fit
    fig, ax = plt.subplots()
    out = plot_states(sm, x_true=data.x, ax=ax, level=0.8)
    assert out is ax
    mean_line, true_line = ax.get_lines()
    np.testing.assert_allclose(mean_line.get_ydata(), sm.mean[:, 0])
    np.testing.assert_allclose(true_line.get_ydata(), data.x[:, 0])
    bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert len(bands) == 1
    lo, hi = sm.interval(0.8)
    ys = bands[0].get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(lo.min()) and ys.max() == pytest.approx(hi.max())


def test_plot_states_options_and_errors(fit):
    _, data, sm = fit
    ax = plot_states(sm, level=0)
    assert not [c for c in ax.collections if isinstance(c, PolyCollection)]
    with pytest.raises(ValueError, match="components must lie in"):
        plot_states(sm, components=[1])
    with pytest.raises(ValueError, match="level must lie in"):
        plot_states(sm, level=1.5)
    with pytest.raises(TypeError, match="estimate must be a StateEstimate"):
        plot_states(sm.mean)
    with pytest.raises(ValueError, match="x_true must have shape"):
        plot_states(sm, x_true=np.zeros((N, 2)))
