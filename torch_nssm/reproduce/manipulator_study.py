"""Section 4.2 of the paper: the two-link manipulator, Table 2 and Figs. 10-12, and the
Kalman-filter maximum likelihood used as an oracle."""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from ..datasets import SimulatedData, make_manipulator, manipulator_transition_matrix
from ..estimator import RobustNSSMEstimator
from ..models import ManipulatorObservation, ManipulatorTransition
from ._common import (
    PAPER,
    _fit,
    _iterations_to,
    _out,
    _progress,
    _pyplot,
    _savefig,
    _scalar,
    _write_settings,
    _write_table,
    torch_threads,
)

__all__ = ["manipulator", "manipulator_estimator", "manipulator_kalman_mle", "MANIPULATOR_INIT"]

#: Initial values of ``theta1, theta2`` in the manipulator experiment.
MANIPULATOR_INIT = {"theta1": 0.8, "theta2": 0.8}


# --------------------------------------------------------------------------------------------
# Table 2, Figs. 10-12
# --------------------------------------------------------------------------------------------


def manipulator_estimator(data, **kwargs) -> RobustNSSMEstimator:
    """The estimator of the manipulator experiment for one record, from ``theta1 = theta2 = 0.8``.

    ``Rw_init`` is the generator's process-noise covariance, ``Rv_init = 1e-3 I``, the prior of
    the first state has the generator's mean and 10 times its covariance, ``tol = 0``; the
    paper's algorithm (no first stage, ``fit_Rw=True``).

    Parameters
    ----------
    data : SimulatedData
        From :func:`~torch_nssm.datasets.make_manipulator`.
    **kwargs
        Further :class:`~torch_nssm.RobustNSSMEstimator` arguments (particles, smoother,
        iterations, ...); they override the defaults above.

    Returns
    -------
    RobustNSSMEstimator
        Not fitted.
    """
    Rw = np.asarray(data.params["Rw"], dtype=float)
    options = dict(
        x0_mean=data.params["x0_mean"],
        x0_cov=np.asarray(data.params["x0_cov"]) * 10,
        Rw_init=np.diag(Rw.reshape(-1)[:4]) if Rw.ndim == 1 else Rw,
        Rv_init=np.eye(2) * 1e-3,
        tol=0.0,
        first_stage=None,  # the paper's algorithm: EM from the paper's start (docs/design.md)
        fit_Rw=True,
    )
    options.update(kwargs)
    return RobustNSSMEstimator(
        ManipulatorTransition(MANIPULATOR_INIT["theta1"], MANIPULATOR_INIT["theta2"]),
        ManipulatorObservation(),
        **options,
    )


def _manipulator_nll(theta: np.ndarray, data: SimulatedData, keep: np.ndarray) -> float:
    """Exact negative log-likelihood of ``theta`` (Kalman filter), true noise, ``y[~keep]`` missing."""
    p = data.params
    A = manipulator_transition_matrix(data.u[:, 0], p["dt"], (float(theta[0]), float(theta[1])))
    Rw, Rv = np.asarray(p["Rw"], dtype=float), np.asarray(p["Rv"], dtype=float)
    m, P = np.asarray(p["x0_mean"], dtype=float), np.asarray(p["x0_cov"], dtype=float)
    nll = 0.0
    for k in range(len(data.y)):
        if keep[k]:  # update with y_k = x_k[2:4] + v_k
            S = P[2:, 2:] + Rv
            e = data.y[k] - m[2:]
            sign, logdet = np.linalg.slogdet(S)
            if sign <= 0:  # far from the data (an unstable theta): not a candidate
                return math.inf
            Si = np.linalg.inv(S)
            nll += 0.5 * (e @ Si @ e + logdet + 2.0 * math.log(2.0 * math.pi))
            K = P[:, 2:] @ Si
            m, P = m + K @ e, P - K @ S @ K.T
        m, P = A[k] @ m, A[k] @ P @ A[k].T + Rw
    return float(nll)


def manipulator_kalman_mle(data: SimulatedData, drop_outliers: bool = True) -> dict:
    """Exact maximum-likelihood estimate of ``(theta1, theta2)`` on one manipulator record.

    Given ``theta`` the manipulator is linear-Gaussian in the state, so a Kalman filter gives the
    exact likelihood.  With the true noise covariances and prior, and the outliers known and left
    out (``drop_outliers``), this is the best a likelihood method can do on the record: an oracle
    that shows how far the *data* pin ``theta`` down, whatever the particle method.

    Parameters
    ----------
    data : SimulatedData
        From :func:`~torch_nssm.datasets.make_manipulator` with Gaussian noise.
    drop_outliers : bool, default=True
        Treat the samples of ``data.outlier_mask`` as missing.

    Returns
    -------
    dict
        ``theta`` (the estimate, a pair) and ``se`` (its standard errors from the inverse of the
        observed information, a finite-difference Hessian).
    """
    from scipy.optimize import minimize

    keep = ~np.asarray(data.outlier_mask, dtype=bool) if drop_outliers else np.ones(len(data.y), bool)
    start = np.array([MANIPULATOR_INIT["theta1"], MANIPULATOR_INIT["theta2"]])
    res = minimize(
        _manipulator_nll, start, args=(data, keep), method="Nelder-Mead", options=dict(xatol=1e-5, fatol=1e-7)
    )
    x, h = res.x, 1e-3
    H = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            ei, ej = np.eye(2)[i] * h, np.eye(2)[j] * h
            H[i, j] = (
                _manipulator_nll(x + ei + ej, data, keep)
                - _manipulator_nll(x + ei - ej, data, keep)
                - _manipulator_nll(x - ei + ej, data, keep)
                + _manipulator_nll(x - ei - ej, data, keep)
            ) / (4 * h * h)
    se = np.sqrt(np.clip(np.diag(np.linalg.inv(H)), 0.0, None))
    return dict(theta=(float(x[0]), float(x[1])), se=(float(se[0]), float(se[1])))


@torch_threads(1)
def manipulator(fast: bool = False, out_dir="reproduction", seed: int = 0, progress: bool = True) -> dict:
    """Section 4.2: two-link manipulator at 5, 10, 20 and 40% outliers (Table 2, Figs. 10-12).

    Error rate (as the paper's Table 2): ``|theta_hat - theta| / theta * 100`` %.

    Parameters
    ----------
    fast : bool, default=False
        Tiny setting (N = 150, 8 iterations, 50 particles, FFBSm) instead of N = 500,
        150 iterations, 1000 particles with the MCMC smoother, last 50 iterates averaged; ``Rw``
        starts at the generator's (:func:`manipulator_estimator`).  The exact Kalman MLE of each
        record (:func:`manipulator_kalman_mle`) is reported beside the estimates.
    out_dir : str or Path
    seed : int, default=0
    progress : bool, default=True

    Returns
    -------
    dict
        ``fits`` (by outlier fraction), ``theta`` and ``error_rate`` (by fraction), ``oracle`` (by
        fraction: the exact Kalman MLE of :func:`manipulator_kalman_mle`, ``theta`` and ``se``),
        ``standard_errors`` (by fraction: our fit's observed-information standard errors of
        ``theta1, theta2``), ``table``, ``files``, ``settings``, ``seconds``.
    """
    out = _out(out_dir)
    s = (
        dict(
            n_samples=150, n_iter=8, n_particles=50, n_particles_final=None, smoother="ffbsm", average_last=0
        )
        if fast
        else dict(
            n_samples=500,
            n_iter=150,
            n_particles=1000,
            n_particles_final=None,
            smoother="mcmc",
            average_last=50,
        )
    )
    levels = (0.05, 0.10, 0.20, 0.40)
    settings = dict(
        experiment="manipulator",
        fast=fast,
        seed=seed,
        outlier_fractions=levels,
        init=MANIPULATOR_INIT,
        Rw_init="generator Rw (diag)",
        Rv_init="1e-3 I",
        x0_cov="10 x true",
        **s,
    )
    fits, theta, err, rows, datas, oracle, standard_errors = {}, {}, {}, [], {}, {}, {}
    t_start = time.perf_counter()
    for frac in _progress(levels, "manipulator fits", progress):
        data = make_manipulator(n_samples=s["n_samples"], outlier_fraction=frac, random_state=seed)
        datas[frac] = data
        est = manipulator_estimator(
            data,
            n_particles=s["n_particles"],
            n_particles_final=s["n_particles_final"],
            smoother=s["smoother"],
            n_iter=s["n_iter"],
            average_last=s["average_last"],
            random_state=seed,
        )
        est, secs = _fit(est, data.u, data.y)
        fits[frac] = est
        t1, t2 = est.f_.theta1.item(), est.f_.theta2.item()
        theta[frac] = (t1, t2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            se_ours = est.standard_errors_  # docs/uncertainty.md
        standard_errors[frac] = (float(se_ours["f.theta1"]), float(se_ours["f.theta2"]))
        err[frac] = (abs(t1 - 1.0) * 100, abs(t2 - 1.0) * 100)
        oracle[frac] = manipulator_kalman_mle(data)
        rows.append(_table2_row(frac, est, secs, err[frac], standard_errors[frac], oracle[frac]))
    total = time.perf_counter() - t_start
    settings["seconds"] = round(total, 1)
    note = (
        f"N = {s['n_samples']}, {s['n_iter']} EM iterations (paper: 200), {s['n_particles']}"
        f"{'->' + str(s['n_particles_final']) if s['n_particles_final'] else ''} particles "
        f"({s['smoother'].upper()}), last {s['average_last']} iterates averaged, "
        "init theta1 = theta2 = 0.8, Rw_init = the generator's Rw, Rv_init = 1e-3 I, "
        f"seed {seed}, {total:.0f} s. "
        "error = |theta_hat - 1| / 1 * 100%. 'iterations to 1%' = first iteration after which the "
        "estimate stays within 1% of the truth (theta1 / theta2; the last iteration + 1 if never). "
        "'exact MLE' = the maximum-likelihood estimate on the same record computed exactly by a Kalman "
        "filter with the true noise covariances and the outliers known and left out (an oracle: what "
        "the data allow), ± its standard error. 's.e. (ours)' = the observed-information standard errors "
        "of our fit (Louis' identity from the particle smoother, docs/uncertainty.md)."
    )
    table = _write_table(out, "table2", TABLE2_HEADER, rows, note)
    files = _manipulator_figures(out, fits, datas, levels)
    files += [str(out / "table2.md"), str(out / "table2.csv")]
    _write_settings(out, "manipulator", settings)
    return dict(
        fits=fits,
        theta=theta,
        error_rate=err,
        oracle=oracle,
        standard_errors=standard_errors,
        table=table,
        files=files,
        settings=settings,
        seconds=total,
    )


def _table2_row(frac: float, est, secs: float, err: tuple, se: tuple, oracle: dict) -> list:
    """Table 2's row of the fit ``est`` at outlier fraction ``frac``."""
    t1, t2 = est.f_.theta1.item(), est.f_.theta2.item()
    it1 = _iterations_to(_scalar(est.history_["f.theta1"]), 1.0, 0.01)
    it2 = _iterations_to(_scalar(est.history_["f.theta2"]), 1.0, 0.01)
    pp = PAPER["table2"][frac]
    (o1, o2), (se1, se2) = oracle["theta"], oracle["se"]
    return [
        f"{frac:.0%}",
        t1,
        f"{err[0]:.2f}%",
        f"{pp[0]:.4f} ({pp[1]:.2f}%)",
        t2,
        f"{err[1]:.2f}%",
        f"{pp[2]:.4f} ({pp[3]:.2f}%)",
        f"{o1:.4f} ± {se1:.4f}",
        f"{o2:.4f} ± {se2:.4f}",
        f"{it1} / {it2}",
        f"{secs:.1f}",
        f"{se[0]:.4f} / {se[1]:.4f}",
    ]


#: Columns of Table 2.
TABLE2_HEADER = [
    "outliers",
    "theta1",
    "error",
    "paper theta1",
    "theta2",
    "error",
    "paper theta2",
    "exact MLE theta1",
    "exact MLE theta2",
    "iterations to 1%",
    "seconds",
    "s.e. theta1 / theta2 (ours)",
]


def _manipulator_figures(out, fits: dict, datas: dict, levels) -> list[str]:
    """Figs. 10/12 (the parameter trajectories) and Fig. 11 (the outputs at 10 % outliers coloured
    by outlier weight); the files written."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.5))
    for frac in levels:
        for i, key in enumerate(("f.theta1", "f.theta2")):
            axes[i].plot(_scalar(fits[frac].history_[key]), label=f"{frac:.0%}")
    for i in range(2):
        axes[i].axhline(1.0, color="k", ls="--", lw=0.8)
        axes[i].set_title(f"theta{i + 1}")
        axes[i].set_xlabel("EM iteration")
        axes[i].grid(alpha=0.3)
    axes[0].legend(title="outliers")
    fig.suptitle("Figs. 10/12: manipulator parameter trajectories")
    files = [_savefig(fig, out / "manipulator_theta.png")]
    from ..plotting import plot_outliers

    d = datas[0.10]
    fig, axes = plt.subplots(2, 1, figsize=(11, 4.5), sharex=True)
    for i in range(2):
        plot_outliers(d.y[:, i], fits[0.10].outlier_weights_, true_outliers=d.outlier_mask, ax=axes[i])
        axes[i].set_ylabel(f"phi{i + 1} (rad)")
    fig.suptitle("Fig. 11: manipulator outputs, 10% outliers, coloured by outlier weight")
    files.append(_savefig(fig, out / "manipulator_outliers.png"))
    return files
