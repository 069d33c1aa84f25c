"""Starts of neural and grey-box models: train or fit something fast first, start EM there.

:func:`simulation_start` (the start for networks) trains ``f`` and ``g`` by robust simulation
error over windows (:func:`torch_nssm.estimation.neural_first_stage.neural_first_stage`) and returns
an unfitted clone of the user's estimator that starts there: the trained modules, the fitted first
state and noise levels that match the simulation.

:func:`distilled_start` (the earlier start) fits a reference model by EM (by default a
:class:`~torch_nssm.blocks.linear.LinearTransition`: closed-form M-steps), smooths the states with
it, sets the networks' normalisation from those states and trains the networks to imitate the
reference (:func:`distill`).  The result is an unfitted clone of the user's estimator that starts
where the reference ended.  Why and how: ``docs/design.md`` ("The distilled start").

Example
-------
>>> from torch_nssm import RobustNSSMEstimator, distilled_start
>>> from torch_nssm.neural import MLPTransition
>>> from torch_nssm.models import PaperObservation
>>> est = RobustNSSMEstimator(MLPTransition(1, 1, hidden=(16,), random_state=0),
...                           PaperObservation(0.5), x0_mean=[0.0], optimizer="adam",
...                           max_iter_mstep=50, n_iter=10, random_state=0)
>>> est = distilled_start(est, u, y).fit(u, y)                # doctest: +SKIP
"""

from __future__ import annotations

import copy
import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Union

import numpy as np
import torch
from sklearn.base import clone
from torch import Tensor, nn

from .. import _validation as V
from .._stats import robust_scale
from ..core.noise import noise_spec, restart_parameters
from ..estimation.neural_first_stage import (
    NeuralFirstStageOptions,
    NeuralFirstStageReport,
    default_options,
    holds_network,
    start_noise_levels,
)
from ..estimation.start import network_first_stage, stage_seed
from ..estimator import RobustNSSMEstimator
from .continuous import ContinuousTimeTransition
from .linear import LinearObservation, LinearTransition
from .neural import GreyBoxTransition, MLPObservation, MLPTransition

__all__ = [
    "distill",
    "simulation_start",
    "distilled_start",
    "DistilledStartInfo",
    "LinearTransition",
    "LinearObservation",
]

ArrayLike = Union[Tensor, np.ndarray, Sequence, float, None]


# ---------------------------------------------------------------------- distillation
def _free_parameters(module: nn.Module) -> list[nn.Parameter]:
    return [p for p in module.parameters() if p.requires_grad]


@torch.no_grad()
def _target(reference: nn.Module, x: Tensor, u: Tensor) -> Tensor:
    return reference(x, u)


def distill(
    module: nn.Module,
    reference: nn.Module,
    x: ArrayLike,
    u: ArrayLike = None,
    *,
    scale: ArrayLike = None,
    baseline: ArrayLike = None,
    max_iter: int = 300,
    tol: float = 1e-10,
) -> float:
    """Train ``module`` in place so that ``module(x, u)`` matches ``reference(x, u)``.

    Minimises the mean squared error ``mean(((module(x, u) - reference(x, u)) / scale)^2)`` over
    the rows of ``x`` and ``u`` by full-batch LBFGS (strong-Wolfe line search) over the module's
    parameters with ``requires_grad=True``.  Used by :func:`distilled_start` to start a neural
    transition at a fitted linear model.

    Parameters
    ----------
    module : nn.Module
        The module to train, called ``module(x, u)`` (e.g. an
        :class:`~torch_nssm.neural.MLPTransition` whose normalisation is already set).
    reference : nn.Module
        The module to imitate, with the same call signature and output width.
    x : array-like of shape (M, nx)
        States where the two must agree.
    u : array-like of shape (M, nu), optional
        Inputs (``None``: no input, ``nu = 0``).
    scale : float or array-like of shape (d,), optional
        Error scale per output column.  Default: the standard deviation of ``reference(x, u) -
        baseline`` (see ``baseline``), or of ``reference(x, u)`` itself.
    baseline : array-like of shape (M, d), optional
        Subtracted from the targets before computing the default ``scale`` (for a transition,
        pass ``x``: the scale becomes that of the increments ``f(x, u) - x``).
    max_iter : int, default=300
        LBFGS iterations.
    tol : float, default=1e-10
        LBFGS tolerance on the change of the loss.

    Returns
    -------
    float
        Relative root-mean-square error after training, ``sqrt(loss)`` (0 is perfect; 1 is as
        bad as predicting a constant).

    Raises
    ------
    TypeError
        If ``module`` or ``reference`` is not an ``nn.Module``.
    ValueError
        If the shapes disagree, the data are not finite, or ``module`` has no free parameters.
    """
    for name, m in (("module", module), ("reference", reference)):
        if not isinstance(m, nn.Module):
            raise TypeError(
                f"{name} must be a torch.nn.Module called as {name}(x, u), got {type(m).__name__}"
            )
    V.check_positive(max_iter, "max_iter", integer=True, minimum=1, inclusive=True)
    V.check_positive(tol, "tol", minimum=0.0, inclusive=True)
    params = _free_parameters(module)
    if not params:
        raise ValueError("module has no parameters with requires_grad=True to train")
    ref_t = next(iter(list(module.parameters()) + list(module.buffers())))
    kw = dict(dtype=ref_t.dtype, device=ref_t.device)
    xt, ut = _distillation_rows(x, u, kw)
    target = _target(copy.deepcopy(reference).to(**kw), xt, ut)
    with torch.no_grad():
        start = module(xt, ut)
    if start.shape != target.shape:
        raise ValueError(
            "module and reference must return the same shape, "
            f"got {tuple(start.shape)} and {tuple(target.shape)}"
        )
    s = _output_scale(target, baseline, scale)

    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=max_iter,
        tolerance_change=tol,
        history_size=50,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Tensor:
        opt.zero_grad()
        loss = (((module(xt, ut) - target) / s) ** 2).mean()
        loss.backward()
        return loss

    backup = copy.deepcopy(module.state_dict())
    with torch.no_grad():
        loss0 = float((((start - target) / s) ** 2).mean())
    opt.step(closure)
    with torch.no_grad():
        loss = float((((module(xt, ut) - target) / s) ** 2).mean())
    if not math.isfinite(loss) or loss > loss0:
        module.load_state_dict(backup)
        loss = loss0
    return math.sqrt(loss)


def _distillation_rows(x, u, kw: dict) -> tuple[Tensor, Tensor]:
    """``x`` ``(M, nx)`` and ``u`` ``(M, nu)`` (``None``: no input) as finite tensors."""
    xt = torch.as_tensor(np.asarray(x, dtype=np.float64) if not isinstance(x, Tensor) else x).to(**kw)
    if xt.dim() != 2 or xt.shape[0] == 0:
        raise ValueError(f"x must have shape (M, nx) with M >= 1, got shape {tuple(xt.shape)}")
    if u is None:
        ut = xt.new_zeros(xt.shape[0], 0)
    else:
        ut = torch.as_tensor(np.asarray(u, dtype=np.float64) if not isinstance(u, Tensor) else u).to(**kw)
        if ut.dim() == 1:
            ut = ut.unsqueeze(-1)
        if ut.dim() != 2 or ut.shape[0] != xt.shape[0]:
            raise ValueError(
                f"u must have shape ({xt.shape[0]}, nu) like x's rows, got shape {tuple(ut.shape)}"
            )
    if not (bool(torch.isfinite(xt).all()) and bool(torch.isfinite(ut).all())):
        raise ValueError("x and u must be finite")
    return xt, ut


def _output_scale(target: Tensor, baseline, scale) -> Tensor:
    """The scale of each output of the distillation loss: ``scale``, or the spread of the targets
    (less ``baseline``)."""
    if scale is None:
        base = target if baseline is None else target - torch.as_tensor(np.asarray(baseline)).to(target)
        s = base.std(dim=0) if base.shape[0] > 1 else base.abs().mean(dim=0)
        return torch.where(torch.isfinite(s) & (s > 1e-12), s, torch.ones_like(s))
    s = torch.as_tensor(np.asarray(scale, dtype=np.float64)).to(target).expand(target.shape[-1]).clone()
    if not bool((s > 0).all()):
        raise ValueError("scale must be positive")
    return s


# ---------------------------------------------------------------------- the distilled start
@dataclass
class DistilledStartInfo:
    """What :func:`distilled_start` did.

    Attributes
    ----------
    reference : RobustNSSMEstimator
        The fitted reference estimator (its ``f_``, ``g_``, ``Rw_``, ``log_likelihood_``...).
    f_error, g_error : float or None
        Relative RMS error of the network's imitation of the reference's ``f`` / ``g``
        (:func:`distill`); ``None`` where no network was trained (the module was taken over).
    f_action, g_action : str
        ``"distilled"`` (a network trained to imitate the reference), ``"physical"`` (a
        grey-box model's physical part took the fitted parameters), ``"fitted"`` (the fitted
        reference module itself is the start) or ``"kept"`` (a module without free parameters,
        unchanged).
    n_rows : int
        Number of state rows used to set the normalisation and to distil.
    seconds : float
        Wall time of the whole start.
    """

    reference: RobustNSSMEstimator
    f_error: float | None
    g_error: float | None
    f_action: str
    g_action: str
    n_rows: int
    seconds: float = field(default=0.0)


def _has_free_parameters(module: nn.Module) -> bool:
    return any(p.requires_grad for p in module.parameters())


def _cheap(module: nn.Module) -> bool:
    """A module the EM engine fits fast: closed form, or nothing to fit."""
    return hasattr(module, "solve_weighted_least_squares") or not _has_free_parameters(module)


def _records(u: Any, y: Any) -> tuple[list[np.ndarray | None], list[np.ndarray], bool]:
    """Inputs and outputs as lists of 2-d numpy arrays (one per record)."""
    multi = V.is_sequence_list(y)
    ys = list(y) if multi else [y]
    if u is None:
        us: list[Any] = [None] * len(ys)
    else:
        us = list(u) if multi else [u]
        if len(us) != len(ys):
            raise ValueError(f"u and y must hold the same number of records, got {len(us)} and {len(ys)}")
    out_y = []
    for a in ys:
        arr = np.asarray(a.detach().cpu() if isinstance(a, Tensor) else a, dtype=np.float64)
        out_y.append(arr.reshape(-1, 1) if arr.ndim == 1 else arr)
    out_u: list[np.ndarray | None] = []
    for a, b in zip(us, out_y):
        if a is None:
            out_u.append(np.zeros((b.shape[0], 0)))
            continue
        arr = np.asarray(a.detach().cpu() if isinstance(a, Tensor) else a, dtype=np.float64)
        out_u.append(arr.reshape(-1, 1) if arr.ndim == 1 else arr)
    return out_u, out_y, multi


def _default_reference_g(nx: int, nu: int, ys: list[np.ndarray]) -> nn.Module:
    """A linear observation in place of an MLP observation, scaled like the outputs."""
    yy = np.concatenate(ys, axis=0)
    med = np.nanmedian(yy, axis=0)
    mad = robust_scale(yy, axis=0, center=med)
    spread = np.where(np.isfinite(mad) & (mad > 0), mad, 1.0)
    p = yy.shape[1]
    C = np.eye(p, nx) * spread[:, None]
    return LinearObservation(nx, nu, p, C=C, d=np.nan_to_num(med))


