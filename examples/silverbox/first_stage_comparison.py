"""Silverbox: what the first stage and a held process noise do to the free-run simulation.

``PYTHONPATH=examples python -m silverbox.first_stage_comparison`` (needs the Silverbox data, see
``examples/README.md``) fits the study's Duffing grey box on 3,000 training samples of the
multisine part (with 5 % injected outliers, and clean) and prints the arrow RMSE of

* the equation-error start (the study's initial values),
* the robust simulation-error fit alone (``first_stage="simulation"`` with ``n_iter=0``): the
  output-error baseline a user would try first, here with a Cauchy loss,
* EM from the equation-error start (no first stage, free process noise: the defaults before
  2026-11-24),
* EM after the first stage with a free process noise,
* EM after the first stage with the process noise held small (``fit_Rw=False``,
  ``Rw_init=1e-6``, normalised units): the setting for a simulation model,
* EM with the defaults (``first_stage="auto"``, ``fit_Rw="auto"``: the first stage, then EM with
  a free process noise, run again with it held if that made the simulation worse).
"""

from __future__ import annotations

import time
import warnings

import torch

from silverbox.study import (
    DuffingTransition,
    PositionObservation,
    arrow_rmse_mv,
    equation_error_init,
    prepare_silverbox,
    simulate_arrow,
)
from torch_nssm import RobustNSSMEstimator

SETTINGS = {
    "equation-error start": dict(n_iter=0, first_stage=None),
    "robust simulation-error fit (first stage alone)": dict(n_iter=0, first_stage="simulation"),
    "EM from the equation-error start (no first stage, Rw free)": dict(first_stage=None, fit_Rw=True),
    "EM after the first stage, Rw free": dict(first_stage="simulation", fit_Rw=True),
    "EM after the first stage, Rw held at 1e-6": dict(
        first_stage="simulation", fit_Rw=False, Rw_init=[1e-6, 1e-6]
    ),
    # what a user gets without options: first_stage="auto" and fit_Rw="auto"
    "EM, defaults": dict(),
}


def estimator(data, **overrides) -> RobustNSSMEstimator:
    init, scale = equation_error_init(data.u_train, data.y_train, nonlinear=True, return_scale=True)
    params = dict(
        x0_mean=[float(data.y_train[0, 0]), float(data.y_train[1, 0] - data.y_train[0, 0])],
        x0_cov=[0.05, 0.5],
        Rw_init=[scale**2, scale**2],
        Rv_init=1e-3,
        n_particles=100,
        n_iter=15,
        average_last=5,
        tol=0,
        smoother="mcmc",
        random_state=0,
    )
    params.update(overrides)
    return RobustNSSMEstimator(DuffingTransition(**init, nonlinear=True), PositionObservation(), **params)


def fit_and_score(est: RobustNSSMEstimator, data) -> tuple[dict, float]:
    """Fit ``est`` on the training segment (warnings silenced); the arrow RMSE (mV) and seconds."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(data.u_train, data.y_train)
    seconds = time.perf_counter() - t0
    return arrow_rmse_mv(simulate_arrow(est, data), data.to_mv(data.y_arrow[:, 0])), seconds


def main() -> None:
    torch.set_num_threads(1)
    print("| training data | fit | arrow RMSE full (mV) | without extrapolation (mV) | dof | seconds |")
    print("|---|---|---|---|---|---|")
    for label, fraction in (("5 % outliers", 0.05), ("clean", 0.0)):
        data = prepare_silverbox(n_train=3000, outlier_fraction=fraction, random_state=0)
        for name, overrides in SETTINGS.items():
            est = estimator(data, **overrides)
            rmse, seconds = fit_and_score(est, data)
            dof = "-" if est.n_iter_ == 0 else f"{est.dof_:.2f}"
            full, short = rmse["full"], rmse["no_extrapolation"]
            print(f"| {label} | {name} | {full:.2f} | {short:.2f} | {dof} | {seconds:.1f} |")


if __name__ == "__main__":
    main()
