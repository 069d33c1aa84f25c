"""Inference at fixed parameters: resampling, the particle filter, smoothers, prediction."""
