"""A damped pendulum driven by a torque: generator and the ``f`` / ``g`` a user would write.

``theta'' = -(g/l) sin(theta) - d theta' + b u`` with the angle ``theta`` measured; the transition
is one classical Runge-Kutta (RK4) step per sample, written by hand in :class:`PendulumTransition`,
and the generator (:func:`make_pendulum`) simulates exactly that discrete model, with a small
random torque as process noise.  Three physical parameters, all free; the model is nonlinear in
them (RK4 of ``sin``).  ``make_pendulum(friction=...)`` adds a dry friction in the pivot that
:func:`pendulum_model` does not have: a gap in the physics for a grey box's correction to fill.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ._plants import (
    PlantData,
    RK4Transition,
    band_noise,
    check_settings,
    check_variances,
    checked_params,
    measurement_noise,
    noise_params,
    process_noise,
    record,
    rk4_step,
    scalar_parameters,
    spawn_streams,
)

__all__ = [
    "PENDULUM_DT",
    "PENDULUM_TRUE",
    "PENDULUM_START",
    "PENDULUM_RW",
    "PENDULUM_RV",
    "PENDULUM_FRICTION_WIDTH",
    "PendulumTransition",
    "PendulumObservation",
    "make_pendulum",
    "pendulum_model",
]

#: Sampling period, s (about 28 samples per period of the small swings, 1.42 s).
PENDULUM_DT: float = 0.05
#: True parameters: ``g_over_l`` (1/s^2; a 0.5 m pendulum), ``damping`` (1/s; damping ratio 5.6 %),
#: ``gain`` (rad/s^2 per N m of torque).
PENDULUM_TRUE: dict[str, float] = {"g_over_l": 19.62, "damping": 0.5, "gain": 4.0}
#: The physically sized start: ``g_over_l`` x 0.6, ``damping`` x 1.5, ``gain`` x 0.7.
PENDULUM_START: dict[str, float] = {"g_over_l": 11.772, "damping": 0.75, "gain": 2.8}
#: Process-noise variances of ``[theta, theta']`` per step: a random torque on the rate only.
PENDULUM_RW: tuple[float, float] = (0.0, 4e-4)
#: Measurement-noise variance of the angle, rad^2 (s.d. 0.01 rad).
PENDULUM_RV: float = 1e-4
#: Torque input: Gaussian noise band-limited to this band (Hz; the resonance is at 0.70 Hz), s.d.
PENDULUM_INPUT_BAND: tuple[float, float] = (0.0, 1.0)
PENDULUM_INPUT_STD: float = 0.7
#: Rate (rad/s) over which the pivot's dry friction ``friction * tanh(theta' / width)`` changes
#: sign (a smooth Coulomb friction; ``make_pendulum(friction=...)``).
PENDULUM_FRICTION_WIDTH: float = 0.1
#: First state of the validation record: released from 0.5 rad (the training record starts at rest).
PENDULUM_VALIDATION_X0: tuple[float, float] = (0.5, 0.0)


class PendulumTransition(RK4Transition):
    """One RK4 step of ``theta'' = -(g/l) sin(theta) - d theta' + b u``; state ``[theta, theta']``.

    Parameters
    ----------
    g_over_l, damping, gain : float
        Initial values (default: the truth, :data:`PENDULUM_TRUE`).
    dt : float
        Step, s.
    friction : float, default=0.0
        The pivot's dry friction of ``make_pendulum(friction=...)`` (fixed, not a parameter): the
        true model of such a record, which the user's model (``friction=0``) lacks.
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    nu = 1

    def __init__(
        self,
        g_over_l: float = PENDULUM_TRUE["g_over_l"],
        damping: float = PENDULUM_TRUE["damping"],
        gain: float = PENDULUM_TRUE["gain"],
        *,
        dt: float = PENDULUM_DT,
        friction: float = 0.0,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        scalar_parameters(self, {"g_over_l": g_over_l, "damping": damping, "gain": gain}, dtype, device)
        self.dt = float(dt)
        self.friction = float(friction)

    def rates(self, x: Tensor, u: Tensor) -> Tensor:
        """``[theta', theta'']`` at ``x`` ``(..., 2)`` and ``u`` ``(..., 1)``."""
        theta, omega = x[..., 0], x[..., 1]
        acc = -self.g_over_l * torch.sin(theta) - self.damping * omega + self.gain * u[..., 0]
        if self.friction:
            acc = acc - self.friction * torch.tanh(omega / PENDULUM_FRICTION_WIDTH)
        return torch.stack([omega, acc], dim=-1)


class PendulumObservation(nn.Module):
    """``y = theta``: the measured angle (no parameters)."""

    nx = 2
    ny = 1

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., :1]


