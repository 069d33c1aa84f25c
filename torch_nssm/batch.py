"""Many independent fits in one tensor pass: Monte Carlo studies and restarts.

``fit_independent(estimator, us, ys)`` fits one model per data set.  The E-steps of all data sets
run together (the particle filter and smoother carry a batch dimension; ``f`` and ``g`` are
evaluated for every data set at once with ``torch.func.vmap`` over their stacked parameters), and
each data set's M-step uses only its own statistics: nothing is averaged across data sets.  The
result is a list of ordinary fitted estimators.
"""

from __future__ import annotations

import copy
import warnings
from collections import defaultdict

import numpy as np
import torch
from sklearn.base import clone
from sklearn.exceptions import ConvergenceWarning
from torch import Tensor, nn
from torch.func import functional_call, stack_module_state, vmap
from tqdm.auto import tqdm

from . import _validation as V
from ._ops import linear_combination, small_matmul, time_blocks
from .em import m_step
from .filtering import NumericalError
from .model import SequenceBatch, StateSpaceModel
from .noise import solve_dof
from .parametric import LinearInParameters

__all__ = ["StackedModule", "fit_independent"]


class StackedModule(nn.Module):
    """``B`` modules of the same architecture, evaluated together with ``vmap``.

    ``forward(x, u)`` takes ``x`` of shape ``(B, ..., nx)`` and ``u`` of shape ``(B, ..., nu)`` and
    applies module ``b`` to ``x[b], u[b]``.

    Parameters
    ----------
    modules : list of torch.nn.Module
        Modules with identical parameter and buffer names and shapes.
    """

    def __init__(self, modules: list[nn.Module]):
        super().__init__()
        params, buffers = stack_module_state(modules)
        self._params = {k: v.detach() for k, v in params.items()}
        self._buffers_stacked = {k: v.detach() for k, v in buffers.items()}
        # A stateless copy to call functionally (parameters are passed in at call time).
        self._template = [copy.deepcopy(modules[0])]
        # Modules linear in their parameters need no vmap: features once, one batched product.
        self._theta = None
        if isinstance(modules[0], LinearInParameters) and not buffers:
            self._theta = torch.stack([m.theta().detach() for m in modules])  # (B, P)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        template = self._template[0]
        if self._theta is not None:
            Phi, offset = template.features(x, u)  # (B, ..., d, P), (B, ..., d)
            theta = self._theta.view(self._theta.shape[0], *([1] * (Phi.dim() - 2)), -1)
            return offset + linear_combination(Phi, theta)  # elementwise: no batch of tiny matmuls

        def call(p, b, xb, ub):
            return functional_call(template, (p, b), (xb, ub))

        return vmap(call)(self._params, self._buffers_stacked, x, u)


def _stack_models(models: list[StateSpaceModel]) -> StateSpaceModel:
    return StateSpaceModel(
        f=StackedModule([m.f for m in models]),
        g=StackedModule([m.g for m in models]),
        Rw=torch.stack([m.Rw for m in models]),
        Rv=torch.stack([m.Rv for m in models]),
        dof=torch.stack([m.dof for m in models]),
        x0_mean=torch.stack([m.x0_mean for m in models]),
        x0_cov=torch.stack([m.x0_cov for m in models]),
    )


def _at(values: Tensor, sl: slice) -> Tensor:
    """Time block ``sl`` of a ``(T, ...)`` tensor, or the tensor itself when it has ``T = 1``
    (shared by all steps)."""
    return values if values.shape[0] == 1 else values[sl]


