"""Measurement-noise families: one file each, one line each in :data:`NOISE_MODELS`.

The registry also turns the estimator's ``noise=`` value into a specification
(:func:`noise_spec`): a registered name, with the estimator's shortcut parameters
(:data:`NOISE_SHORTCUTS`) forwarded to the family, or a specification object as it is.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .base import (
    MaskedScale,
    MeasurementNoise,
    NoiseEvaluator,
    NoiseSpec,
    masked_scale,
    random_source,
    symmetric_pd,
)
from .gaussian import Gaussian, GaussianNoise
from .joint import JointScaleNoise, SquaredNormEvaluator
from .student_t import (
    StudentT,
    StudentTNoise,
    dof_equation,
    latent_scale_expectations,
    sample_student_t,
    solve_dof,
    student_t_log_prob,
)
from .student_t_per_output import StudentTPerOutput, StudentTPerOutputNoise

__all__ = [
    "NOISE_MODELS",
    "NOISE_SHORTCUTS",
    "get_noise_model",
    "register_noise_model",
    "noise_spec",
    "restart_parameters",
    "NoiseSpec",
    "MeasurementNoise",
    "NoiseEvaluator",
    "JointScaleNoise",
    "SquaredNormEvaluator",
    "Gaussian",
    "GaussianNoise",
    "StudentT",
    "StudentTNoise",
    "StudentTPerOutput",
    "StudentTPerOutputNoise",
    "MaskedScale",
    "masked_scale",
    "random_source",
    "symmetric_pd",
    "student_t_log_prob",
    "latent_scale_expectations",
    "dof_equation",
    "solve_dof",
    "sample_student_t",
]

#: The estimator's ``noise=`` names: name -> noise model class (whose ``SPEC`` is the specification).
NOISE_MODELS: dict[str, type[MeasurementNoise]] = {
    "student-t": StudentTNoise,
    "gaussian": GaussianNoise,
    "student-t-per-output": StudentTPerOutputNoise,
}

#: The estimator's shortcut parameters and their defaults: with a ``noise=`` name they are forwarded
#: to the family's :meth:`~.base.NoiseSpec.from_shortcuts` (which reads those it has); with a
#: specification object they must keep these defaults (the object holds its own options).
NOISE_SHORTCUTS: dict[str, Any] = {"dof_init": 5.0, "fit_dof": True, "dof_bounds": (0.1, 1000.0)}


def register_noise_model(model: type[MeasurementNoise]) -> type[MeasurementNoise]:
    """Add a noise family: ``model`` (a :class:`MeasurementNoise` subclass whose ``SPEC`` is its
    :class:`NoiseSpec`) becomes ``noise=model.name``.  Returns ``model`` (usable as a decorator)."""
    if not (isinstance(model, type) and issubclass(model, MeasurementNoise)):
        raise TypeError(f"a noise family must be a MeasurementNoise subclass, got {model!r}")
    spec = model.SPEC
    if not (isinstance(spec, type) and issubclass(spec, NoiseSpec)) or spec is NoiseSpec:
        raise TypeError(f"{model.__name__}.SPEC must be its NoiseSpec subclass, got {spec!r}")
    if not model.name or spec.name != model.name:
        raise ValueError(
            f"{model.__name__}.name and {spec.__name__}.name must be the same non-empty registry name, "
            f"got {model.name!r} and {spec.name!r}"
        )
    NOISE_MODELS[model.name] = model
    return model


def get_noise_model(name: str) -> type[MeasurementNoise]:
    """The noise family registered as ``name``."""
    try:
        return NOISE_MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"noise must be one of {sorted(NOISE_MODELS)}, got {name!r}") from None


def _is_default(value: Any, default: Any) -> bool:
    try:
        a, b = np.asarray(value, dtype=float), np.asarray(default, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.shape == b.shape and bool(np.all(a == b))


def noise_spec(noise: str | NoiseSpec, **shortcuts: Any) -> NoiseSpec:
    """The specification of ``noise``: a registered name (the family's specification from the
    shortcut parameters ``shortcuts``, see :data:`NOISE_SHORTCUTS`) or a specification object,
    returned as it is; the shortcuts must then keep their defaults (a ``ValueError`` says which do
    not)."""
    if isinstance(noise, NoiseSpec):
        changed = [
            k for k, v in shortcuts.items() if k in NOISE_SHORTCUTS and not _is_default(v, NOISE_SHORTCUTS[k])
        ]
        if changed:
            given = ", ".join(f"{k}={shortcuts[k]!r}" for k in changed)
            raise ValueError(
                f"noise={noise!r} holds its own options: set them there and leave "
                f"{', '.join(NOISE_SHORTCUTS)} at their defaults (got {given})"
            )
        return noise
    if not isinstance(noise, str):
        raise TypeError(
            f"noise must be one of {sorted(NOISE_MODELS)} or a noise specification such as "
            f"torch_nssm.noise.StudentT(...), got {noise!r}"
        )
    return get_noise_model(noise).SPEC.from_shortcuts(**shortcuts)


def restart_parameters(noise: str | NoiseSpec, fitted: MeasurementNoise) -> dict[str, Any]:
    """Estimator parameters that start a fit of ``fitted``'s family at its values (``Rv_init``
    aside): for a ``noise=`` name the shortcut parameters of its initial values (e.g. ``dof_init``),
    for a specification object that object with its initial values at ``fitted``'s."""
    spec = fitted.spec.starting_at(fitted)
    return spec.initial_shortcuts() if isinstance(noise, str) else {"noise": spec}
