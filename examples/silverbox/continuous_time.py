"""Silverbox: the Duffing oscillator in continuous time against the study's discrete one.

``PYTHONPATH=examples python -m silverbox.continuous_time`` (needs the Silverbox data, see
``examples/README.md``) fits, on 3,000 training samples of the multisine part (with 5 % injected
outliers, and clean), by the estimator with its defaults (first stage, EM; MCMC smoother, 100
particles, 15 iterations, the last 5 averaged):

* the study's discrete :class:`~silverbox.study.DuffingTransition` (7 coefficients);
* the continuous-time :class:`~silverbox.models.DuffingODE` (``m y'' + c y' + k y + k2 y^2 + k3 y^3
  = u + u0``, 6 parameters per unit mass) through :class:`~torch_nssm.ContinuousTimeTransition`
  with semi-implicit Euler (closed-form M-step) and with RK4 (gradient M-step);
* the same with RK4 fed the mean over each sample interval of the linearly interpolated input,
  ``(u_k + u_{k+1}) / 2`` (``rk4-interpolated``): the Silverbox input is a band-limited voltage,
  not held between samples, and the transition holds what it is given;

and, as the output-error baseline, each model's plain least-squares simulation-error fit
(``scipy.optimize.least_squares`` over the parameters and the first state, from the same start).
It prints the arrow's free-run RMSE (full, and without the extrapolated tail), the fit in percent
on the whole arrow (``est.compare``), the natural frequency and damping ratio of the continuous
models, and the seconds of each fit.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from dataclasses import replace

import numpy as np
import torch
from scipy.optimize import least_squares

from silverbox.data import SILVERBOX_FS
from silverbox.models import DuffingODE
from silverbox.study import (
    DuffingTransition,
    PositionObservation,
    arrow_rmse_mv,
    equation_error_init,
    prepare_silverbox,
    simulate_arrow,
)
from torch_nssm import ContinuousTimeTransition, RobustNSSMEstimator
from torch_nssm.metrics import fit_percent

#: The sample time in milliseconds (the time unit of :class:`DuffingODE`).
TS_MS = 1e3 / SILVERBOX_FS

MODELS = ("discrete", "semi-implicit", "rk4", "rk4-interpolated")


def interval_mean(u: np.ndarray) -> np.ndarray:
    """``(u_k + u_{k+1}) / 2``: the mean over ``[t_k, t_{k+1}]`` of the linearly interpolated input
    (the last sample kept)."""
    out = u.copy()
    out[:-1] = 0.5 * (u[:-1] + u[1:])
    return out


def model_data(model: str, data):
    """The data the model is fitted and scored on (``rk4-interpolated``: the interval means of the
    inputs)."""
    if model != "rk4-interpolated":
        return data
    return replace(data, u_train=interval_mean(data.u_train), u_arrow=interval_mean(data.u_arrow))


def transition(model: str, coef: dict):
    """The model's ``f`` at the equation-error start ``coef`` (:func:`equation_error_init`)."""
    if model == "discrete":
        return DuffingTransition(**coef)
    ode = DuffingODE.from_discrete(coef, TS_MS)
    if model == "semi-implicit":
        return ContinuousTimeTransition(ode, TS_MS, "semi-implicit", velocities=[1])
    return ContinuousTimeTransition(ode, TS_MS, "rk4")  # rk4 and rk4-interpolated


def estimator(model: str, data) -> RobustNSSMEstimator:
    """The estimator with its defaults and the study's starts (first_stage_comparison's settings)."""
    coef, scale = equation_error_init(data.u_train, data.y_train, nonlinear=True, return_scale=True)
    y = data.y_train[:, 0]
    v_unit = 1.0 if model == "discrete" else TS_MS  # the discrete velocity is Ts times dy/dt
    return RobustNSSMEstimator(
        transition(model, coef),
        PositionObservation(),
        x0_mean=[float(y[0]), float(y[1] - y[0]) / v_unit],
        x0_cov=[0.05, 0.5 / v_unit**2],
        Rw_init=[scale**2, scale**2 / v_unit**2],
        Rv_init=1e-3,
        n_particles=100,
        n_iter=15,
        average_last=5,
        tol=0,
        smoother="mcmc",
        random_state=0,
    )


# ---------------------------------------------------------------------- the output-error baseline
def _simulate(model: str, theta: np.ndarray, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Noise-free output of the model at ``theta`` from ``x0`` over inputs ``u`` (N,) (plain Python
    floats: a few microseconds per step)."""
    p, v = float(x0[0]), float(x0[1])
    out = np.empty(len(u))
    if model == "discrete":
        k1, d, b, k2, k3, c, e = (float(t) for t in theta)
        for i, uk in enumerate(u.tolist()):
            out[i] = p
            v = v + k1 * p + d * v + b * uk + k2 * p * p + k3 * p * p * p + c
            p = p + v + e * uk
            if abs(p) > 1e6:
                out[i + 1 :] = np.inf
                break
        return out
    b, c_m, k_m, k2_m, k3_m, a0 = (float(t) for t in theta)
    h = TS_MS

    def acc(p, v, f):
        return f - c_m * v - (k_m + (k2_m + k3_m * p) * p) * p

    for i, uk in enumerate(u.tolist()):  # rk4 and rk4-interpolated (whose u are interval means)
        out[i] = p
        f = b * uk + a0
        if model == "semi-implicit":
            v = v + h * acc(p, v, f)
            p = p + h * v
        else:
            a1 = acc(p, v, f)
            p2, v2 = p + 0.5 * h * v, v + 0.5 * h * a1
            a2 = acc(p2, v2, f)
            p3, v3 = p + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = acc(p3, v3, f)
            p4, v4 = p + h * v3, v + h * a3
            a4 = acc(p4, v4, f)
            p, v = p + h / 6 * (v + 2 * v2 + 2 * v3 + v4), v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        if abs(p) > 1e6:
            out[i + 1 :] = np.inf
            break
    return out


def output_error_fit(model: str, data) -> tuple[np.ndarray, float]:
    """Plain least-squares simulation-error fit (scipy) of the model's parameters and first state
    from the equation-error start; the parameters and the seconds."""
    coef = equation_error_init(data.u_train, data.y_train, nonlinear=True)
    start = transition(model, coef)
    module = start if model == "discrete" else start.rhs
    theta0 = module.theta().detach().numpy()
    y, u = data.y_train[:, 0], data.u_train[:, 0]
    v_unit = 1.0 if model == "discrete" else TS_MS
    z0 = np.concatenate([theta0, [y[0], (y[1] - y[0]) / v_unit]])
    n = theta0.size

    def residuals(z):
        r = _simulate(model, z[:n], z[n:], u) - y
        return np.where(np.isfinite(r), r, 1e3)

    t0 = time.perf_counter()
    sol = least_squares(residuals, z0, method="trf", x_scale="jac", max_nfev=400)
    return sol.x[:n], time.perf_counter() - t0


def scores(sim_mv: np.ndarray, data) -> dict:
    """Arrow RMSE (mV, the scored windows) and the fit in percent over the whole arrow."""
    y_mv = data.to_mv(data.y_arrow[:, 0])
    rmse = arrow_rmse_mv(sim_mv, y_mv)
    fit = float(fit_percent(y_mv, np.nan_to_num(sim_mv, nan=1e9, posinf=1e9, neginf=-1e9))[0])
    return dict(full=rmse["full"], short=rmse["no_extrapolation"], fit=fit)


def physical(model: str, theta: np.ndarray | None = None, module=None) -> str:
    if model == "discrete":
        return "-"
    ode = module if module is not None else DuffingODE(*theta)
    ph = ode.physical()
    if "f0_hz" not in ph:
        return "-"
    return f"{ph['f0_hz']:.2f} Hz, {ph['zeta']:.4f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--skip-clean", action="store_true")
    parser.add_argument("--skip-oe", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(
        "| training data | model | fit | arrow RMSE full (mV) | w/o extrapolation (mV) | arrow fit (%) "
        "| f0, damping ratio | seconds |"
    )
    print("|---|---|---|---|---|---|---|---|")
    settings = [("5 % outliers", 0.05)] + ([] if args.skip_clean else [("clean", 0.0)])
    for label, fraction in settings:
        recorded = prepare_silverbox(n_train=3000, outlier_fraction=fraction, random_state=0)
        for model in args.models:
            data = model_data(model, recorded)
            est = estimator(model, data)
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est.fit(data.u_train, data.y_train)
            seconds = time.perf_counter() - t0
            sc = scores(simulate_arrow(est, data), data)
            result = est.compare(data.u_arrow, data.y_arrow, x0=[float(data.y_arrow[0, 0]), 0.0])
            ph = physical(model, module=None if model == "discrete" else est.f_.rhs)
            print(
                f"| {label} | {model} | EM, defaults | {sc['full']:.2f} | {sc['short']:.2f} | "
                f"{result.fit[0]:.1f} | {ph} | {seconds:.0f} |",
                flush=True,
            )
            if args.skip_oe:
                continue
            theta, seconds = output_error_fit(model, data)
            sim = data.to_mv(_simulate(model, theta, np.array([data.y_arrow[0, 0], 0.0]), data.u_arrow[:, 0]))
            sc = scores(sim, data)
            full = f"{sc['full']:.2f}" if math.isfinite(sc["full"]) else "diverges"
            short = f"{sc['short']:.2f}" if math.isfinite(sc["short"]) else "diverges"
            print(
                f"| {label} | {model} | OE least squares (scipy) | {full} | {short} | {sc['fit']:.1f} | "
                f"{physical(model, theta)} | {seconds:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
