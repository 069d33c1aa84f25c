"""Cost of the standard errors against one E-step, for several particle counts.

For the paper's Section 4.1 model (``N = 500``, 3 + 3 parameters) and a 2-state linear-Gaussian
model (``N = 300``, 12 parameters), at fitted parameters: the median over ``repeats`` of the time
of :func:`~torch_nssm.estimation.uncertainty.observed_information` (500 trajectories) and of one
E-step (filter + FFBSm) at the same particle count, measured alternately on one thread (the
ratio is what to read on a busy machine).  The first call of ``torch.func`` in a process costs
about 1.5 s of imports more, not counted.

``--manipulator`` times instead the information of accelerated EM
(:func:`~torch_nssm.estimation.acceleration.information_at`: module parameters only, 300
trajectories) on the manipulator (paper Section 4.2, ``N = 500``, 10 % outliers, 1,000 particles,
MCMC E-step), whose tiny process noise (``2e-5`` on two states) makes the backward sampler's
rejection tries rarely accept.

``--baseline REV`` also times the implementation of a git revision (its
``estimation/uncertainty.py`` and its backward sampler, ``inference/ffbsi.py`` (``inference/smoothing.py``
in revisions before the smoothers' split), loaded from ``git show`` into a
temporary package beside this checkout's) in the same loop, for an old-against-new comparison on
the same machine load:

    python benchmarks/uncertainty_cost.py
    python benchmarks/uncertainty_cost.py --baseline 3a089ef
    python benchmarks/uncertainty_cost.py --manipulator --particles 1000 --repeats 3

``--cpu-time`` times by the process's CPU time instead of the wall clock: on a machine busy with
other jobs the wall clock also counts the time the process waits for a core.  ``--trajectories M``
sets the trajectories of both informations (the current and a ``--baseline``).
"""

from __future__ import annotations

import argparse
import importlib
import re
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torch_nssm import RobustNSSMEstimator
from torch_nssm.blocks.linear import LinearObservation, LinearTransition
from torch_nssm.datasets import make_manipulator, make_paper_example
from torch_nssm.datasets.paper import PaperObservation, PaperTransition
from torch_nssm.estimation.acceleration import TRAJECTORIES
from torch_nssm.estimation.estep import e_step
from torch_nssm.estimation.uncertainty import observed_information
from torch_nssm.reproduce.manipulator_study import manipulator_estimator


def _paper(L: int) -> RobustNSSMEstimator:
    d = make_paper_example(n_samples=500, random_state=0)
    est = RobustNSSMEstimator(
        PaperTransition(0.9, 1.0),
        PaperObservation(1.0),
        x0_mean=[0.0],
        Rw_init=0.1,
        Rv_init=0.1,
        n_particles=L,
        n_iter=3,
        tol=0,
        random_state=0,
    )
    return est.fit(d.u, d.y)


def _linear(L: int) -> RobustNSSMEstimator:
    rng = np.random.default_rng(0)
    A, B = np.array([[0.8, 0.2], [-0.3, 0.6]]), np.array([[1.0], [0.5]])
    x = np.zeros((300, 2))
    u = rng.standard_normal((300, 1))
    for k in range(299):
        x[k + 1] = A @ x[k] + B @ u[k] + 0.3 * rng.standard_normal(2)
    y = x + 0.25 * rng.standard_normal((300, 2))
    g = LinearObservation(2, 1, 2, fit_offset=False)
    g.C.requires_grad_(False)
    est = RobustNSSMEstimator(
        LinearTransition(2, 1, A=A, B=B),
        g,
        x0_mean=np.zeros(2),
        noise="gaussian",
        n_particles=L,
        n_iter=3,
        tol=0,
        random_state=0,
    )
    return est.fit(u, y)


def _manipulator(L: int) -> RobustNSSMEstimator:
    data = make_manipulator(n_samples=500, outlier_fraction=0.1, random_state=0)
    est = manipulator_estimator(data, n_particles=L, smoother="mcmc", n_iter=3, random_state=0)
    return est.fit(data.u, data.y)


