"""Measurement-noise families: one file each, one line each in :data:`NOISE_MODELS`."""

from __future__ import annotations

from .base import MaskedScale, MeasurementNoise, NoiseEvaluator, masked_scale, symmetric_pd
from .gaussian import GaussianNoise
from .student_t import (
    StudentTNoise,
    dof_equation,
    latent_scale_expectations,
    sample_student_t,
    solve_dof,
    student_t_log_prob,
)
from .student_t_per_output import StudentTPerOutputNoise

__all__ = [
    "NOISE_MODELS",
    "get_noise_model",
    "MeasurementNoise",
    "NoiseEvaluator",
    "GaussianNoise",
    "StudentTNoise",
    "StudentTPerOutputNoise",
    "MaskedScale",
    "masked_scale",
    "symmetric_pd",
    "student_t_log_prob",
    "latent_scale_expectations",
    "dof_equation",
    "solve_dof",
    "sample_student_t",
]

#: The estimator's ``noise=`` choices.
NOISE_MODELS: dict[str, type[MeasurementNoise]] = {
    "student-t": StudentTNoise,
    "gaussian": GaussianNoise,
    "student-t-per-output": StudentTPerOutputNoise,
}


def get_noise_model(name: str) -> type[MeasurementNoise]:
    """The noise family registered as ``name``."""
    try:
        return NOISE_MODELS[name]
    except KeyError:
        raise ValueError(f"noise must be one of {sorted(NOISE_MODELS)}, got {name!r}") from None