def distilled_start(
    estimator: RobustNSSMEstimator,
    u: Any,
    y: Any,
    *,
    reference_f: nn.Module | None = None,
    reference_g: nn.Module | None = None,
    noise: str | None = None,
    n_iter: int = 20,
    n_particles: int | None = None,
    n_jitter: int = 4,
    distill_iter: int = 300,
    random_state: int | None = None,
    return_info: bool = False,
) -> RobustNSSMEstimator | tuple[RobustNSSMEstimator, DistilledStartInfo]:
    """A clone of ``estimator`` whose ``f``, ``g`` and noise start at a fitted reference model.

    Fits a reference model by EM (a linear transition by default: closed-form M-steps, fast),
    smooths the states with it, sets the neural modules' normalisation from the smoothed
    states and trains them to imitate the reference.  Call ``.fit(u, y)`` on the result.

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        The (unfitted) estimator of the model you want, e.g. with an
        :class:`~torch_nssm.neural.MLPTransition` as ``f``.  It is not changed.
    u : array-like of shape (N,) or (N, nu), list of them, or None
        Inputs, as for :meth:`~torch_nssm.RobustNSSMEstimator.fit`.
    y : array-like of shape (N,) or (N, p), or list of them
        Outputs (NaN: missing).
    reference_f : nn.Module, optional
        The reference transition fitted first (its initial values matter as for any EM fit).
        Default: the physical part of a :class:`~torch_nssm.neural.GreyBoxTransition`; a
        :class:`LinearTransition` (``A = 0.5 I``, ``B = 0.5``) for any other module with free
        parameters and no closed-form M-step; ``f`` itself otherwise.
    reference_g : nn.Module, optional
        The reference observation.  Default: ``g`` itself when it has a closed-form M-step or no
        free parameters; a :class:`LinearObservation` (scaled by a robust spread of ``y``) for an
        :class:`~torch_nssm.neural.MLPObservation`; ``g`` itself otherwise.
    noise : str or noise specification, optional
        Measurement-noise model of the reference fit; default the estimator's.
    n_iter : int, default=20
        EM iterations of the reference fit.
    n_particles : int, optional
        Particles of the reference fit; default the estimator's ``n_particles``.
    n_jitter : int, default=4
        Jittered copies of each smoothed state (drawn with the smoothed spread plus the process
        noise) added to the rows the network learns from: the particles of the later fit
        explore that neighbourhood.
    distill_iter : int, default=300
        LBFGS iterations of :func:`distill`.
    random_state : int, optional
        Seed of the jitter and of the reference fit; default the estimator's ``random_state``.
    return_info : bool, default=False
        Also return a :class:`DistilledStartInfo` (the fitted reference, the imitation errors, time).

    Returns
    -------
    RobustNSSMEstimator
        ``sklearn.base.clone(estimator)`` with ``f``, ``g``, ``x0_mean``, ``x0_cov``, ``Rw_init``,
        ``Rv_init`` and the noise family's other initial values (when the reference fitted the
        estimator's family) from the reference; unfitted.  A network distilled from the
        reference keeps the estimator's ``first_stage`` (``"auto"``: ``fit`` trains it by
        simulation error from this start); a grey box gets ``first_stage=None``.
    DistilledStartInfo
        Only with ``return_info=True``.

    Raises
    ------
    TypeError
        If ``estimator`` is not a :class:`~torch_nssm.RobustNSSMEstimator` or a reference is not
        an ``nn.Module``.
    ValueError
        For bad numbers or data (as :meth:`~torch_nssm.RobustNSSMEstimator.fit`).

    Notes
    -----
    Keep ``n_init=1`` for the fit after this start: restarts jitter every network weight
    (``init_jitter``), which throws the start away.
    """
    t0 = time.perf_counter()
    _check_arguments(estimator, reference_f, reference_g, noise, n_iter, n_particles, n_jitter, distill_iter)
    if not isinstance(return_info, (bool, np.bool_)):
        raise TypeError(f"return_info must be True or False, got {return_info!r}")
    f, g = estimator.f, estimator.g
    nx = int(np.asarray(estimator.x0_mean, dtype=np.float64).reshape(-1).size)
    us, ys, multi = _records(u, y)
    nu = us[0].shape[1]
    seed = estimator.random_state if random_state is None else random_state

    # 1. the reference model
    (ref_f, f_action), (ref_g, g_action) = _references(estimator, reference_f, reference_g, nx, nu, ys)
    reference = _reference_estimator(estimator, ref_f, ref_g, noise, n_iter, n_particles, seed)
    reference.fit(u, y)

    # 2. smoothed states: where the network must be right
    sm = reference.smooth(u, y)
    sms = sm if multi else [sm]
    (x_now, x_next, u_now), X, U = _training_rows(reference, sms, us, n_jitter, seed)

    # 3. the modules of the real fit
    f_new, f_error = _transition(f, f_action, reference, x_now, u_now, x_next, X, U, distill_iter)
    g_new, g_error = _observation(g, g_action, reference, X, U, ys, distill_iter)

    retrain = f_action == "distilled" and not isinstance(f, GreyBoxTransition)
    started = _started(estimator, reference, f_new, g_new, retrain)
    if not return_info:
        return started
    info = DistilledStartInfo(
        reference, f_error, g_error, f_action, g_action, int(X.shape[0]), time.perf_counter() - t0
    )
    return started, info