def _baseline(rev: str):
    """``observed_information`` of git revision ``rev``: its uncertainty and smoothing modules,
    their relative imports made absolute (the rest of the package is this checkout's)."""
    root = Path(__file__).resolve().parents[1]
    tmp = Path(tempfile.mkdtemp(prefix="uncertainty_baseline_"))
    sampler = "torch_nssm/inference/ffbsi.py"
    if subprocess.run(["git", "cat-file", "-e", f"{rev}:{sampler}"], cwd=root).returncode:
        sampler = "torch_nssm/inference/smoothing.py"  # before FFBSm and FFBSi had a module each
    sources = {
        "baseline_smoothing": sampler,
        "baseline_uncertainty": "torch_nssm/estimation/uncertainty.py",
    }
    for name, path in sources.items():
        text = subprocess.run(
            ["git", "show", f"{rev}:{path}"], cwd=root, check=True, capture_output=True, text=True
        ).stdout
        package = "torch_nssm.inference" if "inference" in path else "torch_nssm.estimation"
        text = re.sub(r"from \.\.inference\.(smoothing|ffbsi) import", "from baseline_smoothing import", text)
        text = re.sub(r"from \.\.(\w)", r"from torch_nssm.\1", text)
        text = re.sub(r"from \.\. import", "from torch_nssm import", text)
        text = re.sub(r"from \. import", f"from {package} import", text)
        text = re.sub(r"from \.(\w)", rf"from {package}.\1", text)
        (tmp / f"{name}.py").write_text(text)
    sys.path.insert(0, str(tmp))
    return importlib.import_module("baseline_uncertainty").observed_information


def measure(
    build, L: int, repeats: int = 5, baseline=None, clock=time.perf_counter, **info_options
) -> tuple[float, float, float | None]:
    """Median seconds of the information, of one E-step and of the baseline's information
    (``info_options`` for both informations), by ``clock``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = build(L)
    model, data = est._uncertainty_source
    options = est._em_options().estep
    estep = e_step(model, data, options, torch.Generator().manual_seed(0))  # the fit's kind of E-step
    observed_information(model, data, estep, **info_options)  # imports, caches
    if baseline is not None:
        baseline(model, data, estep, **info_options)
    info, step, old = [], [], []
    for r in range(repeats):
        if baseline is not None:
            t = clock()
            baseline(model, data, estep, generator=torch.Generator().manual_seed(r), **info_options)
            old.append(clock() - t)
        t = clock()
        observed_information(model, data, estep, generator=torch.Generator().manual_seed(r), **info_options)
        info.append(clock() - t)
        t = clock()
        e_step(model, data, options, torch.Generator().manual_seed(r))
        step.append(clock() - t)
    return float(np.median(info)), float(np.median(step)), float(np.median(old)) if old else None


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--particles", type=int, nargs="+", default=[200, 500, 1000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--baseline", help="a git revision whose information to time alongside")
    parser.add_argument(
        "--manipulator", action="store_true", help="the manipulator with accelerated EM's information"
    )
    parser.add_argument(
        "--cpu-time",
        action="store_true",
        help="time by the process's CPU time instead of the wall clock (one thread: steadier on a "
        "machine shared with other jobs, which then slow it only through the caches)",
    )
    parser.add_argument("--trajectories", type=int, help="the informations' trajectories (default: theirs)")
    args = parser.parse_args()
    clock = time.process_time if args.cpu_time else time.perf_counter
    torch.set_num_threads(1)
    baseline = _baseline(args.baseline) if args.baseline else None
    head = f"{'model':16s} {'L':>5s} {'information':>12s} {'E-step':>8s} {'ratio':>6s}"
    print(head + (f" {'baseline':>10s} {'ratio':>6s}" if baseline else ""))
    problems = (("paper 4.1", _paper), ("linear 2-state", _linear))
    options = {}
    if args.manipulator:
        problems = (("manipulator", _manipulator),)
        options = dict(fit_Rw=False, fit_Rv=False, fit_shape=False, n_trajectories=TRAJECTORIES)
    if args.trajectories:
        options["n_trajectories"] = args.trajectories
    for name, build in problems:
        for L in args.particles:
            info, step, old = measure(build, L, args.repeats, baseline, clock, **options)
            line = f"{name:16s} {L:5d} {info:10.3f} s {step:6.3f} s {info / step:6.2f}"
            if old is not None:
                line += f" {old:8.3f} s {old / step:6.2f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
