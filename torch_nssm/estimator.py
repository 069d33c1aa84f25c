"""``RobustNSSMEstimator``: the scikit-learn style front of the robust EM method."""

from __future__ import annotations

import copy
import warnings
from collections import defaultdict

import numpy as np
import torch
from sklearn.base import BaseEstimator
from sklearn.exceptions import ConvergenceWarning, NotFittedError
from sklearn.utils import check_random_state
from torch import nn
from tqdm.auto import tqdm

from . import _validation as V
from .em import SMOOTHERS, EStepOutput, MStepOptions, e_step, m_step
from .filtering import NumericalError, particle_filter
from .model import SequenceBatch, StateSpaceModel
from .mstep import OPTIMIZERS
from .resampling import RESAMPLING_SCHEMES
from .results import StateEstimate
from .smoothing import smoothed_moments

__all__ = ["RobustNSSMEstimator"]

NOISE_MODELS = ("student-t", "gaussian")
#: Convergence compares the mean log-likelihood estimate of the last CONVERGENCE_WINDOW iterations
#: with that of the window before: single particle estimates are too noisy to compare.
CONVERGENCE_WINDOW = 5


class RobustNSSMEstimator(BaseEstimator):
    """Robust identification of a nonlinear state-space model by EM with a particle smoother.

    The model is ``x_{k+1} = f(x_k, u_k) + w``, ``w ~ N(0, Rw)`` and ``y_k = g(x_k, u_k) + v``
    with ``v ~ St(0, Rv, dof)`` (multivariate Student-t; ``noise="gaussian"`` for the Gaussian
    baseline).  The E-step runs a bootstrap particle filter and the FFBSm smoother; the M-step
    updates ``f``'s and ``g``'s parameters (closed form when the module offers
    ``solve_weighted_least_squares``, LBFGS or Adam otherwise), ``Rw``, ``Rv``, ``dof`` and the
    initial-state prior (Liu & Yang, Neurocomputing 2019, with the corrections of the method notes).

    Parameters
    ----------
    f : torch.nn.Module
        Transition mean ``f(x, u)``: ``x`` of shape ``(..., nx)``, ``u`` of shape ``(..., nu)``,
        returns ``(..., nx)``.  Its ``nn.Parameter`` s with ``requires_grad=True`` are estimated.
    g : torch.nn.Module
        Observation mean ``g(x, u)`` returning ``(..., p)``.
    x0_mean : array-like of shape (nx,)
        Mean of the prior of the first state (it also fixes ``nx``).
    x0_cov : array-like, optional
        Its covariance ``(nx, nx)`` (a scalar or vector means a diagonal); identity if omitted.
    Rw_init : array-like, optional
        Initial process-noise covariance; ``0.1 * I`` if omitted.
    Rv_init : array-like, optional
        Initial measurement-noise scale matrix; ``0.1 * diag(var(y))`` if omitted.
    dof_init : float, default=5.0
        Initial degrees of freedom of the Student-t noise.
    noise : {"student-t", "gaussian"}, default="student-t"
        Measurement-noise model; ``"gaussian"`` is the non-robust baseline (Gopaluni 2008).
    fit_dof : bool, default=True
        Estimate the DOF; if False it stays at ``dof_init``.
    dof_bounds : (float, float), default=(0.1, 1000.0)
        Bracket of the DOF root-solve.
    fit_x0 : bool, default=True
        Re-estimate the initial-state prior from the smoothed first state (its covariance is
        floored by ``Rw`` so that it cannot collapse on a single record).
    n_particles : int, default=200
        Number of particles ``L``.
    n_iter : int, default=100
        Maximum number of EM iterations.
    tol : float, default=1e-3
        Convergence threshold on the change of the per-observation log-likelihood estimate,
        averaged over windows of 5 iterations (EM with particles is stochastic).
    optimizer : {"lbfgs", "adam"}, default="lbfgs"
        Optimiser of the M-step for modules without a closed-form solve.
    max_iter_mstep : int, default=20
        LBFGS iterations (or Adam steps) per M-step.
    learning_rate : float, default=1e-2
        Adam's step size.
    smoother : {"ffbsm"}, default="ffbsm"
        Particle smoother of the E-step.
    resampling : {"systematic", "stratified", "residual", "multinomial"}, default="systematic"
    ess_threshold : float, default=1.0
        Resample when the effective sample size is below ``ess_threshold * n_particles``
        (1.0: at every step).
    chunk_size : int, optional
        Smoother chunk size (memory bound); automatic if omitted.
    random_state : int, RandomState or None
        Seed of the particle methods.
    device : str or torch.device, default="cpu"
    dtype : torch.dtype, default=torch.float64
    verbose : int, default=0
        Show a progress bar when > 0.

    Attributes
    ----------
    f_, g_ : torch.nn.Module
        Fitted copies of ``f`` and ``g`` (the modules passed in are not changed).
    Rw_ : ndarray of shape (nx, nx)
    Rv_ : ndarray of shape (p, p)
    dof_ : float
        ``inf`` for Gaussian noise.
    x0_mean_ : ndarray of shape (nx,)
    x0_cov_ : ndarray of shape (nx, nx)
    history_ : dict of str to ndarray
        Every parameter and the log-likelihood estimate at every iteration (index 0: the initial
        values), e.g. ``history_["f.a"]``, ``history_["Rv"]``, ``history_["log_likelihood"]``.
    outlier_weights_ : ndarray of shape (N,), or list of them for several records
        ``E[lam_k | y]`` at the fitted parameters: near 0 marks an outlier.
    log_likelihood_ : float
        Particle estimate of the log-likelihood at the fitted parameters.
    n_iter_ : int
        Number of EM iterations run.
    converged_ : bool
    n_states_, n_inputs_, n_outputs_ : int
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
        fit_x0: bool = True,
        n_particles: int = 200,
        n_iter: int = 100,
        tol: float = 1e-3,
        optimizer: str = "lbfgs",
        max_iter_mstep: int = 20,
        learning_rate: float = 1e-2,
        smoother: str = "ffbsm",
        resampling: str = "systematic",
        ess_threshold: float = 1.0,
        chunk_size: int | None = None,
        random_state=None,
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
        self.fit_x0 = fit_x0
        self.n_particles = n_particles
        self.n_iter = n_iter
        self.tol = tol
        self.optimizer = optimizer
        self.max_iter_mstep = max_iter_mstep
        self.learning_rate = learning_rate
        self.smoother = smoother
        self.resampling = resampling
        self.ess_threshold = ess_threshold
        self.chunk_size = chunk_size
        self.random_state = random_state
        self.device = device
        self.dtype = dtype
        self.verbose = verbose

    # ------------------------------------------------------------------ checks and set-up
    def _check_params(self) -> torch.device:
        V.check_choice(self.noise, "noise", NOISE_MODELS)
        V.check_choice(self.optimizer, "optimizer", OPTIMIZERS)
        V.check_choice(self.smoother, "smoother", SMOOTHERS)
        V.check_choice(self.resampling, "resampling", sorted(RESAMPLING_SCHEMES))
        V.check_positive(self.n_particles, "n_particles", integer=True, minimum=2, inclusive=True)
        V.check_positive(self.n_iter, "n_iter", integer=True, minimum=0, inclusive=True)
        V.check_positive(self.tol, "tol", minimum=0.0, inclusive=True)
        V.check_positive(self.max_iter_mstep, "max_iter_mstep", integer=True, minimum=1, inclusive=True)
        V.check_positive(self.learning_rate, "learning_rate")
        V.check_positive(self.dof_init, "dof_init")
        if not (isinstance(self.ess_threshold, (int, float)) and 0 <= self.ess_threshold <= 1):
            raise ValueError(f"ess_threshold must lie in [0, 1], got {self.ess_threshold!r}")
        lo, hi = self.dof_bounds
        if not 0 < lo < hi:
            raise ValueError(f"dof_bounds must satisfy 0 < low < high, got {self.dof_bounds!r}")
        if self.chunk_size is not None:
            V.check_positive(self.chunk_size, "chunk_size", integer=True, minimum=1, inclusive=True)
        if self.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {self.dtype!r}")
        if self.x0_mean is None:
            raise ValueError("x0_mean is required: it fixes the state dimension nx")
        return V.check_device(self.device)

    def _generator(self, device: torch.device, random_state=None) -> torch.Generator:
        rs = check_random_state(self.random_state if random_state is None else random_state)
        gen = torch.Generator(device=device)
        gen.manual_seed(int(rs.randint(0, 2**31 - 1)))
        return gen

    def _batch(self, u, y, device, *, fitted: bool) -> tuple[SequenceBatch, bool]:
        kw = dict(n_inputs=self.n_inputs_, n_outputs=self.n_outputs_) if fitted else {}
        us, ys = V.as_sequence_list(u, y, dtype=self.dtype, device=device, **kw)
        multi = V.is_sequence_list(y)
        return SequenceBatch.from_sequences(us, ys), multi

    def _initial_model(self, data: SequenceBatch, device) -> StateSpaceModel:
        kw = dict(dtype=self.dtype, device=device)
        x0_mean = V.check_vector(self.x0_mean, "x0_mean", None, **kw)
        nx, p, nu = x0_mean.numel(), data.y.shape[-1], data.u.shape[-1]
        x0_cov = V.check_covariance(1.0 if self.x0_cov is None else self.x0_cov, "x0_cov", nx, **kw)
        Rw = V.check_covariance(0.1 if self.Rw_init is None else self.Rw_init, "Rw_init", nx, **kw)
        if self.Rv_init is None:
            var = torch.from_numpy(np.nanvar(data.y.cpu().numpy().reshape(-1, p), axis=0)).to(**kw)
            Rv = torch.diag(0.1 * torch.where(var > 0, var, torch.ones_like(var)))
        else:
            Rv = V.check_covariance(self.Rv_init, "Rv_init", p, **kw)
        f = copy.deepcopy(self.f).to(**kw)
        g = copy.deepcopy(self.g).to(**kw)
        V.check_module_shapes(f, g, nx, nu, p, **kw)
        dof = torch.tensor(float("inf") if self.noise == "gaussian" else float(self.dof_init), **kw)
        return StateSpaceModel(f, g, Rw, Rv, dof, x0_mean, x0_cov)

    def _mstep_options(self) -> MStepOptions:
        return MStepOptions(
            optimizer=self.optimizer,
            max_iter=self.max_iter_mstep,
            learning_rate=self.learning_rate,
            fit_dof=self.fit_dof,
            dof_bounds=tuple(float(b) for b in self.dof_bounds),
            fit_x0=self.fit_x0,
        )

    def _e_step(self, model, data, generator) -> EStepOutput:
        return e_step(
            model, data, self.n_particles, smoother=self.smoother, resampling=self.resampling,
            ess_threshold=self.ess_threshold, chunk_size=self.chunk_size, generator=generator,
        )

    # ------------------------------------------------------------------ fitting
    def fit(self, u, y) -> RobustNSSMEstimator:
        """Estimate the model's parameters by robust EM.

        Parameters
        ----------
        u : array-like of shape (N,) or (N, nu), list of them, or None
            Inputs (``None`` for a system without input).  ``u_k`` drives ``x_k -> x_{k+1}``
            and enters ``g`` at time ``k``.
        y : array-like of shape (N,) or (N, p), or list of them
            Outputs; NaN marks a missing value (skipped by the filter).

        Returns
        -------
        self
        """
        device = self._check_params()
        data, multi = self._batch(u, y, device, fitted=False)
        model = self._initial_model(data, device)
        generator = self._generator(device)
        options = self._mstep_options()
        n_obs = int(data.obs_mask.any(-1).sum())
        history: dict[str, list] = defaultdict(list)
        lls: list[float] = []
        converged = False
        n_done = 0
        bar = tqdm(total=self.n_iter, desc="robust EM", disable=not self.verbose, leave=True)
        try:
            est = self._e_step(model, data, generator)
            for it in range(self.n_iter + 1):
                ll = float(est.log_likelihood.sum())
                _record(history, model, ll)
                lls.append(ll)
                if _converged(lls, n_obs, self.tol):
                    converged = True
                    break
                if it == self.n_iter:
                    break
                backup = (copy.deepcopy(model.f.state_dict()), copy.deepcopy(model.g.state_dict()))
                try:
                    model = m_step(model, data, est, options)
                except NumericalError as exc:
                    model.f.load_state_dict(backup[0])
                    model.g.load_state_dict(backup[1])
                    self._store(model, history, est, data, multi, n_done, False)
                    raise NumericalError(
                        f"EM stopped at iteration {it + 1}: {exc}. The fitted attributes hold the "
                        "last good parameters."
                    ) from exc
                n_done += 1
                est = self._e_step(model, data, generator)
                bar.update(1)
                bar.set_postfix(loglik=f"{est.log_likelihood.sum().item() / n_obs:.4f}/obs",
                                dof=f"{float(model.dof):.3g}")
        finally:
            bar.close()
        self._store(model, history, est, data, multi, n_done, converged)
        if not converged and self.tol > 0 and self.n_iter > 0:
            warnings.warn(
                f"EM did not converge in n_iter={self.n_iter} iterations (tol={self.tol}); "
                "raise n_iter or tol, or average the last iterates",
                ConvergenceWarning,
                stacklevel=2,
            )
        return self

    def _store(self, model, history, est, data, multi, n_done, converged) -> None:
        self.f_ = model.f
        self.g_ = model.g
        self.Rw_ = model.Rw.detach().cpu().numpy()
        self.Rv_ = model.Rv.detach().cpu().numpy()
        self.dof_ = float(model.dof)
        self.x0_mean_ = model.x0_mean.detach().cpu().numpy()
        self.x0_cov_ = model.x0_cov.detach().cpu().numpy()
        self.history_ = {k: np.asarray(v) for k, v in history.items()}
        ow = _masked_outlier_weights(est, data)
        self.outlier_weights_ = ow if multi else ow[0]
        self.log_likelihood_ = float(est.log_likelihood.sum())
        self.n_iter_ = n_done
        self.converged_ = converged
        self.n_states_ = model.state_dim
        self.n_inputs_ = data.u.shape[-1]
        self.n_outputs_ = data.y.shape[-1]

    # ------------------------------------------------------------------ using a fitted model
    def _check_fitted(self) -> None:
        if not hasattr(self, "f_"):
            raise NotFittedError(
                f"This {type(self).__name__} instance is not fitted yet: call fit(u, y) first"
            )

    def _fitted_model(self, device) -> StateSpaceModel:
        kw = dict(dtype=self.dtype, device=device)
        t = lambda a: torch.as_tensor(a, **kw)  # noqa: E731
        return StateSpaceModel(
            self.f_.to(**kw), self.g_.to(**kw), t(self.Rw_), t(self.Rv_), t(self.dof_),
            t(self.x0_mean_), t(self.x0_cov_),
        )

    def _state_estimates(self, u, y, kind: str, return_particles: bool, random_state):
        self._check_fitted()
        device = V.check_device(self.device)
        data, multi = self._batch(u, y, device, fitted=True)
        model = self._fitted_model(device)
        gen = self._generator(device, random_state)
        if kind == "smoother":
            est = self._e_step(model, data, gen)
            filt, log_w = est.filter, est.smoother.log_weights
            ow = _masked_outlier_weights(est, data)
        else:
            filt = particle_filter(
                model, data, self.n_particles, resampling=self.resampling,
                ess_threshold=self.ess_threshold, generator=gen,
            )
            log_w = filt.log_weights
            from .em import latent_scales

            e_lam, _ = latent_scales(model, data, filt)
            ow_all = (torch.exp(log_w) * e_lam).sum(-1)
            ow_all = torch.where(data.obs_mask.any(-1), ow_all, torch.full_like(ow_all, float("nan")))
            ow = [a.cpu().numpy() for a in data.unpad(ow_all)]
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

    def smooth(self, u, y, *, return_particles: bool = False, random_state=None):
        """Smoothed state distribution ``p(x_k | y_{0:N-1})`` at the fitted parameters.

        Parameters
        ----------
        u, y : array-like or lists of them
            As in :meth:`fit`.
        return_particles : bool, default=False
            Keep the particles and smoothing weights in the result (for quantile bands).
        random_state : int, optional
            Seed for this call; defaults to the estimator's ``random_state``.

        Returns
        -------
        StateEstimate or list of StateEstimate
            ``mean`` ``(N, nx)``, ``cov`` ``(N, nx, nx)``, ``outlier_weights`` ``(N,)``, ...
        """
        return self._state_estimates(u, y, "smoother", return_particles, random_state)

    def filter(self, u, y, *, return_particles: bool = False, random_state=None):
        """Filtered state distribution ``p(x_k | y_{0:k})`` at the fitted parameters.

        Same arguments and result type as :meth:`smooth`.
        """
        return self._state_estimates(u, y, "filter", return_particles, random_state)

    def log_likelihood(self, u, y, *, random_state=None) -> float:
        """Particle estimate of ``log p(y | u)`` at the fitted parameters (summed over records)."""
        self._check_fitted()
        device = V.check_device(self.device)
        data, _ = self._batch(u, y, device, fitted=True)
        filt = particle_filter(
            self._fitted_model(device), data, self.n_particles, resampling=self.resampling,
            ess_threshold=self.ess_threshold, generator=self._generator(device, random_state),
        )
        return float(filt.log_likelihood.sum())


def _masked_outlier_weights(est: EStepOutput, data: SequenceBatch) -> list[np.ndarray]:
    ow = est.outlier_weights
    ow = torch.where(data.obs_mask.any(-1), ow, torch.full_like(ow, float("nan")))
    return [a.detach().cpu().numpy() for a in data.unpad(ow)]


def _record(history: dict, model: StateSpaceModel, ll: float) -> None:
    history["log_likelihood"].append(ll)
    for label, module in (("f", model.f), ("g", model.g)):
        for name, p in module.named_parameters():
            history[f"{label}.{name}"].append(p.detach().cpu().numpy().copy())
    history["Rw"].append(model.Rw.detach().cpu().numpy())
    history["Rv"].append(model.Rv.detach().cpu().numpy())
    history["dof"].append(float(model.dof))
    history["x0_mean"].append(model.x0_mean.detach().cpu().numpy())


def _converged(lls: list[float], n_obs: int, tol: float) -> bool:
    w = CONVERGENCE_WINDOW
    if tol <= 0 or len(lls) < 2 * w:
        return False
    recent, before = np.mean(lls[-w:]), np.mean(lls[-2 * w : -w])
    return abs(recent - before) / max(n_obs, 1) < tol
