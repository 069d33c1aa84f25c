"""Before/after identity check of a refactoring of the measurement-noise families.

Runs fits of every family through the public API and saves, per case, the fitted attributes,
``history_``, ``standard_errors_`` (and other outputs); ``--compare`` checks two such files for
*bitwise* equality.  Run it on the code before the change, then after::

    python benchmarks/noise_identity.py --out /tmp/before.pkl          # on the old code
    python benchmarks/noise_identity.py --out /tmp/after.pkl           # on the new code
    python benchmarks/noise_identity.py --compare /tmp/before.pkl /tmp/after.pkl

Cases: the paper example (Student-t, averaged iterates, growing particle count), the paper's
Table 1 setting after 10 iterations (``fit_independent``, 100 records, MCMC smoother), the
per-output Student-t and the Gaussian family (fits and standard errors), Newton-accelerated fits
(the noise parameters' squared extrapolation), a two-output joint t with missing outputs
(autograd standard errors), simulation, the parametric bootstrap, the distilled start, and the
simulated data sets.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import warnings

import numpy as np
import torch

FITTED = ("Rw_", "Rv_", "dof_", "x0_mean_", "x0_cov_", "log_likelihood_", "n_iter_", "outlier_weights_")


def _arrays(value):
    if isinstance(value, dict):
        return {k: _arrays(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_arrays(v) for v in value]
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return value


def _fit_summary(est, se: bool = True) -> dict:
    out = {name: _arrays(getattr(est, name, None)) for name in FITTED}
    out["modules"] = {
        f"{label}.{n}": p.detach().cpu().numpy()
        for label in ("f", "g")
        for n, p in getattr(est, f"{label}_").named_parameters()
    }
    out["history"] = {k: np.asarray(v) for k, v in est.history_.items()}
    if se:
        out["standard_errors"] = est.standard_errors_
        out["names"] = est.parameter_names_
        out["covariance"] = est.parameter_covariance_
        out["intervals"] = est.confidence_intervals(0.9)
    return out


def run() -> dict:
    from torch_nssm import RobustNSSMEstimator, distilled_start, fit_independent
    from torch_nssm.blocks.linear import LinearObservation, LinearTransition
    from torch_nssm.datasets import make_huang_example, make_manipulator, make_paper_example
    from torch_nssm.datasets.two_sensors import make_two_sensor_example
    from torch_nssm.reproduce.paper import _paper_estimator

    torch.set_num_threads(1)
    res: dict = {}
    warnings.simplefilter("ignore")

    # the data sets
    res["data"] = {
        "paper": make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=0).y,
        "paper_t": make_paper_example(n_samples=300, noise="student-t", dof=3.0, random_state=1).y,
        "paper_noise_free": make_paper_example(Rw=0.0, Rv=0.0, random_state=2).y,
        "huang": make_huang_example(n_samples=300, random_state=3).y,
        "manipulator": make_manipulator(n_samples=300, random_state=4).y,
        "manipulator_t": make_manipulator(n_samples=300, noise="student-t", random_state=5).y,
    }
    print("data", flush=True)

    # the paper example (Student-t), averaged iterates and a growing particle count
    data = make_paper_example(n_samples=300, outlier_fraction=0.1, random_state=0)
    est = _paper_estimator("student-t", 80, 15, 0, n_particles_final=120, average_last=4, verbose=0)
    est.fit(data.u, data.y)
    res["paper"] = _fit_summary(est)
    res["paper"]["simulate"] = est.simulate(data.u, n_samples=2, random_state=3)
    res["paper"]["smooth"] = est.smooth(data.u, data.y).mean
    res["paper"]["score"] = est.score(data.u, data.y)
    boot = est.bootstrap(data.u, n_boot=2, n_iter=2, n_particles=30, random_state=0)
    res["paper"]["bootstrap"] = boot.samples
    print("paper", flush=True)

    # the Gaussian family on the same record
    gauss = _paper_estimator("gaussian", 80, 10, 0, verbose=0).fit(data.u, data.y)
    res["gaussian"] = _fit_summary(gauss)
    print("gaussian", flush=True)

    # Newton acceleration (squared extrapolation of Rv and dof)
    acc = _paper_estimator("student-t", 80, 10, 0, verbose=0).set_params(acceleration="newton")
    res["newton"] = _fit_summary(acc.fit(data.u, data.y), se=False)
    print("newton", flush=True)

    # the paper's Table 1 after 10 iterations: 100 records batched
    datas = [make_huang_example(n_samples=1000, random_state=i) for i in range(100)]
    proto = _paper_estimator("student-t", 100, 10, 0, smoother="mcmc", verbose=0)
    fits = fit_independent(proto, [d.u for d in datas], [d.y for d in datas], show_progress=False)
    res["table1"] = [_fit_summary(f, se=(i < 2)) for i, f in enumerate(fits)]
    print("table1", flush=True)

    # per-output Student-t on the two-sensor record (and the joint t, and Newton with it)
    d2 = make_two_sensor_example(300, glitch_fraction=0.1, random_state=0)

    def two(noise, **kw):
        g = LinearObservation(2, 1, 2)
        g.C.requires_grad_(False)
        params = dict(
            x0_mean=np.zeros(2), Rv_init=np.diag([0.2, 0.2]), dof_init=10.0, noise=noise,
            n_particles=100, n_iter=10, tol=0.0, random_state=0,
        )
        params.update(kw)
        return RobustNSSMEstimator(LinearTransition(2, 1), g, **params)

    res["per_output"] = _fit_summary(two("student-t-per-output").fit(d2.u, d2.y))
    res["per_output_newton"] = _fit_summary(
        two("student-t-per-output", acceleration="newton").fit(d2.u, d2.y), se=False
    )
    res["joint_two"] = _fit_summary(two("student-t").fit(d2.u, d2.y))
    y_missing = d2.y.copy()
    rng = np.random.default_rng(0)
    y_missing[rng.random(y_missing.shape) < 0.1] = np.nan
    res["joint_missing"] = _fit_summary(two("student-t", n_iter=5).fit(d2.u, y_missing))
    res["per_output_missing"] = _fit_summary(two("student-t-per-output", n_iter=5).fit(d2.u, y_missing))
    res["gaussian_missing"] = _fit_summary(two("gaussian", n_iter=5).fit(d2.u, y_missing))
    print("two outputs", flush=True)

    # the distilled start's initial values (a linear f: the reference fit is the fit itself)
    warm = distilled_start(two("student-t"), d2.u, d2.y, n_iter=3, n_jitter=0)
    res["warm"] = {k: _arrays(v) for k, v in warm.get_params(deep=False).items() if k.endswith("init")}
    return res


def _equal(a, b, path="") -> list[str]:
    if isinstance(a, dict):
        if not isinstance(b, dict) or set(a) != set(b):
            return [f"{path}: keys {sorted(a)} != {sorted(b) if isinstance(b, dict) else b}"]
        return [m for k in a for m in _equal(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, (list, tuple)) and not isinstance(a, str):
        if not isinstance(b, (list, tuple)) or len(a) != len(b):
            return [f"{path}: lengths differ"]
        return [m for i, (x, y) in enumerate(zip(a, b)) for m in _equal(x, y, f"{path}[{i}]")]
    if hasattr(a, "mean") and hasattr(a, "cov") and not isinstance(a, np.ndarray):
        return _equal(a.mean, b.mean, path + ".mean") + _equal(a.cov, b.cov, path + ".cov")
    x, y = np.asarray(a), np.asarray(b)
    if x.shape != y.shape or x.dtype != y.dtype:
        return [f"{path}: {x.shape} {x.dtype} != {y.shape} {y.dtype}"]
    if x.dtype.kind in "fc":
        same = np.array_equal(x, y, equal_nan=True)
    else:
        same = np.array_equal(x, y)
    gap = np.nanmax(np.abs(x - y)) if x.dtype.kind in "fc" else "-"
    return [] if same else [f"{path}: differ (max |diff| {gap})"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out")
    p.add_argument("--compare", nargs=2)
    args = p.parse_args(argv)
    if args.compare:
        a, b = (pickle.load(open(f, "rb")) for f in args.compare)
        diffs = _equal(a, b)
        for d in diffs:
            print(d)
        print("identical" if not diffs else f"{len(diffs)} differences")
        return int(bool(diffs))
    res = run()
    with open(args.out, "wb") as fh:
        pickle.dump(res, fh)
    return 0


if __name__ == "__main__":
    sys.exit(main())
