"""Command line: ``python -m torch_nssm`` fits the paper's Section 4.1 example and prints the result.

``python -m torch_nssm [demo] [--n-samples N] [--particles L] [--iterations K] [--seed S] [--gaussian]``
(the options may also come before ``demo``)

``python -m torch_nssm reproduce {fig2,gopaluni,table1,manipulator,all} [--fast] [--out DIR] [--seed S]``
regenerates the figures and tables of the paper's Section 4 (see :mod:`torch_nssm.reproduce`).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

__all__ = ["main", "run_demo", "run_reproduce", "build_parser", "parse_args"]


def _demo_parser(sub) -> None:
    p = sub.add_parser("demo", help="fit the paper's Section 4.1 example (default command)")
    _demo_args(p)


def _reproduce_parser(sub) -> None:
    p = sub.add_parser("reproduce", help="regenerate the paper's Section 4 figures and tables")
    p.add_argument(
        "experiment",
        choices=["fig2", "gopaluni", "table1", "manipulator", "all"],
        help="which experiment (all: every one in turn)",
    )
    p.add_argument("--fast", action="store_true", help="tiny settings (seconds), e.g. for CI")
    p.add_argument("--out", default="reproduction", help="output folder (default: ./reproduction)")
    _seed_arg(p)


def run_reproduce(experiment: str, fast: bool = False, out: str = "reproduction", seed: int = 0) -> dict:
    """Run one experiment of :mod:`torch_nssm.reproduce` (or ``"all"``) and print its tables.

    Returns
    -------
    dict
        ``{name: results}`` of the experiments run.
    """
    from . import reproduce

    names = list(reproduce.EXPERIMENTS) if experiment == "all" else [experiment]
    results = {}
    for name in names:
        res = reproduce.EXPERIMENTS[name](fast=fast, out_dir=out, seed=seed)
        print(f"\n== {name} ({res['seconds']:.0f} s) ==\n{res['table']}")
        print("files: " + ", ".join(res["files"]))
        results[name] = res
    return results


#: Defaults of the demo's options.  The options are accepted before and after the subcommand
#: (``--iterations 2 demo`` and ``demo --iterations 2``), so the parsers themselves give no
#: defaults (``argparse.SUPPRESS``: a subcommand's default would overwrite a value given before
#: it) and :func:`parse_args` fills them in.
DEMO_DEFAULTS = dict(
    n_samples=500, outliers=0.1, particles=150, iterations=60, seed=0, gaussian=False, threads=1
)


def _integer(minimum: int):
    """An argparse ``type``: an integer ``>= minimum`` (a usage error otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.__name__ = f"integer >= {minimum}"
    return parse


def _fraction(text: str) -> float:
    """An argparse ``type``: a number in ``[0, 1)``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1), got {text}")
    return value


def _seed_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--seed",
        type=_integer(0),
        default=argparse.SUPPRESS,
        help="seed of the data and of the particle methods (default 0)",
    )


def _demo_args(p: argparse.ArgumentParser) -> None:
    S = argparse.SUPPRESS
    p.add_argument(
        "--n-samples", type=_integer(2), default=S, help="record length N (default and paper: 500)"
    )
    p.add_argument(
        "--outliers",
        type=_fraction,
        default=S,
        help="fraction of outliers in [0, 1) (default and paper: 0.1)",
    )
    p.add_argument("--particles", type=_integer(2), default=S, help="number of particles L (default 150)")
    p.add_argument("--iterations", type=_integer(0), default=S, help="maximum EM iterations (default 60)")
    _seed_arg(p)
    p.add_argument(
        "--gaussian",
        action="store_true",
        default=S,
        help="also fit the Gaussian-noise baseline for comparison",
    )
    p.add_argument(
        "--threads",
        type=_integer(1),
        default=S,
        help="torch CPU threads while the demo runs (default 1: the per-step kernels are small, and "
        "on a busy 2-core machine two threads were measured 100x slower)",
    )


def run_demo(
    n_samples: int = 500,
    outliers: float = 0.1,
    particles: int = 150,
    iterations: int = 60,
    seed: int = 0,
    gaussian: bool = False,
    verbose: int = 1,
) -> dict:
    """Simulate the Section 4.1 system with outliers, fit it, print estimates beside the truth.

    Returns
    -------
    dict
        The fitted estimators (``"robust"``, and ``"gaussian"`` when asked) and the data.
    """
    import torch

    from .datasets import make_paper_example
    from .estimator import RobustNSSMEstimator
    from .models import PaperObservation, PaperTransition

    data = make_paper_example(n_samples=n_samples, outlier_fraction=outliers, random_state=seed)
    truth = data.params
    print(
        f"Paper Section 4.1: x[k+1] = a x[k] + b u[k] + w,  y[k] = c cos(x[k]) + v;  N = {n_samples}, "
        f"{int(data.outlier_mask.sum())} outliers ({outliers:.0%}) uniform in [-5, 5]"
    )
    print(f"initial values a = b = c = 0.5; {particles} particles, up to {iterations} EM iterations\n")
    fits = {"data": data}
    kinds = ["student-t"] + (["gaussian"] if gaussian else [])
    for noise in kinds:
        est = RobustNSSMEstimator(
            PaperTransition(0.5, 0.5, dtype=torch.float64),
            PaperObservation(0.5, dtype=torch.float64),
            x0_mean=[0.0],
            noise=noise,
            n_particles=particles,
            n_iter=iterations,
            random_state=seed,
            verbose=verbose,
        )
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(data.u, data.y)
        est.fit_seconds_ = time.perf_counter() - t0
        fits["robust" if noise == "student-t" else "gaussian"] = est

    rows = [
        ("a", truth["a"], lambda e: e.f_.a.item()),
        ("b", truth["b"], lambda e: e.f_.b.item()),
        ("c", truth["c"], lambda e: e.g_.c.item()),
        ("Rw", truth["Rw"], lambda e: float(e.Rw_[0, 0])),
        ("Rv", truth["Rv"], lambda e: float(e.Rv_[0, 0])),
        ("dof", None, lambda e: float(e.dof_)),
    ]
    names = ["robust"] + (["gaussian"] if gaussian else [])
    header = f"{'parameter':>10} {'true':>9} " + " ".join(f"{n:>10}" for n in names)
    print("\n" + header)
    print("-" * len(header))
    for label, true, get in rows:
        t = "   -     " if true is None else f"{float(np.asarray(true).reshape(-1)[0]):9.4f}"
        vals = " ".join(f"{get(fits[n]):10.4f}" for n in names)
        print(f"{label:>10} {t} {vals}")
    print(f"{'loglik':>10} {'':>9} " + " ".join(f"{fits[n].log_likelihood_:10.1f}" for n in names))
    print(f"{'iterations':>10} {'':>9} " + " ".join(f"{fits[n].n_iter_:10d}" for n in names))
    print(f"{'seconds':>10} {'':>9} " + " ".join(f"{fits[n].fit_seconds_:10.1f}" for n in names))
    print(
        "(Rv of the robust fit is the Student-t scale matrix, not a variance: with dof <= 2 the "
        "noise has no finite variance.)"
    )

    ow = fits["robust"].outlier_weights_
    flagged = fits["robust"].outliers_
    true_out = data.outlier_mask
    n_regular = int((flagged & ~true_out).sum())
    print(
        f"\nOutliers: {int(flagged.sum())} samples flagged (outlier weight E[lambda|y] < "
        f"{float(fits['robust'].outlier_threshold_):.2f}, est.outliers_); "
        f"{int((flagged & true_out).sum())} of the {int(true_out.sum())} injected ones among them, "
        f"{n_regular} regular sample{'' if n_regular == 1 else 's'} flagged."
    )
    print(
        f"Median outlier weight: injected outliers {np.median(ow[true_out]):.3f}, "
        f"regular samples {np.median(ow[~true_out]):.3f}."
    )
    return fits


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m torch_nssm`` (``demo``, the default, and ``reproduce``).

    The demo's options (and ``--seed``) may come before or after the subcommand; they have no
    defaults here: :func:`parse_args` checks and completes the namespace.
    """
    parser = argparse.ArgumentParser(
        prog="python -m torch_nssm",
        description="Robust identification of nonlinear state-space models (Liu & Yang 2019).",
    )
    _demo_args(parser)
    sub = parser.add_subparsers(dest="command")
    _demo_parser(sub)
    _reproduce_parser(sub)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Parse the command line: a usage message and exit code 2 for anything wrong.

    Options of the demo given with ``reproduce`` are refused (they would have no effect);
    options not given take the values of :data:`DEMO_DEFAULTS`.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "reproduce":
        ignored = [k for k in DEMO_DEFAULTS if k != "seed" and hasattr(args, k)]
        if ignored:
            names = ", ".join("--" + k.replace("_", "-") for k in ignored)
            parser.error(f"{names}: option(s) of the demo, not of reproduce")
    for key, value in DEMO_DEFAULTS.items():
        if not hasattr(args, key):
            setattr(args, key, value)
    return args


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m torch_nssm``."""
    args = parse_args(argv)
    if args.command == "reproduce":
        run_reproduce(args.experiment, fast=args.fast, out=args.out, seed=args.seed)
        return 0
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        run_demo(
            n_samples=args.n_samples,
            outliers=args.outliers,
            particles=args.particles,
            iterations=args.iterations,
            seed=args.seed,
            gaussian=args.gaussian,
        )
    finally:
        torch.set_num_threads(threads)
    return 0
