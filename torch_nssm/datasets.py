"""Simulated data sets of the paper's experiments and a loader for the Silverbox benchmark.

Every generator draws from ``np.random.default_rng(random_state)`` and returns a frozen
:class:`SimulatedData`.  Time convention (NOTES §7): sample ``k`` has input ``u_k`` and output
``y_k``; ``y_k`` observes ``x_k``; ``x_{k+1} = f(x_k, u_k) + w_k``.  (The paper writes
``x_k = f(u_{k-1}, x_{k-1}) + w_{k-1}``: the same model shifted by one sample.)

Outliers are *added* to the clean outputs: a random subset of exactly ``round(fraction * N)``
samples gets an independent ``U[lo, hi]`` draw added to every output component, so that
``y - y_clean`` is non-zero exactly where ``outlier_mask`` is True.

The systems
-----------
* :func:`make_paper_example` -- Section 4.1, ``x_{k+1} = a x_k + b u_k + w``,
  ``y_k = c cos(x_k) + v``.
* :func:`make_gopaluni_example` -- the same system as in the comparison with Gopaluni (2008).
* :func:`make_huang_example` -- the same system with Cauchy measurement noise, as in the
  comparison with Huang et al. (2016).
* :func:`make_manipulator` -- Section 4.2, the two-link manipulator of eqs. (49)-(55), with
  physical constants of our own choice (the paper does not give them; see the ``MANIPULATOR_*``
  constants below).
* :func:`load_silverbox` -- the real Silverbox measurements (not simulated).
"""

from __future__ import annotations

import functools
import math
import numbers
import os
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Union

import numpy as np

__all__ = [
    "SimulatedData",
    "ManipulatorConstants",
    "make_paper_example",
    "make_gopaluni_example",
    "make_huang_example",
    "make_manipulator",
    "manipulator_force",
    "manipulator_transition_matrix",
    "load_silverbox",
    "SILVERBOX_FS",
    "SILVERBOX_ARROW_END",
    "PAPER_X0_COV",
    "MANIPULATOR_MASS",
    "MANIPULATOR_LENGTH",
    "MANIPULATOR_GRAVITY",
    "MANIPULATOR_K1",
    "MANIPULATOR_K2",
    "MANIPULATOR_D1",
    "MANIPULATOR_D2",
    "MANIPULATOR_ALPHA10",
    "MANIPULATOR_ALPHA20",
    "MANIPULATOR_ALPHA3",
    "MANIPULATOR_DT",
    "MANIPULATOR_FORCE_AMPLITUDE",
    "MANIPULATOR_FORCE_OMEGA",
    "MANIPULATOR_RW",
    "MANIPULATOR_RV",
    "MANIPULATOR_OUTLIER_RANGE",
    "MANIPULATOR_X0_MEAN",
    "MANIPULATOR_X0_COV",
]

ArrayLike = Union[float, Sequence[float], Sequence[Sequence[float]], np.ndarray]

# --------------------------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------------------------

#: Prior variance of the first state of the Section 4.1 system (``x_0 ~ N(0, PAPER_X0_COV)``).
#: The paper does not state it; 1.0 is our choice.
PAPER_X0_COV: float = 1.0

#: Sampling frequency of the Silverbox records, Hz (``10^7 / 2^14`` ≈ 610.35 Hz).
SILVERBOX_FS: float = 1e7 / 2**14

#: First sample of the multisine part of ``SNLS80mV.csv``; samples ``[0, 40700)`` are the arrow.
SILVERBOX_ARROW_END: int = 40_700

# Two-link manipulator (Section 4.2).  The paper takes its physical constants from K. Liu,
# J. Sound Vib. 206(4), 1997, and does not print them.  The values below are OUR CHOICE, made so
# that (i) the linearised system is stable for every force in [-10, 10] N, (ii) forward Euler with
# the default step MANIPULATOR_DT = 0.2 s is stable (spectral radius of I + dt*A(t) <= 0.96 for
# every force in [-10, 10] N, with theta = (1, 1)) and resolves the motion (|lambda| * dt <= 0.62),
# (iii) the record of N = 500 samples spans exactly one period (100 s) of the paper's force
# F(t) = 10 sin(0.02 pi t) N, and (iv) the force visibly modulates the stiffness (K22 varies
# between about 0.7 and 2.4 N m/rad over the record).  With them the two modes have natural
# frequencies of about 1.5-3.1 rad/s and damping ratios of about 0.3-0.85.

