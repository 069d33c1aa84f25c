"""The suite of plants: our default fit against the baselines a user would try first.

For each plant (``suite.plants``) and each outlier setting, on one training record (seed 0) and
its validation record:

* **OE linear / OE soft-L1** -- ``scipy.optimize.least_squares`` on the output errors of the
  noise-free simulation over the whole training record (``suite.baselines.oe_fit``);
* **true model** -- the true parameters' free run on the validation record (the floor set by the
  process noise);
* **ours** -- ``RobustNSSMEstimator(f, g, x0_mean=x0_guess, random_state=0)`` with nothing else
  (``--estimator-options`` adds keyword arguments), then ``standard_errors_``.

Every method starts from the plant's physically sized start (every parameter 30-50 % off) and the
record's ``x0_guess``, and fits the first state; every fit is scored by the free run of the fitted
model on the validation record against the noise-free measurement (RMSE in the output's unit, and
fit % = ``100 (1 - ||y - yhat|| / ||y - mean(y)||)``), from the first state that fits the
validation record's measured ``y`` best (``suite.baselines.validation_scores``; the same for every
method), and, after a slash, from the true first state.  The fitted first state is the fair score:
a model whose states are defined up to a change of coordinates (the tanks' unmeasured upper level)
starts from a wrong state when given the true one.  Each fit
has a wall-clock budget (``--budget`` seconds; our fit is interrupted as by Ctrl-C and keeps its
last completed EM iteration, OE keeps the best parameters evaluated).  The Silverbox row fits the
study's Duffing grey box on 3,000 real training samples (clean, and with the study's 5 % injected
outliers) and scores on the arrow (RMSE in mV, full / without the extrapolated tail); it is skipped
when the data are absent.

Usage (one torch thread; plants run one after the other)::

    python benchmarks/real_records.py --quick                     # a smoke run (clean records only)
    python benchmarks/real_records.py --out results.json          # the full suite
    python benchmarks/real_records.py --plants pendulum --outliers clean,3 \\
        --estimator-options '{"n_particles": 100}'
    python benchmarks/real_records.py --table a.json b.json       # the tables of saved rows

From Python: ``sys.path.insert(0, "benchmarks")``, ``from real_records import run_plant``;
``run_plant("pendulum", "clean", {"n_particles": 100})`` returns the row as a dict
(:func:`markdown_table` prints rows).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
for _path in (HERE, HERE.parent / "examples"):
    if str(_path) not in sys.path:
        sys.path.insert(0, str(_path))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from suite.baselines import (  # noqa: E402
    default_fit,
    estimator_summary,
    free_parameters,
    oe_fit,
    simulate,
    validation_scores,
)
from suite.plants import PLANT_NAMES, PLANTS, SILVERBOX  # noqa: E402

__all__ = ["run_plant", "run_suite", "markdown_table", "parameter_table", "main"]

#: Wall-clock budget of each fit, s.
DEFAULT_BUDGET = 300.0
#: ``--quick``: our fit's options (the user's ``--estimator-options`` override them) and OE's
#: iteration limit.
QUICK_OPTIONS: dict[str, Any] = {"n_iter": 2, "n_particles": 50}
QUICK_OE_NFEV = 5
#: Outlier settings run by default (percent of the training samples; the pendulum also gets 3 %).
DEFAULT_OUTLIERS = ("clean", "5")
PENDULUM_EXTRA = "3"
#: Silverbox: training samples (full run, ``--quick``).
SILVERBOX_TRAIN = (3000, 500)


def _label(outliers: str | float) -> tuple[str, float]:
    """``"clean"`` or a percentage -> (label, fraction)."""
    if isinstance(outliers, str) and outliers.strip().lower() in ("clean", "0", "0.0"):
        return "clean", 0.0
    pct = float(outliers)
    if not 0 < pct < 100:
        raise ValueError(f"outliers must be 'clean' or a percentage in (0, 100), got {outliers!r}")
    return f"{pct:g} % outliers", pct / 100.0


OE_KEYS = ("seconds", "cpu_seconds", "nfev", "njev", "simulations", "status", "message", "budget_exceeded")
OURS_KEYS = (
    "fit_seconds", "se_seconds", "fit_cpu_seconds", "se_cpu_seconds", "interrupted", "se_interrupted",
    "error", "se_error", "warnings", "se_warnings", "standard_errors",
)


def _say(verbose: bool, name: str, label: str):
    if not verbose:
        return lambda *a: None
    return lambda *a: print(f"[{name}, {label}]", *a, file=sys.stderr, flush=True)


def _oe_row(res: dict, val=None) -> dict[str, Any]:
    row = {k: res[k] for k in OE_KEYS}
    row["f_scale"] = res["f_scale"]
    row["params"] = free_parameters(res["f"], res["g"])
    row["x0"] = np.asarray(res["x0"]).tolist()
    if val is not None:
        row.update(validation_scores(res["f"], res["g"], val))
    return row


def _ours_row(fit: dict, outlier_mask: np.ndarray) -> dict[str, Any]:
    row = {k: fit[k] for k in OURS_KEYS}
    est = fit["estimator"]
    if est is not None:
        row.update(estimator_summary(est, outlier_mask))
        row["params"] = free_parameters(est.f_, est.g_)
    return row


def _notes(ours: dict) -> list[str]:
    """Short words for what happened in our fit (the full texts are in the JSON)."""
    notes = []
    if ours.get("error"):
        notes.append("no fit: " + ours["error"].split(":")[0])
    if ours.get("interrupted"):
        notes.append(f"budget: interrupted after {ours.get('n_iter', '?')} it")
    fs = ours.get("first_stage")
    if fs is not None:
        kept = "kept" if fs["accepted"] else "not kept"
        notes.append(f"1st stage {kept} (R² {fs['explained']:.2f})")
    if ours.get("fit_Rw") is False:
        notes.append("Rw held (2nd EM run)")
    if ours.get("dof", math.inf) < 1:
        notes.append("dof < 1")
    rejected = {k.split(".")[1]: v for k, v in (ours.get("rejected_msteps") or {}).items() if v}
    if rejected:
        notes.append("rejected M-steps " + ", ".join(f"{k}: {v}" for k, v in rejected.items()))
    texts = " ".join(w["message"] for w in ours.get("warnings", []))
    for key, word in (
        ("explains none of y", "free run explains none of y"),
        ("g explains almost none", "g explains ~nothing"),
        ("absorbs much of the data", "noise absorbs data"),
        ("did not converge", "not converged"),
        ("diverges at step", "start diverges"),
        ("did not simulate better", "held-Rw EM not better"),
        ("numerical error", "runs lost"),
    ):
        if key in texts:
            notes.append(word)
    if ours.get("se_error"):
        notes.append("s.e. " + ours["se_error"].split(":")[0])
    # torch's own DeprecationWarnings (torch.jit.script, raised inside torch) are left out of the notes
    for w in ours.get("se_warnings") or []:
        if w["category"] == "DeprecationWarning":
            continue
        missing = re.search(r"no standard error for (.*?);", w["message"])
        notes.append(f"no s.e. for {missing.group(1)}" if missing else "s.e. warning: " + w["message"][:60])
    return notes


def run_plant(
    name: str,
    outliers: str | float = "clean",
    options: dict | None = None,
    *,
    budget: float = DEFAULT_BUDGET,
    clock: str = "wall",
    quick: bool = False,
    random_state: int = 0,
    verbose: bool = False,
) -> dict[str, Any]:
    """Fit one plant with one outlier setting by every method; the row of the table as a dict.

    Parameters
    ----------
    name : str
        A plant of ``suite.plants.PLANTS`` or ``"silverbox"``.
    outliers : "clean" or float
        Percentage of training samples with a gross outlier.
    options : dict, optional
        Keyword arguments added to our estimator (e.g. ``{"n_particles": 100}``).
    budget : float
        Budget of each fit, s (``<= 0``: none).
    clock : {"wall", "cpu"}
        The budget's clock: wall time, or the process's CPU time (for a machine shared with other
        jobs); the table shows the seconds of this clock, the row holds both.
    quick : bool
        Short records, few iterations (a smoke run).
    random_state : int
        Seed of the records.
    verbose : bool
        Print each method's result as it finishes (to stderr).
    """
    if name == "silverbox":
        return _run_silverbox(outliers, options, budget=budget, clock=clock, quick=quick, verbose=verbose)
    if name not in PLANTS:
        raise ValueError(f"unknown plant {name!r}; known: {', '.join(PLANT_NAMES)}")
    plant = PLANTS[name]
    label, fraction = _label(outliers)
    opts = {**(QUICK_OPTIONS if quick else {}), **(options or {})}
    n, n_val = (plant.quick_train, plant.quick_validation) if quick else (plant.n_train, plant.n_validation)
    data = plant.make(n, outlier_fraction=fraction, random_state=random_state, n_validation=n_val)
    val = data.validation
    say = _say(verbose, name, label)
    row: dict[str, Any] = {
        "plant": name, "data": label, "outlier_fraction": fraction, "n_train": n, "n_validation": n_val,
        "unit": plant.unit, "options": opts, "budget": budget, "clock": clock, "quick": quick,
        "seed": random_state,
        "truth": {"params": dict(plant.true), "Rw_diag": np.diag(data.params["Rw"]).tolist(),
                  "Rv_diag": np.diag(data.params["Rv"]).tolist()},
        "start": dict(plant.start), "x0_guess": data.x0_guess.tolist(),
    }
    max_nfev = QUICK_OE_NFEV if quick else None
    for loss, key in (("linear", "oe_linear"), ("soft_l1", "oe_soft_l1")):
        f0, g0 = plant.model(plant.start)
        res = oe_fit(
            f0, g0, data.u, data.y, data.x0_guess, loss=loss, max_nfev=max_nfev, seconds=budget, clock=clock
        )
        row[key] = _oe_row(res, val)
        say(f"OE {loss}: RMSE {row[key]['rmse']:.4g} in {res['seconds']:.1f} s wall, "
            f"{res['cpu_seconds']:.1f} s CPU ({res['simulations']} runs)")
    f_true, g_true = plant.model(None)
    row["true_model"] = validation_scores(f_true, g_true, val)
    f0, g0 = plant.model(plant.start)
    fit = default_fit(f0, g0, data.u, data.y, data.x0_guess, options=opts, seconds=budget, clock=clock)
    ours = _ours_row(fit, data.outlier_mask)
    est = fit["estimator"]
    if est is not None:
        ours.update(validation_scores(est.f_, est.g_, val))
    else:
        ours.update(rmse=math.nan, fit_percent=math.nan, rmse_known_x0=math.nan)
    row["ours"] = ours
    row["ratio_ours_oe_linear"] = _ratio(ours["rmse"], row["oe_linear"]["rmse"])
    row["ratio_known_x0"] = _ratio(ours["rmse_known_x0"], row["oe_linear"]["rmse_known_x0"])
    row["notes"] = _notes(ours)
    say(f"ours: RMSE {ours['rmse']:.4g}, fit {fit['fit_seconds']:.1f} s + s.e. {fit['se_seconds']:.1f} s "
        f"wall ({fit['fit_cpu_seconds']:.1f} + {fit['se_cpu_seconds']:.1f} s CPU); "
        + "; ".join(row["notes"]))
    return row


def _ratio(a: float, b: float) -> float:
    return a / b if b and np.isfinite(b) else math.nan


def _run_silverbox(outliers, options, *, budget, clock, quick, verbose) -> dict[str, Any]:
    """The Silverbox row: the study's Duffing grey box from its equation-error start."""
    from silverbox.study import (
        DuffingTransition,
        PositionObservation,
        arrow_rmse_mv,
        equation_error_init,
        prepare_silverbox,
    )

    label, fraction = _label(outliers)
    opts = {**(QUICK_OPTIONS if quick else {}), **(options or {})}
    n = SILVERBOX_TRAIN[1] if quick else SILVERBOX_TRAIN[0]
    data = prepare_silverbox(n_train=n, outlier_fraction=fraction, random_state=0)
    init = equation_error_init(data.u_train, data.y_train, nonlinear=True)
    x0_guess = np.array([data.y_train[0, 0], data.y_train[1, 0] - data.y_train[0, 0]])
    x0_arrow = np.array([data.y_arrow[0, 0], 0.0])  # from rest at the first output, as the study
    y_arrow_mv = data.to_mv(data.y_arrow[:, 0])
    say = _say(verbose, "silverbox", label)

    def arrow_scores(yhat: np.ndarray) -> dict[str, float]:
        s = arrow_rmse_mv(data.to_mv(np.asarray(yhat).reshape(-1)), y_arrow_mv)
        return {"rmse": s["full"], "rmse_no_extrapolation": s["no_extrapolation"]}

    def model():
        return DuffingTransition(**init), PositionObservation()

    row: dict[str, Any] = {
        "plant": "silverbox", "data": label, "outlier_fraction": fraction, "n_train": n,
        "n_validation": int(data.y_arrow.shape[0]), "unit": "mV (arrow: full / w/o tail)", "options": opts,
        "budget": budget, "clock": clock, "quick": quick, "start": dict(init), "x0_guess": x0_guess.tolist(),
        "truth": None,
    }
    max_nfev = QUICK_OE_NFEV if quick else None
    for loss, key in (("linear", "oe_linear"), ("soft_l1", "oe_soft_l1")):
        f0, g0 = model()
        res = oe_fit(
            f0, g0, data.u_train, data.y_train, x0_guess, loss=loss, max_nfev=max_nfev, seconds=budget,
            clock=clock,
        )
        row[key] = _oe_row(res)
        with np.errstate(all="ignore"):
            row[key].update(arrow_scores(simulate(res["f"], res["g"], data.u_arrow, x0_arrow)))
        say(f"OE {loss}: arrow RMSE {row[key]['rmse']:.3f} mV in {res['seconds']:.1f} s")
    row["true_model"] = {"rmse": math.nan, "fit_percent": math.nan}
    f0, g0 = model()
    fit = default_fit(
        f0, g0, data.u_train, data.y_train, x0_guess, options=opts, seconds=budget, clock=clock
    )
    ours = _ours_row(fit, data.outlier_mask)
    est = fit["estimator"]
    if est is not None:
        with np.errstate(all="ignore"):
            ours.update(arrow_scores(est.predict(data.u_arrow, x0=x0_arrow)))
    else:
        ours.update(rmse=math.nan, rmse_no_extrapolation=math.nan)
    row["ours"] = ours
    row["ratio_ours_oe_linear"] = _ratio(ours["rmse"], row["oe_linear"]["rmse"])
    row["notes"] = _notes(ours)
    say(f"ours: arrow RMSE {ours['rmse']:.3f} mV, fit {fit['fit_seconds']:.1f} s; " + "; ".join(row["notes"]))
    return row


def _g(x: float, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return f"{x:.{digits}g}"


def _rmse_cell(m: dict, silverbox: bool) -> str:
    if silverbox:
        return f"{_g(m.get('rmse'))} / {_g(m.get('rmse_no_extrapolation'))}"
    return f"{_g(m.get('rmse'))} / {_g(m.get('rmse_known_x0'))}"


def markdown_table(rows: list[dict]) -> str:
    """The suite's table: RMSE on the validation record (the plant's unit; Silverbox: mV on the
    arrow, full / without the extrapolated tail) and seconds of each method on the rows' budget
    clock (wall or CPU)."""
    cpu = bool(rows) and rows[0].get("clock") == "cpu"
    s = "CPU s" if cpu else "s"
    lines = [
        f"| plant | data | OE linear: RMSE ({s}) | OE soft-L1: RMSE ({s}) | true model RMSE "
        f"| ours: RMSE (fit + s.e. {s}) | ours / OE lin (known x0) | n_iter | dof | flagged | notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sb = r["plant"] == "silverbox"
        lin, soft, ours = r["oe_linear"], r["oe_soft_l1"], r["ours"]
        oe_cells = []
        for m in (lin, soft):
            mark = " budget" if m.get("budget_exceeded") else ""
            oe_cells.append(f"{_rmse_cell(m, sb)} ({m['cpu_seconds' if cpu else 'seconds']:.1f}{mark})")
        se = ours.get("se_cpu_seconds" if cpu else "se_seconds", math.nan)
        se_cell = f"{se:.1f}" if np.isfinite(se) else "-"
        fit_s = ours["fit_cpu_seconds" if cpu else "fit_seconds"]
        ours_cell = f"{_rmse_cell(ours, sb)} ({fit_s:.1f} + {se_cell})"
        if ours.get("interrupted"):
            ours_cell += " budget"
        flagged = "-"
        if "low_weight_share" in ours:
            share = ours.get("false_flag_share", ours["low_weight_share"])  # older rows: low weights
            flagged = f"({100 * share:.1f} %)"
            if ours["n_outliers"]:
                flagged = f"{ours['flagged_outliers']}/{ours['n_outliers']} {flagged}"
        true_cell = "-" if sb else _g(r["true_model"]["rmse"])
        data = r["data"] + (f", seed {r['seed']}" if r.get("seed") else "")
        lines.append(
            f"| {r['plant']} | {data} | {oe_cells[0]} | {oe_cells[1]} | {true_cell} | {ours_cell} | "
            f"{_g(r['ratio_ours_oe_linear'], 2)} ({_g(r.get('ratio_known_x0'), 2)}) | "
            f"{ours.get('n_iter', '-')} | {_g(ours.get('dof'), 2)} | "
            f"{flagged} | {'; '.join(_notes(ours))} |"
        )
    return "\n".join(lines)


def _largest_relative_error(params: dict | None, truth: dict) -> tuple[str, float]:
    if not params:
        return "-", math.nan
    errors = {k: abs(params[k] - v) / abs(v) for k, v in truth.items() if k in params and v != 0}
    if not errors:
        return "-", math.nan
    key = max(errors, key=errors.get)
    return key, errors[key]


def parameter_table(rows: list[dict]) -> str:
    """Largest relative parameter error against the truth of each method (simulated plants)."""
    lines = [
        "| plant | data | OE linear | OE soft-L1 | ours |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if not r.get("truth"):
            continue
        cells = []
        for key in ("oe_linear", "oe_soft_l1", "ours"):
            name, err = _largest_relative_error(r[key].get("params"), r["truth"]["params"])
            cells.append("-" if name == "-" else f"{100 * err:.2g} % ({name})")
        lines.append(f"| {r['plant']} | {r['data']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _settings_for(plant: str, outliers: list[str] | None, quick: bool = False) -> list[str]:
    if outliers is not None:
        return outliers
    if quick:
        return ["clean"]
    extra = [PENDULUM_EXTRA] if plant == "pendulum" else []
    return list(DEFAULT_OUTLIERS[:1]) + extra + list(DEFAULT_OUTLIERS[1:])


def run_suite(
    plants: list[str] | None = None,
    outliers: list[str] | None = None,
    options: dict | None = None,
    *,
    budget: float = DEFAULT_BUDGET,
    clock: str = "wall",
    quick: bool = False,
    out: str | None = None,
    verbose: bool = True,
    seeds: list[int] | None = None,
) -> list[dict]:
    """Every plant, outlier setting and data seed (``seeds``, default ``[0]``: the simulated
    records' draws; Silverbox runs seed 0 only), one after the other; the rows (also written to
    ``out`` after each row, as JSON)."""
    rows = []
    for name in plants or list(PLANT_NAMES):
        plant_seeds = [0] if name == "silverbox" else (seeds or [0])
        for setting in _settings_for(name, outliers, quick):
            try:
                for seed in plant_seeds:
                    row = run_plant(
                        name, setting, options, budget=budget, clock=clock, quick=quick, verbose=verbose,
                        random_state=seed,
                    )
                    rows.append(row)
                    if out:
                        Path(out).write_text(json.dumps({"rows": [_jsonable(r) for r in rows]}, indent=1))
            except FileNotFoundError as exc:  # the Silverbox data are not here
                print(f"[{name}] skipped: {exc}", file=sys.stderr, flush=True)
                break
    return rows


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return repr(obj)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--plants", default=None, help=f"comma-separated subset of {','.join(PLANT_NAMES)}")
    parser.add_argument(
        "--outliers", default=None,
        help="comma-separated settings, 'clean' or a percentage (default clean,5, the pendulum also 3; "
        "--quick: clean)",
    )
    parser.add_argument("--budget", type=float, default=DEFAULT_BUDGET, help="budget per fit, s (0: none)")
    parser.add_argument(
        "--budget-clock", choices=("wall", "cpu"), default="wall",
        help="the budget's clock, also the table's seconds: wall time, or this process's CPU time (a "
        "machine shared with other jobs)",
    )
    parser.add_argument("--quick", action="store_true", help="short records, few iterations (smoke run)")
    parser.add_argument(
        "--seeds", default="0",
        help="comma-separated seeds of the simulated records' draws (default 0; Silverbox: 0 only)",
    )
    parser.add_argument("--estimator-options", default="{}", help="JSON keyword arguments for our estimator")
    parser.add_argument("--out", default=None, help="write the rows as JSON here")
    parser.add_argument(
        "--table", nargs="+", default=None, metavar="JSON",
        help="print the tables of rows saved by --out (several files: concatenated) and run nothing",
    )
    args = parser.parse_args(argv)
    if args.table:
        rows = [r for path in args.table for r in json.loads(Path(path).read_text())["rows"]]
        print(markdown_table(rows))
        print()
        print(parameter_table(rows))
        return rows
    plants = None
    if args.plants:
        plants = [p.strip() for p in args.plants.split(",") if p.strip()]
        unknown = [p for p in plants if p not in PLANT_NAMES]
        if unknown:
            parser.error(f"unknown plants {unknown}; known: {', '.join(PLANT_NAMES)}")
    outliers = [s.strip() for s in args.outliers.split(",")] if args.outliers else None
    try:
        options = json.loads(args.estimator_options)
    except json.JSONDecodeError as exc:
        parser.error(f"--estimator-options is not JSON: {exc}")
    if not isinstance(options, dict):
        parser.error("--estimator-options must be a JSON object")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rows = run_suite(
        plants, outliers, options, budget=args.budget, clock=args.budget_clock, quick=args.quick,
        out=args.out, seeds=seeds,
    )
    print(markdown_table(rows))
    print()
    print(parameter_table(rows))
    print(f"\n{len(rows)} rows in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    if "silverbox" in (plants or PLANT_NAMES):
        print(f"\nSilverbox: {SILVERBOX}", file=sys.stderr)
    return rows


if __name__ == "__main__":
    main()
