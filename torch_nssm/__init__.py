"""torch_nssm: robust identification of nonlinear state-space models in PyTorch.

``RobustNSSMEstimator(f, g, x0_mean=...).fit(u, y)`` estimates the parameters of
``x_{k+1} = f(x_k, u_k) + w`` and ``y_k = g(x_k, u_k) + v`` with Student-t measurement noise ``v``
(robust to outliers) by EM with a particle smoother (Liu & Yang, Neurocomputing 2019).

The public names are imported on first use (PEP 562), so ``import torch_nssm`` loads neither
matplotlib nor the data sets; :mod:`torch_nssm.reproduce` (the paper's experiments) is an
optional subpackage imported only by name.
"""

from __future__ import annotations

import importlib

__all__ = [
    "RobustNSSMEstimator",
    "LinearInParameters",
    "ContinuousTimeTransition",
    "StateEstimate",
    "NumericalError",
    "fit_independent",
    "WorkerLostError",
    "distilled_start",
    "simulation_start",
    "datasets",
    "diagnostics",
    "models",
    "neural",
    "noise",
    "plotting",
    "starts",
]
__version__ = "0.1.0"

#: public name -> (module, attribute); attribute None: the module itself
_LAZY = {
    "RobustNSSMEstimator": (".estimator", "RobustNSSMEstimator"),
    "LinearInParameters": (".core.parametric", "LinearInParameters"),
    "ContinuousTimeTransition": (".blocks.continuous", "ContinuousTimeTransition"),
    "StateEstimate": (".inference.results", "StateEstimate"),
    "NumericalError": (".inference.filtering", "NumericalError"),
    "fit_independent": (".estimator", "fit_independent"),
    "WorkerLostError": ("._parallel", "WorkerLostError"),
    "distilled_start": (".blocks.starts", "distilled_start"),
    "simulation_start": (".blocks.starts", "simulation_start"),
    "datasets": (".datasets", None),
    "diagnostics": (".diagnostics", None),
    "models": (".models", None),
    "neural": (".neural", None),
    "noise": (".noise", None),
    "plotting": (".plotting", None),
    "starts": (".starts", None),
}

#: old public names -> (new module, attribute), served with a DeprecationWarning for one release
_DEPRECATED = {
    "warm_start_estimator": ("torch_nssm", "distilled_start"),
    "simulation_warm_start": ("torch_nssm", "simulation_start"),
    "warm_start": ("torch_nssm.starts", None),
}


def __getattr__(name: str):
    if name in _DEPRECATED:
        from ._deprecation import resolve

        return resolve(__name__, name, _DEPRECATED)
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    mod = importlib.import_module(module, __name__)
    value = mod if attr is None else getattr(mod, attr)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
