"""Bit-for-bit check of a refactor: fit a set of cases, save every fitted attribute, compare two saves.

    python benchmarks/refactor_check.py save OUT.pkl      # with the checkout on PYTHONPATH
    python benchmarks/refactor_check.py compare A.pkl B.pkl

The cases: the paper example (``python -m torch_nssm``'s fit, ``n_iter=30``), the same with
``noise="gaussian"``, ``n_init=3``, ``acceleration="newton"``, Polyak averaging with a final
particle count, a segmented E-step, the MCMC smoother with Adam, ``warm_start=True``, two records with
the first stage; ``noise="student-t-per-output"`` on the two-sensor data; a Table-1-like
``fit_independent`` study (10 data sets, 10 iterations) and one whose data sets converge at
different iterations; a Silverbox grey-box fit where ``fit_Rw="auto"`` runs EM again (when the
record is present).
Every attribute ending in ``_`` (modules as their state dicts, ``history_``, ``first_stage_`` as a
dict) and the warnings raised (text and category, in order) are saved; ``compare`` demands exact
equality.
"""

from __future__ import annotations

import dataclasses
import pickle
import sys
import warnings
from pathlib import Path

import numpy as np
import torch


def _plain(value):
    """Fitted values as NumPy arrays / Python scalars, recursively."""
    if isinstance(value, torch.nn.Module):
        return {k: v.detach().cpu().numpy().copy() for k, v in value.state_dict().items()}
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy().copy()
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _attributes(est) -> dict:
    out = {k: _plain(v) for k, v in vars(est).items() if k.endswith("_") and not k.startswith("_")}
    out["_y_1d"] = getattr(est, "_y_1d", None)
    return out


def _fit(make, *args):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = make(*args)
    said = [(str(w.message), w.category.__name__) for w in caught]
    return result, said


def cases() -> dict:
    from torch_nssm import RobustNSSMEstimator, fit_independent
    from torch_nssm.blocks.linear import LinearObservation, LinearTransition
    from torch_nssm.datasets import make_paper_example
    from torch_nssm.datasets.two_sensors import make_two_sensor_example
    from torch_nssm.models import PaperObservation, PaperTransition

    def paper(**kw):
        params = dict(x0_mean=[0.0], n_particles=200, n_iter=30, random_state=0)
        params.update(kw)
        f = PaperTransition(0.5, 0.5, dtype=torch.float64)
        return RobustNSSMEstimator(f, PaperObservation(0.5, dtype=torch.float64), **params)

    out = {}
    d = make_paper_example(500, 0.1, random_state=0)
    for name, kw in {
        "paper": {},
        "paper_gaussian": {"noise": "gaussian"},
        "paper_n_init3": {"n_init": 3, "n_iter": 10},
        "paper_newton": {"acceleration": "newton", "n_particles": 300, "n_iter": 15},
        "paper_average_final": {"average_last": 4, "n_particles_final": 300, "n_iter": 12},
        "paper_segmented": {"segment_length": 100, "segment_overlap": 20, "n_iter": 6},
        "paper_mcmc_adam": {"smoother": "mcmc", "optimizer": "adam", "n_iter": 6, "first_stage": None},
    }.items():
        est, said = _fit(lambda kw=kw: paper(**kw).fit(d.u, d.y))
        out[name] = {"attributes": _attributes(est), "warnings": said}

    warm = paper(n_iter=6)
    est, said = _fit(lambda: warm.fit(d.u, d.y).set_params(warm_start=True, n_iter=4).fit(d.u, d.y))
    out["paper_warm_start"] = {"attributes": _attributes(est), "warnings": said}
    halves = ([d.u[:300], d.u[300:]], [d.y[:300], d.y[300:]])
    est, said = _fit(lambda: paper(n_iter=8, first_stage="simulation").fit(*halves))
    out["paper_two_records_first_stage"] = {"attributes": _attributes(est), "warnings": said}

    two = make_two_sensor_example(300, glitch_fraction=0.1, random_state=0)
    g = LinearObservation(2, 1, 2)
    g.C.requires_grad_(False)
    per_output = RobustNSSMEstimator(
        LinearTransition(2, 1), g, x0_mean=np.zeros(2), Rv_init=np.diag([0.2, 0.2]), dof_init=10.0,
        noise="student-t-per-output", n_particles=100, n_iter=30, tol=0.0, random_state=0,
    )
    est, said = _fit(lambda: per_output.fit(two.u, two.y))
    out["two_sensors_per_output"] = {"attributes": _attributes(est), "warnings": said}

    sets = [make_paper_example(100, 0.1, random_state=s) for s in range(10)]
    study = paper(n_particles=100, n_iter=10)
    fits, said = _fit(lambda: fit_independent(study, [s.u for s in sets], [s.y for s in sets]))
    out["table1_independent"] = {"attributes": [_attributes(e) for e in fits], "warnings": said}
    early = paper(n_particles=100, n_iter=15, tol=0.02)  # some data sets converge and leave the batch
    fits, said = _fit(lambda: fit_independent(early, [s.u for s in sets], [s.y for s in sets]))
    out["independent_early_stops"] = {
        "attributes": [_attributes(e) for e in fits], "warnings": said, "n_iter": [e.n_iter_ for e in fits]
    }

    silverbox = _silverbox_case()
    if silverbox is not None:
        out["silverbox_fit_Rw_auto"] = silverbox
    return out


def _silverbox_case():
    import os

    root = Path(__file__).resolve().parents[1]
    folder = os.environ.get("TORCH_NSSM_SILVERBOX", root.parent / "shared" / "data" / "silverbox")
    if not Path(folder).exists():
        return None
    sys.path.insert(0, str(root / "examples"))
    from silverbox.first_stage_comparison import estimator
    from silverbox.study import prepare_silverbox

    data = prepare_silverbox(n_train=3000, outlier_fraction=0.05, random_state=0)
    est, said = _fit(lambda: estimator(data, n_iter=8, average_last=0).fit(data.u_train, data.y_train))
    return {"attributes": _attributes(est), "warnings": said}


def _compare(a, b, path: str, diffs: list) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                diffs.append(f"{path}.{k}: only in {'B' if k not in a else 'A'}")
            else:
                _compare(a[k], b[k], f"{path}.{k}", diffs)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            _compare(x, y, f"{path}[{i}]", diffs)
    elif isinstance(a, (np.ndarray, float, int, np.generic)) or isinstance(b, (np.ndarray, float, int)):
        x, y = np.asarray(a), np.asarray(b)
        same = np.array_equal(x, y, equal_nan=x.dtype.kind == "f") if x.shape == y.shape else False
        if x.dtype != y.dtype or not same:
            diffs.append(f"{path}: {a!r} != {b!r}"[:300])
    elif a != b:
        diffs.append(f"{path}: {a!r} != {b!r}"[:300])


def main(argv: list[str]) -> int:
    torch.set_num_threads(1)
    if argv[:1] == ["save"]:
        result = cases()
        Path(argv[1]).write_bytes(pickle.dumps(result))
        print(f"saved {len(result)} cases to {argv[1]}: {sorted(result)}")
        return 0
    if argv[:1] == ["compare"]:
        a, b = (pickle.loads(Path(p).read_bytes()) for p in argv[1:3])
        diffs: list[str] = []
        _compare(a, b, "", diffs)
        print("\n".join(diffs[:50]) if diffs else f"identical: {len(a)} cases ({sorted(a)})")
        return 1 if diffs else 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
