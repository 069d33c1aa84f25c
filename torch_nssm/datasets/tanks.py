"""Two cascaded tanks with Torricelli outflows and an overflowing upper tank: a slow process with a
hard saturation.  Generator and the ``f`` / ``g`` a user would write.

A pump fills the upper tank (level ``h1``), which drains through a hole into the lower tank (level
``h2``), which drains out; the lower level is measured (with a sensor offset).  Forward Euler at
the sampling period, as a user writes it::

    h1+ = h1 + dt (k4 u - k1 sqrt(h1))
    overflow = max(h1+ - h1_max, 0);   h1+ <- h1+ - overflow         (the upper tank overflows)
    h2+ = h2 + dt (k2 sqrt(h1) - k3 sqrt(h2)) + k5 overflow           (part of it falls below)
    y  = h2 + y_offset

Seven physical parameters, all free (levels in cm, time in s).  The time constants of the
linearised tanks are ``2 sqrt(h) / k``: about 190 samples at mid level.  The generator simulates
exactly this discrete model, with a small process noise on both levels.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ._plants import (
    PlantData,
    check_settings,
    check_variances,
    checked_params,
    measurement_noise,
    noise_params,
    parameter_values,
    process_noise,
    record,
    scalar_parameters,
    spawn_streams,
)

__all__ = [
    "TANKS_DT",
    "TANKS_TRUE",
    "TANKS_START",
    "TANKS_RW",
    "TANKS_RV",
    "TanksTransition",
    "TanksObservation",
    "make_tanks",
    "tanks_model",
]

#: Sampling period, s.
TANKS_DT: float = 4.0
#: True parameters: outflow coefficients ``k1`` (upper), ``k2`` (upper into lower, ``k1`` times the
#: area ratio), ``k3`` (lower), cm^0.5/s; pump gain ``k4`` (cm/s per V); ``k5``, the fraction of the
#: upper tank's overflow that falls into the lower tank; ``h1_max``, the upper tank's height, cm;
#: ``y_offset``, the level sensor's offset, cm.
TANKS_TRUE: dict[str, float] = {
    "k1": 0.006, "k2": 0.0055, "k3": 0.006, "k4": 0.003, "k5": 0.5, "h1_max": 10.0, "y_offset": 0.4,
}
#: The physically sized start: ``k1`` x 1.4, ``k2`` x 0.6, ``k3`` x 1.3, ``k4`` x 0.7, ``k5`` x 0.5,
#: ``h1_max`` x 0.7, ``y_offset`` x 1.5.  More outflow and less pump lower the start's upper levels
#: about 4 times (at most 5.6 cm under 9.5 V): the start never overflows its 7 cm, so its gradient
#: does not see ``h1_max`` or ``k5``, and its lower level is about 3 times too low.
TANKS_START: dict[str, float] = {
    "k1": 0.0084, "k2": 0.0033, "k3": 0.0078, "k4": 0.0021, "k5": 0.25, "h1_max": 7.0, "y_offset": 0.6,
}
#: Process-noise variances of ``[h1, h2]`` per step, cm^2.
TANKS_RW: tuple[float, float] = (2.5e-5, 2.5e-5)
#: Measurement-noise variance of the lower level, cm^2 (s.d. 0.02 cm).
TANKS_RV: float = 4e-4
#: Pump voltage: levels drawn alternately from a low band (the upper tank settles below its top)
#: and a high band (it fills to ``h1_max`` and overflows: above about 6.3 V at rest), each held for
#: a number of samples drawn uniformly in ``TANKS_HOLD``.  The alternation makes every record,
#: training included, see the overflow: a model fitted on a record that never overflows can only
#: guess ``h1_max`` and ``k5``, and its validation would score extrapolation luck.
TANKS_INPUT_RANGE: tuple[float, float] = (2.0, 9.5)
TANKS_LOW_BAND: tuple[float, float] = (2.0, 6.0)
TANKS_HIGH_BAND: tuple[float, float] = (7.5, 9.5)
TANKS_HOLD: tuple[int, int] = (100, 250)
#: Pump voltage before each record starts: the tanks start at its equilibrium (training, validation).
TANKS_PRE_INPUT: tuple[float, float] = (4.0, 6.0)
#: Lower bound of the level under the square roots (the gradient of ``sqrt`` at 0 is infinite).
TANKS_LEVEL_FLOOR: float = 1e-6


class TanksTransition(nn.Module):
    """One forward-Euler step of the cascaded tanks (see the module docstring); state ``[h1, h2]``.

    Parameters
    ----------
    k1, k2, k3, k4, k5, h1_max : float
        Initial values (default: the truth, :data:`TANKS_TRUE`).
    dt : float
        Step, s.
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    nu = 1

    def __init__(
        self,
        k1: float = TANKS_TRUE["k1"],
        k2: float = TANKS_TRUE["k2"],
        k3: float = TANKS_TRUE["k3"],
        k4: float = TANKS_TRUE["k4"],
        k5: float = TANKS_TRUE["k5"],
        h1_max: float = TANKS_TRUE["h1_max"],
        *,
        dt: float = TANKS_DT,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        values = {"k1": k1, "k2": k2, "k3": k3, "k4": k4, "k5": k5, "h1_max": h1_max}
        scalar_parameters(self, values, dtype, device)
        self.dt = float(dt)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        dt = self.dt
        s1 = torch.sqrt(torch.clamp(x[..., 0], min=TANKS_LEVEL_FLOOR))
        s2 = torch.sqrt(torch.clamp(x[..., 1], min=TANKS_LEVEL_FLOOR))
        h1 = x[..., 0] + dt * (self.k4 * u[..., 0] - self.k1 * s1)
        overflow = torch.relu(h1 - self.h1_max)
        h1 = h1 - overflow
        h2 = x[..., 1] + dt * (self.k2 * s1 - self.k3 * s2) + self.k5 * overflow
        return torch.stack([h1, h2], dim=-1)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in parameter_values(self).items()) + f", dt={self.dt:g}"


