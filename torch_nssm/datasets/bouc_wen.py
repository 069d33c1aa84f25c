"""A hysteretic Bouc-Wen oscillator: generator and the ``f`` / ``g`` a user would write.

A mass-spring-damper with a Bouc-Wen hysteretic force ``z`` (the nonlinear system identification
benchmark of Noel & Schoukens, with its parameters, in SI units)::

    m x'' + c x' + k x + z = u
    z' = A x' - beta |x'| z - gamma x' |z|

State ``[x, x', z]`` (m, m/s, N); the displacement is measured, the force ``u`` (N) is the input.
The benchmark's ``beta (gamma |x'| z + delta x' |z|)`` with ``beta = 1000``, ``gamma = 0.8``,
``delta = -1.1`` is written here with ``beta = 800`` and ``gamma = -1100`` (its two products: the
benchmark's three constants are not identifiable separately).  One RK4 step per sample at 750 Hz,
written by hand in :class:`BoucWenTransition`; six parameters, all free.  The generator simulates
exactly this discrete model, with a small random force as process noise.
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
    check_settings,
    check_variances,
    checked_params,
    measurement_noise,
    multisine,
    noise_params,
    process_noise,
    record,
    rk4_step,
    scalar_parameters,
    spawn_streams,
)

__all__ = [
    "BOUC_WEN_DT",
    "BOUC_WEN_TRUE",
    "BOUC_WEN_START",
    "BOUC_WEN_RW",
    "BOUC_WEN_RV",
    "BoucWenTransition",
    "BoucWenObservation",
    "make_bouc_wen",
    "bouc_wen_model",
]

#: Sampling period, s (750 Hz, the benchmark's).
BOUC_WEN_DT: float = 1.0 / 750.0
#: True parameters (the benchmark's): ``mass`` (kg), ``damping`` (N s/m), ``stiffness`` (N/m),
#: ``A`` (N/m), ``beta`` and ``gamma`` (1/m).
BOUC_WEN_TRUE: dict[str, float] = {
    "mass": 2.0, "damping": 10.0, "stiffness": 5e4, "A": 5e4, "beta": 800.0, "gamma": -1100.0,
}
#: The physically sized start: ``mass`` x 1.3, ``damping`` x 1.5, ``stiffness`` x 0.6, ``A`` x 1.4,
#: ``beta`` x 0.5, ``gamma`` x 0.6.
BOUC_WEN_START: dict[str, float] = {
    "mass": 2.6, "damping": 15.0, "stiffness": 3e4, "A": 7e4, "beta": 400.0, "gamma": -660.0,
}
#: Process-noise variances of ``[x, x', z]`` per step: a random force of s.d. 1 N on the velocity,
#: ``(dt * 1 N / m)^2``.
BOUC_WEN_RW: tuple[float, float, float] = (0.0, (BOUC_WEN_DT * 1.0 / 2.0) ** 2, 0.0)
#: Measurement-noise variance of the displacement, m^2 (s.d. 10 um).
BOUC_WEN_RV: float = 1e-10
#: Force: random-phase multisine over this band (Hz; the benchmark's), RMS (N).
BOUC_WEN_INPUT_BAND: tuple[float, float] = (5.0, 150.0)
BOUC_WEN_INPUT_RMS: float = 50.0


class BoucWenTransition(RK4Transition):
    """One RK4 step of the Bouc-Wen oscillator (module docstring); state ``[x, x', z]``.

    Parameters
    ----------
    mass, damping, stiffness, A, beta, gamma : float
        Initial values (default: the truth, :data:`BOUC_WEN_TRUE`).
    dt : float
        Step, s.
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 3
    nu = 1

    def __init__(
        self,
        mass: float = BOUC_WEN_TRUE["mass"],
        damping: float = BOUC_WEN_TRUE["damping"],
        stiffness: float = BOUC_WEN_TRUE["stiffness"],
        A: float = BOUC_WEN_TRUE["A"],
        beta: float = BOUC_WEN_TRUE["beta"],
        gamma: float = BOUC_WEN_TRUE["gamma"],
        *,
        dt: float = BOUC_WEN_DT,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        values = {
            "mass": mass, "damping": damping, "stiffness": stiffness, "A": A, "beta": beta, "gamma": gamma,
        }
        scalar_parameters(self, values, dtype, device)
        self.dt = float(dt)

    def rates(self, x: Tensor, u: Tensor) -> Tensor:
        """``[x', x'', z']`` at ``x`` ``(..., 3)`` and ``u`` ``(..., 1)``."""
        pos, vel, z = x[..., 0], x[..., 1], x[..., 2]
        acc = (u[..., 0] - self.damping * vel - self.stiffness * pos - z) / self.mass
        dz = self.A * vel - self.beta * torch.abs(vel) * z - self.gamma * vel * torch.abs(z)
        return torch.stack([vel, acc, dz], dim=-1)


class BoucWenObservation(nn.Module):
    """``y = x``: the measured displacement (no parameters)."""

    nx = 3
    ny = 1

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., :1]


def bouc_wen_model(
    params: dict[str, float] | None = None, *, dtype: torch.dtype = torch.float64, device=None
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at ``params`` (default: the truth; e.g. :data:`BOUC_WEN_START`)."""
    p = checked_params(params, BOUC_WEN_TRUE)
    return BoucWenTransition(**p, dtype=dtype, device=device), BoucWenObservation()


def _rates(x: np.ndarray, u: float, p: dict[str, float]) -> np.ndarray:
    pos, vel, z = x
    acc = (u - p["damping"] * vel - p["stiffness"] * pos - z) / p["mass"]
    dz = p["A"] * vel - p["beta"] * abs(vel) * z - p["gamma"] * vel * abs(z)
    return np.array([vel, acc, dz])


def _simulate(rng, n, p, Rw, Rv, rms):
    u = multisine(rng, n, BOUC_WEN_DT, BOUC_WEN_INPUT_BAND, rms)
    w = process_noise(rng, n, Rw)
    x = np.zeros((n, 3))
    for k in range(n - 1):
        x[k + 1] = rk4_step(_rates, x[k], u[k], p, BOUC_WEN_DT) + w[k]
    y_true = x[:, :1].copy()
    return u, x, y_true, y_true + measurement_noise(rng, n, Rv)


def make_bouc_wen(
    n_samples: int = 3000,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 3000,
    Rw: Any = BOUC_WEN_RW,
    Rv: Any = BOUC_WEN_RV,
    input_rms: float = BOUC_WEN_INPUT_RMS,
    params: dict[str, float] | None = None,
) -> PlantData:
    """The Bouc-Wen oscillator driven by a random-phase multisine force, displacement measured.

    Both records start at rest (``x0_guess = [0, 0, 0]``, the truth); the multisine (one period per
    record, 5-150 Hz, 50 N RMS as in the benchmark) has a new phase realisation for the validation
    record.  Gross outliers: ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations
    of the clean displacement.

    Parameters
    ----------
    n_samples : int
        Training record length (default 3,000 samples, 4 s).
    outlier_fraction : float in [0, 1)
    random_state : int, Generator or None
    n_validation : int
    Rw : 3 floats
        Process-noise variances of ``[x, x', z]`` per step (default :data:`BOUC_WEN_RW`).
    Rv : float
        Measurement-noise variance, m^2 (default :data:`BOUC_WEN_RV`).
    input_rms : float
        RMS of the force, N.
    params : dict, optional
        True parameters (default :data:`BOUC_WEN_TRUE`).

    Returns
    -------
    PlantData
        ``name="bouc_wen"``; ``u (N, 1)`` (N), ``x (N, 3)`` (m, m/s, N), ``y (N, 1)`` (m).
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 3)
    Rv_v = check_variances(Rv, "Rv", 1)
    p = checked_params(params, BOUC_WEN_TRUE)
    rms = float(input_rms)
    if not (math.isfinite(rms) and rms >= 0):
        raise ValueError(f"input_rms must be a finite non-negative number, got {input_rms!r}")
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {**p, **noise_params(Rw_v, Rv_v), "input_rms": rms, "input_band": list(BOUC_WEN_INPUT_BAND)}
    u, x, y_true, y_clean = _simulate(rng_val, n_val, p, Rw_v, Rv_v, rms)
    validation = record(
        name="bouc_wen", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=BOUC_WEN_DT,
        x0_guess=np.zeros(3),
    )
    u, x, y_true, y_clean = _simulate(rng_train, n, p, Rw_v, Rv_v, rms)
    return record(
        name="bouc_wen", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=BOUC_WEN_DT,
        x0_guess=np.zeros(3), outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )
