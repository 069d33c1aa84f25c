"""Diagnostics of a fit: the residual analysis of its prediction errors (:mod:`.residuals`,
MATLAB's ``resid``) and the warnings a fit or a study raises (:mod:`.fit_warnings`, written from
the report of its EM runs)."""

from __future__ import annotations

from .residuals import OUTLIER_WEIGHT_THRESHOLD, ResidualAnalysis, correlations, residual_analysis

__all__ = ["ResidualAnalysis", "correlations", "residual_analysis", "OUTLIER_WEIGHT_THRESHOLD"]
