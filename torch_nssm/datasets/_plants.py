"""Shared parts of the suite of plants: :class:`PlantData`, inputs, gross outliers, random streams.

Each plant of the suite (:mod:`~torch_nssm.datasets.pendulum`, :mod:`~torch_nssm.datasets.tanks`,
:mod:`~torch_nssm.datasets.axis`, :mod:`~torch_nssm.datasets.oscillator`,
:mod:`~torch_nssm.datasets.wiener_hammerstein`, :mod:`~torch_nssm.datasets.bouc_wen`) has a
generator ``make_<plant>`` that returns a :class:`PlantData`: the training record (with outliers
when asked) and, in ``validation``, a second record of the same plant with another input
realisation, no outliers, and its noise-free measurement ``y_true`` to score a free run against.

Random streams: ``random_state`` seeds one ``np.random.default_rng``, which spawns three
independent streams, for the training record, the validation record and the outliers.  So the
validation record does not depend on the training record's settings, and the training record with
outliers is the clean training record plus the outliers (the clean part is the same whatever
``outlier_fraction``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor, nn

from .. import _validation as V
from ._base import SimulatedData, outlier_rows

__all__ = ["PlantData"]

#: Size of the gross outliers, in standard deviations of the clean training output.
OUTLIER_MAGNITUDE: tuple[float, float] = (2.0, 6.0)


@dataclass(frozen=True, eq=False)
class PlantData(SimulatedData):
    """A simulated record of a plant of the suite (a :class:`SimulatedData` with more).

    Attributes
    ----------
    u, y, x, y_clean, outlier_mask, params, name
        As :class:`SimulatedData`: ``y`` has the gross outliers, ``y_clean`` the measurement noise
        only, ``x`` the true states (process noise included).  ``params`` holds the true physical
        parameters (as in the plant's ``*_TRUE``), ``Rw``, ``Rv`` (nested lists), ``noise`` ("gaussian"),
        ``dt``, ``x0`` and the generator's settings.
    y_true : ndarray, shape (N, p)
        The noise-free measurement ``g(x_k, u_k)`` of the true states: what a free run is scored
        against.
    x0 : ndarray, shape (nx,)
        The record's first state ``x[0]``.
    x0_guess : ndarray, shape (nx,)
        The first state a user would give as ``x0_mean`` for this record (rest, or the measured
        level; each plant says which).
    dt : float
        Sampling period, s.
    validation : PlantData or None
        The validation record (no outliers, ``validation=None`` itself).
    """

    y_true: np.ndarray | None = None
    x0: np.ndarray | None = None
    x0_guess: np.ndarray | None = None
    dt: float = 1.0
    validation: PlantData | None = None

    def __repr__(self) -> str:
        val = None if self.validation is None else self.validation.n_samples
        return (
            f"PlantData(name={self.name!r}, n_samples={self.n_samples}, nx={self.nx}, nu={self.nu}, "
            f"ny={self.ny}, n_outliers={int(self.outlier_mask.sum())}, dt={self.dt:g}, "
            f"n_validation={val})"
        )


def spawn_streams(random_state: Any) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """Three independent generators (training record, validation record, outliers) from one seed."""
    entropy = np.random.default_rng(random_state).integers(0, 2**63, size=4)
    train, val, out = (np.random.default_rng(s) for s in np.random.SeedSequence(entropy).spawn(3))
    return train, val, out


def check_settings(n_samples: Any, n_validation: Any, outlier_fraction: Any) -> tuple[int, int, float]:
    """Validated ``(n_samples, n_validation, outlier_fraction)`` of a plant generator."""
    n = V.check_count(n_samples, "n_samples", 2)
    n_val = V.check_count(n_validation, "n_validation", 2)
    fraction = V.check_real(outlier_fraction, "outlier_fraction", low=0.0, high=1.0, high_open=True)
    return n, n_val, fraction


def check_variances(value: Any, name: str, size: int) -> np.ndarray:
    """A length-``size`` vector of non-negative variances (a scalar is repeated)."""
    a = np.asarray(value, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.full(size, float(a[0]))
    if a.shape != (size,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(f"{name} must be {size} non-negative finite variances (or one), got {value!r}")
    return a


def checked_params(params: Any, defaults: dict[str, float], name: str = "params") -> dict[str, float]:
    """``defaults`` updated with ``params`` (a dict of finite floats with known keys)."""
    out = dict(defaults)
    if params is None:
        return out
    if not isinstance(params, dict):
        raise ValueError(f"{name} must be a dict of parameter values, got {type(params).__name__}")
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(f"{name} has unknown keys {unknown}; known: {sorted(defaults)}")
    for k, v in params.items():
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"{name}[{k!r}] must be finite, got {params[k]!r}")
        out[k] = v
    return out


def multisine(
    rng: np.random.Generator, n: int, dt: float, band: tuple[float, float], rms: float
) -> np.ndarray:
    """A random-phase multisine of ``n`` samples (one period): every frequency line ``j / (n dt)``
    in ``band`` (Hz) with the same amplitude and a uniform random phase, scaled to ``rms``."""
    freqs = np.fft.rfftfreq(n, dt)
    lines = (freqs >= band[0]) & (freqs <= band[1]) & (freqs > 0)
    spectrum = np.zeros(freqs.size, dtype=complex)
    spectrum[lines] = np.exp(2j * np.pi * rng.random(int(lines.sum())))
    u = np.fft.irfft(spectrum, n)
    return rms * u / np.sqrt(np.mean(u**2))


def band_noise(
    rng: np.random.Generator, n: int, dt: float, band: tuple[float, float], std: float
) -> np.ndarray:
    """Gaussian noise filtered to ``band`` (Hz) by zeroing its spectrum outside it, scaled to ``std``."""
    spectrum = np.fft.rfft(rng.standard_normal(n))
    freqs = np.fft.rfftfreq(n, dt)
    spectrum[(freqs < band[0]) | (freqs > band[1])] = 0.0
    u = np.fft.irfft(spectrum, n)
    return std * u / np.sqrt(np.mean(u**2))


def gross_outliers(
    rng: np.random.Generator, y_clean: np.ndarray, fraction: float, scale: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Gross errors on ``round(fraction * N)`` distinct samples: ``+-a * scale`` added to every output,
    ``a ~ U[OUTLIER_MAGNITUDE]`` and a random sign per sample and output; returns ``(y, mask)``."""
    idx, mask = outlier_rows(rng, y_clean.shape[0], fraction)
    y = y_clean.copy()
    if idx.size:
        p = y.shape[1]
        lo, hi = OUTLIER_MAGNITUDE
        sign = rng.choice([-1.0, 1.0], size=(idx.size, p))
        y[idx] += sign * rng.uniform(lo, hi, size=(idx.size, p)) * np.asarray(scale).reshape(1, p)
    return y, mask


def process_noise(rng: np.random.Generator, n: int, Rw: np.ndarray) -> np.ndarray:
    """``n`` draws of ``N(0, diag(Rw))``, shape ``(n, nx)``."""
    return rng.standard_normal((n, Rw.size)) * np.sqrt(Rw)


def measurement_noise(rng: np.random.Generator, n: int, Rv: np.ndarray) -> np.ndarray:
    """``n`` draws of ``N(0, diag(Rv))``, shape ``(n, p)``."""
    return rng.standard_normal((n, Rv.size)) * np.sqrt(Rv)


def record(
    *,
    name: str,
    u: np.ndarray,
    x: np.ndarray,
    y_true: np.ndarray,
    y_clean: np.ndarray,
    params: dict[str, Any],
    dt: float,
    x0_guess: np.ndarray | Callable[[np.ndarray], np.ndarray],
    outlier_fraction: float = 0.0,
    outlier_rng: np.random.Generator | None = None,
    validation: PlantData | None = None,
) -> PlantData:
    """Assemble a :class:`PlantData` (gross outliers sized by the clean output's standard deviation;
    a callable ``x0_guess`` gets the measured outputs, outliers included)."""
    u = np.asarray(u, dtype=np.float64).reshape(len(x), -1)
    y_true = np.asarray(y_true, dtype=np.float64).reshape(len(x), -1)
    y_clean = np.asarray(y_clean, dtype=np.float64).reshape(len(x), -1)
    if outlier_fraction > 0.0:
        y, mask = gross_outliers(outlier_rng, y_clean, outlier_fraction, y_clean.std(axis=0))
    else:
        y, mask = y_clean.copy(), np.zeros(len(x), dtype=bool)
    if callable(x0_guess):
        x0_guess = x0_guess(y)
    params = dict(params)
    params.update(
        dt=float(dt), x0=np.asarray(x[0], dtype=np.float64).tolist(),
        outlier_fraction=float(outlier_fraction), n_outliers=int(mask.sum()),
        outlier_magnitude=list(OUTLIER_MAGNITUDE),
    )
    return PlantData(
        u=u, y=y, x=np.asarray(x, dtype=np.float64), y_clean=y_clean, outlier_mask=mask, params=params,
        name=name, y_true=y_true, x0=np.array(x[0], dtype=np.float64),
        x0_guess=np.asarray(x0_guess, dtype=np.float64), dt=float(dt), validation=validation,
    )


def noise_params(Rw: np.ndarray, Rv: np.ndarray) -> dict[str, Any]:
    """The noise entries of ``params``: ``Rw``, ``Rv`` as nested lists (diagonal), Gaussian."""
    return {"Rw": np.diag(Rw).tolist(), "Rv": np.diag(Rv).tolist(), "noise": "gaussian"}


def scalar_parameters(module: nn.Module, values: dict[str, float], dtype: torch.dtype, device) -> None:
    """Register each ``values`` entry as a 0-dimensional ``nn.Parameter`` of ``module``."""
    for key, value in values.items():
        t = torch.as_tensor(float(value), dtype=dtype, device=device).reshape(())
        setattr(module, key, nn.Parameter(t.clone()))


def parameter_values(module: nn.Module) -> dict[str, float]:
    """The module's scalar parameters as floats (``extra_repr`` of the plants' modules)."""
    return {k: float(p.detach()) for k, p in module.named_parameters() if p.dim() == 0}


class RK4Transition(nn.Module):
    """One classical Runge-Kutta step of ``dx/dt = rates(x, u)`` over ``self.dt``, written out as a
    user writes it in ``f`` (the suite's continuous-time plants subclass it and define ``rates``)."""

    dt: float

    def rates(self, x: Tensor, u: Tensor) -> Tensor:
        raise NotImplementedError

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        h = self.dt
        k1 = self.rates(x, u)
        k2 = self.rates(x + 0.5 * h * k1, u)
        k3 = self.rates(x + 0.5 * h * k2, u)
        k4 = self.rates(x + h * k3, u)
        return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v:.6g}" for k, v in parameter_values(self).items()) + f", dt={self.dt:g}"


def rk4_step(rates, x: np.ndarray, u: float, p: dict[str, float], h: float) -> np.ndarray:
    """:class:`RK4Transition`'s step in NumPy, in the same order of operations (the generators)."""
    k1 = rates(x, u, p)
    k2 = rates(x + 0.5 * h * k1, u, p)
    k3 = rates(x + 0.5 * h * k2, u, p)
    k4 = rates(x + h * k3, u, p)
    return x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
