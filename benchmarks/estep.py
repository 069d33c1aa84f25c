"""E-step and EM-iteration benchmark: torch_nssm's smoothers against the peers, one table.

Every measurement runs in its own subprocess (so that peak memory is that configuration's own,
read as the growth of the resident set over the process's state after imports), on the same data
(the paper's Section 4.1 model, ``peers.simulate_41``, Gaussian measurement noise so that every
library computes the same thing), with one torch thread (docs/method.md §7: with many small per-step
kernels two threads on two cores are slower; measured here in the table's ``threads`` column when
``--threads 2`` is given).

    python benchmarks/estep.py                 # N = 500, L in {100, 300, 1000}   (~5 min)
    python benchmarks/estep.py --full          # N in {500, 2000}, L up to 3000   (long)
    python benchmarks/estep.py --ours-only     # torch_nssm only (no peer packages needed)
    python benchmarks/estep.py --table1 20     # also time the Table 1 study (20 iterations)

Each configuration is timed as the fastest of up to 3 passes while the time spent stays under 2 s
(ours after a warm-up at the same size; the peers by the same rule, ``peers._run_measured``).
torch runs with ``THP_MEM_ALLOC_ENABLE=1`` (transparent huge pages for its large CPU tensors, as
numpy has by default on Linux: first-touch page faults of the fresh (T, L) outputs otherwise cost
~15 % of the filter and the MCMC smoother at N * L >= 10^6, measured on a 2-core CPU);
``--no-thp`` turns it off.  ``--device cuda`` adds our smoothers
on a GPU (``--device-only``: only there).

The peers are the optional ``bench`` extra (see README_peers.md for the install command).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
OURS = ("ffbsm", "ffbsi", "mcmc")
PEERS = ("particles-ON2", "particles-mcmc", "particles-reject", "pyParticleEst-full")


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: Timed passes of one configuration: the fastest of up to this many, while the time spent stays
#: under 2 s (the same rule as peers._run_measured applies to the peers).
REPEAT = 3
REPEAT_BUDGET_S = 2.0


def _worker(impl: str, N: int, L: int, seed: int, threads: int, device: str = "cpu") -> dict:
    sys.path.insert(0, HERE)
    import numpy as np
    import peers

    data = peers.simulate_41(N=N, seed=seed)
    u, y = data["u"], data["y"]
    if impl in OURS:
        import torch

        from torch_nssm.core.model import SequenceBatch, StateSpaceModel
        from torch_nssm.core.noise import GaussianNoise
        from torch_nssm.estimation.estep import EStepOptions, e_step
        from torch_nssm.estimation.mstep import MStepOptions, m_step
        from torch_nssm.inference.ffbsm import smoothed_moments
        from torch_nssm.models import PaperObservation, PaperTransition

        torch.set_num_threads(threads)
        dev = torch.device(device)
        t = lambda v: torch.tensor(v, dtype=torch.float64, device=dev)  # noqa: E731
        cuda = dev.type == "cuda"
        sync = torch.cuda.synchronize if cuda else (lambda: None)
        batch = SequenceBatch.from_sequences([t(u).reshape(-1, 1)], [t(y).reshape(-1, 1)])

        def model():
            return StateSpaceModel(
                PaperTransition(0.9, 1.0).to(dev),
                PaperObservation(1.0).to(dev),
                t([[0.1]]),
                GaussianNoise(t([[0.1]])),
                t([0.0]),
                t([[1.0]]),
            )

        gen = torch.Generator(device=dev).manual_seed(seed)
        e_step(model(), batch, EStepOptions(50, impl), gen)  # warm-up (lazy imports)
        base = _rss_mb()  # peak growth of a full-size E-step over this (the warm-up below included)
        if cuda:
            torch.cuda.reset_peak_memory_stats()
            base_gpu = torch.cuda.memory_allocated()
        e_step(model(), batch, EStepOptions(L, impl), gen)  # warm-up at size (allocator, kernels)
        t_e, spent = float("inf"), 0.0
        for i in range(REPEAT):
            if i > 0 and spent >= REPEAT_BUDGET_S:
                break
            gen.manual_seed(seed)  # the same filter particles for every smoother and pass
            sync()
            t0 = time.perf_counter()
            est = e_step(model(), batch, EStepOptions(L, impl), gen)
            sync()
            dt = time.perf_counter() - t0
            t_e, spent = min(t_e, dt), spent + dt
        peak = (torch.cuda.max_memory_allocated() - base_gpu) / 2**20 if cuda else _rss_mb() - base
        m = model()
        t0 = time.perf_counter()
        new = m_step([m], batch, est, MStepOptions(fit_shape=False)).models[0]
        sync()
        t_m = time.perf_counter() - t0
        theta = [float(new.f.a.detach()), float(new.f.b.detach()), float(new.g.c.detach())]
        mean, _ = smoothed_moments(est.filter.particles, est.smoother.log_weights)
        return {
            "impl": f"torch_nssm-{impl}" + ("" if device == "cpu" else f"@{dev.type}"),
            "N": N,
            "L": L,
            "estep_s": t_e,
            "iter_s": t_e + t_m,
            "peak_mb": peak,
            "theta": theta,
            "smoothed_mean": mean[:, 0, 0].cpu().numpy().tolist(),
        }
    runner = {
        "particles-ON2": peers.particles_ffbs_on2,
        "particles-mcmc": peers.particles_ffbs_mcmc,
        "particles-reject": peers.particles_ffbs_reject,
        "pyParticleEst-full": peers.pyparticleest_full,
    }[impl]
    base = _rss_mb()
    r = runner(u, y, L=L, seed=seed, measure_memory=False, repeat=REPEAT)
    return {
        "impl": impl,
        "N": N,
        "L": L,
        "estep_s": r["seconds_total"],
        "iter_s": float("nan"),
        "peak_mb": _rss_mb() - base,
        "smoothed_mean": np.asarray(r["smoothed_mean"]).tolist(),
    }


def _run(
    impl: str, N: int, L: int, seed: int, threads: int, timeout: float, device: str = "cpu", thp: bool = True
) -> dict | None:
    cmd = [sys.executable, __file__, "--worker", impl, str(N), str(L), str(seed), str(threads), device]
    env = dict(os.environ, THP_MEM_ALLOC_ENABLE="1" if thp else "0")
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=True, env=env)
    except subprocess.TimeoutExpired:
        print(f"  {impl} N={N} L={L}: over {timeout:.0f} s, skipped", file=sys.stderr)
        return None
    except subprocess.CalledProcessError as exc:
        print(f"  {impl} N={N} L={L} failed: {exc.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worker", nargs=6, help=argparse.SUPPRESS)
    p.add_argument("--full", action="store_true", help="N in {500, 2000}, L in {100, 300, 1000, 3000}")
    p.add_argument("--N", type=int, nargs="*", default=None)
    p.add_argument("--L", type=int, nargs="*", default=None)
    p.add_argument("--ours-only", action="store_true")
    p.add_argument("--device-only", action="store_true", help="with --device: skip ours on the CPU")
    p.add_argument(
        "--no-thp",
        action="store_true",
        help="run torch without THP_MEM_ALLOC_ENABLE=1 (transparent huge pages for its CPU tensors; numpy "
        "uses them by default on Linux)",
    )
    p.add_argument("--threads", type=int, default=1)
    p.add_argument(
        "--device",
        default="cpu",
        help="also run ours on this torch device (e.g. cuda); the peers always run on the CPU",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per measurement")
    p.add_argument("--json", help="also write the raw results here")
    p.add_argument(
        "--table1",
        type=int,
        metavar="ITERS",
        help="also time the Table 1 study (100 data sets, N=1000, L=100, mcmc, one batched fit) for "
        "ITERS EM iterations and project it to the paper's 250",
    )
    a = p.parse_args(argv)
    if a.worker:
        impl, N, L, seed, threads, device = a.worker
        print(json.dumps(_worker(impl, int(N), int(L), int(seed), int(threads), device)))
        return 0
    Ns = a.N or ([500, 2000] if a.full else [500])
    Ls = a.L or ([100, 300, 1000, 3000] if a.full else [100, 300, 1000])
    impls = list(OURS) + ([] if a.ours_only else list(PEERS))
    results = []
    for N in Ns:
        for L in Ls:
            runs = [(impl, "cpu") for impl in impls]
            if a.device != "cpu":
                runs[len(OURS) : len(OURS)] = [(impl, a.device) for impl in OURS]
                if a.device_only:
                    runs = runs[len(OURS) :]
            for impl, device in runs:
                r = _run(impl, N, L, a.seed, a.threads, a.timeout, device, not a.no_thp)
                if r is not None:
                    results.append(r)
                    print(
                        f"  {r['impl']:>22} N={N:5d} L={L:5d}  E-step {r['estep_s']:8.3f} s", file=sys.stderr
                    )
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh)
    _table(results, Ns, Ls, a.threads, a.device, not a.no_thp)
    if a.table1:
        _table1(a.table1, a.seed)
    return 0


def _table1(n_iter: int, seed: int) -> None:
    """Time the paper's Table 1 study as one batched call (see ``table1_study.py``)."""
    sys.path.insert(0, HERE)
    import table1_study

    table1_study.print_table([table1_study.run("mcmc", n_iter, seed=seed)])


