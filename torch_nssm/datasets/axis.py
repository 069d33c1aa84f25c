"""A positioning axis recorded in closed loop: generator and the ``f`` / ``g`` a user would write.

A carriage of mass ``M`` on a linear guide, driven by a motor force ``u``, with viscous friction
``b v``, Coulomb friction ``Fc tanh(v / v_s)`` (smoothed, ``v_s`` known) and a constant force
offset ``F0`` (gravity on a slightly inclined axis, a cable chain).  Forward Euler at 1 ms, as a
user writes it::

    p+ = p + dt v
    v+ = v + dt (u - b v - Fc tanh(v / v_s) - F0) / M

A PID position controller tracks point-to-point moves; the record holds the controller's force as
``u`` and the encoder's position (quantised to :data:`AXIS_QUANTUM`) as ``y``.  Four physical
parameters, all free; :class:`AxisTransition` is nonlinear in them (``1 / M``) and
:class:`AxisLinearTransition` is the same model written linear in ``(1/M, b/M, Fc/M, F0/M)``
(:class:`~torch_nssm.LinearInParameters`, closed-form M-steps).  The generator simulates exactly
this discrete model, with a small random force as process noise.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from .._ops import broadcast_leading
from ..core.parametric import LinearInParameters
from ._plants import (
    PlantData,
    check_settings,
    check_variances,
    checked_params,
    noise_params,
    parameter_values,
    process_noise,
    record,
    scalar_parameters,
    spawn_streams,
)

__all__ = [
    "AXIS_DT",
    "AXIS_TRUE",
    "AXIS_START",
    "AXIS_RW",
    "AXIS_QUANTUM",
    "AXIS_VS",
    "AxisTransition",
    "AxisLinearTransition",
    "AxisObservation",
    "axis_linear_parameters",
    "axis_model",
    "make_axis",
]

#: Sampling period of the controller and the record, s.
AXIS_DT: float = 1e-3
#: True parameters: ``mass`` (kg), ``viscous`` (N s/m), ``coulomb`` (N), ``offset`` (N).
AXIS_TRUE: dict[str, float] = {"mass": 5.0, "viscous": 25.0, "coulomb": 8.0, "offset": 2.0}
#: The physically sized start: ``mass`` x 1.4, ``viscous`` x 0.6, ``coulomb`` x 0.5, ``offset`` x 1.5.
AXIS_START: dict[str, float] = {"mass": 7.0, "viscous": 15.0, "coulomb": 4.0, "offset": 3.0}
#: Velocity scale of the smoothed Coulomb friction ``Fc tanh(v / v_s)``, m/s (known, not fitted).
AXIS_VS: float = 0.005
#: Process-noise variances of ``[p, v]`` per step: a random force of s.d. 0.5 N on the velocity,
#: ``(dt * 0.5 N / M)^2``.
AXIS_RW: tuple[float, float] = (0.0, (AXIS_DT * 0.5 / AXIS_TRUE["mass"]) ** 2)
#: Encoder resolution, m: the measured position is ``AXIS_QUANTUM * round(p / AXIS_QUANTUM)``
#: (measurement noise uniform, variance ``AXIS_QUANTUM^2 / 12``).
AXIS_QUANTUM: float = 5e-6
#: PID gains (force per position error, its integral, and the filtered velocity) for a closed-loop
#: bandwidth of about 10 Hz, the derivative's low-pass filter (Hz), and the force limit (N).
AXIS_PID: dict[str, float] = {
    "kp": 19_700.0, "ki": 155_000.0, "kd": 440.0, "d_filter_hz": 200.0, "u_max": 150.0,
}
#: The reference: targets uniform in +-``AXIS_TRAVEL`` m, moves of 0.3-0.8 s along quintic
#: profiles, dwells of 0.1-0.5 s.
AXIS_TRAVEL: float = 0.1
#: First positions of the training and validation records (m); both start at rest, holding.
AXIS_START_POSITIONS: tuple[float, float] = (0.0, 0.05)


class AxisTransition(nn.Module):
    """One forward-Euler step of the axis (module docstring); state ``[p, v]``, input the force.

    Parameters
    ----------
    mass, viscous, coulomb, offset : float
        Initial values (default: the truth, :data:`AXIS_TRUE`).
    dt : float
        Step, s.
    vs : float
        Velocity scale of the Coulomb friction's ``tanh``, m/s (fixed).
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    nu = 1

    def __init__(
        self,
        mass: float = AXIS_TRUE["mass"],
        viscous: float = AXIS_TRUE["viscous"],
        coulomb: float = AXIS_TRUE["coulomb"],
        offset: float = AXIS_TRUE["offset"],
        *,
        dt: float = AXIS_DT,
        vs: float = AXIS_VS,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        values = {"mass": mass, "viscous": viscous, "coulomb": coulomb, "offset": offset}
        scalar_parameters(self, values, dtype, device)
        self.dt, self.vs = float(dt), float(vs)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        p, v = x[..., 0], x[..., 1]
        force = u[..., 0] - self.viscous * v - self.coulomb * torch.tanh(v / self.vs) - self.offset
        return torch.stack([p + self.dt * v, v + self.dt * force / self.mass], dim=-1)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in parameter_values(self).items()) + f", dt={self.dt:g}"