def _reference_estimator(estimator, ref_f, ref_g, noise, n_iter: int, n_particles, seed):
    """The quick fit of the reference modules: ``estimator``'s settings, plain EM from one start."""
    return clone(estimator).set_params(
        f=ref_f,
        g=ref_g,
        noise=estimator.noise if noise is None else noise,
        n_iter=n_iter,
        n_particles=estimator.n_particles if n_particles is None else n_particles,
        n_particles_final=None,
        average_last=0,
        n_init=1,
        warm_start=False,
        optimizer="lbfgs",
        batch_size=None,
        tol=0,
        random_state=seed,
        verbose=0,
    )


def _started(estimator, reference, f_new, g_new, retrain: bool):
    """``estimator`` set to start from the new modules and the reference's fitted noise and prior.

    ``retrain``: ``f`` is a network distilled from the reference, and the estimator's
    ``first_stage`` stays (``"auto"`` trains it by simulation error from this start); otherwise a
    model holding a network gets ``first_stage=None`` (a grey box: its physical part took the
    fitted parameters, its correction starts at zero, and EM refines it)."""
    params: dict[str, Any] = dict(
        f=f_new,
        g=g_new,
        x0_mean=reference.x0_mean_.copy(),
        x0_cov=reference.x0_cov_.copy(),
        Rw_init=reference.Rw_.copy(),
        Rv_init=reference.Rv_.copy(),
    )
    fitted = reference._fitted_noise()
    if fitted.name == estimator._noise_spec().name:  # the reference fitted the estimator's family
        params.update(restart_parameters(estimator.noise, fitted))
    # A network distilled from a linear reference imitates a model that does not simulate (the
    # suite's oscillator: 1.04 mm); EM from there stays near it (0.24 mm after 100 iterations,
    # Bouc-Wen 7.4 times the physical model), where the neural first stage from the same start
    # reaches 0.029 mm and 1.8 times in a third to a half of the CPU; on five pendulum records
    # even on three, worse on two (benchmarks/README.md, "`distilled_start`, then `fit`").
    if holds_network(SimpleNamespace(f=f_new, g=g_new)) and not retrain:
        params["first_stage"] = None  # a grey box's (an MLPObservation's) start is done: EM refines it
    return clone(estimator).set_params(**params)


def _check_arguments(estimator, reference_f, reference_g, noise, n_iter, n_particles, n_jitter, distill_iter):
    if not isinstance(estimator, RobustNSSMEstimator):
        raise TypeError(f"estimator must be a RobustNSSMEstimator, got {type(estimator).__name__}")
    for name, module in (("f", estimator.f), ("g", estimator.g)):
        if not isinstance(module, nn.Module):
            raise TypeError(f"estimator.{name} must be a torch.nn.Module, got {type(module).__name__}")
    if estimator.x0_mean is None:
        raise ValueError("estimator.x0_mean is required: it fixes the state dimension nx")
    for name, ref in (("reference_f", reference_f), ("reference_g", reference_g)):
        if ref is not None and not isinstance(ref, nn.Module):
            raise TypeError(
                f"{name} must be a torch.nn.Module called as {name}(x, u), got {type(ref).__name__}"
            )
    if noise is not None:
        noise_spec(noise)
    V.check_positive(n_iter, "n_iter", integer=True, minimum=1, inclusive=True)
    if n_particles is not None:
        V.check_positive(n_particles, "n_particles", integer=True, minimum=2, inclusive=True)
    V.check_positive(n_jitter, "n_jitter", integer=True, minimum=0, inclusive=True)
    V.check_positive(distill_iter, "distill_iter", integer=True, minimum=1, inclusive=True)


def _references(estimator, reference_f, reference_g, nx: int, nu: int, ys) -> tuple:
    """The reference modules of the quick fit and what becomes of ``f`` and ``g`` (``"kept"``,
    ``"physical"``, ``"fitted"``, ``"distilled"``): ``((ref_f, f_action), (ref_g, g_action))``."""
    f, g = estimator.f, estimator.g
    if reference_f is not None:
        ref_f, f_action = reference_f, "distilled" if _has_free_parameters(f) else "kept"
    elif isinstance(f, GreyBoxTransition):
        ref_f, f_action = copy.deepcopy(f.physical), "physical"
    elif _cheap(f):
        ref_f, f_action = f, "fitted"
    else:
        ref_f, f_action = LinearTransition(nx, nu, dtype=estimator.dtype), "distilled"
    if reference_g is not None:
        ref_g, g_action = reference_g, "distilled" if _has_free_parameters(g) else "kept"
    elif isinstance(g, MLPObservation):
        ref_g, g_action = _default_reference_g(nx, nu, ys), "distilled"
    else:
        ref_g, g_action = g, "fitted"
    return (ref_f, f_action), (ref_g, g_action)


