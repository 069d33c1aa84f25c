"""Thread policy: a fit with ``n_threads=1`` (the default) against torch's own thread pool.

``python benchmarks/threads.py [--N 500] [--L 150] [--iters 10]`` fits the paper's example twice
per setting, alternating, and prints the fastest wall time of each and their ratio.  The machine
this ran on is noted in the README (a shared 2-core CPU).
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.models import PaperObservation, PaperTransition


def _fit(data, n_threads, n_particles: int, n_iter: int) -> float:
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0], n_particles=n_particles,
        n_iter=n_iter, tol=0, random_state=0, n_threads=n_threads,
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(data.u, data.y)
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--N", type=int, default=500)
    p.add_argument("--L", type=int, default=150)
    p.add_argument("--iters", type=int, default=10)
    p.add_argument("--repeat", type=int, default=2)
    args = p.parse_args()
    data = make_paper_example(n_samples=args.N, outlier_fraction=0.1, random_state=0)
    default_pool = torch.get_num_threads()
    times: dict[str, list[float]] = {"n_threads=1": [], f"n_threads=None ({default_pool} torch threads)": []}
    for _ in range(args.repeat):
        for key, n in zip(times, (1, None)):
            times[key].append(_fit(data, n, args.L, args.iters))
    best = {k: min(v) for k, v in times.items()}
    base = best["n_threads=1"]
    print(f"fit of the paper's example, N={args.N}, L={args.L}, {args.iters} iterations;", end=" ")
    print(f"fastest of {args.repeat}")
    print("| setting | seconds | ratio to n_threads=1 |\n|---|---|---|")
    for k, v in best.items():
        print(f"| {k} | {v:.2f} | {v / base:.2f} |")


if __name__ == "__main__":
    main()
