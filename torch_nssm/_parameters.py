"""The checks of :class:`~torch_nssm.RobustNSSMEstimator`'s parameters, as one table.

:data:`PARAMETER_CHECKS` maps each parameter to its check, in the order they run: a check takes
the value, the parameter's name and the estimator (for checks that depend on another parameter)
and raises a ``ValueError`` or ``TypeError`` naming the parameter and what is wrong.
:func:`check_parameters` runs them all before any work starts; :func:`em_options`,
:func:`start_settings`, :func:`em_runner` and :func:`report_settings` turn the parameters into the
settings of the EM loop, of the start policy, of a fit's runs and of its report.
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np
import torch
from torch import nn

from . import _validation as V
from .core.noise import NOISE_SHORTCUTS, NoiseSpec, noise_spec
from .estimation.estep import EStepOptions, auto_segment_length
from .estimation.loop import EMOptions
from .estimation.mstep import MStepOptions
from .estimation.runs import EMRunner
from .estimation.solvers import SOLVERS, SolverSettings
from .estimation.start import Start, StartSettings
from .inference.resampling import RESAMPLING_SCHEMES
from .inference.smoothers import SMOOTHERS, smoother_options

__all__ = [
    "PARAMETER_CHECKS",
    "check_parameters",
    "em_options",
    "start_settings",
    "em_runner",
    "report_settings",
    "resolved_segment_length",
    "segment_length_of",
]

Check = Callable[[object, str, object], None]

#: The gradient solvers' regressions keep at most this many rows per time step (an unbiased
#: thinning of the smoother's particles, :meth:`~torch_nssm.estimation.mstep.Regression.rows`).
ROWS_PER_STEP = 32


def choice(options) -> Check:
    return lambda value, name, _: V.check_choice(value, name, options)


def integer(minimum: int) -> Check:
    return lambda value, name, _: V.check_positive(value, name, integer=True, minimum=minimum, inclusive=True)


def at_least(minimum: float) -> Check:
    return lambda value, name, _: V.check_positive(value, name, minimum=minimum, inclusive=True)


def positive(value, name: str, _) -> None:
    V.check_positive(value, name)


def optional(check: Check) -> Check:
    """``check``, or nothing for ``None``."""
    return lambda value, name, estimator: None if value is None else check(value, name, estimator)


def acceleration(value, name: str, estimator) -> None:
    V.check_choice(value, name, ["newton", "squarem"])
    if value == "newton" and estimator.segment_length not in (None, "auto"):
        raise ValueError(
            "acceleration='newton' needs the exact E-step: set segment_length=None or 'auto' (the "
            "observed information is not computed from the windows of a segmented E-step)"
        )


def segment_length(value, name: str, _) -> None:
    if value is None or value == "auto":
        return
    if isinstance(value, str):
        raise ValueError(f"{name} must be a positive integer, 'auto' or None, got {value!r}")
    integer(1)(value, name, _)


def bool_or_auto(value, name: str, _) -> None:
    if not (isinstance(value, (bool, np.bool_)) or value == "auto"):
        raise ValueError(f"{name} must be True, False or 'auto', got {value!r}")


def boolean(value, name: str, _) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r}")


def unit_interval(value, name: str, _) -> None:
    if not (isinstance(value, (int, float)) and 0 <= value <= 1):
        raise ValueError(f"{name} must lie in [0, 1], got {value!r}")


def options_of_smoother(value, name: str, estimator) -> None:
    if not isinstance(value, dict):
        raise TypeError(f"{name} must be a dict, got {type(value).__name__}")
    allowed = smoother_options(estimator.smoother)
    unknown = sorted(set(value) - set(allowed))
    if unknown:
        raise ValueError(
            f"{name} has {unknown}, which smoother={estimator.smoother!r} does not take "
            f"(its options: {list(allowed)})"
        )


def dtype(value, name: str, _) -> None:
    V.check_dtype(value)


def workers(value, name: str, _) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value == 0:
        raise ValueError(f"{name} must be a nonzero integer or None, got {value!r}")


def required_state(value, name: str, _) -> None:
    if value is None:
        raise ValueError(f"{name} is required: it fixes the state dimension nx")


def module(value, name: str, _) -> None:
    if not isinstance(value, nn.Module):
        kind = type(value).__name__
        raise TypeError(f"{name} must be a torch.nn.Module called as {name}(x, u), got {kind}")


#: Parameter -> check, in the order they run.
PARAMETER_CHECKS: dict[str, Check] = {
    "noise": lambda value, name, estimator: noise_of(estimator) and None,
    "optimizer": choice(sorted([*SOLVERS, "auto"])),
    "smoother": choice(sorted(SMOOTHERS)),
    "first_stage": optional(choice(["auto", "simulation"])),
    "acceleration": optional(acceleration),
    "fit_Rw": bool_or_auto,
    "focus": choice(["prediction", "simulation"]),
    "resampling": choice(sorted(RESAMPLING_SCHEMES)),
    "n_particles": integer(2),
    "n_particles_final": optional(integer(2)),
    "average_last": integer(0),
    "n_iter": integer(0),
    "tol": at_least(0.0),
    "n_init": integer(1),
    "init_jitter": at_least(0.0),
    "max_iter_mstep": integer(1),
    "learning_rate": positive,
    "batch_size": optional(integer(1)),
    "warm_start": boolean,
    "ess_threshold": unit_interval,
    "chunk_size": optional(integer(1)),
    "segment_length": segment_length,
    "segment_overlap": integer(1),
    "smoother_options": optional(options_of_smoother),
    "dtype": dtype,
    "n_threads": optional(integer(1)),
    "n_jobs": optional(workers),
    "x0_mean": required_state,
    "f": module,
    "g": module,
}


def noise_of(estimator) -> NoiseSpec:
    """The measurement noise's specification: ``noise``, with the shortcut parameters forwarded
    to its family (:func:`~torch_nssm.core.noise.noise_spec`; it checks them)."""
    return noise_spec(estimator.noise, **{name: getattr(estimator, name) for name in NOISE_SHORTCUTS})


def check_parameters(estimator) -> torch.device:
    """Run :data:`PARAMETER_CHECKS` on ``estimator``'s parameters; the device they ask for."""
    for name, check in PARAMETER_CHECKS.items():
        check(getattr(estimator, name), name, estimator)
    return V.check_device(estimator.device)


