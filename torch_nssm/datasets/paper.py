"""The numerical example of the paper's Section 4.1: data generators and its ``f`` / ``g``.

``x_{k+1} = a x_k + b u_k + w_k``, ``y_k = c cos(x_k) + v_k`` (eqs. 40-41), with additive outliers
(see :mod:`torch_nssm.datasets`).  Three generators draw it with the settings of the paper's
experiments; :class:`PaperTransition` and :class:`PaperObservation` are the model as ready-made
modules, linear in their parameters (closed-form M-steps).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .. import _validation as V
from .._ops import broadcast_leading
from ..core.parametric import LinearInParameters
from ._base import NOISE_KINDS, SimulatedData, _add_outliers, _measurement_noise, _scalar_parameter

__all__ = [
    "PAPER_X0_COV",
    "make_paper_example",
    "make_gopaluni_example",
    "make_huang_example",
    "PaperTransition",
    "PaperObservation",
]

#: Prior variance of the first state of the Section 4.1 system (``x_0 ~ N(0, PAPER_X0_COV)``).
#: The paper does not state it; 1.0 is our choice.
PAPER_X0_COV: float = 1.0


def _simulate_paper_system(
    *,
    name: str,
    n_samples: Any,
    outlier_fraction: Any,
    outlier_range: Any,
    noise: str,
    a: Any,
    b: Any,
    c: Any,
    Rw: Any,
    Rv: Any,
    dof: Any,
    input_std: Any,
    random_state: Any,
) -> SimulatedData:
    n = V.check_count(n_samples, "n_samples", 1)
    fraction = V.check_real(outlier_fraction, "outlier_fraction", low=0.0, high=1.0, high_open=True)
    rng_out = V.check_pair(outlier_range, "outlier_range")
    noise = V.check_choice(noise, "noise", NOISE_KINDS)
    a = V.check_real(a, "a")
    b = V.check_real(b, "b")
    c = V.check_real(c, "c")
    Rw = V.check_real(Rw, "Rw", low=0.0)
    Rv = V.check_real(Rv, "Rv", low=0.0)
    input_std = V.check_real(input_std, "input_std", low=0.0)
    nu_dof = (
        math.inf if noise == "gaussian"
        else V.check_real(dof, "dof", low=0.0, high=math.inf, low_open=True, high_open=True)
    )

    rng = np.random.default_rng(random_state)
    x0 = rng.normal(0.0, math.sqrt(PAPER_X0_COV))
    u = input_std * rng.standard_normal(n)
    w = math.sqrt(Rw) * rng.standard_normal(n)
    x = np.empty(n)
    x[0] = x0
    for k in range(n - 1):
        x[k + 1] = a * x[k] + b * u[k] + w[k]
    v = _measurement_noise(rng, n, np.array([[Rv]]), noise, dof_init=nu_dof)[:, 0]
    y_clean = (c * np.cos(x) + v)[:, None]
    y, mask = _add_outliers(rng, y_clean, fraction, rng_out)
    params = {
        "a": a,
        "b": b,
        "c": c,
        "Rw": [[Rw]],
        "Rv": [[Rv]],
        "dof": nu_dof,
        "noise": noise,
        "x0_mean": [0.0],
        "x0_cov": [[PAPER_X0_COV]],
        "input_std": input_std,
        "outlier_fraction": fraction,
        "outlier_range": list(rng_out),
        "n_outliers": int(mask.sum()),
    }
    return SimulatedData(
        u=u[:, None],
        y=y,
        x=x[:, None],
        y_clean=y_clean,
        outlier_mask=mask,
        params=params,
        name=name,
    )


def make_paper_example(
    n_samples: int = 500,
    outlier_fraction: float = 0.1,
    outlier_range: tuple[float, float] = (-5.0, 5.0),
    noise: str = "gaussian",
    a: float = 0.9,
    b: float = 1.0,
    c: float = 1.0,
    Rw: float = 0.1,
    Rv: float = 0.1,
    dof: float = 3.0,
    input_std: float = 1.0,
    random_state: int | np.random.Generator | None = None,
) -> SimulatedData:
    """The numerical example of Section 4.1 (eqs. 40-41), with additive outliers.

    ``x_{k+1} = a x_k + b u_k + w_k``, ``y_k = c cos(x_k) + v_k``, ``w_k ~ N(0, Rw)``,
    ``u_k ~ N(0, input_std^2)`` white, ``x_0 ~ N(0, 1)`` (``PAPER_X0_COV = 1``, our choice: the
    paper does not state the initial state).  ``v_k ~ N(0, Rv)`` for ``noise="gaussian"`` or
    ``St(0, Rv, dof)`` (``Rv`` the scale) for ``noise="student-t"``.  Then
    ``round(outlier_fraction * n_samples)`` distinct samples, chosen at random, get a
    ``U[outlier_range]`` draw added to ``y`` (docs/method.md §6-7: additive outliers).

    Parameters
    ----------
    n_samples : int
        Record length ``N`` (the paper: 500).
    outlier_fraction : float in [0, 1)
        Fraction of samples that get an outlier (the paper: 0.1).
    outlier_range : (float, float)
        Range of the uniform outliers (the paper: [-5, 5]).
    noise : {"gaussian", "student-t"}
        Distribution of the measurement noise ``v``.
    a, b, c : float
        True parameters (the paper: 0.9, 1, 1).
    Rw, Rv : float
        Process-noise variance and measurement-noise variance (Gaussian) or scale (Student-t);
        the paper: 0.1 and 0.1.  Zero gives a noise-free record.
    dof : float
        Degrees of freedom of ``v`` when ``noise="student-t"`` (ignored otherwise).
    input_std : float
        Standard deviation of the Gaussian white input.
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.

    Returns
    -------
    SimulatedData
        ``name="paper_example"``; ``u``, ``x``, ``y`` of shape ``(N, 1)``.
    """
    return _simulate_paper_system(
        name="paper_example",
        n_samples=n_samples,
        outlier_fraction=outlier_fraction,
        outlier_range=outlier_range,
        noise=noise,
        a=a,
        b=b,
        c=c,
        Rw=Rw,
        Rv=Rv,
        dof=dof,
        input_std=input_std,
        random_state=random_state,
    )


def make_gopaluni_example(
    n_samples: int = 400,
    outlier_fraction: float = 0.05,
    outlier_range: tuple[float, float] = (-6.0, 6.0),
    random_state: int | np.random.Generator | None = None,
) -> SimulatedData:
    """The data of the comparison with Gopaluni's Gaussian particle EM (Section 4.1, Figs. 3-6).

    The system of :func:`make_paper_example` (``a=0.9``, ``b=1``, ``c=1``, ``Rw=Rv=0.1``,
    Gaussian noise, unit-variance white input) with ``N = 400``; the paper uses 0% and 5%
    outliers, uniform in [-6, 6] (printed "[6,6]" in the paper: a typo).

    Parameters
    ----------
    n_samples : int
        Record length (the paper: 400).
    outlier_fraction : float in [0, 1)
        Fraction of samples with an additive outlier (the paper: 0 and 0.05).
    outlier_range : (float, float)
        Range of the uniform outliers.
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.

    Returns
    -------
    SimulatedData
        ``name="gopaluni_example"``.
    """
    return _simulate_paper_system(
        name="gopaluni_example",
        n_samples=n_samples,
        outlier_fraction=outlier_fraction,
        outlier_range=outlier_range,
        noise="gaussian",
        a=0.9,
        b=1.0,
        c=1.0,
        Rw=0.1,
        Rv=0.1,
        dof=math.inf,
        input_std=1.0,
        random_state=random_state,
    )


def make_huang_example(
    n_samples: int = 1000,
    Rv: float = 0.01,
    dof: float = 1.0,
    random_state: int | np.random.Generator | None = None,
    *,
    Rw: float = 0.1,
) -> SimulatedData:
    """The data of the comparison with Huang et al. (2016) (Section 4.1, Fig. 7, Table 1).

    The system of :func:`make_paper_example` (``a=0.9``, ``b=1``, ``c=1``, unit-variance white
    input) with ``N = 1000`` and heavy-tailed measurement noise ``v ~ St(0, Rv, dof)``; the paper:
    ``St(0, 0.01, 1)``, a Cauchy law of scale 0.1.  No outliers are added: the heavy tail of the
    noise makes them (``y_clean == y``, ``outlier_mask`` all False).  The paper does not restate
    the process noise for this comparison; ``Rw = 0.1`` (Gaussian), as in eq. (41), is our reading.

    Parameters
    ----------
    n_samples : int
        Record length (the paper: 1000).
    Rv : float
        Scale (squared) of the Student-t measurement noise.
    dof : float
        Degrees of freedom (1: Cauchy).
    random_state : int, Generator or None
        Seed of ``np.random.default_rng``.
    Rw : float, keyword-only
        Process-noise variance.

    Returns
    -------
    SimulatedData
        ``name="huang_example"``.
    """
    return _simulate_paper_system(
        name="huang_example",
        n_samples=n_samples,
        outlier_fraction=0.0,
        outlier_range=(-1.0, 1.0),
        noise="student-t",
        a=0.9,
        b=1.0,
        c=1.0,
        Rw=Rw,
        Rv=Rv,
        dof=dof,
        input_std=1.0,
        random_state=random_state,
    )


# --------------------------------------------------------------------------------------------
# The model as f / g modules
# --------------------------------------------------------------------------------------------


class PaperTransition(LinearInParameters):
    """``f(x, u) = a x + b u`` (Section 4.1; ``nx = nu = 1``), linear in ``theta = (a, b)``.

    Parameters
    ----------
    a, b : float or Tensor
        Initial values (default: the paper's true values 0.9 and 1).
    dtype : torch.dtype
        Parameter dtype.
    device : torch.device or str, optional
    """

    nx = 1
    nu = 1

    def __init__(
        self,
        a: float | Tensor = 0.9,
        b: float | Tensor = 1.0,
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.a = _scalar_parameter(a, dtype, device)
        self.b = _scalar_parameter(b, dtype, device)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi = [[x, u]]`` of shape ``(..., 1, 2)`` and a zero offset ``(..., 1)``."""
        x, u = broadcast_leading(x, u)
        Phi = torch.stack([x[..., 0], u[..., 0]], dim=-1).unsqueeze(-2)
        return Phi, torch.zeros_like(x)

    def predict(self, x: Tensor, u: Tensor, theta: Tensor) -> Tensor:
        """``a x + b u`` in two passes (:meth:`LinearInParameters.predict`)."""
        return torch.addcmul(u * theta[..., 1:2], x, theta[..., 0:1])

    def frozen_predict(self, theta: Tensor):
        """``a x + b u`` for one filter pass: ``a`` and ``b`` viewed once, and the input term ``b u``
        of every step made at once (``step_inputs``: ``(B, 1, 1)`` per step, broadcast over the
        particles), so that a step costs one ``addcmul`` (the same values as :meth:`predict`).

        ``a`` is expanded to the particles' shape once (at the first call, again if the shape
        changes): with two broadcast operands ``addcmul`` runs its scalar loop, with one its
        vectorised loop (2.2x faster at 10^4 particles, the same fused multiply-add).
        """
        a, b = theta[..., 0:1], theta[..., 1:2]
        full = [a]

        def f(x: Tensor, bu: Tensor) -> Tensor:
            if full[0].shape != x.shape:
                full[0] = a.expand_as(x).contiguous()
            return torch.addcmul(bu, x, full[0])

        f.step_inputs = lambda u: (u.unsqueeze(-2) * b).unbind(0)
        return f

    def extra_repr(self) -> str:
        return f"a={self.a.item():.6g}, b={self.b.item():.6g}"


class PaperObservation(LinearInParameters):
    """``g(x, u) = c cos(x)`` (Section 4.1; ``p = 1``), linear in ``theta = (c,)``; ``u`` unused.

    Parameters
    ----------
    c : float or Tensor
        Initial value (default: the paper's true value 1).
    dtype : torch.dtype
        Parameter dtype.
    device : torch.device or str, optional
    """

    nx = 1
    ny = 1

    def __init__(
        self,
        c: float | Tensor = 1.0,
        *,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.c = _scalar_parameter(c, dtype, device)

    def features(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``Phi = [[cos x]]`` of shape ``(..., 1, 1)`` and a zero offset ``(..., 1)``."""
        return torch.cos(x).unsqueeze(-1), torch.zeros_like(x)

    def predict(self, x: Tensor, u: Tensor, theta: Tensor) -> Tensor:
        """``c cos(x)`` in two passes (:meth:`LinearInParameters.predict`)."""
        return theta[..., 0:1] * torch.cos(x)

    def frozen_predict(self, theta: Tensor):
        """``c cos(x)`` for one filter pass: ``c`` viewed once, no inputs (``step_inputs``: ``None``
        at every step)."""
        c = theta[..., 0:1]

        def g(x: Tensor, u) -> Tensor:
            return c * torch.cos(x)

        g.step_inputs = lambda u: [None] * u.shape[0]
        return g

    def extra_repr(self) -> str:
        return f"c={self.c.item():.6g}"
