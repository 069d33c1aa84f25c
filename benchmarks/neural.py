"""Neural transition models: the README's recipe against its baselines.

The studies, each a subcommand (one torch thread; times are CPU seconds of this process, with the
wall seconds beside them, because the machines these ran on were shared):

* ``pendulum`` -- the suite's damped pendulum (2,000 samples, 3 % outliers, validation record of
  2,000 samples).  The physical model fitted with the defaults (``RobustNSSMEstimator(f, g,
  x0_mean=..., random_state=0)``) against the README's explicit form, ``MLPTransition(2, 1,
  hidden=(32,))`` with ``optimizer="adam", max_iter_mstep=50, n_iter=30``, started by
  ``simulation_start`` (the network trained by robust simulation error, then EM), the same
  estimator fitted with the defaults (the README's recipe, whose fit the targets are computed on:
  ``first_stage="auto"`` runs the same training inside ``fit``),
  and against its baselines: the same network trained by simulation error alone (the first stage), the linear
  state-space reference of ``distilled_start`` and the earlier recipe (``distilled_start``
  then EM).  Scores: validation free-run RMSE against the noise-free angle; the physical model
  from the record's known first state (and from a fitted one), every model from a first state
  fitted to the first 200 validation samples (``fit_initial_states``).
* ``pendulum-records`` -- the defaults on other records of the pendulum family (``--seeds``: each
  seed draws a record and initialises the network), beside the physical model's default fit.
* ``silverbox`` -- a neural state-space model of the Silverbox (network ``f``, linear ``g`` with a
  direct input term, no physical part) trained on the multisine record (``--n-train``; all 90,372
  samples by default), clean and with 5 % outliers, by robust simulation error (Cauchy) and by least
  squares (the Gaussian baseline); arrow free-run RMSE in mV (full and without the extrapolated
  tail), the free run from a first state fitted to the arrow's first 100 samples (the scored windows
  start at 150); ``--em`` adds EM after the robust
  training (Student-t noise, the process noise held small).
* ``suite`` -- the simulated plants of ``benchmarks/suite``: an ``MLPTransition`` (normalised by the
  plant's state scales as a user would from the physics) with the plant's own ``g``, fitted with
  the defaults (``fit`` trains the network by simulation error first), against the physical
  model's default fit; validation RMSE.
* ``first-stage-spread`` -- the neural first stage alone over the pendulum family's records and
  several network initialisations (``--records``, ``--net-seeds``), or over network seeds of the
  suite's plants, for each ``--weight-decay`` (and a ``--validation-fraction``): validation RMSE,
  the training record's free run, the best held-out score and CPU seconds.
* ``first-stage-starts`` -- the neural first stage from several starts of the network (as built;
  trained one step ahead on the true states, an oracle; ``distilled_start`` with a linear or the
  physical reference; one step ahead on the linear reference's smoothed states or in delay
  coordinates of the output): what the start is worth,
  and whether a start a user can build reaches it (``--record-length`` for longer suite records).
* ``distilled-start`` -- ``distilled_start`` then ``fit`` with ``first_stage=None`` (EM alone from
  the distilled network) and with ``"auto"`` (the neural first stage from it, the default since a
  distilled network keeps the estimator's ``first_stage``), beside the physical model's default
  fit (``--plants``, ``--records`` for the pendulum family).
* ``grey-box`` -- a ``GreyBoxTransition`` of the pendulum's RK4 model (plus a 16-unit correction)
  fitted with the defaults and after ``distilled_start``, beside the physical model's default fit
  and the true model's free run (``--records``; ``--friction``: a dry friction in the pivot that
  the physical model lacks; ``--plants oscillator``: the suite's oscillator, the user's physical
  model a linear spring).

Usage::

    python benchmarks/neural.py pendulum --out pendulum.json
    python benchmarks/neural.py silverbox --out silverbox.json            # about 10 min per fit
    python benchmarks/neural.py suite --plants tanks,oscillator --out suite.json
    python benchmarks/neural.py pendulum-records --seeds 1,2,3,4           # about 5 min per seed
    python benchmarks/neural.py first-stage-spread --plants pendulum,bouc_wen --weight-decay 0,1e-3
    python benchmarks/neural.py first-stage-starts --plants oscillator,bouc_wen
    python benchmarks/neural.py distilled-start --plants oscillator,bouc_wen,pendulum --records 0,1,2
    python benchmarks/neural.py grey-box --records 0 --friction 1             # about 10 min per record
    python benchmarks/neural.py grey-box --plants oscillator                  # about 20 min
    python benchmarks/neural.py pendulum --quick                           # a smoke run
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
for _path in (HERE, HERE.parent / "examples"):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torch_nssm import RobustNSSMEstimator, distilled_start, simulation_start  # noqa: E402
from torch_nssm.core.model import SequenceBatch, StateSpaceModel  # noqa: E402
from torch_nssm.estimation.neural_first_stage import (  # noqa: E402
    NeuralFirstStageOptions,
    fit_initial_states,
)
from torch_nssm.estimation.process_noise_check import process_noise_check  # noqa: E402
from torch_nssm.neural import MLPTransition  # noqa: E402

_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731


# ------------------------------------------------------------------------------ helpers
class Clock:
    """CPU and wall seconds since construction."""

    def __init__(self) -> None:
        self.cpu, self.wall = time.process_time(), time.perf_counter()

    def read(self) -> dict[str, float]:
        return {"cpu_s": time.process_time() - self.cpu, "wall_s": time.perf_counter() - self.wall}


def simulate(f, g, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """Noise-free outputs ``(N, p)`` from ``x0``."""
    ut = _t(np.asarray(u).reshape(len(u), -1))
    with torch.no_grad(), np.errstate(all="ignore"):
        x = _t(x0).reshape(1, -1)
        out = []
        for k in range(ut.shape[0]):
            out.append(g(x, ut[k : k + 1])[0])
            x = f(x, ut[k : k + 1])
    return torch.stack(out).numpy()


def fitted_first_state(f, g, u, y, x0_guess, n: int = 200) -> np.ndarray:
    """The first state that simulates the record's first ``n`` outputs best (robust loss)."""
    data = SequenceBatch.from_sequences(
        [_t(np.asarray(u).reshape(len(u), -1))], [_t(np.asarray(y).reshape(len(y), -1))]
    )
    model = StateSpaceModel(f, g, None, None, _t(x0_guess), None)
    return fit_initial_states(model, data, n_samples=n)[0].numpy()


def rmse(a, b) -> float:
    e = np.asarray(a, dtype=float).reshape(-1) - np.asarray(b, dtype=float).reshape(-1)
    return float(np.sqrt(np.mean(e**2))) if np.all(np.isfinite(e)) else math.inf


def fit_quietly(est: RobustNSSMEstimator, u, y) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(u, y)
    return sorted({f"{w.category.__name__}: {w.message}" for w in caught})


def em_summary(est: RobustNSSMEstimator, u, y, outlier_mask: np.ndarray | None) -> dict[str, Any]:
    flags = est.history_["rejected.f"][1:]
    out = {
        "n_iter": int(est.n_iter_),
        "rejected_f": int(np.sum(flags)),
        "Rw_diag": np.diag(est.Rw_).tolist(),
        "Rv_diag": np.diag(np.atleast_2d(est.Rv_)).tolist(),
        "dof": float(np.min(est.dof_)),
    }
    if outlier_mask is not None and outlier_mask.any():
        # the estimator's own flags (weight below outlier_threshold_, not 0.5: at dof near 1 a
        # weight below 0.5 is a residual of 1.7 scales, a third of the regular samples)
        flag = np.asarray(est.outliers_).reshape(len(outlier_mask), -1).any(-1)
        out["flagged"] = f"{int(np.sum(flag & outlier_mask))}/{int(outlier_mask.sum())}"
        out["false_alarms"] = int(np.sum(flag & ~outlier_mask))
    device = torch.device("cpu")
    data, _ = est._batch(u, y, device, fitted=True)
    check = process_noise_check(est._fitted_model(device), data, generator=torch.Generator().manual_seed(0))
    out["process_noise_ratio"] = check.ratio
    return out


# ------------------------------------------------------------------------------ pendulum
def pendulum(quick: bool = False, old: bool = True) -> dict[str, Any]:
    from torch_nssm.datasets import PENDULUM_START, make_pendulum, pendulum_model

    n = 400 if quick else 2000
    d = make_pendulum(n, outlier_fraction=0.03, random_state=0, n_validation=n)
    v = d.validation
    rows: dict[str, Any] = {"n_train": n, "outliers": "3 %"}

    def score(f, g, known_x0=None) -> dict[str, float]:
        x0 = fitted_first_state(f, g, v.u, v.y, np.zeros(2))
        out = {"rmse": rmse(simulate(f, g, v.u, x0), v.y_true)}
        if known_x0 is not None:
            out["rmse_known_x0"] = rmse(simulate(f, g, v.u, known_x0), v.y_true)
        return out

    em_options = dict(n_iter=3, n_particles=50) if quick else {}
    # the physical model with the defaults
    f, g = pendulum_model(PENDULUM_START)
    clock = Clock()
    phys = RobustNSSMEstimator(f, g, x0_mean=d.x0_guess, random_state=0, **em_options)
    said = fit_quietly(phys, d.u, d.y)
    rows["physical"] = {
        **clock.read(),
        **score(phys.f_, phys.g_, v.x0),
        **em_summary(phys, d.u, d.y, d.outlier_mask),
        "warnings": said,
    }
    print("physical", rows["physical"], flush=True)

    def recipe() -> RobustNSSMEstimator:
        _, g = pendulum_model()
        options = dict(optimizer="adam", max_iter_mstep=50, n_iter=30, random_state=0)
        options.update(em_options)
        return RobustNSSMEstimator(
            MLPTransition(2, 1, hidden=(32,), random_state=0), g, x0_mean=[0.0, 0.0], **options
        )

    # the README's recipe: simulation-error training, then EM
    clock = Clock()
    opts = NeuralFirstStageOptions(max_iter=20) if quick else None
    warm, report = simulation_start(recipe(), d.u, d.y, options=opts, return_report=True)
    stage = clock.read()
    rows["first_stage"] = {
        **stage,
        **score(warm.f, warm.g),
        "iterations": report.iterations,
        "best_iteration": report.best_iteration,
        "stop": report.stop_reason,
        "accepted": report.accepted,
        "free_run_train": report.free_run_after,
    }
    print("first stage", rows["first_stage"], flush=True)
    said = fit_quietly(warm, d.u, d.y)
    rows["recipe"] = {
        **clock.read(),
        **score(warm.f_, warm.g_),
        **em_summary(warm, d.u, d.y, d.outlier_mask),
        "warnings": said,
    }
    print("recipe", rows["recipe"], flush=True)

    # the default fit: first_stage="auto" runs the same training inside fit, then the start policy
    if not quick:
        clock = Clock()
        auto = recipe()
        said = fit_quietly(auto, d.u, d.y)
        rows["default_fit"] = {
            **clock.read(),
            **score(auto.f_, auto.g_),
            **em_summary(auto, d.u, d.y, d.outlier_mask),
            "simulation_model": bool(auto.simulation_model_),
            "same_training": auto.first_stage_.free_run_after == report.free_run_after,
            "warnings": said,
        }
        print("default fit", rows["default_fit"], flush=True)

    # the linear reference and the earlier recipe (distilled_start)
    clock = Clock()
    old_est, info = distilled_start(recipe(), d.u, d.y, return_info=True)
    ref = info.reference
    rows["linear_reference"] = {
        **clock.read(),
        **score(ref.f_, ref.g_),
        **em_summary(ref, d.u, d.y, d.outlier_mask),
    }
    print("linear reference", rows["linear_reference"], flush=True)
    if old:
        # the earlier recipe: EM alone from the distilled network (distilled_start leaves a
        # distilled network's first stage to the estimator: "auto" would train it first)
        said = fit_quietly(old_est.set_params(first_stage=None), d.u, d.y)
        rows["earlier_recipe"] = {
            **clock.read(),
            **score(old_est.f_, old_est.g_),
            **em_summary(old_est, d.u, d.y, d.outlier_mask),
            "warnings": said,
        }
        print("earlier recipe", rows["earlier_recipe"], flush=True)
    # the targets are the README recipe's: the defaults (the explicit form's where --quick skips them)
    p, r = rows["physical"], rows.get("default_fit", rows["recipe"])
    rows["targets"] = {
        "rmse_ratio": r["rmse"] / p["rmse_known_x0"],
        "rmse_ratio_same_x0_rule": r["rmse"] / p["rmse"],
        "rejected_share": r["rejected_f"] / max(r["n_iter"], 1),
        "cpu_ratio": r["cpu_s"] / p["cpu_s"],
        "wall_ratio": r["wall_s"] / p["wall_s"],
    }
    print("targets", rows["targets"], flush=True)
    return rows


