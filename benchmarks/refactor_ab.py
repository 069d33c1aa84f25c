"""A/B timing of two checkouts on the paper example: E-step and EM iteration, one thread.

    python benchmarks/refactor_ab.py OLD_ROOT NEW_ROOT [--rounds 6]

Each round runs one fresh process per checkout (alternating, ``PYTHONPATH`` = the checkout), which
times, after a warm-up, 10 E-steps at the start (``e_step`` as the loop calls it) and a 20-iteration
EM run (``run_em``, ``tol=0``, no first stage) on ``make_paper_example(500, 0.1, random_state=0)``
with 200 particles.  Prints the median of each and the ratio NEW / OLD.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

CHILD = r"""
import json, time, torch
torch.set_num_threads(1)
from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.estimation.estep import e_step
from torch_nssm.estimation.loop import run_em
from torch_nssm.models import PaperObservation, PaperTransition

d = make_paper_example(500, 0.1, random_state=0)
f, g = PaperTransition(0.5, 0.5, dtype=torch.float64), PaperObservation(0.5, dtype=torch.float64)
kw = dict(x0_mean=[0.0], n_particles=200, n_iter=20, tol=0.0, first_stage=None, random_state=0)
est = RobustNSSMEstimator(f, g, **kw)
est._check_params()
data, _ = est._batch(d.u, d.y, torch.device("cpu"), fitted=False)
model = est._initial_model(data, torch.device("cpu"))
options = est._em_options()
gen = torch.Generator().manual_seed(0)
for _ in range(3):
    e_step(model, data, options.estep, gen, records=False)
t0 = time.perf_counter()
for _ in range(10):
    e_step(model, data, options.estep, gen, records=False)
estep = (time.perf_counter() - t0) / 10
cpu = torch.device("cpu")
run_em([est._initial_model(data, cpu)], data, est._em_options(), torch.Generator().manual_seed(1))
t0 = time.perf_counter()
(result,) = run_em([est._initial_model(data, cpu)], data, est._em_options(), torch.Generator().manual_seed(2))
iteration = (time.perf_counter() - t0) / result.n_done
print(json.dumps({"estep": estep, "iteration": iteration}))
"""


def _run(root: str) -> dict:
    env = dict(os.environ, PYTHONPATH=root, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    cmd = [sys.executable, "-c", CHILD]
    out = subprocess.run(cmd, env=env, cwd=root, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str]) -> int:
    old, new = argv[0], argv[1]
    rounds = int(argv[argv.index("--rounds") + 1]) if "--rounds" in argv else 6
    times: dict[str, list[dict]] = {"old": [], "new": []}
    for r in range(rounds):
        order = (("old", old), ("new", new)) if r % 2 == 0 else (("new", new), ("old", old))
        for label, root in order:
            times[label].append(_run(root))
        print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]}" for k, v in times.items()), flush=True)
    for key in ("estep", "iteration"):
        o = float(np.median([t[key] for t in times["old"]]))
        n = float(np.median([t[key] for t in times["new"]]))
        print(f"{key}: old {o * 1e3:.1f} ms, new {n * 1e3:.1f} ms, new/old {n / o:.3f}")
    return 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main(sys.argv[1:])
    print(f"({time.perf_counter() - t0:.0f} s)")
    raise SystemExit(code)
