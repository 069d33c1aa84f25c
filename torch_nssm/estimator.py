"""``RobustNSSMEstimator``: the scikit-learn style front of the robust EM method.

The estimator validates its arguments, turns them into the options of the EM loop
(:func:`torch_nssm.estimation.loop.run_em`), stores what the loop returns as fitted attributes,
and hands prediction and simulation to :mod:`torch_nssm.inference.prediction`.
:func:`fit_independent` is the same loop over many data sets at once.
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import replace

import numpy as np
import torch
from sklearn.base import BaseEstimator, RegressorMixin, clone
from sklearn.exceptions import ConvergenceWarning, NotFittedError
from sklearn.metrics import r2_score
from sklearn.utils import check_random_state
from torch import nn

from . import _parallel
from . import _validation as V
from ._stats import MAD_TO_STD, robust_scale
from ._threads import limited_threads, with_thread_limit
from .core.model import SequenceBatch, StateSpaceModel
from .core.noise import NOISE_MODELS, get_noise_model, symmetric_pd
from .core.parametric import LinearInParameters
from .estimation.estep import EStepOptions, e_step, latent_scales, outlier_weights
from .estimation.first_stage import first_stage_applies, held_process_noise, simulation_error_fit
from .estimation.loop import EMOptions, EMResult, run_em
from .estimation.mstep import MStepOptions
from .estimation.solvers import SOLVERS, SolverSettings
from .inference import prediction
from .inference.filtering import NumericalError, particle_filter
from .inference.random import SequenceStreams, sequence_seed
from .inference.resampling import RESAMPLING_SCHEMES
from .inference.results import StateEstimate
from .inference.smoothers import SMOOTHERS, smoother_options
from .inference.smoothing import smoothed_moments
from .metrics import robust_r2_score

__all__ = ["RobustNSSMEstimator", "fit_independent"]

class RobustNSSMEstimator(RegressorMixin, BaseEstimator):
    """Robust identification of a nonlinear state-space model by EM with a particle smoother.

    The model is ``x_{k+1} = f(x_k, u_k) + w``, ``w ~ N(0, Rw)`` and ``y_k = g(x_k, u_k) + v``
    with ``v ~ St(0, Rv, dof)`` (multivariate Student-t; see ``noise`` for the other families).
    The E-step runs a bootstrap particle filter and a particle smoother; the M-step updates ``f``'s
    and ``g``'s parameters (closed form for :class:`~torch_nssm.LinearInParameters` modules, LBFGS
    or Adam otherwise), ``Rw``, the noise parameters and the initial-state prior (Liu & Yang,
    Neurocomputing 2019, with the corrections of docs/method.md).

    Data follow the time convention: sample ``k`` has input ``u_k`` and output ``y_k``; ``y_k``
    observes ``x_k``; the mean of ``x_{k+1}`` is ``f(x_k, u_k)``.  Every method takes one record
    (``u`` of shape ``(N,)`` or ``(N, nu)``, ``y`` of shape ``(N,)`` or ``(N, p)``) or several
    records of the same system as *lists of arrays* of possibly different lengths; the results
    then come as lists too.  NaN in ``y`` marks a missing output.

    Parameters
    ----------
    f : torch.nn.Module
        Transition mean ``f(x, u)``: ``x`` of shape ``(..., nx)``, ``u`` of shape ``(..., nu)``,
        returns ``(..., nx)``.  Its ``nn.Parameter`` s with ``requires_grad=True`` are estimated.
        It is copied, never changed.
    g : torch.nn.Module
        Observation mean ``g(x, u)`` returning ``(..., p)``.
    x0_mean : array-like of shape (nx,)
        Mean of the prior of the first state (it also fixes ``nx``).
    x0_cov : array-like, optional
        Its covariance ``(nx, nx)`` (a scalar or vector means a diagonal); identity if omitted.
    Rw_init : array-like, optional
        Initial process-noise covariance; ``0.1 * I`` if omitted.
    Rv_init : array-like, optional
        Initial measurement-noise scale matrix; ``0.02 * diag(s^2)`` if omitted, ``s`` a robust
        spread (1.4826 MAD) of each output (docs/design.md, "Estimator settings").
    dof_init : float, default=5.0
        Initial degrees of freedom of the Student-t noise.
    noise : {"student-t", "gaussian", "student-t-per-output"}, default="student-t"
        Measurement-noise model: the multivariate Student-t (one outlier weight per sample),
        ``"gaussian"`` (the non-robust baseline, Gopaluni 2008), or ``"student-t-per-output"``
        (independent t per output with diagonal ``Rv`` and one ``dof`` per output: a glitch in one
        sensor down-weights only that sensor).
    fit_dof : bool, default=True
        Estimate the DOF; if False it stays at ``dof_init``.
    dof_bounds : (float, float), default=(0.1, 1000.0)
        Bracket of the DOF root-solve.
    fit_Rw : bool or "auto", default="auto"
        Estimate the process-noise covariance; if False it stays at ``Rw_init`` (e.g. known from
        the physics, or for a simulation model).  ``"auto"``: estimate it, but when the first
        stage ran and EM made the model's noise-free simulation of the training record more than
        10 % worse than the first stage's (the process noise carrying what ``f`` should simulate),
        run EM again from the first stage with the process noise held small and keep that fit if
        it simulates better (a warning says so; ``fit_Rw_`` says what the kept fit did).
    fit_Rv : bool, default=True
        Estimate the measurement-noise scale matrix; if False it stays at ``Rv_init``.
    fit_x0 : bool, default=True
        Re-estimate the initial-state prior from the smoothed first state (its covariance is
        floored by ``Rw`` so that it cannot collapse on a single record).
    n_particles : int, default=200
        Number of particles ``L``.
    n_particles_final : int, optional
        The particle count grows geometrically from ``n_particles`` to this at iteration
        ``n_iter``; the final E-step and later ``smooth``/``predict`` calls use it.
    average_last : int, default=0
        If > 1, the fitted parameters are the average of the last ``average_last`` iterates
        (Polyak-Ruppert); the final E-step runs at the averaged parameters.
    acceleration : {None, "newton"}, default=None
        ``"newton"``: after each M-step, move ``f``'s and ``g``'s free parameters by a Newton step
        on the log-likelihood instead (the observed information by Louis' identity from the same
        E-step, :mod:`torch_nssm.estimation.acceleration`), until a step falls within one standard
        error; from there EM, with the noise parameters jumping along their own EM path by squared
        extrapolation (SQUAREM).  Fewer iterations where EM is slow (a small process noise); each
        Newton step costs one information computation (a few E-steps).
        ``history_["accelerated"]`` marks the iterates it produced.  Needs ``segment_length=None``.
    n_iter : int, default=100
        Maximum number of EM iterations (of each restart).
    tol : float, default=1e-3
        Convergence threshold on the change of the per-observation log-likelihood estimate,
        averaged over windows of 5 iterations (EM with particles is stochastic).  ``0`` runs all
        ``n_iter`` iterations without a :class:`~sklearn.exceptions.ConvergenceWarning`.
    n_init : int, default=1
        Number of EM runs; the one with the highest final log-likelihood estimate is kept.  Run 0
        starts from ``f`` and ``g`` as given, run ``r > 0`` from their free parameters times
        ``exp(init_jitter * N(0, 1))`` (signs and zeros kept; redrawn until ``f``'s noise-free
        simulation stays bounded), with ``g`` refitted to ``y`` along that simulation (robust least
        squares, for ``g`` linear in its parameters) and its own particle seed.
    init_jitter : float, default=1.0
        Standard deviation of the log-normal factor of the restarts (docs/design.md).
    first_stage : {"auto", "simulation", None}, default="auto"
        ``"simulation"``: before EM, fit ``f``, ``g`` and the first state by robust (Cauchy) simulation
        error over windows of ``FIRST_STAGE_WINDOW`` samples (multiple shooting), and start EM there
        (:mod:`torch_nssm.estimation.first_stage`); ``first_stage_`` reports the simulation RMSE
        before and after.  Restarts (``n_init``) jitter around the first stage's result.
        ``"auto"``: the same for physical and grey-box models (free parameters, no network layer
        in ``f`` or ``g``) when ``n_iter > 0``; models with networks start with
        :func:`~torch_nssm.warm_start_estimator` instead.  ``None``: EM starts from the given
        values.  docs/design.md, "How a fit starts".
    warm_start : bool, default=False
        If True and the estimator is fitted, :meth:`fit` continues EM from the fitted parameters
        (``n_iter`` more iterations, one run whatever ``n_init``); ``history_`` is extended.  The
        new data must have the same numbers of inputs and outputs.
    optimizer : {"lbfgs", "adam"}, default="lbfgs"
        Optimiser of the M-step for modules without a closed-form solve.
    max_iter_mstep : int, default=20
        LBFGS iterations (or Adam steps) per M-step.
    learning_rate : float, default=1e-2
        Adam's step size.
    batch_size : int, optional
        With ``optimizer="adam"``: minibatch size over the ``N L`` weighted regression rows of the
        M-step; ``max_iter_mstep`` is then a number of epochs, early-stopped on the full weighted
        objective (the M-step for neural networks).  Full-batch steps if omitted.
    smoother : {"ffbsm", "ffbsi", "mcmc"}, default="ffbsm"
        Particle smoother of the E-step (registry :data:`torch_nssm.inference.smoothers.SMOOTHERS`):
        ``"ffbsm"`` exact forward-filtering backward-smoothing, O(N L^2), no sampling noise of its
        own; ``"ffbsi"`` (rejection) and ``"mcmc"`` (Metropolis-Hastings moves) backward
        simulation, O(N L), the same M-step estimates within Monte Carlo error; ``"mcmc"`` is the
        fastest for large ``L``.
    resampling : {"systematic", "stratified", "residual", "multinomial"}, default="systematic"
    ess_threshold : float, default=1.0
        Resample when the effective sample size is below ``ess_threshold * n_particles``
        (1.0: at every step).
    chunk_size : int, optional
        FFBSm's chunk size (memory bound); automatic if omitted (a shortcut for
        ``smoother_options={"chunk_size": ...}``).
    smoother_options : dict, optional
        Keyword options of the chosen smoother (e.g. ``{"kernel_dtype": torch.float64}`` for
        ``"ffbsm"``, ``{"mcmc_steps": 2}`` or ``{"n_trajectories": 500}`` for ``"mcmc"``).
    segment_length : int, optional
        Time-parallel E-step for long records: each record longer than this is cut into windows
        owning ``segment_length`` samples, with ``segment_overlap`` samples of burn-in before and
        look-ahead after, all filtered and smoothed as one batch; each window starts from the
        previous iteration's filter prediction at its first sample.  ``None`` (default): one exact
        pass.  A few hundred to a few thousand samples; see docs/design.md ("Long records").
    segment_overlap : int, default=100
        Burn-in and look-ahead of each window: longer than the system's memory (its slowest time
        constant, in samples) and than the smoother's useful look-ahead.
    random_state : int, RandomState or None
        Seed of the particle methods and of the restarts.  With an int, every call (``fit``,
        ``smooth``, ``predict(..., horizon=k)``, ``simulate``...) is reproducible; the methods
        also take their own ``random_state``.
    n_threads : int or None, default=1
        CPU threads of torch and BLAS while the estimator's methods run; the caller's settings are
        restored afterwards (docs/design.md, "Threads").  ``None`` leaves them alone.
    n_jobs : int or None, default=None
        Workers (processes, through joblib) for the ``n_init`` restarts of :meth:`fit` and the
        chunks of :func:`fit_independent`: ``None`` means 1 unless a ``joblib.parallel_config``
        context says otherwise (``backend="dask"`` runs them on a Dask cluster), ``-1`` all
        cores.  Results equal the serial run's for the same ``random_state``; each worker uses
        ``n_threads`` threads (README, "Running on a cluster").
    device : str or torch.device, default="cpu"
        Where the filter, smoother and M-step run (``"cuda"`` for a GPU: the data, ``f``, ``g`` and
        the random numbers live there; fitted attributes come back as NumPy arrays and pickled
        fits load on a CPU).
    dtype : torch.dtype, default=torch.float64
    verbose : int, default=0
        Show a progress bar when > 0.

    Attributes
    ----------
    f_, g_ : torch.nn.Module
        Fitted copies of ``f`` and ``g`` (the modules passed in are not changed).
    Rw_ : ndarray of shape (nx, nx)
    Rv_ : ndarray of shape (p, p)
    dof_ : float, or ndarray of shape (p,)
        ``inf`` for Gaussian noise; one per output for ``"student-t-per-output"``.
    x0_mean_ : ndarray of shape (nx,)
    x0_cov_ : ndarray of shape (nx, nx)
    history_ : dict of str to ndarray
        Every parameter and the log-likelihood estimate at every iteration (index 0: the initial
        values), e.g. ``history_["f.a"]``, ``history_["Rv"]``, ``history_["log_likelihood"]``;
        ``history_["rejected.f"]``/``["rejected.g"]``: the iterations whose M-step of that module
        was undone (a warning says so).  With ``n_init > 1``: the kept run's.
    outlier_weights_ : ndarray of shape (N,) or (N, p), or list of them for several records
        ``E[lam_k | y]`` at the fitted parameters: near 0 marks an outlier (NaN where ``y_k`` is
        missing); per output for ``"student-t-per-output"``.
    log_likelihood_ : float
        Particle estimate of the log-likelihood at the fitted parameters.
    first_stage_ : FirstStageReport or None
        What the first stage did (simulation errors before and after, whether it was kept, the
        free-run error scales after the first stage and after EM); ``None`` if it did not run.
    fit_Rw_ : bool
        Whether the kept fit estimated the process noise (False when ``fit_Rw="auto"`` held it).
    init_log_likelihoods_ : ndarray of shape (n_init,)
        Final log-likelihood estimate of each run (``-inf`` for a run stopped by a
        :class:`~torch_nssm.NumericalError`).
    n_iter_ : int
        Number of EM iterations run (by the kept run, in the last call to ``fit``).
    converged_ : bool
    n_states_, n_inputs_, n_outputs_ : int
    n_features_in_ : int
        ``n_inputs_`` (scikit-learn's name).

    Notes
    -----
    A fit whose particle weights all underflow, or whose M-step produces a non-finite value,
    raises :class:`~torch_nssm.NumericalError`; the fitted attributes then hold the last good
    parameters (those of the last completed iteration), never NaN.

    Estimators pickle (``pickle``, ``joblib``) with their fitted modules; the modules are saved
    on the CPU, so a model fitted on a GPU loads anywhere.
    """

    def __init__(
        self,
        f: nn.Module,
        g: nn.Module,
        *,
        x0_mean=None,
        x0_cov=None,
        Rw_init=None,
        Rv_init=None,
        dof_init: float = 5.0,
        noise: str = "student-t",
        fit_dof: bool = True,
        dof_bounds: tuple[float, float] = (0.1, 1000.0),
        fit_Rw: bool | str = "auto",
        fit_Rv: bool = True,
        fit_x0: bool = True,
        n_particles: int = 200,
        n_particles_final: int | None = None,
        average_last: int = 0,
        acceleration: str | None = None,
        n_iter: int = 100,
        tol: float = 1e-3,
        n_init: int = 1,
        init_jitter: float = 1.0,
        first_stage: str | None = "auto",
        warm_start: bool = False,
        optimizer: str = "lbfgs",
        max_iter_mstep: int = 20,
        learning_rate: float = 1e-2,
        batch_size: int | None = None,
        smoother: str = "ffbsm",
        resampling: str = "systematic",
        ess_threshold: float = 1.0,
        chunk_size: int | None = None,
        smoother_options: dict | None = None,
        segment_length: int | None = None,
        segment_overlap: int = 100,
        random_state=None,
        n_threads: int | None = 1,
        n_jobs: int | None = None,
        device="cpu",
        dtype: torch.dtype = torch.float64,
        verbose: int = 0,
    ):
        self.f = f
        self.g = g
        self.x0_mean = x0_mean
        self.x0_cov = x0_cov
        self.Rw_init = Rw_init
        self.Rv_init = Rv_init
        self.dof_init = dof_init
        self.noise = noise
        self.fit_dof = fit_dof
        self.dof_bounds = dof_bounds
        self.fit_Rw = fit_Rw
        self.fit_Rv = fit_Rv
        self.fit_x0 = fit_x0
        self.n_particles = n_particles
        self.n_particles_final = n_particles_final
        self.average_last = average_last
        self.acceleration = acceleration
        self.n_iter = n_iter
        self.tol = tol
        self.n_init = n_init
        self.init_jitter = init_jitter
        self.first_stage = first_stage
        self.warm_start = warm_start
        self.optimizer = optimizer
        self.max_iter_mstep = max_iter_mstep
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.smoother = smoother
        self.resampling = resampling
        self.ess_threshold = ess_threshold
        self.chunk_size = chunk_size
        self.smoother_options = smoother_options
        self.segment_length = segment_length
        self.segment_overlap = segment_overlap
        self.random_state = random_state
        self.n_threads = n_threads
        self.n_jobs = n_jobs
        self.device = device
        self.dtype = dtype
        self.verbose = verbose

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.target_tags.required = True
        tags.target_tags.multi_output = True  # as many outputs as g returns
        tags.regressor_tags.poor_score = True  # a free-run simulation is not fitted to each row
        return tags

    # ------------------------------------------------------------------ scikit-learn parameters
    def get_params(self, deep: bool = True) -> dict:
        """The estimator's parameters; with ``deep``, also the initial values of ``f``'s and ``g``'s
        parameters as ``f__<name>`` / ``g__<name>`` (floats or arrays), for ``set_params``,
        ``GridSearchCV`` and ``clone``."""
        params = super().get_params(deep=False)
        if deep:
            for label in ("f", "g"):
                module = params.get(label)
                if isinstance(module, nn.Module):
                    for name, p in module.named_parameters():
                        value = p.detach().cpu().numpy().copy()
                        params[f"{label}__{name}"] = float(value) if value.ndim == 0 else value
        return params

    def set_params(self, **params) -> RobustNSSMEstimator:
        """Set parameters; ``f__a=0.3`` sets the initial value of ``f``'s parameter ``a`` (on a copy
        of ``f``: the module passed in is not changed)."""
        nested = {k: params.pop(k) for k in list(params) if k.startswith(("f__", "g__"))}
        super().set_params(**params)
        copied = set()
        for key, value in nested.items():
            label, name = key.split("__", 1)
            module = getattr(self, label)
            if not isinstance(module, nn.Module):
                raise ValueError(f"Invalid parameter {key!r}: {label} is not a torch.nn.Module")
            if label not in copied:
                module = copy.deepcopy(module)
                setattr(self, label, module)
                copied.add(label)
            named = dict(module.named_parameters())
            if name not in named:
                raise ValueError(f"Invalid parameter {key!r}: {label} has parameters {sorted(named)}")
            target = named[name]
            try:
                new = torch.as_tensor(np.asarray(value, dtype=float), dtype=target.dtype).to(target.device)
                new = new.expand_as(target) if new.dim() == 0 else new.reshape(target.shape)
            except (TypeError, ValueError, RuntimeError) as exc:
                shape = tuple(target.shape)
                raise ValueError(f"{key} must be a number or an array of shape {shape}") from exc
            with torch.no_grad():
                target.copy_(new)
        return self

    def __getstate__(self):
        state = super().__getstate__()
        for name in ("f_", "g_"):  # save the fitted modules on the CPU: they load anywhere
            module = state.get(name)
            if isinstance(module, nn.Module) and any(
                t.device.type != "cpu" for t in list(module.parameters()) + list(module.buffers())
            ):
                state[name] = copy.deepcopy(module).to("cpu")
        return state

    # ------------------------------------------------------------------ checks and set-up
    def _check_params(self) -> torch.device:
        V.check_choice(self.noise, "noise", sorted(NOISE_MODELS))
        V.check_choice(self.optimizer, "optimizer", sorted(SOLVERS))
        V.check_choice(self.smoother, "smoother", sorted(SMOOTHERS))
        if self.first_stage is not None:
            V.check_choice(self.first_stage, "first_stage", ["auto", "simulation"])
        if self.acceleration is not None:
            V.check_choice(self.acceleration, "acceleration", ["newton"])
            if self.segment_length is not None:
                raise ValueError(
                    "acceleration='newton' needs the exact E-step: set segment_length=None (the "
                    "observed information is not computed from the windows of a segmented E-step)"
                )
        if not (isinstance(self.fit_Rw, (bool, np.bool_)) or self.fit_Rw == "auto"):
            raise ValueError(f"fit_Rw must be True, False or 'auto', got {self.fit_Rw!r}")
        V.check_choice(self.resampling, "resampling", sorted(RESAMPLING_SCHEMES))
        V.check_positive(self.n_particles, "n_particles", integer=True, minimum=2, inclusive=True)
        if self.n_particles_final is not None:
            V.check_positive(
                self.n_particles_final, "n_particles_final", integer=True, minimum=2, inclusive=True
            )
        V.check_positive(self.average_last, "average_last", integer=True, minimum=0, inclusive=True)
        V.check_positive(self.n_iter, "n_iter", integer=True, minimum=0, inclusive=True)
        V.check_positive(self.tol, "tol", minimum=0.0, inclusive=True)
        V.check_positive(self.n_init, "n_init", integer=True, minimum=1, inclusive=True)
        V.check_positive(self.init_jitter, "init_jitter", minimum=0.0, inclusive=True)
        V.check_positive(self.max_iter_mstep, "max_iter_mstep", integer=True, minimum=1, inclusive=True)
        V.check_positive(self.learning_rate, "learning_rate")
        if self.batch_size is not None:
            V.check_positive(self.batch_size, "batch_size", integer=True, minimum=1, inclusive=True)
        V.check_positive(self.dof_init, "dof_init")
        if not isinstance(self.warm_start, (bool, np.bool_)):
            raise TypeError(f"warm_start must be True or False, got {self.warm_start!r}")
        if not (isinstance(self.ess_threshold, (int, float)) and 0 <= self.ess_threshold <= 1):
            raise ValueError(f"ess_threshold must lie in [0, 1], got {self.ess_threshold!r}")
        try:
            lo, hi = (float(b) for b in self.dof_bounds)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"dof_bounds must be a pair (low, high), got {self.dof_bounds!r}") from exc
        if not 0 < lo < hi:
            raise ValueError(f"dof_bounds must satisfy 0 < low < high, got {self.dof_bounds!r}")
        if self.chunk_size is not None:
            V.check_positive(self.chunk_size, "chunk_size", integer=True, minimum=1, inclusive=True)
        if self.segment_length is not None:
            V.check_positive(self.segment_length, "segment_length", integer=True, minimum=1, inclusive=True)
        V.check_positive(self.segment_overlap, "segment_overlap", integer=True, minimum=1, inclusive=True)
        if self.smoother_options is not None:
            if not isinstance(self.smoother_options, dict):
                kind = type(self.smoother_options).__name__
                raise TypeError(f"smoother_options must be a dict, got {kind}")
            allowed = smoother_options(self.smoother)
            unknown = sorted(set(self.smoother_options) - set(allowed))
            if unknown:
                raise ValueError(
                    f"smoother_options has {unknown}, which smoother={self.smoother!r} does not take "
                    f"(its options: {list(allowed)})"
                )
        V.check_dtype(self.dtype)
        if self.n_threads is not None:
            V.check_positive(self.n_threads, "n_threads", integer=True, minimum=1, inclusive=True)
        if self.n_jobs is not None and (
            isinstance(self.n_jobs, bool)
            or not isinstance(self.n_jobs, (int, np.integer))
            or self.n_jobs == 0
        ):
            raise ValueError(f"n_jobs must be a nonzero integer or None, got {self.n_jobs!r}")
        if self.x0_mean is None:
            raise ValueError("x0_mean is required: it fixes the state dimension nx")
        for name in ("f", "g"):
            module = getattr(self, name)
            if not isinstance(module, nn.Module):
                raise TypeError(
                    f"{name} must be a torch.nn.Module called as {name}(x, u), got {type(module).__name__}"
                )
        return V.check_device(self.device)

    def _generator(self, device: torch.device, random_state=None) -> torch.Generator:
        rs = check_random_state(self.random_state if random_state is None else random_state)
        return _seeded_generator(device, rs)

    def _batch(self, u, y, device, *, fitted: bool, require_y: bool = True) -> tuple[SequenceBatch, bool]:
        """Validated data as a padded batch, and whether several records were given."""
        kw = dict(n_inputs=self.n_inputs_, n_outputs=self.n_outputs_) if fitted else {}
        us, ys, multi = V.as_sequence_list(u, y, dtype=self.dtype, device=device, require_y=require_y, **kw)
        if ys is None:  # inputs only (free run, simulation): outputs all missing
            nan = math.nan
            ys = [torch.full((a.shape[0], self.n_outputs_), nan, dtype=a.dtype, device=device) for a in us]
        return SequenceBatch.from_sequences(us, ys), multi

    def _initial_model(self, data: SequenceBatch, device) -> StateSpaceModel:
        kw = dict(dtype=self.dtype, device=device)
        x0_mean = V.check_vector(self.x0_mean, "x0_mean", None, **kw)
        nx, p, nu = x0_mean.numel(), data.y.shape[-1], data.u.shape[-1]
        x0_cov = V.check_covariance(1.0 if self.x0_cov is None else self.x0_cov, "x0_cov", nx, **kw)
        Rw = V.check_covariance(0.1 if self.Rw_init is None else self.Rw_init, "Rw_init", nx, **kw)
        if self.Rv_init is None:
            Rv = torch.diag(default_rv_init(data.y.cpu().numpy().reshape(-1, p))).to(**kw)
        else:
            Rv = V.check_covariance(self.Rv_init, "Rv_init", p, **kw)
        f = copy.deepcopy(self.f).to(**kw)
        g = copy.deepcopy(self.g).to(**kw)
        _check_data_against_model(data, f, g, nu, p)
        V.check_module_shapes(f, g, nx, nu, p, **kw)
        noise = get_noise_model(self.noise).initial(Rv, float(self.dof_init))
        return StateSpaceModel(f, g, Rw, noise, x0_mean, x0_cov)

    def _em_options(self, progress: str | None = None, *, fit_Rw: bool | None = None) -> EMOptions:
        """The EM loop's settings from the estimator's parameters (``fit_Rw`` overrides theirs)."""
        smoother_opts = dict(self.smoother_options or {})
        if self.chunk_size is not None and self.smoother == "ffbsm":
            smoother_opts.setdefault("chunk_size", self.chunk_size)
        opts = EMOptions(
            n_iter=self.n_iter,
            tol=self.tol,
            n_particles_final=self.n_particles_final,
            average_last=self.average_last,
            acceleration=self.acceleration,
            estep=EStepOptions(
                n_particles=self.n_particles,
                smoother=self.smoother,
                smoother_options=smoother_opts,
                resampling=self.resampling,
                ess_threshold=self.ess_threshold,
                segment_length=self.segment_length,
                segment_overlap=self.segment_overlap,
            ),
            mstep=MStepOptions(
                optimizer=self.optimizer,
                solver=SolverSettings(
                    max_iter=self.max_iter_mstep,
                    learning_rate=self.learning_rate,
                    batch_size=self.batch_size,
                    generator=self._generator(torch.device("cpu")),
                ),
                fit_dof=bool(self.fit_dof),
                dof_bounds=tuple(float(b) for b in self.dof_bounds),
                fit_x0=bool(self.fit_x0),
                fit_Rw=bool(self.fit_Rw) if fit_Rw is None else fit_Rw,
                fit_Rv=bool(self.fit_Rv),
            ),
            progress=progress if self.verbose else None,
        )
        import os
        if os.environ.get("NSSM_OPT"):
            opts.mstep.optimizer = os.environ["NSSM_OPT"]
        if os.environ.get("NSSM_ROWS"):
            opts.mstep.rows_per_step = int(os.environ["NSSM_ROWS"])
        return opts

    def _e_step(self, model, data, generator):
        """The E-step at the final particle count (``smooth``, outlier weights)."""
        options = self._em_options()
        estep = options.estep
        estep.n_particles = options.n_particles(None)
        return e_step(model, data, estep, generator)

    def _filter(self, model, data, generator):
        return particle_filter(
            model,
            data,
            self._em_options().n_particles(None),
            resampling=self.resampling,
            ess_threshold=self.ess_threshold,
            generator=generator,
        )

    # ------------------------------------------------------------------ fitting
    @with_thread_limit
    def fit(self, u, y) -> RobustNSSMEstimator:
        """Estimate the model's parameters by robust EM.

        Parameters
        ----------
        u : array-like of shape (N,) or (N, nu), list of them, or None
            Inputs (``None`` for a system without input).  ``u_k`` drives ``x_k -> x_{k+1}``
            and enters ``g`` at time ``k``.  Several records (experiments on the same system,
            of possibly different lengths) go in a list of arrays: their statistics add up in
            every M-step.  A list of numbers or of Python lists is *one* record.
        y : array-like of shape (N,) or (N, p), or list of them
            Outputs; NaN marks a missing value (skipped by the filter).

        Returns
        -------
        self

        Raises
        ------
        ValueError, TypeError
            For bad arguments or data, before any work starts.
        NumericalError
            If the particle weights underflow or an update is not finite; the fitted attributes
            then hold the last good parameters.
        """
        device = self._check_params()
        warm = bool(self.warm_start) and hasattr(self, "f_")
        data, multi = self._batch(u, y, device, fitted=warm)
        if warm:
            base, n_runs = self._fitted_model(device), 1
        else:
            base, n_runs = self._initial_model(data, device), self.n_init
        staged = staged_run = None
        if not warm:
            self.first_stage_ = None
        if not warm and self._runs_first_stage(base):
            base, staged_run = self._first_stage(base, data)
            staged = _copy_model(base) if staged_run is not None else None
        limit = _divergence_limit(base, data, warn=not warm)
        seeds = _restart_seeds(self.random_state, n_runs)
        n_workers = min(n_runs, _parallel.effective_n_jobs(self.n_jobs))
        # a warm start continues what the fit did with the process noise (fit_Rw="auto" may have held it)
        fit_Rw = self._fitted_Rw() if warm else None
        import os
        self._policy = os.environ.get("NSSM_POLICY", "")
        if self._policy == "P1" and staged is not None and self.fit_Rw == "auto":
            # simulation model: the process noise held small, Rv from the first stage's residuals
            base = replace(base, Rw=held_process_noise(staged_run[0], data))
            if self.Rv_init is None:
                err = torch.cat(data.unpad(data.y - staged_run[1])).cpu().numpy()
                s2 = torch.as_tensor(np.nanmedian(np.abs(err), axis=0) * 1.4826) ** 2
                base = replace(base, noise=base.noise.replace(Rv=torch.diag(s2).to(base.Rw)))
            fit_Rw = False
            staged = None
        if n_workers > 1:  # each restart on a worker; run r depends on (random_state, r) only
            tasks = [(self, base, data, r, seeds[r], limit, device, False, fit_Rw) for r in range(n_runs)]
            runs = _parallel.run_tasks(_restart, tasks, self.n_jobs, f"{n_runs} EM restarts")
        else:
            runs = []
            for r in range(n_runs):
                runs.append(_restart(self, base, data, r, seeds[r], limit, device, True, fit_Rw))
                if runs[-1].interrupted:
                    break
        if runs[-1].interrupted and runs[-1].estep is None and len(runs) == 1:
            raise KeyboardInterrupt  # nothing was fitted yet
        ok = [run for run in runs if run.error is None and run.estep is not None]
        init_lls = np.array([run.log_likelihood if run.error is None else -np.inf for run in runs])
        y_1d = _is_1d(y, multi)
        if not ok:
            candidates = [run for run in runs if run.estep is not None]
            if candidates:
                last = max(candidates, key=lambda run: run.log_likelihood)
                self._store_run(last, data, multi, warm, y_1d, init_lls)
            raise NumericalError(_error_message(runs[0]))
        if len(ok) < len(runs):
            first = next(r.error for r in runs if r.error)
            warnings.warn(
                f"{len(runs) - len(ok)} of {len(runs)} EM runs stopped on a numerical error and "
                f"were discarded (first: {first})",
                RuntimeWarning,
                stacklevel=3,
            )
        best = max(ok, key=lambda run: run.log_likelihood)
        free_run_outputs = prediction.free_run(best.model, data.u)[1]  # (T, B, p) of the fitted model
        self.fit_Rw_ = self._fitted_Rw() if warm else (bool(self.fit_Rw) if fit_Rw is None else fit_Rw)
        if staged is not None:
            best, free_run_outputs = self._keep_the_simulation(
                staged, staged_run, best, free_run_outputs, data, seeds[0], limit, device
            )
        self._store_run(best, data, multi, warm, y_1d, init_lls)
        message = self._rejection_message(best)
        if message:
            warnings.warn(message, RuntimeWarning, stacklevel=3)
        message = _noise_absorbing_message(self.dof_, self.outlier_weights_)
        if message:
            warnings.warn(message, RuntimeWarning, stacklevel=3)
        explained, simulated = _explained_fraction(best, data, free_run_outputs)
        if explained >= EXPLAINED_FLOOR and simulated < 0.0:
            warnings.warn(
                f"the model's noise-free simulation explains none of y (robust R² of the free run "
                f"{simulated:.2f}, of the smoothed outputs {explained:.2f}): the states follow y through "
                "the process noise, not through f; f and g may sit in a wrong basin (check the scale of "
                "g's output against y's, try other initial values or n_init > 1), or the model is a "
                "tracking model rather than a simulation model (fit_Rw=False with a small Rw_init "
                "holds the process noise)",
                RuntimeWarning,
                stacklevel=3,
            )
        if explained < EXPLAINED_FLOOR:
            warnings.warn(
                f"g explains almost none of the variance of y (robust R² of the smoothed outputs "
                f"{explained:.3f}): the fit may sit where g is nearly constant and the noise explains "
                "the data; check the scale of g's output against y's, try other initial values of g, "
                "or n_init > 1",
                RuntimeWarning,
                stacklevel=3,
            )
        if best.interrupted:
            warnings.warn(
                f"fit interrupted (KeyboardInterrupt) after {best.n_done} EM iterations: the fitted "
                "attributes hold the last completed iteration",
                RuntimeWarning,
                stacklevel=3,
            )
        elif not best.converged and self.tol > 0 and self.n_iter > 0:
            warnings.warn(
                f"EM did not converge in n_iter={self.n_iter} iterations (tol={self.tol}); "
                "raise n_iter or tol, or average the last iterates",
                ConvergenceWarning,
                stacklevel=3,
            )
        return self

    def _runs_first_stage(self, start: StateSpaceModel) -> bool:
        """Whether the first stage runs from ``start`` (``first_stage`` and, for ``"auto"``, the model)."""
        if self.first_stage == "auto":  # a start for EM: none needed without EM (n_iter=0 evaluates a model)
            return self.n_iter > 0 and first_stage_applies(start)
        return self.first_stage == "simulation"

    def _first_stage(
        self, base: StateSpaceModel, data: SequenceBatch
    ) -> tuple[StateSpaceModel, tuple | None]:
        """The start after the robust simulation-error fit (``first_stage_`` says what it did), and
        the noise-free simulation ``(states, outputs)`` of that start if the first stage was kept."""
        given = _copy_model(base)
        report = simulation_error_fit(base, data)
        self.first_stage_ = report
        if report.accepted:
            staged = replace(base, x0_mean=report.record_states.mean(0))
            run = prediction.free_run(staged, data.u)
            yt = torch.cat(data.unpad(data.y)).cpu().numpy()
            report.explained = float(robust_r2_score(yt, torch.cat(data.unpad(run[1])).cpu().numpy()))
            if self.first_stage != "auto" or report.explained >= SIMULATION_R2_FLOOR:
                return staged, run
            # the process noise dominates y: a simulation-error fit is no guide to the parameters
            # (the paper's example: robust R² 0.47-0.65 at the true values, and the first stage can
            # land in a wrong basin), so EM starts from the given values
            report.accepted = False
            report.first_states = None
        elif self.first_stage != "auto":  # "auto": the given start is as good, no news
            warnings.warn(
                "the first stage (robust simulation-error fit) did not improve the start; EM starts "
                "from the given values",
                RuntimeWarning,
                stacklevel=4,
            )
        return given, None

    def _keep_the_simulation(
        self, staged: StateSpaceModel, staged_run: tuple, best: EMResult, free_run_outputs: torch.Tensor,
        data, seed, limit, device,
    ) -> tuple[EMResult, torch.Tensor]:
        """Compare the EM fit's free run with the first stage's (``staged_run``: its states and
        outputs); under ``fit_Rw="auto"``, when EM made it more than 10 % worse, run EM again from
        the first stage with the process noise held small and keep the run that simulates better.
        Returns the kept run and its free-run outputs."""
        before = _free_run_scale(staged_run[1], data)
        after = _free_run_scale(free_run_outputs, data)
        self.first_stage_.free_run_scale_before_em = before
        self.first_stage_.free_run_scale_after_em = after
        if not (np.isfinite(after) and after > SIMULATION_TOLERANCE * before):
            return best, free_run_outputs
        said = (
            f"EM made the model simulate worse than its first stage did (robust scale of the training "
            f"free-run errors {after:.4g} after EM, {before:.4g} after the first stage): the process noise "
            "is carrying what f should simulate"
        )
        if self.fit_Rw != "auto":
            warnings.warn(
                f"{said}. For a simulation model hold it (fit_Rw=False with a small Rw_init, or "
                "fit_Rw='auto'), or keep the first stage's parameters",
                RuntimeWarning,
                stacklevel=4,
            )
            return best, free_run_outputs
        Rw = held_process_noise(staged_run[0], data)
        held = _restart(self, replace(staged, Rw=Rw), data, 0, seed, limit, device, True, fit_Rw=False)
        outputs = prediction.free_run(held.model, data.u)[1] if held.estep is not None else None
        scale = _free_run_scale(outputs, data) if outputs is not None else math.nan
        if held.error is not None or not np.isfinite(scale) or scale >= after:
            warnings.warn(
                f"{said}; EM again from the first stage with the process noise held did not simulate "
                f"better ({scale:.4g}), so the fit keeps the estimated process noise",
                RuntimeWarning,
                stacklevel=4,
            )
            return best, free_run_outputs
        warnings.warn(
            f"{said}. So EM ran again from the first stage with the process noise held at "
            f"{np.array2string(torch.diagonal(Rw).cpu().numpy(), precision=3)} (diagonal; fit_Rw='auto'), "
            f"which simulates with a scale of {scale:.4g}: that fit is kept (fit_Rw_ is False). Pass "
            "fit_Rw=True to keep the estimated process noise",
            UserWarning,
            stacklevel=4,
        )
        self.fit_Rw_ = False
        self.first_stage_.free_run_scale_after_em = scale
        return held, outputs

    def _rejection_message(self, run: EMResult) -> str | None:
        """Words for the M-step updates that were undone in ``run`` (``None`` if none were)."""
        parts = []
        for label, module in (("f", run.model.f), ("g", run.model.g)):
            flags = run.history.get(f"rejected.{label}", [])[1:]
            n = int(np.sum(flags))
            if n:
                names = [name for name, p in module.named_parameters() if p.requires_grad]
                shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
                kind = type(module).__name__
                parts.append(f"{label} ({kind}: {shown}) at {n} of {len(flags)} iterations")
        if not parts:
            return None
        if self.optimizer == "adam":
            advice = (
                f"lower learning_rate (now {self.learning_rate}), raise max_iter_mstep, or try "
                "optimizer='lbfgs'"
            )
        else:
            advice = (
                "the weighted loss got worse or non-finite at every step tried: check that the module "
                "returns finite values near the current parameters, or start from other values"
            )
        return (
            "the M-step update was rejected (the step was undone and the parameters did not move) "
            f"for {'; '.join(parts)}; history_['rejected.f'] / ['rejected.g'] mark the iterations. "
            f"To fix: {advice}."
        )

    def _store_run(self, run: EMResult, data, multi, warm: bool, y_1d: bool, init_lls) -> None:
        history = run.history
        if warm:  # continue the previous trajectories; index 0 of this run repeats their end
            history = {k: list(self.history_[k]) + list(v[1:]) for k, v in history.items()}
        self._store(run.model, history, run.estep, data, multi, run.n_done, run.converged, y_1d=y_1d)
        self.init_log_likelihoods_ = init_lls

    def _store(self, model, history, est, data, multi, n_done, converged, *, y_1d=False) -> None:
        self.f_ = model.f
        self.g_ = model.g
        self.Rw_ = model.Rw.detach().cpu().numpy()
        self.Rv_ = model.Rv.detach().cpu().numpy()
        dof = getattr(model.noise, "dof", None)
        if dof is None:
            self.dof_ = math.inf
        else:
            self.dof_ = float(dof) if dof.dim() == 0 else dof.detach().cpu().numpy()
        self.x0_mean_ = model.x0_mean.detach().cpu().numpy()
        self.x0_cov_ = model.x0_cov.detach().cpu().numpy()
        self.history_ = {k: np.asarray(v) for k, v in history.items()}
        ow = outlier_weights(est.smoother.log_weights, est.e_lam, data)
        self.outlier_weights_ = ow if multi else ow[0]
        self.log_likelihood_ = float(est.log_likelihood.sum())
        self.n_iter_ = n_done
        self.converged_ = converged
        self.n_states_ = model.state_dim
        self.n_inputs_ = data.u.shape[-1]
        self.n_outputs_ = data.y.shape[-1]
        self.n_features_in_ = self.n_inputs_
        self._y_1d = bool(y_1d) and self.n_outputs_ == 1
        # the standard errors are computed on first use, from an E-step at the fitted parameters on
        # these data (keeping the fit's own E-step would hold ~10 (N, L) tensors for the
        # estimator's lifetime, and in every pickled or cloned copy)
        self._uncertainty = None
        self._uncertainty_source = (model, data)

    # ------------------------------------------------------------------ standard errors
    def _parameter_uncertainty(self, warn: bool = True):
        """The observed information at the fitted parameters (computed once, on first use); with
        ``warn``, its warnings (a module left out, parameters without a standard error)."""
        from .estimation.uncertainty import observed_information

        self._check_fitted()
        if self.__dict__.get("_uncertainty") is None:  # also a fit pickled before standard errors existed
            source = self.__dict__.get("_uncertainty_source")
            if source is None:
                raise AttributeError(
                    "this estimator was pickled by a version without standard errors: refit it"
                )
            model, data = source
            with limited_threads(self.n_threads):
                est = self._e_step(model, data, self._generator(data.y.device))
                self._uncertainty = observed_information(
                    model, data, est, fit_Rw=self._fitted_Rw(), fit_Rv=bool(self.fit_Rv),
                    fit_dof=bool(self.fit_dof), generator=self._generator(data.y.device),
                )
            self._uncertainty_source = None
        for message in self._uncertainty.warnings() if warn else ():
            warnings.warn(message, RuntimeWarning, stacklevel=3)
        return self._uncertainty

    def _fitted_Rw(self) -> bool:
        """Whether the fit estimated the process noise (``fit_Rw_``; fits pickled before it: ``fit_Rw``)."""
        return bool(self.__dict__.get("fit_Rw_", self.fit_Rw))

    @property
    def standard_errors_(self) -> dict:
        """Standard errors keyed like ``history_`` (``"f.a"``, ``"g.C"``, ``"Rw"``, ``"Rv"``,
        ``"dof"``), each shaped like its parameter: the observed information by Louis' identity from
        the final E-step's particle smoother (docs/uncertainty.md).  Parameters held fixed have none."""
        return self._parameter_uncertainty().standard_errors

    @property
    def parameter_covariance_(self) -> np.ndarray:
        """Asymptotic covariance of the free parameters' entries, in ``parameter_names_`` order."""
        return self._parameter_uncertainty().covariance

    @property
    def parameter_names_(self) -> list:
        """Names of the entries of :attr:`parameter_covariance_` (``"f.A[0, 1]"``, ``"Rw[1, 0]"``, ...;
        the lower triangle of a covariance matrix)."""
        return list(self._parameter_uncertainty().names)

    def confidence_intervals(self, level: float = 0.95) -> dict:
        """Confidence intervals ``(lower, upper)`` keyed like :attr:`standard_errors_`.

        Normal intervals from the observed information; for variances and degrees of freedom they are
        formed on the log scale (so they stay positive).  :meth:`bootstrap` gives intervals that do
        not rely on the asymptotics.
        """
        return self._parameter_uncertainty().confidence_intervals(level)

    def bootstrap(self, u, *, n_boot: int = 100, level: float = 0.95, random_state=None, **fit_options):
        """Parametric-bootstrap percentile intervals: ``n_boot`` records simulated from the fitted
        model with the inputs ``u`` are refitted from the fitted estimate in one
        :func:`fit_independent` call (:func:`torch_nssm.bootstrap.parametric_bootstrap`)."""
        from .bootstrap import parametric_bootstrap

        return parametric_bootstrap(
            self, u, n_boot=n_boot, level=level, random_state=random_state, **fit_options
        )

    # ------------------------------------------------------------------ using a fitted model
    def _check_fitted(self) -> torch.device:
        if not hasattr(self, "f_"):
            raise NotFittedError(
                f"This {type(self).__name__} instance is not fitted yet: call fit(u, y) first"
            )
        return V.check_device(self.device)

    def _fitted_model(
        self, device, x0=None, data: SequenceBatch | None = None, random_state=None
    ) -> StateSpaceModel:
        """The fitted model on ``device``, with copies of the fitted modules, starting at ``x0``
        (see :meth:`_initial_states`)."""
        kw = dict(dtype=self.dtype, device=device)
        t = lambda a: torch.as_tensor(a, **kw)  # noqa: E731
        family = get_noise_model(self.noise)
        noise = family(**{name: t(getattr(self, f"{name}_")) for name in family.CORE_DIMS})
        model = StateSpaceModel(
            copy.deepcopy(self.f_).to(**kw),
            copy.deepcopy(self.g_).to(**kw),
            t(self.Rw_),
            noise,
            t(self.x0_mean_),
            t(self.x0_cov_),
        )
        if x0 is None:
            return model
        mean, cov = self._initial_states(model, data, x0, random_state)
        return replace(model, x0_mean=mean, x0_cov=cov)

    def _initial_states(self, model: StateSpaceModel, data: SequenceBatch, x0, random_state=None) -> tuple:
        """Prior mean and covariance of the first state of each record of ``data`` for ``x0``:
        ``"estimate"`` (from the record's first outputs) or values ``(nx,)``, ``(B, nx)`` or a list
        of ``(nx,)`` (their covariance: the fitted ``x0_cov_``)."""
        B, nx = data.n_sequences, model.state_dim
        if isinstance(x0, str):
            if x0 != "estimate":
                raise ValueError(
                    f"x0 must be 'estimate' or an array of shape ({nx},) or ({B}, {nx}), got {x0!r}"
                )
            return self._estimate_initial_states(model, data, self._generator(data.y.device, random_state))
        kw = dict(dtype=self.dtype, device=data.y.device)
        try:
            values = torch.as_tensor(np.asarray(x0, dtype=float), **kw)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"x0 must be 'estimate' or numbers of shape ({nx},) or ({B}, {nx})") from exc
        if values.shape == (nx,):
            values = values.expand(B, nx)
        if tuple(values.shape) != (B, nx):
            raise ValueError(
                f"x0 must have shape ({nx},) or ({B}, {nx}) (one state per record), "
                f"got {tuple(values.shape)}"
            )
        if not bool(torch.isfinite(values).all()):
            raise ValueError("x0 contains NaN or infinite values")
        return values, model.per_sequence("x0_cov", B)

    def _estimate_initial_states(self, model: StateSpaceModel, data: SequenceBatch, generator) -> tuple:
        """Smoothed distribution of each record's first state given its first ``INITIAL_SAMPLES``
        outputs, from a broad prior (the fitted prior's covariance times 100, plus ``Rw``)."""
        if not bool(data.obs_mask.any()):
            raise ValueError("x0='estimate' needs the measured outputs y of the record(s)")
        n = min(data.n_steps, INITIAL_SAMPLES)
        head = SequenceBatch(data.u[:n], data.y[:n], data.lengths.clamp(max=n))
        broad = replace(model, x0_cov=100.0 * model.x0_cov + model.Rw)
        est = self._e_step(broad, head, generator)
        mean, cov = smoothed_moments(est.filter.particles[:1], est.smoother.log_weights[:1])
        eye = torch.eye(model.state_dim, dtype=cov.dtype, device=cov.device)
        return mean[0], symmetric_pd(cov[0] + 1e-9 * eye)

    def _outputs(self, values: torch.Tensor, data: SequenceBatch, multi: bool):
        """Time-major ``(T, B, p)`` outputs as arrays shaped like ``y`` (a list for records)."""
        out = [a.detach().cpu().numpy() for a in data.unpad(values)]
        if getattr(self, "_y_1d", False):
            out = [a[:, 0] for a in out]
        return out if multi else out[0]

    def _predictions(self, data: SequenceBatch, horizon, random_state, device, x0=None) -> torch.Tensor:
        """Free-run (``horizon=None``) or k-step-ahead outputs, time-major ``(T, B, p)``."""
        model = self._fitted_model(device, x0, data, random_state)
        if horizon is None:
            return prediction.free_run(model, data.u)[1]
        gen = self._generator(device, random_state)
        return prediction.k_step_ahead(model, data.u, self._filter(model, data, gen), horizon, gen)

    def _check_horizon(self, horizon, y, x0=None) -> None:
        if horizon is None:
            if y is not None and not (isinstance(x0, str) and x0 == "estimate"):
                raise ValueError(
                    "predict(u, y) needs horizon=k (k-step-ahead predictions from y); "
                    "predict(u) alone gives the free-run simulation"
                )
            return
        V.check_positive(horizon, "horizon", integer=True, minimum=0, inclusive=True)
        if y is None:
            raise ValueError(f"horizon={horizon} needs the measured outputs y")

    @with_thread_limit
    def predict(self, u, y=None, *, horizon: int | None = None, x0=None, random_state=None):
        """Predicted outputs: the free-run simulation, or k-step-ahead predictions given ``y``.

        Parameters
        ----------
        u : array-like of shape (N,) or (N, nu), or list of them
            Inputs (for a model without input: an array of shape ``(N, 0)``, or ``None`` with
            ``y``).
        y : array-like of shape (N,) or (N, p), or list of them, optional
            Measured outputs, needed with ``horizon`` (NaN: missing).
        horizon : int, optional
            ``None``: the *free-run* output ``g(x_k, u_k)`` with ``x_0 = x0_mean_`` and
            ``x_{k+1} = f(x_k, u_k)``, noise-free (it does not look at ``y``).  ``k >= 0``: the
            ``k``-step-ahead prediction ``E[g(x_t, u_t) | y_{0:t-k}]`` from the particle filter:
            its particles at ``t - k`` are propagated ``k`` steps through ``f`` *with* process
            noise and ``g`` is averaged over them with the filter weights; for ``t < k`` the
            initial-state prior is propagated instead.  ``0`` gives the filtered outputs.
        x0 : array-like of shape (nx,) or (n_records, nx), or "estimate", optional
            The first state of the record(s) (default: ``x0_mean_``, the *training* record's).
            ``"estimate"``: from the record's first outputs (a smoothing pass over its first
            ``INITIAL_SAMPLES`` samples from a broad prior; needs ``y``, also for the free run).
        random_state : int, optional
            Seed of the particle filter for ``horizon`` (default: the estimator's).

        Returns
        -------
        ndarray of shape (N,) or (N, p), or list of them
            Shaped like the ``y`` given to :meth:`fit`.
        """
        device = self._check_fitted()
        self._check_horizon(horizon, y, x0)
        data, multi = self._batch(u, y, device, fitted=True, require_y=horizon is not None)
        return self._outputs(self._predictions(data, horizon, random_state, device, x0), data, multi)

    @with_thread_limit
    def score(
        self,
        u,
        y,
        sample_weight=None,
        *,
        horizon: int | None = None,
        robust: bool = False,
        x0=None,
        random_state=None,
    ):
        """Coefficient of determination R² of :meth:`predict` (scikit-learn's regressor score).

        ``1 - SS_res / SS_tot`` per output column over the observed (non-NaN) samples of all
        records pooled, then the uniform average over the outputs (scikit-learn's
        ``r2_score(..., multioutput="uniform_average")``).  By default it scores the free-run
        simulation ``predict(u)``, the demanding test of a dynamic model; ``horizon=k`` scores
        the ``k``-step-ahead predictions instead.  R² is the default (scikit-learn's convention);
        outliers in ``y`` dominate it: ``robust=True`` gives
        :func:`torch_nssm.metrics.robust_r2_score` (``scoring=robust_r2_scorer`` in model selection).

        Parameters
        ----------
        u, y : array-like or lists of them
            As in :meth:`fit`.
        sample_weight : array-like of shape (N,), optional
            Weights of the samples (one record only).
        horizon : int, optional
            See :meth:`predict`.
        robust : bool, default=False
            Score with robust scales instead of variances (no ``sample_weight``).
        x0 : array-like or "estimate", optional
            The first state of the record(s), as in :meth:`predict`.
        random_state : int, optional
            Seed for ``horizon``.

        Returns
        -------
        float
        """
        device = self._check_fitted()
        if robust and sample_weight is not None:
            raise ValueError("sample_weight is not supported with robust=True")
        if horizon is not None:
            self._check_horizon(horizon, y)
        data, multi = self._batch(u, y, device, fitted=True)
        pred = self._predictions(data, horizon, random_state, device, x0)
        yt = torch.cat(data.unpad(data.y)).cpu().numpy()
        yp = torch.cat(data.unpad(pred)).cpu().numpy()
        sw = None
        if sample_weight is not None:
            if multi:
                raise ValueError("sample_weight is only supported for one record")
            sw = np.asarray(sample_weight, dtype=float).reshape(-1)
            if sw.shape[0] != yt.shape[0]:
                raise ValueError(
                    f"sample_weight must have {yt.shape[0]} entries (one per sample), got {sw.shape[0]}"
                )
        if robust:
            return robust_r2_score(yt, yp)
        scores = []
        for j in range(yt.shape[1]):
            m = ~np.isnan(yt[:, j])
            w = None if sw is None else sw[m]
            scores.append(r2_score(yt[m, j], yp[m, j], sample_weight=w))
        return float(np.mean(scores))

    @with_thread_limit
    def simulate(self, u, n_samples: int = 1, random_state=None, *, x0=None):
        """Sample state and output trajectories from the fitted model, noise included.

        ``x_0 ~ N(x0_mean_, x0_cov_)``, ``x_{k+1} = f(x_k, u_k) + w_k``, ``w ~ N(0, Rw_)``,
        ``y_k = g(x_k, u_k) + v_k``, ``v ~ St(0, Rv_, dof_)`` (heavy tails included; Gaussian
        for ``dof_ = inf``).

        Parameters
        ----------
        u : array-like of shape (N,) or (N, nu), or list of them
            Inputs (``(N, 0)`` for a model without input).
        n_samples : int, default=1
            Number of trajectories.
        random_state : int, RandomState or None
            Seed (default: the estimator's ``random_state``).
        x0 : array-like of shape (nx,) or (n_records, nx), optional
            Mean of the first state (default ``x0_mean_``); its spread stays ``x0_cov_``.

        Returns
        -------
        states : ndarray of shape (n_samples, N, nx), or list of them
        outputs : ndarray of shape (n_samples, N, p), or list of them
        """
        device = self._check_fitted()
        V.check_positive(n_samples, "n_samples", integer=True, minimum=1, inclusive=True)
        data, multi = self._batch(u, None, device, fitted=True, require_y=False)
        gen = self._generator(device, random_state)
        if isinstance(x0, str):
            raise ValueError("simulate has no outputs to estimate x0 from: pass the state (nx,) itself")
        x, yy = prediction.simulate(self._fitted_model(device, x0, data), data.u, n_samples, gen)
        xs = [a.transpose(0, 1).cpu().numpy() for a in data.unpad(x)]
        ys = [a.transpose(0, 1).cpu().numpy() for a in data.unpad(yy)]
        return (xs, ys) if multi else (xs[0], ys[0])

    def _state_estimates(self, u, y, kind: str, return_particles: bool, random_state, x0=None):
        device = self._check_fitted()
        data, multi = self._batch(u, y, device, fitted=True)
        model = self._fitted_model(device, x0, data, random_state)
        gen = self._generator(device, random_state)
        if kind == "smoother":
            est = self._e_step(model, data, gen)
            filt, log_w, e_lam = est.filter, est.smoother.log_weights, est.e_lam
        else:
            filt = self._filter(model, data, gen)
            log_w, e_lam = filt.log_weights, latent_scales(model, data, filt)[0]
        ow = outlier_weights(log_w, e_lam, data)
        mean, cov = smoothed_moments(filt.particles, log_w)
        out = []
        for b, n in enumerate(data.lengths.tolist()):
            out.append(
                StateEstimate(
                    mean=mean[:n, b].cpu().numpy(),
                    cov=cov[:n, b].cpu().numpy(),
                    outlier_weights=ow[b],
                    log_likelihood=float(filt.log_likelihood[b]),
                    particles=filt.particles[:n, b].cpu().numpy() if return_particles else None,
                    weights=torch.exp(log_w[:n, b]).cpu().numpy() if return_particles else None,
                    kind=kind,
                )
            )
        return out if multi else out[0]

    @with_thread_limit
    def smooth(self, u, y, *, return_particles: bool = False, x0=None, random_state=None):
        """Smoothed state distribution ``p(x_k | y_{0:N-1})`` at the fitted parameters.

        Parameters
        ----------
        u, y : array-like or lists of them
            As in :meth:`fit`.
        return_particles : bool, default=False
            Keep the particles and smoothing weights in the result (weighted quantile bands).
        x0 : array-like or "estimate", optional
            Prior mean of the first state (default ``x0_mean_``, covariance ``x0_cov_``), as in
            :meth:`predict`.
        random_state : int, optional
            Seed for this call; defaults to the estimator's ``random_state``.

        Returns
        -------
        StateEstimate or list of StateEstimate
            ``mean`` ``(N, nx)``, ``cov`` ``(N, nx, nx)``, ``outlier_weights`` ``(N,)``,
            ``interval(level)``, ``quantiles(q)``, ...
        """
        return self._state_estimates(u, y, "smoother", return_particles, random_state, x0)

    @with_thread_limit
    def filter(self, u, y, *, return_particles: bool = False, x0=None, random_state=None):
        """Filtered state distribution ``p(x_k | y_{0:k})`` at the fitted parameters.

        Same arguments and result type as :meth:`smooth`; the outlier weights use the filter
        weights.
        """
        return self._state_estimates(u, y, "filter", return_particles, random_state, x0)

    @with_thread_limit
    def log_likelihood(self, u, y, *, x0=None, random_state=None) -> float:
        """Particle estimate of ``log p(y | u)`` at the fitted parameters (summed over records);
        ``x0`` as in :meth:`smooth`."""
        device = self._check_fitted()
        data, _ = self._batch(u, y, device, fitted=True)
        model = self._fitted_model(device, x0, data, random_state)
        filt = self._filter(model, data, self._generator(device, random_state))
        return float(filt.log_likelihood.sum())

    def residual_analysis(
        self, u, y, *, max_lag: int = 25, horizon: int = 1, level: float = 0.99, robust: bool = True,
        random_state=None,
    ):
        """Whiteness and independence tests of the prediction errors, as MATLAB's ``resid``
        (:func:`torch_nssm.diagnostics.residual_analysis`; ``plotting.plot_residuals`` draws them)."""
        from .diagnostics import residual_analysis

        options = dict(max_lag=max_lag, horizon=horizon, level=level, robust=robust)
        return residual_analysis(self, u, y, random_state=random_state, **options)

    @with_thread_limit
    def initial_state(self, u, y, *, random_state=None):
        """The first state of a new record, estimated from its first outputs.

        A smoothing pass over the first ``INITIAL_SAMPLES`` samples from a broad prior (the fitted
        prior's covariance times 100, plus ``Rw_``); what ``x0="estimate"`` uses.

        Returns
        -------
        mean : ndarray of shape (nx,), or (n_records, nx) for a list of records
        cov : ndarray of shape (nx, nx), or (n_records, nx, nx)
        """
        device = self._check_fitted()
        data, multi = self._batch(u, y, device, fitted=True)
        model = self._fitted_model(device)
        mean, cov = self._estimate_initial_states(model, data, self._generator(device, random_state))
        mean, cov = mean.cpu().numpy(), cov.cpu().numpy()
        return (mean, cov) if multi else (mean[0], cov[0])