def _block_features(template: LinearInParameters, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """``Phi`` ``(t, B, L, d, P)`` and offset ``(t, B, L, d)`` for states ``(t, B, L, nx)`` and inputs
    ``(t, B, nu)``."""
    return template.features(x, u.unsqueeze(2).expand(*x.shape[:-1], u.shape[-1]))


def _batched_linear_solve(
    template: LinearInParameters,
    thetas: Tensor,
    x: Tensor,
    u: Tensor,
    target: Tensor,
    weight,
    whitener: Tensor,
    ridge: float = 1e-12,
) -> Tensor:
    """Closed-form weighted least squares for ``B`` independent parameter vectors at once.

    Rows are time-major ``(T, B, L, ...)``: ``x`` ``(T, B, L, nx)``, ``u`` ``(T, B, nu)``,
    ``target`` ``(T, B, L, d)`` (zero where missing), ``thetas`` ``(B, P)``; ``weight(sl)`` returns
    the row weights ``(t, B, L)`` of the time block ``sl``; ``whitener`` ``C`` of shape
    ``(T or 1, B, d, d)`` defines the metric ``C^T C`` (zero columns for missing components).  The
    normal equations ``sum w (CA)^T CA`` and ``sum w (CA)^T C r`` are accumulated block by block.
    Returns the new ``thetas`` (the old one where a solve is not finite).
    """
    free = template.free_mask()
    T, B = x.shape[:2]
    F = int(free.sum())
    G = torch.zeros(B, F, F, dtype=x.dtype, device=x.device)
    h = torch.zeros(B, F, dtype=x.dtype, device=x.device)
    fixed = thetas[:, ~free]
    for sl in time_blocks(T, B * x.shape[2]):
        Phi, offset = _block_features(template, x[sl], u[sl])
        if fixed.shape[-1]:
            offset = offset + linear_combination(Phi[..., ~free], fixed.view(1, B, 1, 1, -1))
        A = Phi[..., free] if fixed.shape[-1] else Phi
        r = target[sl] - offset
        C = _at(whitener, sl).unsqueeze(2)  # (t, B, 1, d, d)
        w = weight(sl)
        if A.shape[-2] == 1:  # one output: the metric is a scalar weight
            A, r, w = A[..., 0, :], r[..., 0], w * C[..., 0, 0] ** 2
        else:
            # whitened components become rows of their own: (t, B, L * d, F) and (t, B, L * d)
            A = small_matmul(C, A).flatten(2, 3)
            r = small_matmul(C, r.unsqueeze(-1)).squeeze(-1).flatten(2, 3)
            w = w.repeat_interleave(C.shape[-1], dim=2)
        Aw = A * w.unsqueeze(-1)
        # per-(step, set) products over the particles, then a sum over steps: ~4x faster than one
        # einsum, which copies the block into set-major order first
        G += (Aw.transpose(-1, -2) @ A).sum(0)
        h += (Aw.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1).sum(0)
    scale = torch.diagonal(G, dim1=-2, dim2=-1).mean(-1).abs() + 1e-300
    eye = torch.eye(F, dtype=G.dtype, device=G.device)
    sol = torch.linalg.solve(G + ridge * scale.view(-1, 1, 1) * eye, h)
    new = thetas.clone()
    new[:, free] = sol
    return torch.where(torch.isfinite(sol).all(-1, keepdim=True), new, thetas)


def _residual_scatter(
    template: LinearInParameters,
    thetas: Tensor,
    x: Tensor,
    u: Tensor,
    target: Tensor,
    weight,
    mask: Tensor | None = None,
    transform: Tensor | None = None,
) -> Tensor:
    """``sum_{k, l} w r r^T`` per data set, ``r = K (target - out)``, block by block.

    ``mask`` ``(T, B, d)`` zeroes the missing components of ``r`` before the optional ``transform``
    ``K`` of shape ``(T or 1, B, d, d)``; other arguments as for :func:`_batched_linear_solve`.
    """
    T, B = x.shape[:2]
    d = target.shape[-1]
    S = torch.zeros(B, d, d, dtype=x.dtype, device=x.device)
    theta = thetas.view(1, B, 1, 1, -1)
    for sl in time_blocks(T, B * x.shape[2]):
        Phi, offset = _block_features(template, x[sl], u[sl])
        r = target[sl] - offset - linear_combination(Phi, theta)  # (t, B, L, d)
        if mask is not None:
            r = torch.where(mask[sl].unsqueeze(2), r, torch.zeros_like(r))
        if transform is not None:
            r = small_matmul(_at(transform, sl).unsqueeze(2), r.unsqueeze(-1)).squeeze(-1)
        rw = r * weight(sl).unsqueeze(-1)
        S += (rw.transpose(-1, -2) @ r).sum(0)
    return S


def _linear_m_step(
    models: list[StateSpaceModel], data: SequenceBatch, est, options
) -> tuple[list[StateSpaceModel], list[bool]]:
    """The M-step of :func:`torch_nssm.em.m_step` for ``B`` independent data sets in one pass.

    For ``f`` and ``g`` linear in their parameters (closed-form solves); the formulas are those
    of :mod:`torch_nssm.mstep`, with a batch dimension instead of a loop over data sets.
    Returns the new models and, per data set, whether its update was valid (finite and
    positive definite); an invalid one keeps its previous model.
    """
    B = len(models)
    stacked = _stack_models(models)
    f0, g0 = models[0].f, models[0].g
    filt, sm = est.filter, est.smoother
    X = filt.particles
    # theta_f and Rw (ECM: metric Rw_old^-1)
    thetas_f = torch.stack([m.f.theta().detach() for m in models])
    trans_args = (X[:-1], data.u[:-1], sm.next_mean, lambda sl: sm.transition_weights[sl])
    theta_f = _batched_linear_solve(f0, thetas_f, *trans_args, _inverse_cholesky(stacked.Rw).unsqueeze(0))
    n_trans = data.transition_mask.sum(0).clamp_min(1).to(X.dtype)
    Rw = _residual_scatter(f0, theta_f, *trans_args) + sm.residual_scatter
    Rw = _sym(Rw / n_trans.view(B, 1, 1)) if options.fit_Rw else stacked.Rw
    # theta_g and Rv (weights W <lam>, metric Rv_old^-1 on the observed components)
    scale = filt.scale
    observed = data.obs_mask.any(-1)  # (T, B)

    def smoothing_weights(sl: slice) -> Tensor:  # W_{k|N}, zero where y_k is missing
        return torch.exp(sm.log_weights[sl]) * observed[sl].unsqueeze(-1)

    m = scale.mask.to(X.dtype)
    P = (scale.chol_inv.transpose(-1, -2) @ scale.chol_inv) * m.unsqueeze(-1) * m.unsqueeze(-2)
    y = scale.fill_missing(data.y).unsqueeze(2).expand(*X.shape[:-1], -1)
    thetas_g = torch.stack([m_.g.theta().detach() for m_ in models])
    obs_args = (X, data.u, y, lambda sl: smoothing_weights(sl) * est.e_lam[sl])
    theta_g = _batched_linear_solve(g0, thetas_g, *obs_args, scale.whitener())
    K = stacked.Rv.unsqueeze(0) @ P  # (T, B, p, p): identity on the observed block
    cond = stacked.Rv.unsqueeze(0) - K @ stacked.Rv.unsqueeze(0)
    n_obs = observed.sum(0).clamp_min(1).to(X.dtype)
    Rv = _residual_scatter(g0, theta_g, *obs_args, mask=scale.mask, transform=K)
    # sum_l W_{k|N}^l = 1 on the observed steps
    Rv = _sym((Rv + torch.einsum("tb,tbpq->bpq", observed.to(X.dtype), cond)) / n_obs.view(B, 1, 1))
    if not options.fit_Rv:
        Rv = stacked.Rv
    dof = stacked.dof
    if options.fit_dof and not bool(torch.isinf(dof).all()):
        c = torch.zeros(B, dtype=X.dtype, device=X.device)
        for sl in time_blocks(X.shape[0], B * X.shape[2]):
            c += (smoothing_weights(sl) * (est.e_log_lam[sl] - est.e_lam[sl])).sum((0, 2))
        dof = solve_dof(c / n_obs, *options.dof_bounds).to(X.dtype)
    x0_mean, x0_cov = stacked.x0_mean, stacked.x0_cov
    if options.fit_x0:
        w0 = torch.exp(sm.log_weights[0]).unsqueeze(-1)  # (B, L, 1)
        x0_mean = (w0 * X[0]).sum(1)
        d = X[0] - x0_mean.unsqueeze(1)
        x0_cov = _sym((w0 * d).transpose(-1, -2) @ d + Rw)
    ok = torch.isfinite(theta_f).all(-1) & torch.isfinite(theta_g).all(-1)
    for M in (Rw, Rv, x0_cov):
        ok &= torch.isfinite(M).flatten(1).all(-1) & (torch.linalg.cholesky_ex(M).info == 0)
    new_models, valid = [], ok.tolist()
    for b, model in enumerate(models):
        if not valid[b]:
            new_models.append(model)
            continue
        model.f.set_theta(theta_f[b])
        model.g.set_theta(theta_g[b])
        new_models.append(StateSpaceModel(model.f, model.g, Rw[b], Rv[b], dof[b], x0_mean[b], x0_cov[b]))
    return new_models, valid


def _inverse_cholesky(S: Tensor) -> Tensor:
    """``C`` with ``C^T C = S^-1`` (the inverse of the lower Cholesky factor)."""
    chol = torch.linalg.cholesky(S)
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device).expand_as(chol)
    return torch.linalg.solve_triangular(chol, eye, upper=False)