def em_options(estimator, progress: str | None = None, fit_Rw: bool | None = None) -> EMOptions:
    """The EM loop's settings from ``estimator``'s parameters (``fit_Rw`` overrides theirs)."""
    smoother_opts = dict(estimator.smoother_options or {})
    if estimator.chunk_size is not None and estimator.smoother == "ffbsm":
        smoother_opts.setdefault("chunk_size", estimator.chunk_size)
    return EMOptions(
        n_iter=estimator.n_iter,
        tol=estimator.tol,
        n_particles_final=estimator.n_particles_final,
        average_last=estimator.average_last,
        acceleration=estimator.acceleration,
        estep=EStepOptions(
            n_particles=estimator.n_particles,
            smoother=estimator.smoother,
            smoother_options=smoother_opts,
            resampling=estimator.resampling,
            ess_threshold=estimator.ess_threshold,
            segment_length=segment_length_of(estimator),
            segment_overlap=estimator.segment_overlap,
        ),
        mstep=MStepOptions(
            optimizer=estimator.optimizer,
            solver=SolverSettings(
                max_iter=estimator.max_iter_mstep,
                learning_rate=estimator.learning_rate,
                batch_size=estimator.batch_size,
                generator=estimator._generator(torch.device("cpu")),
            ),
            fit_x0=bool(estimator.fit_x0),
            fit_Rw=bool(estimator.fit_Rw) if fit_Rw is None else fit_Rw,
            fit_Rv=bool(estimator.fit_Rv),
            rows_per_step=ROWS_PER_STEP,
        ),
        progress=progress if estimator.verbose else None,
    )


def segment_length_of(estimator) -> int | None:
    """The time-parallel E-step's window length: ``segment_length``, or for ``"auto"`` what the
    last fit chose from its records (``segment_length_``; ``None`` before a fit)."""
    if estimator.segment_length == "auto":
        return estimator.__dict__.get("segment_length_")
    return estimator.segment_length


def resolved_segment_length(estimator, data) -> int | None:
    """``segment_length`` for a fit of ``data``: ``"auto"`` cuts records of at least ten windows of
    ten times ``segment_overlap`` (:func:`~torch_nssm.estimation.estep.auto_segment_length`), except
    for ``acceleration="newton"``, which needs the exact pass."""
    if estimator.segment_length != "auto":
        return estimator.segment_length
    if estimator.acceleration == "newton":
        return None
    return auto_segment_length(int(data.lengths.max()), estimator.segment_overlap)


def start_settings(estimator, warm: bool) -> StartSettings:
    """The start policy's settings from the estimator's parameters (one run for ``warm``)."""
    e = estimator
    n_runs = 1 if warm else e.n_init
    return StartSettings(
        e.first_stage, e.n_iter, n_runs, e.init_jitter, e.random_state, warm,
        focus=e.focus, fit_Rw=e.fit_Rw, Rw_given=e.Rw_init is not None,
        Rv_given=e.Rv_init is not None, x0_cov_given=e.x0_cov is not None,
    )  # fmt: skip


def em_runner(estimator, device: torch.device, warm: bool, start: Start) -> EMRunner:
    """One EM run of a fit: a simulation model's keeps ``f`` and ``g``; ``warm_start=True``
    continues what the fit did (the process noise held or not, the modules held or not)."""
    fit_Rw = estimator.fit_Rw_ if warm else None
    hold = bool(estimator.__dict__.get("simulation_model_", False)) if warm else start.hold_modules
    make_options = functools.partial(em_options, estimator)
    return EMRunner(make_options, estimator.n_threads, estimator.n_init, device, fit_Rw, hold)


def report_settings(estimator) -> dict:
    """The settings a fit's report quotes in its warnings."""
    return {k: getattr(estimator, k) for k in ("n_iter", "tol", "optimizer", "learning_rate")}
