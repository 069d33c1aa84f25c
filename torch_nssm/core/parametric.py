"""Mean functions that are linear in their parameters, with a closed-form weighted M-step.

Many physical models are affine in their unknowns: the paper's ``f = a x + b u`` and
``g = c cos(x)``, or a discretised mechanical system whose stiffness entries are unknown.  For them
the weighted least-squares problems of the M-step (paper eqs. 44-45, 48; docs/method.md §4) have closed-form
solutions, which the EM engine uses instead of a gradient optimiser.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from .._ops import linear_combination, small_matmul, time_blocks

__all__ = ["LinearInParameters", "ResidualMoments", "linear_normal_equations", "solve_normal_equations"]


class LinearInParameters(nn.Module):
    """Base class for ``out = offset(x, u) + Phi(x, u) @ theta``.

    ``theta`` is the concatenation of the flattened ``nn.Parameter`` s of the module, in the order
    of :meth:`torch.nn.Module.parameters`.  Subclasses implement :meth:`features`.  A parameter with
    ``requires_grad=False`` is held fixed by :meth:`solve_weighted_least_squares`.
    """

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Regressors ``Phi`` of shape ``(..., d, P)`` and offset of shape ``(..., d)``."""
        raise NotImplementedError

    def theta(self) -> Tensor:
        """All parameters as one flat vector."""
        return torch.cat([p.reshape(-1) for p in self.parameters()])

    def free_mask(self) -> Tensor:
        """Boolean mask over ``theta``: True for entries of parameters with ``requires_grad``."""
        return torch.cat(
            [
                torch.full((p.numel(),), p.requires_grad, dtype=torch.bool, device=p.device)
                for p in self.parameters()
            ]
        )

    @torch.no_grad()
    def set_theta(self, theta: Tensor) -> None:
        """Write the flat vector ``theta`` back into the parameters (in :meth:`theta` order)."""
        start = 0
        for p in self.parameters():
            p.copy_(theta[start : start + p.numel()].view_as(p))
            start += p.numel()

    def predict(self, x: Tensor, u: Tensor, theta: Tensor) -> Tensor:
        """``offset + Phi @ theta`` for parameters ``theta`` of shape ``(..., P)`` whose leading
        dimensions broadcast against the rows' (``x`` ``(..., nx)``; e.g. ``(B, 1, 1, P)`` for one
        parameter vector per sequence), shape ``(..., d)``.

        The particle methods evaluate the modules through this method (once per time step for
        ``B * L`` particles); a subclass may override it with the few operations its model needs
        (``a * x + b * u``: 2 passes over the particles instead of building ``Phi`` and the zero
        offset, 6), and must then return the same values.
        """
        Phi, offset = self.features(x, u)
        return offset + linear_combination(Phi, theta.unsqueeze(-2))

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        if type(self).predict is not LinearInParameters.predict:  # the subclass's own evaluation
            return self.predict(x, u, self.theta())
        return self._linear(x, u, self.theta().unsqueeze(-1))

    def _linear(self, x: Tensor, u: Tensor, theta_column: Tensor) -> Tensor:
        # (..., d, P) @ (P, 1): on large batches 2.7x faster than a product with the vector (P,)
        Phi, offset = self.features(x, u)
        return offset + (Phi @ theta_column).squeeze(-1)

    def frozen(self) -> Callable[[Tensor, Tensor], Tensor]:
        """This module's ``forward`` with ``theta`` gathered once, for a pass that does not change
        the parameters (the particle filter calls ``f`` and ``g`` at every time step, where
        concatenating the parameters and the module call cost as much as the arithmetic).

        Returns the module itself when a subclass overrides ``forward`` or hooks are registered.
        """
        hooks = self._forward_hooks or self._forward_pre_hooks
        if type(self).forward is not LinearInParameters.forward or hooks:
            return self
        if type(self).predict is not LinearInParameters.predict:  # the subclass's own evaluation
            return self.frozen_predict(self.theta())
        theta_column = self.theta().unsqueeze(-1)
        return lambda x, u: self._linear(x, u, theta_column)

    def frozen_predict(self, theta: Tensor) -> Callable[[Tensor, Tensor], Tensor]:
        """:meth:`predict` with ``theta`` fixed for one filter pass over particle arrays ``(B, L, nx)``
        (``theta`` broadcast against them, e.g. ``(P,)`` or ``(B, 1, P)``): :meth:`frozen`'s evaluator,
        and a stacked module's.

        A subclass may return a function that takes the views of ``theta`` it needs once, not at
        every step; that function may also have a ``step_inputs(u)`` attribute, which maps the
        pass's time-major inputs ``u`` ``(T, B, nu)`` to what it takes in place of the particles'
        inputs at each step (e.g. the input term of every step, computed at once: the particle
        filter then passes ``step_inputs(u)[k]`` at step ``k``).  The values must equal
        ``predict(x, u, theta)``.

        Parameters
        ----------
        theta : Tensor, shape (..., P)
            The parameters, broadcast against the particles' leading dimensions.

        Returns
        -------
        callable
            ``(x, u) -> out``, shape ``(..., d)``.
        """
        return lambda x, u: self.predict(x, u, theta)

    @torch.no_grad()
    def solve_weighted_least_squares(
        self,
        x: Tensor,
        u: Tensor,
        target: Tensor,
        weight: Tensor,
        precision: Tensor | None = None,
        ridge: float = 1e-12,
    ) -> None:
        """Set the free parameters to ``argmin sum_n w_n r_n^T P_n r_n``, ``r_n = target_n - out_n``.

        Parameters
        ----------
        x : Tensor, shape (n, nx)
        u : Tensor, shape (n, nu)
        target : Tensor, shape (n, d)
            Targets; entries where ``precision`` has zero rows/columns are ignored.
        weight : Tensor, shape (n,)
            Non-negative row weights.
        precision : Tensor, shape (d, d) or (n, d, d), optional
            Metric ``P`` (inverse noise covariance); identity if omitted.
        ridge : float
            Relative Tikhonov term keeping the normal equations solvable.
        """
        free = self.free_mask()
        if not bool(free.any()):
            return
        d = target.shape[-1]
        if precision is None:
            precision = torch.eye(d, dtype=x.dtype, device=x.device)
        # the rows as n time steps of one sequence with one particle; C^T C = P
        evals, evecs = torch.linalg.eigh(precision)
        C = torch.sqrt(evals.clamp_min(0)).unsqueeze(-1) * evecs.transpose(-1, -2)
        C = C.reshape(-1, 1, d, d)
        theta = self.theta()
        G, h = linear_normal_equations(
            self, theta.unsqueeze(0), x.view(-1, 1, 1, x.shape[-1]), u.view(-1, 1, u.shape[-1]),
            torch.nan_to_num(target).view(-1, 1, 1, d), lambda sl: weight.view(-1, 1, 1)[sl], C,
        )
        sol = solve_normal_equations(G[0], h[0], ridge)
        if not bool(torch.isfinite(sol).all()):
            return
        new_theta = theta.clone()
        new_theta[free] = sol
        self.set_theta(new_theta)


def linear_normal_equations(
    template: LinearInParameters,
    thetas: Tensor,
    x: Tensor,
    u: Tensor,
    target: Tensor,
    weight: Callable[[slice], Tensor],
    whitener: Tensor,
    *,
    scatter: bool = False,
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, ResidualMoments | None]:
    """Normal equations ``G`` ``(B, F, F)``, ``h`` ``(B, F)`` of the free parameters, per sequence.

    Rows are time-major: ``x`` ``(T, B, L, nx)``, ``u`` ``(T, B, nu)``, ``target`` ``(T, B, L or 1,
    d)`` (zero where missing); ``thetas`` ``(B, P)`` supplies the fixed entries; ``weight(sl)`` gives
    the weights ``(t, B, L)`` (or ``(t, B, L, d)`` per whitened component) of the time block ``sl``;
    ``whitener`` ``C`` ``(T or 1, B, d, d)`` defines the metric ``C^T C``.  The whitened components
    of each row are rows of their own; the sums run block by block (bounded memory).

    ``scatter=True`` returns a third value: the :class:`ResidualMoments` of the same pass (one
    output and at most :data:`FEW_FEATURES` free parameters, else ``None``), from which the
    weighted residual scatter at any free parameters follows without another pass.
    """
    free = template.free_mask()
    T, B = x.shape[:2]
    F = int(free.sum())
    G = torch.zeros(B, F, F, dtype=x.dtype, device=x.device)
    h = torch.zeros(B, F, dtype=x.dtype, device=x.device)
    fixed = thetas[:, ~free]
    few = target.shape[-1] == 1 and F <= FEW_FEATURES
    moments = None
    if scatter and few:
        moments = ResidualMoments(torch.zeros_like(G), torch.zeros_like(h), x.new_zeros(B))
    for sl in time_blocks(T, B * x.shape[2]):
        xs = x[sl]
        Phi, offset = template.features(xs, u[sl].unsqueeze(2).expand(*xs.shape[:-1], u.shape[-1]))
        if fixed.shape[-1]:
            offset = offset + linear_combination(Phi[..., ~free], fixed.view(1, B, 1, 1, -1))
        A = Phi[..., free] if fixed.shape[-1] else Phi
        r = target[sl] - offset
        C = (whitener if whitener.shape[0] == 1 else whitener[sl]).unsqueeze(2)  # (t, B, 1, d, d)
        w = weight(sl)
        c2 = None
        if few:  # one output, few features
            w = w[..., 0] if w.dim() == 4 else w
            AwA, Awr = _few_feature_products(A[..., 0, :], r[..., 0], w)
            if moments is not None:  # unwhitened, and sum w r^2 (two passes more)
                r1 = r[..., 0].expand_as(w)
                moments.G += AwA.sum(0)
                moments.h += Awr.sum(0)
                moments.s += torch.linalg.vecdot(w * r1, r1).sum(0)
            c2 = C[..., 0, 0, 0] ** 2  # the metric: a scalar weight per (step, sequence), (t or 1, B)
            G += (AwA * c2[..., None, None]).sum(0)
            h += (Awr * c2[..., None]).sum(0)
            continue
        if A.shape[-2] == 1:  # one output: the metric is a scalar weight per (step, sequence)
            w = w[..., 0] if w.dim() == 4 else w
            # applied to the (t, B, F, F) products below, not to every row (one pass fewer)
            A, r, c2 = A[..., 0, :], r[..., 0], C[..., 0, 0] ** 2  # c2: (t or 1, B, 1)
        else:
            # whitened components become rows of their own: (t, B, L * d, F) and (t, B, L * d)
            A = small_matmul(C, A).flatten(2, 3)
            r = small_matmul(C, r.unsqueeze(-1)).squeeze(-1).flatten(2, 3)
            w = w.flatten(2, 3) if w.dim() == 4 else w.repeat_interleave(C.shape[-1], dim=2)
        Aw = A * w.unsqueeze(-1)
        # per-(step, sequence) products over the particles, then a sum over steps: ~4x faster than
        # one einsum, which copies the block into sequence-major order first
        AwA, Awr = Aw.transpose(-1, -2) @ A, (Aw.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)
        if c2 is not None:
            AwA, Awr = AwA * c2.unsqueeze(-1), Awr * c2
        G += AwA.sum(0)
        h += Awr.sum(0)
    return (G, h, moments) if scatter else (G, h)


@dataclass
class ResidualMoments:
    """Unwhitened weighted moments of a one-output regression, per sequence (or pooled).

    With the rows' features ``A`` of the free parameters and ``r = target - offset`` (less the
    fixed parameters' part): ``G = sum w A A^T`` ``(..., F, F)``, ``h = sum w A r`` ``(..., F)``,
    ``s = sum w r^2`` ``(...)``.  The weighted residual scatter at free parameters ``theta`` is
    ``s - 2 theta^T h + theta^T G theta`` (:meth:`scatter_at`).
    """

    G: Tensor
    h: Tensor
    s: Tensor

    #: :meth:`scatter_at` reports a scatter as unreliable where its terms exceed it by more than
    #: this factor: their rounding errors (~1e-16 each in double precision) then reach ~1e-12 of
    #: it.  Scaled by the machine epsilon of other dtypes: in single precision (~6e-8 each) no
    #: cancellation is small enough, and the residuals' pass is always taken (a float32 model's
    #: scatter is 1.7e-4 off at a cancellation of ~10, where the residuals give ~1e-6).
    MAX_CANCELLATION = 1e4

    def scatter_at(self, theta: Tensor) -> tuple[Tensor, Tensor]:
        """The scatter at ``theta`` ``(..., F)`` (clipped at zero), and whether it is reliable:
        ``s + 2 |theta|^T |h| + |theta|^T |G| |theta|`` at most :attr:`MAX_CANCELLATION` times
        it (else the caller computes it from the residuals)."""
        t = theta.unsqueeze(-1)
        value = self.s - 2.0 * (theta * self.h).sum(-1) + (t.transpose(-1, -2) @ self.G @ t)[..., 0, 0]
        a = t.abs()
        quadratic = (a.transpose(-1, -2) @ self.G.abs() @ a)[..., 0, 0]
        terms = self.s + 2.0 * (theta.abs() * self.h.abs()).sum(-1) + quadratic
        value = value.clamp_min(0.0)
        limit = self.MAX_CANCELLATION * torch.finfo(torch.float64).eps / torch.finfo(value.dtype).eps
        return value, terms <= limit * value


#: Up to this many free parameters of a one-output module, :func:`linear_normal_equations` forms
#: the sums over the particles as one dot product per pair of features (F (F + 3) / 2 passes over
#: the rows) instead of batched ``(F, L) @ (L, F)`` products per (step, sequence), whose broadcast
#: weighting and tiny matrix products cost more: the closed form of the paper's f (F = 2) 69 -> 48 ms
#: at the Table 1 size, a three-feature module on 3e6 rows 43 -> 35 ms (one thread).
FEW_FEATURES = 3


def _few_feature_products(A: Tensor, r: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """``sum_l w A A^T`` ``(t, B, F, F)`` and ``sum_l w A r`` ``(t, B, F)`` per (step, sequence) from
    the rows ``A`` ``(t, B, L, F)``, ``r`` and ``w`` ``(t, B, L)``: one weighted copy and one dot
    product over the particles per feature and pair."""
    cols = A.unbind(-1)
    weighted = [w * c for c in cols]
    F = len(cols)
    AwA = [[None] * F for _ in range(F)]
    for i in range(F):
        for j in range(i + 1):
            AwA[i][j] = AwA[j][i] = torch.linalg.vecdot(weighted[i], cols[j])
    Awr = torch.stack([torch.linalg.vecdot(wc, r) for wc in weighted], -1)
    return torch.stack([torch.stack(row, -1) for row in AwA], -2), Awr


def solve_normal_equations(G: Tensor, h: Tensor, ridge: float = 1e-12) -> Tensor:
    """``(G + ridge * mean(diag G) I)^-1 h`` for a batch ``(..., F, F)``."""
    scale = torch.diagonal(G, dim1=-2, dim2=-1).mean(-1).abs() + 1e-300
    eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    return torch.linalg.solve(G + ridge * scale[..., None, None] * eye, h)
