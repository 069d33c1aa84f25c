"""torch_nssm: robust identification of nonlinear state-space models in PyTorch.

``RobustNSSMEstimator(f, g, x0_mean=...).fit(u, y)`` estimates the parameters of
``x_{k+1} = f(x_k, u_k) + w`` and ``y_k = g(x_k, u_k) + v`` with Student-t measurement noise ``v``
(robust to outliers) by EM with a particle smoother (Liu & Yang, Neurocomputing 2019).
"""

from . import datasets, models, neural, plotting, warm_start
from .batch import fit_independent
from .estimator import RobustNSSMEstimator
from .filtering import NumericalError
from .parametric import LinearInParameters
from .results import StateEstimate
from .warm_start import warm_start_estimator

__all__ = [
    "RobustNSSMEstimator",
    "LinearInParameters",
    "StateEstimate",
    "NumericalError",
    "fit_independent",
    "warm_start_estimator",
    "datasets",
    "models",
    "neural",
    "plotting",
    "warm_start",
]
__version__ = "0.1.0"