def pendulum_model(
    params: dict[str, float] | None = None, *, dtype: torch.dtype = torch.float64, device=None
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at ``params`` (default: the truth; e.g. :data:`PENDULUM_START`)."""
    p = checked_params(params, PENDULUM_TRUE)
    return PendulumTransition(**p, dtype=dtype, device=device), PendulumObservation()


def _rates(x: np.ndarray, u: float, p: dict[str, float]) -> np.ndarray:
    acc = -p["g_over_l"] * np.sin(x[0]) - p["damping"] * x[1] + p["gain"] * u
    if p.get("friction"):  # the pivot's dry friction, absent from PendulumTransition
        acc = acc - p["friction"] * np.tanh(x[1] / PENDULUM_FRICTION_WIDTH)
    return np.array([x[1], acc])


def _simulate(
    rng: np.random.Generator, n: int, x0, p: dict[str, float], Rw: np.ndarray, Rv: np.ndarray, std: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    u = band_noise(rng, n, PENDULUM_DT, PENDULUM_INPUT_BAND, std)
    w = process_noise(rng, n, Rw)
    x = np.empty((n, 2))
    x[0] = x0
    for k in range(n - 1):
        x[k + 1] = rk4_step(_rates, x[k], u[k], p, PENDULUM_DT) + w[k]
    y_true = x[:, :1].copy()
    return u, x, y_true, y_true + measurement_noise(rng, n, Rv)


def make_pendulum(
    n_samples: int = 2000,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 2000,
    Rw: Any = PENDULUM_RW,
    Rv: Any = PENDULUM_RV,
    input_std: float = PENDULUM_INPUT_STD,
    params: dict[str, float] | None = None,
    friction: float = 0.0,
) -> PlantData:
    """A damped pendulum driven by a band-limited random torque, angle measured.

    The training record starts at rest (``x0_guess = [0, 0]``, the truth); the validation record
    (``n_validation`` samples, another torque realisation, no outliers) is released from
    :data:`PENDULUM_VALIDATION_X0`.  With the default torque (s.d. 0.7 N m) the angle swings to
    +-1.6-1.9 rad (s.d. about 0.5 rad), far into the ``sin`` nonlinearity.  Gross outliers:
    ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations of the clean angle.

    Parameters
    ----------
    n_samples : int
        Training record length (default 2,000 samples, 100 s).
    outlier_fraction : float in [0, 1)
        Fraction of training samples with a gross outlier.
    random_state : int, Generator or None
        Seed (see :mod:`torch_nssm.datasets._plants` for the streams).
    n_validation : int
        Validation record length.
    Rw : pair of float
        Process-noise variances of ``[theta, theta']`` per step (default :data:`PENDULUM_RW`).
    Rv : float
        Measurement-noise variance of the angle (default :data:`PENDULUM_RV`).
    input_std : float
        Standard deviation of the torque, N m.
    params : dict, optional
        True parameters (default :data:`PENDULUM_TRUE`; missing keys keep their default).
    friction : float, default=0.0
        Dry friction of the pivot, rad/s^2: ``- friction * tanh(theta' / PENDULUM_FRICTION_WIDTH)``
        in the angular acceleration.  :func:`pendulum_model` does not have it (with ``friction=1``
        the true parameters without it simulate the validation record to about 0.2 rad): a record
        for grey-box models (:class:`~torch_nssm.neural.GreyBoxTransition`).

    Returns
    -------
    PlantData
        ``name="pendulum"``; ``u (N, 1)``, ``x (N, 2)``, ``y (N, 1)``.
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 2)
    Rv_v = check_variances(Rv, "Rv", 1)
    p = checked_params(params, PENDULUM_TRUE)
    std = float(input_std)
    if not (math.isfinite(std) and std >= 0):
        raise ValueError(f"input_std must be a finite non-negative number, got {input_std!r}")
    dry = float(friction)
    if not (math.isfinite(dry) and dry >= 0):
        raise ValueError(f"friction must be a finite non-negative number, got {friction!r}")
    if dry:
        p = {**p, "friction": dry}
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {**p, **noise_params(Rw_v, Rv_v), "input_std": std, "input_band": list(PENDULUM_INPUT_BAND)}
    u, x, y_true, y_clean = _simulate(rng_val, n_val, PENDULUM_VALIDATION_X0, p, Rw_v, Rv_v, std)
    validation = record(
        name="pendulum", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=PENDULUM_DT,
        x0_guess=np.zeros(2),
    )
    u, x, y_true, y_clean = _simulate(rng_train, n, (0.0, 0.0), p, Rw_v, Rv_v, std)
    return record(
        name="pendulum", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=PENDULUM_DT,
        x0_guess=np.zeros(2), outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )
