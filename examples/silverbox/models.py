"""Richer Silverbox transitions, still linear in their parameters (closed-form M-step).

:class:`PolyStateSpace` is a discrete-time state-space transition of the PNLSS family::

    x_{k+1} = A x_k + B u_k + c + E zeta(x_k)

with ``zeta`` a chosen list of monomials of the states (``p^2``, ``p^3``, ``p^2 v`` ...), observed
by ``y = x_0`` (:class:`~silverbox.study.PositionObservation`).  Each row of the transition has its
own coefficient vector (``w0, w1, ...``), so every row is a linear regression and the EM engine
solves the M-step in closed form.  The study's :class:`~silverbox.study.DuffingTransition` is a
special case (:func:`from_duffing` writes it in this form exactly), so a richer structure starts
from the fitted Duffing grey box, in its basin, and can only improve the simulation error it is
fitted by.  Extra states (``nx > 2``: unmodelled electronics) start driven by the input and
uncoupled from the oscillator, so the gradient reaches the coupling.

:class:`DuffingODE` is the Duffing oscillator in continuous time, ``m y'' + c y' + k y + k2 y^2 +
k3 y^3 = u + u0``, as the right-hand side ``dx/dt`` of a
:class:`~torch_nssm.ContinuousTimeTransition` (time in milliseconds): its parameters do not
depend on the sample time or the integrator, and :meth:`DuffingODE.physical` gives the mass,
damping and stiffness (and the natural frequency and damping ratio).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torch_nssm._ops import broadcast_leading
from torch_nssm.core.parametric import LinearInParameters

__all__ = ["PolyStateSpace", "from_duffing", "monomials", "FeedthroughObservation", "DuffingODE"]


def monomials(nvars: int, degrees: Sequence[int]) -> list[tuple[int, ...]]:
    """All exponent tuples over ``nvars`` variables whose total degree is in ``degrees``."""
    out: list[tuple[int, ...]] = []

    def rec(prefix: tuple[int, ...], left: int) -> None:
        if len(prefix) == nvars:
            if left == 0:
                out.append(prefix)
            return
        for e in range(left, -1, -1):
            rec(prefix + (e,), left - e)

    for d in degrees:
        rec((), int(d))
    return out


class PolyStateSpace(LinearInParameters):
    """``x_{k+1} = A x_k + B u_k + c + E zeta(x_k)``, one coefficient vector per row.

    Row ``i`` regresses ``x_{k+1, i}`` on the features ``[x_k, u_k, 1, zeta(x_k)]``; the
    monomials ``zeta`` are exponent tuples over the first ``n_poly_states`` states (e.g.
    ``(2, 0)`` is ``p^2``, ``(2, 1)`` is ``p^2 v``).

    Parameters
    ----------
    nx : int
        State dimension (``x_0`` is the measured position).
    mono : sequence of tuple of int
        Exponents of the monomials, each of length ``n_poly_states``.
    n_poly_states : int, default=2
        The monomials involve the states ``x_0 .. x_{n_poly_states - 1}``.
    rows : sequence of sequence of float, optional
        Initial coefficients, one row of length ``nx + 2 + len(mono)`` per state (default zeros).
    """

    nu = 1

    def __init__(
        self,
        nx: int,
        mono: Sequence[Sequence[int]],
        *,
        n_poly_states: int = 2,
        rows: Sequence[Sequence[float]] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.nx = int(nx)
        self.mono = [tuple(int(e) for e in m) for m in mono]
        self.n_poly_states = int(n_poly_states)
        if any(len(m) != self.n_poly_states for m in self.mono):
            raise ValueError("every monomial needs one exponent per polynomial state")
        self.n_feat = self.nx + 2 + len(self.mono)
        for i in range(self.nx):
            init = torch.zeros(self.n_feat, dtype=dtype)
            if rows is not None:
                init = torch.tensor(rows[i], dtype=dtype)
            if init.shape != (self.n_feat,):
                raise ValueError(f"row {i} needs {self.n_feat} coefficients, got {tuple(init.shape)}")
            setattr(self, f"w{i}", nn.Parameter(init))

    def feature_vector(self, x: Tensor, u: Tensor) -> Tensor:
        """``[x, u, 1, zeta(x)]``, shape ``(..., n_feat)``."""
        x, u = broadcast_leading(x, u)
        cols = [x[..., j] for j in range(self.nx)] + [u[..., 0], torch.ones_like(x[..., 0])]
        for m in self.mono:
            term = torch.ones_like(x[..., 0])
            for j, e in enumerate(m):
                if e:
                    term = term * x[..., j] ** e
            cols.append(term)
        return torch.stack(cols, dim=-1)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        phi = self.feature_vector(x, u)  # (..., F)
        F = self.n_feat
        Phi = phi.new_zeros(*phi.shape[:-1], self.nx, self.nx * F)
        for i in range(self.nx):
            Phi[..., i, i * F : (i + 1) * F] = phi
        return Phi, phi.new_zeros(*phi.shape[:-1], self.nx)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        # the same map without the block-diagonal regressor (the simulation's hot loop)
        phi = self.feature_vector(x, u)
        W = torch.stack([getattr(self, f"w{i}") for i in range(self.nx)])  # (nx, F)
        return phi @ W.T

    def coefficient_matrix(self) -> Tensor:
        """``(nx, n_feat)``: row ``i`` holds ``[A_i, B_i, c_i, E_i]``."""
        return torch.stack([getattr(self, f"w{i}").detach() for i in range(self.nx)])


def from_duffing(
    coef: dict[str, float],
    mono: Sequence[Sequence[int]],
    *,
    nx: int = 2,
    extra_poles: Sequence[float] = (0.6, 0.2, -0.3),
    extra_gains: Sequence[float] = (0.1, -0.1, 0.05),
) -> PolyStateSpace:
    """The fitted Duffing grey box (``coef``: :meth:`DuffingTransition.coefficients`) as a
    :class:`PolyStateSpace` with monomials ``mono`` over ``(p, v)`` (they must include ``p^2``
    and ``p^3``; every other coefficient starts at 0).

    Semi-implicit Euler: ``v' = (1 + d) v + k1 p + b u + c + k2 p^2 + k3 p^3`` and ``p' = p + v' +
    e u``.  State ``j`` beyond the second (``nx > 2``) starts as ``z' = extra_poles[j - 2] z +
    extra_gains[j - 2] u``, not coupled to ``p`` and ``v`` (distinct poles: the extra states are not
    interchangeable, so the gradient tells them apart).
    """
    mono = [tuple(m) for m in mono]
    F = nx + 2 + len(mono)
    rv = [0.0] * F
    rv[0], rv[1], rv[nx], rv[nx + 1] = coef["k1"], 1.0 + coef["d"], coef["b"], coef["c"]
    rv[nx + 2 + mono.index((2, 0))] = coef["k2"]
    rv[nx + 2 + mono.index((3, 0))] = coef["k3"]
    rp = list(rv)
    rp[0] += 1.0
    rp[nx] += coef["e"]
    rows = [rp, rv]
    for j in range(2, nx):
        rz = [0.0] * F
        rz[j], rz[nx] = extra_poles[j - 2], extra_gains[j - 2]
        rows.append(rz)
    return PolyStateSpace(nx, mono, rows=rows)


class FeedthroughObservation(LinearInParameters):
    """``y = x_0 + D u``: a direct input-to-output term (``D`` starts at ``D``, default 0); linear
    in ``D``, so EM's M-step for ``g`` is closed-form too."""

    def __init__(self, D: float = 0.0, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.D = nn.Parameter(torch.tensor(float(D), dtype=dtype))

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        x, u = broadcast_leading(x, u)
        return u[..., :1].unsqueeze(-1), x[..., :1]


class DuffingODE(LinearInParameters):
    """``dx/dt`` of the Duffing oscillator ``m y'' + c y' + k y + k2 y^2 + k3 y^3 = u + u0``, state
    ``x = [y, v]`` (``v = dy/dt``), time in milliseconds; divided by the mass, it is linear in

        ``theta = (b, c_m, k_m, k2_m, k3_m, a0) = (1, c, k, k2, k3, u0) / m``::

        dy/dt = v
        dv/dt = b u - c_m v - k_m y - k2_m y^2 - k3_m y^3 + a0

    so with :class:`~torch_nssm.ContinuousTimeTransition` and explicit or semi-implicit Euler
    (``velocities=[1]``) the EM engine updates it in closed form; with RK4 by gradient.  Semi-implicit
    Euler with one step per sample is the study's :class:`~silverbox.study.DuffingTransition` with
    ``e = 0`` (:meth:`from_discrete` maps one to the other).  Units: those of the normalised ``y``
    and ``u`` (:func:`~silverbox.study.prepare_silverbox`) and milliseconds.

    Parameters
    ----------
    b, c_m, k_m, k2_m, k3_m, a0 : float
        Initial values.
    """

    names = ("b", "c_m", "k_m", "k2_m", "k3_m", "a0")

    def __init__(
        self,
        b: float = 0.1,
        c_m: float = 0.05,
        k_m: float = 0.15,
        k2_m: float = 0.0,
        k3_m: float = 0.0,
        a0: float = 0.0,
        *,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        for name, value in zip(self.names, (b, c_m, k_m, k2_m, k3_m, a0)):
            setattr(self, name, nn.Parameter(torch.tensor(float(value), dtype=dtype)))

    @classmethod
    def from_discrete(cls, coef: dict[str, float], Ts: float) -> DuffingODE:
        """The ODE whose semi-implicit Euler step of ``Ts`` (ms) is :class:`DuffingTransition` with
        coefficients ``coef`` (its ``e`` ignored): ``v_discrete = Ts v``, so ``k_m = -k1 / Ts^2``,
        ``c_m = -d / Ts``, ``b = b_discrete / Ts^2`` and likewise."""
        h2 = Ts * Ts
        return cls(
            b=coef["b"] / h2, c_m=-coef["d"] / Ts, k_m=-coef["k1"] / h2, k2_m=-coef["k2"] / h2,
            k3_m=-coef["k3"] / h2, a0=coef["c"] / h2,
        )

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` ``(..., 2, 6)`` (zero in the position row) and offset ``[v, 0]``."""
        x, u = broadcast_leading(x, u)
        y, v = x[..., 0], x[..., 1]
        zero = torch.zeros_like(y)
        row_v = torch.stack([u[..., 0], -v, -y, -y * y, -y * y * y, torch.ones_like(y)], dim=-1)
        Phi = torch.stack([torch.zeros_like(row_v), row_v], dim=-2)
        return Phi, torch.stack([v, zero], dim=-1)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        # the same function as features() @ theta, in a few operations (the integrator's hot loop)
        y, v = x[..., 0], x[..., 1]
        acc = self.b * u[..., 0] - self.c_m * v - (self.k_m + (self.k2_m + self.k3_m * y) * y) * y + self.a0
        return torch.stack(torch.broadcast_tensors(v, acc), dim=-1)

    def physical(self) -> dict[str, float]:
        """Mass ``m = 1 / b``, damping ``c``, stiffnesses ``k``, ``k2``, ``k3``, input offset ``u0``,
        natural frequency ``f0 = sqrt(k / m) / 2 pi`` (Hz) and damping ratio ``zeta = c / (2 sqrt(k m))``."""
        t = {name: float(getattr(self, name).detach()) for name in self.names}
        m = 1.0 / t["b"]
        out = dict(m=m, c=t["c_m"] * m, k=t["k_m"] * m, k2=t["k2_m"] * m, k3=t["k3_m"] * m, u0=t["a0"] * m)
        if t["k_m"] > 0:
            out["f0_hz"] = 1e3 * (t["k_m"] ** 0.5) / (2 * 3.141592653589793)
            out["zeta"] = t["c_m"] / (2 * t["k_m"] ** 0.5)
        return out

    def extra_repr(self) -> str:
        return ", ".join(f"{n}={float(getattr(self, n).detach()):.4g}" for n in self.names)
