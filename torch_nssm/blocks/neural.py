"""Neural ``f`` / ``g`` blocks: MLP transition and observation models, and a grey-box transition.

Every block is a ``torch.nn.Module`` called as ``f(x, u)`` / ``g(x, u)`` with ``x`` of shape
``(..., nx)`` and ``u`` of shape ``(..., nu)`` (``nu = 0``: no input), fitted by the estimator's
gradient M-step.

* :class:`MLPTransition`: ``f(x, u) = x + out_scale * MLP([x_norm, u_norm])``, close to the
  identity when untrained.
* :class:`MLPObservation`: ``g(x, u) = y_mean + y_scale * MLP([x_norm, u_norm])``.
* :class:`GreyBoxTransition`: ``f(x, u) = physical(x, u) + out_scale * MLP([x_norm, u_norm])``,
  exactly ``physical`` when untrained.
* :class:`MLPDerivative`: ``dx/dt = out_scale * MLP([x_norm, u_norm])``, the right-hand side of a
  neural ODE (:class:`~torch_nssm.blocks.continuous.ContinuousTimeTransition` integrates it over a
  sample).

``x_norm = (x - x_mean) / x_scale`` and likewise ``u_norm``; the means and scales are buffers
(saved and moved with the module, not estimated): set them in the constructor or with
``fit_normalisation`` before fitting.  Design notes: ``docs/design.md`` ("Neural blocks").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Callable, Union

import numpy as np
import torch
from torch import Tensor, nn

from .. import _validation as V
from .._ops import broadcast_leading
from .._stats import robust_scale_torch

__all__ = ["MLPTransition", "MLPObservation", "GreyBoxTransition", "MLPDerivative", "ACTIVATIONS"]

#: Activation names accepted by the blocks (a ``nn.Module`` subclass or factory works too).
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "gelu": nn.GELU,
    "silu": nn.SiLU,
    "elu": nn.ELU,
    "softplus": nn.Softplus,
    "sigmoid": nn.Sigmoid,
}

Activation = Union[str, Callable[[], nn.Module]]
ArrayLike = Union[Tensor, np.ndarray, Sequence, float, None]


# ---------------------------------------------------------------------- helpers
def _activation_factory(activation: Activation) -> Callable[[], nn.Module]:
    if isinstance(activation, str):
        try:
            return ACTIVATIONS[activation.lower()]
        except KeyError:
            raise ValueError(
                f"activation must be one of {sorted(ACTIVATIONS)} or a nn.Module factory, got {activation!r}"
            ) from None
    if callable(activation):
        return activation
    raise TypeError(f"activation must be a string or a nn.Module factory, got {type(activation).__name__}")


def _check_hidden(hidden: Sequence[int]) -> tuple[int, ...]:
    if isinstance(hidden, (int, np.integer)):
        hidden = (int(hidden),)
    return tuple(V.check_count(h, "every hidden width", 1) for h in hidden)


def _buffer(value: ArrayLike, n: int, name: str, default: float, dtype, device, positive=False) -> Tensor:
    """A buffer of shape ``(n,)`` from a scalar or an array of ``n`` numbers (``None``: default)."""
    arr = V.check_vector_array(default if value is None else value, name, n, positive=positive)
    return torch.as_tensor(arr, dtype=dtype, device=device)


def _as_rows(value: ArrayLike, n: int, name: str) -> Tensor:
    """Data as a float64 CPU tensor of shape ``(rows, n)``."""
    return torch.from_numpy(V.as_rows_array(value, name, n))


def _build_mlp(
    n_in: int,
    n_out: int,
    hidden: tuple[int, ...],
    activation: Activation,
    last_layer_scale: float | None,
    dtype: torch.dtype,
    device,
) -> nn.Sequential:
    """``Linear -> act -> ... -> Linear``; the last layer gets weights of standard deviation
    ``last_layer_scale / sqrt(fan_in)`` and a zero bias (``None``: torch's default init)."""
    make_act = _activation_factory(activation)
    layers: list[nn.Module] = []
    width = n_in
    for h in hidden:
        layers += [nn.Linear(width, h, dtype=dtype, device=device), make_act()]
        width = h
    last = nn.Linear(width, n_out, dtype=dtype, device=device)
    if last_layer_scale is not None:
        with torch.no_grad():
            if last_layer_scale == 0 or width == 0:
                last.weight.zero_()
            else:
                last.weight.normal_(0.0, float(last_layer_scale) / math.sqrt(width))
            last.bias.zero_()
    layers.append(last)
    return nn.Sequential(*layers)


def _mean_std(t: Tensor) -> tuple[Tensor, Tensor]:
    """NaN-aware column means and standard deviations; a constant (or empty) column gets scale 1."""
    ok = ~torch.isnan(t)
    count = ok.sum(0).clamp_min(1)
    filled = torch.where(ok, t, torch.zeros_like(t))
    mean = filled.sum(0) / count
    var = (torch.where(ok, t - mean, torch.zeros_like(t)) ** 2).sum(0) / count
    std = var.sqrt()
    tiny = std <= 1e-12 * mean.abs().clamp_min(1.0)
    return mean, torch.where(tiny | ~torch.isfinite(std), torch.ones_like(std), std)


_HOOKS = ("_forward_hooks", "_forward_pre_hooks", "_backward_hooks", "_backward_pre_hooks")


def _forward_only(*modules: nn.Module) -> bool:
    """Whether calling each module runs its ``forward`` and nothing else: no hooks (its own or
    global: what ``nn.Module.__call__`` checks), not compiled, not traced."""
    registry = torch.nn.modules.module
    if any(getattr(registry, "_global" + name, None) for name in _HOOKS) or torch._C._get_tracing_state():
        return False
    return not any(
        getattr(m, name, None) for m in modules for name in (*_HOOKS, "_compiled_call_impl")
    )


# ---------------------------------------------------------------------- the shared base
class _NeuralBlock(nn.Module):
    """Input normalisation buffers ``x_mean``, ``x_scale``, ``u_mean``, ``u_scale`` and the MLP."""

    net: nn.Sequential

    def __init__(
        self,
        nx: int,
        nu: int,
        *,
        x_mean: ArrayLike,
        x_scale: ArrayLike,
        u_mean: ArrayLike,
        u_scale: ArrayLike,
        dtype: torch.dtype,
        device,
    ) -> None:
        super().__init__()
        self.nx = V.check_count(nx, "nx", 1)
        self.nu = V.check_count(nu, "nu", 0)
        kw = dict(dtype=dtype, device=device)
        self.register_buffer("x_mean", _buffer(x_mean, self.nx, "x_mean", 0.0, **kw))
        self.register_buffer("x_scale", _buffer(x_scale, self.nx, "x_scale", 1.0, **kw, positive=True))
        self.register_buffer("u_mean", _buffer(u_mean, self.nu, "u_mean", 0.0, **kw))
        self.register_buffer("u_scale", _buffer(u_scale, self.nu, "u_scale", 1.0, **kw, positive=True))

    def normalised_input(self, x: Tensor, u: Tensor) -> Tensor:
        """``[(x - x_mean) / x_scale, (u - u_mean) / u_scale]`` of shape ``(..., nx + nu)``."""
        x, u = broadcast_leading(x, u)
        return torch.cat([(x - self.x_mean) / self.x_scale, (u - self.u_mean) / self.u_scale], dim=-1)

    def _set_input_normalisation(self, x: ArrayLike, u: ArrayLike) -> None:
        mean, std = _mean_std(_as_rows(x, self.nx, "x"))
        self.x_mean.copy_(mean)
        self.x_scale.copy_(std)
        if u is not None and self.nu > 0:
            mean, std = _mean_std(_as_rows(u, self.nu, "u"))
            self.u_mean.copy_(mean)
            self.u_scale.copy_(std)

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}"

    def _increment_function(self, u: Tensor, block: type) -> Callable[[Tensor, int], Tensor] | None:
        """``increment(x, t)``, equal bit for bit to ``out_scale * net(normalised_input(x, u[:, t]))``
        (the transitions' network term; ``x`` ``(n, nx)``, ``u`` ``(n, T, nu)``), or ``None`` where
        calling the layers directly would skip something: hooks, a compiled module, a subclass's own
        ``forward`` (other than ``block``'s, whose step the caller builds) or normalisation."""
        layers = list(self.net)
        plain = (
            type(self).forward is block.forward
            and type(self).normalised_input is _NeuralBlock.normalised_input
            and type(self.net) is nn.Sequential
            and _forward_only(self, self.net, *layers)
        )
        if not plain:
            return None
        u_norm = (u - self.u_mean) / self.u_scale
        # F.linear of a matrix with a bias is addmm(bias, input, weight.t()): the transposes are
        # taken once here instead of at every step (fewer graph nodes to differentiate)
        calls = [
            (layer.bias, layer.weight.t())
            if type(layer) is nn.Linear and layer.bias is not None
            else layer.forward
            for layer in layers
        ]
        x_mean, x_scale, out_scale = self.x_mean, self.x_scale, self.out_scale

        def increment(x: Tensor, t: int) -> Tensor:
            h = torch.cat([(x - x_mean) / x_scale, u_norm[:, t]], dim=-1)
            for call in calls:
                h = torch.addmm(call[0], h, call[1]) if isinstance(call, tuple) else call(h)
            return out_scale * h

        return increment

    def _add_step_network(
        self, hidden, activation, last_layer_scale, out_scale, random_state, dtype, device
    ) -> None:
        """The state-increment network of the transitions: ``out_scale * MLP([x_norm, u_norm])``
        with a last layer of weight scale ``last_layer_scale`` (0: starts at exactly zero), seeded
        by ``random_state`` without touching torch's global random state."""
        self.hidden = _check_hidden(hidden)
        self.activation = activation
        if not last_layer_scale >= 0:
            raise ValueError(f"last_layer_scale must be >= 0, got {last_layer_scale!r}")
        out = self.x_scale if out_scale is None else out_scale
        out = _buffer(out, self.nx, "out_scale", 1.0, dtype, device, positive=True)
        self.register_buffer("out_scale", out)
        with torch.random.fork_rng(devices=[]):
            if random_state is not None:
                torch.manual_seed(int(random_state))
            self.net = _build_mlp(
                self.nx + self.nu, self.nx, self.hidden, activation, last_layer_scale, dtype, device
            )