def fit_independent(
    estimator: RobustNSSMEstimator, u, y, *, show_progress: bool | None = None, n_jobs: int | None = None
) -> list:
    """Fit one copy of ``estimator`` to each data set, the E-steps of a chunk of data sets in one
    batched pass.

    Parameters
    ----------
    estimator : RobustNSSMEstimator
        The settings (``f``, ``g``, initial values, ``n_iter``, ``tol``, particles, ...) used for
        every data set; it is cloned, not changed.
    u : list of array-like (N_b,) or (N_b, nu), or None
        Inputs of each data set (``None`` for systems without input).
    y : list of array-like (N_b,) or (N_b, p)
        Outputs of each data set (NaN: missing).
    show_progress : bool, optional
        Progress bar over iterations (serial runs only); defaults to ``estimator.verbose > 0``.
    n_jobs : int, optional
        Workers (joblib): the data sets are split into as many chunks, each fitted as one batched
        pass on a worker; defaults to ``estimator.n_jobs`` (``None``: 1 unless a
        ``joblib.parallel_config`` context says otherwise; ``-1``: all cores).

    Returns
    -------
    list of RobustNSSMEstimator
        Fitted estimators, one per data set, each with its own parameters, ``history_``,
        ``n_iter_`` and ``converged_`` (a data set leaves the batch once it has converged).

    Raises
    ------
    WorkerLostError
        If a worker died (a crash, a memory limit): its ``results`` hold the fits that finished
        (``None`` for the lost data sets).

    Notes
    -----
    Each data set draws its random numbers from its own stream, seeded from ``(random_state,
    index of the data set)`` (:class:`~torch_nssm.inference.random.SequenceStreams`): its fit is
    the same whatever data sets it is batched with and whatever the number of workers or chunks.
    """
    device = estimator._check_params()
    if estimator.segment_length is not None:
        raise ValueError(
            "segment_length applies to fit (one model for all records); fit_independent runs each data "
            "set whole: set segment_length=None"
        )
    if estimator.acceleration is not None:
        raise ValueError(
            "acceleration applies to fit (one model); fit_independent runs plain EM: set acceleration=None"
        )
    if not V.is_sequence_list(y):
        raise ValueError("y must be a list of data sets (one array per data set)")
    n_sets = len(y)
    us = [None] * n_sets if u is None else list(u)
    if len(us) != n_sets:
        raise ValueError(f"u and y must hold the same number of data sets, got {len(us)} and {n_sets}")
    datas = []
    for b in range(n_sets):
        ub, yb, _ = V.as_sequence_list(us[b], y[b], dtype=estimator.dtype, device=device)
        datas.append(SequenceBatch.from_sequences(ub, yb))
    y_1d = [np.ndim(y[b]) == 1 for b in range(n_sets)]
    entropy = _entropy(estimator.random_state)
    n_jobs = estimator.n_jobs if n_jobs is None else n_jobs
    n_chunks = min(n_sets, _parallel.effective_n_jobs(n_jobs))
    chunks = [c.tolist() for c in np.array_split(np.arange(n_sets), n_chunks) if c.size]
    verbose = estimator.verbose > 0 if show_progress is None else show_progress
    if len(chunks) == 1:
        outcomes = _fit_chunk(estimator, datas, list(range(n_sets)), y_1d, entropy, device, verbose)
    else:
        tasks = [
            (estimator, [datas[b] for b in c], c, [y_1d[b] for b in c], entropy, device, False)
            for c in chunks
        ]
        try:
            parts = _parallel.run_tasks(_fit_chunk, tasks, n_jobs, f"fit_independent on {n_sets} data sets")
        except _parallel.WorkerLostError as exc:
            fits: list = [None] * n_sets
            for c, part in zip(chunks, exc.results):
                for b, outcome in zip(c, part or []):
                    fits[b] = outcome[0]
            lost = [b for i in exc.lost for b in chunks[i]]
            raise _parallel.WorkerLostError(
                f"{exc} (data sets {_ranges(lost)} are lost; the {n_sets - len(lost)} finished fits are in "
                "this error's `results`, None for the lost ones; each data set's fit depends on its "
                "random_state and its index only, so a rerun of the whole study gives the same fits)",
                fits,
                lost,
            ) from exc
        outcomes = [o for part in parts for o in part]
    estimators = [o[0] for o in outcomes]
    n_unconverged = n_rejected = 0
    first_rejection = None
    for b, (_, error, rejection, has_estep, converged, _) in enumerate(outcomes):
        if error is not None:
            warnings.warn(f"data set {b}: {error}", stacklevel=2)
        if rejection is not None:
            n_rejected += 1
            first_rejection = first_rejection or rejection
        if not has_estep:
            raise NumericalError(f"data set {b}: {error}")
        n_unconverged += not converged
    if n_rejected:
        warnings.warn(
            f"{n_rejected} of {n_sets} fits had rejected M-steps; the first: {first_rejection}",
            RuntimeWarning,
            stacklevel=2,
        )
    if outcomes and outcomes[0][5]:
        warnings.warn(
            "fit_independent interrupted (KeyboardInterrupt): each fit holds its last completed iteration",
            RuntimeWarning,
            stacklevel=2,
        )
    elif n_unconverged and estimator.tol > 0 and estimator.n_iter > 0:
        warnings.warn(
            f"{n_unconverged} of {n_sets} fits did not converge in n_iter={estimator.n_iter} iterations",
            ConvergenceWarning,
            stacklevel=2,
        )
    return estimators


