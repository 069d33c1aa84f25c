"""Standard errors of the fitted parameters: the observed information by Louis' identity.

At any parameter value ``theta`` (docs/uncertainty.md)::

    -d2 log p(y; theta) = E[-d2 log p(x, y; theta) | y] - Var[d log p(x, y; theta) | y]

* The first term is the Hessian of the M-step's expected complete-data log-likelihood ``Q``, written
  with the smoother's statistics exactly as the M-step writes it (docs/method.md §4): the
  transition term from the rows ``(x_k^i, u_k) -> xbar_k^i`` with weights ``s_k^i`` plus the
  parameter-free scatter, the observation term from the rows ``(x_k^l, u_k) -> y_k`` with the
  smoothing weights ``W_{k|N}^l``.  For Student-t noise the observation term is the marginal t
  density of ``y_k`` given ``x_k`` (the latent scales integrated out).
* The second term needs the *joint* smoothing distribution: ``M`` trajectories are drawn from the
  particle approximation by backward simulation
  (:func:`~torch_nssm.inference.smoothing.backward_trajectories`) and the complete-data score of
  each (autograd, per trajectory) gives its sample covariance.

Both are computed on a working scale where normal approximations are better: module parameters as
they are, full covariances (``Rw``, ``Rv``) by their log-Cholesky factor, diagonal variances and
degrees of freedom by their logarithm.  The covariance is mapped back to the natural entries by the
delta method; intervals of variances and ``dof`` are formed on the log scale.  The initial-state
prior is held fixed (its influence on a long record is negligible).
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
from ..inference.smoothing import backward_trajectories
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
    """One estimated parameter: its key (``"f.a"``, ``"Rw"``, ``"dof"``), its value and how it is
    put on the working scale (``kind``: ``"plain"``, ``"cholesky"`` (log-Cholesky of a full
    covariance), ``"logdiag"`` (log of a diagonal covariance's variances) or ``"log"``)."""

    key: str
    kind: str
    value: Tensor

    @property
    def n_working(self) -> int:
        n = self.value.shape[-1] if self.value.dim() else 1
        return {"cholesky": n * (n + 1) // 2, "logdiag": n}.get(self.kind, self.value.numel())

    def to_working(self) -> Tensor:
        v = self.value
        if self.kind == "plain":
            return v.reshape(-1)
        if self.kind == "log":
            return torch.log(v).reshape(-1)
        if self.kind == "logdiag":
            return torch.log(torch.diagonal(v))
        C = torch.linalg.cholesky(v)
        rows, cols = torch.tril_indices(v.shape[0], v.shape[0], -1)
        return torch.cat([torch.log(torch.diagonal(C)), C[rows, cols]])

    def from_working(self, w: Tensor) -> Tensor:
        if self.kind == "plain":
            return w.reshape(self.value.shape)
        if self.kind == "log":
            return torch.exp(w).reshape(self.value.shape)
        if self.kind == "logdiag":
            return torch.diag_embed(torch.exp(w))
        n = self.value.shape[0]
        rows, cols = torch.tril_indices(n, n, -1)
        C = torch.diag_embed(torch.exp(w[:n]))
        if rows.numel():
            C = C.index_put((rows, cols), w[n:])
        return C @ C.transpose(-1, -2)

    def natural_entries(self, value: Tensor) -> Tensor:
        """The free entries on the natural scale (lower triangle of a full covariance)."""
        if self.kind == "cholesky":
            rows, cols = torch.tril_indices(value.shape[0], value.shape[0])
            return value[rows, cols]
        if self.kind == "logdiag":
            return torch.diagonal(value)
        return value.reshape(-1)

    def entry_index(self) -> list[tuple[int, ...]]:
        """Index into the parameter's array of each natural entry."""
        if self.kind == "cholesky":
            rows, cols = torch.tril_indices(self.value.shape[0], self.value.shape[0])
            return list(zip(rows.tolist(), cols.tolist()))
        if self.kind == "logdiag":
            return [(i, i) for i in range(self.value.shape[0])]
        shape = tuple(self.value.shape)
        return [tuple(int(j) for j in np.unravel_index(i, shape)) for i in range(self.value.numel())]

    def working_names(self) -> list[str]:
        label = lambda i: f"[{', '.join(map(str, i))}]"  # noqa: E731
        if self.kind == "plain":
            return [self.key if self.value.dim() == 0 else self.key + label(i) for i in self.entry_index()]
        if self.kind == "log":
            suffix = (lambda i: "") if self.value.dim() == 0 else label  # noqa: E731
            return [f"log {self.key}{suffix(i)}" for i in self.entry_index()]
        if self.kind == "logdiag":
            return [f"log {self.key}{label(i)}" for i in self.entry_index()]
        n = self.value.shape[0]
        rows, cols = torch.tril_indices(n, n, -1)
        return [f"log chol({self.key})[{i}, {i}]" for i in range(n)] + [
            f"chol({self.key})[{i}, {j}]" for i, j in zip(rows.tolist(), cols.tolist())
        ]

    def log_scale(self) -> list[bool]:
        """Which natural entries are positive by construction (their intervals are formed on the log
        scale): variances and degrees of freedom."""
        return [self.kind == "log" or (self.kind != "plain" and i[0] == i[1]) for i in self.entry_index()]


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
    #: per key: (shape, positions in ``names``, index of each entry, whether its interval is on the log scale)
    layout: dict[str, tuple[tuple, list, list, list]] = field(default_factory=dict, repr=False)

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
        """Normal intervals ``(lower, upper)`` per key; variances and ``dof`` on the log scale."""
        if not 0 < level < 1:
            raise ValueError(f"level must lie in (0, 1), got {level!r}")
        z = NormalDist().inv_cdf(0.5 + level / 2)
        se = np.sqrt(np.diagonal(self.covariance))
        est = self.estimate
        lower, upper = est - z * se, est + z * se
        log = np.zeros(len(est), dtype=bool)
        for _, positions, _, logs in self.layout.values():
            log[positions] = logs
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.exp(z * se / est)
        lower = np.where(log, est / r, lower)
        upper = np.where(log, est * r, upper)
        lo, hi = self._unflatten(lower), self._unflatten(upper)
        return {k: (lo[k], hi[k]) for k in lo}

    def _unflatten(self, values: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for key, (shape, positions, index, _) in self.layout.items():
            a = np.zeros(shape)
            for pos, idx in zip(positions, index):
                a[idx] = values[pos]
                if len(idx) == 2 and key in ("Rw", "Rv"):
                    a[idx[::-1]] = values[pos]
            out[key] = a
        return out


def free_parameter_count(module: nn.Module) -> int:
    """Number of entries of the module's parameters with ``requires_grad``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def _blocks(
    model: StateSpaceModel, fit_Rw: bool, fit_Rv: bool, fit_dof: bool
) -> tuple[list[_Block], list[str]]:
    blocks, excluded = [], []
    for label, module in (("f", model.f), ("g", model.g)):
        if free_parameter_count(module) > MAX_INFORMATION_PARAMETERS:
            excluded.append(label)
            continue
        for name, p in module.named_parameters():
            if p.requires_grad:
                blocks.append(_Block(f"{label}.{name}", "plain", p.detach()))
    if fit_Rw:
        blocks.append(_Block("Rw", "cholesky", model.Rw.detach()))
    noise = model.noise
    if fit_Rv:
        blocks.append(_Block("Rv", "logdiag" if noise.per_component else "cholesky", noise.Rv.detach()))
    dof = getattr(noise, "dof", None)
    if fit_dof and dof is not None and bool(torch.isfinite(dof).all()):
        blocks.append(_Block("dof", "log", dof.detach()))
    return blocks, excluded


class _LogLikelihood:
    """The complete-data log-likelihood's terms as functions of the working parameters ``w``."""

    def __init__(self, model: StateSpaceModel, blocks: list[_Block]):
        self.model, self.blocks = model, blocks
        self.sizes = [b.n_working for b in blocks]
        self.family = type(model.noise).name
        if self.family not in ("gaussian", "student-t", "student-t-per-output"):
            raise NotImplementedError(f"standard errors are not implemented for noise={self.family!r}")
        dof = getattr(model.noise, "dof", None)
        self.gaussian = dof is None or not bool(torch.isfinite(dof).all())

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
        Rv = params.get("Rv", self.model.noise.Rv)
        dof = params.get("dof", getattr(self.model.noise, "dof", None))
        m = mask.to(r.dtype)
        if self.family == "student-t-per-output":
            var = torch.diagonal(Rv)
            half = 0.5 * (dof + 1.0)
            per = (
                torch.lgamma(half) - torch.lgamma(0.5 * dof) - 0.5 * torch.log(dof * math.pi)
                - 0.5 * torch.log(var) - half * torch.log1p(r * r / (var * dof))
            )
            return (per * m).sum(-1)
        p = r.shape[-1]
        if all_observed:
            C = torch.linalg.cholesky(Rv)
            Ci = torch.linalg.solve_triangular(C, torch.eye(p, dtype=C.dtype, device=C.device), upper=False)
            z = r @ Ci.transpose(-1, -2)
            logdet = 2.0 * torch.log(torch.diagonal(C)).sum()
            n_obs = torch.full(r.shape[:-1], float(p), dtype=r.dtype, device=r.device)
        else:  # the observed block of Rv, per row
            eye = torch.eye(p, dtype=r.dtype, device=r.device)
            Rm = Rv * m.unsqueeze(-1) * m.unsqueeze(-2) + eye * (1.0 - m).unsqueeze(-1)
            C = torch.linalg.cholesky(Rm)
            z = torch.linalg.solve_triangular(C, (r * m).unsqueeze(-1), upper=False).squeeze(-1)
            logdet = 2.0 * torch.log(torch.diagonal(C, dim1=-2, dim2=-1)).sum(-1)
            n_obs = m.sum(-1)
        delta2 = (z * z).sum(-1)
        if self.gaussian:
            return -0.5 * (n_obs * math.log(2 * math.pi) + logdet + delta2)
        half = 0.5 * (dof + n_obs)
        return (
            torch.lgamma(half) - torch.lgamma(0.5 * dof) - 0.5 * n_obs * torch.log(dof * math.pi)
            - 0.5 * logdet - half * torch.log1p(delta2 / dof)
        )


def _expected_rows(data: SequenceBatch, est: EStepOutput):
    """The M-step's weighted rows (transition and observation), above :data:`ROW_WEIGHT_CUTOFF`."""
    X, sm = est.filter.particles, est.smoother
    T, B, L, nx = X.shape
    s = sm.transition_weights
    keep = s > ROW_WEIGHT_CUTOFF
    u_rows = data.u.unsqueeze(2).expand(T, B, L, data.u.shape[-1])
    trans = (X[:-1][keep], u_rows[:-1][keep], sm.next_mean[keep], s[keep])
    observed = data.obs_mask.any(-1)  # (T, B)
    W = torch.exp(sm.log_weights) * observed.unsqueeze(-1)
    keep = W > ROW_WEIGHT_CUTOFF
    y = torch.nan_to_num(data.y).unsqueeze(2).expand(T, B, L, data.y.shape[-1])
    mask = data.obs_mask.unsqueeze(2).expand(T, B, L, data.y.shape[-1])
    obs = (X[keep], u_rows[keep], y[keep], mask[keep], W[keep])
    return trans, obs


def observed_information(
    model: StateSpaceModel,
    data: SequenceBatch,
    est: EStepOutput,
    *,
    fit_Rw: bool = True,
    fit_Rv: bool = True,
    fit_dof: bool = True,
    n_trajectories: int = DEFAULT_TRAJECTORIES,
    generator: torch.Generator | None = None,
) -> ParameterUncertainty:
    """The observed information at ``model`` by Louis' identity, and the parameters' covariance.

    Parameters
    ----------
    model : StateSpaceModel
        One (unbatched) model, shared by the sequences of ``data``.
    data : SequenceBatch
    est : EStepOutput
        The E-step of ``data`` at ``model`` (the fit's final E-step).
    fit_Rw, fit_Rv, fit_dof : bool
        Which noise parameters were estimated (the others are held fixed).
    n_trajectories : int
        Backward-simulated trajectories for the variance of the score.
    generator : torch.Generator, optional

    Returns
    -------
    ParameterUncertainty
    """
    blocks, excluded = _blocks(model, fit_Rw, fit_Rv, fit_dof)
    ll = _LogLikelihood(model, blocks)
    dtype = est.filter.particles.dtype
    with torch.no_grad():
        w0 = torch.cat([b.to_working() for b in blocks]).to(dtype) if blocks else torch.zeros(0, dtype=dtype)
    d = w0.numel()
    trans, obs = _expected_rows(data, est)
    scatter = est.smoother.residual_scatter.sum(0)
    n_trans = float(data.transition_mask.sum())
    all_observed = bool(data.obs_mask[data.obs_mask.any(-1)].all())

    # Q(w), the M-step's expected complete-data log-likelihood, in its two independent parts:
    # the transition (f, Rw) and the observation (g, Rv, dof); the Hessian is block diagonal
    def transition_part(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        x, u, xbar, s = trans
        return ll.transition(params, xbar - ll.f(params, x, u), s, scatter, n_trans)

    def observation_part(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        x, u, y, mask, W = obs
        r = torch.where(mask, y - ll.g(params, x, u), torch.zeros_like(y))
        return (W * ll.observation(params, r, mask, all_observed)).sum()

    hessian = torch.zeros(d, d, dtype=dtype)
    owner = np.concatenate([[b.key.startswith("f.") or b.key == "Rw"] * b.n_working for b in blocks] or [[]])
    for part, mine in ((transition_part, owner.astype(bool)), (observation_part, ~owner.astype(bool))):
        idx = torch.as_tensor(np.flatnonzero(mine), dtype=torch.long)
        if idx.numel():
            def restricted(v: Tensor, part=part, idx=idx) -> Tensor:
                return part(w0.index_put((idx,), v))

            h = torch.autograd.functional.hessian(restricted, w0[idx])
            hessian[idx.unsqueeze(-1), idx] = h.detach().cpu()

    # the complete-data score of each backward-simulated trajectory, per time step
    Js = backward_trajectories(model, data, est.filter, n_trajectories, generator=generator)  # (T, B, M)
    X = est.filter.particles
    T, B, L, nx = X.shape
    M = Js.shape[-1]
    paths = torch.gather(X, 2, Js.unsqueeze(-1).expand(T, B, M, nx)).permute(2, 0, 1, 3)  # (M, T, B, nx)
    H = hessian.numpy()
    if d:
        contributions = _score_contributions(ll, w0, paths, data, all_observed)  # (M, T, B, d)
        V, lag = _windowed_covariance(contributions)
        mean_score = contributions.sum((1, 2)).mean(0)
    else:
        V, lag, mean_score = np.zeros((0, 0)), 0, np.zeros(0)
    info = -H - V
    info = 0.5 * (info + info.T)
    cov_w = _inverse(info)

    # delta method to the natural entries
    def natural(w: Tensor) -> Tensor:
        params = ll.unpack(w)
        return torch.cat([b.natural_entries(params[b.key]) for b in blocks]) if blocks else w

    J = torch.autograd.functional.jacobian(natural, w0).cpu().numpy() if d else np.zeros((0, 0))
    with np.errstate(invalid="ignore"):
        cov = J @ np.nan_to_num(cov_w) @ J.T
    bad = ~np.isfinite(np.diagonal(cov_w)) if d else np.zeros(0, dtype=bool)
    if bad.any():  # the undetermined working directions leave their natural entries undetermined
        touched = (np.abs(J[:, bad]) > 0).any(1)
        cov[touched, :] = np.nan
        cov[:, touched] = np.nan
    with torch.no_grad():
        estimate = natural(w0).cpu().numpy()

    names, layout, start, working = [], {}, 0, []
    for b in blocks:
        working.extend(b.working_names())
        idx = b.entry_index()
        positions = list(range(start, start + len(idx)))
        start += len(idx)
        names.extend(b.key if b.value.dim() == 0 else f"{b.key}[{', '.join(map(str, i))}]" for i in idx)
        layout[b.key] = (tuple(b.value.shape), positions, idx, b.log_scale())
    with np.errstate(divide="ignore", invalid="ignore"):
        missing = np.diagonal(V) / np.diagonal(-H)
    return ParameterUncertainty(
        names, working, estimate, cov, info, -H, V, missing, mean_score, M, lag, excluded, J, layout
    )


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


def _score_contributions(
    ll: _LogLikelihood, w0: Tensor, paths: Tensor, data: SequenceBatch, all_observed: bool
) -> np.ndarray:
    """Per trajectory and time step, the gradient of ``log p(y_k | x_k) + log p(x_{k+1} | x_k)``
    (autograd, vectorised over the rows): ``(M, T, B, d)``."""
    M, T, B, nx = paths.shape
    dtype = paths.dtype
    x_next = torch.cat([paths[:, 1:], paths[:, -1:]], 1)  # the last step has no transition
    valid = torch.cat([data.transition_mask, torch.zeros_like(data.transition_mask[:1])], 0).to(dtype)
    observed = data.obs_mask.any(-1).to(dtype)
    y, mask = torch.nan_to_num(data.y), data.obs_mask
    one = torch.ones(1, dtype=dtype, device=paths.device)

    def row(w, x, xn, u, yk, mk, vk, ok):
        params = ll.unpack(w)
        x, u = x.unsqueeze(0), u.unsqueeze(0)
        out = vk * ll.transition(params, xn.unsqueeze(0) - ll.f(params, x, u), one, None, 1.0)
        r = torch.where(mk, yk - ll.g(params, x, u)[0], torch.zeros_like(yk))
        return out + ok * ll.observation(params, r.unsqueeze(0), mk.unsqueeze(0), all_observed)[0]

    def flat(a: Tensor) -> Tensor:  # (T, B, ...) -> (M * T * B, ...)
        return a.unsqueeze(0).expand(M, *a.shape).reshape(M * T * B, *a.shape[2:])

    args = (
        paths.reshape(M * T * B, nx), x_next.reshape(M * T * B, nx), flat(data.u), flat(y), flat(mask),
        flat(valid), flat(observed),
    )
    chunk = max(1, _ROW_CHUNK)
    grads = torch.func.vmap(torch.func.grad(row), in_dims=(None,) + (0,) * 7, chunk_size=chunk)(w0, *args)
    return grads.detach().reshape(M, T, B, -1).cpu().numpy()


#: Rows per vectorised chunk of the per-step scores (bounds the memory).
_ROW_CHUNK = 1 << 16

#: Trajectories whose autocorrelations choose the lag window.
_WINDOW_PATHS = 128

#: Sokal's window constant: the lag window is the smallest ``K`` with ``K >= c * tau(K)``.
_SOKAL_C = 5.0


def _windowed_covariance(contributions: np.ndarray) -> tuple[np.ndarray, int]:
    """``Var[sum_k s_k | y]`` from per-step scores ``(M, T, B, d)`` of ``M`` trajectories, summing
    the cross-step covariances ``Cov(s_k, s_j)`` up to a lag window ``K``.

    Each of the ``T^2`` cross terms has a particle bias of order ``1/L``; summed over all pairs
    that is ``T^2 / L`` against a variance of order ``T``, so the plain covariance of the
    trajectories' total scores is biased by a relative ``O(T / L)`` (measured: +20 % on a
    measurement-noise variance with ``T = 300``, ``L = 2000``).  The true covariances decay
    geometrically with the lag (the smoother forgets), so the window keeps what matters:
    Sokal's rule on the autocorrelation of each parameter's score, the largest window over the
    parameters (docs/uncertainty.md).
    """
    M, T, B, d = contributions.shape
    c = contributions - contributions.mean(0, keepdims=True)
    # autocovariance of each parameter's centred score by FFT, summed over (at most _WINDOW_PATHS)
    # trajectories and the sequences: it only chooses the window
    n = 1 << int(np.ceil(np.log2(2 * T)))
    F = np.fft.rfft(c[:_WINDOW_PATHS], n=n, axis=1)
    acov = np.fft.irfft((F * F.conj()).sum((0, 2)), n=n, axis=0)[:T]  # (T, d)
    rho = acov / np.where(acov[:1] > 0, acov[:1], 1.0)
    tau = 1.0 + 2.0 * np.cumsum(rho[1:], axis=0)  # tau(K) for K = 1 .. T-1
    K = np.arange(1, T)
    lag = 0
    for i in range(d):
        ok = K >= _SOKAL_C * tau[:, i] if T > 1 else np.zeros(0, dtype=bool)
        lag = max(lag, int(K[ok][0]) if ok.any() else T - 1)
    # V = sum_k sum_{|j-k| <= lag} c_k c_j^T: each step against the window sum around it
    cs = np.concatenate([np.zeros_like(c[:, :1]), np.cumsum(c, axis=1)], 1)
    hi = np.minimum(np.arange(T) + lag + 1, T)
    lo = np.maximum(np.arange(T) - lag, 0)
    window = cs[:, hi] - cs[:, lo]  # (M, T, B, d)
    V = np.einsum("mtbi,mtbj->ij", c, window) / max(M - 1, 1)
    return 0.5 * (V + V.T), lag
