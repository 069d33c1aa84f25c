"""Small robust statistics shared by the application modules."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["MAD_TO_STD", "robust_scale", "robust_scale_torch"]

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