def _fit_chunk(
    estimator: RobustNSSMEstimator,
    datas: list[SequenceBatch],
    indices: list[int],
    y_1d: list[bool],
    entropy: int,
    device: torch.device,
    progress: bool,
) -> list[tuple]:
    """Fit the data sets ``indices`` (``datas``) as one batched EM pass (on a worker or here).

    Returns, per data set, ``(fitted estimator, error, rejection message, has an E-step, converged,
    interrupted)``: the caller raises the warnings and errors of the whole study.
    """
    models, estimators = [], []
    with limited_threads(estimator.n_threads):
        for data_b, b in zip(datas, indices):
            est_b = clone(estimator)
            if isinstance(estimator.random_state, (int, np.integer)):
                est_b.random_state = int(estimator.random_state) + b
            estimators.append(est_b)
            start = est_b._initial_model(data_b, device)
            if est_b._runs_first_stage(start):  # per data set, before the batched EM
                start = est_b._first_stage(start, data_b)[0]
            models.append(start)
        all_data = SequenceBatch.from_sequences([d.u[:, 0] for d in datas], [d.y[:, 0] for d in datas])
        n = len(indices)
        options = estimator._em_options(f"robust EM x{n}")
        options.progress = f"robust EM x{n}" if progress else None
        streams = SequenceStreams([sequence_seed(entropy, b) for b in indices], device)
        options.mstep.solver.generator = streams  # each data set's minibatch orders from its stream
        results = run_em(models, all_data, options, streams, shared=False)
    outcomes = []
    for j, (est_b, run) in enumerate(zip(estimators, results)):
        rejection = est_b._rejection_message(run)
        if run.estep is not None:
            # the stored E-step is padded like the batch (lengths kept)
            est_b._store(
                run.model, run.history, run.estep, all_data.select(slice(j, j + 1)), False, run.n_done,
                run.converged, y_1d=y_1d[j],
            )
        outcomes.append((est_b, run.error, rejection, run.estep is not None, run.converged, run.interrupted))
    return outcomes


