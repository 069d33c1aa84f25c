"""The suite of plants and its baselines (``benchmarks/real_records.py`` runs them).

Put ``benchmarks`` on the path (``sys.path.insert(0, "benchmarks")``) and import ``suite``:
:mod:`suite.plants` (the plants: records, user models, starts), :mod:`suite.baselines` (OE least
squares, the true model's free run, our default fit, the scores).
"""

from .baselines import default_fit, estimator_summary, fit_percent, oe_fit, rmse, simulate
from .plants import PLANT_NAMES, PLANTS, Plant

__all__ = [
    "PLANTS",
    "PLANT_NAMES",
    "Plant",
    "default_fit",
    "estimator_summary",
    "fit_percent",
    "oe_fit",
    "rmse",
    "simulate",
]