#: Mass of each link, kg (our choice).
MANIPULATOR_MASS: float = 1.0
#: Length of each link, m (our choice).  With l = 1 the paper's printed ``b4 = 3 m l^2 g / 2``
#: and the dimensionally correct ``3 m g l / 2`` (used here) coincide numerically.
MANIPULATOR_LENGTH: float = 1.0
#: Gravitational acceleration, m/s^2.
MANIPULATOR_GRAVITY: float = 9.81
#: Torsional stiffness of joint 1, N m/rad (our choice).
MANIPULATOR_K1: float = 8.0
#: Torsional stiffness of joint 2, N m/rad (our choice).
MANIPULATOR_K2: float = 2.0
#: Viscous damping of joint 1, N m s/rad (our choice).
MANIPULATOR_D1: float = 3.0
#: Viscous damping of joint 2, N m s/rad (our choice).
MANIPULATOR_D2: float = 0.5
#: Equilibrium angle of link 1, rad (5 degrees, our choice).
MANIPULATOR_ALPHA10: float = math.radians(5.0)
#: Equilibrium angle of link 2, rad (5 degrees, our choice).
MANIPULATOR_ALPHA20: float = math.radians(5.0)
#: Direction of the force, rad (the paper: alpha_3 = 90 degrees, a vertical force).
MANIPULATOR_ALPHA3: float = math.pi / 2
#: Forward-Euler step, s (our choice; N = 500 samples then cover one period of the force).
MANIPULATOR_DT: float = 0.2
#: Amplitude of the force F(t), N (the paper).
MANIPULATOR_FORCE_AMPLITUDE: float = 10.0
#: Angular frequency of the force F(t), rad/s (the paper: 0.02 pi, a period of 100 s).
MANIPULATOR_FORCE_OMEGA: float = 0.02 * math.pi
#: Default process-noise variances of ``[dphi1, dphi2, phi1, phi2]`` per step (our choice):
#: s.d. 0.05 rad/s on the angular velocities (a random torque disturbance) and 0.005 rad on the
#: angles (model error of the Euler step).  The angles then fluctuate with s.d. ≈ 0.05-0.1 rad.
MANIPULATOR_RW: tuple[float, ...] = (0.05**2, 0.05**2, 0.005**2, 0.005**2)
#: Default measurement-noise variance of each angle sensor, rad^2 (s.d. 0.01 rad, our choice).
MANIPULATOR_RV: float = 1e-4
#: Default range of the additive outliers, rad (our choice): up to about 3-10 times the spread of
#: the angles, i.e. plainly visible in a plot, while the smallest are buried in the noise.
MANIPULATOR_OUTLIER_RANGE: tuple[float, float] = (-1.0, 1.0)
#: Default prior mean of the first state ``[dphi1, dphi2, phi1, phi2]``: both links released
#: from rest at 0.3 rad from equilibrium (our choice; the transient dies out in about 10 s).
MANIPULATOR_X0_MEAN: tuple[float, ...] = (0.0, 0.0, 0.3, 0.3)
#: Default prior variances of the first state (our choice).
MANIPULATOR_X0_COV: tuple[float, ...] = (1e-4, 1e-4, 1e-4, 1e-4)


@dataclass(frozen=True)
class ManipulatorConstants:
    """Physical constants of the two-link manipulator (eqs. 50-51); defaults: module constants.

    Attributes
    ----------
    mass, length : float
        Mass (kg) and length (m) of each (identical, uniform) link.
    gravity : float
        Gravitational acceleration, m/s^2.
    k1, k2 : float
        Joint stiffnesses, N m/rad.
    d1, d2 : float
        Joint viscous damping, N m s/rad.
    alpha10, alpha20 : float
        Equilibrium angles of the links, rad.
    alpha3 : float
        Direction of the force, rad (90 degrees: vertical).
    force_amplitude : float
        Amplitude of ``F(t) = A sin(omega t)``, N.
    force_omega : float
        Angular frequency ``omega`` of the force, rad/s.
    """

    mass: float = MANIPULATOR_MASS
    length: float = MANIPULATOR_LENGTH
    gravity: float = MANIPULATOR_GRAVITY
    k1: float = MANIPULATOR_K1
    k2: float = MANIPULATOR_K2
    d1: float = MANIPULATOR_D1
    d2: float = MANIPULATOR_D2
    alpha10: float = MANIPULATOR_ALPHA10
    alpha20: float = MANIPULATOR_ALPHA20
    alpha3: float = MANIPULATOR_ALPHA3
    force_amplitude: float = MANIPULATOR_FORCE_AMPLITUDE
    force_omega: float = MANIPULATOR_FORCE_OMEGA

    @property
    def b1(self) -> float:
        """Inertia of the first row of ``M``, ``4 m l^2 / 3``."""
        return 4.0 * self.mass * self.length**2 / 3.0

    @property
    def b3(self) -> float:
        """Inertia of the second row of ``M``, ``m l^2 / 3``."""
        return self.mass * self.length**2 / 3.0

    @property
    def b4(self) -> float:
        """Gravity stiffness of link 1, ``3 m g l / 2`` (the paper prints ``l^2``; equal at l=1)."""
        return 1.5 * self.mass * self.gravity * self.length

    @property
    def b5(self) -> float:
        """Gravity stiffness of link 2, ``m g l / 2`` (the paper prints ``l^2``; equal at l=1)."""
        return 0.5 * self.mass * self.gravity * self.length

    def mass_matrix(self) -> np.ndarray:
        """``M = diag(b1, b3)`` (eq. 50)."""
        return np.diag([self.b1, self.b3])

    def damping_matrix(self) -> np.ndarray:
        """``E = [[d1 + d2, -d2], [-d2, d2]]`` (eq. 51)."""
        return np.array([[self.d1 + self.d2, -self.d2], [-self.d2, self.d2]])

    def stiffness_parts(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K0, K1)`` with ``K(t) = K0 + F(t) K1`` (eq. 51)."""
        K0 = np.array(
            [
                [self.k1 + self.k2 - self.b4 * math.sin(self.alpha10), -self.k2],
                [-self.k2, self.k2 - self.b5 * math.sin(self.alpha20)],
            ]
        )
        K1 = np.diag(
            [
                -self.length * math.cos(self.alpha10 - self.alpha3),
                -self.length * math.cos(self.alpha20 - self.alpha3),
            ]
        )
        return K0, K1

    def continuous_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(M^-1 E, M^-1 K0, M^-1 K1)``: the upper blocks of ``A(t)`` are their negatives."""
        Minv = np.diag([1.0 / self.b1, 1.0 / self.b3])
        K0, K1 = self.stiffness_parts()
        return Minv @ self.damping_matrix(), Minv @ K0, Minv @ K1


