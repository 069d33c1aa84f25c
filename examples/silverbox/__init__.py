"""The Silverbox case study (robust identification of a Duffing oscillator from real records).

Not part of the installed package: put ``examples`` on ``sys.path`` and ``import silverbox``.
"""

from .data import ENV_VAR, SILVERBOX_ARROW_END, SILVERBOX_FS, load_silverbox
from .study import (
    ARROW_WINDOWS,
    PUBLISHED_RMSE_MV,
    DuffingTransition,
    PositionObservation,
    SilverboxData,
    SilverboxStudy,
    arrow_rmse_mv,
    equation_error_init,
    prepare_silverbox,
    silverbox_study,
    simulate_arrow,
)

__all__ = [
    "load_silverbox",
    "SILVERBOX_FS",
    "SILVERBOX_ARROW_END",
    "ENV_VAR",
    "DuffingTransition",
    "PositionObservation",
    "SilverboxData",
    "SilverboxStudy",
    "prepare_silverbox",
    "silverbox_study",
    "equation_error_init",
    "arrow_rmse_mv",
    "simulate_arrow",
    "ARROW_WINDOWS",
    "PUBLISHED_RMSE_MV",
]
