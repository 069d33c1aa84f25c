"""The library's LinearTransition against a hand-written linear module, side by side.

A 2-state, 2-output linear system (N = 500), 300 particles, MCMC smoother, 5 EM iterations; each
fit timed 3 times, alternating, fastest kept.  ``python benchmarks/linear_blocks.py``
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import torch
from torch import nn

from torch_nssm import RobustNSSMEstimator
from torch_nssm.starts import LinearObservation, LinearTransition


class HandWritten(nn.Module):
    """``x A^T + u B^T`` (no closed form: LBFGS M-step)."""

    def __init__(self):
        super().__init__()
        self.A = nn.Parameter(torch.tensor(0.5 * np.eye(2)))
        self.B = nn.Parameter(torch.full((2, 1), 0.5, dtype=torch.float64))

    def forward(self, x, u):
        return x @ self.A.T + u @ self.B.T


def record(n: int = 500, seed: int = 0):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 1))
    A, B = np.array([[0.8, 0.2], [-0.1, 0.7]]), np.array([[1.0], [0.5]])
    x = np.zeros((n, 2))
    for k in range(n - 1):
        x[k + 1] = A @ x[k] + B @ u[k] + 0.3 * rng.standard_normal(2)
    return u, x @ np.array([[1.0, 0.0], [0.5, 1.0]]).T + 0.2 * rng.standard_normal((n, 2))


def fit_seconds(f: nn.Module, u, y) -> float:
    est = RobustNSSMEstimator(
        f, LinearObservation(2, 1, 2), x0_mean=[0.0, 0.0], n_particles=300, n_iter=5, tol=0, random_state=0,
        smoother="mcmc",
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
    return time.perf_counter() - t0


def main() -> None:
    u, y = record()
    times: dict[str, list[float]] = {"LinearTransition": [], "hand-written": []}
    for _ in range(3):
        times["LinearTransition"].append(fit_seconds(LinearTransition(2, 1), u, y))
        times["hand-written"].append(fit_seconds(HandWritten(), u, y))
    base = min(times["hand-written"])
    print("| f | seconds | ratio to hand-written |\n|---|---|---|")
    for name, v in times.items():
        print(f"| {name} | {min(v):.3f} | {min(v) / base:.2f} |")


if __name__ == "__main__":
    main()
