"""Estimation: the E-step, the M-step and its solvers, the EM loop, independent fits."""
