"""Standard errors of the fitted parameters: the observed information by Louis' identity.

At any parameter value ``theta`` (docs/uncertainty.md)::

    -d2 log p(y; theta) = E[-d2 log p(x, y; theta) | y] - Var[d log p(x, y; theta) | y]

* The first term is the Hessian of the M-step's expected complete-data log-likelihood ``Q``, written
  with the smoother's statistics exactly as the M-step writes it (docs/method.md §4): the
  transition term from the rows ``(x_k^i, u_k) -> xbar_k^i`` with weights ``s_k^i`` plus the
  parameter-free scatter, the observation term from the rows ``(x_k^l, u_k) -> y_k`` with the
  smoothing weights ``W_{k|N}^l``.  The observation term is the noise family's marginal density
  of ``y_k`` given ``x_k`` (the latent scales integrated out:
  :meth:`~torch_nssm.core.noise.MeasurementNoise.residual_log_prob`).
  Gaussian parts whose mean is linear in its parameters are written with the rows' weighted
  moments, an elliptical noise family's observation with its closed-form terms besides
  (:meth:`~torch_nssm.core.noise.MeasurementNoise.elliptical_terms`); autograd over the rows
  otherwise.
* The second term needs the *joint* smoothing distribution, but only over a lag window of a few
  steps: ``M`` draws of pieces of trajectories from the particle approximation
  (:func:`~torch_nssm.inference.ffbsi.backward_segments`), the complete-data score of each step
  in closed form given the residuals, and their covariances summed up to the window
  (:func:`_windowed_covariance`).

Both are computed on a working scale where normal approximations are better
(:mod:`torch_nssm.core.scales`): module parameters as they are, ``Rw`` by its log-Cholesky factor,
the noise family's parameters on the scales it declares (``MeasurementNoise.WORKING``: a full
``Rv`` by its log-Cholesky factor, diagonal variances and degrees of freedom by their logarithm).
The covariance is mapped back to the natural entries by the delta method; intervals of the
entries positive by construction (variances, degrees of freedom) are formed on the log scale.  The
initial-state prior is held fixed (its influence on a long record is negligible).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np
import torch
from torch import Tensor, nn
from torch.func import functional_call

from ..core.model import SequenceBatch, StateSpaceModel
from ..core.noise import MeasurementNoise
from ..core.parametric import LinearInParameters
from ..core.scales import LOG_CHOLESKY, PLAIN, WorkingScale, cholesky_and_inverse, log_cholesky_scores
from ..inference.ffbsi import backward_segments
from .estep import EStepOutput
from .mstep import ROW_WEIGHT_CUTOFF

__all__ = [
    "ParameterUncertainty",
    "observed_information",
    "free_parameter_count",
    "DEFAULT_TRAJECTORIES",
    "MAX_INFORMATION_PARAMETERS",
]

#: Backward-simulated trajectories for the variance of the complete-data score (measured on a
#: linear-Gaussian model: 300 or more keep the Monte Carlo part of the error below ~10 %).
DEFAULT_TRAJECTORIES = 500

#: Modules with more free parameters than this (neural networks) get no standard errors: their
#: information matrix is large and, for an over-parameterised network, singular.  The other
#: parameters' standard errors are then conditional on that module (docs/uncertainty.md).
MAX_INFORMATION_PARAMETERS = 100


@dataclass
class _Block:
    """One estimated parameter: its key (``"f.a"``, ``"Rw"``, ``"Rv"``), its value and the working
    scale it is put on (:mod:`torch_nssm.core.scales`)."""

    key: str
    scale: WorkingScale
    value: Tensor

    @property
    def n_working(self) -> int:
        return self.scale.n_working(self.value)

    def to_working(self) -> Tensor:
        return self.scale.to_working(self.value)

    def from_working(self, w: Tensor) -> Tensor:
        return self.scale.from_working(w, self.value)

    def natural_entries(self, value: Tensor) -> Tensor:
        """The free entries on the natural scale (lower triangle of a full covariance)."""
        return self.scale.natural_entries(value)

    def entry_index(self) -> list[tuple[int, ...]]:
        """Index into the parameter's array of each natural entry."""
        return self.scale.entry_index(self.value)

    def working_names(self) -> list[str]:
        return self.scale.working_names(self.key, self.value)

    def log_scale(self) -> list[bool]:
        """Which natural entries are positive by construction (their intervals are formed on the log
        scale): variances and degrees of freedom."""
        return self.scale.log_scale(self.value)


@dataclass
class ParameterUncertainty:
    """The observed information and what follows from it, on the natural scale of the parameters.

    Attributes
    ----------
    working_names : list of str
        The working parameters (rows of ``information``): ``"log chol(Rw)[0, 0]"``,
        ``"chol(Rw)[1, 0]"``, ``"log Rv[0, 0]"``, ``"log dof"``; module entries as in ``names``.
    names : list of str
        The free parameters' entries, e.g. ``"f.a"``, ``"f.A[0, 1]"``, ``"Rw[1, 0]"``, ``"dof"``
        (only the lower triangle of a full covariance).
    estimate : ndarray of shape (d,)
        Their fitted values.
    covariance : ndarray of shape (d, d)
        Their asymptotic covariance (delta method from the working scale); NaN rows and columns
        for directions the information does not determine.
    information : ndarray of shape (d, d)
        The observed information on the working scale (see the module docstring):
        ``complete_information - score_variance``.
    complete_information : ndarray of shape (d, d)
        ``E[-d2 log p(x, y) | y]`` on the working scale.
    score_variance : ndarray of shape (d, d)
        ``Var[d log p(x, y) | y]`` on the working scale (lag-windowed, see
        :func:`_windowed_covariance`).
    missing_information : ndarray of shape (d,)
        Per working parameter, ``Var[score] / E[-Hessian]`` (diagonals): the fraction of the
        complete-data information lost because the states are not observed.
    mean_score : ndarray of shape (d,)
        ``E[d log p(x, y) | y]`` on the working scale (about 0 at the maximum likelihood).
    n_trajectories : int
    lag_window : int
        The largest lag ``|k - j|`` of the score covariances ``Cov(s_k, s_j | y)`` summed (see
        :func:`_windowed_covariance`).
    excluded : list of str
        Keys of modules left out (too many parameters); the others are conditional on them.
    """

    names: list[str]
    working_names: list[str]
    estimate: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    complete_information: np.ndarray
    score_variance: np.ndarray
    missing_information: np.ndarray
    mean_score: np.ndarray
    n_trajectories: int
    lag_window: int
    excluded: list[str] = field(default_factory=list)
    #: ``d natural / d working`` at the estimate
    jacobian: np.ndarray | None = field(default=None, repr=False)
    #: per key: (shape, positions in ``names``, index of each entry, whether its interval is on the log
    #: scale, whether it is a symmetric matrix given by its lower triangle)
    layout: dict[str, tuple[tuple, list, list, list, bool]] = field(default_factory=dict, repr=False)

    @property
    def standard_errors(self) -> dict[str, np.ndarray]:
        """Per key of ``history_`` (``"f.a"``, ``"Rw"``, ...), arrays shaped like the parameter
        (zero at the fixed entries of a diagonal covariance; an off-diagonal covariance entry
        appears in both its places)."""
        se = np.sqrt(np.clip(np.diagonal(self.covariance), 0.0, None))
        se = np.where(np.isfinite(np.diagonal(self.covariance)), se, np.nan)
        return self._unflatten(se)

    def warnings(self) -> list[str]:
        """What a user should be told: modules left out, parameters without a standard error."""
        out = []
        if self.excluded:
            out.append(
                f"no standard errors for {', '.join(self.excluded)}: more than {MAX_INFORMATION_PARAMETERS} "
                "free parameters (a neural network); the other standard errors treat it as known "
                "(docs/uncertainty.md)"
            )
        undetermined = [n for n, v in zip(self.names, np.diagonal(self.covariance)) if not np.isfinite(v)]
        if undetermined:
            out.append(
                "the observed information is not positive definite along some directions (Monte Carlo "
                "error, a fit far from the maximum, or parameters the data do not determine): no standard "
                f"error for {', '.join(undetermined)}; more particles for the final E-step "
                "(n_particles_final) or a converged fit help (docs/uncertainty.md)"
            )
        return out

    def correlation(self) -> np.ndarray:
        """The correlation matrix of the free parameters (``names`` order)."""
        s = np.sqrt(np.diagonal(self.covariance))
        return self.covariance / np.outer(s, s)

    def confidence_intervals(self, level: float = 0.95) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Normal intervals ``(lower, upper)`` per key; entries positive by construction (variances,
        degrees of freedom) on the log scale."""
        if not 0 < level < 1:
            raise ValueError(f"level must lie in (0, 1), got {level!r}")
        z = NormalDist().inv_cdf(0.5 + level / 2)
        se = np.sqrt(np.diagonal(self.covariance))
        value = self.estimate
        lower, upper = value - z * se, value + z * se
        log = np.zeros(len(value), dtype=bool)
        for _, positions, _, logs, _ in self.layout.values():
            log[positions] = logs
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.exp(z * se / value)
        lower = np.where(log, value / r, lower)
        upper = np.where(log, value * r, upper)
        lo, hi = self._unflatten(lower), self._unflatten(upper)
        return {k: (lo[k], hi[k]) for k in lo}

    def _unflatten(self, values: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for key, (shape, positions, index, _, symmetric) in self.layout.items():
            a = np.zeros(shape)
            for pos, idx in zip(positions, index):
                a[idx] = values[pos]
                if len(idx) == 2 and symmetric:
                    a[idx[::-1]] = values[pos]
            out[key] = a
        return out


def free_parameter_count(module: nn.Module) -> int:
    """Number of entries of the module's parameters with ``requires_grad``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def _blocks(
    model: StateSpaceModel, fit_Rw: bool, fit_Rv: bool, fit_shape: bool
) -> tuple[list[_Block], list[str]]:
    """The estimated parameters: the free ones of ``f`` and ``g`` (modules with more than
    :data:`MAX_INFORMATION_PARAMETERS` left out, their labels in the second list), ``Rw`` if
    ``fit_Rw``, and the noise family's (:meth:`~torch_nssm.core.noise.MeasurementNoise.estimated`)."""
    blocks, excluded = [], []
    for label, module in (("f", model.f), ("g", model.g)):
        if free_parameter_count(module) > MAX_INFORMATION_PARAMETERS:
            excluded.append(label)
            continue
        for name, p in module.named_parameters():
            if p.requires_grad:
                blocks.append(_Block(f"{label}.{name}", PLAIN, p.detach()))
    if fit_Rw:
        blocks.append(_Block("Rw", LOG_CHOLESKY, model.Rw.detach()))
    noise = model.noise
    for name in noise.estimated(fit_Rv, fit_shape):
        blocks.append(_Block(name, noise.WORKING[name], getattr(noise, name).detach()))
    return blocks, excluded


class _LogLikelihood:
    """The complete-data log-likelihood's terms as functions of the working parameters ``w``."""

    def __init__(self, model: StateSpaceModel, blocks: list[_Block]):
        self.model, self.blocks = model, blocks
        self.sizes = [b.n_working for b in blocks]
        self.noise = model.noise

    def unpack(self, w: Tensor) -> dict[str, Tensor]:
        params = {}
        for block, part in zip(self.blocks, torch.split(w, self.sizes)):
            params[block.key] = block.from_working(part)
        return params

    def _module_params(self, params: dict[str, Tensor], label: str) -> dict[str, Tensor]:
        n = len(label) + 1
        return {k[n:]: v for k, v in params.items() if k.startswith(label + ".")}

    def f(self, params, x: Tensor, u: Tensor) -> Tensor:
        return functional_call(self.model.f, self._module_params(params, "f"), (x, u))

    def g(self, params, x: Tensor, u: Tensor) -> Tensor:
        return functional_call(self.model.g, self._module_params(params, "g"), (x, u))

    def Rw(self, params) -> Tensor:
        return params.get("Rw", self.model.Rw)

    def noise_at(self, params, dtype: torch.dtype | None = None) -> MeasurementNoise:
        """The noise model with its estimated parameters at ``params``; with ``dtype``, the others
        detached and cast to it (the closed forms, which run without autograd)."""
        held = (lambda v: v) if dtype is None else (lambda v: v.detach().to(dtype))  # noqa: E731
        return self.noise.at(
            **{n: params[n] if n in params else held(v) for n, v in self.noise.parameters().items()}
        )

    def transition(self, params, r: Tensor, weight: Tensor, scatter: Tensor | None, n_trans: float) -> Tensor:
        """``sum w log N(r; 0, Rw)`` (plus ``-tr(Rw^-1 scatter) / 2``) over rows ``r`` ``(..., nx)``."""
        C = torch.linalg.cholesky(self.Rw(params))
        nx = r.shape[-1]
        # one small inverse, then a broadcast product: a batched triangular solve against one
        # factor differentiates ~10x slower (its backward expands the factor to every row)
        Ci = torch.linalg.solve_triangular(C, torch.eye(nx, dtype=C.dtype, device=C.device), upper=False)
        z = r @ Ci.transpose(-1, -2)
        logdet = 2.0 * torch.log(torch.diagonal(C)).sum()
        out = -0.5 * (weight * (z * z).sum(-1)).sum() - 0.5 * n_trans * (logdet + nx * math.log(2 * math.pi))
        if scatter is not None:
            out = out - 0.5 * (Ci @ scatter @ Ci.transpose(-1, -2)).diagonal().sum()
        return out

    def observation(self, params, r: Tensor, mask: Tensor, all_observed: bool) -> Tensor:
        """Log-density of the residuals ``r`` ``(..., p)`` (zero where missing) under the noise."""
        return self.noise_at(params).residual_log_prob(r, mask, all_observed)


