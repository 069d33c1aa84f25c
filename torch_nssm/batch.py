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
from .em import e_step, m_step
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
            return offset + (Phi * theta).sum(-1)  # elementwise: no batch of tiny matmuls

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


def _batched_linear_solve(
    template: LinearInParameters,
    thetas: Tensor,
    x: Tensor,
    u: Tensor,
    target: Tensor,
    weight: Tensor,
    whitener: Tensor,
    ridge: float = 1e-12,
) -> tuple[Tensor, Tensor]:
    """Closed-form weighted least squares for ``B`` independent parameter vectors at once.

    Rows are time-major ``(T, B, L, ...)``: ``x`` ``(T, B, L, nx)``, ``target`` ``(T, B, L, d)``
    (zero where missing), ``weight`` ``(T, B, L)``, ``thetas`` ``(B, P)``; ``whitener`` ``C``,
    broadcastable to ``(T, B, L, d, d)``, defines the metric ``C^T C`` (zero columns for missing
    components).  The whitened, weighted rows are stacked per data set and the normal equations
    are two batched matmuls.  Returns the new ``thetas`` (the old one where a solve is not
    finite) and the fitted means.
    """
    free = template.free_mask()
    Phi, offset = template.features(x, u)  # (T, B, L, d, P), (T, B, L, d)
    if bool((~free).any()):
        fixed = thetas[:, ~free]
        offset = offset + (Phi[..., ~free] * fixed.view(1, fixed.shape[0], 1, 1, -1)).sum(-1)
    A = Phi[..., free]
    sw = weight.sqrt().unsqueeze(-1)
    CA = _small_matmul(whitener, A) * sw.unsqueeze(-1)  # (T, B, L, d, F)
    Cr = _small_matmul(whitener, (target - offset).unsqueeze(-1)).squeeze(-1) * sw  # (T, B, L, d)
    B, F = thetas.shape[0], CA.shape[-1]
    CA = CA.transpose(0, 1).reshape(B, -1, F)
    Cr = Cr.transpose(0, 1).reshape(B, -1, 1)
    G = CA.transpose(1, 2) @ CA
    h = (CA.transpose(1, 2) @ Cr).squeeze(-1)
    scale = torch.diagonal(G, dim1=-2, dim2=-1).mean(-1).abs() + 1e-300
    eye = torch.eye(F, dtype=G.dtype, device=G.device)
    sol = torch.linalg.solve(G + ridge * scale.view(-1, 1, 1) * eye, h)
    new = thetas.clone()
    new[:, free] = sol
    new = torch.where(torch.isfinite(sol).all(-1, keepdim=True), new, thetas)
    fitted = offset + (A * new[:, free].view(1, B, 1, 1, F)).sum(-1)
    return new, fitted


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
    X, T = filt.particles, filt.particles.shape[0]
    L = X.shape[2]
    U = data.u.unsqueeze(2).expand(T, B, L, data.u.shape[-1])
    # theta_f and Rw (ECM: metric Rw_old^-1)
    theta_f, fitted = _batched_linear_solve(
        f0,
        torch.stack([m.f.theta().detach() for m in models]),
        X[:-1],
        U[:-1],
        sm.next_mean,
        sm.transition_weights,
        _inverse_cholesky(stacked.Rw).view(1, B, 1, *stacked.Rw.shape[1:]),  # metric Rw_old^-1
    )
    r = sm.next_mean - fitted
    n_trans = data.transition_mask.sum(0).clamp_min(1).to(X.dtype)
    Rw = torch.einsum("tbl,tblp,tblq->bpq", sm.transition_weights, r, r) + sm.residual_scatter
    Rw = _sym(Rw / n_trans.view(B, 1, 1)) if options.fit_Rw else stacked.Rw
    # theta_g and Rv (weights W <lam>, metric Rv_old^-1 on the observed components)
    scale = filt.scale
    observed = data.obs_mask.any(-1)  # (T, B)
    W = torch.exp(sm.log_weights) * observed.unsqueeze(-1)
    m = scale.mask.to(X.dtype)
    P = (scale.chol_inv.transpose(-1, -2) @ scale.chol_inv) * m.unsqueeze(-1) * m.unsqueeze(-2)
    y = torch.where(scale.mask, data.y, torch.zeros_like(data.y)).unsqueeze(2).expand(T, B, L, -1)
    theta_g, fitted = _batched_linear_solve(
        g0,
        torch.stack([m_.g.theta().detach() for m_ in models]),
        X,
        U,
        y,
        W * est.e_lam,
        (scale.chol_inv * m.unsqueeze(-2)).unsqueeze(2),
    )
    r = torch.where(scale.mask.unsqueeze(2), y - fitted, torch.zeros_like(fitted))
    K = stacked.Rv.unsqueeze(0) @ P  # (T, B, p, p): identity on the observed block
    rhat = _small_matmul(K.unsqueeze(2), r.unsqueeze(-1)).squeeze(-1)
    cond = stacked.Rv.unsqueeze(0) - K @ stacked.Rv.unsqueeze(0)
    n_obs = observed.sum(0).clamp_min(1).to(X.dtype)
    Rv = torch.einsum("tbl,tblp,tblq->bpq", W * est.e_lam, rhat, rhat)
    Rv = _sym((Rv + torch.einsum("tb,tbpq->bpq", W.sum(-1), cond)) / n_obs.view(B, 1, 1))
    if not options.fit_Rv:
        Rv = stacked.Rv
    dof = stacked.dof
    if options.fit_dof and not bool(torch.isinf(dof).all()):
        c = (W * (est.e_log_lam - est.e_lam)).sum((0, 2)) / n_obs
        dof = solve_dof(c, *options.dof_bounds).to(X.dtype)
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


def _small_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for huge batches of tiny matrices, elementwise (a batched matmul of millions of
    2x2 products is dominated by per-product overhead)."""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


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
            est = e_step(
                batch_model,
                all_data.select(idx),
                estimator._particles(it),
                smoother=estimator.smoother,
                resampling=estimator.resampling,
                ess_threshold=estimator.ess_threshold,
                chunk_size=estimator.chunk_size,
                generator=generator,
            )
            update = []  # positions j in the batch of the data sets that take an M-step
            for j, b in enumerate(active):
                est_b = est.select(slice(j, j + 1))
                last_est[b] = est_b
                ll = float(est_b.log_likelihood.sum())
                _record(histories[b], models[b], ll)
                lls[b].append(ll)
                if _converged(lls[b], n_obs[b], estimator.tol):
                    converged[b] = True
                elif it < estimator.n_iter:
                    update.append(j)
            still = []
            if update and batched_mstep:
                sel = torch.tensor(update, device=device)
                ids = [active[j] for j in update]
                new, valid = _linear_m_step(
                    [models[b] for b in ids], all_data.select(idx[sel]), est.select(sel), options
                )
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
                    models[b] = m_step(models[b], datas[b], est_b, options)
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
        est = e_step(
            _stack_models([models[b] for b in final]),
            all_data.select(idx),
            estimator._particles(),
            smoother=estimator.smoother,
            resampling=estimator.resampling,
            ess_threshold=estimator.ess_threshold,
            chunk_size=estimator.chunk_size,
            generator=generator,
        )
        for j, b in enumerate(final):
            last_est[b] = est.select(slice(j, j + 1))
    n_unconverged = 0
    for b in range(n_sets):
        estimators[b]._store(
            models[b],
            histories[b],
            last_est[b],
            datas[b],
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