class TanksObservation(nn.Module):
    """``y = h2 + y_offset``: the lower level, measured with an offset.

    Parameters
    ----------
    y_offset : float
        Initial value (default: the truth).
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 2
    ny = 1

    def __init__(
        self, y_offset: float = TANKS_TRUE["y_offset"], *, dtype: torch.dtype = torch.float64, device=None
    ) -> None:
        super().__init__()
        scalar_parameters(self, {"y_offset": y_offset}, dtype, device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., 1:2] + self.y_offset

    def extra_repr(self) -> str:
        return f"y_offset={float(self.y_offset.detach()):.6g}"


def tanks_model(
    params: dict[str, float] | None = None, *, dtype: torch.dtype = torch.float64, device=None
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at ``params`` (default: the truth; e.g. :data:`TANKS_START`)."""
    p = checked_params(params, TANKS_TRUE)
    offset = p.pop("y_offset")
    g = TanksObservation(offset, dtype=dtype, device=device)
    return TanksTransition(**p, dtype=dtype, device=device), g


def _step(x: np.ndarray, u: float, p: dict[str, float], dt: float) -> np.ndarray:
    """The step of :class:`TanksTransition`, in the same order of operations."""
    s1 = np.sqrt(max(x[0], TANKS_LEVEL_FLOOR))
    s2 = np.sqrt(max(x[1], TANKS_LEVEL_FLOOR))
    h1 = x[0] + dt * (p["k4"] * u - p["k1"] * s1)
    overflow = max(h1 - p["h1_max"], 0.0)
    h1 = h1 - overflow
    h2 = x[1] + dt * (p["k2"] * s1 - p["k3"] * s2) + p["k5"] * overflow
    return np.array([h1, h2])


