"""Small robust statistics shared by the application modules."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["MAD_TO_STD", "robust_scale", "robust_scale_torch", "quantization_step", "gross_error_share"]

#: ``1 / Phi^-1(3/4)``: the median absolute deviation times this estimates a Gaussian s.d.
MAD_TO_STD = 1.4826


def robust_scale(values, axis: int | None = 0, center=None) -> np.ndarray:
    """``1.4826 * median(|values - center|)`` along ``axis``, ignoring NaN.

    ``center`` defaults to the NaN-ignoring median.  An all-NaN slice gives NaN (callers choose a
    fallback).
    """
    a = np.asarray(values, dtype=np.float64)
    med = np.nanmedian(a, axis=axis, keepdims=True) if center is None else center
    return MAD_TO_STD * np.nanmedian(np.abs(a - med), axis=axis)


def robust_scale_torch(values: Tensor, dim: int = 0) -> tuple[Tensor, Tensor]:
    """NaN-ignoring median and ``1.4826 * MAD`` of a tensor along ``dim``."""
    med = torch.nanmedian(values, dim=dim, keepdim=True).values
    mad = MAD_TO_STD * torch.nanmedian((values - med).abs(), dim=dim).values
    return med.squeeze(dim), mad


def quantization_step(y) -> np.ndarray:
    """The resolution of each output column of ``y`` ``(N, p)`` whose values sit on a grid (an
    encoder, an A/D converter), else 0.

    The resolution ``q`` is a gap between distinct values that recurs (the most frequent gaps are
    tried) and of which at least 80 % of the gaps are whole multiples (so that a few gross outliers
    off the grid do not hide it); continuous data have no recurring gap.
    """
    a = np.asarray(y, dtype=np.float64)
    a = a.reshape(a.shape[0], -1)
    out = np.zeros(a.shape[1])
    for j in range(a.shape[1]):
        values = np.unique(a[:, j][np.isfinite(a[:, j])])
        if values.size < 10:
            continue
        gaps = np.diff(values)
        span = float(values[-1] - values[0])
        distinct, counts = np.unique(np.round(gaps / span, 9), return_counts=True)
        for i in np.argsort(-counts)[:3]:
            if counts[i] < 3:
                break
            q = float(np.median(gaps[np.round(gaps / span, 9) == distinct[i]]))
            k = gaps / q
            if q > 0 and np.mean(np.abs(k - np.round(k)) <= 1e-3) >= 0.8:
                out[j] = q
                break
    return out


def gross_error_share(residuals, z: float = 5.0) -> float:
    """Share of the finite ``residuals`` beyond ``z`` robust standard deviations (1.4826 MAD about
    0, per column): about 6e-7 for Gaussian noise at ``z = 5``, much more where glitches are."""
    a = np.asarray(residuals, dtype=np.float64)
    a = a.reshape(a.shape[0], -1)
    counts, total = 0, 0
    for j in range(a.shape[1]):
        col = a[:, j][np.isfinite(a[:, j])]
        if not col.size:
            continue
        s = MAD_TO_STD * np.median(np.abs(col))
        if not s > 0:
            continue
        counts += int(np.sum(np.abs(col) > z * s))
        total += col.size
    return counts / total if total else 0.0