def _training_rows(reference, sms: list, us: list, n_jitter: int, seed) -> tuple:
    """From the reference's smoothed states ``sms``: the transitions ``(x_now, x_next, u_now)``,
    and the rows ``X``, ``U`` where the modules are distilled (the smoothed means and ``n_jitter``
    copies jittered by their spread plus the process noise)."""
    rng = np.random.default_rng(
        None if seed is None or not isinstance(seed, (int, np.integer)) else int(seed)
    )
    Rw_diag = np.clip(np.diag(reference.Rw_), 0.0, None)
    xs, xn, uu = [], [], []
    for est_r, ur in zip(sms, us):
        mean = est_r.mean
        xs.append(mean[:-1])
        xn.append(mean[1:])
        uu.append(ur[:-1])
    x_now, x_next, u_now = (np.concatenate(a, axis=0) for a in (xs, xn, uu))
    spread = [np.sqrt(np.clip(np.diagonal(s.cov, axis1=-2, axis2=-1), 0.0, None) + Rw_diag) for s in sms]
    rows_x = [np.concatenate([s.mean for s in sms], axis=0)]
    rows_u = [np.concatenate(us, axis=0)]
    for _ in range(n_jitter):
        rows_x.append(
            np.concatenate(
                [s.mean + sd * rng.standard_normal(s.mean.shape) for s, sd in zip(sms, spread)], axis=0
            )
        )
        rows_u.append(rows_u[0])
    X, U = np.concatenate(rows_x, axis=0), np.concatenate(rows_u, axis=0)
    return (x_now, x_next, u_now), X, U


def _transition(f, action: str, reference, x_now, u_now, x_next, X, U, distill_iter: int) -> tuple:
    """The ``f`` of the real fit and its distillation error (``None`` if not distilled)."""
    f_new = copy.deepcopy(f)
    f_error: float | None = None
    if action == "fitted":
        f_new = copy.deepcopy(reference.f_)
    elif action == "physical":
        f_new.physical.load_state_dict(reference.f_.state_dict())
        f_new.fit_normalisation(x_now, u_now, x_next=x_next)
    elif action == "distilled":
        neural_ode = isinstance(f_new, ContinuousTimeTransition) and hasattr(f_new.rhs, "fit_normalisation")
        if isinstance(f_new, (MLPTransition, GreyBoxTransition)) or neural_ode:
            f_new.fit_normalisation(x_now, u_now, x_next=x_next)
        f_error = distill(f_new, reference.f_, X, U, baseline=X, max_iter=distill_iter)
    return f_new, f_error


def _observation(g, action: str, reference, X, U, ys, distill_iter: int) -> tuple:
    """The ``g`` of the real fit and its distillation error (``None`` if not distilled)."""
    g_new = copy.deepcopy(g)
    g_error: float | None = None
    if action == "fitted":
        g_new = copy.deepcopy(reference.g_)
    elif action == "distilled":
        if isinstance(g_new, MLPObservation):
            g_new.fit_normalisation(X, U if g_new.nu > 0 else None, y=np.concatenate(ys, axis=0))
        g_error = distill(g_new, reference.g_, X, U, max_iter=distill_iter)
    return g_new, g_error


