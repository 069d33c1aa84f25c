"""Coverage of the 95 % confidence intervals on the paper's Section 4.1 model with outliers.

``n_sets`` data sets of ``x_{k+1} = a x_k + b u_k + w``, ``y_k = c cos(x_k) + v`` (``a = 0.9``,
``b = c = 1``, ``Rw = Rv = 0.1``, ``N = 500``, 10 % additive outliers in ``[-5, 5]``; seeds
``seed .. seed + n_sets - 1``) are fitted with Student-t noise in one :func:`fit_independent` call,
started at the true values (the study is about the intervals, not about the basins of attraction:
docs/method.md §7).  Each fit's observed-information intervals (docs/uncertainty.md) are checked
against the true ``a``, ``b``, ``c``; the script prints the coverage of each parameter with its
binomial standard error, the mean standard error against the Monte Carlo s.d. of the estimates,
and the cost of the information against one E-step.

    python benchmarks/coverage_study.py                      # 100 data sets
    python benchmarks/coverage_study.py --sets 20 --iters 20 # a quick look
    python benchmarks/coverage_study.py --trajectories 200 --compare 500

``--trajectories M`` sets the number of backward-simulated trajectories of the information (default:
the library's rule for the particle count); ``--compare M2`` also computes, on the same fits and
their same final E-steps, the information with ``M2`` trajectories, and prints its coverage and the
mean relative difference of the standard errors.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import torch

from torch_nssm import RobustNSSMEstimator, fit_independent
from torch_nssm.datasets import make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.estimation.estep import e_step
from torch_nssm.estimation.uncertainty import observed_information

TRUE = {"f.a": 0.9, "f.b": 1.0, "g.c": 1.0}


def run(
    n_sets: int = 100,
    n_iter: int = 40,
    n_particles: int = 200,
    seed: int = 0,
    level: float = 0.95,
    n_trajectories: int | None = None,
    compare: int | None = None,
) -> dict:
    """Fit the study; returns the coverage, standard errors and timings (with ``compare``, also
    those of the information with ``compare`` trajectories on the same fits and E-steps)."""
    torch.set_num_threads(1)
    datas = [make_paper_example(n_samples=500, random_state=seed + i) for i in range(n_sets)]
    proto = RobustNSSMEstimator(
        PaperTransition(0.9, 1.0),
        PaperObservation(1.0),
        x0_mean=[0.0],
        x0_cov=[[1.0]],
        Rw_init=0.1,
        Rv_init=0.1,
        n_particles=n_particles,
        n_iter=n_iter,
        tol=0,
        average_last=10,
        random_state=seed,
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = fit_independent(proto, [d.u for d in datas], [d.y for d in datas], show_progress=False)
    fit_seconds = time.perf_counter() - t0
    estimates, errors, covered, info_seconds = [], [], [], []
    errors2, covered2 = [], []
    for est in fits:
        t = time.perf_counter()
        if n_trajectories is None and compare is None:  # the estimator's own path
            se = est.standard_errors_
            ci = est.confidence_intervals(level)
        else:  # as the estimator does, with the trajectories set
            unc = _information(est, n_trajectories)
            se, ci = unc.standard_errors, unc.confidence_intervals(level)
        info_seconds.append(time.perf_counter() - t)
        estimates.append([_value(est, k) for k in TRUE])
        errors.append([float(se[k]) for k in TRUE])
        covered.append([bool(ci[k][0] <= v <= ci[k][1]) for k, v in TRUE.items()])
        if compare is not None:
            unc = _information(est, compare)
            se, ci = unc.standard_errors, unc.confidence_intervals(level)
            errors2.append([float(se[k]) for k in TRUE])
            covered2.append([bool(ci[k][0] <= v <= ci[k][1]) for k, v in TRUE.items()])
    # one E-step of one data set at its fitted parameters, for the cost ratio
    est = fits[-1]
    device = torch.device("cpu")
    model = est._fitted_model(device)
    data = est._batch(datas[-1].u, datas[-1].y, device, fitted=True)[0]
    options = est._em_options().estep
    options.n_particles = est._em_options().n_particles(None)
    e_step(model, data, options, torch.Generator().manual_seed(0))  # warm
    t = time.perf_counter()
    for _ in range(3):
        e_step(model, data, options, torch.Generator().manual_seed(0))
    estep_seconds = (time.perf_counter() - t) / 3
    estimates, errors, covered = np.array(estimates), np.array(errors), np.array(covered)
    extra = {}
    if compare is not None:
        errors2, covered2 = np.array(errors2), np.array(covered2)
        extra = dict(
            compare=compare,
            compare_coverage=covered2.mean(0),
            compare_mean_se=errors2.mean(0),
            relative_difference=np.abs(errors / errors2 - 1.0).mean(0),
            relative_bias=(errors / errors2 - 1.0).mean(0),
        )
    return dict(
        **extra,
        n_sets=n_sets,
        n_iter=n_iter,
        n_particles=n_particles,
        coverage=covered.mean(0),
        coverage_se=np.sqrt(covered.mean(0) * (1 - covered.mean(0)) / n_sets),
        mean_se=errors.mean(0),
        mc_sd=estimates.std(0, ddof=1),
        mean=estimates.mean(0),
        fit_seconds=fit_seconds,
        info_seconds=np.median(info_seconds[1:]) if n_sets > 1 else info_seconds[0],
        first_info_seconds=info_seconds[0],
        estep_seconds=estep_seconds,
    )


def _information(est: RobustNSSMEstimator, n_trajectories: int | None):
    """The estimator's observed information (its final E-step, its generators) with
    ``n_trajectories`` (``None``: the default rule)."""
    model, data = est._uncertainty_source
    device = data.y.device
    estep = est._e_step(model, data, est._generator(device))
    options = {} if n_trajectories is None else dict(n_trajectories=n_trajectories)
    return observed_information(
        model, data, estep, fit_Rw=est.fit_Rw_, fit_Rv=bool(est.fit_Rv),
        generator=est._generator(device), **options,
    )


def _value(est: RobustNSSMEstimator, key: str) -> float:
    module, name = key.split(".")
    return float(getattr(getattr(est, f"{module}_"), name).detach())


def main() -> None:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--sets", type=int, default=100)
    parser.add_argument("--iters", type=int, default=40)
    parser.add_argument("--particles", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trajectories", type=int, help="the information's trajectories (default: the rule)")
    parser.add_argument("--compare", type=int, help="also the information with this many trajectories")
    args = parser.parse_args()
    r = run(
        args.sets, args.iters, args.particles, args.seed,
        n_trajectories=args.trajectories, compare=args.compare,
    )
    print(
        f"{r['n_sets']} data sets, N = 500, 10 % outliers, {r['n_iter']} EM iterations (last 10 averaged), "
        f"{r['n_particles']} particles (FFBSm); fit {r['fit_seconds']:.0f} s"
    )
    print(f"{'':4s} {'coverage':>14s} {'mean':>8s} {'mean s.e.':>10s} {'MC s.d.':>8s}")
    for i, k in enumerate(TRUE):
        print(
            f"{k:4s} {100 * r['coverage'][i]:7.1f} ± {100 * r['coverage_se'][i]:3.1f} % "
            f"{r['mean'][i]:8.4f} {r['mean_se'][i]:10.4f} {r['mc_sd'][i]:8.4f}"
        )
    if "compare" in r:
        print(f"with {r['compare']} trajectories on the same fits:")
        for i, k in enumerate(TRUE):
            print(
                f"{k:4s} coverage {100 * r['compare_coverage'][i]:5.1f} %, "
                f"mean s.e. {r['compare_mean_se'][i]:.4f}; "
                f"s.e. differ by {100 * r['relative_difference'][i]:.1f} % on average "
                f"(mean ratio - 1: {100 * r['relative_bias'][i]:+.1f} %)"
            )
    print(
        f"information {r['info_seconds']:.3f} s per data set (first call {r['first_info_seconds']:.2f} s, "
        f"imports included); one E-step {r['estep_seconds']:.3f} s; ratio "
        f"{r['info_seconds'] / r['estep_seconds']:.2f}"
    )


if __name__ == "__main__":
    main()
