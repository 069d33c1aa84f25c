"""A Wiener-Hammerstein system (filter - static nonlinearity - filter): generator and ``f`` / ``g``.

Two second-order discrete-time filters ``G(q) = (b1 q + b2) / (q^2 + a1 q + a2)`` in observer
canonical form around the saturating nonlinearity ``w = tanh(z + offset) + slope z``::

    x1+ = [[-a11, 1], [-a12, 0]] x1 + [b11, b12] u                  z = x1[0]
    x2+ = [[-a21, 1], [-a22, 0]] x2 + [b21, b22] w(z)               y = x2[0]

State ``[x1, x2]`` (4 states), dimensionless, one sample per time unit.  The fixed shape of
``tanh`` (no input or output scale of its own) leaves no gain to trade between the blocks, so all
ten parameters are identifiable.  ``f`` is linear in the filters' coefficients and nonlinear in
``offset``.  The generator simulates exactly this model with a small process noise on every state.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ._plants import (
    PlantData,
    band_noise,
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
    "WH_TRUE",
    "WH_START",
    "WH_RW",
    "WH_RV",
    "WienerHammersteinTransition",
    "WienerHammersteinObservation",
    "make_wiener_hammerstein",
    "wiener_hammerstein_model",
]

#: True parameters.  First filter: poles 0.9 +- 0.2j, DC gain 3; second filter: poles 0.6 +- 0.5j,
#: zero at 0.5, DC gain 0.49; the nonlinearity ``tanh(z + 0.3) + 0.1 z``.
WH_TRUE: dict[str, float] = {
    "a11": -1.8, "a12": 0.85, "b11": 0.1, "b12": 0.05,
    "offset": 0.3, "slope": 0.1,
    "a21": -1.2, "a22": 0.61, "b21": 0.4, "b22": -0.2,
}
#: The physically sized start: ``a11`` x 0.7, ``a12`` x 0.6, ``b11`` x 1.4, ``b12`` x 1.5,
#: ``offset`` x 1.5, ``slope`` x 0.5, ``a21`` x 0.7, ``a22`` x 1.3, ``b21`` x 0.6, ``b22`` x 1.4
#: (directions chosen so that both filters stay stable: poles 0.63 +- 0.34j and 0.42 +- 0.79j).
WH_START: dict[str, float] = {
    "a11": -1.26, "a12": 0.51, "b11": 0.14, "b12": 0.075,
    "offset": 0.45, "slope": 0.05,
    "a21": -0.84, "a22": 0.793, "b21": 0.24, "b22": -0.28,
}
#: Process-noise variances of the four states per step.
WH_RW: tuple[float, ...] = (1e-5, 1e-5, 1e-5, 1e-5)
#: Measurement-noise variance of ``y`` (s.d. 0.005, about 1 % of the output's s.d.).
WH_RV: float = 2.5e-5
#: Input: Gaussian noise band-limited to this band (cycles per sample), s.d.
WH_INPUT_BAND: tuple[float, float] = (0.0, 0.2)
WH_INPUT_STD: float = 0.7


def _filter_names(i: int) -> tuple[str, str, str, str]:
    return f"a{i}1", f"a{i}2", f"b{i}1", f"b{i}2"


class WienerHammersteinTransition(nn.Module):
    """The two filters and the nonlinearity between them (module docstring); state ``(..., 4)``.

    Parameters
    ----------
    a11, a12, b11, b12, offset, slope, a21, a22, b21, b22 : float
        Initial values (default: the truth, :data:`WH_TRUE`).
    dtype : torch.dtype
    device : torch.device or str, optional
    """

    nx = 4
    nu = 1

    def __init__(
        self,
        a11: float = WH_TRUE["a11"],
        a12: float = WH_TRUE["a12"],
        b11: float = WH_TRUE["b11"],
        b12: float = WH_TRUE["b12"],
        offset: float = WH_TRUE["offset"],
        slope: float = WH_TRUE["slope"],
        a21: float = WH_TRUE["a21"],
        a22: float = WH_TRUE["a22"],
        b21: float = WH_TRUE["b21"],
        b22: float = WH_TRUE["b22"],
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        values = {
            "a11": a11, "a12": a12, "b11": b11, "b12": b12, "offset": offset, "slope": slope,
            "a21": a21, "a22": a22, "b21": b21, "b22": b22,
        }
        scalar_parameters(self, values, dtype, device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        z = x[..., 0]
        w = torch.tanh(z + self.offset) + self.slope * z
        s = x[..., 2]
        return torch.stack(
            [
                -self.a11 * z + x[..., 1] + self.b11 * u[..., 0],
                -self.a12 * z + self.b12 * u[..., 0],
                -self.a21 * s + x[..., 3] + self.b21 * w,
                -self.a22 * s + self.b22 * w,
            ],
            dim=-1,
        )

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in parameter_values(self).items())


class WienerHammersteinObservation(nn.Module):
    """``y = x2[0]``: the second filter's output (no parameters)."""

    nx = 4
    ny = 1

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x[..., 2:3]