def _expected_rows(data: SequenceBatch, estep_out: EStepOutput):
    """The M-step's weighted rows (transition and observation), above :data:`ROW_WEIGHT_CUTOFF`."""
    X, sm = estep_out.filter.particles, estep_out.smoother
    T, B, L, nx = X.shape
    # the kept rows' flat indices, found once (a boolean mask per tensor costs one search each),
    # and the per-step tensors indexed by the rows' steps instead of expanded to every particle
    Xf = X.reshape(-1, nx)
    u = data.u.reshape(T * B, -1)
    s = sm.transition_weights.reshape(-1)
    rows = torch.nonzero(s > ROW_WEIGHT_CUTOFF).squeeze(-1)
    trans = (Xf[rows], u[rows // L], sm.next_mean.reshape(-1, nx)[rows], s[rows])
    observed = data.obs_mask.any(-1)  # (T, B)
    W = (torch.exp(sm.log_weights) * observed.unsqueeze(-1)).reshape(-1)
    rows = torch.nonzero(W > ROW_WEIGHT_CUTOFF).squeeze(-1)
    steps = rows // L
    y = torch.nan_to_num(data.y).reshape(T * B, -1)
    obs = (Xf[rows], u[steps], y[steps], data.obs_mask.reshape(T * B, -1)[steps], W[rows])
    return trans, obs


def _entry_layout(blocks) -> tuple[list, list, dict]:
    """The names of the natural entries, of the working coordinates, and each block's layout
    ``(shape, positions, entry index, log scale, symmetric)``."""
    names, layout, start, working = [], {}, 0, []
    for b in blocks:
        working.extend(b.working_names())
        idx = b.entry_index()
        positions = list(range(start, start + len(idx)))
        start += len(idx)
        names.extend(b.key if b.value.dim() == 0 else f"{b.key}[{', '.join(map(str, i))}]" for i in idx)
        layout[b.key] = (tuple(b.value.shape), positions, idx, b.log_scale(), b.scale.symmetric)
    return names, working, layout


def observed_information(
    model: StateSpaceModel,
    data: SequenceBatch,
    estep_out: EStepOutput,
    *,
    fit_Rw: bool = True,
    fit_Rv: bool = True,
    fit_shape: bool = True,
    n_trajectories: int = DEFAULT_TRAJECTORIES,
    generator: torch.Generator | None = None,
) -> ParameterUncertainty:
    """The observed information at ``model`` by Louis' identity, and the parameters' covariance.

    Parameters
    ----------
    model : StateSpaceModel
        One (unbatched) model, shared by the sequences of ``data``.
    data : SequenceBatch
    estep_out : EStepOutput
        The E-step of ``data`` at ``model`` (the fit's final E-step).
    fit_Rw, fit_Rv : bool
        Whether ``Rw`` and ``Rv`` were estimated (else they are held fixed).
    fit_shape : bool
        Whether the noise family's other parameters were estimated, those its specification
        estimates (e.g. the Student-t's ``dof`` with ``fit_dof``); False holds them all.
    n_trajectories : int
        Backward-simulated trajectories for the variance of the score.
    generator : torch.Generator, optional

    Returns
    -------
    ParameterUncertainty
    """
    blocks, excluded = _blocks(model, fit_Rw, fit_Rv, fit_shape)
    ll = _LogLikelihood(model, blocks)
    dtype = estep_out.filter.particles.dtype
    with torch.no_grad():
        w0 = torch.cat([b.to_working() for b in blocks]).to(dtype) if blocks else torch.zeros(0, dtype=dtype)
    d = w0.numel()
    all_observed = bool(data.obs_mask[data.obs_mask.any(-1)].all())
    H = _q_hessian(_q_parts(ll, model, data, estep_out, w0, all_observed), blocks, w0).numpy()

    # the variance of the complete-data score, from pieces of backward-simulated trajectories
    if d:
        V, lag, mean_score = _score_variance(
            ll, w0, model, data, estep_out, n_trajectories, all_observed, generator
        )
    else:
        V, lag, mean_score = np.zeros((0, 0)), 0, np.zeros(0)
    M = int(n_trajectories)
    info = -H - V
    info = 0.5 * (info + info.T)
    estimate, cov, J = _natural_covariance(ll, blocks, w0, _inverse(info))
    names, working, layout = _entry_layout(blocks)
    with np.errstate(divide="ignore", invalid="ignore"):
        missing = np.diagonal(V) / np.diagonal(-H)
    return ParameterUncertainty(
        names, working, estimate, cov, info, -H, V, missing, mean_score, M, lag, excluded, J, layout
    )


def _q_parts(
    ll: _LogLikelihood, model: StateSpaceModel, data: SequenceBatch, estep_out: EStepOutput, w0: Tensor,
    all_observed: bool,
) -> dict:
    """``Q(w)``, the M-step's expected complete-data log-likelihood, in its two independent parts:
    ``{"transition": ..., "observation": ...}`` (``f``, ``Rw``; ``g``, the noise's), each a function
    of the working parameters ``w`` or, for an elliptical noise family and a ``g`` linear in its
    parameters, the observation part's Hessian at ``w0`` in closed form (a tensor ``(d, d)``)."""
    trans, obs = _expected_rows(data, estep_out)
    scatter = estep_out.smoother.residual_scatter.sum(0)
    n_trans = float(data.transition_mask.sum())

    def transition_part(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        x, u, xbar, s = trans
        return ll.transition(params, xbar - ll.f(params, x, u), s, scatter, n_trans)

    def observation_part(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        x, u, y, mask, W = obs
        r = torch.where(mask, y - ll.g(params, x, u), torch.zeros_like(y))
        return (W * ll.observation(params, r, mask, all_observed)).sum()

    # the Gaussian parts with a mean linear in its parameters (always the transition's for such an
    # f; the observation's for Gaussian noise): Q from the weighted moments, a tiny function of w
    moments = {
        "transition": _gaussian_moments(ll, "f", trans[0], trans[1], trans[2], trans[3]),
        "observation": (
            _gaussian_moments(ll, "g", obs[0], obs[1], obs[2], obs[4])
            if model.noise.is_gaussian and all_observed else None
        ),
    }
    n_obs = float(obs[4].sum())

    def transition_moments(w: Tensor) -> Tensor:
        return _gaussian_term(moments["transition"], w, ll.Rw(ll.unpack(w)), scatter, n_trans)

    def observation_moments(w: Tensor) -> Tensor:
        return _gaussian_term(moments["observation"], w, ll.unpack(w).get("Rv", model.noise.Rv), None, n_obs)

    parts = {
        "transition": transition_part if moments["transition"] is None else transition_moments,
        "observation": observation_part if moments["observation"] is None else observation_moments,
    }
    if moments["observation"] is None and model.noise.elliptical and all_observed:
        if _linear_in_parameters(model.g) or not _module_columns(ll, "g")[0]:
            try:
                hessian = _elliptical_observation_hessian(ll, w0, obs)
            except _NotLinear:  # its forward is not offset + Phi theta: autograd (_q_hessian)
                hessian = None
            if hessian is not None:
                parts["observation"] = hessian
    return parts


def _q_hessian(parts: dict, blocks: list, w0: Tensor) -> Tensor:
    """The Hessian of ``Q`` at ``w0`` ``(d, d)`` on the CPU, block diagonal in the parts of
    :func:`_q_parts`: each part's block in closed form where it has one, else by autograd over the
    part's own parameters."""
    d = w0.numel()
    hessian = torch.zeros(d, d, dtype=w0.dtype)
    owner = np.concatenate([[b.key.startswith("f.") or b.key == "Rw"] * b.n_working for b in blocks] or [[]])
    for name, mine in (("transition", owner.astype(bool)), ("observation", ~owner.astype(bool))):
        idx = torch.as_tensor(np.flatnonzero(mine), dtype=torch.long)
        part = parts[name]
        if idx.numel() and isinstance(part, Tensor):
            hessian[idx.unsqueeze(-1), idx] = part[idx.unsqueeze(-1), idx].detach().cpu()
        elif idx.numel():

            def restricted(v: Tensor, part=part, idx=idx) -> Tensor:
                return part(w0.index_put((idx,), v))

            h = torch.autograd.functional.hessian(restricted, w0[idx], vectorize=True)
            hessian[idx.unsqueeze(-1), idx] = h.detach().cpu()
    return hessian


def _natural_covariance(ll: _LogLikelihood, blocks: list, w0: Tensor, cov_w: np.ndarray) -> tuple:
    """The delta method from the working covariance ``cov_w`` to the natural entries: their
    estimate, covariance (NaN rows and columns for the entries an undetermined working direction
    touches) and the Jacobian ``J`` of the map."""
    d = w0.numel()

    def natural(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        return torch.cat([b.natural_entries(params[b.key]) for b in blocks]) if blocks else w

    J = np.zeros((0, 0))
    if d:
        J = torch.autograd.functional.jacobian(natural, w0, vectorize=True).cpu().numpy()
    with np.errstate(invalid="ignore"):
        cov = J @ np.nan_to_num(cov_w) @ J.T
    bad = ~np.isfinite(np.diagonal(cov_w)) if d else np.zeros(0, dtype=bool)
    if bad.any():  # the undetermined working directions leave their natural entries undetermined
        touched = (np.abs(J[:, bad]) > 0).any(1)
        cov[touched, :] = np.nan
        cov[:, touched] = np.nan
    with torch.no_grad():
        estimate = natural(w0).cpu().numpy()
    return estimate, cov, J

#: Eigenvalues of the information below this fraction of the largest count as zero.
_RANK_TOLERANCE = 1e-10

#: A working parameter with more than this share of its direction (squared eigenvector entries) in
#: the undetermined eigendirections gets no standard error (NaN); the others come from the inverse
#: on the determined subspace.
_LOADING_TOLERANCE = 1e-2


def _inverse(info: np.ndarray) -> np.ndarray:
    """The inverse of the information; NaN rows and columns for the parameters that load on its
    non-positive eigenvalues (Monte Carlo error or parameters the data do not determine)."""
    if info.size == 0:
        return info
    vals, vecs = np.linalg.eigh(info)
    good = vals > _RANK_TOLERANCE * max(vals.max(), 0.0)
    cov = (vecs[:, good] / vals[good]) @ vecs[:, good].T
    if not good.all():
        loads = (vecs[:, ~good] ** 2).sum(1) > _LOADING_TOLERANCE
        cov[loads, :] = np.nan
        cov[:, loads] = np.nan
    return cov


#: Rows per vectorised chunk of the per-step scores (bounds the memory).
_ROW_CHUNK = 1 << 16

#: Trajectories whose autocorrelations choose the lag window.
_WINDOW_PATHS = 64

#: Sokal's window constant: the lag window is the smallest ``K`` with ``K >= c * tau(K)``.
_SOKAL_C = 5.0

#: The trajectories are drawn as pieces (:func:`~torch_nssm.inference.ffbsi.backward_segments`):
#: each piece owns :data:`_PIECE_CORE` steps and runs :data:`_PIECE_MARGIN` steps past them, which
#: must exceed the lag window (else the pieces are drawn again with a wider margin).
_PIECE_MARGIN = 12
_PIECE_CORE = 64

#: Rejection tries per backward index before its exact ``O(L)`` draw, per particle, and at least
#: :data:`_MIN_TRIES`: the draw costs ``O(L)``, a try ``O(1)`` (the tries beyond the first round are
#: drawn in rounds for the indices left, each round a dozen small operations), so more particles pay
#: for more tries.  The exact draw builds one table per distinct (row, next particle) pair, shared by
#: the indices left there, so it pays off early: 1/50 and 6 (6 / 10 / 20 tries at L = 200 / 500 /
#: 1000) take 4-12 % off the information against 1/20 and 8 (CPU time, both test models);
#: 4 rather than 6 at L = 200 (all tries in the first round, no further round: a round's dozen
#: operations a step cost more than the exact draws they save) another 4-8 % (200 trajectories).
_TRIES_PER_PARTICLE = 1 / 50
_MIN_TRIES = 4


@dataclass
class _Rows:
    """Per-step rows of the trajectories: ``x_k``, ``x_{k+1}``, ``u_k``, ``y_k`` (NaN as 0), its mask,
    whether the transition ``k -> k+1`` exists and whether anything of ``y_k`` is observed."""

    x: Tensor
    x_next: Tensor
    u: Tensor
    y: Tensor
    mask: Tensor
    valid: Tensor
    observed: Tensor

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, sl: slice) -> _Rows:
        return _Rows(*(getattr(self, k)[sl] for k in self.__dataclass_fields__))


def _pieces(T: int, margin: int, core: int) -> tuple[list[int], int, np.ndarray]:
    """Starts and length of the pieces, and which of their steps each owns ``(G, length)``: piece
    ``s`` owns ``[s c, (s + 1) c)`` and runs ``margin`` steps further (the last one ends at ``T - 1``
    and owns the steps from ``(G - 1) c`` to it), with ``c`` at most ``core``, chosen so that the
    pieces cover the record with (almost) no step drawn twice beyond the margins; one piece (whole
    trajectories) when the record is not longer than ``core + margin``."""
    if core + margin >= T:
        return [0], T, np.ones((1, T), dtype=bool)
    G = -(-(T - margin) // core)
    core = -(-(T - margin) // G)
    length = core + margin
    starts = [min(s * core, T - length) for s in range(G)]
    steps = np.asarray(starts)[:, None] + np.arange(length)
    first, end = np.arange(G) * core, np.append(np.arange(1, G) * core, T)  # the last owns to the end
    own = (steps >= first[:, None]) & (steps < end[:, None])
    return starts, length, own


def _piece_rows(X: Tensor, data: SequenceBatch, Js: Tensor, starts: list[int]) -> _Rows:
    """The rows of trajectory pieces ``Js`` ``(G, n, B, M)``, ordered ``(G, n, B, M)``."""
    G, n, B, M = Js.shape
    T, _, L, nx = X.shape
    device = X.device
    times = torch.as_tensor(starts, device=device).unsqueeze(1) + torch.arange(n, device=device)  # (G, n)
    flat = (times.view(G, n, 1, 1) * B + torch.arange(B, device=device).view(1, 1, B, 1)) * L + Js
    paths = X.reshape(-1, nx)[flat.view(-1)].view(G, n, B, M, nx)
    x_next = torch.cat([paths[:, 1:], paths[:, -1:]], 1)  # a piece's last step has no transition
    trans = torch.cat([data.transition_mask, torch.zeros_like(data.transition_mask[:1])], 0)[times]
    valid = trans & (torch.arange(n, device=device) < n - 1).view(1, n, 1)  # (G, n, B)

    def rows(a: Tensor) -> Tensor:  # (G, n, B, ...) -> (G * n * B * M, ...)
        a = a.unsqueeze(3)
        return a.expand(*a.shape[:3], M, *a.shape[4:]).reshape(G * n * B * M, *a.shape[4:])

    y, mask = torch.nan_to_num(data.y)[times], data.obs_mask[times]
    return _Rows(
        paths.reshape(-1, nx), x_next.reshape(-1, nx), rows(data.u[times]), rows(y), rows(mask),
        rows(valid.to(X.dtype).unsqueeze(-1)).squeeze(-1),
        rows(mask.any(-1).to(X.dtype).unsqueeze(-1)).squeeze(-1),
    )


def _score_variance(
    ll: _LogLikelihood,
    w0: Tensor,
    model: StateSpaceModel,
    data: SequenceBatch,
    estep_out: EStepOutput,
    n_trajectories: int,
    all_observed: bool,
    generator: torch.Generator | None,
) -> tuple[np.ndarray, int, np.ndarray]:
    """``Var[sum_k s_k | y]`` (lag-windowed), the lag window and the mean score, from ``M`` draws of
    pieces of smoothed trajectories.

    The window sums the covariances ``Cov(s_k, s_j)`` of the per-step scores up to a lag ``K``
    (:func:`_windowed_covariance`), so only pieces that span each step and ``K`` steps after it
    are needed: pieces of :data:`_PIECE_CORE` + :data:`_PIECE_MARGIN` steps, drawn backward all at
    once from the E-step's marginal smoothing weights (one short loop instead of one of ``T``
    steps).  Where the window the scores call for does not fit in the margin, the pieces are drawn
    again with a margin of twice the window.
    """
    X = estep_out.filter.particles
    T = X.shape[0]
    tries = int(min(53, max(_MIN_TRIES, X.shape[2] * _TRIES_PER_PARTICLE)))
    margin = _PIECE_MARGIN
    while True:
        starts, length, own = _pieces(T, margin, max(_PIECE_CORE, 3 * margin))
        Js = backward_segments(
            model, data, estep_out.filter, n_trajectories, starts, length,
            log_weights=estep_out.smoother.log_weights, max_tries=tries, generator=generator,
        )
        G, n, B, M = Js.shape
        scores = _row_scores(ll, w0, _piece_rows(X, data, Js, starts), all_observed).view(G, n, B, M, -1)
        V, lag, mean_score = _windowed_covariance(scores, torch.as_tensor(own, device=X.device))
        if G == 1 or lag < margin:
            return V, lag, mean_score
        margin = 2 * lag


def _row_scores(ll: _LogLikelihood, w0: Tensor, rows: _Rows, all_observed: bool) -> Tensor:
    """Per row, the gradient of ``log p(y_k | x_k) + log p(x_{k+1} | x_k)`` in the working parameters
    ``(R, d)`` (masked by ``observed`` and ``valid``).

    The noise parameters' scores are closed form given the residuals (:func:`_closed_form_scores`);
    the module parameters' are the residual gradients times the modules' Jacobians in their
    parameters (:func:`_module_jacobian`).  Where that is not possible (a noise family without
    closed-form scores, or partly observed outputs of a multivariate one; a module the Jacobian's
    vectorisation over the rows cannot batch) the whole row is differentiated by reverse mode,
    vectorised over the rows (:func:`_row_scores_autograd`).
    """
    out = torch.empty(len(rows), w0.numel(), dtype=w0.dtype, device=w0.device)
    closed = ll.noise.scores_in_closed_form(all_observed)
    for start in range(0, len(rows), _ROW_CHUNK):
        chunk = rows[start : start + _ROW_CHUNK]
        done = False
        if closed:
            try:
                out[start : start + _ROW_CHUNK] = _closed_form_scores(ll, w0, chunk)
                done = True
            except (RuntimeError, NotImplementedError):  # a module vmap cannot batch row by row
                closed = False
        if not done:
            out[start : start + _ROW_CHUNK] = _row_scores_autograd(ll, w0, chunk, all_observed)
    return out


def _linear_in_parameters(module: nn.Module) -> bool:
    """Whether ``module`` computes ``offset + Phi theta`` (a :class:`LinearInParameters`, whose
    ``forward`` is by contract that function, without hooks): its Jacobian in ``theta`` is ``Phi``.
    :func:`_module_jacobian` checks the contract on the rows' first few."""
    return isinstance(module, LinearInParameters) and not (module._forward_hooks or module._forward_pre_hooks)


def _matches_features(
    module: nn.Module, x: Tensor, u: Tensor, Phi: Tensor, offset: Tensor, theta: Tensor
) -> bool:
    """Whether ``module(x, u)`` is ``offset + Phi theta`` on these rows (the contract's check)."""
    return torch.allclose(module(x, u), offset + (Phi @ theta.unsqueeze(-1)).squeeze(-1))


def _module_columns(ll: _LogLikelihood, label: str) -> tuple[list[int], list[_Block]]:
    cols, parts, start = [], [], 0
    for block, size in zip(ll.blocks, ll.sizes):
        if block.key.startswith(label + "."):
            cols.extend(range(start, start + size))
            parts.append(block)
        start += size
    return cols, parts


def _linear_features(module: nn.Module, x: Tensor, u: Tensor, dtype: torch.dtype):
    """``(Phi, offset, theta, free)`` of a module linear in its parameters on rows ``x``, ``u``
    (its free entries' indices ``free``); :class:`_NotLinear` where its forward is not
    ``offset + Phi theta`` (checked on the first rows)."""
    with torch.no_grad():
        Phi, offset = module.features(x, u)
        theta = module.theta().detach().to(dtype)
        head = slice(0, 8)
        if not _matches_features(module, x[head], u[head], Phi[head], offset[head], theta):
            raise _NotLinear(f"{type(module).__name__}.forward is not offset + Phi theta")
        free = torch.nonzero(module.free_mask()).squeeze(-1)
    return Phi, offset, theta, free


def _module_jacobian(
    ll: _LogLikelihood, label: str, w: Tensor, x: Tensor, u: Tensor, linear: tuple | None = None
):
    """``module(x, u)`` ``(R, out)`` at the working parameters ``w``, its Jacobian in the module's
    working parameters ``(R, out, d_module)`` (``None`` without free parameters) and their columns
    in ``w``.

    For a module linear in its parameters the value is ``offset + Phi theta`` and the Jacobian
    ``Phi``'s free columns (``linear``: its :func:`_linear_features` on these rows, if already at
    hand); otherwise each row's Jacobian by reverse mode, vectorised over the rows."""
    module = ll.model.f if label == "f" else ll.model.g
    cols, parts = _module_columns(ll, label)
    if cols and _linear_in_parameters(module):
        Phi, offset, theta, free = linear or _linear_features(module, x, u, w.dtype)
        value = offset + (Phi @ theta.unsqueeze(-1)).squeeze(-1)
        return value, (Phi if free.numel() == theta.numel() else Phi[..., free]), cols
    with torch.no_grad():
        value = module(x, u)
    if not cols:
        return value, None, cols
    idx = torch.as_tensor(cols, device=w.device)
    sizes = [b.n_working for b in parts]

    def row(v: Tensor, x_r: Tensor, u_r: Tensor) -> Tensor:
        split = torch.split(v, sizes)
        params = {b.key[len(label) + 1 :]: p.reshape(b.value.shape) for b, p in zip(parts, split)}
        return functional_call(module, params, (x_r.unsqueeze(0), u_r.unsqueeze(0)))[0]

    # each row's Jacobian by reverse mode, vectorised over the rows: 2-9x faster than forward mode
    # over all rows (torch.func.jacfwd), whose first use also loads torch's forward-mode
    # decompositions through the deprecated torch.jit.script (18 DeprecationWarnings)
    jac = torch.func.vmap(torch.func.jacrev(row), in_dims=(None, 0, 0))(w[idx].detach(), x, u)
    return value, jac.detach(), cols


def _columns(ll: _LogLikelihood) -> dict[str, slice]:
    offsets = np.cumsum([0] + ll.sizes)
    return {b.key: slice(int(offsets[i]), int(offsets[i + 1])) for i, b in enumerate(ll.blocks)}


class _NotLinear(RuntimeError):
    """A :class:`LinearInParameters` module whose ``forward`` is not ``offset + Phi theta``."""


def _transition_scores(
    ll: _LogLikelihood, w: Tensor, x: Tensor, u: Tensor, x_next: Tensor, weight: Tensor
) -> list[tuple[list[int], Tensor]]:
    """``weight`` times the gradient of ``log N(x_next; f(x, u), Rw)`` per row, as ``(columns of w,
    rows (R, k))`` pairs for ``f``'s and ``Rw``'s parameters."""
    params = ll.unpack(w)
    col = _columns(ll)
    fx, Jf, f_cols = _module_jacobian(ll, "f", w, x, u)
    C, Ci = cholesky_and_inverse(params["Rw"] if "Rw" in params else ll.model.Rw.detach().to(w.dtype))
    z = (x_next - fx) @ Ci.mT
    v = z @ Ci  # Rw^-1 (x_next - f)
    weight = weight.unsqueeze(-1)
    out = []
    if Jf is not None:
        out.append((f_cols, weight * _row_products(v, Jf)))
    if "Rw" in col:
        out.append((list(range(col["Rw"].start, col["Rw"].stop)), weight * log_cholesky_scores(C, z, v, 1.0)))
    return out


def _observation_scores(
    ll: _LogLikelihood, w: Tensor, x: Tensor, u: Tensor, y: Tensor, mask: Tensor, weight: Tensor
) -> list[tuple[list[int], Tensor]]:
    """``weight`` times the gradient of ``log p_v(y - g(x, u))`` per row (the observed components),
    as ``(columns of w, rows (R, k))`` pairs for ``g``'s and the noise's parameters: the noise
    family's closed forms (:meth:`~torch_nssm.core.noise.MeasurementNoise.residual_scores`), the
    gradient in the mean times ``g``'s Jacobian."""
    params = ll.unpack(w)
    col = _columns(ll)
    gx, Jg, g_cols = _module_jacobian(ll, "g", w, x, u)
    r = torch.where(mask, y - gx, torch.zeros_like(gx))
    grad_mu, put = ll.noise_at(params, w.dtype).residual_scores(r, mask, weight.unsqueeze(-1))
    out = []
    if Jg is not None:
        out.append((g_cols, _row_products(grad_mu, Jg)))
    out.extend((list(range(col[k].start, col[k].stop)), v) for k, v in put.items() if k in col)
    return out


def _closed_form_scores(ll: _LogLikelihood, w0: Tensor, rows: _Rows) -> Tensor:
    """Per-row scores ``(R, d)`` in closed form given the residuals.

    The transition's: with ``r`` a residual, ``Rw = C C^T``, ``z = C^-1 r`` and ``v = Rw^-1 r``, the
    gradient in the prediction is ``v``, in the log-Cholesky entries ``C_ii v_i z_i - 1`` (diagonal,
    log scale) and ``v_i z_j`` (``i > j``).  The observation's are the noise family's
    (:meth:`~torch_nssm.core.noise.MeasurementNoise.residual_scores`).  The module parameters'
    scores are the prediction gradients times the modules' Jacobians (:func:`_module_jacobian`).
    """
    out = torch.zeros(len(rows), w0.numel(), dtype=w0.dtype, device=w0.device)
    with torch.no_grad():
        parts = _transition_scores(ll, w0, rows.x, rows.u, rows.x_next, rows.valid)
        parts += _observation_scores(ll, w0, rows.x, rows.u, rows.y, rows.mask, rows.observed)
    for cols, value in parts:
        if cols == list(range(cols[0], cols[0] + len(cols))):
            out[:, cols[0] : cols[0] + len(cols)] = value
        else:
            out[:, cols] = value
    return out


def _row_products(a: Tensor, J: Tensor) -> Tensor:
    """``a_r^T J_r`` per row: ``a`` ``(R, n)``, ``J`` ``(R, n, k)`` -> ``(R, k)`` (elementwise for small
    ``n``: a batched product of ``1 x n`` by ``n x k`` matrices is ~5x slower)."""
    out = a[:, :1] * J[:, 0]
    for i in range(1, a.shape[1]):
        out = out + a[:, i : i + 1] * J[:, i]
    return out


def _gaussian_moments(
    ll: _LogLikelihood,
    label: str,
    x: Tensor,
    u: Tensor,
    target: Tensor,
    weight: Tensor,
    linear: tuple | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
    """For a Gaussian term ``sum_r w_r log N(target_r; m(x_r, u_r), Sigma)`` whose mean
    ``m = offset + Phi theta`` is linear in the module's parameters: the weighted moments that
    give ``E(theta) = sum_r w_r e_r e_r^T``, ``e_r = target_r - m_r``, for any ``theta``
    (docs/method.md §4, as the M-step's normal equations), and the module's ``theta``, its free
    entries and their columns in ``w``.  ``None`` where the module is not linear in its parameters
    (``linear``: its :func:`_linear_features` on these rows, if already at hand)."""
    module = ll.model.f if label == "f" else ll.model.g
    cols, _ = _module_columns(ll, label)
    with torch.no_grad():
        if not cols:  # nothing free: the mean is a constant
            e, Phi = target - module(x, u), None
            theta = free = None
        elif _linear_in_parameters(module):
            try:
                Phi, offset, theta, free = linear or _linear_features(module, x, u, x.dtype)
            except _NotLinear:
                return None
            e = target - offset
        else:
            return None
        n = e.shape[-1]
        root = weight.clamp_min(0.0).sqrt().unsqueeze(-1)  # the weights are not negative
        if Phi is None:
            e = e * root
            G = e.mT @ e
        else:
            # the features' columns that are zero on every row (e.g. half of a Kronecker product's)
            # add nothing: the product over the others only (a third of the work for
            # LinearTransition), of the rows scaled by the weights' roots (a product of a matrix by
            # its own transpose: ~3x cheaper than of two)
            Phi = Phi.reshape(-1, n * Phi.shape[-1])
            used = torch.nonzero((Phi != 0).any(0)).squeeze(-1)
            F = torch.cat([e, Phi.index_select(1, used)], -1).mul_(root)
            Gu = F.mT @ F
            keep = torch.cat([torch.arange(n, device=used.device), n + used])
            G = torch.zeros(n + Phi.shape[-1], n + Phi.shape[-1], dtype=Gu.dtype, device=Gu.device)
            G[keep.unsqueeze(-1), keep] = Gu  # (n + n P, n + n P)
    return G, theta, free, torch.as_tensor(cols, dtype=torch.long), n


def _gaussian_term(moments, w: Tensor, Sigma: Tensor, extra: Tensor | None, count: Tensor | float) -> Tensor:
    """``-tr(Sigma^-1 (E(theta) + extra)) / 2 - count log det Sigma / 2`` from :func:`_gaussian_moments`,
    with the module's free parameters taken from ``w``."""
    G, theta, free, cols, n = moments
    if theta is None:
        E = G
    else:
        th = theta.index_copy(0, free, w[cols.to(w.device)])
        P = th.numel()
        M1 = G[:n, n:].reshape(n, n, P)  # sum w e_i Phi_jp
        M2 = G[n:, n:].reshape(n, P, n, P)  # sum w Phi_ip Phi_jq
        cross = M1 @ th  # (n, n): sum w e_i (Phi theta)_j
        E = G[:n, :n] - cross - cross.mT + torch.einsum("p,ipjq,q->ij", th, M2, th)
    if extra is not None:
        E = E + extra
    C, Ci = cholesky_and_inverse(Sigma)
    return -0.5 * (Ci @ E @ Ci.mT).diagonal().sum() - count * torch.log(torch.diagonal(C)).sum()


def _elliptical_observation_hessian(ll: _LogLikelihood, w0: Tensor, obs) -> Tensor | None:
    """The Hessian ``(d, d)`` of the observation part of ``Q``, ``sum_r W_r log p_v(y_r - g(x_r))``
    (every component observed), for ``g`` linear in its parameters and a noise family whose
    log-density is ``h(q) - log det C`` with ``q = |C^-1 (y - g)|^2``, ``Rv = C C^T``
    (:meth:`~torch_nssm.core.noise.MeasurementNoise.elliptical_terms` gives ``lam = -2 h_q``,
    ``h_qq`` and the terms in its other parameters); ``None`` otherwise.

    * ``sum_r W_r h_q d2 q`` is the Hessian of ``-sum_r W_r lam_r q_r(w) / 2`` with the ``lam_r``
      held fixed: a Gaussian term with weights ``W lam``, from its moments
      (:func:`_gaussian_moments`, a tiny function of ``w``);
    * ``sum_r W_r h_qq dq dq^T`` is one weighted product of the rows' ``dq`` (closed form:
      ``-2 Phi^T v`` and ``-2 v_i z_j``, ``-2 C_ii v_i z_i``);
    * the terms in the family's other (scalar) parameters are closed form per row.
    The log-determinant is linear on the log-Cholesky scale."""
    x, u, y, mask, W = obs
    col = _columns(ll)
    params = ll.unpack(w0)
    g = ll.model.g  # its features once, for its Jacobian and its moments
    linear = None
    if _module_columns(ll, "g")[0] and _linear_in_parameters(g):
        linear = _linear_features(g, x, u, w0.dtype)
    with torch.no_grad():
        gx, Jg, g_cols = _module_jacobian(ll, "g", w0, x, u, linear)
        noise = ll.noise_at(params, w0.dtype)
        p = y.shape[-1]
        C, Ci = cholesky_and_inverse(noise.Rv)
        z = (y - gx) @ Ci.mT
        v = z @ Ci
        q = (z * z).sum(-1)
        terms = noise.elliptical_terms(q, p, [k for k in noise.parameters() if k in col and k != "Rv"])
        if terms is None:
            return None
        lam, h_qq, shape = terms
        # dq only in the columns q depends on (g's and Rv's; not the other noise parameters', nor
        # f's and Rw's)
        parts = []
        if Jg is not None:
            parts.append((list(g_cols), -2.0 * _row_products(v, Jg)))
        if "Rv" in col:
            diagonal = (torch.arange(p * (p + 1) // 2, device=w0.device) < p).to(w0.dtype)
            rv_cols = list(range(col["Rv"].start, col["Rv"].stop))
            parts.append((rv_cols, -2.0 * (log_cholesky_scores(C, z, v, 1.0) + diagonal)))
        H = torch.zeros(w0.numel(), w0.numel(), dtype=w0.dtype, device=w0.device)
        if parts:
            idx = torch.as_tensor(sum((c for c, _ in parts), []), device=w0.device)
            dq = torch.cat([value for _, value in parts], -1)  # (R, columns of idx)
            H[idx.unsqueeze(-1), idx] = (dq * (W * h_qq).unsqueeze(-1)).mT @ dq
        for name, (cross_term, second) in shape.items():
            if col[name].stop - col[name].start != 1:
                return None  # closed forms for scalar parameters only: autograd
            k = col[name].start
            if parts:
                cross = dq.mT @ (W * cross_term)
                H[k, idx] += cross
                H[idx, k] += cross
            H[k, k] += (W * second).sum()
        moments = _gaussian_moments(ll, "g", x, u, y, W * lam, linear)
    if moments is None:
        return None

    def weighted(w: Tensor) -> Tensor:
        return _gaussian_term(moments, w, ll.unpack(w).get("Rv", ll.model.noise.Rv), None, 0.0)

    return H + torch.autograd.functional.hessian(weighted, w0, vectorize=True)


def _row_scores_autograd(ll: _LogLikelihood, w0: Tensor, rows: _Rows, all_observed: bool) -> Tensor:
    """:func:`_row_scores` by reverse-mode autograd of each row's log-density (vectorised over the
    rows with ``torch.func``): general, and the reference the closed forms are tested against."""
    dtype = w0.dtype
    one = torch.ones(1, dtype=dtype, device=w0.device)

    def row(w, x, xn, u, yk, mk, vk, ok):
        params = ll.unpack(w)
        x, u = x.unsqueeze(0), u.unsqueeze(0)
        out = vk * ll.transition(params, xn.unsqueeze(0) - ll.f(params, x, u), one, None, 1.0)
        r = torch.where(mk, yk - ll.g(params, x, u)[0], torch.zeros_like(yk))
        return out + ok * ll.observation(params, r.unsqueeze(0), mk.unsqueeze(0), all_observed)[0]

    args = (rows.x, rows.x_next, rows.u, rows.y, rows.mask, rows.valid, rows.observed)
    vectorised = torch.func.vmap(torch.func.grad(row), in_dims=(None,) + (0,) * 7, chunk_size=_ROW_CHUNK)
    grads = vectorised(w0, *args)
    return grads.detach()


@torch.inference_mode()  # returns arrays only: no autograd bookkeeping on its ~200 small operations
def _windowed_covariance(
    scores: Tensor, own: Tensor, lag: int | None = None
) -> tuple[np.ndarray, int, np.ndarray]:
    """``Var[sum_k s_k | y]`` from per-step scores ``(G, n, B, M, d)`` of ``M`` draws of ``G``
    trajectory pieces, summing the cross-step covariances ``Cov(s_k, s_j)`` up to a lag window
    ``K``; ``own`` ``(G, n)`` marks the steps each piece stands for (every step of the record once).
    Also the lag ``K`` and the mean score ``E[sum_k s_k | y]``.

    Each of the ``T^2`` cross terms has a particle bias of order ``1/L``; summed over all pairs
    that is ``T^2 / L`` against a variance of order ``T``, so the plain covariance of the
    trajectories' total scores is biased by a relative ``O(T / L)`` (measured: +20 % on a
    measurement-noise variance with ``T = 300``, ``L = 2000``).  The true covariances decay
    geometrically with the lag (the smoother forgets), so the window keeps what matters:
    Sokal's rule on the autocorrelation of each parameter's score, the largest window over the
    parameters (docs/uncertainty.md).  A piece gives ``Cov(s_k, s_j)`` for its owned ``k`` and
    ``k <= j <= k + K`` (it must run ``K`` steps past them):
    ``V = sum_k sum_{|j - k| <= K} c_k c_j^T = V1 + V1^T - sum_k c_k c_k^T`` with
    ``V1 = sum_k c_k (sum_{j=k}^{k+K} c_j)^T``.  ``lag`` sets ``K`` instead (tests).
    """
    G, n, B, M, d = scores.shape
    # autocovariance of each parameter's centred score over the pieces' steps, summed over (at most
    # _WINDOW_PATHS) draws, the pieces and the sequences, per lag divided by its number of pairs: it
    # only chooses the window.  From the products of all pairs of steps, one batched product of
    # (d, n, draws) by its transpose, summed along the diagonals (~7x cheaper than by FFT for
    # the pieces' ~70 steps)
    some = scores[:, :, :, :_WINDOW_PATHS]
    some = (some - some.mean(3, keepdim=True)).permute(4, 1, 0, 2, 3).reshape(d, n, -1)
    S = some @ some.mT  # (d, n, n): sum over the series of s_i s_j
    ar = torch.arange(n, device=S.device)
    cols = ar.unsqueeze(-1) + ar  # (i, k) -> i + k
    S = torch.cat([S, torch.zeros_like(S)], -1)  # S[:, i, i + k] is 0 past the last step
    acov = torch.gather(S, 2, cols.expand(d, n, n)).sum(1).T  # (n, d): lag k summed over i
    acov = (acov / torch.arange(n, 0, -1, dtype=acov.dtype, device=acov.device).unsqueeze(-1)).cpu().numpy()
    rho = acov / np.where(acov[:1] > 0, acov[:1], 1.0)
    tau = 1.0 + 2.0 * np.cumsum(rho[1:], axis=0)  # tau(K) for K = 1 .. n-1
    K = np.arange(1, n)
    if lag is None:
        lag = 0
        for i in range(d):
            ok = K >= _SOKAL_C * tau[:, i] if n > 1 else np.zeros(0, dtype=bool)
            lag = max(lag, int(K[ok][0]) if ok.any() else n - 1)
    # piece by piece (a piece's scores stay in cache through the few passes), uncentred: per
    # sequence sum_m c_k c_j^T = sum_m s_k s_j^T - S_k S_j^T / M with S_k = sum_m s_k, so that the
    # draws' scores are read by a cumulative sum, one difference and one product (the centring is
    # the same sums over the sequences' S, M times smaller); the owned steps [a, b) are consecutive
    V = torch.zeros(d, d, dtype=scores.dtype, device=scores.device)
    centring = torch.zeros(d, d, dtype=scores.dtype, device=scores.device)
    mean_score = torch.zeros(d, dtype=scores.dtype, device=scores.device)
    own = own.to(scores.device)
    for g in range(G):
        s = scores[g]  # (n, B, M, d)
        steps = torch.nonzero(own[g]).squeeze(-1)
        a, b = int(steps[0]), int(steps[-1]) + 1
        if b - a != steps.numel():
            raise ValueError("the steps a piece owns must be consecutive")
        top = min(b + lag, n)
        hi = torch.clamp(torch.arange(a, b, device=s.device) + lag, max=n - 1) - a + 1
        cs = torch.empty(top - a + 1, B, M, d, dtype=s.dtype, device=s.device)
        cs[0] = 0.0
        torch.cumsum(s[a:top], 0, out=cs[1:])  # cs[i]: sum over [a, a + i)
        half = cs[hi].sub_(cs[: b - a]).sub_(s[a:b], alpha=0.5)  # sum_{j=k}^{k+K} s_j - s_k / 2
        V += s[a:b].reshape(-1, d).mT @ half.reshape(-1, d)  # (V1 + V1^T - sum s s^T) / 2
        S = s[a:top].sum(2)  # (top - a, B, d)
        cS = torch.cat([torch.zeros_like(S[:1]), torch.cumsum(S, 0)])
        centring += S[: b - a].reshape(-1, d).mT @ (cS[hi] - cS[: b - a] - 0.5 * S[: b - a]).reshape(-1, d)
        mean_score += S[: b - a].sum((0, 1)) / M
    V = 2.0 * (V - centring / M)  # symmetrised below
    V = (V / max(M - 1, 1)).cpu().numpy()
    return 0.5 * (V + V.T), lag, mean_score.cpu().numpy()