@dataclass(frozen=True, eq=False)
class SimulatedData:
    """A simulated record: inputs, outputs, true states and the true parameters.

    Attributes
    ----------
    u : ndarray, shape (N, nu)
        Inputs (``nu = 0`` for a system without input).
    y : ndarray, shape (N, p)
        Outputs, with outliers.
    x : ndarray, shape (N, nx)
        True states; ``y[k]`` observes ``x[k]``.
    y_clean : ndarray, shape (N, p)
        Outputs without the added outliers (measurement noise included).
    outlier_mask : ndarray of bool, shape (N,)
        True for the samples that got an outlier (in any output component).
    params : dict
        True values: model parameters, ``Rw``, ``Rv`` (matrices as nested lists), ``dof``
        (``inf`` for Gaussian noise), ``x0_mean`` (list), ``x0_cov`` (nested list), and the
        generator's settings.
    name : str
        Which system: ``"paper_example"``, ``"gopaluni_example"``, ``"huang_example"`` or
        ``"manipulator"`` (:func:`torch_nssm.models.true_model` dispatches on it).
    """

    u: np.ndarray
    y: np.ndarray
    x: np.ndarray
    y_clean: np.ndarray
    outlier_mask: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)
    name: str = ""

    @property
    def n_samples(self) -> int:
        """Number of samples ``N``."""
        return int(self.y.shape[0])

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.x.shape[1])

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.u.shape[1])

    @property
    def ny(self) -> int:
        """Output dimension ``p``."""
        return int(self.y.shape[1])

    def __repr__(self) -> str:
        return (
            f"SimulatedData(name={self.name!r}, n_samples={self.n_samples}, nx={self.nx}, "
            f"nu={self.nu}, ny={self.ny}, n_outliers={int(self.outlier_mask.sum())})"
        )


# --------------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------------


def _check_n_samples(n_samples: Any) -> int:
    if isinstance(n_samples, bool) or not isinstance(n_samples, numbers.Integral):
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    if n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples!r}")
    return int(n_samples)


def _check_real(value: Any, name: str, *, low: float | None = None, strict: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if math.isnan(v):
        raise ValueError(f"{name} must not be NaN")
    if low is not None and (v < low or (strict and v == low)):
        rel = ">" if strict else ">="
        raise ValueError(f"{name} must be {rel} {low}, got {value!r}")
    return v


def _check_fraction(fraction: Any) -> float:
    f = _check_real(fraction, "outlier_fraction")
    if not 0.0 <= f < 1.0:
        raise ValueError(f"outlier_fraction must lie in [0, 1), got {fraction!r}")
    return f


def _check_range(value: Any, name: str = "outlier_range") -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high) of numbers, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or not lo < hi:
        raise ValueError(f"{name} must be a finite pair with low < high, got {value!r}")
    return lo, hi


def _check_noise(noise: Any) -> str:
    if noise not in ("gaussian", "student-t"):
        raise ValueError(f"noise must be 'gaussian' or 'student-t', got {noise!r}")
    return noise


