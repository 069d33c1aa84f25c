"""Shared parts of the simulated data sets: :class:`SimulatedData`, noise and outliers.

Time convention (docs/method.md §7): sample ``k`` has input ``u_k`` and output ``y_k``; ``y_k``
observes ``x_k``; ``x_{k+1} = f(x_k, u_k) + w_k``.  Outliers are *added* to the clean outputs: a
random subset of exactly ``round(fraction * N)`` samples gets an independent ``U[lo, hi]`` draw
added to every output component, so ``y - y_clean`` is non-zero exactly where ``outlier_mask``
is True.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Union

import numpy as np
import torch
from torch import Tensor, nn

from ..core.noise import NOISE_MODELS, noise_spec
from ..core.noise.base import psd_sqrt

__all__ = ["SimulatedData"]

#: The measurement-noise families a simulated record can have (those registered with the package).
NOISE_KINDS = tuple(NOISE_MODELS)

ArrayLike = Union[float, Sequence[float], Sequence[Sequence[float]], np.ndarray]


@dataclass(frozen=True, eq=False)
class SimulatedData:
    """A simulated record: inputs, outputs, true states and the true parameters.

    Attributes
    ----------
    u : ndarray, shape (N, nu)
        Inputs (``nu = 0`` for a system without input).
    y : ndarray, shape (N, p)
        Outputs, with outliers.
    x : ndarray, shape (N, nx)
        True states; ``y[k]`` observes ``x[k]``.
    y_clean : ndarray, shape (N, p)
        Outputs without the added outliers (measurement noise included).
    outlier_mask : ndarray of bool, shape (N,)
        True for the samples that got an outlier (in any output component).
    params : dict
        True values: model parameters, ``Rw``, ``Rv`` (matrices as nested lists), ``dof``
        (``inf`` for Gaussian noise), ``x0_mean`` (list), ``x0_cov`` (nested list), and the
        generator's settings.
    name : str
        Which system: ``"paper_example"``, ``"gopaluni_example"``, ``"huang_example"`` or
        ``"manipulator"`` (:func:`torch_nssm.models.true_model` dispatches on it).
    """

    u: np.ndarray
    y: np.ndarray
    x: np.ndarray
    y_clean: np.ndarray
    outlier_mask: np.ndarray
    params: dict[str, Any] = field(default_factory=dict)
    name: str = ""

    @property
    def n_samples(self) -> int:
        """Number of samples ``N``."""
        return int(self.y.shape[0])

    @property
    def nx(self) -> int:
        """State dimension."""
        return int(self.x.shape[1])

    @property
    def nu(self) -> int:
        """Input dimension."""
        return int(self.u.shape[1])

    @property
    def ny(self) -> int:
        """Output dimension ``p``."""
        return int(self.y.shape[1])

    def __repr__(self) -> str:
        return (
            f"SimulatedData(name={self.name!r}, n_samples={self.n_samples}, nx={self.nx}, "
            f"nu={self.nu}, ny={self.ny}, n_outliers={int(self.outlier_mask.sum())})"
        )



# --------------------------------------------------------------------------------------------
# Noise and outliers
# --------------------------------------------------------------------------------------------


#: A matrix ``S`` with ``S S^T = cov`` (works for singular PSD matrices).
_cov_sqrt = psd_sqrt


def _measurement_noise(
    rng: np.random.Generator, n: int, cov: np.ndarray, noise: str, **shortcuts
) -> np.ndarray:
    """``n`` draws (shape ``(n, p)``) of the measurement noise ``noise`` (a registered family, with
    the estimator's shortcut parameters ``shortcuts`` for its values, e.g. ``dof_init``) of scale
    ``cov``, by the family's sampler from the stream ``rng``."""
    model = noise_spec(noise, **shortcuts).initial(torch.as_tensor(np.asarray(cov, dtype=np.float64)))
    return model.sample((n,), rng).numpy()


def outlier_rows(rng: np.random.Generator, n: int, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """``round(fraction * n)`` distinct samples drawn from ``rng``: their indices and the mask."""
    n_out = int(round(fraction * n))
    mask = np.zeros(n, dtype=bool)
    idx = rng.choice(n, size=n_out, replace=False) if n_out > 0 else np.zeros(0, dtype=int)
    mask[idx] = True
    return idx, mask


def _add_outliers(
    rng: np.random.Generator,
    y_clean: np.ndarray,
    fraction: float,
    outlier_range: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    idx, mask = outlier_rows(rng, y_clean.shape[0], fraction)
    y = y_clean.copy()
    if idx.size:
        lo, hi = outlier_range
        y[idx] += rng.uniform(lo, hi, size=(idx.size, y.shape[1]))
    return y, mask


def _to_list(a: np.ndarray) -> Any:
    return np.asarray(a, dtype=np.float64).tolist()



def _scalar_parameter(value: float | Tensor, dtype: torch.dtype, device) -> nn.Parameter:
    """A 0-dimensional parameter of the ready-made models."""
    t = torch.as_tensor(value, dtype=dtype, device=device).detach().clone().reshape(())
    return nn.Parameter(t)