def wiener_hammerstein_model(
    params: dict[str, float] | None = None, *, dtype: torch.dtype = torch.float64, device=None
) -> tuple[nn.Module, nn.Module]:
    """``(f, g)`` at ``params`` (default: the truth; e.g. :data:`WH_START`)."""
    p = checked_params(params, WH_TRUE)
    return WienerHammersteinTransition(**p, dtype=dtype, device=device), WienerHammersteinObservation()


def _step(x: np.ndarray, u: float, p: dict[str, float]) -> np.ndarray:
    """The step of :class:`WienerHammersteinTransition`, in the same order of operations."""
    z, s = x[0], x[2]
    w = math.tanh(z + p["offset"]) + p["slope"] * z
    return np.array(
        [
            -p["a11"] * z + x[1] + p["b11"] * u,
            -p["a12"] * z + p["b12"] * u,
            -p["a21"] * s + x[3] + p["b21"] * w,
            -p["a22"] * s + p["b22"] * w,
        ]
    )


def wiener_hammerstein_equilibrium(params: dict[str, float] | None = None) -> np.ndarray:
    """The rest state under ``u = 0``: the first filter at 0, the second at the response to the
    constant ``w = tanh(offset)``."""
    p = checked_params(params, WH_TRUE)
    w = math.tanh(p["offset"])
    s = (p["b21"] + p["b22"]) * w / (1.0 + p["a21"] + p["a22"])
    return np.array([0.0, 0.0, s, -p["a22"] * s + p["b22"] * w])


def _simulate(rng, n, p, Rw, Rv, std):
    u = band_noise(rng, n, 1.0, WH_INPUT_BAND, std)
    w = process_noise(rng, n, Rw)
    x = np.empty((n, 4))
    x[0] = wiener_hammerstein_equilibrium(p)
    for k in range(n - 1):
        x[k + 1] = _step(x[k], u[k], p) + w[k]
    y_true = x[:, 2:3].copy()
    return u, x, y_true, y_true + measurement_noise(rng, n, Rv)


def make_wiener_hammerstein(
    n_samples: int = 3000,
    outlier_fraction: float = 0.0,
    random_state: int | np.random.Generator | None = None,
    *,
    n_validation: int = 3000,
    Rw: Any = WH_RW,
    Rv: Any = WH_RV,
    input_std: float = WH_INPUT_STD,
    params: dict[str, float] | None = None,
) -> PlantData:
    """A Wiener-Hammerstein system driven by band-limited Gaussian noise.

    Both records start at rest under ``u = 0`` (:func:`wiener_hammerstein_equilibrium`, which a user
    does not know: ``x0_guess`` is zero).  With the default input the nonlinearity's input ``z``
    has a standard deviation of about 1.3, well into the saturation.  Gross outliers:
    ``round(outlier_fraction * N)`` samples get +-(2-6) standard deviations of the clean output.

    Parameters
    ----------
    n_samples : int
        Training record length (default 3,000).
    outlier_fraction : float in [0, 1)
    random_state : int, Generator or None
    n_validation : int
    Rw : float or 4 floats
        Process-noise variances per step (default :data:`WH_RW`).
    Rv : float
        Measurement-noise variance (default :data:`WH_RV`).
    input_std : float
        Standard deviation of the input.
    params : dict, optional
        True parameters (default :data:`WH_TRUE`).

    Returns
    -------
    PlantData
        ``name="wiener_hammerstein"``; ``u (N, 1)``, ``x (N, 4)``, ``y (N, 1)``; ``dt = 1``.
    """
    n, n_val, fraction = check_settings(n_samples, n_validation, outlier_fraction)
    Rw_v = check_variances(Rw, "Rw", 4)
    Rv_v = check_variances(Rv, "Rv", 1)
    p = checked_params(params, WH_TRUE)
    std = float(input_std)
    if not (math.isfinite(std) and std >= 0):
        raise ValueError(f"input_std must be a finite non-negative number, got {input_std!r}")
    rng_train, rng_val, rng_out = spawn_streams(random_state)
    settings = {**p, **noise_params(Rw_v, Rv_v), "input_std": std, "input_band": list(WH_INPUT_BAND)}
    u, x, y_true, y_clean = _simulate(rng_val, n_val, p, Rw_v, Rv_v, std)
    validation = record(
        name="wiener_hammerstein", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=1.0,
        x0_guess=np.zeros(4),
    )
    u, x, y_true, y_clean = _simulate(rng_train, n, p, Rw_v, Rv_v, std)
    return record(
        name="wiener_hammerstein", u=u, x=x, y_true=y_true, y_clean=y_clean, params=settings, dt=1.0,
        x0_guess=np.zeros(4), outlier_fraction=fraction, outlier_rng=rng_out, validation=validation,
    )