# ---------------------------------------------------------------------- the blocks


class MLPTransition(_NeuralBlock):
    """Residual MLP transition ``f(x, u) = x + out_scale * MLP([x_norm, u_norm])``.

    The last layer starts small (weights of s.d. ``last_layer_scale / sqrt(width)``, zero bias),
    so the untrained model is within about ``last_layer_scale * out_scale`` of ``f(x, u) = x``:
    EM starts from a stable random walk.  The network learns the increment in units of
    ``out_scale``.

    Parameters
    ----------
    nx : int
        State dimension.
    nu : int
        Input dimension (0 for a system without input).
    hidden : sequence of int, default=(32, 32)
        Widths of the hidden layers (``()``: an affine map).
    activation : str or callable, default="tanh"
        A name in :data:`ACTIVATIONS` or a factory returning a ``nn.Module``.
    x_mean, x_scale : float or array-like of shape (nx,), optional
        Input normalisation of the state (default 0 and 1).
    u_mean, u_scale : float or array-like of shape (nu,), optional
        Input normalisation of the input (default 0 and 1).
    out_scale : float or array-like of shape (nx,), optional
        Scale of the increment (default ``x_scale``).
    last_layer_scale : float, default=1e-3
        Size of the last layer's initial weights (0: exactly the identity at the start).
    random_state : int, optional
        Seed of the weight initialisation (torch's global random state is left alone).
    dtype : torch.dtype, default=torch.float64
    device : torch.device or str, optional

    Attributes
    ----------
    net : nn.Sequential
        The MLP, ``nx + nu -> nx``.
    x_mean, x_scale, u_mean, u_scale, out_scale : Tensor
        Buffers (saved and moved with the module, not estimated).

    Examples
    --------
    >>> f = MLPTransition(1, 1, hidden=(16,), random_state=0)
    >>> x = torch.randn(5, 1, dtype=torch.float64)
    >>> bool(torch.allclose(f(x, torch.zeros(5, 1, dtype=torch.float64)), x, atol=1e-2))
    True
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        hidden: Sequence[int] = (32, 32),
        activation: Activation = "tanh",
        *,
        x_mean: ArrayLike = None,
        x_scale: ArrayLike = None,
        u_mean: ArrayLike = None,
        u_scale: ArrayLike = None,
        out_scale: ArrayLike = None,
        last_layer_scale: float = 1e-3,
        random_state: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(
            nx, nu, x_mean=x_mean, x_scale=x_scale, u_mean=u_mean, u_scale=u_scale, dtype=dtype, device=device
        )
        self._add_step_network(hidden, activation, last_layer_scale, out_scale, random_state, dtype, device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """Next-state mean, shape ``(..., nx)`` (leading dimensions of ``x`` and ``u`` broadcast)."""
        z = self.normalised_input(x, u)
        return x + self.out_scale * self.net(z)

    def step_function(self, u: Tensor) -> Callable[[Tensor, int], Tensor]:
        """``step(x, t)``, equal bit for bit to ``self(x, u[:, t])`` with ``x`` of shape ``(n, nx)``,
        for simulating over inputs ``u`` of shape ``(n, T, nu)``.

        The inputs are normalised once for all steps and the layers are called without the module
        machinery, which takes a fifth to a quarter of the time off the neural first stage of a
        small network (most of a step is call overhead there).  Where that would skip something (a
        subclass's own ``forward``, hooks, a compiled module) the step calls the module.
        """
        increment = self._increment_function(u, MLPTransition)
        if increment is None:
            return lambda x, t: self(x, u[:, t])
        return lambda x, t: x + increment(x, t)

    @torch.no_grad()
    def fit_normalisation(self, x: ArrayLike, u: ArrayLike = None, x_next: ArrayLike = None) -> MLPTransition:
        """Set the normalisation buffers from data (call it before fitting).

        Parameters
        ----------
        x : array-like of shape (..., nx)
            Representative states (e.g. simulated by a physical model); NaN is ignored.
        u : array-like of shape (..., nu), optional
            Representative inputs (``None`` keeps ``u_mean``, ``u_scale``).
        x_next : array-like of shape (..., nx), optional
            The states one step after ``x``: ``out_scale`` becomes the standard deviation of the
            increments ``x_next - x``.  Otherwise ``out_scale = x_scale``.

        Returns
        -------
        self
        """
        self._set_input_normalisation(x, u)
        if x_next is None:
            self.out_scale.copy_(self.x_scale)
        else:
            dx = _as_rows(x_next, self.nx, "x_next") - _as_rows(x, self.nx, "x")
            self.out_scale.copy_(_mean_std(dx)[1])
        return self

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}, hidden={self.hidden}, activation={self.activation!r}"


class MLPObservation(_NeuralBlock):
    """MLP observation ``g(x, u) = y_mean + y_scale * MLP([x_norm, u_norm])``.

    The network has torch's default initialisation (a non-constant ``g`` from the start: a
    constant one tells the E-step nothing about the state).  ``y_mean`` and ``y_scale`` are
    buffers; :meth:`fit_normalisation` sets them from the measured outputs (NaN ignored), with a
    robust (median / MAD) option for records with outliers.

    Parameters
    ----------
    nx : int
        State dimension.
    nu : int
        Input dimension (0 for a system without input, or when ``g`` ignores ``u``).
    p : int
        Number of outputs.
    hidden : sequence of int, default=(32,)
        Widths of the hidden layers.
    activation : str or callable, default="tanh"
    x_mean, x_scale : float or array-like of shape (nx,), optional
    u_mean, u_scale : float or array-like of shape (nu,), optional
    y_mean, y_scale : float or array-like of shape (p,), optional
        Output offset and scale (default 0 and 1).
    last_layer_scale : float, optional
        If given, the last layer's weights get standard deviation ``last_layer_scale /
        sqrt(width)`` and a zero bias; by default torch's initialisation.
    random_state : int, optional
    dtype : torch.dtype, default=torch.float64
    device : torch.device or str, optional

    Attributes
    ----------
    net : nn.Sequential
        The MLP, ``nx + nu -> p``.
    x_mean, x_scale, u_mean, u_scale, y_mean, y_scale : Tensor
        Buffers.
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        p: int,
        hidden: Sequence[int] = (32,),
        activation: Activation = "tanh",
        *,
        x_mean: ArrayLike = None,
        x_scale: ArrayLike = None,
        u_mean: ArrayLike = None,
        u_scale: ArrayLike = None,
        y_mean: ArrayLike = None,
        y_scale: ArrayLike = None,
        last_layer_scale: float | None = None,
        random_state: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(
            nx, nu, x_mean=x_mean, x_scale=x_scale, u_mean=u_mean, u_scale=u_scale, dtype=dtype, device=device
        )
        self.p = V.check_count(p, "p", 1)
        self.hidden = _check_hidden(hidden)
        self.activation = activation
        self.register_buffer("y_mean", _buffer(y_mean, self.p, "y_mean", 0.0, dtype, device))
        y_scale = _buffer(y_scale, self.p, "y_scale", 1.0, dtype, device, positive=True)
        self.register_buffer("y_scale", y_scale)
        with torch.random.fork_rng(devices=[]):
            if random_state is not None:
                torch.manual_seed(int(random_state))
            self.net = _build_mlp(
                self.nx + self.nu, self.p, self.hidden, activation, last_layer_scale, dtype, device
            )

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """Output mean, shape ``(..., p)``."""
        return self.y_mean + self.y_scale * self.net(self.normalised_input(x, u))

    @torch.no_grad()
    def fit_normalisation(
        self, x: ArrayLike = None, u: ArrayLike = None, y: ArrayLike = None, *, robust: bool = True
    ) -> MLPObservation:
        """Set the normalisation buffers from data (call it before fitting).

        Parameters
        ----------
        x : array-like of shape (..., nx), optional
            Representative states (``None`` keeps ``x_mean``, ``x_scale``).
        u : array-like of shape (..., nu), optional
            Representative inputs.
        y : array-like of shape (..., p) or (N,) when p == 1, optional
            Measured outputs (NaN ignored): set ``y_mean``, ``y_scale``.
        robust : bool, default=True
            Use the median and ``1.4826 * MAD`` of ``y`` (insensitive to outliers) instead of
            the mean and standard deviation.

        Returns
        -------
        self
        """
        if x is not None:
            self._set_input_normalisation(x, u)
        elif u is not None and self.nu > 0:
            mean, std = _mean_std(_as_rows(u, self.nu, "u"))
            self.u_mean.copy_(mean)
            self.u_scale.copy_(std)
        if y is not None:
            rows = _as_rows(y, self.p, "y")
            if robust:
                med, mad = robust_scale_torch(rows, dim=0)
                fallback = _mean_std(rows)[1]
                ok = torch.isfinite(mad) & (mad > 1e-12 * med.abs().clamp_min(1.0))
                self.y_mean.copy_(torch.nan_to_num(med))
                self.y_scale.copy_(torch.where(ok, mad, fallback))
            else:
                mean, std = _mean_std(rows)
                self.y_mean.copy_(mean)
                self.y_scale.copy_(std)
        return self

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}, p={self.p}, hidden={self.hidden}, activation={self.activation!r}"


