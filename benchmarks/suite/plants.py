"""The plants of the suite: how to make each record, its user model, its start, what it tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch_nssm.datasets import (
    AXIS_START,
    AXIS_TRUE,
    BOUC_WEN_START,
    BOUC_WEN_TRUE,
    OSCILLATOR_START,
    OSCILLATOR_TRUE,
    PENDULUM_START,
    PENDULUM_TRUE,
    TANKS_START,
    TANKS_TRUE,
    WH_START,
    WH_TRUE,
    axis_model,
    bouc_wen_model,
    make_axis,
    make_bouc_wen,
    make_oscillator,
    make_pendulum,
    make_tanks,
    make_wiener_hammerstein,
    oscillator_model,
    pendulum_model,
    tanks_model,
    wiener_hammerstein_model,
)

__all__ = ["Plant", "PLANTS", "PLANT_NAMES", "SILVERBOX"]


@dataclass(frozen=True)
class Plant:
    """One plant of the suite.

    Attributes
    ----------
    name : str
    make : callable
        ``make(n_samples, outlier_fraction, random_state, n_validation=...) -> PlantData``.
    model : callable
        ``model(params) -> (f, g)``: the user's modules at the given physical parameters.
    true, start : dict
        True parameters and the physically sized start (every parameter 30-50 % off).
    n_train, n_validation : int
        Record lengths of the full run; ``quick_train``, ``quick_validation`` those of ``--quick``.
    unit : str
        Unit of the output (of the RMSE).
    tests : str
        What the plant is there to test.
    """

    name: str
    make: Callable
    model: Callable
    true: dict
    start: dict
    n_train: int
    n_validation: int
    quick_train: int
    quick_validation: int
    unit: str
    tests: str


PLANTS: dict[str, Plant] = {
    p.name: p
    for p in (
        Plant(
            "pendulum", make_pendulum, pendulum_model, PENDULUM_TRUE, PENDULUM_START,
            n_train=2000, n_validation=2000, quick_train=300, quick_validation=300, unit="rad",
            tests="a user's first nonlinear model: RK4 written by hand in f, 3 physical parameters, small "
            "process noise, swings far into sin(); default fit against OE in time and accuracy",
        ),
        Plant(
            "tanks", make_tanks, tanks_model, TANKS_TRUE, TANKS_START,
            n_train=1024, n_validation=1024, quick_train=300, quick_validation=300, unit="cm",
            tests="a slow process: time constants of ~190 samples (the first state matters over the whole "
            "record), a hard saturation (the upper tank overflows), square roots, 7 parameters",
        ),
        Plant(
            "axis", make_axis, axis_model, AXIS_TRUE, AXIS_START,
            n_train=25_000, n_validation=10_000, quick_train=2000, quick_validation=1000, unit="m",
            tests="a long record (25,000 samples at 1 ms) in closed loop (PID), an integrator, Coulomb "
            "friction (tanh), encoder quantisation as the only measurement noise (s.d. 1.4 um)",
        ),
        Plant(
            "oscillator", make_oscillator, oscillator_model, OSCILLATOR_TRUE, OSCILLATOR_START,
            n_train=3000, n_validation=3000, quick_train=400, quick_validation=400, unit="mm",
            tests="fast, lightly damped dynamics (3 % damping, 6-10 samples per period, a hardening "
            "spring): a simulation-error cost with many local minima in the frequency",
        ),
        Plant(
            "wiener_hammerstein", make_wiener_hammerstein, wiener_hammerstein_model, WH_TRUE, WH_START,
            n_train=3000, n_validation=3000, quick_train=400, quick_validation=400, unit="-",
            tests="a block-structured model: 4 states, 10 non-physical parameters (two filters' "
            "coefficients and a saturation), unmeasured internal signal",
        ),
        Plant(
            "bouc_wen", make_bouc_wen, bouc_wen_model, BOUC_WEN_TRUE, BOUC_WEN_START,
            n_train=3000, n_validation=3000, quick_train=400, quick_validation=400, unit="m",
            tests="hysteresis: an unmeasured third state with a non-smooth rate, SI units (states from "
            "1e-3 m to 1e2 N, parameters from 2 to 5e4)",
        ),
    )
}

PLANT_NAMES: tuple[str, ...] = tuple(PLANTS) + ("silverbox",)

#: What the Silverbox row tests (real data, ``examples/silverbox``).
SILVERBOX = (
    "real data (the Silverbox electronic Duffing oscillator): the study's grey box, linear in its 7 "
    "parameters, 3,000 training samples, scored on the arrow (extrapolation)"
)
