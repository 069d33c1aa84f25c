"""The estimator's model state: its parameters and fitted attributes as model objects and back.

:class:`ModelState` is a mixin of :class:`~torch_nssm.RobustNSSMEstimator`: the validated data
as a batch (``_batch``), the initial model from the parameters (``_initial_model``), the fitted
attributes from a fit (``_store``) and the fitted model from them (``_fitted_model``), with the
first state of a new record (``_initial_states``, ``_estimate_initial_states``), and outputs shaped
like the ``y`` given to ``fit`` (``_outputs``).
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import replace

import numpy as np
import torch
from sklearn.exceptions import NotFittedError
from sklearn.utils import check_random_state

from . import _validation as V
from ._stats import robust_scale
from ._threads import limited_threads
from .core.model import SequenceBatch, StateSpaceModel
from .core.noise import MeasurementNoise, NoiseSpec, symmetric_pd
from .estimation.estep import e_step, latent_scales, outlier_weights
from .estimation.start import seeded_generator, state_spread
from .inference import prediction
from .inference.ffbsm import smoothed_moments
from .inference.filtering import particle_filter
from .inference.results import StateEstimate
from .metrics import robust_r2_score

__all__ = ["ModelState", "INITIAL_SAMPLES", "default_rv_init"]

#: Samples of a new record from which ``x0="estimate"`` / :meth:`RobustNSSMEstimator.initial_state`
#: estimate its first state.
INITIAL_SAMPLES = 50


class ModelState:
    """The conversions between a :class:`~torch_nssm.RobustNSSMEstimator`'s parameters or fitted
    attributes and :class:`~torch_nssm.core.model.StateSpaceModel` objects."""

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
        V.check_data_against_model(data, f, g, nu, p)
        V.check_module_shapes(f, g, nx, nu, p, **kw)
        noise = self._noise_spec().initial(Rv)
        return StateSpaceModel(f, g, Rw, noise, x0_mean, x0_cov)


    def _store(self, model, history, estep, data, multi, n_done, converged, *, y_1d=False) -> None:
        self.f_ = model.f
        self.g_ = model.g
        self.Rw_ = model.Rw.detach().cpu().numpy()
        noise = model.noise.attributes()  # Rv_, dof_, ...: the noise family's
        for name in set(self.__dict__.get("_noise_attributes", ())) - set(noise):
            self.__dict__.pop(f"{name}_", None)  # another family's, from an earlier fit
        for name, value in noise.items():
            setattr(self, f"{name}_", value)
        self._noise_attributes = tuple(noise)
        self.x0_mean_ = model.x0_mean.detach().cpu().numpy()
        self.x0_cov_ = model.x0_cov.detach().cpu().numpy()
        self.history_ = {k: np.asarray(v) for k, v in history.items()}
        # whether the fit estimated the process noise (``fit`` sets it first: "auto" may hold it)
        self.fit_Rw_ = bool(self.__dict__.get("fit_Rw_", self.fit_Rw))
        per_component = model.noise.per_component
        ow = outlier_weights(estep.smoother.log_weights, estep.e_lam, data, per_component=per_component)
        self.outlier_weights_ = ow if multi else ow[0]
        self.outlier_threshold_ = model.noise.outlier_threshold(ow)
        flags = [np.isfinite(w) & (w < self.outlier_threshold_) for w in ow]
        self.outliers_ = flags if multi else flags[0]
        self.log_likelihood_ = float(estep.log_likelihood.sum())
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


    def _fitted_model(
        self, device, x0=None, data: SequenceBatch | None = None, random_state=None
    ) -> StateSpaceModel:
        """The fitted model on ``device``, with copies of the fitted modules, starting at ``x0``
        (see :meth:`_initial_states`)."""
        kw = dict(dtype=self.dtype, device=device)
        t = lambda a: torch.as_tensor(a, **kw)  # noqa: E731
        model = StateSpaceModel(
            copy.deepcopy(self.f_).to(**kw),
            copy.deepcopy(self.g_).to(**kw),
            t(self.Rw_),
            self._fitted_noise(device),
            t(self.x0_mean_),
            t(self.x0_cov_),
        )
        if x0 is None:
            return model
        mean, cov = self._initial_states(model, data, x0, random_state)
        return replace(model, x0_mean=mean, x0_cov=cov)

    def _noise_spec(self) -> NoiseSpec:
        """The measurement noise's specification (:func:`~torch_nssm._parameters.noise_of`)."""
        from ._parameters import noise_of

        return noise_of(self)

    def _fitted_noise(self, device="cpu") -> MeasurementNoise:
        """The fitted measurement noise on ``device``: its family's parameters from the fitted
        attributes ``<name>_``."""
        spec = self._noise_spec()
        kw = dict(dtype=self.dtype, device=device)
        names = spec.noise_model.CORE_DIMS
        return spec.state(**{n: torch.as_tensor(getattr(self, f"{n}_"), **kw) for n in names})

    def _initial_states(self, model: StateSpaceModel, data: SequenceBatch, x0, random_state=None) -> tuple:
        """Prior mean and covariance of the first state of each record of ``data`` for ``x0``:
        ``"estimate"`` (from the record's first outputs), values ``(nx,)``, ``(B, nx)`` or a list
        of ``(nx,)`` (their covariance: the fitted ``x0_cov_``), or the pair ``(mean, cov)`` that
        :meth:`initial_state` returns (``cov`` ``(nx, nx)`` or ``(B, nx, nx)``)."""
        B, nx = data.n_sequences, model.state_dim
        if isinstance(x0, str):
            if x0 != "estimate":
                raise ValueError(
                    f"x0 must be 'estimate' or an array of shape ({nx},) or ({B}, {nx}), got {x0!r}"
                )
            return self._estimate_initial_states(model, data, self._generator(data.y.device, random_state))
        kw = dict(dtype=self.dtype, device=data.y.device)
        cov = None
        if _is_mean_cov_pair(x0):
            x0, cov = x0
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
        if cov is None:
            return values, model.per_sequence("x0_cov", B)
        return values, _initial_covariances(cov, B, nx, **kw)

    def _estimate_initial_states(self, model: StateSpaceModel, data: SequenceBatch, generator) -> tuple:
        """Smoothed distribution of each record's first state given its first ``INITIAL_SAMPLES``
        outputs, from a broad prior: the fitted prior's covariance times 100, plus ``Rw``, plus
        the variance of each state along the model's free run of the record (the fitted prior
        describes the training records' first state, which can pin it far more tightly than a new
        record's start is known)."""
        if not bool(data.obs_mask.any()):
            raise ValueError("x0='estimate' needs the measured outputs y of the record(s)")
        n = min(data.n_steps, INITIAL_SAMPLES)
        head = SequenceBatch(data.u[:n], data.y[:n], data.lengths.clamp(max=n))
        wide = 100.0 * model.x0_cov + model.Rw
        # this record's spread; a state whose free run is not finite or does not move adds nothing
        spread = state_spread(replace(model, x0_cov=torch.zeros_like(wide)), data)
        broad = replace(model, x0_cov=wide + spread)
        estep = self._e_step(broad, head, generator)
        mean, cov = smoothed_moments(estep.filter.particles[:1], estep.smoother.log_weights[:1])
        eye = torch.eye(model.state_dim, dtype=cov.dtype, device=cov.device)
        return mean[0], symmetric_pd(cov[0] + 1e-9 * eye)

    def _outputs(self, values: torch.Tensor, data: SequenceBatch, multi: bool):
        """Time-major ``(T, B, p)`` outputs as arrays shaped like ``y`` (a list for records)."""
        out = [a.detach().cpu().numpy() for a in data.unpad(values)]
        if getattr(self, "_y_1d", False):
            out = [a[:, 0] for a in out]
        return out if multi else out[0]


    def _generator(self, device: torch.device, random_state=None) -> torch.Generator:
        rs = check_random_state(self.random_state if random_state is None else random_state)
        return seeded_generator(device, rs)

    def _store_run(self, run, *, data, multi, warm: bool, y_1d: bool, init_lls) -> None:
        history = run.history
        if warm:  # continue the previous trajectories; index 0 of this run repeats their end
            history = {k: list(self.history_[k]) + list(v[1:]) for k, v in history.items()}
        self._store(run.model, history, run.estep, data, multi, run.n_done, run.converged, y_1d=y_1d)
        self.init_log_likelihoods_ = init_lls

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
                estep_out = self._e_step(model, data, self._generator(data.y.device))
                self._uncertainty = observed_information(
                    model, data, estep_out, fit_Rw=self.fit_Rw_, fit_Rv=bool(self.fit_Rv),
                    generator=self._generator(data.y.device),
                )
            self._uncertainty_source = None
        for message in self._uncertainty.warnings() if warn else ():
            warnings.warn(message, RuntimeWarning, stacklevel=3)
        return self._uncertainty

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        if "f_" in self.__dict__ and "fit_Rw_" not in self.__dict__:
            self.fit_Rw_ = bool(self.fit_Rw)  # a fit pickled before ``fit_Rw_`` existed

    def _e_step(self, model, data, generator):
        """The E-step at the final particle count (``smooth``, outlier weights)."""
        options = self._em_options()
        estep = options.estep
        estep.n_particles = options.n_particles(None)
        return e_step(model, data, estep, generator)

    def _filter(self, model, data, generator):
        """The particle filter at the final particle count (``filter``, ``predict`` with a horizon)."""
        return particle_filter(
            model,
            data,
            self._em_options().n_particles(None),
            resampling=self.resampling,
            ess_threshold=self.ess_threshold,
            generator=generator,
        )

    def _check_fitted(self) -> torch.device:
        if not hasattr(self, "f_"):
            raise NotFittedError(
                f"This {type(self).__name__} instance is not fitted yet: call fit(u, y) first"
            )
        return V.check_device(self.device)

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

    def _state_estimates(self, u, y, kind: str, return_particles: bool, random_state, x0=None):
        device = self._check_fitted()
        data, multi = self._batch(u, y, device, fitted=True)
        model = self._fitted_model(device, x0, data, random_state)
        gen = self._generator(device, random_state)
        if kind == "smoother":
            estep_out = self._e_step(model, data, gen)
            filt, log_w, e_lam = estep_out.filter, estep_out.smoother.log_weights, estep_out.e_lam
        else:
            filt = self._filter(model, data, gen)
            log_w, e_lam = filt.log_weights, latent_scales(model, data, filt)[0]
        ow = outlier_weights(log_w, e_lam, data, per_component=model.noise.per_component)
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

    def _score_outputs(
        self, data: SequenceBatch, pred: torch.Tensor, sample_weight, multi: bool, robust: bool
    ):
        """:meth:`score` of the predictions ``pred`` ``(T, B, p)`` of ``data``'s outputs."""
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
        from sklearn.metrics import r2_score  # here: importing sklearn.metrics loads ~60 modules

        scores = []
        for j in range(yt.shape[1]):
            m = ~np.isnan(yt[:, j])
            w = None if sw is None else sw[m]
            scores.append(r2_score(yt[m, j], yp[m, j], sample_weight=w))
        return float(np.mean(scores))