def _check_cov(value: Any, dim: int, name: str) -> np.ndarray:
    """A covariance from a scalar (times I), a vector of variances, or a (dim, dim) matrix."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None
    if arr.ndim == 0:
        arr = arr * np.eye(dim)
    elif arr.ndim == 1 and arr.shape == (dim,):
        arr = np.diag(arr)
    elif arr.shape != (dim, dim):
        raise ValueError(
            f"{name} must be a scalar, a length-{dim} vector or a ({dim}, {dim}) matrix, "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    if not np.allclose(arr, arr.T, rtol=1e-10, atol=1e-14):
        raise ValueError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(arr).min() < -1e-12 * max(1.0, float(np.abs(arr).max())):
        raise ValueError(f"{name} must be positive semi-definite")
    return arr


def _check_vector(value: Any, dim: int, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None
    if arr.ndim == 0:
        arr = np.full(dim, float(arr))
    if arr.shape != (dim,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite length-{dim} vector, got {value!r}")
    return arr


# --------------------------------------------------------------------------------------------
# Noise and outliers
# --------------------------------------------------------------------------------------------


def _cov_sqrt(cov: np.ndarray) -> np.ndarray:
    """A matrix ``S`` with ``S S^T = cov`` (works for singular PSD matrices)."""
    vals, vecs = np.linalg.eigh(cov)
    return vecs * np.sqrt(np.clip(vals, 0.0, None))


def _measurement_noise(rng: np.random.Generator, n: int, cov: np.ndarray, dof: float) -> np.ndarray:
    """``n`` draws of ``St(0, cov, dof)`` (Gaussian when ``dof`` is inf), shape (n, p).

    Uses the scale mixture ``v | lam ~ N(0, cov / lam)``, ``lam ~ Gamma(dof/2, rate dof/2)``,
    with one ``lam`` per sample (a multivariate t).
    """
    p = cov.shape[0]
    z = rng.standard_normal((n, p)) @ _cov_sqrt(cov).T
    if math.isinf(dof):
        return z
    lam = rng.gamma(shape=dof / 2.0, scale=2.0 / dof, size=n)
    return z / np.sqrt(lam)[:, None]


def _add_outliers(
    rng: np.random.Generator,
    y_clean: np.ndarray,
    fraction: float,
    outlier_range: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    n, p = y_clean.shape
    n_out = int(round(fraction * n))
    mask = np.zeros(n, dtype=bool)
    y = y_clean.copy()
    if n_out > 0:
        idx = rng.choice(n, size=n_out, replace=False)
        mask[idx] = True
        lo, hi = outlier_range
        y[idx] += rng.uniform(lo, hi, size=(n_out, p))
    return y, mask


def _to_list(a: np.ndarray) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()


# --------------------------------------------------------------------------------------------
# Section 4.1 system
# --------------------------------------------------------------------------------------------


def _simulate_paper_system(
    *,
    name: str,
    n_samples: Any,
    outlier_fraction: Any,
    outlier_range: Any,
    noise: str,
    a: Any,
    b: Any,
    c: Any,
    Rw: Any,
    Rv: Any,
    dof: Any,
    input_std: Any,
    random_state: Any,
) -> SimulatedData:
    n = _check_n_samples(n_samples)
    fraction = _check_fraction(outlier_fraction)
    rng_out = _check_range(outlier_range)
    noise = _check_noise(noise)
    a = _check_real(a, "a")
    b = _check_real(b, "b")
    c = _check_real(c, "c")
    Rw = _check_real(Rw, "Rw", low=0.0)
    Rv = _check_real(Rv, "Rv", low=0.0)
    input_std = _check_real(input_std, "input_std", low=0.0)
    nu_dof = math.inf if noise == "gaussian" else _check_real(dof, "dof", low=0.0, strict=True)

    rng = np.random.default_rng(random_state)
    x0 = rng.normal(0.0, math.sqrt(PAPER_X0_COV))
    u = input_std * rng.standard_normal(n)
    w = math.sqrt(Rw) * rng.standard_normal(n)
    x = np.empty(n)
    x[0] = x0
    for k in range(n - 1):
        x[k + 1] = a * x[k] + b * u[k] + w[k]
    v = _measurement_noise(rng, n, np.array([[Rv]]), nu_dof)[:, 0]
    y_clean = (c * np.cos(x) + v)[:, None]
    y, mask = _add_outliers(rng, y_clean, fraction, rng_out)
    params = {
        "a": a,
        "b": b,
        "c": c,
        "Rw": [[Rw]],
        "Rv": [[Rv]],
        "dof": nu_dof,
        "noise": noise,
        "x0_mean": [0.0],
        "x0_cov": [[PAPER_X0_COV]],
        "input_std": input_std,
        "outlier_fraction": fraction,
        "outlier_range": list(rng_out),
        "n_outliers": int(mask.sum()),
    }
    return SimulatedData(
        u=u[:, None],
        y=y,
        x=x[:, None],
        y_clean=y_clean,
        outlier_mask=mask,
        params=params,
        name=name,
    )


def make_paper_example(
    n_samples: int = 500,
    outlier_fraction: float = 0.1,
    outlier_range: tuple[float, float] = (-5.0, 5.0),
    noise: str = "gaussian",
    a: float = 0.9,
    b: float = 1.0,
    c: float = 1.0,
    Rw: float = 0.1,
    Rv: float = 0.1,
    dof: float = 3.0,
    input_std: float = 1.0,
    random_state: int | np.random.Generator | None = None,
) -> SimulatedData:
    """The numerical example of Section 4.1 (eqs. 40-41), with additive outliers.

    ``x_{k+1} = a x_k + b u_k + w_k``, ``y_k = c cos(x_k) + v_k``, ``w_k ~ N(0, Rw)``,
    ``u_k ~ N(0, input_std^2)`` white, ``x_0 ~ N(0, 1)`` (``PAPER_X0_COV = 1``, our choice: the
    paper does not state the initial state).  ``v_k ~ N(0, Rv)`` for ``noise="gaussian"`` or
    ``St(0, Rv, dof)`` (``Rv`` the scale) for ``noise="student-t"``.  Then
    ``round(outlier_fraction * n_samples)`` distinct samples, chosen at random, get a
    ``U[outlier_range]`` draw added to ``y`` (NOTES §6-7: additive outliers).

    Parameters
    ----------
    n_samples : int
        Record length ``N`` (the paper: 500).
    outlier_fraction : float in [0, 1)
        Fraction of samples that get an outlier (the paper: 0.1).
    outlier_range : (float, float)
        Range of the uniform outliers (the paper: [-5, 5]).
    noise : {"gaussian", "student-t"}
        Distribution of the measurement noise ``v``.
    a, b, c : float
        True parameters (the paper: 0.9, 1, 1).
    Rw, Rv : float
        Process-noise variance and measurement-noise variance (Gaussian) or scale (Student-t);
        the paper: 0.1 and 0.1.  Zero gives a noise-free record.
    dof : float
        Degrees of freedom of ``v`` when ``noise="student-t"`` (ignored otherwise).
    input_std : float
        Standard deviation of the Gaussian white input.
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.

    Returns
    -------
    SimulatedData
        ``name="paper_example"``; ``u``, ``x``, ``y`` of shape ``(N, 1)``.
    """
    return _simulate_paper_system(
        name="paper_example",
        n_samples=n_samples,
        outlier_fraction=outlier_fraction,
        outlier_range=outlier_range,
        noise=noise,
        a=a,
        b=b,
        c=c,
        Rw=Rw,
        Rv=Rv,
        dof=dof,
        input_std=input_std,
        random_state=random_state,
    )


def make_gopaluni_example(
    n_samples: int = 400,
    outlier_fraction: float = 0.05,
    outlier_range: tuple[float, float] = (-6.0, 6.0),
    random_state: int | np.random.Generator | None = None,
) -> SimulatedData:
    """The data of the comparison with Gopaluni's Gaussian particle EM (Section 4.1, Figs. 3-6).

    The system of :func:`make_paper_example` (``a=0.9``, ``b=1``, ``c=1``, ``Rw=Rv=0.1``,
    Gaussian noise, unit-variance white input) with ``N = 400``; the paper uses 0% and 5%
    outliers, uniform in [-6, 6] (printed "[6,6]" in the paper: a typo).

    Parameters
    ----------
    n_samples : int
        Record length (the paper: 400).
    outlier_fraction : float in [0, 1)
        Fraction of samples with an additive outlier (the paper: 0 and 0.05).
    outlier_range : (float, float)
        Range of the uniform outliers.
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.

    Returns
    -------
    SimulatedData
        ``name="gopaluni_example"``.
    """
    return _simulate_paper_system(
        name="gopaluni_example",
        n_samples=n_samples,
        outlier_fraction=outlier_fraction,
        outlier_range=outlier_range,
        noise="gaussian",
        a=0.9,
        b=1.0,
        c=1.0,
        Rw=0.1,
        Rv=0.1,
        dof=math.inf,
        input_std=1.0,
        random_state=random_state,
    )


def make_huang_example(
    n_samples: int = 1000,
    Rv: float = 0.01,
    dof: float = 1.0,
    random_state: int | np.random.Generator | None = None,
    *,
    Rw: float = 0.1,
) -> SimulatedData:
    """The data of the comparison with Huang et al. (2016) (Section 4.1, Fig. 7, Table 1).

    The system of :func:`make_paper_example` (``a=0.9``, ``b=1``, ``c=1``, unit-variance white
    input) with ``N = 1000`` and heavy-tailed measurement noise ``v ~ St(0, Rv, dof)``; the paper:
    ``St(0, 0.01, 1)``, a Cauchy law of scale 0.1.  No outliers are added: the heavy tail of the
    noise makes them (``y_clean == y``, ``outlier_mask`` all False).  The paper does not restate
    the process noise for this comparison; ``Rw = 0.1`` (Gaussian), as in eq. (41), is our reading.

    Parameters
    ----------
    n_samples : int
        Record length (the paper: 1000).
    Rv : float
        Scale (squared) of the Student-t measurement noise.
    dof : float
        Degrees of freedom (1: Cauchy).
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.
    Rw : float, keyword-only
        Process-noise variance.

    Returns
    -------
    SimulatedData
        ``name="huang_example"``.
    """
    return _simulate_paper_system(
        name="huang_example",
        n_samples=n_samples,
        outlier_fraction=0.0,
        outlier_range=(-1.0, 1.0),
        noise="student-t",
        a=0.9,
        b=1.0,
        c=1.0,
        Rw=Rw,
        Rv=Rv,
        dof=dof,
        input_std=1.0,
        random_state=random_state,
    )


# --------------------------------------------------------------------------------------------
# Section 4.2: two-link manipulator
# --------------------------------------------------------------------------------------------


def manipulator_force(t: ArrayLike, constants: ManipulatorConstants | None = None) -> np.ndarray:
    """The known force ``F(t) = 10 sin(0.02 pi t)`` N (defaults; see :class:`ManipulatorConstants`).

    Parameters
    ----------
    t : array_like
        Times, s.
    constants : ManipulatorConstants, optional

    Returns
    -------
    ndarray
        ``F(t)``, same shape as ``t``.
    """
    cst = constants or ManipulatorConstants()
    return cst.force_amplitude * np.sin(cst.force_omega * np.asarray(t, dtype=np.float64))


def manipulator_transition_matrix(
    force: ArrayLike,
    dt: float = MANIPULATOR_DT,
    theta: tuple[float, float] = (1.0, 1.0),
    constants: ManipulatorConstants | None = None,
) -> np.ndarray:
    """The forward-Euler transition matrix ``I + dt A(t)`` of eq. (54) for given forces.

    ``A = [[-M^-1 E, -M^-1 K(t)], [diag(theta1, theta2), 0]]`` for the state
    ``x = [dphi1, dphi2, phi1, phi2]``, with ``K(t) = K0 + F(t) K1``; the mean of the next state
    is ``(I + dt A(t_k)) x_k``.

    Parameters
    ----------
    force : array_like, shape (...)
        Values of ``F(t_k)``, N.
    dt : float
        Euler step, s.
    theta : (float, float)
        The entries of the lower-left block (true values 1, 1).
    constants : ManipulatorConstants, optional

    Returns
    -------
    ndarray, shape (..., 4, 4)
    """
    cst = constants or ManipulatorConstants()
    MinvE, MinvK0, MinvK1 = cst.continuous_blocks()
    F = np.asarray(force, dtype=np.float64)[..., None, None]
    A = np.zeros(F.shape[:-2] + (4, 4))
    A[..., :2, :2] = -MinvE
    A[..., :2, 2:] = -(MinvK0 + F * MinvK1)
    A[..., 2, 0] = theta[0]
    A[..., 3, 1] = theta[1]
    return np.eye(4) + dt * A


def _manipulator_mean(
    x: np.ndarray,
    force: float,
    dt: float,
    theta: tuple[float, float],
    blocks: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """One Euler step, written the way :class:`torch_nssm.models.ManipulatorTransition` is."""
    MinvE, MinvK0, MinvK1 = blocks
    vel, ang = x[:2], x[2:]
    acc = -(MinvE @ vel) - (MinvK0 @ ang) - force * (MinvK1 @ ang)
    return np.concatenate([vel + dt * acc, ang + dt * np.asarray(theta) * vel])


def make_manipulator(
    n_samples: int = 500,
    outlier_fraction: float = 0.1,
    outlier_range: tuple[float, float] = MANIPULATOR_OUTLIER_RANGE,
    dt: float = MANIPULATOR_DT,
    theta: tuple[float, float] = (1.0, 1.0),
    Rw: ArrayLike = MANIPULATOR_RW,
    Rv: ArrayLike = MANIPULATOR_RV,
    random_state: int | np.random.Generator | None = None,
    *,
    noise: str = "gaussian",
    dof: float = 3.0,
    x0_mean: ArrayLike = MANIPULATOR_X0_MEAN,
    x0_cov: ArrayLike = MANIPULATOR_X0_COV,
    constants: ManipulatorConstants | None = None,
) -> SimulatedData:
    """The two-link manipulator of Section 4.2 (eqs. 49-55), discretised by forward Euler.

    ``M Phi'' + E Phi' + K(t) Phi = 0`` with ``Phi = [alpha11, alpha21]`` (small deviations of the
    link angles from equilibrium), ``M = diag(4ml^2/3, ml^2/3)``,
    ``E = [[d1+d2, -d2], [-d2, d2]]``, ``K11 = k1 + k2 - b4 sin(alpha10) - F(t) l cos(alpha10 -
    alpha3)``, ``K12 = K21 = -k2``, ``K22 = k2 - b5 sin(alpha20) - F(t) l cos(alpha20 - alpha3)``.
    The force enters only through the stiffness (parametric excitation), so the single input
    column is ``u_k = F(t_k)``, ``t_k = k dt``, ``F(t) = 10 sin(0.02 pi t)`` N.  State
    ``x = [dphi1, dphi2, phi1, phi2]``; ``x_{k+1} = (I + dt A(t_k; theta)) x_k + w_k`` (eq. 54)
    with ``theta1, theta2`` in the lower-left block of ``A``; output ``y_k = [phi1, phi2] + v_k``
    (eq. 55).  The physical constants are our choice (see :class:`ManipulatorConstants` and the
    ``MANIPULATOR_*`` module constants).  A ``RuntimeWarning`` is issued when the Euler step is
    unstable (spectral radius above 1) for some force in the record.

    Outliers are added to both angles of the chosen samples.

    Parameters
    ----------
    n_samples : int
        Record length (the paper: 500).
    outlier_fraction : float in [0, 1)
        Fraction of samples with an additive outlier (the paper: 0.05, 0.1, 0.2, 0.4).
    outlier_range : (float, float)
        Range of the uniform outliers, rad (default (-1, 1), our choice).
    dt : float
        Euler step / sampling period, s (default 0.2, our choice).
    theta : (float, float)
        True ``theta1, theta2`` (the paper: 1, 1).
    Rw : float, length-4 vector or (4, 4) matrix
        Process-noise covariance (default ``diag(MANIPULATOR_RW)``).
    Rv : float, length-2 vector or (2, 2) matrix
        Measurement-noise covariance (Gaussian) or scale (Student-t); default ``1e-4 I``.
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.
    noise : {"gaussian", "student-t"}
        Distribution of the measurement noise (the paper: Gaussian plus outliers).
    dof : float
        Degrees of freedom when ``noise="student-t"``.
    x0_mean : length-4 vector
        Prior mean of the first state (default: at rest, both angles 0.3 rad).
    x0_cov : float, length-4 vector or (4, 4) matrix
        Prior covariance of the first state.
    constants : ManipulatorConstants, optional
        Physical constants (default: the module constants).  ``noise`` to ``constants`` are
        keyword-only.

    Returns
    -------
    SimulatedData
        ``name="manipulator"``; ``u (N, 1)``, ``x (N, 4)``, ``y (N, 2)``.  ``params`` holds
        ``theta1``, ``theta2``, ``dt``, ``constants`` (a dict), the noise settings and the
        maximum spectral radius of the Euler step over the record (``max_spectral_radius``).
    """
    n = _check_n_samples(n_samples)
    fraction = _check_fraction(outlier_fraction)
    rng_out = _check_range(outlier_range)
    dt = _check_real(dt, "dt", low=0.0, strict=True)
    try:
        th = tuple(float(t) for t in theta)
    except (TypeError, ValueError):
        raise ValueError(f"theta must be a pair of numbers, got {theta!r}") from None
    if len(th) != 2 or not all(math.isfinite(t) for t in th):
        raise ValueError(f"theta must be a pair of finite numbers, got {theta!r}")
    Rw_m = _check_cov(Rw, 4, "Rw")
    Rv_m = _check_cov(Rv, 2, "Rv")
    noise = _check_noise(noise)
    nu_dof = math.inf if noise == "gaussian" else _check_real(dof, "dof", low=0.0, strict=True)
    m0 = _check_vector(x0_mean, 4, "x0_mean")
    P0 = _check_cov(x0_cov, 4, "x0_cov")
    if constants is None:
        constants = ManipulatorConstants()
    elif not isinstance(constants, ManipulatorConstants):
        raise ValueError(f"constants must be a ManipulatorConstants, got {type(constants)!r}")

    t = dt * np.arange(n)
    force = manipulator_force(t, constants)
    rho = float(np.abs(np.linalg.eigvals(manipulator_transition_matrix(force, dt, th, constants))).max())
    if rho > 1.0:
        warnings.warn(
            f"the forward-Euler step is unstable for this record (spectral radius {rho:.3f} > 1); "
            "reduce dt or increase the damping",
            RuntimeWarning,
            stacklevel=2,
        )

    rng = np.random.default_rng(random_state)
    blocks = constants.continuous_blocks()
    x = np.empty((n, 4))
    x[0] = m0 + _cov_sqrt(P0) @ rng.standard_normal(4)
    w = rng.standard_normal((n, 4)) @ _cov_sqrt(Rw_m).T
    for k in range(n - 1):
        x[k + 1] = _manipulator_mean(x[k], force[k], dt, th, blocks) + w[k]
    v = _measurement_noise(rng, n, Rv_m, nu_dof)
    y_clean = x[:, 2:] + v
    y, mask = _add_outliers(rng, y_clean, fraction, rng_out)
    params = {
        "theta1": th[0],
        "theta2": th[1],
        "dt": dt,
        "Rw": _to_list(Rw_m),
        "Rv": _to_list(Rv_m),
        "dof": nu_dof,
        "noise": noise,
        "x0_mean": _to_list(m0),
        "x0_cov": _to_list(P0),
        "constants": asdict(constants),
        "outlier_fraction": fraction,
        "outlier_range": list(rng_out),
        "n_outliers": int(mask.sum()),
        "max_spectral_radius": rho,
    }
    return SimulatedData(
        u=force[:, None],
        y=y,
        x=x,
        y_clean=y_clean,
        outlier_mask=mask,
        params=params,
        name="manipulator",
    )


# --------------------------------------------------------------------------------------------
# Silverbox
# --------------------------------------------------------------------------------------------

_REPO_ROOT = Path(__file__).resolve().parent.parent


@functools.lru_cache(maxsize=4)
def _read_silverbox_csv(path: str, mtime_ns: int) -> np.ndarray:
    with open(path, encoding="utf-8") as fh:
        header = fh.readline()
    names = [h.strip().strip('"') for h in header.strip().split(",")]
    try:
        cols = (names.index("V1"), names.index("V2"))
    except ValueError:
        raise ValueError(f"{path}: expected columns 'V1' and 'V2' in the header, got {names}") from None
    data = np.loadtxt(path, delimiter=",", skiprows=1, usecols=cols, dtype=np.float64, ndmin=2)
    data.setflags(write=False)
    return data


def load_silverbox(
    path: str | os.PathLike[str] | None = None,
    part: str = "multisine",
    file: str = "SNLS80mV.csv",
) -> tuple[np.ndarray, np.ndarray]:
    """Read the Silverbox benchmark (Wigren & Schoukens 2013): input ``V1``, output ``V2``.

    The sampling frequency is :data:`SILVERBOX_FS` (``10^7 / 2^14`` Hz).  In ``SNLS80mV.csv``
    samples ``[0, 40700)`` are the "arrow" part (usual test set) and ``[40700, end)`` the
    multisine part (usual training set).  Other files (``Schroeder80mV.csv``) only have
    ``part="all"``.

    Parameters
    ----------
    path : str or path-like, optional
        Directory holding the CSV files.  Default: ``../shared/data/silverbox`` relative to the
        current working directory, then relative to the repository root.
    part : {"multisine", "arrow", "all"}
        Which samples to return.
    file : str
        File name inside the directory.

    Returns
    -------
    u, y : ndarray, shape (N, 1)
        Input and output voltages, float64.

    Raises
    ------
    FileNotFoundError
        If the file is in none of the directories tried (listed in the message).
    ValueError
        If ``part`` is unknown, or not ``"all"`` for a file other than ``SNLS80mV.csv``.
    """
    if part not in ("multisine", "arrow", "all"):
        raise ValueError(f"part must be 'multisine', 'arrow' or 'all', got {part!r}")
    if part != "all" and file != "SNLS80mV.csv":
        raise ValueError(f"part={part!r} is defined for SNLS80mV.csv only; use part='all' for {file!r}")
    if path is not None:
        dirs = [Path(path)]
    else:
        dirs = [
            Path.cwd() / ".." / "shared" / "data" / "silverbox",
            _REPO_ROOT / ".." / "shared" / "data" / "silverbox",
        ]
    tried = []
    for d in dirs:
        candidate = (d / file).resolve()
        tried.append(str(candidate))
        if candidate.is_file():
            data = _read_silverbox_csv(str(candidate), candidate.stat().st_mtime_ns)
            break
    else:
        raise FileNotFoundError(
            f"Silverbox file {file!r} not found; tried: {', '.join(tried)}. Get the data from "
            "the nonlinear system identification benchmark collection "
            "(https://www.nonlinearbenchmark.org, or the `nonlinear-benchmarks` Python package, "
            "which downloads it) and pass its directory as `path`."
        )
    if part == "arrow":
        data = data[:SILVERBOX_ARROW_END]
    elif part == "multisine":
        data = data[SILVERBOX_ARROW_END:]
    return data[:, :1].copy(), data[:, 1:2].copy()
