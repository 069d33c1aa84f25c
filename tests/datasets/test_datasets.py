"""Tests of the simulated data sets (:mod:`torch_nssm.datasets`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from torch_nssm.datasets import (
    MANIPULATOR_DT,
    MANIPULATOR_RW,
    ManipulatorConstants,
    SimulatedData,
    make_gopaluni_example,
    make_huang_example,
    make_manipulator,
    make_paper_example,
    manipulator_force,
    manipulator_transition_matrix,
)

GENERATORS = [make_paper_example, make_gopaluni_example, make_huang_example, make_manipulator]


# ------------------------------------------------------------------------------------------
# Shapes, reproducibility
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("gen", GENERATORS)
def test_shapes_and_types(gen):
    d = gen(random_state=0)
    assert isinstance(d, SimulatedData)
    n = d.n_samples
    for arr in (d.u, d.y, d.x, d.y_clean):
        assert arr.ndim == 2 and arr.shape[0] == n and arr.dtype == np.float64
        assert np.all(np.isfinite(arr))
    assert d.y.shape == d.y_clean.shape
    assert d.outlier_mask.shape == (n,) and d.outlier_mask.dtype == bool
    for key in ("Rw", "Rv", "dof", "x0_mean", "x0_cov"):
        assert key in d.params
    assert np.asarray(d.params["Rw"]).shape == (d.nx, d.nx)
    assert np.asarray(d.params["Rv"]).shape == (d.ny, d.ny)
    assert np.asarray(d.params["x0_mean"]).shape == (d.nx,)
    assert np.asarray(d.params["x0_cov"]).shape == (d.nx, d.nx)
    with pytest.raises(AttributeError):
        d.name = "other"  # frozen
    assert d.name in repr(d)


def test_default_sizes():
    assert make_paper_example().y.shape == (500, 1)
    assert make_gopaluni_example().y.shape == (400, 1)
    assert make_huang_example().y.shape == (1000, 1)
    d = make_manipulator()
    assert (d.u.shape, d.x.shape, d.y.shape) == ((500, 1), (500, 4), (500, 2))


@pytest.mark.parametrize("gen", GENERATORS)
def test_reproducible_and_seed_dependent(gen):
    a, b, c = gen(random_state=3), gen(random_state=3), gen(random_state=4)
    for name in ("u", "y", "x", "y_clean", "outlier_mask"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.x, c.x)
    assert not np.array_equal(a.y, c.y)


def test_generator_instance_accepted():
    d1 = make_paper_example(random_state=np.random.default_rng(7))
    d2 = make_paper_example(random_state=7)
    np.testing.assert_array_equal(d1.y, d2.y)


# ------------------------------------------------------------------------------------------
# Outliers
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "gen, kwargs",
    [
        (make_paper_example, dict(n_samples=500, outlier_fraction=0.1)),
        (make_paper_example, dict(n_samples=333, outlier_fraction=0.37)),
        (make_gopaluni_example, dict(outlier_fraction=0.05)),
        (make_gopaluni_example, dict(outlier_fraction=0.0)),
        (make_manipulator, dict(outlier_fraction=0.2)),
        (make_manipulator, dict(outlier_fraction=0.4, outlier_range=(-2.0, 3.0))),
    ],
)
def test_outliers_where_mask_says(gen, kwargs):
    d = gen(random_state=11, **kwargs)
    n_expected = round(kwargs["outlier_fraction"] * d.n_samples)
    assert int(d.outlier_mask.sum()) == n_expected == d.params["n_outliers"]
    diff = d.y - d.y_clean
    # additive outliers on every component of the marked samples, nothing elsewhere
    assert np.all(diff[~d.outlier_mask] == 0.0)
    assert np.all(diff[d.outlier_mask] != 0.0)
    lo, hi = d.params["outlier_range"]
    assert np.all(diff[d.outlier_mask] >= lo) and np.all(diff[d.outlier_mask] <= hi)
    if n_expected > 20:  # uniform on the range
        assert (
            stats.kstest(diff[d.outlier_mask].ravel(), stats.uniform(lo, hi - lo).cdf).pvalue > 1e-3
        )


def test_huang_has_no_added_outliers():
    d = make_huang_example(random_state=0)
    assert not d.outlier_mask.any()
    np.testing.assert_array_equal(d.y, d.y_clean)
    assert d.params["dof"] == 1.0


def test_gaussian_dof_is_inf():
    assert make_paper_example(random_state=0).params["dof"] == math.inf
    assert make_manipulator(random_state=0).params["dof"] == math.inf
    assert make_paper_example(noise="student-t", dof=4.0, random_state=0).params["dof"] == 4.0


# ------------------------------------------------------------------------------------------
# Noise statistics (the exact checks of the mean dynamics are in test_models.py)
# ------------------------------------------------------------------------------------------


def _within(est, true, n, k=5.0):
    """Variance estimate within k standard errors (sd of a variance estimate: true*sqrt(2/n))."""
    return abs(est - true) <= k * true * math.sqrt(2.0 / n)


def test_paper_noise_variances():
    n = 5000
    d = make_paper_example(n_samples=n, Rw=0.1, Rv=0.2, outlier_fraction=0.0, random_state=1)
    a, b, c = d.params["a"], d.params["b"], d.params["c"]
    x, u = d.x[:, 0], d.u[:, 0]
    w = x[1:] - a * x[:-1] - b * u[:-1]
    v = d.y_clean[:, 0] - c * np.cos(x)
    assert _within(w.var(), 0.1, n) and abs(w.mean()) < 5 * math.sqrt(0.1 / n)
    assert _within(v.var(), 0.2, n) and abs(v.mean()) < 5 * math.sqrt(0.2 / n)
    assert _within(u.var(), 1.0, n)
    assert abs(stats.pearsonr(v[1:], v[:-1])[0]) < 5 / math.sqrt(n)  # white


@pytest.mark.parametrize("dof", [1.0, 4.0])
def test_student_t_measurement_noise(dof):
    n, Rv = 4000, 0.05
    d = make_paper_example(
        n_samples=n, noise="student-t", dof=dof, Rv=Rv, outlier_fraction=0.0, random_state=2
    )
    v = d.y_clean[:, 0] - d.params["c"] * np.cos(d.x[:, 0])
    assert stats.kstest(v, stats.t(df=dof, scale=math.sqrt(Rv)).cdf).pvalue > 1e-3


def test_huang_noise_is_cauchy():
    d = make_huang_example(n_samples=4000, random_state=5)
    v = d.y_clean[:, 0] - np.cos(d.x[:, 0])
    assert stats.kstest(v, stats.cauchy(scale=0.1).cdf).pvalue > 1e-3


def test_manipulator_noise_covariances():
    n = 6000
    d = make_manipulator(n_samples=n, outlier_fraction=0.0, random_state=3)
    Rv = np.asarray(d.params["Rv"])
    v = d.y_clean - d.x[:, 2:]
    for i in range(2):
        assert _within(v[:, i].var(), Rv[i, i], n)
    assert abs(np.corrcoef(v.T)[0, 1]) < 5 / math.sqrt(n)


def test_noise_free_record():
    d = make_paper_example(Rw=0.0, Rv=0.0, outlier_fraction=0.0, random_state=0)
    x, u = d.x[:, 0], d.u[:, 0]
    np.testing.assert_allclose(x[1:], 0.9 * x[:-1] + u[:-1], rtol=0, atol=1e-13)
    np.testing.assert_allclose(d.y[:, 0], np.cos(x), rtol=0, atol=0)


def test_zero_input_std():
    d = make_paper_example(input_std=0.0, random_state=0)
    assert np.all(d.u == 0.0)


# ------------------------------------------------------------------------------------------
# Manipulator: force, discretisation, stability
# ------------------------------------------------------------------------------------------


def test_manipulator_input_is_force():
    d = make_manipulator(random_state=0)
    t = MANIPULATOR_DT * np.arange(d.n_samples)
    np.testing.assert_allclose(d.u[:, 0], 10.0 * np.sin(0.02 * np.pi * t), atol=1e-12)
    np.testing.assert_allclose(manipulator_force(t), d.u[:, 0])
    # the default record covers one period (100 s) of the force
    assert d.n_samples * MANIPULATOR_DT == pytest.approx(100.0)


def test_manipulator_matrices_follow_eqs_50_51():
    cst = ManipulatorConstants()
    m, l, g = cst.mass, cst.length, cst.gravity
    assert cst.b1 == pytest.approx(4 * m * l**2 / 3)
    assert cst.b3 == pytest.approx(m * l**2 / 3)
    F = 3.7
    K0, K1 = cst.stiffness_parts()
    K = K0 + F * K1
    a10, a20, a3 = cst.alpha10, cst.alpha20, cst.alpha3
    assert K[0, 0] == pytest.approx(
        cst.k1 + cst.k2 - 1.5 * m * g * l * np.sin(a10) - F * l * np.cos(a10 - a3)
    )
    assert K[1, 1] == pytest.approx(
        cst.k2 - 0.5 * m * g * l * np.sin(a20) - F * l * np.cos(a20 - a3)
    )
    assert K[0, 1] == K[1, 0] == -cst.k2
    E = cst.damping_matrix()
    np.testing.assert_array_equal(E, [[cst.d1 + cst.d2, -cst.d2], [-cst.d2, cst.d2]])
    dt, theta = 0.1, (1.3, 0.7)
    T = manipulator_transition_matrix(F, dt, theta)
    Minv = np.linalg.inv(cst.mass_matrix())
    A = np.block([[-Minv @ E, -Minv @ K], [np.diag(theta), np.zeros((2, 2))]])
    np.testing.assert_allclose(T, np.eye(4) + dt * A, atol=1e-14)
    # batched forces
    assert manipulator_transition_matrix(np.zeros((3, 5))).shape == (3, 5, 4, 4)


def test_manipulator_euler_step_is_stable():
    cst = ManipulatorConstants()
    forces = np.linspace(-cst.force_amplitude, cst.force_amplitude, 201)
    # continuous-time system stable for every force the record can see ...
    Ac = (manipulator_transition_matrix(forces, dt=1.0) - np.eye(4)) / 1.0
    assert np.linalg.eigvals(Ac).real.max() < 0
    # ... and its forward-Euler discretisation too, with a margin
    rho = np.abs(np.linalg.eigvals(manipulator_transition_matrix(forces))).max(axis=-1)
    assert rho.max() < 0.97
    d = make_manipulator(random_state=0)
    assert d.params["max_spectral_radius"] < 0.97
    # the noise-free response decays, the noisy one stays bounded over a long record
    d0 = make_manipulator(n_samples=2000, Rw=0.0, Rv=0.0, outlier_fraction=0.0, random_state=0)
    assert np.abs(d0.x[-100:]).max() < 1e-3 * np.abs(d0.x[:10]).max()
    d1 = make_manipulator(n_samples=5000, outlier_fraction=0.0, random_state=1)
    assert np.abs(d1.x[:, 2:]).max() < 1.0  # radians: small-angle regime
    assert np.abs(d1.x[:, :2]).max() < 3.0


def test_manipulator_outliers_visible():
    d = make_manipulator(random_state=0)
    clean_spread = d.y_clean[50:].std(axis=0)  # after the initial transient
    lo, hi = d.params["outlier_range"]
    assert (hi - lo) / math.sqrt(12) > 3 * clean_spread.max()  # outlier s.d. vs signal s.d.
    assert np.sqrt(np.diag(d.params["Rv"])).max() < 0.5 * clean_spread.min()


def test_manipulator_unstable_step_warns():
    with pytest.warns(RuntimeWarning, match="unstable"):
        make_manipulator(n_samples=20, dt=1.0, random_state=0)


def test_manipulator_covariance_forms():
    d1 = make_manipulator(n_samples=50, Rw=0.01, Rv=[1e-4, 2e-4], random_state=0)
    np.testing.assert_allclose(d1.params["Rw"], 0.01 * np.eye(4))
    np.testing.assert_allclose(d1.params["Rv"], np.diag([1e-4, 2e-4]))
    full = np.array([[2e-4, 1e-4], [1e-4, 2e-4]])
    d2 = make_manipulator(n_samples=50, Rv=full, random_state=0)
    np.testing.assert_allclose(d2.params["Rv"], full)


# ------------------------------------------------------------------------------------------
# Argument validation
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("gen", GENERATORS)
@pytest.mark.parametrize("bad", [-1, 0, 2.5, "10", True])
def test_bad_n_samples(gen, bad):
    with pytest.raises(ValueError, match="n_samples"):
        gen(n_samples=bad)


@pytest.mark.parametrize("gen", [make_paper_example, make_gopaluni_example, make_manipulator])
@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5, float("nan")])
def test_bad_fraction(gen, bad):
    with pytest.raises(ValueError, match="outlier_fraction"):
        gen(outlier_fraction=bad)


@pytest.mark.parametrize("gen", [make_paper_example, make_gopaluni_example, make_manipulator])
@pytest.mark.parametrize("bad", [(5.0, -5.0), (1.0, 1.0), (0.0,), (0.0, np.inf), "ab", None])
def test_bad_range(gen, bad):
    with pytest.raises(ValueError, match="outlier_range"):
        gen(outlier_range=bad)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(noise="cauchy"), "noise"),
        (dict(noise="student-t", dof=0.0), "dof"),
        (dict(noise="student-t", dof=-2.0), "dof"),
        (dict(Rw=-0.1), "Rw"),
        (dict(Rv=-0.1), "Rv"),
        (dict(input_std=-1.0), "input_std"),
        (dict(a="x"), "a"),
    ],
)
def test_bad_paper_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        make_paper_example(**kwargs)


@pytest.mark.parametrize(
    "kwargs, name",
    [(dict(Rv=-0.01), "Rv"), (dict(dof=0.0), "dof"), (dict(Rw=-1.0), "Rw")],
)
def test_bad_huang_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        make_huang_example(**kwargs)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(dt=0.0), "dt"),
        (dict(dt=-0.1), "dt"),
        (dict(theta=(1.0,)), "theta"),
        (dict(theta=(1.0, np.nan)), "theta"),
        (dict(Rw=np.ones((3, 3))), "Rw"),
        (dict(Rw=[1.0, 2.0]), "Rw"),
        (dict(Rw=-np.eye(4)), "Rw"),
        (dict(Rv=np.array([[1.0, 0.5], [0.0, 1.0]])), "Rv"),
        (dict(noise="laplace"), "noise"),
        (dict(x0_mean=[0.0, 0.0]), "x0_mean"),
        (dict(x0_cov=-1.0), "x0_cov"),
        (dict(constants={"mass": 1.0}), "constants"),
    ],
)
def test_bad_manipulator_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        make_manipulator(**kwargs)


def test_positional_signatures():
    """random_state keeps the position of the published signatures; extras are keyword-only."""
    np.testing.assert_array_equal(
        make_huang_example(50, 0.01, 1.0, 3).y, make_huang_example(n_samples=50, random_state=3).y
    )
    np.testing.assert_array_equal(
        make_manipulator(50, 0.1, (-1.0, 1.0), 0.2, (1.0, 1.0), MANIPULATOR_RW, 1e-4, 3).y,
        make_manipulator(n_samples=50, random_state=3).y,
    )
