"""A/B of the E-step and of EM iterations, in one process, alternating: a copy of the package at an
earlier revision, renamed ``torch_nssm_before``, against this checkout's ``torch_nssm``; CPU time,
one thread (the machine's load moves wall times by 2x; CPU time within one process, paired, much
less).  Per case and kind: the median of the paired ratios after/before, of the medians, of the
minima::

    mkdir -p /tmp/before && git archive c6352b6 torch_nssm | tar -x -C /tmp/before
    mv /tmp/before/torch_nssm /tmp/before/torch_nssm_before
    python benchmarks/noise_ab.py /tmp/before 11          # 11 pairs per case
    python benchmarks/noise_ab.py /tmp/before 25 "paper gaussian" "estep,em 2 it"

The package has no absolute self-imports, so the renamed copy imports itself.
"""

from __future__ import annotations

import importlib
import sys
import time
import warnings

import numpy as np
import torch

torch.set_num_threads(1)
warnings.simplefilter("ignore")
sys.path.insert(0, sys.argv[1])


def load(name):
    m = lambda s: importlib.import_module(f"{name}.{s}")  # noqa: E731
    top = importlib.import_module(name)
    return dict(
        Est=top.RobustNSSMEstimator, lin=m("blocks.linear"), ds=m("datasets"), paper=m("datasets.paper"),
        two=m("datasets.two_sensors"), estep=m("estimation.estep"), loop=m("estimation.loop"),
        ind=m("estimation.independent"), model=m("core.model"),
    )


def cases(P):
    out = {}
    def setup(est, u, y):
        device = est._check_params()
        data, _ = est._batch(u, y, device, fitted=False)
        return data, (lambda: est._initial_model(data, device))
    for noise in ("student-t", "gaussian"):
        d = P["ds"].make_paper_example(n_samples=400, outlier_fraction=0.1, random_state=0)
        f, g = P["paper"].PaperTransition(0.5, 0.5), P["paper"].PaperObservation(0.5)
        est = P["Est"](f, g, x0_mean=[0.0], noise=noise)
        out[f"paper {noise}"] = setup(est, d.u, d.y)
    for noise in ("student-t-per-output", "student-t"):
        d = P["two"].make_two_sensor_example(300, glitch_fraction=0.1, random_state=0)
        f, g = P["lin"].LinearTransition(2, 1), P["lin"].LinearObservation(2, 1, 2)
        est = P["Est"](f, g, x0_mean=np.zeros(2), Rv_init=np.diag([0.2, 0.2]), noise=noise)
        out[f"two {noise}"] = setup(est, d.u, d.y)
    ds = [P["ds"].make_huang_example(n_samples=400, random_state=i) for i in range(10)]
    est = P["Est"](P["paper"].PaperTransition(0.5, 0.5), P["paper"].PaperObservation(0.5), x0_mean=[0.0])
    device = est._check_params()
    datas = [est._batch(d.u, d.y, device, fitted=False)[0] for d in ds]
    data = P["model"].SequenceBatch.from_sequences([d.u[:, 0] for d in datas], [d.y[:, 0] for d in datas])
    out["batched 10x400"] = (data, lambda: [est._initial_model(d, device) for d in datas])
    return out


V = {"before": load("torch_nssm_before"), "after": load("torch_nssm")}
C = {k: cases(P) for k, P in V.items()}


def run(version, case, kind):
    P = V[version]
    data, model = C[version][case]
    batched = case.startswith("batched")
    L = 100 if batched else 200
    if kind == "estep":
        m = P["ind"].stack_models(model()) if batched else model()
        options = P["estep"].EStepOptions(n_particles=L)
        f = lambda: P["estep"].e_step(m, data, options, torch.Generator().manual_seed(0))  # noqa: E731
    else:
        ms = model() if batched else [model()]
        opts = P["loop"].EMOptions(n_iter=2, tol=0.0, estep=P["estep"].EStepOptions(n_particles=L))
        f = lambda: P["loop"].run_em(ms, data, opts, torch.Generator().manual_seed(0), shared=not batched)  # noqa: E731
    t = time.process_time()
    f()
    return time.process_time() - t


reps = int(sys.argv[2]) if len(sys.argv) > 2 else 9
chosen = sys.argv[3].split(",") if len(sys.argv) > 3 else list(C["after"])
kinds = sys.argv[4].split(",") if len(sys.argv) > 4 else ["estep", "em 2 it"]
for case in chosen:
    for kind in kinds:
        for v in V:
            run(v, case, kind)  # warm-up
        ratios, ts = [], {"before": [], "after": []}
        for r in range(reps):
            order = ("before", "after") if r % 2 == 0 else ("after", "before")
            got = {v: run(v, case, kind) for v in order}
            for v in V:
                ts[v].append(got[v])
            ratios.append(got["after"] / got["before"])
        b, a = np.array(ts["before"]), np.array(ts["after"])
        print(
            f"{case:26s} {kind:8s} before {np.median(b):.4f} s  after {np.median(a):.4f} s  after/before: "
            f"median of paired {np.median(ratios):.3f}, of medians {np.median(a) / np.median(b):.3f}, "
            f"of minima {a.min() / b.min():.3f}",
            flush=True,
        )