# ------------------------------------------------------------------------------ silverbox
def silverbox(
    n_train: int,
    outliers: list[float],
    em: bool,
    hidden: int,
    nx: int,
    max_seconds: float | None,
    max_iter: int | None = None,
    losses=("cauchy", "squared"),
    linear_part: bool = False,
) -> dict[str, Any]:
    from silverbox import arrow_rmse_mv, prepare_silverbox

    from torch_nssm.blocks.linear import LinearObservation, LinearTransition
    from torch_nssm.neural import GreyBoxTransition

    results: dict[str, Any] = {
        "n_train": n_train,
        "hidden": hidden,
        "nx": nx,
        "linear_part": linear_part,
        "rows": [],
    }
    for fraction in outliers:
        data = prepare_silverbox(n_train=n_train, outlier_fraction=fraction, random_state=0)
        u, y = data.u_train, data.y_train

        def scores(f, g, data=data) -> dict[str, float]:
            # the state's coordinates are the network's own: the first state is fitted to the arrow's
            # first 100 samples (inside the unscored first 150)
            x0 = fitted_first_state(f, g, data.u_arrow[:100], data.y_arrow[:100], np.zeros(nx), n=100)
            sim = simulate(f, g, data.u_arrow, x0)[:, 0]
            s = arrow_rmse_mv(data.to_mv(sim), data.to_mv(data.y_arrow[:, 0]))
            return {"full_mv": s["full"], "no_extrapolation_mv": s["no_extrapolation"]}

        for loss in losses:
            if linear_part:  # x+ = A x + B u + c + MLP(x, u): a linear state-space model plus a network
                f = GreyBoxTransition(LinearTransition(nx, 1), nx, 1, hidden=(hidden,), random_state=0)
            else:  # x+ = x + MLP(x, u)
                f = MLPTransition(nx, 1, hidden=(hidden,), random_state=0)
            g = LinearObservation(nx, 1, 1, feedthrough=True)  # y = C x + D u + d: a direct input term
            est = RobustNSSMEstimator(
                f,
                g,
                x0_mean=np.zeros(nx),
                noise="gaussian" if loss == "squared" else "student-t",
                random_state=0,
            )
            clock = Clock()
            options = NeuralFirstStageOptions(loss=loss, max_seconds=max_seconds, max_iter=max_iter)
            warm, report = simulation_start(est, u, y, options=options, return_report=True)
            row = {
                "outliers": fraction,
                "fit": f"simulation error ({loss})",
                **clock.read(),
                **scores(warm.f, warm.g),
                "iterations": report.iterations,
                "best_iteration": report.best_iteration,
                "stop": report.stop_reason,
                "validation_losses": report.validation_losses,
            }
            results["rows"].append(row)
            print(row, flush=True)
            if em and loss == "cauchy":
                warm.set_params(
                    fit_Rw=False,
                    Rw_init=np.diag(np.full(nx, 1e-6)),
                    n_particles=100,
                    n_iter=10,
                    tol=0,
                    smoother="mcmc",
                    segment_length=1000 if n_train > 5000 else None,
                    optimizer="adam",
                    max_iter_mstep=20,
                )
                said = fit_quietly(warm, u, y)
                row = {
                    "outliers": fraction,
                    "fit": "simulation error (cauchy), then EM (Student-t, Rw held)",
                    **clock.read(),
                    **scores(warm.f_, warm.g_),
                    **em_summary(warm, u, y, data.outlier_mask),
                    "warnings": said,
                }
                results["rows"].append(row)
                print(row, flush=True)
    return results


