"""Plain EM against EM with Newton-type steps (``acceleration="newton"``): iterations and wall time.

For each problem, both fits run side by side in this process (one torch thread) for ``--iters``
iterations from the same start and seed.  Printed per fit:

* the iterations until the parameters of ``f`` and ``g`` stay within 2 standard errors of the
  final estimate (the mean of the last ``--tail`` iterates of *plain* EM; standard errors from the
  plain fit's observed information, or the exact Kalman ones for the manipulator);
* the iterations until the 5-iterate running mean of the log-likelihood estimate reaches the
  final plateau (mean of both fits' last ``--tail`` iterates) less one standard deviation of it;
* the wall time of a fit stopped at those iterations (timed again), and the final estimates.

Problems: the manipulator (paper Section 4.2, 10 % outliers, N = 500, 1,000 particles, MCMC
smoother: EM is slow there), the paper's Section 4.1 example (N = 500, 200 particles) and the
Silverbox record (3,000 samples, the defaults; needs ``../shared/data``).

    python benchmarks/accelerated_em.py [--iters 80] [--problems manipulator paper silverbox]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_manipulator, make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.reproduce.manipulator_study import manipulator_estimator, manipulator_kalman_mle


def _manipulator(n_iter: int, acceleration):
    data = make_manipulator(n_samples=500, outlier_fraction=0.1, random_state=0)
    est = manipulator_estimator(
        data, n_particles=1000, smoother="mcmc", n_iter=n_iter, random_state=0, acceleration=acceleration
    )
    return est, data.u, data.y, ("f.theta1", "f.theta2"), manipulator_kalman_mle(data)["se"]


def _paper(n_iter: int, acceleration):
    d = make_paper_example(n_samples=500, random_state=0)
    est = RobustNSSMEstimator(
        PaperTransition(0.5, 0.5),
        PaperObservation(0.5),
        x0_mean=[0.0],
        n_particles=200,
        n_iter=n_iter,
        tol=0,
        random_state=0,
        smoother="mcmc",
        acceleration=acceleration,
    )
    return est, d.u, d.y, ("f.a", "f.b", "g.c"), None


def _silverbox(n_iter: int, acceleration):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from silverbox.first_stage_comparison import estimator
    from silverbox.study import prepare_silverbox

    data = prepare_silverbox(n_train=3000, outlier_fraction=0.05, random_state=0)
    est = estimator(data, n_iter=n_iter, average_last=0, acceleration=acceleration)
    return est, data.u_train, data.y_train, ("f.k1", "f.d", "f.b", "f.k3"), None


PROBLEMS = {"manipulator": _manipulator, "paper": _paper, "silverbox": _silverbox}


def _fit(make, n_iter: int, acceleration):
    est, u, y, keys, se = make(n_iter, acceleration)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
    return est, time.perf_counter() - t0, keys, se


def _iterations(hist: np.ndarray, final: np.ndarray, se: np.ndarray) -> int:
    """First iteration after which every parameter stays within 2 s.e. of ``final``."""
    outside = np.flatnonzero(np.any(np.abs(hist - final) > 2 * se, axis=1))
    return 0 if outside.size == 0 else int(outside[-1] + 1)


def run(name: str, n_iter: int, tail: int) -> list[dict]:
    make = PROBLEMS[name]
    fits = {acc: _fit(make, n_iter, acc) for acc in (None, "newton")}
    plain, _, keys, se = fits[None]
    hists = {
        acc: np.stack([np.asarray(e.history_[k], float).reshape(-1) for k in keys], 1)
        for acc, (e, *_) in fits.items()
    }
    final = hists[None][-tail:].mean(0)
    if se is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            se = np.array([float(np.asarray(plain.standard_errors_[k]).reshape(-1)[0]) for k in keys])
    se = np.asarray(se, float)
    lls = {acc: np.asarray(e.history_["log_likelihood"], float) for acc, (e, *_) in fits.items()}
    both = np.concatenate([v[-tail:] for v in lls.values()])
    plateau, spread = both.mean(), both.std()
    rows = []
    for acc, (est, secs, _, _) in fits.items():
        running = np.convolve(lls[acc], np.ones(5) / 5, mode="valid")
        k_ll = int(np.argmax(running >= plateau - spread)) if np.any(running >= plateau - spread) else n_iter
        k_theta = _iterations(hists[acc], final, se)
        timed = {}
        for label, k in (("theta", k_theta), ("ll", k_ll)):
            timed[label] = _fit(make, k, acc)[1] if k > 0 else 0.0
        accelerated = est.history_.get("accelerated")
        rows.append(
            dict(
                problem=name,
                fit="EM" if acc is None else "EM + Newton",
                iters=n_iter,
                seconds=secs,
                k_theta=k_theta,
                k_ll=k_ll,
                t_theta=timed["theta"],
                t_ll=timed["ll"],
                n_newton=0 if accelerated is None else int(np.sum(accelerated)),
                final=hists[acc][-tail:].mean(0),
                ll=lls[acc][-tail:].mean(),
                plateau=plateau,
                spread=spread,
            )
        )
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=80)
    p.add_argument("--tail", type=int, default=20)
    p.add_argument("--problems", nargs="*", default=list(PROBLEMS))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    print(
        "| problem | fit | Newton steps | iterations to θ within 2 s.e. of final | s | iterations to "
        "log-lik plateau | s | final θ (mean of last iterates) | final log-lik | s for all iterations |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in a.problems:
        for r in run(name, a.iters, a.tail):
            theta = ", ".join(f"{v:.4f}" for v in r["final"])
            print(
                f"| {r['problem']} | {r['fit']} | {r['n_newton']} | {r['k_theta']} | {r['t_theta']:.1f} | "
                f"{r['k_ll']} | {r['t_ll']:.1f} | {theta} | {r['ll']:.1f} (plateau {r['plateau']:.1f} "
                f"± {r['spread']:.1f}) | {r['seconds']:.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