class GreyBoxTransition(_NeuralBlock):
    """Physical model plus neural correction: ``f(x, u) = physical(x, u) + out_scale * MLP(...)``.

    The MLP sees ``[x_norm, u_norm]`` like :class:`MLPTransition`.  Its last layer starts at zero
    (``last_layer_scale=0``: zero weights and bias), so the untrained model equals ``physical``
    exactly; the gradient still reaches the last layer, so the correction grows where the
    physical model misses.  The physical module's free parameters are estimated jointly with the
    network unless ``freeze_physical=True``.

    Parameters
    ----------
    physical : nn.Module
        The first-principles transition, called ``physical(x, u)`` and returning ``(..., nx)``.
        It is stored as a sub-module (not copied): ``.to()`` and pickling include it.
    nx : int
        State dimension.
    nu : int
        Input dimension (0 for a system without input).
    hidden : sequence of int, default=(16,)
        Widths of the correction's hidden layers.
    activation : str or callable, default="tanh"
    x_mean, x_scale : float or array-like of shape (nx,), optional
    u_mean, u_scale : float or array-like of shape (nu,), optional
    out_scale : float or array-like of shape (nx,), optional
        Scale of the correction (default ``x_scale``).
    last_layer_scale : float, default=0.0
        Size of the correction's initial last-layer weights (0: starts exactly as ``physical``).
    freeze_physical : bool, default=False
        Set ``requires_grad=False`` on the physical module's parameters (only the correction is
        estimated).
    random_state : int, optional
    dtype : torch.dtype, default=torch.float64
        Dtype of the correction and its buffers (``physical`` is converted too).
    device : torch.device or str, optional

    Attributes
    ----------
    physical : nn.Module
    net : nn.Sequential
        The correction MLP, ``nx + nu -> nx``.
    x_mean, x_scale, u_mean, u_scale, out_scale : Tensor
        Buffers.
    """

    def __init__(
        self,
        physical: nn.Module,
        nx: int,
        nu: int,
        hidden: Sequence[int] = (16,),
        activation: Activation = "tanh",
        *,
        x_mean: ArrayLike = None,
        x_scale: ArrayLike = None,
        u_mean: ArrayLike = None,
        u_scale: ArrayLike = None,
        out_scale: ArrayLike = None,
        last_layer_scale: float = 0.0,
        freeze_physical: bool = False,
        random_state: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        if not isinstance(physical, nn.Module):
            raise TypeError(f"physical must be a torch.nn.Module, got {type(physical).__name__}")
        super().__init__(
            nx, nu, x_mean=x_mean, x_scale=x_scale, u_mean=u_mean, u_scale=u_scale, dtype=dtype, device=device
        )
        self.physical = physical.to(dtype=dtype, device=device)
        if freeze_physical:
            for prm in self.physical.parameters():
                prm.requires_grad_(False)
        self._add_step_network(hidden, activation, last_layer_scale, out_scale, random_state, dtype, device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """Next-state mean, shape ``(..., nx)``."""
        return self.physical(x, u) + self.out_scale * self.net(self.normalised_input(x, u))

    def step_function(self, u: Tensor) -> Callable[[Tensor, int], Tensor]:
        """``step(x, t)``, equal bit for bit to ``self(x, u[:, t])`` with ``x`` of shape ``(n, nx)``,
        for simulating over inputs ``u`` of shape ``(n, T, nu)``: the network's term as in
        :meth:`MLPTransition.step_function`, ``physical`` called as a module."""
        increment = self._increment_function(u, GreyBoxTransition)
        if increment is None:
            return lambda x, t: self(x, u[:, t])
        physical = self.physical
        return lambda x, t: physical(x, u[:, t]) + increment(x, t)

    def correction(self, x: Tensor, u: Tensor) -> Tensor:
        """The neural part alone, ``out_scale * MLP([x_norm, u_norm])``, shape ``(..., nx)``."""
        return self.out_scale * self.net(self.normalised_input(x, u))

    @torch.no_grad()
    def fit_normalisation(
        self, x: ArrayLike, u: ArrayLike = None, x_next: ArrayLike = None
    ) -> GreyBoxTransition:
        """Set the normalisation buffers from data (call it before fitting).

        Parameters
        ----------
        x : array-like of shape (..., nx)
            Representative states; NaN is ignored.
        u : array-like of shape (..., nu), optional
            Representative inputs.
        x_next : array-like of shape (..., nx), optional
            The states one step after ``x``: ``out_scale`` becomes the standard deviation of the
            physical model's one-step errors ``x_next - physical(x, u)`` (needs ``u`` when
            ``nu > 0``).  Otherwise ``out_scale = x_scale``.

        Returns
        -------
        self
        """
        self._set_input_normalisation(x, u)
        if x_next is None:
            self.out_scale.copy_(self.x_scale)
            return self
        xr = _as_rows(x, self.nx, "x")
        if self.nu == 0:
            ur = xr.new_zeros(xr.shape[0], 0)
        elif u is None:
            raise ValueError("fit_normalisation needs u to compute the physical model's errors")
        else:
            ur = _as_rows(u, self.nu, "u")
        ref = self.x_mean
        pred = self.physical(xr.to(ref), ur.to(ref)).to(xr)
        self.out_scale.copy_(_mean_std(_as_rows(x_next, self.nx, "x_next") - pred)[1])
        return self

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}, hidden={self.hidden}, activation={self.activation!r}"


class MLPDerivative(_NeuralBlock):
    """Neural ODE right-hand side ``dx/dt = out_scale * MLP([x_norm, u_norm])``.

    The ``rhs`` of a :class:`~torch_nssm.blocks.continuous.ContinuousTimeTransition` (``f =
    ContinuousTimeTransition(MLPDerivative(nx, nu), Ts)``).  As in :class:`MLPTransition`, the last
    layer starts small, so the untrained derivative is near zero and the transition near ``x' = x``.

    Parameters
    ----------
    nx, nu : int
        State and input dimensions.
    hidden : sequence of int, default=(32, 32)
    activation : str or callable, default="tanh"
    x_mean, x_scale, u_mean, u_scale : float or array-like, optional
        Input normalisation (default 0 and 1).
    out_scale : float or array-like of shape (nx,), optional
        Scale of the derivative (default ``x_scale``: per unit of time).
    last_layer_scale : float, default=1e-3
    random_state : int, optional
    dtype : torch.dtype, default=torch.float64
    device : torch.device or str, optional

    Attributes
    ----------
    net : nn.Sequential
        The MLP, ``nx + nu -> nx``.
    x_mean, x_scale, u_mean, u_scale, out_scale : Tensor
        Buffers.
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        hidden: Sequence[int] = (32, 32),
        activation: Activation = "tanh",
        *,
        x_mean: ArrayLike = None,
        x_scale: ArrayLike = None,
        u_mean: ArrayLike = None,
        u_scale: ArrayLike = None,
        out_scale: ArrayLike = None,
        last_layer_scale: float = 1e-3,
        random_state: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(
            nx, nu, x_mean=x_mean, x_scale=x_scale, u_mean=u_mean, u_scale=u_scale, dtype=dtype, device=device
        )
        self._add_step_network(hidden, activation, last_layer_scale, out_scale, random_state, dtype, device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """``dx/dt``, shape ``(..., nx)``."""
        return self.out_scale * self.net(self.normalised_input(x, u))

    @torch.no_grad()
    def fit_normalisation(self, x: ArrayLike, u: ArrayLike = None, dxdt: ArrayLike = None) -> MLPDerivative:
        """Set the normalisation buffers from data (call it before fitting).

        Parameters
        ----------
        x : array-like of shape (..., nx)
            Representative states; NaN is ignored.
        u : array-like of shape (..., nu), optional
            Representative inputs (``None`` keeps ``u_mean``, ``u_scale``).
        dxdt : array-like of shape (..., nx), optional
            Derivatives at ``x`` (e.g. one-sample increments over ``Ts``): ``out_scale`` becomes
            their standard deviation.  Otherwise ``out_scale = x_scale``.

        Returns
        -------
        self
        """
        self._set_input_normalisation(x, u)
        if dxdt is None:
            self.out_scale.copy_(self.x_scale)
        else:
            self.out_scale.copy_(_mean_std(_as_rows(dxdt, self.nx, "dxdt"))[1])
        return self

    def extra_repr(self) -> str:
        return f"nx={self.nx}, nu={self.nu}, hidden={self.hidden}, activation={self.activation!r}"
