"""``RobustNSSMEstimator``: the scikit-learn style front of the robust EM method.

The estimator checks its arguments (:mod:`torch_nssm._parameters`), plans the start of EM
(:mod:`torch_nssm.estimation.start`), runs EM (:mod:`torch_nssm.estimation.runs`, over
:func:`torch_nssm.estimation.loop.run_em`), stores what the runs returned as fitted attributes
(:mod:`torch_nssm._model_state`) and raises the warnings of the fit's report
(:mod:`torch_nssm.diagnostics.fit_warnings`); prediction and simulation go to
:mod:`torch_nssm.inference.prediction`.  :func:`fit_independent` (:mod:`torch_nssm.studies`) is the
same loop over many data sets at once.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from sklearn.base import BaseEstimator, RegressorMixin
from torch import nn

from . import _validation as V
from ._model_state import ModelState
from ._module_params import ModuleParams
from ._parameters import (
    check_parameters,
    em_options,
    em_runner,
    report_settings,
    resolved_segment_length,
    start_settings,
)
from ._threads import with_thread_limit
from .core.noise import NoiseSpec
from .diagnostics import fit_warnings
from .estimation.loop import EMOptions
from .estimation.runs import (
    FitReport,
    RunOutcome,
    best_run,
    first_stage_fallback,
    fit_runs,
    kept_outputs,
    last_good_run,
)
from .estimation.start import plan_start
from .inference import prediction
from .inference.filtering import NumericalError
from .studies import fit_independent

__all__ = ["RobustNSSMEstimator", "fit_independent"]



class RobustNSSMEstimator(ModelState, ModuleParams, RegressorMixin, BaseEstimator):
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
        Its covariance ``(nx, nx)`` (a scalar or vector means a diagonal).  If omitted: after a
        kept first stage, the variance of each state along its noise-free simulation (diagonal: a
        prior on the states' own scale); otherwise the identity.  EM estimates it (with
        ``fit_x0``; for a simulation model about the first state its first stage fitted).
    Rw_init : array-like, optional
        Initial process-noise covariance.  If omitted: a tenth of the variance of each state's
        change per step along the start's noise-free simulation (diagonal; ``0.1 * I`` where that
        is not finite or does not move).
    Rv_init : array-like, optional
        Initial measurement-noise scale matrix.  If omitted: for a simulation model the robust
        spread of the first stage's output errors, else ``0.02 * diag(s^2)``, ``s`` a robust
        spread (1.4826 MAD) of each output (docs/design.md, "How a fit starts").
    dof_init : float, default=5.0
        Initial degrees of freedom of the Student-t noise (one per output, or one for all, for
        ``"student-t-per-output"``): a shortcut for the family's option, see ``noise``.
    noise : str or noise specification, default="student-t"
        Measurement-noise model (docs/noise_models.md): ``"student-t"``, the multivariate Student-t
        (one outlier weight per sample); ``"gaussian"`` (the non-robust baseline, Gopaluni 2008);
        ``"student-t-per-output"`` (independent t per output with diagonal ``Rv`` and one ``dof``
        per output: a glitch in one sensor down-weights only that sensor); or a family registered
        with :func:`torch_nssm.noise.register_noise_model`.  A name takes its options from the
        shortcuts ``dof_init``, ``fit_dof`` and ``dof_bounds`` (families without degrees of
        freedom ignore them).  Or a specification object with its options, e.g.
        ``torch_nssm.noise.StudentT(dof=3.0, fit_dof=False)``, ``StudentTPerOutput(...)``,
        ``Gaussian()``; the shortcuts must then keep their defaults (``ValueError`` otherwise).
    fit_dof : bool, default=True
        Estimate the DOF; if False it stays at ``dof_init`` (a shortcut, see ``noise``).
    dof_bounds : (float, float), default=(0.1, 1000.0)
        Bracket of the DOF root-solve (a shortcut, see ``noise``).
    fit_Rw : bool or "auto", default="auto"
        Estimate the process-noise covariance; if False it stays at ``Rw_init`` (e.g. known from
        the physics).  ``"auto"`` is True (``focus`` decides what EM may do with ``f`` and ``g``).
    fit_Rv : bool, default=True
        Estimate the measurement-noise scale matrix; if False it stays at ``Rv_init``.
    fit_x0 : bool, default=True
        Re-estimate the initial-state prior from the smoothed first state (its covariance is
        floored by ``Rw`` so that it cannot collapse on a single record); a simulation model
        (``simulation_model_``) keeps its first stage's first state and re-estimates the
        covariance about it.
    n_particles : int, default=200
        Number of particles ``L``.
    n_particles_final : int, optional
        The particle count grows geometrically from ``n_particles`` to this at iteration
        ``n_iter``; the final E-step and later ``smooth``/``predict`` calls use it.
    average_last : int, default=0
        If > 1, the fitted parameters are the average of the last ``average_last`` iterates
        (Polyak-Ruppert); the final E-step runs at the averaged parameters.
    acceleration : {"squarem", "newton", None}, default="squarem"
        ``"squarem"``: the noise parameters (``Rw`` and the measurement noise's) jump along their
        own EM path by squared extrapolation (SQUAREM) where it moves steadily, at no extra cost
        (single fits; EM converges in the noise parameters at a slow linear rate).  ``None``: plain
        EM (the paper's algorithm).
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
        EM with particles is stochastic: it has converged when, over the last 5 iterations, neither
        the log-likelihood estimate (by more than ``tol`` per observation and iteration) nor any
        parameter (beyond a relative ``max(tol, 1e-4)``, or a standard error for the noise
        parameters) drifts more than its iteration-to-iteration jitter explains
        (:func:`torch_nssm.estimation.convergence.has_converged`).  ``0`` runs all ``n_iter``
        iterations without a :class:`~sklearn.exceptions.ConvergenceWarning`.
    n_init : int, default=1
        Number of EM runs; the one with the highest final log-likelihood estimate is kept.  Run 0
        starts from ``f`` and ``g`` as given, run ``r > 0`` from their free parameters times
        ``exp(init_jitter * N(0, 1))`` (signs and zeros kept; redrawn until ``f``'s noise-free
        simulation stays bounded), with ``g`` refitted to ``y`` along that simulation (robust least
        squares, for ``g`` linear in its parameters) and its own particle seed.
    init_jitter : float, default=1.0
        Standard deviation of the log-normal factor of the restarts (docs/design.md).
    first_stage : {"auto", "simulation", None}, default="auto"
        ``"simulation"``: before EM, fit ``f``, ``g`` and each record's first state by robust
        (Cauchy) simulation error, with windows that start short (from the outputs' correlation
        time) and grow until one covers each record, each stage judged by the free run of the whole
        records (:mod:`torch_nssm.estimation.first_stage`); EM starts at the best stage.
        ``first_stage_`` reports every stage.  Restarts (``n_init``) jitter around its result.
        When ``f`` or ``g`` holds a network layer, the neural first stage instead: the networks
        trained by robust simulation error over windows of doubling length, with an early stop on
        the held-out end of each record (:mod:`torch_nssm.estimation.neural_first_stage`; its
        options and report: :func:`~torch_nssm.simulation_start`); a grey box's physical
        parameters (free parameters of ``f`` outside its network layers) get the first stage
        above first, the network held.
        ``"auto"``: the same when ``n_iter > 0`` and ``f`` or ``g`` has free parameters, and EM
        starts there only if that free run explains at least half of ``y`` (robust R²; below it the
        process noise dominates).  ``None``: EM starts from the given values.  docs/design.md,
        "How a fit starts".
    focus : {"simulation", "prediction"}, default="simulation"
        What the model is for (MATLAB's ``Focus``).  ``"simulation"``: when the first stage's
        noise-free simulation explains at least 90 % of ``y`` (robust R²: a simulation model), EM
        keeps its ``f``, ``g`` and first state (the robust simulation-error fit simulates best)
        and estimates the noise around them: the process and measurement noise, the outlier
        weights and the first state's spread (``simulation_model_`` is True).
        ``"prediction"``, or a first stage that explains less (the process noise carries much of
        ``y``): EM estimates ``f`` and ``g`` too, the maximum-likelihood model, whose states may
        follow ``y`` through the process noise (for filtering and k-step-ahead prediction).
    warm_start : bool, default=False
        If True and the estimator is fitted, :meth:`fit` continues EM from the fitted parameters
        (``n_iter`` more iterations, one run whatever ``n_init``); ``history_`` is extended.  The
        new data must have the same numbers of inputs and outputs.
    optimizer : {"auto", "gauss-newton", "lbfgs", "adam"}, default="auto"
        Optimiser of the M-step for modules without a closed-form solve: ``"gauss-newton"``
        (Levenberg-Marquardt on the weighted residuals, a finite-difference Jacobian: for a few
        parameters, e.g. a physical model not linear in them), LBFGS, or Adam; ``"auto"``:
        Gauss-Newton for modules with at most 64 free parameters, else LBFGS.  Their regressions
        keep at most 32 of the smoother's particles per time step (drawn by systematic resampling
        of the smoothing weights).
    max_iter_mstep : int, default=20
        Gauss-Newton or LBFGS iterations (or Adam steps) per M-step.
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
    segment_length : int, "auto" or None, default="auto"
        Time-parallel E-step for long records: each record longer than this is cut into windows
        owning ``segment_length`` samples, with ``segment_overlap`` samples of burn-in before and
        look-ahead after, all filtered and smoothed as one batch; each window starts from the
        previous iteration's filter prediction at its first sample.  ``None``: one exact pass.
        ``"auto"``: windows of ``10 * segment_overlap`` samples for a fit whose longest record
        holds at least ten of them (10,000 samples by default), else the exact pass;
        ``segment_length_`` says what the fit used.  A few hundred to a few thousand samples;
        see docs/design.md ("Long records").
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
        ``inf`` for Gaussian noise; one per output for ``"student-t-per-output"``.  Each parameter
        of the noise family is a fitted attribute ``<name>_`` (``Rv_``, ``dof_``, ...).
    x0_mean_ : ndarray of shape (nx,)
    x0_cov_ : ndarray of shape (nx, nx)
    history_ : dict of str to ndarray
        Every parameter and the log-likelihood estimate at every iteration (index 0: the initial
        values), e.g. ``history_["f.a"]``, ``history_["Rv"]``, ``history_["log_likelihood"]``;
        ``history_["rejected.f"]``/``["rejected.g"]``: the iterations whose M-step of that module
        was undone (a warning says so).  With ``n_init > 1``: the kept run's.
    outlier_weights_ : ndarray of shape (N,) or (N, p), or list of them for several records
        ``E[lam_k | y]`` at the fitted parameters: near 0 marks an outlier, about 1 a regular
        sample, above 1 a small residual (up to ``(dof + p) / dof``); NaN where ``y_k`` is
        missing; per output for ``"student-t-per-output"``.
    outliers_, outlier_threshold_ : ndarray of bool shaped as ``outlier_weights_``; float or (p,)
        The flagged samples: weight below ``outlier_threshold_``, for Student-t noise
        ``(dof + p) / (dof + k chi2_p(0.999))``: a residual beyond the 99.9 % quantile of its
        Gaussian core, widened by ``k >= 1`` to the median of the samples' own distances
        (:func:`torch_nssm.core.noise.base.bulk_spread`); else 0.5.
    log_likelihood_ : float
        Particle estimate of the log-likelihood at the fitted parameters.
    first_stage_ : FirstStageReport, NeuralFirstStageReport or None
        What the first stage did (simulation errors before and after, whether it was kept, the
        free-run error scales after the first stage and after EM); ``None`` if it did not run.
    fit_Rw_ : bool
        Whether the fit estimated the process noise.
    simulation_model_ : bool
        Whether EM kept the first stage's ``f`` and ``g`` and estimated the noise around them (a
        simulation model with ``focus="simulation"``).
    segment_length_ : int or None
        The window length of the fit's time-parallel E-step (``None``: the exact pass).
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
        noise: str | NoiseSpec = "student-t",
        fit_dof: bool = True,
        dof_bounds: tuple[float, float] = (0.1, 1000.0),
        fit_Rw: bool | str = "auto",
        focus: str = "simulation",
        fit_Rv: bool = True,
        fit_x0: bool = True,
        n_particles: int = 200,
        n_particles_final: int | None = None,
        average_last: int = 0,
        acceleration: str | None = "squarem",
        n_iter: int = 100,
        tol: float = 1e-3,
        n_init: int = 1,
        init_jitter: float = 1.0,
        first_stage: str | None = "auto",
        warm_start: bool = False,
        optimizer: str = "auto",
        max_iter_mstep: int = 20,
        learning_rate: float = 1e-2,
        batch_size: int | None = None,
        smoother: str = "ffbsm",
        resampling: str = "systematic",
        ess_threshold: float = 1.0,
        chunk_size: int | None = None,
        smoother_options: dict | None = None,
        segment_length: int | str | None = "auto",
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
        self.focus = focus
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

    # ------------------------------------------------------------------ checks and set-up
    def _check_params(self) -> torch.device:
        return check_parameters(self)

    def _em_options(self, progress: str | None = None, *, fit_Rw: bool | None = None) -> EMOptions:
        """The EM loop's settings from the estimator's parameters (``fit_Rw`` overrides theirs)."""
        return em_options(self, progress, fit_Rw)

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
            If the particle weights underflow or an update is not finite in every EM run; the
            fitted attributes then hold the last good parameters.  After a kept first stage the
            fit instead keeps its start (the first stage's ``f`` and ``g`` with the starting noise
            parameters) and says so in a ``RuntimeWarning``.
        """
        device = self._check_params()
        warm = bool(self.warm_start) and hasattr(self, "f_")
        data, multi = self._batch(u, y, device, fitted=warm)
        base = self._fitted_model(device) if warm else self._initial_model(data, device)
        start = plan_start(base, data, start_settings(self, warm))  # first stage, divergence limit, seeds
        if not warm:
            self.first_stage_ = start.first_stage
        fit_warnings.warn_start(start, stacklevel=3)
        self.segment_length_ = resolved_segment_length(self, data)
        runner = em_runner(self, device, warm, start)
        if start.interrupted:  # Ctrl-C in the first stage: its best stage, evaluated, and no EM
            runner, start.seeds = runner.without_iterations(), start.seeds[:1]
        runs = fit_runs(runner, start, data, self.n_jobs)  # [(EMResult, start was stable)] per restart
        report = FitReport([RunOutcome.of(*run) for run in runs], report_settings(self), start=start)
        store = dict(data=data, multi=multi, warm=warm, y_1d=V.is_1d_record(y, multi))
        fallback = functools.partial(first_stage_fallback, runner, start, data)
        best = best_run(runs, report, fallback)  # or KeyboardInterrupt; None: every run failed
        if best is None:
            self._raise_numerical_error(runs, report, store)
        self.fit_Rw_ = self.fit_Rw_ if warm else bool(self.fit_Rw)
        self.simulation_model_ = runner.hold_modules
        outputs = kept_outputs(start, best, data, report)
        self._store_run(best, init_lls=report.init_log_likelihoods(), **store)
        report.describe_kept(best, data, outputs, self.outlier_weights_)
        fit_warnings.warn_fit(report, stacklevel=3)
        return self

    def _raise_numerical_error(self, runs: list, report: FitReport, store: dict):
        """Warn from the report of a fit whose every run failed, keep the last good parameters of
        the best run that has them as the fitted attributes, and raise :class:`NumericalError`."""
        fit_warnings.warn_fit(report, stacklevel=4)
        last = last_good_run(runs)
        if last is not None:
            self._store_run(last, init_lls=report.init_log_likelihoods(), **store)
        raise NumericalError(fit_warnings.error_message(report.outcomes[0]))

    # ------------------------------------------------------------------ standard errors
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
        x0 : array-like of shape (nx,) or (n_records, nx), pair, or "estimate", optional
            The first state of the record(s) (default: ``x0_mean_``, the *training* record's).
            ``(mean, cov)``: what :meth:`initial_state` returns (the free run starts at ``mean``;
            the filter's prior is ``N(mean, cov)``).  ``"estimate"``: from the record's first
            outputs (a smoothing pass over its first ``INITIAL_SAMPLES`` samples from a broad
            prior; needs ``y``, also for the free run).
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
        x0 : array-like, pair or "estimate", optional
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
        return self._score_outputs(data, pred, sample_weight, multi, robust)

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
        x0 : array-like of shape (nx,) or (n_records, nx), or pair, optional
            Mean of the first state (default ``x0_mean_``); its spread stays ``x0_cov_``, or is
            ``cov`` for the pair ``(mean, cov)`` that :meth:`initial_state` returns.

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

    @with_thread_limit
    def smooth(self, u, y, *, return_particles: bool = False, x0=None, random_state=None):
        """Smoothed state distribution ``p(x_k | y_{0:N-1})`` at the fitted parameters.

        Parameters
        ----------
        u, y : array-like or lists of them
            As in :meth:`fit`.
        return_particles : bool, default=False
            Keep the particles and smoothing weights in the result (weighted quantile bands).
        x0 : array-like, pair or "estimate", optional
            Prior mean of the first state (default ``x0_mean_``, covariance ``x0_cov_``), or the
            pair ``(mean, cov)`` of :meth:`initial_state`, as in :meth:`predict`.
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

    def compare(self, u, y, *, horizon: int | None = None, x0=None, robust: bool = False, random_state=None):
        """The predicted outputs of a record beside the measured ones, with the fit in percent per
        output, as MATLAB's ``compare`` (:func:`torch_nssm.evaluation.compare`;
        ``plotting.plot_compare`` draws it).  ``robust=True`` leaves out the samples flagged as
        outliers (smoothed outlier weight below 0.5)."""
        from .evaluation import compare

        options = dict(horizon=horizon, x0=x0, robust=robust, random_state=random_state)
        return compare(self, u, y, **options)

    @with_thread_limit
    def initial_state(self, u, y, *, random_state=None):
        """The first state of a new record, estimated from its first outputs.

        A smoothing pass over the first ``INITIAL_SAMPLES`` samples from a broad prior (the fitted
        prior's covariance times 100, plus ``Rw_``, plus each state's variance along the model's
        free run of this record); what ``x0="estimate"`` uses.  The pair goes
        back in as it is: ``predict(u, x0=est.initial_state(u, y))`` (also ``simulate``,
        ``smooth``, ``filter``, ``score``, ``compare``).

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

