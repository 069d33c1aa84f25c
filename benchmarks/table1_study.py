"""The paper's Table 1 study as one batched call, timed, for each smoother: speed and accuracy.

100 data sets (Cauchy measurement noise ``St(0, 0.01, 1)``, N = 1000, seeds ``seed..seed+99``),
each fitted from a = b = c = 0.5 with 100 particles by :func:`torch_nssm.fit_independent` (one
tensor pass for all data sets, each with its own parameters).  Prints, per smoother, the wall time,
the seconds per iteration, the projection to the paper's 250 iterations, and the estimates: mean
and s.d. over the data sets of the average of each fit's last 10 iterates, and the bias norm
``||theta - mean(theta_hat)||``.

    python benchmarks/table1_study.py                          # mcmc and ffbsm, 50 iterations
    python benchmarks/table1_study.py --iters 250 --smoothers mcmc

Besides the wall time it prints the process's CPU time per iteration, which is what to compare on
a busy machine (other jobs' load inflates the wall time; the CPU time only through shared caches),
and the minor page faults per iteration (first touches of fresh memory: the load does not move
them; docs/design.md, "Cost per particle-step").
"""

from __future__ import annotations

import argparse
import os
import resource
import time
import warnings

import numpy as np
import torch

from torch_nssm import fit_independent
from torch_nssm.datasets import make_huang_example
from torch_nssm.reproduce import _paper_estimator

THETA = np.array([0.9, 1.0, 1.0])


def run(
    smoother: str = "mcmc", n_iter: int = 50, n_sets: int = 100, seed: int = 0, n_avg: int = 10, device="cpu"
) -> dict:
    """Fit the study once; returns timings, estimates and bias norms."""
    torch.set_num_threads(1)
    datas = [make_huang_example(n_samples=1000, random_state=seed + i) for i in range(n_sets)]
    proto = _paper_estimator("student-t", 100, n_iter, seed, smoother=smoother, verbose=0)
    proto.set_params(device=device)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = fit_independent(proto, [d.u for d in datas], [d.y for d in datas], show_progress=False)
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    hist = np.stack(
        [
            np.stack([np.asarray(e.history_[k], dtype=float).reshape(-1) for k in ("f.a", "f.b", "g.c")], 1)
            for e in fits
        ]
    )  # (sets, iterations + 1, 3)
    est = hist[:, -n_avg:].mean(1)
    return dict(
        smoother=smoother if device == "cpu" else f"{smoother} ({device})",
        n_iter=n_iter,
        n_sets=n_sets,
        seconds=secs,
        per_iteration=secs / (n_iter + 1),  # n_iter M-steps, n_iter + 1 E-steps
        cpu_per_iteration=cpu / (n_iter + 1),  # the process's CPU time: robust to a busy machine
        faults_per_iteration=faults / (n_iter + 1),  # minor page faults: independent of the load
        mean=est.mean(0),
        std=est.std(0, ddof=1),
        bias_norm=float(np.linalg.norm(THETA - est.mean(0))),
        bias_norm_last=float(np.linalg.norm(THETA - hist[:, -1].mean(0))),
    )


def print_table(results: list[dict]) -> None:
    print(
        f"\nTable 1 study: {results[0]['n_sets']} data sets x N = 1000, 100 particles, one batched fit, "
        f"1 torch thread, THP_MEM_ALLOC_ENABLE={os.environ.get('THP_MEM_ALLOC_ENABLE', '0')}"
    )
    print(
        "| smoother | iterations | seconds | s / iteration | CPU s / iteration | page faults / iteration "
        "| 250 iterations (CPU) | a | b | c | bias norm (avg last 10) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        cols = " | ".join(f"{m:.4f} ± {s:.4f}" for m, s in zip(r["mean"], r["std"]))
        print(
            f"| {r['smoother']} | {r['n_iter']} | {r['seconds']:.0f} | {r['per_iteration']:.2f} | "
            f"{r['cpu_per_iteration']:.2f} | {r['faults_per_iteration']:.0f} | "
            f"{250 * r['per_iteration'] / 60:.1f} min "
            f"({250 * r['cpu_per_iteration'] / 60:.1f} min) | {cols} | {r['bias_norm']:.4f} |"
        )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=50)
    p.add_argument("--smoothers", nargs="+", default=["mcmc", "ffbsm"])
    p.add_argument("--sets", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="torch device of the fits, e.g. cuda")
    a = p.parse_args(argv)
    print_table([run(s, a.iters, a.sets, a.seed, device=a.device) for s in a.smoothers])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