def _table(results: list[dict], Ns, Ls, threads: int, device: str = "cpu", thp: bool = True) -> None:
    import numpy as np

    by = {(r["impl"], r["N"], r["L"]): r for r in results}
    print(
        f"\nE-step (filter + smoother) seconds, Section 4.1 model, Gaussian noise, torch threads={threads}, "
        f"THP_MEM_ALLOC_ENABLE={int(thp)}; fastest of up to {REPEAT} passes within {REPEAT_BUDGET_S:.0f} s"
    )
    print(
        "| N | L | implementation | E-step s | EM iter s | peak MB | RMS vs our FFBSm "
        "| a, b, c after one M-step | ours faster by |"
        + (f" ours on {device} faster by |" if device != "cpu" else "")
    )
    print("|---|---|---|---|---|---|---|---|---|" + ("---|" if device != "cpu" else ""))
    dev = "" if device == "cpu" else "@" + device.split(":")[0]
    pair = {
        "particles-ON2": "torch_nssm-ffbsm",
        "pyParticleEst-full": "torch_nssm-ffbsm",
        "particles-reject": "torch_nssm-ffbsi",
        "particles-mcmc": "torch_nssm-mcmc",
    }
    for N in Ns:
        for L in Ls:
            ref = by.get(("torch_nssm-ffbsm", N, L))
            ours_dev = [f"torch_nssm-{o}{dev}" for o in OURS] if dev else []
            for impl in [f"torch_nssm-{o}" for o in OURS] + ours_dev + list(PEERS):
                r = by.get((impl, N, L))
                if r is None:
                    continue
                rms = (
                    float(np.sqrt(np.mean((np.array(r["smoothed_mean"]) - ref["smoothed_mean"]) ** 2)))
                    if ref
                    else float("nan")
                )
                ours = by.get((pair.get(impl, ""), N, L))
                ratio = f"{r['estep_s'] / ours['estep_s']:.1f}x ({pair[impl][11:]})" if ours else ""
                if dev:
                    ours_d = by.get((pair.get(impl, "") + dev, N, L))
                    ratio += f" | {r['estep_s'] / ours_d['estep_s']:.1f}x" if ours_d else " |"
                it = "" if np.isnan(r["iter_s"]) else f"{r['iter_s']:.3f}"
                th = ", ".join(f"{v:.4f}" for v in r["theta"]) if r.get("theta") else ""
                if dev and impl.startswith("torch_nssm"):
                    ratio += " |"
                print(
                    f"| {N} | {L} | {impl} | {r['estep_s']:.3f} | {it} | {r['peak_mb']:.0f} | "
                    f"{rms:.3f} | {th} | {ratio} |"
                )
    for o in ("ffbsi", "mcmc"):
        for N in Ns:
            a, b = by.get((f"torch_nssm-{o}", N, 300)), by.get((f"torch_nssm-{o}", N, 3000))
            if a and b:
                k = np.log(b["estep_s"] / a["estep_s"]) / np.log(10.0)
                print(f"\ntorch_nssm-{o}, N={N}: E-step time grows as L^{k:.2f} from L=300 to L=3000")


if __name__ == "__main__":
    raise SystemExit(main())
