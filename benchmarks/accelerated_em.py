"""Plain EM against accelerated EM (``acceleration="newton"``): iterations and wall time.

For each problem, both fits run side by side in this process (one torch thread) for
``--iters`` iterations from the same start and seed.  Printed per fit:

* the iterations until the parameters of ``f`` and ``g`` stay within 2 standard errors of the
  final estimate (the mean of the last ``--tail`` iterates of *plain* EM; standard errors from the
  plain fit's observed information, or the exact Kalman ones for the manipulator);
* the same for every parameter, the noise's included (``Rw``'s diagonal, ``Rv``'s, the degrees of
  freedom; their standard errors from the plain fit's ``standard_errors_``);
* the iterations until the 5-iterate running mean of the log-likelihood estimate reaches the
  final plateau (mean of both fits' last ``--tail`` iterates) less one standard deviation of it;
* the wall time from the first iterate (after the first E-step, which both fits share, and the
  process's warm-ups) to those iterates (each iterate's time is recorded as the fit runs), and
  the final estimates.

Problems: the manipulator (paper Section 4.2, 10 % outliers, N = 500, 1,000 particles, MCMC
smoother: EM is slow there), the paper's Section 4.1 example (N = 500, 200 particles) and the
Silverbox record (3,000 samples, the defaults; needs ``../shared/data``).

    python benchmarks/accelerated_em.py [--iters 80] [--problems manipulator paper silverbox]
    python benchmarks/accelerated_em.py --problems manipulator --seeds 0 1 2 3 4 5

``--seeds``: the manipulator's data seeds (one table row per seed and fit).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import torch_nssm.estimation.loop as em_loop
from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_manipulator, make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.reproduce.manipulator_study import manipulator_estimator, manipulator_kalman_mle


def _manipulator(n_iter: int, acceleration, seed: int = 0):
    data = make_manipulator(n_samples=500, outlier_fraction=0.1, random_state=seed)
    est = manipulator_estimator(
        data, n_particles=1000, smoother="mcmc", n_iter=n_iter, random_state=0, acceleration=acceleration
    )
    return est, data.u, data.y, ("f.theta1", "f.theta2"), manipulator_kalman_mle(data)["se"]


def _paper(n_iter: int, acceleration, seed: int = 0):
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


def _silverbox(n_iter: int, acceleration, seed: int = 0):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from silverbox.first_stage_comparison import estimator
    from silverbox.study import prepare_silverbox

    data = prepare_silverbox(n_train=3000, outlier_fraction=0.05, random_state=0)
    est = estimator(data, n_iter=n_iter, average_last=0, acceleration=acceleration)
    return est, data.u_train, data.y_train, ("f.k1", "f.d", "f.b", "f.k3"), None


PROBLEMS = {"manipulator": _manipulator, "paper": _paper, "silverbox": _silverbox}


FITS = (None, "newton")
NOISE_KEYS = ("Rw", "Rv", "dof")


def _fit(make, n_iter: int, acceleration, seed: int = 0):
    est, u, y, keys, se = make(n_iter, acceleration, seed)
    record, times = em_loop.record, []

    def timed_record(history, model, log_likelihood):  # the time each iterate is reached
        times.append(time.perf_counter())
        record(history, model, log_likelihood)

    em_loop.record = timed_record
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(u, y)
    finally:
        em_loop.record = record
    seconds = time.perf_counter() - t0
    est.iterate_seconds_ = np.asarray(times[-len(est.history_["log_likelihood"]) :]) - t0
    return est, seconds, keys, se


def _iterations(hist: np.ndarray, final: np.ndarray, se: np.ndarray) -> int:
    """First iteration after which every parameter stays within 2 s.e. of ``final``."""
    outside = np.flatnonzero(np.any(np.abs(hist - final) > 2 * se, axis=1))
    return 0 if outside.size == 0 else int(outside[-1] + 1)


def _noise(est, keys, se: dict | None = None) -> np.ndarray:
    """The noise parameters ``keys`` of every iterate (``Rw``'s and ``Rv``'s diagonals, the dof),
    or of the standard errors ``se``, as columns."""
    cols = []
    for key in keys:
        values = [np.asarray(se[key], float)] if se is not None else est.history_[key]
        cols.append(
            np.stack([np.diagonal(v) if v.ndim == 2 else np.ravel(v) for v in map(np.asarray, values)])
        )
    return np.concatenate(cols, axis=1)


def run(name: str, n_iter: int, tail: int, seed: int = 0) -> list[dict]:
    make = PROBLEMS[name]
    fits = {acc: _fit(make, n_iter, acc, seed) for acc in FITS}
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
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        errors = plain.standard_errors_
    # the estimated noise parameters (a held Rw has no standard error)
    noise_keys = [k for k in NOISE_KEYS if k in errors and all(k in e.history_ for e, *_ in fits.values())]
    se_all = np.concatenate([se, _noise(plain, noise_keys, errors)[0]])
    noise = {acc: _noise(e, noise_keys) for acc, (e, *_) in fits.items()}
    everything = {acc: np.concatenate([hists[acc], noise[acc]], 1) for acc in fits}
    final_all = everything[None][-tail:].mean(0)
    lls = {acc: np.asarray(e.history_["log_likelihood"], float) for acc, (e, *_) in fits.items()}
    both = np.concatenate([v[-tail:] for v in lls.values()])
    plateau, spread = both.mean(), both.std()
    rows = []
    for acc, (est, secs, _, _) in fits.items():
        running = np.convolve(lls[acc], np.ones(5) / 5, mode="valid")
        k_ll = int(np.argmax(running >= plateau - spread)) if np.any(running >= plateau - spread) else n_iter
        k_theta = _iterations(hists[acc], final, se)
        k_all = _iterations(everything[acc], final_all, se_all)
        t = est.iterate_seconds_ - est.iterate_seconds_[0]  # from the first E-step's end (warm-ups)
        timed = {
            label: float(t[min(k, len(t) - 1)])
            for label, k in (("theta", k_theta), ("ll", k_ll), ("all", k_all))
        }
        accelerated = est.history_.get("accelerated")
        rows.append(
            dict(
                problem=name if name != "manipulator" else f"manipulator (seed {seed})",
                fit={None: "EM", "newton": "EM + Newton"}[acc],
                iters=n_iter,
                seconds=secs,
                k_theta=k_theta,
                k_ll=k_ll,
                k_all=k_all,
                t_all=timed["all"],
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
    p.add_argument("--seeds", type=int, nargs="*", default=[0], help="the manipulator's data seeds")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    print(
        "| problem | fit | accelerated iterates | iterations to θ within 2 s.e. of final | s | iterations "
        "to all parameters within 2 s.e. | s | iterations to log-lik plateau | s | final θ (mean of last "
        "iterates) | final log-lik | s for all iterations |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in a.problems:
        for seed in a.seeds if name == "manipulator" else [0]:
            for r in run(name, a.iters, a.tail, seed):
                theta = ", ".join(f"{v:.4f}" for v in r["final"])
                print(
                    f"| {r['problem']} | {r['fit']} | {r['n_newton']} | {r['k_theta']} | "
                    f"{r['t_theta']:.1f} | {r['k_all']} | {r['t_all']:.1f} | "
                    f"{r['k_ll']} | {r['t_ll']:.1f} | {theta} | {r['ll']:.1f} (plateau {r['plateau']:.1f} "
                    f"± {r['spread']:.1f}) | {r['seconds']:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