# ------------------------------------------------------------------------------ the suite
def suite(plants: list[str], quick: bool) -> dict[str, Any]:
    from suite.plants import PLANTS

    results: dict[str, Any] = {}
    for name in plants:
        plant = PLANTS[name]
        n, n_val = (
            (plant.quick_train, plant.quick_validation) if quick else (plant.n_train, plant.n_validation)
        )
        d = plant.make(n, outlier_fraction=0.0, random_state=0, n_validation=n_val)
        v = d.validation
        em_options = dict(n_iter=3, n_particles=50) if quick else {}
        row: dict[str, Any] = {"n_train": n}
        f, g = plant.model(plant.start)
        clock = Clock()
        phys = RobustNSSMEstimator(f, g, x0_mean=d.x0_guess, random_state=0, **em_options)
        said = fit_quietly(phys, d.u, d.y)
        row["physical"] = {
            **clock.read(),
            "rmse": rmse(simulate(phys.f_, phys.g_, v.u, v.x0), v.y_true),
            "warnings": said,
        }
        # the user's neural f: normalised by the scales of the plant's states (the physics says them)
        net = _suite_network(d, n, 0)
        _, g_start = plant.model(plant.start)
        # the defaults, as the README recommends: fit() trains the network by simulation error
        # first (first_stage="auto") and runs the noise EM of the simulation model it holds
        clock = Clock()
        est = RobustNSSMEstimator(net, g_start, x0_mean=d.x0_guess, random_state=0, **em_options)
        said = fit_quietly(est, d.u, d.y)
        x0 = fitted_first_state(est.f_, est.g_, v.u, v.y, v.x0)
        report = est.first_stage_
        row["neural"] = {
            **clock.read(),
            "rmse": rmse(simulate(est.f_, est.g_, v.u, x0), v.y_true),
            "first_stage_accepted": bool(getattr(report, "accepted", False)),
            "first_stage_iterations": getattr(report, "iterations", None),
            "first_stage_seconds": getattr(report, "seconds", None),
            "simulation_model": bool(est.simulation_model_),
            **em_summary(est, d.u, d.y, None),
            "warnings": said,
        }
        row["ratio"] = row["neural"]["rmse"] / row["physical"]["rmse"]
        results[name] = row
        print(
            name,
            {
                k: (v_ if not isinstance(v_, dict) else {kk: vv for kk, vv in v_.items() if kk != "warnings"})
                for k, v_ in row.items()
            },
            flush=True,
        )
    return results


def pendulum_records(seeds: list[int], n: int = 2000) -> dict[str, Any]:
    """The README's recipe on other records of the pendulum family: for each seed ``s`` a record of
    ``n`` samples (3 % outliers) drawn with ``random_state=s`` and a network initialised with
    ``random_state=s``; the physical model's default fit beside it (ratios of RMSE and CPU)."""
    from torch_nssm.datasets import PENDULUM_START, make_pendulum, pendulum_model

    rows: dict[str, Any] = {}
    print(f"{'seed':>4} {'physical':>9} {'network':>9} {'ratio':>6} {'CPU s phys':>10} {'CPU s net':>9} "
          f"{'CPU ratio':>9} {'flagged':>8} {'false':>5}", flush=True)
    for seed in seeds:
        d = make_pendulum(n, outlier_fraction=0.03, random_state=seed, n_validation=n)
        v = d.validation
        f, g = pendulum_model(PENDULUM_START)
        clock = Clock()
        phys = RobustNSSMEstimator(f, g, x0_mean=d.x0_guess, random_state=0)
        fit_quietly(phys, d.u, d.y)
        x0 = fitted_first_state(phys.f_, phys.g_, v.u, v.y, v.x0)  # the same rule as the network's
        p = {**clock.read(), "rmse": rmse(simulate(phys.f_, phys.g_, v.u, x0), v.y_true)}
        _, g = pendulum_model()
        clock = Clock()
        net = RobustNSSMEstimator(
            MLPTransition(2, 1, hidden=(32,), random_state=seed), g, x0_mean=[0.0, 0.0], random_state=0
        )
        said = fit_quietly(net, d.u, d.y)
        x0 = fitted_first_state(net.f_, net.g_, v.u, v.y, np.zeros(2))
        r = {
            **clock.read(),
            "rmse": rmse(simulate(net.f_, net.g_, v.u, x0), v.y_true),
            "simulation_model": bool(net.simulation_model_),
            **em_summary(net, d.u, d.y, d.outlier_mask),
            "warnings": said,
        }
        rows[str(seed)] = {"physical": p, "network": r}
        cells = [
            f"{seed:>4} {p['rmse']:9.4f} {r['rmse']:9.4f} {r['rmse'] / p['rmse']:6.2f}",
            f"{p['cpu_s']:10.1f} {r['cpu_s']:9.1f} {r['cpu_s'] / p['cpu_s']:9.2f}",
            f"{r['flagged']:>8} {r['false_alarms']:5d}",
        ]
        print(" ".join(cells), flush=True)
    return rows


def _normalised_network(x: np.ndarray, u: np.ndarray, seed: int) -> MLPTransition:
    """An ``MLPTransition(hidden=(32,))`` normalised by the spread of the states ``x`` ``(N, nx)``,
    of their steps and of the inputs ``u`` ``(N, nu)``."""
    dx = np.diff(x, axis=0)
    return MLPTransition(
        x.shape[1],
        u.shape[1],
        hidden=(32,),
        x_mean=x.mean(0),
        x_scale=x.std(0) + 1e-12,
        u_mean=u.mean(0),
        u_scale=u.std(0) + 1e-12,
        out_scale=dx.std(0) + 1e-12,
        random_state=seed,
    )


def _suite_network(d, n: int, seed: int) -> MLPTransition:
    """The suite study's ``MLPTransition`` for record ``d``: normalised by the plant's state scales."""
    return _normalised_network(np.asarray(d.x), np.asarray(d.u).reshape(n, -1), seed)