class AxisLinearTransition(LinearInParameters):
    """The axis of :class:`AxisTransition` written linear in ``theta = (1/M, b/M, Fc/M, F0/M)``::

        p+ = p + dt v                                              (offset)
        v+ = v + dt (inv_mass u - b_over_m v - fc_over_m tanh(v / v_s) - f0_over_m)

    Parameters
    ----------
    inv_mass, b_over_m, fc_over_m, f0_over_m : float
        Initial values (default: the truth, :func:`axis_linear_parameters` of :data:`AXIS_TRUE`).
    dt, vs : float
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    nu = 1

    def __init__(
        self,
        inv_mass: float = 1.0 / AXIS_TRUE["mass"],
        b_over_m: float = AXIS_TRUE["viscous"] / AXIS_TRUE["mass"],
        fc_over_m: float = AXIS_TRUE["coulomb"] / AXIS_TRUE["mass"],
        f0_over_m: float = AXIS_TRUE["offset"] / AXIS_TRUE["mass"],
        *,
        dt: float = AXIS_DT,
        vs: float = AXIS_VS,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        values = {"inv_mass": inv_mass, "b_over_m": b_over_m, "fc_over_m": fc_over_m, "f0_over_m": f0_over_m}
        scalar_parameters(self, values, dtype, device)
        self.dt, self.vs = float(dt), float(vs)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` ``(..., 2, 4)`` (the velocity row ``dt [u, -v, -tanh(v / v_s), -1]``) and the
        offset ``[p + dt v, v]``."""
        x, u = broadcast_leading(x, u)
        p, v = x[..., 0], x[..., 1]
        dt = self.dt
        zero = torch.zeros_like(v)
        friction = torch.tanh(v / self.vs)
        row_v = torch.stack([dt * u[..., 0], -dt * v, -dt * friction, torch.full_like(v, -dt)], dim=-1)
        Phi = torch.stack([torch.stack([zero, zero, zero, zero], -1), row_v], dim=-2)
        return Phi, torch.stack([p + dt * v, v], dim=-1)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in parameter_values(self).items()) + f", dt={self.dt:g}"


class AxisObservation(nn.Module):
    """``y = p``: the encoder's position (no parameters; the quantisation is the measurement noise)."""

    nx = 2
    ny = 1

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., :1]


def axis_linear_parameters(params: dict[str, float] | None = None) -> dict[str, float]:
    """The physical parameters (default :data:`AXIS_TRUE`) as :class:`AxisLinearTransition`'s."""
    p = checked_params(params, AXIS_TRUE)
    m = p["mass"]
    return {
        "inv_mass": 1.0 / m, "b_over_m": p["viscous"] / m, "fc_over_m": p["coulomb"] / m,
        "f0_over_m": p["offset"] / m,
    }


