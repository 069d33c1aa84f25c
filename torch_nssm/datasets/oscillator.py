"""A lightly damped hardening (Duffing) oscillator with fast dynamics: generator and ``f`` / ``g``.

``x'' + 2 zeta omega0 x' + omega0^2 x + alpha x^3 = gain u``, position ``x`` in mm measured, force
``u`` in N.  The natural frequency (15 Hz) is sampled 10 times per period at 150 Hz (fewer at large
amplitudes, where the spring hardens), with a damping ratio of 3 %.  One RK4 step per sample,
written by hand in :class:`OscillatorTransition`; the model is nonlinear in its four parameters.
The generator simulates exactly this discrete model with a small random force as process noise.
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
    "OSCILLATOR_DT",
    "OSCILLATOR_TRUE",
    "OSCILLATOR_START",
    "OSCILLATOR_RW",
    "OSCILLATOR_RV",
    "OscillatorTransition",
    "OscillatorObservation",
    "make_oscillator",
    "oscillator_model",
]

#: Sampling period, s (150 Hz).
OSCILLATOR_DT: float = 1.0 / 150.0
#: True parameters: ``omega0`` (rad/s; 15 Hz), ``zeta`` (damping ratio), ``alpha`` (cubic stiffness
#: per mass, 1/(mm^2 s^2): the spring is 50 % stiffer at 2 mm), ``gain`` (mm/s^2 per N: 1 / mass).
OSCILLATOR_TRUE: dict[str, float] = {
    "omega0": 2 * math.pi * 15.0, "zeta": 0.03, "alpha": 1100.0, "gain": 1000.0,
}
#: The physically sized start: ``omega0`` x 0.7, ``zeta`` x 1.5, ``alpha`` x 0.6, ``gain`` x 1.4.
OSCILLATOR_START: dict[str, float] = {
    "omega0": 0.7 * 2 * math.pi * 15.0, "zeta": 0.045, "alpha": 660.0, "gain": 1400.0,
}
#: Process-noise variances of ``[x, x']`` per step: a random force on the velocity, (mm/s)^2.
OSCILLATOR_RW: tuple[float, float] = (0.0, 0.01)
#: Measurement-noise variance of the position, mm^2 (s.d. 0.01 mm).
OSCILLATOR_RV: float = 1e-4
#: Force: random-phase multisine over this band (Hz), RMS (N).
OSCILLATOR_INPUT_BAND: tuple[float, float] = (3.0, 30.0)
OSCILLATOR_INPUT_RMS: float = 4.0


class OscillatorTransition(RK4Transition):
    """One RK4 step of the Duffing oscillator; state ``[x, x']`` (mm, mm/s), input the force (N).

    Parameters
    ----------
    omega0, zeta, alpha, gain : float
        Initial values (default: the truth, :data:`OSCILLATOR_TRUE`).
    dt : float
        Step, s.
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    nu = 1

    def __init__(
        self,
        omega0: float = OSCILLATOR_TRUE["omega0"],
        zeta: float = OSCILLATOR_TRUE["zeta"],
        alpha: float = OSCILLATOR_TRUE["alpha"],
        gain: float = OSCILLATOR_TRUE["gain"],
        *,
        dt: float = OSCILLATOR_DT,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        scalar_parameters(self, {"omega0": omega0, "zeta": zeta, "alpha": alpha, "gain": gain}, dtype, device)
        self.dt = float(dt)

    def rates(self, x: Tensor, u: Tensor) -> Tensor:
        """``[x', x'']`` at ``x`` ``(..., 2)`` and ``u`` ``(..., 1)``."""
        pos, vel = x[..., 0], x[..., 1]
        w = self.omega0
        acc = -2.0 * self.zeta * w * vel - w * w * pos - self.alpha * pos**3 + self.gain * u[..., 0]
        return torch.stack([vel, acc], dim=-1)


class OscillatorObservation(nn.Module):
    """``y = x``: the measured position (no parameters)."""

    nx = 2
    ny = 1

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., :1]


def oscillator_model(
    params: dict[str, float] | None = None, *, dtype: torch.dtype = torch.float64, device=None
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at ``params`` (default: the truth; e.g. :data:`OSCILLATOR_START`)."""
    p = checked_params(params, OSCILLATOR_TRUE)
    return OscillatorTransition(**p, dtype=dtype, device=device), OscillatorObservation()


def _rates(x: np.ndarray, u: float, p: dict[str, float]) -> np.ndarray:
    w = p["omega0"]
    acc = -2.0 * p["zeta"] * w * x[1] - w * w * x[0] - p["alpha"] * x[0] ** 3 + p["gain"] * u
    return np.array([x[1], acc])


def _simulate(rng, n, p, Rw, Rv, rms):
    u = multisine(rng, n, OSCILLATOR_DT, OSCILLATOR_INPUT_BAND, rms)
    w = process_noise(rng, n, Rw)
    x = np.zeros((n, 2))
    for k in range(n - 1):
        x[k + 1] = rk4_step(_rates, x[k], u[k], p, OSCILLATOR_DT) + w[k]
    y_true = x[:, :1].copy()
    return u, x, y_true, y_true + measurement_noise(rng, n, Rv)


def make_oscillator(
    n_samples: int = 3000,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 3000,
    Rw: Any = OSCILLATOR_RW,
    Rv: Any = OSCILLATOR_RV,
    input_rms: float = OSCILLATOR_INPUT_RMS,
    params: dict[str, float] | None = None,
) -> PlantData:
    """A lightly damped Duffing oscillator driven by a random-phase multisine, position measured.

    Both records start at rest (``x0_guess = [0, 0]``, the truth); the multisine (one period per
    record, every frequency line in :data:`OSCILLATOR_INPUT_BAND`) has a new phase realisation for
    the validation record.  With the default force the position reaches +-3-4 mm (s.d. about 1 mm),
    where the cubic term more than doubles the stiffness.  Gross outliers:
    ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations of the clean position.

    Parameters
    ----------
    n_samples : int
        Training record length (default 3,000 samples, 20 s).
    outlier_fraction : float in [0, 1)
    random_state : int, Generator or None
    n_validation : int
    Rw : pair of float
        Process-noise variances of ``[x, x']`` per step (default :data:`OSCILLATOR_RW`).
    Rv : float
        Measurement-noise variance, mm^2 (default :data:`OSCILLATOR_RV`).
    input_rms : float
        RMS of the force, N.
    params : dict, optional
        True parameters (default :data:`OSCILLATOR_TRUE`).

    Returns
    -------
    PlantData
        ``name="oscillator"``; ``u (N, 1)`` (N), ``x (N, 2)`` (mm, mm/s), ``y (N, 1)`` (mm).
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 2)
    Rv_v = check_variances(Rv, "Rv", 1)
    p = checked_params(params, OSCILLATOR_TRUE)
    rms = float(input_rms)
    if not (math.isfinite(rms) and rms >= 0):
        raise ValueError(f"input_rms must be a finite non-negative number, got {input_rms!r}")
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {**p, **noise_params(Rw_v, Rv_v), "input_rms": rms, "input_band": list(OSCILLATOR_INPUT_BAND)}
    u, x, y_true, y_clean = _simulate(rng_val, n_val, p, Rw_v, Rv_v, rms)
    validation = record(
        name="oscillator", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=OSCILLATOR_DT,
        x0_guess=np.zeros(2),
    )
    u, x, y_true, y_clean = _simulate(rng_train, n, p, Rw_v, Rv_v, rms)
    return record(
        name="oscillator", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=OSCILLATOR_DT,
        x0_guess=np.zeros(2), outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )
