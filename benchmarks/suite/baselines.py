"""The fits of the suite: output-error least squares, the true model's free run, our default fit.

Every method starts from the same modules (the plant's physically sized start) and the same first
state (the record's ``x0_guess``), and *fits* the first state; every fitted model is scored by its
noise-free free run on the validation record from that record's known first state, against the
noise-free measurement ``y_true``.

* :func:`oe_fit` -- what a competent user writes first: ``scipy.optimize.least_squares`` on the
  output errors of the noise-free simulation over the whole training record, the torch modules
  simulated in a Python loop under ``torch.inference_mode``, the Jacobian by scipy's finite
  differences (``"2-point"``, the default a user keeps), ``x_scale="jac"`` (the parameters' scales
  differ by orders of magnitude).
* :func:`default_fit` -- ``RobustNSSMEstimator(f, g, x0_mean=..., random_state=0)`` with nothing else,
  then ``standard_errors_``; each under a wall-clock budget (``KeyboardInterrupt``, as Ctrl-C).
"""

from __future__ import annotations

import copy
import math
import signal
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from scipy.optimize import least_squares
from torch import nn

from torch_nssm import RobustNSSMEstimator

__all__ = [
    "simulate",
    "rmse",
    "fit_percent",
    "score",
    "free_parameters",
    "oe_fit",
    "default_fit",
    "budget",
    "BudgetExceeded",
]

#: Robust scale of residuals: 1.4826 times the median absolute value (a Gaussian's s.d.).
MAD_TO_STD = 1.4826


class BudgetExceeded(Exception):
    """Raised inside a least-squares residual function when the wall-clock budget is spent."""


# ------------------------------------------------------------------------------ simulation, scores
def simulate(f: nn.Module, g: nn.Module, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """Noise-free free run ``x_{k+1} = f(x_k, u_k)``, ``y_k = g(x_k, u_k)`` from ``x0``, shape ``(N, p)``."""
    dtype = next(iter(f.parameters()), torch.zeros((), dtype=torch.float64)).dtype
    ut = torch.as_tensor(np.asarray(u, dtype=np.float64), dtype=dtype)
    with torch.inference_mode():
        x = torch.as_tensor(np.asarray(x0, dtype=np.float64), dtype=dtype)
        states = torch.empty(ut.shape[0], x.shape[-1], dtype=dtype)
        for k in range(ut.shape[0]):
            states[k] = x
            x = f(x, ut[k])
        return g(states, ut).numpy()


def rmse(yhat: np.ndarray, y: np.ndarray) -> float:
    """Root mean square error (inf for a non-finite simulation)."""
    e = np.asarray(yhat, dtype=np.float64) - np.asarray(y, dtype=np.float64)
    return float(np.sqrt(np.mean(e**2))) if np.all(np.isfinite(e)) else math.inf


def fit_percent(yhat: np.ndarray, y: np.ndarray) -> float:
    """``100 (1 - ||y - yhat|| / ||y - mean(y)||)`` (-inf for a non-finite simulation)."""
    y = np.asarray(y, dtype=np.float64)
    e = np.asarray(yhat, dtype=np.float64) - y
    if not np.all(np.isfinite(e)):
        return -math.inf
    return float(100.0 * (1.0 - np.linalg.norm(e) / np.linalg.norm(y - y.mean(axis=0))))


def score(yhat: np.ndarray, y_true: np.ndarray) -> dict[str, float]:
    """``{"rmse": ..., "fit_percent": ...}`` of a validation free run."""
    return {"rmse": rmse(yhat, y_true), "fit_percent": fit_percent(yhat, y_true)}


def fitted_first_state(
    f: nn.Module, g: nn.Module, u: np.ndarray, y: np.ndarray, x0: np.ndarray
) -> np.ndarray:
    """The first state whose free run fits the measured ``y`` of a record best (least squares, from
    ``x0``): the model's own first state of a record it has not seen."""
    y = np.asarray(y, dtype=np.float64).reshape(len(u), -1)

    def residuals(x: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            e = (simulate(f, g, u, x) - y).reshape(-1)
        return np.where(np.isfinite(e), e, 1e6 * (float(np.nanstd(y)) or 1.0))

    start = np.asarray(x0, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(residuals(start))):
        return start
    return least_squares(residuals, start, x_scale="jac", max_nfev=200).x


def validation_scores(f: nn.Module, g: nn.Module, val) -> dict[str, Any]:
    """Scores of the free run on a validation record ``val`` (``u``, ``y``, ``y_true``, ``x0``):
    ``rmse``, ``fit_percent`` from the first state fitted to the measured ``y``
    (:func:`fitted_first_state`, started at the true ``x0``), and ``rmse_known_x0`` from the true
    first state.  The fitted first state is the fair one: where a model's states are defined up to
    a change of coordinates (the tanks' unmeasured upper level scales with its pump gain, overflow
    height and overflow share; the filters of a Wiener-Hammerstein chain trade gains), the true
    first state is not the fitted model's, and the known-x0 score penalises an exact model."""
    with np.errstate(all="ignore"):
        x0 = fitted_first_state(f, g, val.u, val.y, val.x0)
        out = score(simulate(f, g, val.u, x0), val.y_true)
        out["rmse_known_x0"] = score(simulate(f, g, val.u, val.x0), val.y_true)["rmse"]
    out["x0_fitted"] = np.asarray(x0).tolist()
    return out


def free_parameters(*modules: nn.Module) -> dict[str, float]:
    """The scalar free parameters of the modules by name (``f.``/``g.`` prefixes dropped)."""
    out = {}
    for module in modules:
        for name, p in module.named_parameters():
            if p.requires_grad and p.numel() == 1:
                out[name] = float(p.detach())
            elif p.requires_grad:
                for i, v in enumerate(p.detach().reshape(-1).tolist()):
                    out[f"{name}[{i}]"] = float(v)
    return out


# ------------------------------------------------------------------------------ budget
#: The clocks of a budget: wall time, or the process's CPU time (user + system; robust to other
#: jobs on a shared machine), with their interval timer and signal.
CLOCKS = {"wall": (signal.ITIMER_REAL, signal.SIGALRM), "cpu": (signal.ITIMER_PROF, signal.SIGPROF)}


def clock_now(clock: str) -> float:
    """Seconds on ``clock`` ("wall" or "cpu")."""
    return time.perf_counter() if clock == "wall" else time.process_time()


@contextmanager
def budget(seconds: float | None, grace: float | None = None, clock: str = "wall") -> Iterator[dict]:
    """Raise ``KeyboardInterrupt`` in the main thread after ``seconds`` on ``clock`` (as Ctrl-C), and
    once more ``grace`` seconds later if the work is still running (a fit that goes on after its
    first interrupt, e.g. a second EM run).  Yields a dict whose ``"fired"`` counts the interrupts
    raised.  ``None`` or ``<= 0``: no budget."""
    state = {"fired": 0}
    if not seconds or seconds <= 0:
        yield state
        return
    grace = max(30.0, 0.25 * seconds) if grace is None else grace
    timer, signum = CLOCKS[clock]

    def handler(signum, frame):
        state["fired"] += 1
        if state["fired"] == 1 and grace > 0:
            signal.setitimer(timer, grace)
        raise KeyboardInterrupt

    previous = signal.signal(signum, handler)
    signal.setitimer(timer, seconds)
    try:
        yield state
    finally:
        signal.setitimer(timer, 0)
        signal.signal(signum, previous)


# ------------------------------------------------------------------------------ OE least squares
def oe_fit(
    f: nn.Module,
    g: nn.Module,
    u: np.ndarray,
    y: np.ndarray,
    x0: np.ndarray,
    *,
    loss: str = "linear",
    max_nfev: int | None = None,
    seconds: float | None = None,
    clock: str = "wall",
) -> dict[str, Any]:
    """Output-error least squares of ``f``, ``g`` and the first state over the whole record.

    ``loss="linear"``: plain least squares.  ``loss="soft_l1"``: ``f_scale`` is the robust scale
    (1.4826 MAD) of the start's residuals; a second pass from the first one's solution uses the
    robust scale of its residuals (the start's residuals are mostly model error, far larger than
    the noise).  A simulation that diverges (not finite, or errors beyond 1e6 times ``y``'s spread)
    gives residuals of 1e6 times that spread (the trust region then shrinks).  ``seconds``: a budget
    on ``clock`` ("wall" or "cpu"); when spent, the best parameters evaluated so far are kept
    (``"budget_exceeded": True``).

    Returns
    -------
    dict
        ``f``, ``g`` (fitted copies), ``x0``, ``seconds`` (wall), ``cpu_seconds``, ``nfev`` and
        ``njev`` (scipy's counts, of the passes that finished), ``simulations`` (every simulation of
        the record, the finite differences' included), ``status``, ``message``, ``cost``,
        ``budget_exceeded``, ``f_scale`` (soft-L1 passes), ``loss``.
    """
    f, g = copy.deepcopy(f), copy.deepcopy(g)
    params = [p for p in list(f.parameters()) + list(g.parameters()) if p.requires_grad]
    sizes = [p.numel() for p in params]
    y = np.asarray(y, dtype=np.float64).reshape(len(u), -1)
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    nx = x0.size
    theta0 = np.concatenate([p.detach().numpy().reshape(-1) for p in params] + [x0])
    spread = float(np.nanstd(y)) or 1.0
    t0, c0, b0 = time.perf_counter(), time.process_time(), clock_now(clock)
    # the best parameters evaluated in the current pass, by that pass's loss (kept when the budget ends it)
    best = {"cost": math.inf, "theta": theta0.copy(), "f_scale": 1.0}
    counts = {"nfev": 0, "njev": 0, "simulations": 0}

    def set_theta(theta: np.ndarray) -> None:
        start = 0
        with torch.no_grad():
            for p, n in zip(params, sizes):
                p.copy_(torch.as_tensor(theta[start : start + n]).view_as(p))
                start += n

    def residuals(theta: np.ndarray) -> np.ndarray:
        if seconds and seconds > 0 and clock_now(clock) - b0 > seconds:
            raise BudgetExceeded
        counts["simulations"] += 1
        set_theta(theta)
        with np.errstate(all="ignore"):
            r = (simulate(f, g, u, theta[-nx:]) - y).reshape(-1)
        if not (np.all(np.isfinite(r)) and np.abs(r).max() < 1e6 * spread):  # diverged
            return np.full(r.shape, 1e6 * spread)
        z = (r / best["f_scale"]) ** 2
        cost = float(np.sum(z if loss == "linear" else 2.0 * (np.sqrt(1.0 + z) - 1.0)))
        if cost < best["cost"]:
            best.update(cost=cost, theta=theta.copy())
        return r

    status, message, exceeded, scales = 0, "", False, []
    theta = theta0
    passes = [0] if loss == "linear" else [0, 1]
    try:
        for _ in passes:
            f_scale = 1.0
            if loss != "linear":
                r = residuals(theta)
                f_scale = MAD_TO_STD * float(np.median(np.abs(r))) or 1.0
                scales.append(f_scale)
            best.update(cost=math.inf, theta=theta.copy(), f_scale=f_scale)
            with np.errstate(over="ignore"):
                res = least_squares(
                    residuals, theta, loss=loss, f_scale=f_scale, x_scale="jac", max_nfev=max_nfev
                )
            counts["nfev"] += res.nfev
            counts["njev"] += int(res.njev or 0)
            theta, status, message = res.x, res.status, res.message
    except BudgetExceeded:
        exceeded, message = True, f"budget of {seconds:g} s spent: the best parameters evaluated so far kept"
        theta = best["theta"]
    set_theta(theta)
    r = (simulate(f, g, u, theta[-nx:]) - y).reshape(-1)
    return {
        "f": f,
        "g": g,
        "x0": theta[-nx:].copy(),
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
        "nfev": counts["nfev"],
        "njev": counts["njev"],
        "simulations": counts["simulations"],
        "status": int(status),
        "message": str(message),
        "cost": float(0.5 * r @ r) if np.all(np.isfinite(r)) else math.inf,
        "budget_exceeded": exceeded,
        "f_scale": scales,
        "loss": loss,
    }


# ------------------------------------------------------------------------------ our default fit
def _dedupe(caught) -> list[dict[str, str]]:
    seen, out = set(), []
    for w in caught:
        key = (w.category.__name__, str(w.message))
        if key not in seen:
            seen.add(key)
            out.append({"category": key[0], "message": key[1]})
    return out


def default_fit(
    f: nn.Module,
    g: nn.Module,
    u: np.ndarray,
    y: np.ndarray,
    x0_mean: np.ndarray,
    *,
    options: dict | None = None,
    seconds: float | None = 300.0,
    clock: str = "wall",
    standard_errors: bool = True,
) -> dict[str, Any]:
    """``RobustNSSMEstimator(f, g, x0_mean=x0_mean, random_state=0, **options).fit(u, y)``, then
    ``standard_errors_``, each under a budget of ``seconds`` on ``clock`` (a first
    ``KeyboardInterrupt`` when it is spent, a second one a grace period later).

    Returns
    -------
    dict
        ``estimator`` (or ``None`` when nothing was fitted), ``fit_seconds``, ``se_seconds`` (wall),
        ``fit_cpu_seconds``, ``se_cpu_seconds``,
        ``interrupted`` (how many interrupts the fit got), ``se_interrupted``, ``error`` (text of an
        exception that ended the fit), ``se_error``, ``warnings`` (deduplicated), ``standard_errors``
        (dict of floats or lists).
    """
    kwargs = {"x0_mean": np.asarray(x0_mean, dtype=float).tolist(), "random_state": 0}
    kwargs.update(options or {})
    est = RobustNSSMEstimator(f, g, **kwargs)
    out: dict[str, Any] = {"estimator": None, "error": None, "se_error": None, "standard_errors": None}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            with budget(seconds, clock=clock) as state:
                est.fit(u, y)
            out["estimator"] = est
        except KeyboardInterrupt:
            out["error"] = "KeyboardInterrupt escaped fit (budget spent outside the EM iterations)"
        except Exception as exc:  # noqa: BLE001 -- a failed fit is a row of the table
            out["error"] = f"{type(exc).__name__}: {exc}"
            if hasattr(est, "f_"):
                out["estimator"] = est
        out["fit_seconds"] = time.perf_counter() - t0
        out["fit_cpu_seconds"] = time.process_time() - c0
        out["interrupted"] = state["fired"]
        fit_warnings = _dedupe(caught)
    out["se_seconds"], out["se_cpu_seconds"], out["se_interrupted"] = math.nan, math.nan, 0
    se_warnings: list[dict[str, str]] = []
    if standard_errors and out["estimator"] is not None and out["error"] is None:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                with budget(seconds, grace=0, clock=clock) as state:
                    se = est.standard_errors_
                out["standard_errors"] = {k: np.asarray(v).tolist() for k, v in se.items()}
            except KeyboardInterrupt:
                out["se_error"] = "interrupted (budget)"
            except Exception as exc:  # noqa: BLE001
                out["se_error"] = f"{type(exc).__name__}: {exc}"
            out["se_seconds"] = time.perf_counter() - t0
            out["se_cpu_seconds"] = time.process_time() - c0
            out["se_interrupted"] = state["fired"]
            se_warnings = _dedupe(caught)
    out["warnings"] = fit_warnings
    out["se_warnings"] = se_warnings
    return out


def estimator_summary(est: RobustNSSMEstimator, outlier_mask: np.ndarray) -> dict[str, Any]:
    """What a fitted estimator says about itself (the columns of the suite's table)."""
    w = np.asarray(est.outlier_weights_, dtype=float).reshape(len(outlier_mask), -1).min(axis=-1)
    low = w < 0.5
    flagged = np.asarray(est.outliers_).reshape(len(outlier_mask), -1).any(axis=-1)
    n_out = int(np.sum(outlier_mask))
    fs = getattr(est, "first_stage_", None)
    history = est.history_
    rejected = {
        k: int(np.sum(history[k][1:])) for k in ("rejected.f", "rejected.g") if k in history
    }
    return {
        "n_iter": int(est.n_iter_),
        "converged": bool(est.converged_),
        "dof": float(np.min(est.dof_)),
        "Rv_diag": np.diag(np.atleast_2d(est.Rv_)).tolist(),
        "Rw_diag": np.diag(np.atleast_2d(est.Rw_)).tolist(),
        "fit_Rw": bool(getattr(est, "fit_Rw_", est.fit_Rw)),
        "x0_mean": np.asarray(est.x0_mean_).tolist(),
        "low_weight_share": float(np.mean(low)),
        "flagged_share": float(np.mean(flagged)),
        "false_flag_share": float(np.mean(flagged[~outlier_mask])) if (~outlier_mask).any() else 0.0,
        "flagged_outliers": int(np.sum(flagged & outlier_mask)),
        "low_weight_outliers": int(np.sum(low & outlier_mask)),
        "n_outliers": n_out,
        "rejected_msteps": rejected,
        "log_likelihood": float(est.log_likelihood_),
        "first_stage": None
        if fs is None
        else {
            "accepted": bool(fs.accepted),
            "explained": float(fs.explained),
            "rmse_before": float(fs.rmse_before),
            "rmse_after": float(fs.rmse_after),
            "free_run_scale_before_em": float(fs.free_run_scale_before_em),
            "free_run_scale_after_em": float(fs.free_run_scale_after_em),
        },
    }