def _batchable(module: nn.Module) -> bool:
    """Modules whose M-step runs batched over data sets: linear in their parameters."""
    return isinstance(module, LinearInParameters)


def _sym(S: Tensor) -> Tensor:
    return 0.5 * (S + S.transpose(-1, -2))


def fit_independent(estimator, u, y, *, show_progress: bool | None = None) -> list:
    """Fit one copy of ``estimator`` to each data set, all E-steps in one batched pass.

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
        Progress bar over iterations; defaults to ``estimator.verbose > 0``.

    Returns
    -------
    list of RobustNSSMEstimator
        Fitted estimators, one per data set, each with its own parameters, ``history_``,
        ``n_iter_`` and ``converged_`` (a data set leaves the batch once it has converged).
    """
    device = estimator._check_params()
    if not V.is_sequence_list(y):
        raise ValueError("y must be a list of data sets (one array per data set)")
    n_sets = len(y)
    us = [None] * n_sets if u is None else list(u)
    if len(us) != n_sets:
        raise ValueError(f"u and y must hold the same number of data sets, got {len(us)} and {n_sets}")
    datas, models, estimators = [], [], []
    for b in range(n_sets):
        ub, yb, _ = V.as_sequence_list(us[b], y[b], dtype=estimator.dtype, device=device)
        datas.append(SequenceBatch.from_sequences(ub, yb))
        est_b = clone(estimator)
        if estimator.random_state is not None and isinstance(estimator.random_state, int):
            est_b.random_state = estimator.random_state + b
        estimators.append(est_b)
        models.append(est_b._initial_model(datas[-1], device))
    all_data = SequenceBatch.from_sequences([d.u[:, 0] for d in datas], [d.y[:, 0] for d in datas])
    options = estimator._mstep_options()
    generator = estimator._generator(device)
    n_obs = [int(d.obs_mask.any(-1).sum()) for d in datas]
    histories = [defaultdict(list) for _ in range(n_sets)]
    lls: list[list[float]] = [[] for _ in range(n_sets)]
    n_done = [0] * n_sets
    converged = [False] * n_sets
    active = list(range(n_sets))
    last_est: dict[int, object] = {}
    from .estimator import _converged, _record  # the single-fit bookkeeping, reused

    batched_mstep = all(_batchable(m) for m in (models[0].f, models[0].g))
    verbose = estimator.verbose > 0 if show_progress is None else show_progress
    bar = tqdm(total=estimator.n_iter, desc=f"robust EM x{n_sets}", disable=not verbose)
    try:
        for it in range(estimator.n_iter + 1):
            if not active:
                break
            idx = torch.tensor(active, device=device)
            batch_model = _stack_models([models[b] for b in active])
            est = estimator._e_step(batch_model, all_data.select(idx), generator, it)
            update = []  # positions j in the batch of the data sets that take an M-step
            batch_lls = est.log_likelihood.tolist()
            for j, b in enumerate(active):
                last_est[b] = (est, j)  # selected when stored (a select per set and step is costly)
                ll = batch_lls[j]
                _record(histories[b], models[b], ll)
                lls[b].append(ll)
                if _converged(lls[b], n_obs[b], estimator.tol):
                    converged[b] = True
                elif it < estimator.n_iter:
                    update.append(j)
            still = []
            if update and batched_mstep:
                ids = [active[j] for j in update]
                if len(update) == len(active):  # the usual case: no copy of the E-step output
                    sub_data, sub_est = all_data.select(idx), est
                else:
                    sel = torch.tensor(update, device=device)
                    sub_data, sub_est = all_data.select(idx[sel]), est.select(sel)
                new, valid = _linear_m_step([models[b] for b in ids], sub_data, sub_est, options)
                for b, model, good in zip(ids, new, valid):
                    if not good:
                        warnings.warn(
                            f"data set {b}: EM stopped at iteration {it + 1}: the M-step gave a "
                            "non-finite or non-positive-definite update",
                            stacklevel=2,
                        )
                        continue
                    models[b] = model
                    n_done[b] += 1
                    still.append(b)
                update = []
            for j in update:
                b = active[j]
                est_b = est.select(slice(j, j + 1))
                backup = (copy.deepcopy(models[b].f.state_dict()), copy.deepcopy(models[b].g.state_dict()))
                try:
                    models[b] = m_step(models[b], all_data.select(slice(b, b + 1)), est_b, options)
                except NumericalError as exc:
                    models[b].f.load_state_dict(backup[0])
                    models[b].g.load_state_dict(backup[1])
                    warnings.warn(f"data set {b}: EM stopped at iteration {it + 1}: {exc}", stacklevel=2)
                    continue
                n_done[b] += 1
                still.append(b)
            active = still
            bar.update(1)
    finally:
        bar.close()
    # As in a single fit: average the last iterates and/or finish at the final particle count,
    # with one more (batched) E-step at the parameters that are returned.
    K = estimator.average_last
    final = [
        b for b in range(n_sets) if (K > 1 and n_done[b] >= K) or (estimator.n_particles_final and n_done[b])
    ]
    if final:
        from .estimator import _averaged

        for b in final:
            if K > 1 and n_done[b] >= K:
                models[b] = _averaged(models[b], histories[b], K)
        idx = torch.tensor(final, device=device)
        est = estimator._e_step(_stack_models([models[b] for b in final]), all_data.select(idx), generator)
        for j, b in enumerate(final):
            last_est[b] = (est, j)
    n_unconverged = 0
    for b in range(n_sets):
        estimators[b]._store(
            models[b],
            histories[b],
            last_est[b][0].select(slice(last_est[b][1], last_est[b][1] + 1)),
            all_data.select(slice(b, b + 1)),  # padded like the E-step output (lengths kept)
            False,
            n_done[b],
            converged[b],
            y_1d=np.ndim(y[b]) == 1,
        )
        n_unconverged += not converged[b]
    if n_unconverged and estimator.tol > 0 and estimator.n_iter > 0:
        warnings.warn(
            f"{n_unconverged} of {n_sets} fits did not converge in n_iter={estimator.n_iter} iterations",
            ConvergenceWarning,
            stacklevel=2,
        )
    return estimators