def tanks_equilibrium(u: float, params: dict[str, float] | None = None) -> np.ndarray:
    """The levels ``[h1, h2]`` at rest under a constant pump voltage ``u`` (below the overflow)."""
    p = checked_params(params, TANKS_TRUE)
    h1 = min((p["k4"] * u / p["k1"]) ** 2, p["h1_max"])
    return np.array([h1, (p["k2"] * np.sqrt(h1) / p["k3"]) ** 2])


def _pump_voltage(rng: np.random.Generator, n: int) -> np.ndarray:
    u = np.empty(n)
    k, high = 0, bool(rng.integers(2))
    while k < n:
        hold = int(rng.integers(TANKS_HOLD[0], TANKS_HOLD[1] + 1))
        u[k : k + hold] = rng.uniform(*(TANKS_HIGH_BAND if high else TANKS_LOW_BAND))
        k, high = k + hold, not high
    return u


def _simulate(rng, n, u_pre, p, Rw, Rv):
    u = _pump_voltage(rng, n)
    w = process_noise(rng, n, Rw)
    x = np.empty((n, 2))
    x[0] = tanks_equilibrium(u_pre, p)
    for k in range(n - 1):
        x[k + 1] = _step(x[k], u[k], p, TANKS_DT) + w[k]
    y_true = x[:, 1:2] + p["y_offset"]
    return u, x, y_true, y_true + measurement_noise(rng, n, Rv)


def make_tanks(
    n_samples: int = 1024,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 1024,
    Rw: Any = TANKS_RW,
    Rv: Any = TANKS_RV,
    params: dict[str, float] | None = None,
) -> PlantData:
    """Two cascaded tanks driven by a multilevel pump voltage, lower level measured.

    Each record starts at the equilibrium of a pump voltage applied before it
    (:data:`TANKS_PRE_INPUT`: 4 V for training, 6 V for validation); a user does not know the upper
    level, so ``x0_guess`` is the median of the first 10 measured outputs for both levels.  The
    pump voltage steps alternately to a low and a high level held for 100-250 samples; at the high
    levels the upper tank fills to ``h1_max`` and overflows, in training as in validation.  Gross
    outliers: ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations of the clean level.

    Parameters
    ----------
    n_samples : int
        Training record length (default 1,024 samples, 68 min).
    outlier_fraction : float in [0, 1)
    random_state : int, Generator or None
    n_validation : int
    Rw : pair of float
        Process-noise variances of ``[h1, h2]`` per step, cm^2 (default :data:`TANKS_RW`).
    Rv : float
        Measurement-noise variance, cm^2 (default :data:`TANKS_RV`).
    params : dict, optional
        True parameters (default :data:`TANKS_TRUE`).

    Returns
    -------
    PlantData
        ``name="tanks"``; ``u (N, 1)`` (V), ``x (N, 2)`` (cm), ``y (N, 1)`` (cm).
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 2)
    Rv_v = check_variances(Rv, "Rv", 1)
    p = checked_params(params, TANKS_TRUE)
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {
        **p, **noise_params(Rw_v, Rv_v), "input_range": list(TANKS_INPUT_RANGE), "hold": list(TANKS_HOLD),
    }
    u, x, y_true, y_clean = _simulate(rng_val, n_val, TANKS_PRE_INPUT[1], p, Rw_v, Rv_v)
    validation = record(
        name="tanks", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=TANKS_DT,
        x0_guess=_level_guess,
    )
    u, x, y_true, y_clean = _simulate(rng_train, n, TANKS_PRE_INPUT[0], p, Rw_v, Rv_v)
    return record(
        name="tanks", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=TANKS_DT,
        x0_guess=_level_guess, outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )


def _level_guess(y: np.ndarray) -> np.ndarray:
    """A user's first state: both levels at the median of the first 10 measured outputs."""
    return np.full(2, float(np.median(y[:10])))
