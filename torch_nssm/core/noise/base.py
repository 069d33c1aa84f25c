"""The measurement-noise protocol and the masked scale matrix shared by every noise family.

A noise family is one file with two classes:

* a *specification* (:class:`NoiseSpec`, a frozen dataclass of plain values): what the user passes
  as ``noise=`` -- the family, the initial values of its parameters other than ``Rv`` and its
  options (which parameters are estimated, their bounds);
* the *noise model* (:class:`MeasurementNoise`, a frozen dataclass of tensors, its parameters such
  as ``Rv`` and ``dof``, carrying its specification) with the methods that use them:

  - the filter's per-step log-density (:meth:`MeasurementNoise.evaluator`), its hot loop;
  - the E-step's latent-scale expectations (:meth:`~MeasurementNoise.latent_expectations`);
  - the M-step's sufficient statistics and closed-form update (:meth:`~MeasurementNoise.statistics`,
    :meth:`~MeasurementNoise.updated`);
  - sampling (:meth:`~MeasurementNoise.sample`) and a plain log-density (:meth:`~MeasurementNoise.log_prob`);
  - what the observed information needs (:meth:`~MeasurementNoise.residual_log_prob` on the working
    scales ``WORKING``, and optional closed forms of its scores and Hessian).

The registry (``core/noise/__init__.py``) maps a name to the noise model's class, whose ``SPEC``
is its specification.  Parameters may carry a leading batch dimension (one model per data set in
independent fits).  Missing output components are handled by masking the scale matrix
(:func:`masked_scale`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ..scales import LOG_CHOLESKY, WorkingScale

__all__ = [
    "MeasurementNoise",
    "NoiseSpec",
    "NoiseEvaluator",
    "MaskedScale",
    "masked_scale",
    "random_source",
    "step_views",
    "symmetric_pd",
]


@dataclass
class MaskedScale:
    """Scale matrix restricted to the observed components of each sample.

    Attributes
    ----------
    chol_inv : Tensor, shape (..., p, p)
        Inverse of the lower Cholesky factor of ``M R M + (I - M)``; ``chol_inv @ r`` whitens a
        residual ``r`` that is zero where missing.
    logdet : Tensor, shape (...)
        ``log det`` of the observed block of ``R``.
    n_obs : Tensor, shape (...)
        Number of observed components.
    mask : Tensor, shape (..., p), bool
        True where the component is observed.
    """

    chol_inv: Tensor
    logdet: Tensor
    n_obs: Tensor
    mask: Tensor

    def select(self, index) -> MaskedScale:
        """The scales of the sequences ``index`` (second dimension of time-major ``(T, B, ...)``)."""
        return MaskedScale(
            self.chol_inv[:, index], self.logdet[:, index], self.n_obs[:, index], self.mask[:, index]
        )

    def whitener(self) -> Tensor:
        """``chol_inv`` with zero columns at the missing components: applied to a residual whose
        missing entries are finite (see :meth:`fill_missing`), it needs no mask."""
        return self.chol_inv * self.mask.unsqueeze(-2).to(self.chol_inv.dtype)

    def precision(self) -> Tensor:
        """``R^-1`` on the observed block, zero rows and columns at the missing components."""
        m = self.mask.to(self.chol_inv.dtype)
        return (self.chol_inv.transpose(-1, -2) @ self.chol_inv) * m.unsqueeze(-1) * m.unsqueeze(-2)

    def fill_missing(self, y: Tensor) -> Tensor:
        """Outputs ``y`` (shape of the mask) with the missing entries set to 0."""
        return torch.where(self.mask, y, torch.zeros_like(y))


def masked_scale(R: Tensor, mask: Tensor) -> MaskedScale:
    """The per-sample scale of the observed components of ``R`` ``(..., p, p)`` under ``mask``."""
    m = mask.to(R.dtype)
    eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
    Rm = R * m.unsqueeze(-1) * m.unsqueeze(-2) + eye * (1.0 - m).unsqueeze(-1)
    if R.shape[-1] == 1 and bool((Rm > 0).all()):  # one output: the 1 x 1 Cholesky factor is the
        # square root and its inverse the reciprocal, the same values as LAPACK's (4x cheaper at
        # T = 1000, B = 100: 2 vs 8.5 ms per filter pass); a scale that is not positive goes
        # through cholesky below, which raises
        chol = torch.sqrt(Rm)
        chol_inv = torch.reciprocal(chol)
    else:
        chol = torch.linalg.cholesky(Rm)
        chol_inv = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    logdet = 2.0 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return MaskedScale(chol_inv=chol_inv, logdet=logdet, n_obs=m.sum(-1), mask=mask)


def step_views(values: Tensor) -> Sequence[Tensor]:
    """The views ``values[k]`` of every step ``k`` of a time-major ``values``, for a loop over the
    steps (indexing a list is free, a tensor select is an operation).

    Parameters
    ----------
    values : Tensor, shape (T, ...)

    Returns
    -------
    list or tuple of Tensor
        One view repeated ``T`` times (a list) when every step holds the same values (e.g. a
        whitener or a Student-t coefficient of records without missing outputs), else
        ``values.unbind(0)``.
    """
    if same_at_every_step(values):
        return [values[0]] * values.shape[0]
    return values.unbind(0)


def same_at_every_step(values: Tensor) -> bool:
    """Whether the time-major ``values`` ``(T, ...)`` (``T > 1``) hold the same values at every step."""
    return values.shape[0] > 1 and torch.equal(values, values[:1].expand_as(values))


def symmetric_pd(S: Tensor, jitter: float = 0.0) -> Tensor:
    """The symmetric part of ``S``, plus ``jitter`` times its mean diagonal on the diagonal."""
    S = 0.5 * (S + S.transpose(-1, -2))
    if jitter > 0:
        eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
        mean_diag = torch.diagonal(S, dim1=-2, dim2=-1).mean(-1).abs() + 1e-300
        S = S + jitter * eye * mean_diag[..., None, None]
    return S


class NoiseEvaluator:
    """The filter's view of a noise model for one pass over a batch.

    Attributes
    ----------
    const : Tensor, shape (T, B)
        The part of each step's log-density that does not depend on the particles.
    statistics : Tensor, shape (T, B, L, ...)
        Filled by :meth:`step`: what the latent-scale expectations need of each particle's residual.
    """

    const: Tensor
    statistics: Tensor

    def step(self, k: int, z: Tensor) -> Tensor:
        """Log-density minus ``const[k]`` of the whitened residuals ``z`` ``(B, L, p)`` of step
        ``k`` (zero at missing components), shape ``(B, L)``; records ``statistics[k]``.  The
        result may be modified in place by the caller, and may be an array of the evaluator's own
        that the next call overwrites."""
        raise NotImplementedError


@dataclass(frozen=True)
class NoiseSpec:
    """Base class of the families' specifications: what ``noise=`` takes (see the module docstring).

    A specification holds plain values (initial values of the family's parameters other than
    ``Rv``, which parameters are estimated, bounds), so that scikit-learn's ``clone`` copies it and
    ``get_params`` shows it; the tensors live in the noise model it makes (:meth:`initial`).
    """

    #: Registry name (the estimator's ``noise=`` string).
    name: ClassVar[str] = ""
    #: The family's noise model class (set by the class whose ``SPEC`` this is).
    noise_model: ClassVar[type[MeasurementNoise]]

    @classmethod
    def from_shortcuts(cls, **shortcuts: Any) -> NoiseSpec:
        """The specification from the estimator's shortcut parameters (``NOISE_SHORTCUTS`` of the
        registry, e.g. ``dof_init``): a family reads those it has and ignores the others."""
        return cls()

    def initial(self, Rv: Tensor) -> MeasurementNoise:
        """The noise model at the initial values: ``Rv`` and this specification's (none here: a
        family with other parameters makes their tensors)."""
        return self.state(Rv=Rv)

    def state(self, **params: Tensor) -> MeasurementNoise:
        """The noise model at the parameter values ``params`` (e.g. the fitted ``Rv_``, ``dof_``),
        carrying this specification."""
        return self.noise_model(**params, spec=self)

    def starting_at(self, noise: MeasurementNoise) -> NoiseSpec:
        """This specification with its initial values at ``noise``'s (``distilled_start``, the bootstrap)."""
        return self

    def initial_shortcuts(self) -> dict[str, Any]:
        """Its initial values as the estimator's shortcut parameters (e.g. ``{"dof_init": 3.2}``)."""
        return {}


#: Tail probability of the Student-t families' Gaussian core beyond which a sample is flagged as an
#: outlier (:meth:`MeasurementNoise.outlier_threshold`).
OUTLIER_LEVEL = 1e-3


def core_outlier_threshold(dof, p: int, weights=None) -> np.ndarray:
    """The weight ``E[lam | y] = (dof + p) / (dof + delta2)`` of a residual at the ``1 - OUTLIER_LEVEL``
    quantile of the Gaussian core's squared distance (``chi2_p``): a sample weighted below it lies
    further out than the core puts one sample in a thousand.  With ``dof`` near 1 a weight below 0.5
    is a residual of only 1.7 scales (a third of a Cauchy's samples); this threshold is about 0.17
    there, 0.38 at ``dof = 5`` and tends to 1 with the Gaussian limit (where every weight is 1).

    ``weights``: the fit's outlier weights (an array, or a list of them, one per record; a column
    per output where ``p == 1`` is one output's); the core is then widened to the bulk of the
    samples' own distances (:func:`bulk_spread`)."""
    from scipy.stats import chi2  # scipy.stats costs a quarter of a second to import

    nu = np.asarray(dof, dtype=float)
    c = float(chi2.ppf(1.0 - OUTLIER_LEVEL, p))
    if weights is not None:
        c = c * bulk_spread(weights, nu, p)
    with np.errstate(invalid="ignore"):
        return np.where(np.isinf(nu), 1.0, (nu + p) / (nu + c))