def default_rv_init(y: np.ndarray) -> torch.Tensor:
    """Default initial ``diag(Rv)``: ``0.02`` times a robust variance of each output column."""
    s2 = robust_scale(y, axis=0) ** 2
    var = np.where(s2 > 0, s2, np.nanvar(y, axis=0))
    return torch.from_numpy(0.02 * np.where(var > 0, var, 1.0))


def _is_mean_cov_pair(x0) -> bool:
    """Whether ``x0`` is the pair ``(mean, cov)`` of :meth:`RobustNSSMEstimator.initial_state`: a
    tuple of two arrays, the second with one dimension more than the first."""
    if not isinstance(x0, tuple) or len(x0) != 2:
        return False
    try:
        mean_dim, cov_dim = np.ndim(x0[0]), np.ndim(x0[1])
    except ValueError:  # ragged
        return False
    return mean_dim in (1, 2) and cov_dim == mean_dim + 1


def _initial_covariances(cov, B: int, nx: int, *, dtype, device) -> torch.Tensor:
    """The covariances ``(B, nx, nx)`` of the first states from ``cov`` ``(nx, nx)`` (every record)
    or ``(B, nx, nx)`` (one per record), each checked symmetric positive definite."""
    try:
        values = torch.as_tensor(np.asarray(cov, dtype=float), dtype=dtype, device=device)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"x0's covariance must be numbers of shape ({nx}, {nx}) or ({B}, {nx}, {nx})"
        ) from exc
    if values.shape == (nx, nx):
        values = values.expand(B, nx, nx)
    if tuple(values.shape) != (B, nx, nx):
        raise ValueError(
            f"x0 = (mean, cov): cov must have shape ({nx}, {nx}) or ({B}, {nx}, {nx}), "
            f"got {tuple(values.shape)}"
        )
    for b in range(B):
        V.check_covariance(values[b], "x0's covariance", nx, dtype=dtype, device=device)
    return values