def _first_stage_records(
    plants: list[str], records: list[int], quick: bool, n_train: int | None = None, friction: float = 0.0
):
    """The records the first-stage studies train on: for ``pendulum`` record ``r`` of the README's
    family (3 % outliers) per entry of ``records``, for a suite plant its clean record of seed 0
    (``n_train`` samples, default the plant's).  Yields ``(name, record, data, x0_guess,
    validation_guess, physical_f_at_start, g, network)``, ``network(seed)`` building the study's
    ``MLPTransition`` (the README's recipe; the suite study's, normalised by the state scales);
    ``friction``: the pendulum's dry friction (``make_pendulum(friction=...)``, absent from its
    physical model)."""
    from suite.plants import PLANTS

    from torch_nssm.datasets import PENDULUM_START, make_pendulum, pendulum_model

    for name in plants:
        for record in records if name == "pendulum" else [0]:
            if name == "pendulum":
                n = 400 if quick else 2000
                d = make_pendulum(
                    n, outlier_fraction=0.03, random_state=record, n_validation=n, friction=friction
                )
                f_phys, g = pendulum_model(PENDULUM_START)
                network = lambda seed: MLPTransition(2, 1, hidden=(32,), random_state=seed)  # noqa: E731
                yield name, record, d, np.zeros(2), np.zeros(2), f_phys, g, network
            else:
                plant = PLANTS[name]
                n = plant.quick_train if quick else (n_train or plant.n_train)
                n_val = plant.quick_validation if quick else plant.n_validation
                d = plant.make(n, outlier_fraction=0.0, random_state=0, n_validation=n_val)
                f_phys, g = plant.model(plant.start)
                network = lambda seed, d=d, n=n: _suite_network(d, n, seed)  # noqa: E731
                # the first-state guesses as the suite study
                yield name, record, d, d.x0_guess, d.validation.x0, f_phys, g, network


def first_stage_spread(
    plants: list[str],
    records: list[int],
    offsets: list[int],
    decays: list[float],
    quick: bool,
    validation_fraction: float = 0.15,
) -> list[dict[str, Any]]:
    """The neural first stage alone (``simulation_start`` with the defaults but ``weight_decay`` and
    ``validation_fraction``) over records and network initialisations: ``pendulum`` draws record
    ``r`` of the README's family and initialises the network with ``r + offset``; a suite plant
    keeps its record (seed 0) and initialises the network with ``offset``.  Validation RMSE of the
    free run from a first state fitted to the validation record's first 200 samples, the training
    record's free run (the same rule), the best held-out score, CPU s."""
    rows: list[dict[str, Any]] = []
    print(f"{'plant':>18} {'record':>6} {'net':>4} {'decay':>7} {'validation':>10} {'training':>9} "
          f"{'held-out':>8} {'CPU s':>6} {'iter.':>5}", flush=True)
    for name, record, d, x0_guess, val_guess, _, g, network in _first_stage_records(plants, records, quick):
        seeds = [record + offset for offset in offsets] if name == "pendulum" else list(offsets)
        v = d.validation
        for seed in seeds:
            for decay in decays:
                est = RobustNSSMEstimator(network(seed), g, x0_mean=x0_guess, random_state=0)
                options = NeuralFirstStageOptions(
                    weight_decay=decay, validation_fraction=validation_fraction
                )
                clock = Clock()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    warm, report = simulation_start(est, d.u, d.y, options=options, return_report=True)
                cpu = clock.read()["cpu_s"]
                x0 = fitted_first_state(warm.f, warm.g, v.u, v.y, val_guess)
                x0_train = fitted_first_state(warm.f, warm.g, d.u, d.y, x0_guess)
                row = {
                    "plant": name,
                    "record": record,
                    "network_seed": seed,
                    "weight_decay": decay,
                    "validation_fraction": validation_fraction,
                    "validation_rmse": rmse(simulate(warm.f, warm.g, v.u, x0), v.y_true),
                    "training_rmse": rmse(simulate(warm.f, warm.g, d.u, x0_train), d.y_true),
                    "held_out": min(report.validation_losses) if report.validation_losses else math.nan,
                    "cpu_s": cpu,
                    "iterations": report.iterations,
                }
                rows.append(row)
                cells = [
                    f"{name:>18} {record:>6} {seed:>4} {decay:7.0e} {row['validation_rmse']:10.4g}",
                    f"{row['training_rmse']:9.4g} {row['held_out']:8.4f} {cpu:6.1f}",
                    f"{report.iterations:>5}",
                ]
                print(" ".join(cells), flush=True)
    return rows


#: The starts ``first-stage-starts`` compares (see its docstring).
STARTS = (
    "defaults", "true-states", "linear-reference", "physical-reference", "linear-states", "delay-coordinates"
)


def _one_step_fit(net: MLPTransition, states: np.ndarray, u: np.ndarray, max_iter: int = 3000) -> None:
    """Train ``net`` one step ahead on a state sequence ``(N, nx)`` (least squares of the steps
    scaled by their spread; full-batch LBFGS)."""
    X, U = _t(states), _t(u.reshape(len(states), -1))
    scale = _t(np.diff(states, axis=0).std(0) + 1e-12)
    opt = torch.optim.LBFGS(
        net.parameters(), max_iter=max_iter, line_search_fn="strong_wolfe",
        tolerance_grad=1e-12, tolerance_change=1e-15, history_size=100,
    )

    def closure():
        opt.zero_grad()
        loss = (((net(X[:-1], U[:-1]) - X[1:]) / scale) ** 2).mean()
        loss.backward()
        return loss

    opt.step(closure)


def _delay_states(y: np.ndarray, nx: int) -> np.ndarray:
    """``(y_k, y_{k-1}, ..., y_{k-nx+1})`` of the first output (the first rows repeat ``y_0``)."""
    col = np.asarray(y, dtype=float).reshape(len(y), -1)[:, 0]
    return np.stack([np.concatenate([np.full(j, col[0]), col[: len(col) - j]]) for j in range(nx)], axis=1)


def _started_estimator(start: str, d, g, f_phys, network, seed: int, x0_guess) -> RobustNSSMEstimator | None:
    """The estimator whose ``f`` the first stage then trains, for one of ``STARTS`` (``None``
    where the start does not apply: delay coordinates need a ``g`` that reads the first state)."""
    u, n = np.asarray(d.u), len(d.y)
    if start == "defaults":
        return RobustNSSMEstimator(network(seed), g, x0_mean=x0_guess, random_state=0)
    if start in ("linear-reference", "physical-reference"):
        est = RobustNSSMEstimator(network(seed), g, x0_mean=x0_guess, random_state=0)
        kw = {"reference_f": copy.deepcopy(f_phys)} if start == "physical-reference" else {}
        return distilled_start(est, d.u, d.y, random_state=0, **kw)
    if start == "true-states":
        states = np.asarray(d.x)
    elif start == "linear-states":
        est = RobustNSSMEstimator(network(seed), g, x0_mean=x0_guess, random_state=0)
        _, info = distilled_start(est, d.u, d.y, random_state=0, return_info=True)
        states = np.asarray(info.reference.smooth(d.u, d.y).mean)
    elif start != "delay-coordinates":
        raise ValueError(f"--starts: unknown start {start!r}; choose from {', '.join(STARTS)}")
    else:
        nx = len(np.asarray(x0_guess).reshape(-1))
        probe = torch.randn(5, nx, dtype=torch.float64)
        with torch.no_grad():
            out = g(probe, torch.zeros(5, u.reshape(n, -1).shape[1], dtype=torch.float64))
        reads_first = torch.equal(out, probe[:, :1])
        if not reads_first:
            return None
        states = _delay_states(d.y, nx)
    net = _normalised_network(states, u.reshape(n, -1), seed)
    _one_step_fit(net, states, u)
    return RobustNSSMEstimator(net, g, x0_mean=states[0], random_state=0)


def first_stage_starts(
    plants: list[str], records: list[int], starts: list[str], quick: bool, n_train: int | None = None
) -> list[dict[str, Any]]:
    """The neural first stage (``simulation_start``, the defaults) from several starts of the
    network, on clean records (the pendulum family's ``records`` with their 3 % outliers):

    * ``defaults``: the network as built (the suite study's, or the README's recipe);
    * ``true-states``: trained one step ahead on the record's true states (an oracle: a bound on
      what a start can give, not something a user has);
    * ``linear-reference`` / ``physical-reference``: ``distilled_start`` with its linear reference
      or the plant's physical model at its start parameters as the reference;
    * ``linear-states``: trained one step ahead on the smoothed states of ``distilled_start``'s
      linear reference fit;
    * ``delay-coordinates``: trained one step ahead on ``(y_k, ..., y_{k-nx+1})`` of the measured
      output (where ``g`` reads the first state).

    Validation RMSE of the start's network and of the trained one, the training record's free run,
    CPU s of the start and of the first stage.  ``n_train``: the suite plants' training length."""
    rows: list[dict[str, Any]] = []
    print(f"{'plant':>18} {'record':>6} {'start':>18} {'start val.':>10} {'validation':>10} {'training':>9} "
          f"{'CPU start':>9} {'CPU stage':>9} {'iter.':>5}", flush=True)
    for name, record, d, x0_guess, val_guess, f_phys, g, network in _first_stage_records(
        plants, records, quick, n_train
    ):
        seed = record if name == "pendulum" else 0
        n = len(d.y)
        v = d.validation
        for start in starts:
            clock = Clock()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est = _started_estimator(start, d, g, f_phys, network, seed, x0_guess)
            if est is None:
                continue
            cpu_start = clock.read()["cpu_s"]
            # the plant's validation guess is in the true states' coordinates; the other starts
            # choose their own, and their first state is the guess
            same_states = start in ("defaults", "true-states")
            guess = val_guess if same_states else np.asarray(est.x0_mean).reshape(-1)
            x0 = fitted_first_state(est.f, est.g, v.u, v.y, guess)
            start_val = rmse(simulate(est.f, est.g, v.u, x0), v.y_true)
            clock = Clock()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                warm, report = simulation_start(est, d.u, d.y, return_report=True)
            cpu = clock.read()["cpu_s"]
            x0 = fitted_first_state(warm.f, warm.g, v.u, v.y, guess)
            x0_train = fitted_first_state(warm.f, warm.g, d.u, d.y, np.asarray(warm.x0_mean).reshape(-1))
            row = {
                "plant": name,
                "record": record,
                "n_train": n,
                "start": start,
                "start_validation_rmse": start_val,
                "validation_rmse": rmse(simulate(warm.f, warm.g, v.u, x0), v.y_true),
                "training_rmse": rmse(simulate(warm.f, warm.g, d.u, x0_train), d.y_true),
                "cpu_start_s": cpu_start,
                "cpu_s": cpu,
                "iterations": report.iterations,
            }
            rows.append(row)
            print(
                f"{name:>18} {record:>6} {start:>18} {start_val:10.4g} {row['validation_rmse']:10.4g} "
                f"{row['training_rmse']:9.4g} {cpu_start:9.1f} {cpu:9.1f} {report.iterations:>5}",
                flush=True,
            )
    return rows


def _scored_fit(est, d, mask: np.ndarray | None, guess=None, distil: bool = False, **params):
    """Fit ``est`` on record ``d`` (after ``distilled_start`` if ``distil``, its CPU included; then
    ``set_params(**params)``) and score it: validation RMSE from a first state fitted to the
    validation record (from ``guess``, default the estimator's ``x0_mean``), CPU s, the fit's
    warnings, its ``em_summary``.  Returns ``(fitted estimator, row)``."""
    clock = Clock()
    if distil:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the reference fit's; the fit's own are recorded
            est = distilled_start(est, d.u, d.y, random_state=0)
    est.set_params(**params)
    said = fit_quietly(est, d.u, d.y)
    cpu = clock.read()["cpu_s"]
    v = d.validation
    guess = np.asarray(est.x0_mean).reshape(-1) if guess is None else guess
    x0 = fitted_first_state(est.f_, est.g_, v.u, v.y, guess)
    row = {
        "validation_rmse": rmse(simulate(est.f_, est.g_, v.u, x0), v.y_true),
        "cpu_s": cpu,
        "simulation_model": bool(getattr(est, "simulation_model_", False)),
        **em_summary(est, d.u, d.y, mask),
        "warnings": said,
    }
    return est, row


def distilled_start_fits(plants: list[str], records: list[int], quick: bool) -> list[dict[str, Any]]:
    """``distilled_start`` (its linear reference), then ``fit``, two ways: ``first_stage=None`` (EM
    alone from the distilled network) and the estimator's ``first_stage="auto"`` (the neural first
    stage from the distilled network, then EM: what the result of ``distilled_start`` does),
    beside the physical model's default fit on the same record; the suite plants' clean records of
    seed 0, the pendulum family's ``records``.  Validation RMSE (ratio to the physical fit), CPU s
    of the whole fit (the reference's fit included), EM iterations, whether the network is held
    as a simulation model, outliers and regular samples flagged."""
    rows: list[dict[str, Any]] = []
    print(f"{'plant':>18} {'record':>6} {'fit':>16} {'validation':>10} {'ratio':>6} {'CPU s':>7} "
          f"{'EM it.':>6} {'sim.':>5} {'flagged':>8} {'regular':>7}", flush=True)
    em_options = dict(n_iter=3, n_particles=50, random_state=0) if quick else dict(random_state=0)
    for name, record, d, x0_guess, val_guess, f_phys, g, network in _first_stage_records(
        plants, records, quick
    ):
        seed = record if name == "pendulum" else 0
        mask = getattr(d, "outlier_mask", None)
        mask = None if mask is None else np.asarray(mask)
        phys = RobustNSSMEstimator(copy.deepcopy(f_phys), g, x0_mean=x0_guess, **em_options)
        _, physical = _scored_fit(phys, d, mask, val_guess)
        for fit in ("physical", None, "auto"):
            if fit == "physical":
                row = {"fit": "physical", **physical}
            else:
                net = RobustNSSMEstimator(network(seed), g, x0_mean=x0_guess, **em_options)
                _, scored = _scored_fit(net, d, mask, distil=True, first_stage=fit)
                row = {"fit": f"distilled, {fit}", **scored}
            val = row["validation_rmse"]
            row = {"plant": name, "record": record, "ratio": val / physical["validation_rmse"], **row}
            rows.append(row)
            print(
                f"{name:>18} {record:>6} {row['fit']:>16} {val:10.4g} {row['ratio']:6.2f} "
                f"{row['cpu_s']:7.1f} {row['n_iter']:>6} {str(row['simulation_model']):>5} "
                f"{row.get('flagged', '-'):>8} {row.get('false_alarms', '-'):>7}",
                flush=True,
            )
    return rows


def _grey_box_records(plant: str, records: list[int], quick: bool, friction: float):
    """The grey-box study's records: ``(record, data, x0_guess, validation guess, physical f at its
    start, g, the true f, whether to normalise the correction)``.  ``pendulum``: the family's
    ``records`` with the pivot's dry ``friction``, which the physical model lacks; ``oscillator``:
    the suite's record of seed 0 with 3 % outliers, the user's physical model a linear spring (the
    cubic stiffness ``alpha`` held at zero)."""
    if plant == "pendulum":
        from torch_nssm.datasets import PENDULUM_TRUE

        for _, record, d, x0_guess, val_guess, f_phys, g, _ in _first_stage_records(
            ["pendulum"], records, quick, friction=friction
        ):
            f_true = type(f_phys)(**PENDULUM_TRUE, friction=friction)
            yield record, d, x0_guess, val_guess, f_phys, g, f_true, False
        return
    from suite.plants import PLANTS

    spec = PLANTS[plant]
    n = spec.quick_train if quick else spec.n_train
    n_val = spec.quick_validation if quick else spec.n_validation
    d = spec.make(n, outlier_fraction=0.03, random_state=0, n_validation=n_val)
    f_phys, g = spec.model({**spec.start, "alpha": 0.0})
    f_phys.alpha.requires_grad_(False)
    f_true, _ = spec.model(spec.true)
    yield 0, d, d.x0_guess, d.validation.x0, f_phys, g, f_true, True


