"""Continuous-time models: a transition ``f`` from an ODE ``dx/dt = F(x, u)`` and a sample time ``Ts``.

A record is a continuous-time plant sampled every ``Ts``.  :class:`ContinuousTimeTransition` takes
the right-hand side ``F`` as a ``torch.nn.Module`` (physical parameters, or a network such as
:class:`~torch_nssm.blocks.neural.MLPDerivative`) and integrates it over one sample with the input
held (zero-order hold)::

    x[k+1] = x[k] + integral over [0, Ts] of F(x(t), u[k]) dt      (approximated by a fixed-step method)

with ``substeps`` steps of ``h = Ts / substeps`` of one of :data:`METHODS`:

* ``"euler"``: ``x + h F(x)``;
* ``"semi-implicit"`` (symplectic Euler) for mechanical systems: the states listed in
  ``velocities`` advance first, ``v' = v + h F_v(q, v)``, then the others (positions) with the new
  velocities, ``q' = q + h F_q(q, v')``; it keeps the energy of an undamped oscillator bounded,
  where explicit Euler's grows;
* ``"rk4"``: the classical fourth-order Runge-Kutta step (error ``O(h^4)``).

The estimated parameters are ``F``'s own (``Ts`` is a float attribute, not a parameter): they keep
their physical meaning whatever the sample time and the method.

When ``F`` is a :class:`~torch_nssm.LinearInParameters` (``F = c(x, u) + Phi(x, u) theta``), one
step of explicit Euler is linear in ``theta`` too (features ``Ts Phi``, offset ``x + Ts c``), and so
is one step of semi-implicit Euler when the position rows of ``F`` are affine in the velocities
with coefficients free of ``theta`` (``dq/dt = v`` is) or the velocity rows hold no ``theta``.  For
these the transition is a :class:`LinearContinuousTimeTransition`, itself a
:class:`~torch_nssm.LinearInParameters`, so the EM engine updates ``theta`` in closed form; every
other combination (RK4, several substeps) takes the gradient M-step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from .. import _validation as V
from ..core.parametric import LinearInParameters

__all__ = ["ContinuousTimeTransition", "LinearContinuousTimeTransition", "METHODS", "integrate_step"]

#: The fixed-step integrators of :class:`ContinuousTimeTransition`.
METHODS = ("euler", "semi-implicit", "rk4")

Derivative = Callable[[Tensor, Tensor], Tensor]


def _closed_form_applies(rhs, method: str, substeps: int) -> bool:
    return isinstance(rhs, LinearInParameters) and method in ("euler", "semi-implicit") and substeps == 1


def integrate_step(
    F: Derivative,
    x: Tensor,
    u: Tensor,
    Ts: float,
    method: str = "rk4",
    substeps: int = 1,
    velocity_mask: Tensor | None = None,
) -> Tensor:
    """The state after one sample ``Ts`` of ``dx/dt = F(x, u)`` with ``u`` held (zero-order hold).

    Parameters
    ----------
    F : callable
        ``F(x, u) -> dx/dt``, shape ``(..., nx)``.
    x : Tensor, shape (..., nx)
    u : Tensor, shape (..., nu)
    Ts : float
        The sample time.
    method : {"euler", "semi-implicit", "rk4"}
    substeps : int
        Steps of ``Ts / substeps`` per sample.
    velocity_mask : Tensor of shape (nx,), optional
        ``1.0`` at the velocity states, ``0.0`` elsewhere (``"semi-implicit"`` only).

    Returns
    -------
    Tensor, shape (..., nx)
    """
    h = Ts / substeps
    for _ in range(substeps):
        if method == "euler":
            x = x + h * F(x, u)
        elif method == "rk4":
            k1 = F(x, u)
            k2 = F(x + (0.5 * h) * k1, u)
            k3 = F(x + (0.5 * h) * k2, u)
            k4 = F(x + h * k3, u)
            x = x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        else:  # semi-implicit: the velocities first, then the positions with the new velocities
            x = x + (h * velocity_mask) * F(x, u)
            x = x + (h * (1.0 - velocity_mask)) * F(x, u)
    return x


class ContinuousTimeTransition(nn.Module):
    """Transition ``f`` from an ODE: ``x[k+1]`` is the state ``Ts`` after ``x[k]`` under
    ``dx/dt = rhs(x, u[k])`` (the input held over the sample), by a fixed-step integrator.

    Called as ``f(x, u)`` with ``x`` of shape ``(..., nx)`` and ``u`` of shape ``(..., nu)`` like
    any ``f`` (batched over particles).  The estimated parameters are those of ``rhs`` (named
    ``rhs.<name>``: ``est.f_.rhs.k``, ``est.standard_errors_["f.rhs.k"]``).

    With a ``rhs`` that is a :class:`~torch_nssm.LinearInParameters` and ``method="euler"`` or
    ``"semi-implicit"`` with one substep, the constructor returns a
    :class:`LinearContinuousTimeTransition` (a subclass, itself linear in the parameters: closed-form
    M-steps); ``closed_form=False`` keeps the gradient M-step.

    Parameters
    ----------
    rhs : nn.Module
        ``rhs(x, u) -> dx/dt`` of shape ``(..., nx)``, in units of the state per unit of ``Ts``'s
        time.  Stored as a sub-module (not copied).
    Ts : float
        Sample time (> 0), in the time unit of ``rhs``'s derivatives.
    method : {"euler", "semi-implicit", "rk4"}, default="rk4"
        The integrator (:data:`METHODS`; see the module docstring).
    substeps : int, default=1
        Integration steps per sample (step ``Ts / substeps``).
    velocities : sequence of int, optional
        ``method="semi-implicit"`` only, where it is required: the indices of the velocity states
        (e.g. ``[1]`` for ``x = [angle, angular velocity]``); the other states are the positions.
    closed_form : bool, default=True
        Use the closed-form M-step where it applies (see above).

    Attributes
    ----------
    rhs : nn.Module
    Ts : float
    method : str
    substeps : int
    velocities : tuple of int
        Empty unless ``method="semi-implicit"``.

    Examples
    --------
    >>> class Decay(nn.Module):                  # dx/dt = -a x + u
    ...     def __init__(self):
    ...         super().__init__()
    ...         self.a = nn.Parameter(torch.tensor(2.0, dtype=torch.float64))
    ...     def forward(self, x, u):
    ...         return -self.a * x + u
    >>> f = ContinuousTimeTransition(Decay(), Ts=0.1)
    >>> x = torch.ones(4, 1, dtype=torch.float64)
    >>> round(float(f(x, torch.zeros(4, 1, dtype=torch.float64))[0, 0]), 6)   # exp(-0.2)
    0.818733
    """

    def __new__(cls, rhs: nn.Module | None = None, Ts: float | None = None, method: str = "rk4", **kwargs):
        if (
            cls is ContinuousTimeTransition
            and kwargs.get("closed_form", True)
            and _closed_form_applies(rhs, method, kwargs.get("substeps", 1))
        ):
            cls = LinearContinuousTimeTransition
        return super().__new__(cls)

    def __init__(
        self,
        rhs: nn.Module,
        Ts: float,
        method: str = "rk4",
        *,
        substeps: int = 1,
        velocities: Sequence[int] | None = None,
        closed_form: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(rhs, nn.Module):
            raise TypeError(
                f"rhs must be a torch.nn.Module returning dx/dt = rhs(x, u), got {type(rhs).__name__}"
            )
        self.rhs = rhs
        self.Ts = float(V.check_positive(Ts, "Ts"))
        if not np.isfinite(self.Ts):
            raise ValueError(f"Ts must be finite, got {Ts!r}")
        self.method = V.check_choice(method, "method", METHODS)
        self.substeps = V.check_count(substeps, "substeps", 1)
        if not isinstance(closed_form, (bool, np.bool_)):
            raise TypeError(f"closed_form must be True or False, got {closed_form!r}")
        self.closed_form = bool(closed_form)
        if self.method == "semi-implicit":
            if velocities is None:
                raise ValueError(
                    "method='semi-implicit' needs velocities=[...]: the indices of the velocity states "
                    "(e.g. velocities=[1] for x = [angle, angular velocity])"
                )
            entries = np.atleast_1d(velocities).tolist()
            idx = [V.check_count(i, "every entry of velocities", 0) for i in entries]
            if not idx or len(set(idx)) != len(idx):
                raise ValueError(f"velocities must list distinct state indices, got {velocities!r}")
            self.velocities = tuple(sorted(idx))
        elif velocities is not None:
            raise ValueError(
                f"velocities applies to method='semi-implicit' only (method={self.method!r} treats every "
                "state alike): drop it or choose method='semi-implicit'"
            )
        else:
            self.velocities = ()
        self._masks: dict = {}

    def velocity_mask(self, x: Tensor) -> Tensor | None:
        """``1.0`` at the velocity states and ``0.0`` elsewhere, shape ``(nx,)``, on ``x``'s device and
        dtype (made once per device and dtype); ``None`` unless ``method="semi-implicit"``."""
        if not self.velocities:
            return None
        nx = x.shape[-1]
        key = (x.device, x.dtype, nx)
        mask = self._masks.get(key)
        if mask is None:
            if self.velocities[-1] >= nx:
                raise ValueError(
                    f"velocities={list(self.velocities)} names states beyond the state dimension nx = {nx}"
                )
            mask = torch.zeros(nx, dtype=x.dtype)
            mask[list(self.velocities)] = 1.0
            mask = mask.to(x.device)
            self._masks[key] = mask
        return mask

    def step(self, F: Derivative, x: Tensor, u: Tensor) -> Tensor:
        """One sample of ``dx/dt = F(x, u)`` by this transition's method (``F``: ``rhs`` or another
        evaluation of it, e.g. at other parameters)."""
        return integrate_step(F, x, u, self.Ts, self.method, self.substeps, self.velocity_mask(x))

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """The state one sample later, shape ``(..., nx)``."""
        return self.step(self.rhs, x, u)

    @torch.no_grad()
    def fit_normalisation(self, x, u=None, x_next=None) -> ContinuousTimeTransition:
        """Set ``rhs``'s normalisation from states (e.g. ``distilled_start``'s smoothed states): calls
        ``rhs.fit_normalisation(x, u, dxdt=(x_next - x) / Ts)`` (the derivative's scale from the
        one-sample increments; ``x_next=None``: ``dxdt=None``).

        Raises
        ------
        TypeError
            If ``rhs`` has no ``fit_normalisation`` (e.g. a physical model).
        """
        own = getattr(self.rhs, "fit_normalisation", None)
        if not callable(own):
            raise TypeError(f"rhs ({type(self.rhs).__name__}) has no fit_normalisation to call")
        dxdt = None
        if x_next is not None:
            dxdt = (np.asarray(x_next, dtype=np.float64) - np.asarray(x, dtype=np.float64)) / self.Ts
        own(x, u, dxdt=dxdt)
        return self

    def __getstate__(self):
        state = dict(super().__getstate__())
        state["_masks"] = {}  # device tensors made on demand: pickles load anywhere
        return state

    def extra_repr(self) -> str:
        extra = f", velocities={list(self.velocities)}" if self.velocities else ""
        return f"Ts={self.Ts:g}, method={self.method!r}, substeps={self.substeps}{extra}"


class LinearContinuousTimeTransition(ContinuousTimeTransition, LinearInParameters):
    """A :class:`ContinuousTimeTransition` that is linear in ``rhs``'s parameters: explicit or
    semi-implicit Euler, one step per sample, of a ``rhs`` that is a
    :class:`~torch_nssm.LinearInParameters` (``dx/dt = c(x, u) + Phi(x, u) theta``).

    ``ContinuousTimeTransition(rhs, Ts, method)`` returns this class where it applies; its
    ``theta`` is ``rhs``'s (the same parameters, in the same order), and the EM engine solves its
    M-step in closed form.

    * Euler: ``x' = x + Ts c + Ts Phi theta``.
    * Semi-implicit Euler (velocities ``v``, positions ``q``): ``v' = v + Ts (c_v + Phi_v theta)``,
      ``q' = q + Ts F_q(q, v')``.  With ``F_q`` affine in ``v`` (``F_q(q, v) = c_q(q, v* ) + M (v -
      v*) + Phi_q theta``, ``M`` and ``Phi_q`` free of ``theta``, ``v* = v + Ts c_v``) this is
      ``q + Ts c_q(q, v*) + Ts (Phi_q + Ts M Phi_v) theta``; ``M`` comes from ``rhs``'s offsets at
      unit steps of each velocity (exact for an affine ``c_q``).  :meth:`features` checks on its
      first and last rows, at ``theta`` and at another parameter vector, that this equals the
      integrator's step, and says so when ``rhs`` does not have this form.
    """

    def __init__(self, rhs: nn.Module, Ts: float, method: str = "euler", **kwargs) -> None:
        super().__init__(rhs, Ts, method, **kwargs)
        if not (self.closed_form and _closed_form_applies(rhs, self.method, self.substeps)):
            raise ValueError(
                "LinearContinuousTimeTransition needs a LinearInParameters rhs, method='euler' or "
                "'semi-implicit', substeps=1 and closed_form=True; ContinuousTimeTransition takes any"
            )

    def predict(self, x: Tensor, u: Tensor, theta: Tensor) -> Tensor:
        """The step at parameters ``theta`` ``(..., P)`` (broadcast against the rows), through
        ``rhs.predict``."""
        rhs = self.rhs
        return self.step(lambda xx, uu: rhs.predict(xx, uu, theta), x, u)

    def frozen(self) -> Callable[[Tensor, Tensor], Tensor]:
        """The step with ``theta`` gathered once (:meth:`LinearInParameters.frozen`), or the module
        itself where hooks are registered."""
        if self._forward_hooks or self._forward_pre_hooks:
            return self
        return self.frozen_predict(self.theta())

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi`` ``(..., nx, P)`` and offset ``(..., nx)`` of the step: ``x' = offset + Phi theta``.

        Raises
        ------
        ValueError
            For semi-implicit Euler, if the step of ``rhs`` is not of this form (position rows not
            affine in the velocities, or with features that depend on them while the velocity rows
            hold parameters): use ``closed_form=False`` or another method.
        """
        Ts = self.Ts
        Phi, c = self.rhs.features(x, u)
        if self.method == "euler":
            return Ts * Phi, x + Ts * c
        vel = self.velocity_mask(x)
        pos = 1.0 - vel
        x_star = x + (Ts * vel) * c  # the velocities advanced by the offset's part
        Phi_s, c_s = self.rhs.features(x_star, u)
        # M Phi_v: the offset's change per unit velocity (affine: exact) times the velocity rows' features
        MPhi = torch.zeros_like(Phi_s)
        for j in self.velocities:
            e_j = torch.zeros_like(vel)
            e_j[j] = 1.0
            d_j = self.rhs.features(x_star + e_j, u)[1] - c_s  # (..., nx)
            MPhi = MPhi + d_j.unsqueeze(-1) * Phi[..., j : j + 1, :]
        vel_rows, pos_rows = vel.unsqueeze(-1), pos.unsqueeze(-1)
        Phi_out = (Ts * vel_rows) * Phi + (Ts * pos_rows) * (Phi_s + Ts * MPhi)
        offset = x + (Ts * vel) * c + (Ts * pos) * c_s
        self._check_semi_implicit(x, u, Phi_out, offset)
        return Phi_out, offset

    @torch.no_grad()
    def _check_semi_implicit(self, x: Tensor, u: Tensor, Phi: Tensor, offset: Tensor) -> None:
        """``offset + Phi theta`` against the integrator's step on the first and last rows, at
        ``theta`` and at ``2 theta + 1``."""
        lead = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1], offset.shape[:-1])
        if not len(lead) or any(n == 0 for n in lead):
            rows = [()] if not len(lead) else []
        else:
            rows = [(0,) * len(lead), tuple(n - 1 for n in lead)]
        theta = self.theta().detach()
        xb, ub = x.expand(*lead, x.shape[-1]), u.expand(*lead, u.shape[-1])
        Phib = Phi.expand(*lead, *Phi.shape[-2:])
        offb = offset.expand(*lead, offset.shape[-1])
        eps = torch.finfo(x.dtype).eps
        for r in rows:
            xr, ur, Pr, orow = xb[r], ub[r], Phib[r], offb[r]
            for th in (theta, 2.0 * theta + 1.0):
                want = self.predict(xr, ur, th)
                got = orow + Pr @ th
                scale = orow.abs() + Pr.abs() @ th.abs() + want.abs() + 1.0
                if not bool(((got - want).abs() <= 1e4 * eps * scale).all()):
                    raise ValueError(
                        "the semi-implicit Euler step of this rhs is not linear in its parameters: its "
                        "position rows must be affine in the velocities with parameter-free coefficients "
                        "(dq/dt = v is), or its velocity rows must hold no parameters; pass "
                        "closed_form=False (gradient M-step) or choose method='euler'"
                    )
