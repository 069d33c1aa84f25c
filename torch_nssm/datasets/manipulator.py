"""The two-link manipulator of the paper's Section 4.2: constants, physics, generator, ``f`` / ``g``.

``M Phi'' + E Phi' + K(t) Phi = 0`` (eqs. 49-55), discretised by forward Euler; the known force
``F(t)`` is the input.  The paper does not print the physical constants: the ``MANIPULATOR_*``
values below are our choice (the comment above them says why).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor, nn

from .. import _validation as V
from .._ops import broadcast_leading
from ..core.parametric import LinearInParameters
from ._base import (
    NOISE_KINDS,
    ArrayLike,
    SimulatedData,
    _add_outliers,
    _cov_sqrt,
    _measurement_noise,
    _scalar_parameter,
    _to_list,
)

__all__ = [
    "ManipulatorConstants",
    "make_manipulator",
    "manipulator_force",
    "manipulator_transition_matrix",
    "ManipulatorTransition",
    "ManipulatorObservation",
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
    (eq. 55).  The physical constants are our choice (:class:`ManipulatorConstants`, the
    ``MANIPULATOR_*`` constants).  A ``RuntimeWarning`` says when the Euler step is unstable.

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
    n = V.check_count(n_samples, "n_samples", 1)
    fraction = V.check_real(outlier_fraction, "outlier_fraction", low=0.0, high=1.0, high_open=True)
    rng_out = V.check_pair(outlier_range, "outlier_range")
    dt = V.check_real(dt, "dt", low=0.0, low_open=True)
    th = _check_theta(theta)
    Rw_m = V.check_covariance_array(Rw, "Rw", 4)
    Rv_m = V.check_covariance_array(Rv, "Rv", 2)
    noise = V.check_choice(noise, "noise", NOISE_KINDS)
    nu_dof = (
        math.inf if noise == "gaussian"
        else V.check_real(dof, "dof", low=0.0, high=math.inf, low_open=True, high_open=True)
    )
    m0 = V.check_vector_array(x0_mean, "x0_mean", 4)
    P0 = V.check_covariance_array(x0_cov, "x0_cov", 4)
    if constants is None:
        constants = ManipulatorConstants()
    elif not isinstance(constants, ManipulatorConstants):
        raise ValueError(f"constants must be a ManipulatorConstants, got {type(constants)!r}")

    t = dt * np.arange(n)
    force = manipulator_force(t, constants)
    rho = _euler_radius(force, dt, th, constants)
    rng = np.random.default_rng(random_state)
    x = _states(rng, n, m0, P0, Rw_m, force, dt, th, constants)
    v = _measurement_noise(rng, n, Rv_m, noise, dof_init=nu_dof)
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


def _check_theta(theta) -> tuple[float, float]:
    try:
        th = tuple(float(t) for t in theta)
    except (TypeError, ValueError):
        raise ValueError(f"theta must be a pair of numbers, got {theta!r}") from None
    if len(th) != 2 or not all(math.isfinite(t) for t in th):
        raise ValueError(f"theta must be a pair of finite numbers, got {theta!r}")
    return th


def _euler_radius(force: np.ndarray, dt: float, th, constants: ManipulatorConstants) -> float:
    """The largest spectral radius of the forward-Euler step over the record (a warning above 1)."""
    rho = float(np.abs(np.linalg.eigvals(manipulator_transition_matrix(force, dt, th, constants))).max())
    if rho > 1.0:
        warnings.warn(
            f"the forward-Euler step is unstable for this record (spectral radius {rho:.3f} > 1); "
            "reduce dt or increase the damping",
            RuntimeWarning,
            stacklevel=3,
        )
    return rho


def _states(rng, n: int, m0, P0, Rw_m, force, dt: float, th, constants: ManipulatorConstants) -> np.ndarray:
    """The simulated states ``(n, 4)``: the first from the prior, then the Euler steps plus noise."""
    blocks = constants.continuous_blocks()
    x = np.empty((n, 4))
    x[0] = m0 + _cov_sqrt(P0) @ rng.standard_normal(4)
    w = rng.standard_normal((n, 4)) @ _cov_sqrt(Rw_m).T
    for k in range(n - 1):
        x[k + 1] = _manipulator_mean(x[k], force[k], dt, th, blocks) + w[k]
    return x


# --------------------------------------------------------------------------------------------
# The model as f / g modules
# --------------------------------------------------------------------------------------------


class ManipulatorTransition(LinearInParameters):
    """Forward-Euler step of the two-link manipulator (eq. 54), linear in ``(theta1, theta2)``.

    State ``x = [dphi1, dphi2, phi1, phi2]``, input ``u = [F(t_k)]`` (the force, N).  With
    ``M^-1 E``, ``M^-1 K0``, ``M^-1 K1`` from :class:`~torch_nssm.datasets.ManipulatorConstants`
    (``K(t) = K0 + F(t) K1``)::

        dphi_{k+1} = dphi_k + dt (-M^-1 E dphi_k - M^-1 (K0 + F_k K1) phi_k)     (offset)
        phi_{k+1}  = phi_k  + dt diag(theta1, theta2) dphi_k                     (Phi @ theta)

    It reproduces :func:`~torch_nssm.datasets.make_manipulator` exactly when built with the same
    ``dt`` and ``constants``.

    Parameters
    ----------
    theta1, theta2 : float or Tensor
        Initial values (default: the true values 1, 1).
    dt : float
        Euler step, s (default :data:`~torch_nssm.datasets.MANIPULATOR_DT`).
    constants : ManipulatorConstants, optional
        Physical constants (default: the module constants of :mod:`torch_nssm.datasets`).
    dtype : torch.dtype
        Dtype of the parameters and buffers.
    device : torch.device or str, optional
    """

    nx = 4
    nu = 1

    def __init__(
        self,
        theta1: float | Tensor = 1.0,
        theta2: float | Tensor = 1.0,
        *,
        dt: float = MANIPULATOR_DT,
        constants: ManipulatorConstants | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.theta1 = _scalar_parameter(theta1, dtype, device)
        self.theta2 = _scalar_parameter(theta2, dtype, device)
        self.dt = float(dt)
        self.constants = constants if constants is not None else ManipulatorConstants()
        MinvE, MinvK0, MinvK1 = self.constants.continuous_blocks()
        for name, mat in (("MinvE", MinvE), ("MinvK0", MinvK0), ("MinvK1", MinvK1)):
            self.register_buffer(name, torch.as_tensor(mat, dtype=dtype, device=device).clone())

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` of shape ``(..., 4, 2)`` (``dt dphi_i`` at row ``2 + i``, column ``i``), offset
        ``(..., 4)``."""
        x, u = broadcast_leading(x, u)
        vel, ang = x[..., :2], x[..., 2:]
        force = u[..., :1]
        acc = -(vel @ self.MinvE.T) - (ang @ self.MinvK0.T) - force * (ang @ self.MinvK1.T)
        offset = torch.cat([vel + self.dt * acc, ang], dim=-1)
        Phi = x.new_zeros(x.shape[:-1] + (4, 2))
        Phi[..., 2, 0] = self.dt * vel[..., 0]
        Phi[..., 3, 1] = self.dt * vel[..., 1]
        return Phi, offset

    def extra_repr(self) -> str:
        return f"theta1={self.theta1.item():.6g}, theta2={self.theta2.item():.6g}, dt={self.dt:g}"


class ManipulatorObservation(nn.Module):
    """``g(x, u) = [phi1, phi2]`` (eq. 55): the two angles; no parameters, ``u`` unused.

    A plain ``nn.Module`` (``LinearInParameters`` needs at least one parameter); the EM engine
    skips the M-step of a module without free parameters.
    """

    nx = 4
    ny = 2

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., 2:4]
