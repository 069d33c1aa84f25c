"""A damped pendulum driven by a torque, simulated in continuous time and sampled every ``Ts``.

``d angle/dt = omega``, ``d omega/dt = -w2 sin(angle) - c omega + b u``: ``w2 = g / l`` (1/s²),
``c`` the damping (1/s), ``b`` the input gain.  The input is held over each sample (zero-order
hold) and the ODE is integrated exactly (``scipy.integrate.solve_ivp``, DOP853, ``rtol=1e-10``); an
unmeasured random torque adds ``N(0, process_noise)`` to the angular velocity at each sample.  The
angle is measured with Gaussian noise and glitches.  The example of
:class:`~torch_nssm.ContinuousTimeTransition` (README, "Continuous-time models").
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from .. import _validation as V
from ._base import SimulatedData, _add_outliers, _to_list

__all__ = ["make_continuous_pendulum", "CT_PENDULUM_PARAMS", "CT_PENDULUM_TS"]

#: True physical parameters of :func:`make_continuous_pendulum`.
CT_PENDULUM_PARAMS = {"w2": 4.0, "c": 0.3, "b": 2.0}
#: Sample time (s).
CT_PENDULUM_TS = 0.05


def make_continuous_pendulum(
    n_samples: int = 300,
    *,
    Ts: float = CT_PENDULUM_TS,
    w2: float = CT_PENDULUM_PARAMS["w2"],
    c: float = CT_PENDULUM_PARAMS["c"],
    b: float = CT_PENDULUM_PARAMS["b"],
    input_amplitude: float = 1.5,
    hold: int = 10,
    process_noise: float = 1e-3,
    noise_std: float = 0.02,
    outlier_fraction: float = 0.025,
    outlier_range: tuple[float, float] = (0.5, 1.0),
    random_state: int | None = 0,
) -> SimulatedData:
    """Simulate the pendulum from rest; ``y`` is the measured angle (rad).

    Parameters
    ----------
    n_samples : int, default=300
    Ts : float, default=0.05
        Sample time (s).
    w2, c, b : float
        Physical parameters (default :data:`CT_PENDULUM_PARAMS`).
    input_amplitude : float, default=1.5
        The input is uniform on ``[-input_amplitude, input_amplitude]``, ...
    hold : int, default=10
        ... a new value every ``hold`` samples.
    process_noise : float, default=1e-3
        Variance of the random torque's effect on the angular velocity per sample ((rad/s)²).
    noise_std : float, default=0.02
        Standard deviation of the angle sensor's noise (rad).
    outlier_fraction : float, default=0.025
        Fraction of samples with a glitch of random sign and a size in ``outlier_range`` (rad).
    outlier_range : (float, float), default=(0.5, 1.0)
    random_state : int, optional

    Returns
    -------
    SimulatedData
        ``u`` ``(N, 1)``, ``y`` ``(N, 1)``, ``x`` ``(N, 2)`` (angle, angular velocity); ``params``
        holds ``w2``, ``c``, ``b``, ``Ts``, ``Rw``, ``Rv`` and the settings.
    """
    n = V.check_count(n_samples, "n_samples", 2)
    Ts = V.check_positive(Ts, "Ts")
    hold = V.check_count(hold, "hold", 1)
    V.check_positive(process_noise, "process_noise", inclusive=True)
    V.check_positive(noise_std, "noise_std", inclusive=True)
    fraction = V.check_real(outlier_fraction, "outlier_fraction", low=0.0, high=1.0, high_open=True)
    lo, hi = V.check_pair(outlier_range, "outlier_range")
    rng = np.random.default_rng(random_state)
    u = np.repeat(rng.uniform(-input_amplitude, input_amplitude, size=n // hold + 1), hold)[:n, None]
    x = np.zeros((n, 2))
    state = np.zeros(2)
    for k in range(n):
        x[k] = state
        uk = float(u[k, 0])

        def rhs(t, s, uk=uk):
            return [s[1], -w2 * np.sin(s[0]) - c * s[1] + b * uk]

        sol = solve_ivp(rhs, (0.0, Ts), state, method="DOP853", rtol=1e-10, atol=1e-12)
        state = sol.y[:, -1] + np.array([0.0, np.sqrt(process_noise) * rng.standard_normal()])
    y_clean = x[:, :1] + noise_std * rng.standard_normal((n, 1))
    signs = rng.choice([-1.0, 1.0], size=n)
    y, mask = _add_outliers(rng, y_clean, fraction, (lo, hi))
    y = np.where(mask[:, None], y_clean + signs[:, None] * (y - y_clean), y)
    params = dict(
        w2=float(w2), c=float(c), b=float(b), Ts=float(Ts),
        Rw=_to_list(np.diag([0.0, process_noise])), Rv=[[noise_std**2]],
        x0_mean=[0.0, 0.0], input_amplitude=float(input_amplitude), hold=hold,
        outlier_fraction=fraction, outlier_range=[lo, hi],
    )
    return SimulatedData(u=u, y=y, x=x, y_clean=y_clean, outlier_mask=mask, params=params, name="pendulum")
