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
            theta = self._theta.view(self._theta.shape[0], *([1] * (Phi.dim() - 3)), -1, 1)
            return offset + (Phi @ theta).squeeze(-1)

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
                estimator.n_particles,
                smoother=estimator.smoother,
                resampling=estimator.resampling,
                ess_threshold=estimator.ess_threshold,
                chunk_size=estimator.chunk_size,
                generator=generator,
            )
            still = []
            for j, b in enumerate(active):
                est_b = est.select(slice(j, j + 1))
                last_est[b] = est_b
                ll = float(est_b.log_likelihood.sum())
                _record(histories[b], models[b], ll)
                lls[b].append(ll)
                if _converged(lls[b], n_obs[b], estimator.tol):
                    converged[b] = True
                    continue
                if it == estimator.n_iter:
                    continue
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
    n_unconverged = 0
    for b in range(n_sets):
        estimators[b]._store(
            models[b], histories[b], last_est[b], datas[b], False, n_done[b], converged[b],
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