def axis_model(
    params: dict[str, float] | None = None,
    *,
    linear: bool = False,
    dtype: torch.dtype = torch.float64,
    device=None,
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at the physical ``params`` (default: the truth; e.g. :data:`AXIS_START`);
    ``linear=True``: ``f`` is :class:`AxisLinearTransition` at the same parameters."""
    p = checked_params(params, AXIS_TRUE)
    if linear:
        f = AxisLinearTransition(**axis_linear_parameters(p), dtype=dtype, device=device)
        return f, AxisObservation()
    return AxisTransition(**p, dtype=dtype, device=device), AxisObservation()


def _step(p_: float, v: float, u: float, prm: dict[str, float]) -> tuple[float, float]:
    """The step of :class:`AxisTransition`, in the same order of operations."""
    force = u - prm["viscous"] * v - prm["coulomb"] * math.tanh(v / AXIS_VS) - prm["offset"]
    return p_ + AXIS_DT * v, v + AXIS_DT * force / prm["mass"]


def _reference(rng: np.random.Generator, n: int, start: float) -> np.ndarray:
    """Point-to-point moves along quintic profiles with dwells, from ``start``."""
    r = np.empty(n)
    k, pos = 0, start
    while k < n:
        dwell = int(rng.uniform(0.1, 0.5) / AXIS_DT)
        r[k : k + dwell] = pos
        k += dwell
        target = rng.uniform(-AXIS_TRAVEL, AXIS_TRAVEL)
        steps = int(rng.uniform(0.3, 0.8) / AXIS_DT)
        s = np.arange(1, steps + 1) / steps
        r[k : k + steps] = (pos + (target - pos) * (10 * s**3 - 15 * s**4 + 6 * s**5))[: max(0, n - k)]
        k += steps
        pos = target
    return r


def _closed_loop(rng, n, start, prm, Rw, quantum):
    """The PID loop: returns the force ``u``, the states and the quantised positions."""
    r = _reference(rng, n, start)
    w = process_noise(rng, n, Rw)
    kp, ki, kd = AXIS_PID["kp"], AXIS_PID["ki"], AXIS_PID["kd"]
    a = math.exp(-2 * math.pi * AXIS_PID["d_filter_hz"] * AXIS_DT)
    u_max = AXIS_PID["u_max"]
    x = np.empty((n, 2))
    u = np.empty(n)
    yq = np.empty(n)
    p_, v = start, 0.0
    integral = prm["offset"]  # the loop was holding the axis before the record starts
    vf, y_prev = 0.0, None
    for k in range(n):
        x[k] = (p_, v)
        y_k = quantum * round(p_ / quantum) if quantum > 0 else p_
        yq[k] = y_k
        vf = a * vf + (1 - a) * (0.0 if y_prev is None else (y_k - y_prev) / AXIS_DT)
        y_prev = y_k
        e = r[k] - y_k
        integral += ki * AXIS_DT * e
        u[k] = min(max(kp * e + integral - kd * vf, -u_max), u_max)
        p_, v = _step(p_, v, u[k], prm)
        p_, v = p_ + w[k, 0], v + w[k, 1]
    return u, x, yq


def make_axis(
    n_samples: int = 25_000,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 10_000,
    Rw: Any = AXIS_RW,
    quantum: float = AXIS_QUANTUM,
    params: dict[str, float] | None = None,
) -> PlantData:
    """A positioning axis under PID position control; force and quantised position recorded.

    Each record starts at rest, holding its first position (:data:`AXIS_START_POSITIONS`), with the
    controller's integrator at the force offset; ``x0_guess`` is a user's: ``[median of the first 10
    measured positions, 0]``.  The reference moves between targets in +-0.1 m (peak speeds up to
    about 1 m/s), so the carriage crosses zero speed at every reversal (Coulomb friction) and spends
    about 40 % of the time holding.  The measurement noise is the encoder's quantisation
    (``quantum``; 0 switches it off).  Gross outliers (recording glitches, not seen by the
    controller): ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations of the
    position.

    Parameters
    ----------
    n_samples : int
        Training record length (default 25,000 samples, 25 s).
    outlier_fraction : float in [0, 1)
    random_state : int, Generator or None
    n_validation : int
        Validation record length (default 10,000 samples).
    Rw : pair of float
        Process-noise variances of ``[p, v]`` per step (default :data:`AXIS_RW`).
    quantum : float
        Encoder resolution, m (default :data:`AXIS_QUANTUM`).
    params : dict, optional
        True parameters (default :data:`AXIS_TRUE`).

    Returns
    -------
    PlantData
        ``name="axis"``; ``u (N, 1)`` (N), ``x (N, 2)`` (m, m/s), ``y (N, 1)`` (m).  ``params["Rv"]``
        is the quantisation's variance ``quantum^2 / 12``.
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 2)
    q = float(quantum)
    if not (math.isfinite(q) and q >= 0):
        raise ValueError(f"quantum must be a finite non-negative number, got {quantum!r}")
    prm = checked_params(params, AXIS_TRUE)
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {
        **prm, **noise_params(Rw_v, np.array([q**2 / 12.0])), "quantum": q, "vs": AXIS_VS,
        "pid": dict(AXIS_PID),
    }

    def guess(y: np.ndarray) -> np.ndarray:
        return np.array([float(np.median(y[:10])), 0.0])

    u, x, yq = _closed_loop(rng_val, n_val, AXIS_START_POSITIONS[1], prm, Rw_v, q)
    validation = record(
        name="axis", u=u, x=x, y_true=x[:, :1], y_clean=yq, params=settings, dt=AXIS_DT, x0_guess=guess
    )
    u, x, yq = _closed_loop(rng_train, n, AXIS_START_POSITIONS[0], prm, Rw_v, q)
    return record(
        name="axis", u=u, x=x, y_true=x[:, :1], y_clean=yq, params=settings, dt=AXIS_DT, x0_guess=guess,
        outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )
