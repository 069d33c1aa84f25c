"""A 2-state, 2-output linear system whose first sensor glitches: the example of the per-output
Student-t noise (docs/noise_models.md).

``x_{k+1} = A x_k + B u_k + w``, ``y_k = x_k + v`` with Gaussian ``w ~ N(0, 0.05 I)`` and
``v ~ N(0, 0.1 I)``; a fraction of the samples of output 1 get a glitch of random sign and size in
``glitch_range``, output 2 stays clean.
"""

from __future__ import annotations

import math

import numpy as np

from ._base import SimulatedData

__all__ = ["make_two_sensor_example", "TWO_SENSOR_A", "TWO_SENSOR_B", "TWO_SENSOR_RW", "TWO_SENSOR_RV"]

TWO_SENSOR_A = np.array([[0.8, 0.2], [0.0, 0.6]])
TWO_SENSOR_B = np.array([[1.0], [0.5]])
#: Process- and measurement-noise variances (each component).
TWO_SENSOR_RW, TWO_SENSOR_RV = 0.05, 0.1


def make_two_sensor_example(
    n_samples: int = 400,
    *,
    glitch_fraction: float = 0.1,
    glitch_range: tuple[float, float] = (4.0, 8.0),
    random_state: int | None = 0,
) -> SimulatedData:
    """Simulate the two-sensor system; ``outlier_mask`` marks the samples whose output 1 glitched.

    Parameters
    ----------
    n_samples : int, default=400
    glitch_fraction : float, default=0.1
        Expected fraction of samples with a glitch in output 1.
    glitch_range : (float, float), default=(4.0, 8.0)
        Range of the glitches' size (their sign is random).
    random_state : int, optional

    Returns
    -------
    SimulatedData
    """
    rng = np.random.default_rng(random_state)
    n = int(n_samples)
    u = rng.normal(size=(n, 1))
    x = np.zeros((n, 2))
    sw = math.sqrt(TWO_SENSOR_RW)
    for k in range(n - 1):
        x[k + 1] = TWO_SENSOR_A @ x[k] + TWO_SENSOR_B @ u[k] + rng.normal(scale=sw, size=2)
    y = x + rng.normal(scale=math.sqrt(TWO_SENSOR_RV), size=(n, 2))
    y_clean = y.copy()
    glitch = rng.random(n) < glitch_fraction
    y[glitch, 0] += rng.choice([-1.0, 1.0], glitch.sum()) * rng.uniform(*glitch_range, glitch.sum())
    params = dict(
        A=TWO_SENSOR_A.tolist(),
        B=TWO_SENSOR_B.tolist(),
        Rw=(TWO_SENSOR_RW * np.eye(2)).tolist(),
        Rv=(TWO_SENSOR_RV * np.eye(2)).tolist(),
        glitch_fraction=glitch_fraction,
        glitch_range=list(glitch_range),
    )
    return SimulatedData(u, y, x, y_clean, glitch, params, name="two_sensor_example")