def _ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5]`` as ``"0-2, 5"``."""
    parts, start = [], None
    for i, b in enumerate(indices):
        if start is None:
            start = b
        if i + 1 == len(indices) or indices[i + 1] != b + 1:
            parts.append(str(start) if start == b else f"{start}-{b}")
            start = None
    return ", ".join(parts)


def _entropy(random_state) -> int:
    """One integer that seeds a whole study (drawn once, in the caller's process)."""
    if random_state is None:
        return int(np.random.SeedSequence().entropy % (2**63))
    if isinstance(random_state, (int, np.integer)):
        return int(random_state)
    return int(check_random_state(random_state).randint(0, 2**31 - 1))


def _restart_seeds(random_state, n_runs: int) -> list[int]:
    """The seed of each EM run: run 0 the estimator's own (the one ``_generator()`` draws), run
    ``r > 0`` the ``r``-th of a sequence drawn up front, so that run ``r`` depends on
    ``random_state`` and ``r`` alone (not on how many draws the earlier restarts' jitter needed)."""
    rs = check_random_state(random_state)
    first = int(rs.randint(0, 2**31 - 1))
    return [first] + [int(v) for v in rs.randint(0, 2**31 - 1, size=n_runs - 1)]


def _restart(
    estimator: RobustNSSMEstimator,
    base: StateSpaceModel,
    data: SequenceBatch,
    r: int,
    seed: int,
    limit: float,
    device: torch.device,
    progress: bool,
    fit_Rw: bool | None = None,
) -> EMResult:
    """EM run ``r`` of :meth:`RobustNSSMEstimator.fit` (here or on a worker): run 0 from ``base``,
    the others from a jittered copy, all randomness from ``seed`` (``fit_Rw`` overrides the
    estimator's)."""
    n_runs = estimator.n_init
    with limited_threads(estimator.n_threads):
        rs = np.random.RandomState(seed)
        if r == 0:  # the particle seed of a single fit, as before restarts existed
            generator = torch.Generator(device=device).manual_seed(seed)
        else:
            generator = _seeded_generator(device, rs)
        if r == 0:
            start = _copy_model(base)
        else:
            start = _stable_jitter(base, estimator.init_jitter, rs, data, limit)
        desc = "robust EM" if n_runs == 1 else f"robust EM (run {r + 1}/{n_runs})"
        options = estimator._em_options(desc, fit_Rw=fit_Rw)
        if not progress:
            options.progress = None
        return run_em([start], data, options, generator)[0]


def _seeded_generator(device: torch.device, rs: np.random.RandomState) -> torch.Generator:
    gen = torch.Generator(device=device)
    gen.manual_seed(int(rs.randint(0, 2**31 - 1)))
    return gen


def _copy_model(model: StateSpaceModel) -> StateSpaceModel:
    return replace(model, f=copy.deepcopy(model.f), g=copy.deepcopy(model.g))


#: Tuning constant of the Cauchy weights (95 % efficiency at the normal).
CAUCHY_TUNING = 2.385

#: Window of the first stage's multiple shooting (samples).
FIRST_STAGE_WINDOW = 50

#: ``first_stage="auto"`` keeps the first stage only when its noise-free simulation explains at
#: least this share of ``y`` (robust R²): a simulation model.  Below it the process noise dominates.
SIMULATION_R2_FLOOR = 0.5

#: How much worse than the first stage's (robust scale of the training free-run errors) EM may
#: leave the simulation before ``fit_Rw="auto"`` holds the process noise.
SIMULATION_TOLERANCE = 1.1


def _free_run_scale(outputs: torch.Tensor, data: SequenceBatch) -> float:
    """Robust scale (1.4826 MAD about 0) of the free run's output errors on the observed samples."""
    yt = torch.cat(data.unpad(data.y)).cpu().numpy()
    err = (yt - torch.cat(data.unpad(outputs)).cpu().numpy())[np.isfinite(yt)]
    return float(robust_scale(err, axis=None, center=0.0)) if err.size else math.nan


def _first_windows(data: SequenceBatch, window: int) -> list[int]:
    """Index, among all windows, of each record's first window (as the first stage orders them)."""
    out, i = [], 0
    for n in data.lengths.tolist():
        out.append(i)
        i += sum(1 for s in range(0, n, window) if min(s + window, n) - s >= 2)
    return out


#: Samples of a new record from which ``x0="estimate"`` / :meth:`RobustNSSMEstimator.initial_state`
#: estimate its first state.
INITIAL_SAMPLES = 50

#: A fitted dof below this (tails heavier than Cauchy's), or more than DOWNWEIGHTED_SHARE of the
#: samples with an outlier weight below 0.5, is reported: the noise model may be absorbing model
#: error (genuinely Cauchy noise down-weights about a third of the samples).
DOF_FLOOR = 1.0
DOWNWEIGHTED_SHARE = 0.4


def _noise_absorbing_message(dof, weights) -> str | None:
    """Words for a fit whose noise model explains too much (``None`` if it does not)."""
    ws = weights if isinstance(weights, list) else [weights]
    w = np.concatenate([np.asarray(a, dtype=float).reshape(-1) for a in ws])
    w = w[np.isfinite(w)]
    share = float(np.mean(w < 0.5)) if w.size else 0.0
    low = np.min(np.atleast_1d(dof)) < DOF_FLOOR
    if not low and share <= DOWNWEIGHTED_SHARE:
        return None
    return (
        f"the measurement noise absorbs much of the data: dof {np.round(np.atleast_1d(dof), 2).tolist()}, "
        f"{100 * share:.0f} % of the samples have an outlier weight below 0.5. Unless the sensor "
        "noise really is that heavy-tailed, the noise model is absorbing what f and g cannot explain "
        "(model error, not outliers): check the residuals (torch_nssm.diagnostics), raise the lower "
        "dof bound (dof_bounds=(2.0, 1000.0)) or hold it (fit_dof=False), or improve the model"
    )


#: Below this robust R² of the smoothed outputs against ``y``, a fit is reported as explaining nothing.
EXPLAINED_FLOOR = 0.05


@torch.no_grad()
def _explained_fraction(
    run: EMResult, data: SequenceBatch, free_run_outputs: torch.Tensor
) -> tuple[float, float]:
    """Robust R² against ``y`` of the smoothed outputs ``sum_l W_{k|N}^l g(x_k^l, u_k)`` and of the
    noise-free simulation (NaN scores count as explained: nothing to report)."""
    est = run.estep
    g = run.model.observation_steps(est.filter.particles, data.u)  # (T, B, L, p)
    w = torch.softmax(est.smoother.log_weights, dim=-1).unsqueeze(-1)
    yt = torch.cat(data.unpad(data.y)).cpu().numpy()
    scores = []
    for y_hat in ((w * g).sum(2), free_run_outputs):
        score = robust_r2_score(yt, torch.cat(data.unpad(y_hat)).cpu().numpy())
        scores.append(score if np.isfinite(score) else 1.0)
    return scores[0], scores[1]


def _divergence_limit(model: StateSpaceModel, data: SequenceBatch, warn: bool) -> float:
    """How far a restart's simulation may go before it counts as diverging: 1e3 times the larger of
    the start's own free-run range and the prior's scale.  With ``warn``, a start whose own
    simulation leaves every finite bound (1e6 times that scale) is named in a warning."""
    states, _ = prediction.free_run(model, data.u[:1000])
    finite = states[torch.isfinite(states)]
    prior = float(model.x0_mean.abs().max() + model.x0_cov.diagonal().sqrt().max())
    own = float(finite.abs().max()) if finite.numel() else 0.0
    scale = max(1.0, prior, own if own < 1e6 else 0.0)
    step = prediction.first_divergent_step(states, 1e6 * scale) if warn else None
    if step is not None:
        warnings.warn(
            f"the noise-free simulation of f from x0_mean diverges at step {step} with the initial "
            "parameters (the state leaves every finite bound): start from values for which f is "
            "stable, or EM may fail with non-finite updates",
            RuntimeWarning,
            stacklevel=4,
        )
    return 1e3 * scale


def _stable_jitter(
    base: StateSpaceModel, scale: float, rs: np.random.RandomState, data: SequenceBatch, limit: float
) -> StateSpaceModel:
    """A jittered restart whose noise-free simulation stays bounded (up to 20 draws; the last draw
    if none does, with a warning)."""
    for _ in range(20):
        start = _jittered(base, scale, rs)
        if prediction.divergence(start, data.u, limit) is None:
            return _g_fitted_to_y(start, data)
    warnings.warn(
        f"no jittered restart (init_jitter={scale}) gave a stable simulation of f in 20 draws; "
        "lower init_jitter",
        RuntimeWarning,
        stacklevel=4,
    )
    return start


@torch.no_grad()
def _g_fitted_to_y(model: StateSpaceModel, data: SequenceBatch, n_reweight: int = 3) -> StateSpaceModel:
    """For a ``g`` linear in its parameters: its free parameters refitted to ``y`` along the noise-free
    simulation of ``f`` (robust least squares, Cauchy weights), so that a restart's ``g`` has the
    scale of the data whatever the jitter drew.  Other modules are left as drawn."""
    g = model.g
    if not isinstance(g, LinearInParameters) or not bool(g.free_mask().any()):
        return model
    states, _ = prediction.free_run(model, data.u)
    mask = data.obs_mask  # (T, B, p)
    x, u, y = states[mask.any(-1)], data.u[mask.any(-1)], data.y[mask.any(-1)]
    m = mask[mask.any(-1)].to(y.dtype)
    precision = torch.diag_embed(m)  # missing components carry no weight
    weight = torch.ones(y.shape[0], dtype=y.dtype, device=y.device)
    backup = copy.deepcopy(g.state_dict())
    for _ in range(n_reweight + 1):
        g.solve_weighted_least_squares(x, u, y, weight, precision)
        r = torch.nan_to_num(y - g(x, u)) * m
        size = r.abs().sum(-1)
        scale = MAD_TO_STD * float(torch.median(size)) + 1e-300  # robust scale about 0
        weight = 1.0 / (1.0 + (size / (CAUCHY_TUNING * scale)) ** 2)  # Cauchy IRLS weights
    if not all(bool(torch.isfinite(p).all()) for p in g.parameters()):
        g.load_state_dict(backup)
    return model


def _jittered(model: StateSpaceModel, scale: float, rs: np.random.RandomState) -> StateSpaceModel:
    """A copy whose free module parameters are multiplied by ``exp(scale * N(0, 1))``."""
    new = _copy_model(model)
    with torch.no_grad():
        for module in (new.f, new.g):
            for p in module.parameters():
                if p.requires_grad:
                    eps = torch.from_numpy(rs.standard_normal(tuple(p.shape))).to(p)
                    p.mul_(torch.exp(scale * eps))
    return new


def default_rv_init(y: np.ndarray) -> torch.Tensor:
    """Default initial ``diag(Rv)``: ``0.02`` times a robust variance of each output column."""
    s2 = robust_scale(y, axis=0) ** 2
    var = np.where(s2 > 0, s2, np.nanvar(y, axis=0))
    return torch.from_numpy(0.02 * np.where(var > 0, var, 1.0))


def _check_data_against_model(data: SequenceBatch, f: nn.Module, g: nn.Module, nu: int, p: int) -> None:
    """Contradictions between the data and the model that would fit nonsense without a word."""
    for label, module in (("f", f), ("g", g)):
        declared = getattr(module, "nu", None)
        if isinstance(declared, int) and declared != nu:
            raise ValueError(
                f"u has {nu} input column(s) but {label} ({type(module).__name__}) declares nu={declared}: "
                "pass the inputs the module was built for"
            )
    y = data.y
    for j in range(p):
        col = y[..., j][~torch.isnan(y[..., j])]
        if col.numel() > 1 and bool((col == col[0]).all()):
            raise ValueError(
                f"y{'' if p == 1 else f'[:, {j}]'} is constant ({float(col[0]):g} at every observed sample): "
                "there is nothing to identify"
            )
    n_obs = int(data.obs_mask.any(-1).sum())
    n_free = sum(int(q.numel()) for m in (f, g) for q in m.parameters() if q.requires_grad)
    if n_obs < 10 * max(n_free, 1):
        warnings.warn(
            f"only {n_obs} observed samples for {n_free} free parameters of f and g (plus the noise "
            "parameters): the estimates will be poorly determined; use a longer record",
            UserWarning,
            stacklevel=5,
        )


def _is_1d(y, multi: bool) -> bool:
    first = y[0] if multi else y
    return (first.dim() if isinstance(first, torch.Tensor) else np.asarray(first).ndim) == 1


def _error_message(run: EMResult) -> str:
    if run.estep is None or run.n_done == 0 and run.error and "could not start" in run.error:
        return run.error
    return f"{run.error}. The fitted attributes hold the last good parameters (after iteration {run.n_done})."
