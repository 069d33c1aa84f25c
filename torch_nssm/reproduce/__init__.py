"""Reproduce the experiments of Section 4 of Liu & Yang (2019): figures (PNG) and tables (Markdown, CSV).

One function per experiment, each ``f(fast=False, out_dir="reproduction", seed=0, progress=True)``
returning a results dict:

* :func:`fig2` -- Section 4.1, Fig. 2: trajectories of ``a, b, c, Rw, Rv, dof`` over the EM
  iterations, N = 500 with 10% outliers in [-5, 5].
* :func:`gopaluni` -- Figs. 4 and 6: the Gaussian particle EM (Gopaluni 2008) against the robust
  one, N = 400 with 0% and 5% outliers in [-6, 6].
* :func:`table1` -- Table 1: 100 Monte Carlo data sets, N = 1000, Cauchy measurement noise
  ``St(0, 0.01, 1)``; mean and s.d. of ``a, b, c`` and the bias norm ``||theta - E theta_hat||``.
  The data sets are fitted in one batched pass (:func:`torch_nssm.fit_independent`).
* :func:`manipulator` -- Section 4.2, Table 2 and Figs. 10-12: the two-link manipulator with 5,
  10, 20 and 40% outliers; error rate ``|theta_hat - theta| / theta`` in percent.

``fast=True`` runs a tiny version of each (seconds; used by the tests and the notebooks);
``fast=False`` runs the scale documented in ``docs/reproduction.md``.  The settings used
(particles, iterations, initial values, smoother, seed) are returned under ``"settings"`` and
written next to the tables.  The command line is ``python -m torch_nssm reproduce
{fig2,gopaluni,table1,manipulator,all} [--fast] [--out DIR]``.
"""

from ._common import PAPER, PAPER_INIT
from .manipulator_study import (
    MANIPULATOR_INIT,
    _manipulator_nll,
    manipulator,
    manipulator_estimator,
    manipulator_kalman_mle,
)
from .paper import _paper_estimator, fig2, gopaluni, table1

__all__ = [
    "fig2",
    "gopaluni",
    "table1",
    "manipulator",
    "manipulator_estimator",
    "manipulator_kalman_mle",
    "run_all",
    "EXPERIMENTS",
    "PAPER",
    "PAPER_INIT",
    "MANIPULATOR_INIT",
]
# _paper_estimator and _manipulator_nll are re-exported for benchmarks/table1_study.py and the tests
_PRIVATE = (_paper_estimator, _manipulator_nll)

EXPERIMENTS = {"fig2": fig2, "gopaluni": gopaluni, "table1": table1, "manipulator": manipulator}


def run_all(fast: bool = False, out_dir="reproduction", seed: int = 0, progress: bool = True) -> dict:
    """Run every experiment in turn; returns ``{name: results}``."""
    return {
        name: fn(fast=fast, out_dir=out_dir, seed=seed, progress=progress) for name, fn in EXPERIMENTS.items()
    }