def bulk_spread(weights, dof, p: int) -> np.ndarray:
    """How much wider the bulk of the samples is than the fitted Student-t's core, at least 1: the
    median of the samples' squared distances ``delta2 = (dof + p) / w - dof`` (from their outlier
    weights ``w``) over the median of ``chi2_p``, per column of ``weights`` (pooled over records).

    A Student-t of ``dof`` below about 1, which gross outliers call for, has a scale well inside the
    regular samples' spread, and its own core's 99.9 % quantile flags 3-13 % of the regular samples
    of the development suite's records with 5 % outliers (benchmarks/README.md, "Flags"); measured
    from the samples' own median the core is that spread."""
    from scipy.stats import chi2

    w = np.concatenate(_records(weights), axis=0)
    nu = np.asarray(dof, dtype=float).reshape(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d2 = np.clip((nu + p) / w - nu, 0.0, None)
    d2 = np.where(np.isfinite(d2), d2, np.nan)
    if not np.isfinite(d2).any():
        return np.ones(w.shape[1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without an observed sample
        ratio = np.nanmedian(d2, axis=0) / float(chi2.median(p))
    spread = np.where(np.isfinite(ratio), np.maximum(ratio, 1.0), 1.0)
    return spread if spread.size > 1 else spread.reshape(())


#: More than this share of the samples with an outlier weight below 0.5 is reported after a fit:
#: the noise model may be absorbing model error (genuinely Cauchy noise down-weights about a third).
DOWNWEIGHTED_SHARE = 0.4


#: Odds ratio of two consecutive down-weighted samples (weight below 0.5) at and above which the
#: down-weighted samples are said to cluster in time.  Model error leaves serially correlated
#: residuals, so its down-weighted samples come in runs; isolated glitches and genuinely
#: heavy-tailed sensor noise leave them independent of their neighbours (odds ratio near 1).
CLUSTER_ODDS = 3.0


def _records(weights) -> list[np.ndarray]:
    """The outlier weights (an array, or a list of them, one per record) as one 2-D array per
    record: samples by outputs (one column for a family with one latent scale per sample)."""
    ws = weights if isinstance(weights, list) else [weights]
    out = []
    for a in ws:
        a = np.asarray(a, dtype=float)
        out.append(a.reshape(a.shape[0], -1) if a.ndim else a.reshape(1, 1))
    return out


def _record_columns(weights) -> list[np.ndarray]:
    """The outlier weights as a list of 1-D time series (one per record and output)."""
    return [a[:, j] for a in _records(weights) for j in range(a.shape[1])]


def clustering_odds(weights) -> float:
    """Odds ratio that a sample is down-weighted (weight below 0.5) given that the previous one is,
    against given that it is not, pooled over records and outputs: 1 for down-weighted samples
    scattered independently in time, large for runs of them; 1 when none or all are down-weighted."""
    counts = np.zeros((2, 2))
    for w in _record_columns(weights):
        if w.size < 2:
            continue
        valid = np.isfinite(w[:-1]) & np.isfinite(w[1:])
        a, b = (w[:-1] < 0.5)[valid], (w[1:] < 0.5)[valid]
        for i in (0, 1):
            for j in (0, 1):
                counts[i, j] += np.sum((a == bool(i)) & (b == bool(j)))
    if counts[1].sum() == 0 or counts[0].sum() == 0:
        return 1.0
    c = counts + 0.5
    return float(c[1, 1] * c[0, 0] / (c[1, 0] * c[0, 1]))


def downweighted_share(weights) -> float:
    """Share of the finite outlier ``weights`` (an array or a list of them) below 0.5."""
    w = np.concatenate([a.reshape(-1) for a in _records(weights)])
    w = w[np.isfinite(w)]
    return float(np.mean(w < 0.5)) if w.size else 0.0


def absorbed_in_runs(weights) -> bool:
    """Whether the down-weighted samples look like model error rather than outliers: they come in
    runs (:func:`clustering_odds` at least :data:`CLUSTER_ODDS`) or are nearly all of them."""
    return downweighted_share(weights) > 0.9 or clustering_odds(weights) >= CLUSTER_ODDS


@dataclass(frozen=True)
class MeasurementNoise:
    """Base class of the noise models (see the module docstring).

    Every family has the scale matrix ``Rv`` of shape ``(..., p, p)``; the other fields are
    family-specific parameters, listed with their number of non-batch dimensions in
    ``CORE_DIMS``.  ``spec`` is the specification the model was made from (its options); the
    family's default specification when not given.
    """

    Rv: Tensor
    spec: NoiseSpec | None = field(default=None, kw_only=True, compare=False, repr=False)

    #: Registry name (the estimator's ``noise=`` value).
    name: ClassVar[str] = ""
    #: The family's specification class.
    SPEC: ClassVar[type[NoiseSpec]] = NoiseSpec
    #: The parameters, in order, and the number of non-batch dimensions of each.
    CORE_DIMS: ClassVar[dict[str, int]] = {"Rv": 2}
    #: The working scale of each parameter (standard errors, extrapolation).
    WORKING: ClassVar[dict[str, WorkingScale]] = {"Rv": LOG_CHOLESKY}
    #: Whether the latent scales are per output component (shape ``(..., p)``) or per sample.
    per_component: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any):
        super().__init_subclass__(**kwargs)
        if "SPEC" in cls.__dict__:  # a family's noise model: its specification makes it
            cls.SPEC.noise_model = cls

    def __post_init__(self):
        if self.spec is None:
            object.__setattr__(self, "spec", self.SPEC())

    # ------------------------------------------------------------------ construction, batching
    def parameters(self) -> dict[str, Tensor]:
        """The parameters by name (the keys of ``history_`` and the fitted attributes ``<name>_``)."""
        return {name: getattr(self, name) for name in self.CORE_DIMS}

    def replace(self, **params: Any) -> MeasurementNoise:
        return dataclasses.replace(self, **params)

    def at(self, **params: Tensor) -> MeasurementNoise:
        """A copy with the parameters ``params`` replaced, unchecked (values an autograd transform
        differentiates, which a family's checks could not read)."""
        new = copy.copy(self)
        for name, value in params.items():
            object.__setattr__(new, name, value)
        return new

    def to(self, **kwargs: Any) -> MeasurementNoise:
        return self.replace(**{k: v.to(**kwargs) for k, v in self.parameters().items()})

    @property
    def n_outputs(self) -> int:
        return self.Rv.shape[-1]

    @property
    def batched(self) -> bool:
        return self.Rv.dim() > 2

    def per_sequence(self, name: str, n_sequences: int) -> Tensor:
        """Parameter ``name`` with a leading batch dimension of ``n_sequences``."""
        value = getattr(self, name)
        if value.dim() == self.CORE_DIMS[name]:
            return value.expand(n_sequences, *value.shape)
        return value

    @classmethod
    def stack(cls, noises: list[MeasurementNoise]) -> MeasurementNoise:
        """One batched noise model from unbatched ones (independent fits; the first one's
        specification)."""
        names = noises[0].parameters()
        return cls(**{n: torch.stack([getattr(m, n) for m in noises]) for n in names}, spec=noises[0].spec)

    def unstack(self) -> list[MeasurementNoise]:
        """The unbatched noise models of a batched one."""
        params = self.parameters()
        return [self.replace(**{n: v[b] for n, v in params.items()}) for b in range(self.Rv.shape[0])]

    def convergence_scales(self, n_obs: int) -> dict[str, Tensor]:
        """The relative standard error of each positive parameter (complete data: the latent scales
        known) at ``n_obs`` observations, by name: EM has converged in a parameter once its changes
        are small against this (:func:`torch_nssm.estimation.convergence.has_converged`).  A
        variance estimated from ``n`` samples has relative standard error ``sqrt(2 / n)``."""
        return {"Rv": torch.full_like(self.Rv, math.sqrt(2.0 / max(n_obs, 1)))}

    def is_valid(self) -> Tensor:
        """Admissible parameters (:meth:`admissible`) and a positive-definite ``Rv``, per batch entry
        (shape ``(...)``)."""
        ok = torch.linalg.cholesky_ex(self.Rv).info == 0
        for name, v in self.parameters().items():
            core = self.CORE_DIMS[name]
            finite = self.admissible(name, v)
            ok = ok & (finite.flatten(v.dim() - core).all(-1) if core else finite)
        return ok

    def admissible(self, name: str, value: Tensor) -> Tensor:
        """Per entry, whether ``value`` is a valid value of parameter ``name``: finite."""
        return torch.isfinite(value)

    # ------------------------------------------------------------------ the estimator's view
    def attributes(self) -> dict[str, Any]:
        """The estimator's fitted attributes (``Rv_``, ...) without the trailing underscore: the
        parameters, 0-dimensional ones as floats, the others as arrays."""
        return {
            name: float(v) if v.dim() == 0 else v.detach().cpu().numpy()
            for name, v in self.parameters().items()
        }

    def outlier_threshold(self, weights=None) -> np.ndarray:
        """The outlier weight below which a sample (an output's sample, for a family with one
        latent scale per output: one threshold per output) is flagged as an outlier: 0.5 unless the
        family says otherwise (the Student-t families: :func:`core_outlier_threshold`, widened to
        the bulk of the fit's ``weights`` where given)."""
        return np.asarray(0.5)

    def absorption_message(self, weights) -> str | None:
        """Words for a fit whose noise model explains too much of the data (``None`` if it does
        not), from its outlier ``weights``: more than :data:`DOWNWEIGHTED_SHARE` of the samples
        weighted below 0.5, in runs (:func:`absorbed_in_runs`)."""
        share = downweighted_share(weights)
        if share <= DOWNWEIGHTED_SHARE or not absorbed_in_runs(weights):
            return None
        return (
            f"the measurement noise absorbs much of the data: {100 * share:.0f} % of the samples have an "
            "outlier weight below 0.5. Unless the sensors really have that many outliers, the noise model "
            "is absorbing what f and g cannot explain (model error, not outliers): check the residuals "
            "(torch_nssm.diagnostics) or improve the model"
        )

    def floored(self, floor: Tensor) -> MeasurementNoise:
        """This noise with each output's variance ``Rv[j, j]`` raised to at least ``floor[j]`` (the
        difference added to the diagonal, so ``Rv`` stays positive definite)."""
        diag = self.Rv.diagonal(dim1=-2, dim2=-1)
        lift = torch.clamp(floor.to(self.Rv) - diag, min=0.0)
        if not bool((lift > 0).any()):
            return self
        return replace(self, Rv=self.Rv + torch.diag_embed(lift))

    # ------------------------------------------------------------------ the filter
    def evaluator(self, scale: MaskedScale, n_particles: int) -> NoiseEvaluator:
        """The per-step log-density of the filter for the batch whose masked scale is ``scale``."""
        raise NotImplementedError

    def log_prob(self, residual: Tensor) -> Tensor:
        """Log-density of fully observed residuals ``(..., p)`` (unbatched parameters)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ E-step and M-step
    def latent_expectations(self, statistics: Tensor, scale: MaskedScale, sl: slice) -> tuple[Tensor, Tensor]:
        """``<lam>`` and ``<log lam>`` of each particle from the filter's ``statistics`` of the
        time block ``sl`` (``scale`` is the whole pass's).  Shape ``(t, B, L)``, or
        ``(t, B, L, p)`` for per-component scales."""
        raise NotImplementedError

    def statistics(
        self, r: Tensor, W: Tensor, e_lam: Tensor, e_log_lam: Tensor, scale: MaskedScale, sl: slice
    ) -> dict[str, Tensor]:
        """The M-step's sufficient statistics of one time block, summed per sequence ``(B, ...)``.

        Parameters
        ----------
        r : Tensor, shape (t, B, L, p)
            Output residuals ``y - g(x, u)`` at the new ``theta_g``, zero where missing.
        W : Tensor, shape (t, B, L)
            Smoothing weights, zero at steps without an observation.
        e_lam, e_log_lam : Tensor
            The latent-scale expectations of the block.
        scale : MaskedScale
            The E-step's masked scale (whole pass); ``sl`` selects the block.
        """
        raise NotImplementedError

    def updated(
        self, stats: dict[str, Tensor], *, fit_Rv: bool = True, fit_shape: bool = True
    ) -> MeasurementNoise:
        """The closed-form update from pooled ``stats`` (as from :meth:`statistics`, batch as this
        model's): ``Rv`` if ``fit_Rv``, the other parameters its specification estimates if
        ``fit_shape`` (``False`` holds them all)."""
        raise NotImplementedError

    def sample(self, shape: tuple[int, ...], generator=None) -> Tensor:
        """Draws of shape ``shape + (p,)`` (unbatched parameters); ``generator``: a
        ``torch.Generator`` (or ``None``, the global stream) or a ``numpy.random.Generator``
        (:func:`random_source`)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ the observed information
    def estimated(self, fit_Rv: bool = True, fit_shape: bool = True) -> list[str]:
        """The parameters a fit estimates (their standard errors, the bootstrap's samples): ``Rv``
        if ``fit_Rv``, the others if ``fit_shape``."""
        return [n for n in self.CORE_DIMS if (fit_Rv if n == "Rv" else fit_shape)]

    def bounds(self, name: str) -> tuple[float, float] | None:
        """The bracket of parameter ``name`` (extrapolated values are clipped to it), if any."""
        return None

    def residual_log_prob(self, r: Tensor, mask: Tensor, all_observed: bool) -> Tensor:
        """Log-density of residual rows ``r`` ``(..., p)`` (zero where ``mask`` is False) over their
        observed components, differentiable in this model's tensors (the observed information
        evaluates it at parameters on their working scales, :meth:`at`).  ``all_observed``: every
        component of every row is observed."""
        raise NotImplementedError(
            f"the noise family {self.name!r} has no residual_log_prob: no standard errors for it"
        )

    @property
    def is_gaussian(self) -> bool:
        """Whether the residuals are ``N(0, Rv)`` (every latent scale 1): the observed information
        then writes the observation term with the rows' moments."""
        return False

    def scores_in_closed_form(self, all_observed: bool) -> bool:
        """Whether :meth:`residual_scores` applies (``all_observed``: every component observed)."""
        return False

    def residual_scores(self, r: Tensor, mask: Tensor, weight: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """``weight`` ``(R, 1)`` times the gradient of :meth:`residual_log_prob` per row ``(R, p)``:
        in the mean (``(R, p)``) and in each parameter's working coordinates (``{name: (R, k)}``),
        where :meth:`scores_in_closed_form`."""
        raise NotImplementedError

    @property
    def elliptical(self) -> bool:
        """Whether :meth:`elliptical_terms` applies: a log-density ``h(q) - log det C`` of the
        squared norm ``q = |C^-1 r|^2`` of a residual (``Rv = C C^T``)."""
        return False

    def elliptical_terms(
        self, q: Tensor, p: int, names: Sequence[str] = ()
    ) -> tuple[Tensor, Tensor, dict[str, tuple[Tensor, Tensor]]] | None:
        """Where :attr:`elliptical`, per row of squared norms ``q`` of ``p`` components: ``lam = -2
        h_q``, ``h_qq``, and for each scalar parameter ``theta`` in ``names`` (those estimated, other
        than ``Rv``) on its working scale ``s`` the derivatives ``d2h / dq ds`` and ``d2h / ds2``
        (``{name: (cross, second)}``); ``None`` if the family has no such form (the observed
        information then differentiates :meth:`residual_log_prob`)."""
        return None


# ---------------------------------------------------------------------------- random draws
def psd_sqrt(cov: np.ndarray) -> np.ndarray:
    """A matrix ``S`` with ``S S^T = cov`` (works for singular PSD matrices)."""
    vals, vecs = np.linalg.eigh(cov)
    return vecs * np.sqrt(np.clip(vals, 0.0, None))


class _TorchDraws:
    """Draws from a ``torch.Generator`` (``None``: the global stream)."""

    def __init__(self, generator: torch.Generator | None, like: Tensor):
        self.generator, self.dtype, self.device = generator, like.dtype, like.device

    def standard_normal(self, shape: tuple[int, ...]) -> Tensor:
        return torch.randn(*shape, dtype=self.dtype, device=self.device, generator=self.generator)

    def gaussian(self, shape: tuple[int, ...], cov: Tensor) -> Tensor:
        """``N(0, cov)`` draws ``shape + (p,)``."""
        chol = torch.linalg.cholesky(cov)
        return self.standard_normal((*shape, chol.shape[-1])) @ chol.transpose(-1, -2)

    def gamma(self, concentration: Tensor, rate: Tensor | float) -> Tensor:
        """``Gamma(concentration, rate)`` draws shaped like ``concentration``."""
        return standard_gamma(concentration, self.generator) / rate

    def scale_mixture(self, z: Tensor, concentration: Tensor, rate: Tensor | float) -> Tensor:
        """Gaussian draws ``z`` ``(..., p)`` over the square roots of ``Gamma(concentration, rate)``
        draws shaped like ``z`` (one per component) or ``z.shape[:-1]`` (one per row)."""
        root = torch.sqrt(self.gamma(concentration, rate))
        return z / (root if concentration.dim() == z.dim() else root.unsqueeze(-1))

    def uniform(self, shape: tuple[int, ...]) -> Tensor:
        return torch.rand(*shape, dtype=self.dtype, device=self.device, generator=self.generator)


class _NumpyDraws:
    """Draws from a ``numpy.random.Generator`` (the simulated data sets), as tensors like ``like``."""

    def __init__(self, rng: np.random.Generator, like: Tensor):
        self.rng, self.dtype, self.device = rng, like.dtype, like.device

    def _tensor(self, a: np.ndarray) -> Tensor:
        return torch.as_tensor(a, dtype=self.dtype, device=self.device)

    def standard_normal(self, shape: tuple[int, ...]) -> Tensor:
        return self._tensor(self.rng.standard_normal(shape))

    def gaussian(self, shape: tuple[int, ...], cov: Tensor) -> Tensor:
        c = cov.detach().cpu().numpy()
        return self._tensor(self.rng.standard_normal((*shape, c.shape[-1])) @ psd_sqrt(c).T)

    def _gamma(self, concentration: Tensor, rate: Tensor | float) -> np.ndarray:
        k = concentration.detach().cpu().numpy()
        r = np.asarray(rate.detach().cpu().numpy() if isinstance(rate, Tensor) else rate, dtype=float)
        if k.size and r.size == 1 and np.all(k == k.flat[0]):  # one shape and rate: NumPy's scalar path
            return self.rng.gamma(shape=float(k.flat[0]), scale=1.0 / float(r), size=k.shape)
        return self.rng.gamma(shape=k, scale=1.0 / r)

    def gamma(self, concentration: Tensor, rate: Tensor | float) -> Tensor:
        return self._tensor(self._gamma(concentration, rate))

    def scale_mixture(self, z: Tensor, concentration: Tensor, rate: Tensor | float) -> Tensor:
        # in NumPy from the draws on (its square root and division are not always torch's to the bit)
        root = np.sqrt(self._gamma(concentration, rate))
        root = root if concentration.dim() == z.dim() else root[..., None]
        return self._tensor(z.detach().cpu().numpy() / root)

    def uniform(self, shape: tuple[int, ...]) -> Tensor:
        return self._tensor(self.rng.random(shape))


def random_source(generator, like: Tensor) -> _TorchDraws | _NumpyDraws:
    """The draws of the families' samplers from ``generator``: a ``torch.Generator`` or ``None``
    (the global stream), or a ``numpy.random.Generator`` (the simulated data sets' streams, whose
    records stay the same numbers whatever torch does); tensors of ``like``'s dtype and device.

    Its methods: ``standard_normal(shape)``, ``gaussian(shape, cov)`` (``N(0, cov)``, a trailing
    ``p``), ``uniform(shape)``, ``gamma(concentration, rate)`` and ``scale_mixture(z, concentration,
    rate)`` (``z`` over the square roots of gamma draws)."""
    if isinstance(generator, np.random.Generator):
        return _NumpyDraws(generator, like)
    return _TorchDraws(generator, like)


def gaussian_log_normaliser(n_obs: Tensor, logdet: Tensor) -> Tensor:
    """``-(p log(2 pi) + log det R) / 2``."""
    return -0.5 * (n_obs * math.log(2.0 * math.pi) + logdet)


def standard_gamma(concentration: Tensor, generator: torch.Generator | None) -> Tensor:
    """``Gamma(concentration, 1)`` draws, reproducible with ``generator`` (torch's sampler has no
    generator argument: the global stream is seeded from it and restored)."""
    if generator is None:
        return torch._standard_gamma(concentration)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device))
    device = concentration.device
    with torch.random.fork_rng(devices=[] if device.type == "cpu" else [device]):
        torch.manual_seed(seed)
        return torch._standard_gamma(concentration)