def grey_box(
    records: list[int], quick: bool, hidden: int = 16, friction: float = 0.0, plant: str = "pendulum"
) -> list[dict[str, Any]]:
    """A physical model with a gap and a ``GreyBoxTransition`` of it (the same model at its start
    parameters plus an ``hidden``-unit correction that starts at zero; ``_grey_box_records``: the
    pendulum with a dry ``friction``, or the oscillator whose user's model has a linear spring)
    fitted with the defaults (inside ``fit``: the physical part's first stage, the neural first
    stage of both, the noise EM) and after ``distilled_start`` (the physical part at the
    reference's fit, EM refines both), beside the physical model's default fit and the true
    model's free run (the floor).  The oscillator's correction is normalised by the record's state
    and step scales (``fit_normalisation``), as the suite study's networks are.  Validation RMSE
    (ratio to the physical fit), CPU s, EM iterations, the neural first stage's iterations,
    outliers and regular samples flagged, the fitted physical parameters."""
    from torch_nssm.neural import GreyBoxTransition

    rows: list[dict[str, Any]] = []
    print(f"{'record':>6} {'fit':>18} {'validation':>10} {'ratio':>6} {'CPU s':>7} {'EM it.':>6} "
          f"{'stage it.':>9} {'flagged':>8} {'regular':>7}", flush=True)
    em_options = dict(n_iter=3, n_particles=50, random_state=0) if quick else dict(random_state=0)
    for record, d, x0_guess, val_guess, f_phys, g, f_true, normalise in _grey_box_records(
        plant, records, quick, friction
    ):
        mask = np.asarray(d.outlier_mask)
        v = d.validation
        floor = rmse(simulate(f_true, g, v.u, fitted_first_state(f_true, g, v.u, v.y, val_guess)), v.y_true)
        rmse_physical = None
        for fit in ("physical", "grey box, defaults", "grey box, distilled"):
            f = copy.deepcopy(f_phys)
            if fit != "physical":
                f = GreyBoxTransition(f, d.x.shape[1], 1, hidden=(hidden,), random_state=0)
                if normalise:
                    x, u = np.asarray(d.x), np.asarray(d.u).reshape(len(d.y), -1)
                    f.fit_normalisation(x[:-1], u[:-1], x_next=x[1:])
            est = RobustNSSMEstimator(f, g, x0_mean=x0_guess, **em_options)
            guess = val_guess if fit == "physical" else None
            est, row = _scored_fit(est, d, mask, guess, distil=fit == "grey box, distilled")
            val = row["validation_rmse"]
            rmse_physical = val if rmse_physical is None else rmse_physical
            stage = est.first_stage_
            stage_it = getattr(stage, "iterations", None) if hasattr(stage, "optimizer") else None
            physical = est.f_.physical if fit != "physical" else est.f_
            row = {"plant": plant, "record": record, "friction": friction, "fit": fit,
                   "ratio": val / rmse_physical, **row}
            row["first_stage_iterations"] = stage_it
            row["true_model_rmse"] = floor
            row["physical_parameters"] = {k: float(p.detach()) for k, p in physical.named_parameters()}
            rows.append(row)
            print(
                f"{record:>6} {fit:>18} {val:10.4g} {row['ratio']:6.2f} {row['cpu_s']:7.1f} "
                f"{row['n_iter']:>6} {str(stage_it or '-'):>9} {row['flagged']:>8} {row['false_alarms']:>7}  "
                + " ".join(f"{k}={p:.4g}" for k, p in row["physical_parameters"].items()),
                flush=True,
            )
        print(f"{record:>6} {'true model':>18} {floor:10.4g} {floor / rmse_physical:6.2f}", flush=True)
    return rows


# ------------------------------------------------------------------------------ main
def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    return obj


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "study",
        choices=[
            "pendulum", "pendulum-records", "silverbox", "suite", "first-stage-spread", "first-stage-starts",
            "distilled-start", "grey-box",
        ],
    )
    parser.add_argument("--seeds", default="1,2,3,4", help="pendulum-records: records' and networks' seeds")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--no-old", action="store_true", help="pendulum: skip the earlier recipe")
    parser.add_argument("--n-train", type=int, default=90_372)
    parser.add_argument("--outliers", default="0,0.05")
    parser.add_argument("--em", action="store_true", help="silverbox: EM after the robust training")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--nx", type=int, default=3)
    parser.add_argument("--max-seconds", type=float, default=None)
    parser.add_argument("--max-iter", type=int, default=None, help="silverbox: LBFGS iterations per phase")
    parser.add_argument("--losses", default="cauchy,squared", help="silverbox: the training losses")
    parser.add_argument("--linear-part", action="store_true", help="silverbox: f = linear model + network")
    parser.add_argument("--plants", default="pendulum,tanks,oscillator,wiener_hammerstein,bouc_wen,axis")
    parser.add_argument("--records", default="0,1,2,3,4", help="first-stage-spread: pendulum records")
    parser.add_argument("--net-seeds", default="0,10,20", help="first-stage-spread: network seed offsets")
    parser.add_argument("--weight-decay", default="0,1e-3", help="first-stage-spread: weight decays")
    parser.add_argument("--validation-fraction", type=float, default=0.15, help="first-stage-spread")
    parser.add_argument("--starts", default=",".join(STARTS), help="first-stage-starts: the network's starts")
    parser.add_argument("--friction", type=float, default=0.0, help="grey-box: the pendulum's dry friction")
    parser.add_argument(
        "--record-length", type=int, default=None, help="first-stage-starts: suite plants' training samples"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.study == "pendulum":
        out = pendulum(args.quick, old=not args.no_old)
    elif args.study == "pendulum-records":
        out = pendulum_records([int(a) for a in args.seeds.split(",")], 400 if args.quick else 2000)
    elif args.study == "silverbox":
        fractions = [float(a) for a in args.outliers.split(",")]
        out = silverbox(
            args.n_train,
            fractions,
            args.em,
            args.hidden,
            args.nx,
            args.max_seconds,
            args.max_iter,
            args.losses.split(","),
            args.linear_part,
        )
    elif args.study == "first-stage-spread":
        out = first_stage_spread(
            args.plants.split(","),
            [int(a) for a in args.records.split(",")],
            [int(a) for a in args.net_seeds.split(",")],
            [float(a) for a in args.weight_decay.split(",")],
            args.quick,
            args.validation_fraction,
        )
    elif args.study == "first-stage-starts":
        unknown = sorted(set(args.starts.split(",")) - set(STARTS))
        if unknown:
            parser.error(f"--starts: unknown {', '.join(unknown)}; choose from {', '.join(STARTS)}")
        out = first_stage_starts(
            args.plants.split(","),
            [int(a) for a in args.records.split(",")],
            args.starts.split(","),
            args.quick,
            args.record_length,
        )
    elif args.study == "grey-box":
        plant = args.plants if args.plants in ("pendulum", "oscillator") else "pendulum"
        records = [int(a) for a in args.records.split(",")]
        out = grey_box(records, args.quick, friction=args.friction, plant=plant)
    elif args.study == "distilled-start":
        records = [int(a) for a in args.records.split(",")]
        out = distilled_start_fits(args.plants.split(","), records, args.quick)
    else:
        out = suite(args.plants.split(","), args.quick)
    if args.out:
        args.out.write_text(json.dumps(_jsonable(out), indent=1))


if __name__ == "__main__":
    main()
