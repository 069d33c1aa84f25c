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

The suite of plants (``benchmarks/real_records.py`` fits them with the defaults and baselines),
each generator returning a :class:`PlantData` with its validation record, each module with the
true parameters (``*_TRUE``), a physically sized start (``*_START``, every parameter 30-50 % off)
and the ``f`` / ``g`` a user would write (``*_model(params)``):

* :mod:`~torch_nssm.datasets.pendulum` -- damped pendulum, RK4 in ``f``: :func:`make_pendulum`.
* :mod:`~torch_nssm.datasets.tanks` -- cascaded tanks with an overflow, slow: :func:`make_tanks`.
* :mod:`~torch_nssm.datasets.axis` -- positioning axis in closed loop, quantised encoder, 25,000
  samples; also linear in its parameters: :func:`make_axis`.
* :mod:`~torch_nssm.datasets.oscillator` -- lightly damped Duffing, fast: :func:`make_oscillator`.
* :mod:`~torch_nssm.datasets.wiener_hammerstein` -- filter, saturation, filter:
  :func:`make_wiener_hammerstein`.
* :mod:`~torch_nssm.datasets.bouc_wen` -- hysteretic Bouc-Wen oscillator: :func:`make_bouc_wen`.

Each module also holds its system's ready-made ``f`` / ``g`` (collected in :mod:`torch_nssm.models`).
The Silverbox loader lives with its case study in ``examples/silverbox``.
"""

from ._base import SimulatedData
from ._plants import PlantData
from .axis import (
    AXIS_START,
    AXIS_TRUE,
    AxisLinearTransition,
    AxisObservation,
    AxisTransition,
    axis_linear_parameters,
    axis_model,
    make_axis,
)
from .bouc_wen import (
    BOUC_WEN_START,
    BOUC_WEN_TRUE,
    BoucWenObservation,
    BoucWenTransition,
    bouc_wen_model,
    make_bouc_wen,
)
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
from .oscillator import (
    OSCILLATOR_START,
    OSCILLATOR_TRUE,
    OscillatorObservation,
    OscillatorTransition,
    make_oscillator,
    oscillator_model,
)
from .paper import PAPER_X0_COV, make_gopaluni_example, make_huang_example, make_paper_example
from .pendulum import (
    PENDULUM_START,
    PENDULUM_TRUE,
    PendulumObservation,
    PendulumTransition,
    make_pendulum,
    pendulum_model,
)
from .tanks import TANKS_START, TANKS_TRUE, TanksObservation, TanksTransition, make_tanks, tanks_model
from .two_sensors import make_two_sensor_example
from .wiener_hammerstein import (
    WH_START,
    WH_TRUE,
    WienerHammersteinObservation,
    WienerHammersteinTransition,
    make_wiener_hammerstein,
    wiener_hammerstein_model,
)

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
    "PlantData",
    "make_pendulum",
    "pendulum_model",
    "PendulumTransition",
    "PendulumObservation",
    "PENDULUM_TRUE",
    "PENDULUM_START",
    "make_tanks",
    "tanks_model",
    "TanksTransition",
    "TanksObservation",
    "TANKS_TRUE",
    "TANKS_START",
    "make_axis",
    "axis_model",
    "axis_linear_parameters",
    "AxisTransition",
    "AxisLinearTransition",
    "AxisObservation",
    "AXIS_TRUE",
    "AXIS_START",
    "make_oscillator",
    "oscillator_model",
    "OscillatorTransition",
    "OscillatorObservation",
    "OSCILLATOR_TRUE",
    "OSCILLATOR_START",
    "make_wiener_hammerstein",
    "wiener_hammerstein_model",
    "WienerHammersteinTransition",
    "WienerHammersteinObservation",
    "WH_TRUE",
    "WH_START",
    "make_bouc_wen",
    "bouc_wen_model",
    "BoucWenTransition",
    "BoucWenObservation",
    "BOUC_WEN_TRUE",
    "BOUC_WEN_START",
]