# ---------------------------------------------------------------------- the simulation-error start
def simulation_start(
    estimator: RobustNSSMEstimator,
    u: Any,
    y: Any,
    *,
    options: NeuralFirstStageOptions | None = None,
    return_report: bool = False,
) -> RobustNSSMEstimator | tuple[RobustNSSMEstimator, NeuralFirstStageReport]:
    """A clone of ``estimator`` whose ``f`` and ``g`` were trained by robust simulation error.

    Runs the neural first stage (:func:`~torch_nssm.estimation.neural_first_stage.neural_first_stage`:
    windows of the record simulated noise-free, a Cauchy loss, LBFGS, an early stop on the held-out
    end of each record) on the estimator's modules and returns an unfitted clone that starts EM
    there; a grey box's physical parameters are fitted first, the network held
    (:func:`~torch_nssm.estimation.start.physical_part_first`).  Call ``.fit(u, y)`` on the result.

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        The (unfitted) estimator of the model you want, e.g. with an
        :class:`~torch_nssm.neural.MLPTransition` as ``f``.  It is not changed; its ``x0_mean`` is
        the first windows' starting state.
    u : array-like of shape (N,) or (N, nu), list of them, or None
        Inputs, as for :meth:`~torch_nssm.RobustNSSMEstimator.fit`.
    y : array-like of shape (N,) or (N, p), or list of them
        Outputs (NaN: missing).
    options : NeuralFirstStageOptions, optional
        Settings of the training (window length, iterations, loss...).  By default those of
        ``first_stage="auto"``: the robust (Cauchy) loss, or least squares for Gaussian noise
        (:func:`~torch_nssm.estimation.neural_first_stage.default_options`).
    return_report : bool, default=False
        Also return the :class:`~torch_nssm.estimation.neural_first_stage.NeuralFirstStageReport`.

    Returns
    -------
    RobustNSSMEstimator
        ``sklearn.base.clone(estimator)`` with the trained ``f`` and ``g``, ``x0_mean`` at the fitted
        first state (the mean over the records), ``Rv_init`` from the trained simulation's output
        errors unless the estimator sets it, and ``first_stage=None`` (the start is done).  With
        ``fit_Rw="auto"`` (the default) the network is a simulation model and EM holds its process
        noise small: ``fit_Rw=False`` and ``Rw_init`` 1e-6 times the variance of each simulated
        state (:func:`~torch_nssm.estimation.neural_first_stage.start_noise_levels`) unless given;
        ``fit_Rw=True`` lets EM estimate it.  If the training did not improve the free run
        (``report.accepted`` is False) the modules are the given ones (a grey box's: at its
        physical part's fit where that improved it) and a warning says so.
    NeuralFirstStageReport
        Only with ``return_report=True``.

    Raises
    ------
    TypeError
        If ``estimator`` is not a :class:`~torch_nssm.RobustNSSMEstimator`.
    ValueError
        For bad settings or data (as :meth:`~torch_nssm.RobustNSSMEstimator.fit`).

    Notes
    -----
    Keep ``n_init=1`` for the fit after it: restarts jitter every network weight.
    """
    if not isinstance(estimator, RobustNSSMEstimator):
        raise TypeError(f"estimator must be a RobustNSSMEstimator, got {type(estimator).__name__}")
    if not isinstance(return_report, (bool, np.bool_)):
        raise TypeError(f"return_report must be True or False, got {return_report!r}")
    if options is None:
        options = default_options(estimator._noise_spec().name)
    elif not isinstance(options, NeuralFirstStageOptions):
        raise TypeError(f"options must be a NeuralFirstStageOptions, got {type(options).__name__}")
    if estimator.x0_mean is None:
        raise ValueError("estimator.x0_mean is required: it fixes the state dimension nx")
    device = estimator._check_params()
    data, _ = estimator._batch(u, y, device, fitted=False)
    model = estimator._initial_model(data, device)
    generator = torch.Generator().manual_seed(stage_seed(estimator.random_state))
    report, first_states = network_first_stage(model, data, options, generator)
    if report.interrupted:  # Ctrl-C in a grey box's physical stage: no start to return
        raise KeyboardInterrupt
    params: dict[str, Any] = dict(f=model.f, g=model.g, first_stage=None)
    if first_states is not None:
        Rw, Rv = start_noise_levels(model, data, first_states)
        params["x0_mean"] = first_states.mean(0).cpu().numpy()
        if estimator.Rv_init is None:
            params["Rv_init"] = Rv.cpu().numpy()
        if estimator.fit_Rw == "auto":  # a simulation model: EM holds its process noise small
            params["fit_Rw"] = False
            if estimator.Rw_init is None:
                params["Rw_init"] = Rw.cpu().numpy()
    if not report.accepted:
        where = "the given modules" if first_states is None else "the physical part's fit (the network held)"
        warnings.warn(
            f"the simulation-error training did not improve the free run of the record (trimmed RMS of "
            f"its errors {report.free_run_after:.4g}, the start's {report.free_run_before:.4g}): EM starts "
            f"from {where}",
            RuntimeWarning,
            stacklevel=2,
        )
    started = clone(estimator).set_params(**params)
    return (started, report) if return_report else started
