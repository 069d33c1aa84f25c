"""Simulated data sets of the paper's experiments, one module per system.

Every generator draws from ``np.random.default_rng(random_state)`` and returns a frozen
:class:`SimulatedData` (time convention and outliers: :mod:`torch_nssm.datasets._base`).

* :mod:`~torch_nssm.datasets.paper` -- Section 4.1, ``x_{k+1} = a x_k + b u_k + w``,
  ``y_k = c cos(x_k) + v``: :func:`make_paper_example`, :func:`make_gopaluni_example`,
  :func:`make_huang_example`.
* :mod:`~torch_nssm.datasets.manipulator` -- Section 4.2, the two-link manipulator:
  :func:`make_manipulator` and its constants and physics.
* :mod:`~torch_nssm.datasets.two_sensors` -- a 2-output linear system whose first sensor
  glitches: :func:`make_two_sensor_example` (the per-output noise's example).
* :mod:`~torch_nssm.datasets.pendulum` -- a torque-driven pendulum simulated in continuous time:
  :func:`make_continuous_pendulum` (the continuous-time models' example).

Each module also holds its system's ready-made ``f`` / ``g`` (collected in :mod:`torch_nssm.models`).
The Silverbox loader lives with its case study in ``examples/silverbox``.
"""

from ._base import SimulatedData
from .continuous_pendulum import CT_PENDULUM_PARAMS, CT_PENDULUM_TS, make_continuous_pendulum
from .manipulator import (
    MANIPULATOR_ALPHA3,
    MANIPULATOR_ALPHA10,
    MANIPULATOR_ALPHA20,
    MANIPULATOR_D1,
    MANIPULATOR_D2,
    MANIPULATOR_DT,
    MANIPULATOR_FORCE_AMPLITUDE,
    MANIPULATOR_FORCE_OMEGA,
    MANIPULATOR_GRAVITY,
    MANIPULATOR_K1,
    MANIPULATOR_K2,
    MANIPULATOR_LENGTH,
    MANIPULATOR_MASS,
    MANIPULATOR_OUTLIER_RANGE,
    MANIPULATOR_RV,
    MANIPULATOR_RW,
    MANIPULATOR_X0_COV,
    MANIPULATOR_X0_MEAN,
    ManipulatorConstants,
    make_manipulator,
    manipulator_force,
    manipulator_transition_matrix,
)
from .paper import PAPER_X0_COV, make_gopaluni_example, make_huang_example, make_paper_example
from .two_sensors import make_two_sensor_example

__all__ = [
    "make_two_sensor_example",
    "make_continuous_pendulum",
    "CT_PENDULUM_PARAMS",
    "CT_PENDULUM_TS",
    "SimulatedData",
    "ManipulatorConstants",
    "make_paper_example",
    "make_gopaluni_example",
    "make_huang_example",
    "make_manipulator",
    "manipulator_force",
    "manipulator_transition_matrix",
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
