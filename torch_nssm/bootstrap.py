"""Parametric-bootstrap intervals: simulate from the fitted model, refit every record in one batched
EM pass (:func:`~torch_nssm.studies.fit_independent`), read percentile intervals.

The observed-information intervals (``RobustNSSMEstimator.confidence_intervals``) rest on the
normal approximation of the estimator; the bootstrap does not, at the price of ``n_boot`` refits
(docs/uncertainty.md).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from sklearn.base import clone
from sklearn.utils import check_random_state

from .core.noise import restart_parameters
from .studies import fit_independent

__all__ = ["BootstrapResult", "parametric_bootstrap", "parameter_values"]


@dataclass
class BootstrapResult:
    """Refitted parameters of the bootstrap records and their percentile intervals.

    Attributes
    ----------
    samples : dict of str to ndarray
        Keyed like ``standard_errors_`` (``"f.a"``, ``"Rw"``, ...): ``(n_boot, *shape)``.
    intervals : dict of str to (ndarray, ndarray)
        Percentile intervals ``(lower, upper)`` at ``level``.
    standard_errors : dict of str to ndarray
        Standard deviations of the refitted values.
    level : float
    n_boot : int
    """

    samples: dict
    intervals: dict
    standard_errors: dict
    level: float
    n_boot: int


def parameter_values(est) -> dict:
    """The fitted values keyed like ``standard_errors_``: the free parameters of ``f_`` and ``g_``
    and the estimated noise parameters (``Rw``, and the measurement noise's as its family says:
    ``Rv``, ``dof``, ...)."""
    out = {}
    for label in ("f", "g"):
        for name, p in getattr(est, f"{label}_").named_parameters():
            if p.requires_grad:
                out[f"{label}.{name}"] = p.detach().cpu().numpy().copy()
    if est.fit_Rw_:
        out["Rw"] = np.asarray(est.Rw_)
    for name in est._fitted_noise().estimated(fit_Rv=bool(est.fit_Rv)):
        out[name] = np.asarray(getattr(est, f"{name}_"))
    return out


def parametric_bootstrap(est, u, *, n_boot: int = 100, level: float = 0.95, random_state=None, **fit_options):
    """Percentile intervals from ``n_boot`` records simulated from the fitted ``est`` and refitted.

    Parameters
    ----------
    est : RobustNSSMEstimator
        A fitted estimator.
    u : array-like of shape (N,) or (N, nu), or None
        Inputs of the simulated records (usually the training inputs).
    n_boot : int, default=100
    level : float, default=0.95
    random_state : int, RandomState or None
        Seeds the simulation and the refits.
    **fit_options
        Estimator parameters for the refits (e.g. ``n_iter=30``, ``n_particles=100``); by default
        those of ``est``.  Each refit starts at the fitted values.

    Returns
    -------
    BootstrapResult
    """
    est._check_fitted()
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    if not (isinstance(n_boot, (int, np.integer)) and n_boot >= 2):
        raise ValueError(f"n_boot must be an integer >= 2, got {n_boot!r}")
    rs = check_random_state(random_state)
    _, ys = est.simulate(u, n_samples=int(n_boot), random_state=int(rs.randint(2**31 - 1)))
    if isinstance(ys, list):
        raise ValueError("bootstrap takes one record's inputs u, not a list of records")
    if getattr(est, "_y_1d", False):
        ys = ys[..., 0]
    start = clone(est).set_params(
        f=copy.deepcopy(est.f_),
        g=copy.deepcopy(est.g_),
        Rw_init=np.asarray(est.Rw_),
        Rv_init=np.asarray(est.Rv_),
        **restart_parameters(est.noise, est._fitted_noise()),  # e.g. dof_init
        x0_mean=np.asarray(est.x0_mean_),
        x0_cov=np.asarray(est.x0_cov_),
        n_init=1,
        warm_start=False,
        first_stage=None,
        fit_Rw=est.fit_Rw_,  # what the fit did (fit_Rw="auto" may have held the process noise)
        segment_length=None,  # fit_independent runs whole records (the bootstrap records are batched)
        verbose=0,
        random_state=int(rs.randint(2**31 - 1)),
    )
    start.set_params(**fit_options)
    fits = fit_independent(start, [u] * int(n_boot), list(ys), show_progress=False)
    values = [parameter_values(f) for f in fits]
    samples = {k: np.stack([v[k] for v in values]) for k in values[0]}
    q = [(1 - level) / 2, (1 + level) / 2]
    intervals = {}
    for k, s in samples.items():
        lo, hi = np.quantile(s, q, axis=0)
        intervals[k] = (lo, hi)
    errors = {k: s.std(0, ddof=1) for k, s in samples.items()}
    return BootstrapResult(samples, intervals, errors, float(level), int(n_boot))

