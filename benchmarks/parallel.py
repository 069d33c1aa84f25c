"""The Table 1 study on a 2-worker ``dask.distributed`` LocalCluster against one process, and the
cost of the per-sequence random streams that make the two runs' estimates identical.

``--overhead``: one EM iteration of the Table 1 workload (100 records x N = 1000, L = 100, the
MCMC smoother) with one ``torch.Generator`` for the batch against per-sequence streams
(:class:`torch_nssm.inference.random.SequenceStreams`), alternated, best of ``--reps``.

Default: the study (``make_huang_example``, Cauchy noise, 100 data sets, N = 1000, 100 particles,
``smoother="mcmc"``, fitted from a = b = c = 0.5 like :func:`torch_nssm.reproduce.paper.table1`)
fitted by :func:`torch_nssm.fit_independent` in this process (``n_jobs=1``), then on a LocalCluster
of 2 process workers with 1 thread each (``joblib.parallel_config(backend="dask")``, ``n_jobs=-1``:
2 chunks of 50 data sets); prints the wall times, their ratio and the largest difference of the
estimates (every iterate of every parameter).  The cluster is started (and its workers have
imported torch_nssm) before the clock starts.

    python benchmarks/parallel.py --overhead
    python benchmarks/parallel.py --iters 10          # quick
    python benchmarks/parallel.py --iters 250         # the paper's iterations
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np
import torch

from torch_nssm import fit_independent
from torch_nssm.core.model import SequenceBatch
from torch_nssm.datasets import make_huang_example
from torch_nssm.estimation.estep import e_step
from torch_nssm.estimation.independent import stack_models
from torch_nssm.estimation.mstep import m_step
from torch_nssm.inference.random import SequenceStreams, sequence_seeds
from torch_nssm.reproduce import _paper_estimator


def _study(n_sets: int, n_samples: int):
    datas = [make_huang_example(n_samples=n_samples, random_state=i) for i in range(n_sets)]
    return [d.u for d in datas], [d.y for d in datas]


def overhead(n_sets: int = 100, n_samples: int = 1000, reps: int = 5) -> dict:
    """Seconds of one E-step (and of the M-step) with one generator vs per-sequence streams."""
    torch.set_num_threads(1)
    u, y = _study(n_sets, n_samples)
    proto = _paper_estimator("student-t", 100, 1, 0, smoother="mcmc")
    tensors = [torch.as_tensor(np.asarray(a, dtype=float)).reshape(-1, 1) for a in u]
    outputs = [torch.as_tensor(np.asarray(a, dtype=float)).reshape(-1, 1) for a in y]
    data = SequenceBatch.from_sequences(tensors, outputs)
    models = [proto._initial_model(data.select(slice(b, b + 1)), torch.device("cpu")) for b in range(n_sets)]
    model = stack_models(models)
    options = proto._em_options()
    # CPU time of this process (the machine may be shared: wall time then measures the others'
    # load too) and wall time, best of ``reps``, the two kinds alternated
    times: dict[str, list[tuple[float, float]]] = {"generator": [], "streams": []}
    est = None
    for _ in range(reps):
        for kind in times:
            if kind == "generator":
                gen = torch.Generator().manual_seed(0)
            else:
                gen = SequenceStreams(sequence_seeds(0, n_sets))
            c0, t0 = time.process_time(), time.perf_counter()
            est = e_step(model, data, options.estep, gen)
            times[kind].append((time.process_time() - c0, time.perf_counter() - t0))
    c0, t0 = time.process_time(), time.perf_counter()
    m_step(models, data, est, options.mstep, shared=False)
    m_cpu, m_wall = time.process_time() - c0, time.perf_counter() - t0
    gen_cpu, gen_wall = np.min(times["generator"], 0)
    str_cpu, str_wall = np.min(times["streams"], 0)
    return dict(
        e_generator=(gen_cpu, gen_wall),
        e_streams=(str_cpu, str_wall),
        m_step=(m_cpu, m_wall),
        ratio_estep=(str_cpu / gen_cpu, str_wall / gen_wall),
        ratio_iteration=((str_cpu + m_cpu) / (gen_cpu + m_cpu), (str_wall + m_wall) / (gen_wall + m_wall)),
    )


def study(n_iter: int, n_sets: int = 100, n_samples: int = 1000, seed: int = 0) -> dict:
    """Wall times of the study in one process and on a 2-worker LocalCluster, and the largest
    difference between their estimates."""
    import joblib
    from distributed import Client, LocalCluster

    u, y = _study(n_sets, n_samples)
    proto = _paper_estimator("student-t", 100, n_iter, seed, smoother="mcmc")
    warnings.simplefilter("ignore")
    load_before = os.getloadavg()[0]
    c0, t0 = time.process_time(), time.perf_counter()
    serial = fit_independent(proto, u, y, n_jobs=1)
    t_serial, c_serial = time.perf_counter() - t0, time.process_time() - c0
    fit_independent(proto, u[:2], y[:2], n_jobs=2)  # start joblib's loky pool (2 process workers)
    t0 = time.perf_counter()
    par_loky = fit_independent(proto, u, y, n_jobs=2)
    t_loky = time.perf_counter() - t0
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with Client(cluster) as client:
            client.run(lambda: __import__("torch_nssm.estimator"))  # workers warm
            cpu_before = client.run(time.process_time)
            with joblib.parallel_config(backend="dask"):
                t0 = time.perf_counter()
                par = fit_independent(proto, u, y, n_jobs=-1)
                t_dask = time.perf_counter() - t0
            cpu_after = client.run(time.process_time)
            c_dask = max(cpu_after[w] - cpu_before[w] for w in cpu_before)  # the busier worker

    def rel(a, b):  # relative difference (absolute below 1)
        a, b = np.asarray(a, float), np.asarray(b, float)
        return float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1.0)))

    diff = max(
        rel(a.history_[k], b.history_[k])
        for other in (par, par_loky)
        for a, b in zip(serial, other)
        for k in a.history_
    )
    theta = np.array([0.9, 1.0, 1.0])
    last = np.array([[float(np.ravel(e.history_[k])[-1]) for k in ("f.a", "f.b", "g.c")] for e in serial])
    return dict(
        n_iter=n_iter,
        n_sets=n_sets,
        serial=t_serial,
        dask=t_dask,
        speedup=t_serial / t_dask,
        loky=t_loky,
        loky_speedup=t_serial / t_loky,
        serial_cpu=c_serial,
        dask_cpu=c_dask,
        cpu_speedup=c_serial / c_dask,
        max_diff=diff,
        bias_norm_last=float(np.linalg.norm(theta - last.mean(0))),
        load=(load_before, os.getloadavg()[0]),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--overhead", action="store_true", help="measure the per-sequence streams' cost")
    parser.add_argument("--iters", type=int, default=10, help="EM iterations of the study")
    parser.add_argument("--sets", type=int, default=100)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--reps", type=int, default=5)
    args = parser.parse_args()
    if args.overhead:
        r = overhead(args.sets, args.samples, args.reps)
        print(f"{'':<34}{'CPU (s)':>9}{'wall (s)':>10}")
        rows = (
            ("E-step, one generator", "e_generator"),
            ("E-step, per-sequence streams", "e_streams"),
            ("M-step (the same for both)", "m_step"),
            ("ratio, E-step", "ratio_estep"),
            ("ratio, EM iteration", "ratio_iteration"),
        )
        for label, key in rows:
            print(f"{label:<34}{r[key][0]:9.3f}{r[key][1]:10.3f}")
        return
    r = study(args.iters, args.sets, args.samples)
    setting = f"{r['n_sets']} data sets x N = {args.samples}, L = 100, mcmc, {r['n_iter']} iterations"
    print(f"Table 1 study: {setting}")
    print(f"{'run':<36}{'wall (s)':>10}{'CPU (s)':>10}")
    print(f"{'one process (n_jobs=1)':<36}{r['serial']:10.1f}{r['serial_cpu']:10.1f}")
    print(f"{'joblib loky, 2 workers':<36}{r['loky']:10.1f}{'':>10}")
    print(f"{'LocalCluster, 2 workers x 1 thread':<36}{r['dask']:10.1f}{r['dask_cpu']:10.1f}")
    print(f"speed-up with loky {r['loky_speedup']:.2f}x in wall time")
    print(
        f"speed-up on the LocalCluster {r['speedup']:.2f}x in wall time; {r['cpu_speedup']:.2f}x from CPU "
        "times (the busier worker's: what two free cores give)"
    )
    print(
        f"largest relative difference from the serial estimates (both backends, all iterates, log-lik.): "
        f"{r['max_diff']:.1e}"
    )
    print(f"bias norm of the last iterates: {r['bias_norm_last']:.4f}")
    load = f"{r['load'][0]:.2f} / {r['load'][1]:.2f}"
    print(f"load average (1 min) before/after: {load} on {os.cpu_count()} cores (above: shared with others)")


if __name__ == "__main__":
    main()
