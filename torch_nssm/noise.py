"""Measurement-noise families for ``RobustNSSMEstimator(noise=...)`` (docs/noise_models.md).

Pass a name (``"student-t"``, ``"gaussian"``, ``"student-t-per-output"``), whose options come from
the estimator's ``dof_init``, ``fit_dof`` and ``dof_bounds``, or a specification object with its
own options::

    from torch_nssm.noise import StudentT
    RobustNSSMEstimator(f, g, x0_mean=[0.0], noise=StudentT(dof=3.0, dof_bounds=(2.0, 1000.0)))

A new family is a :class:`NoiseSpec` (its options) and a :class:`MeasurementNoise` (its
parameters as tensors and what the filter, the E- and M-steps and the standard errors ask of them)
in one file, made reachable by name with :func:`register_noise_model` (docs/design.md).
"""

from __future__ import annotations

from .core.noise import (
    NOISE_MODELS,
    Gaussian,
    MeasurementNoise,
    NoiseSpec,
    StudentT,
    StudentTPerOutput,
    get_noise_model,
    register_noise_model,
)

__all__ = [
    "Gaussian",
    "StudentT",
    "StudentTPerOutput",
    "NoiseSpec",
    "MeasurementNoise",
    "NOISE_MODELS",
    "get_noise_model",
    "register_noise_model",
]
