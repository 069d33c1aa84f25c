"""The cost of a fit outside its EM iterations: the free run, the fit's phases, the import.

Three tables, one torch thread, every configuration of the fit in its own process.  All times are
CPU times of the process (``time.process_time``: with one thread, far less sensitive to the load of a
shared machine than wall time, which moved 2.6x between two runs of the same fit here):

1. **Free run, per step** (``--free-run``): ``prediction.free_run`` at one sequence against the
   per-step implementation it replaced (kept below as :func:`reference_free_run`), measured
   alternately in the same process (fastest of ``--repeat`` passes each): the paper's model
   (``PaperTransition`` / ``PaperObservation``), a generic ``nn.Module`` (``a x + b u``), a 2-state
   :class:`~torch_nssm.LinearInParameters` module (its ``features``: the base class's evaluation) and
   the ``MLPTransition``; also ``simulate`` (one trajectory) and ``divergence``.  "same" says whether
   both give the same values to the last bit.
2. **The fit's fixed cost** (``--fit``): one record of the paper's Section 4.1 model
   (``make_paper_example``, 10 % outliers), ``segment_length=500``, ``tol=0`` (exactly ``--n-iter``
   iterations), from ``a, b, c = 0.5``.  The phases are timed by wrapping the functions the pipeline
   calls, wherever it imports them from (found by identity in the loaded ``torch_nssm`` modules, so
   the table follows a restructured estimator): the EM loop (``run_em``: its initial E-step, the
   iterations and the final records), the first stage (``simulation_error_fit``), every
   ``free_run`` and ``divergence``.  **Fixed cost = the fit's time - the time inside
   ``run_em``**; **EM iteration = time inside ``run_em`` / iterations done** (its initial E-step
   spread over them: an upper bound of one iteration).  The phase times are inclusive (the first
   stage's own free run is also in the ``free_run`` row).  Each process first runs an untimed small
   fit (N = 2,000), so one-off costs of the first fit in a process (torch's lazy imports: the first
   ``torch.optim`` optimizer imports ``torch._dynamo``) are not in the table; they are in table 3.
   ``--reference`` adds a row with the reference free run and divergence patched in.
3. **Import and first use** (``--imports``): fresh processes, the median of ``--repeat`` of each, of
   ``import torch`` (with ``sklearn.base``: the floor of any ``BaseEstimator`` subclass),
   ``import torch_nssm``, ``from torch_nssm import RobustNSSMEstimator``, that plus ``torch._dynamo``
   (imported by the first ``torch.optim`` optimizer of a process: the first stage's LBFGS) and that
   plus a first small fit (N = 200, 2 iterations, 50 particles), with the bytecode cache on (as an
   installed package has it, whatever ``PYTHONDONTWRITEBYTECODE`` says), each after one untimed
   warm-up process.  ``--against PATH`` times another checkout in alternation (its ``torch_nssm``
   imported from ``PATH``).

    python benchmarks/fixed_costs.py                      # tables 1 and 2 (N = 40,000)
    python benchmarks/fixed_costs.py --free-run --steps 50000
    python benchmarks/fixed_costs.py --fit --reference --smoother mcmc --particles 200
    python benchmarks/fixed_costs.py --fit --million      # N = 1,000,000 (minutes; ~10 GB at L = 100)
    python benchmarks/fixed_costs.py --imports --repeat 9 --against /tmp/base
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


# ------------------------------------------------------------------------------------------------
# The reference: the per-step implementations the fast ones replaced (one module call a step)
# ------------------------------------------------------------------------------------------------


def reference_free_run(model, u):
    """``prediction.free_run`` as it was: one ``model.transition`` call and one copy a step."""
    import torch

    with torch.no_grad():
        T, B, _ = u.shape
        x = model.per_sequence("x0_mean", B).unsqueeze(1)  # (B, 1, nx)
        states = torch.empty(T, B, x.shape[-1], dtype=x.dtype, device=x.device)
        for k in range(T):
            states[k] = x[:, 0]
            if k + 1 < T:
                x = model.transition(x, u[k])
        return states, model.g(states, u)


def reference_divergence(model, u, limit, max_steps=1000):
    """``prediction.divergence`` as it was: the whole free run (``g`` included), then the check."""
    from torch_nssm.inference.prediction import first_divergent_step

    return first_divergent_step(reference_free_run(model, u[:max_steps])[0], limit)


def reference_simulate(model, u, n_samples, generator=None):
    """``prediction.simulate`` as it was: one ``model.transition`` call, one draw, one copy a step."""
    import torch

    from torch_nssm.inference.filtering import sample_initial_state

    with torch.no_grad():
        T, B, _ = u.shape
        chol_w = torch.linalg.cholesky(model.per_sequence("Rw", B))
        x = sample_initial_state(model, B, n_samples, generator)
        states = torch.empty(T, *x.shape, dtype=x.dtype, device=x.device)
        for k in range(T):
            states[k] = x
            if k + 1 < T:
                noise = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
                x = model.transition(x, u[k]) + noise @ chol_w.transpose(-1, -2)
        mean = model.observation(states, u)
        return states, mean + model.noise.sample(mean.shape[:-1], generator=generator)


# ------------------------------------------------------------------------------------------------
# 1. free run per step
# ------------------------------------------------------------------------------------------------


def _models():
    """``(label, model)`` of the free-run table, each with one sequence's parameters."""
    import torch
    from torch import nn

    from torch_nssm import LinearInParameters
    from torch_nssm.blocks import LinearObservation, MLPTransition
    from torch_nssm.core.model import StateSpaceModel
    from torch_nssm.core.noise import GaussianNoise
    from torch_nssm.models import PaperObservation, PaperTransition

    d = torch.float64
    t = lambda v: torch.tensor(v, dtype=d)  # noqa: E731

    class Affine(nn.Module):
        """``a x + b u``: a plain module (no closed form, its own forward)."""

        def __init__(self):
            super().__init__()
            self.a, self.b = nn.Parameter(t(0.9)), nn.Parameter(t(1.0))

        def forward(self, x, u):
            return self.a * x + self.b * u

    class Cosine(nn.Module):
        def __init__(self):
            super().__init__()
            self.c = nn.Parameter(t(1.0))

        def forward(self, x, u):
            return self.c * torch.cos(x)

    class MassSpring(LinearInParameters):
        """A discretised mass-spring-damper, linear in its stiffness and damping ``theta = (k, d)``:
        ``x1+ = x1 + dt x2``, ``x2+ = x2 + dt (u - k x1 - d x2)`` (the base class's evaluation)."""

        dt = 0.1

        def __init__(self):
            super().__init__()
            self.k, self.d = nn.Parameter(t(1.0)), nn.Parameter(t(0.3))

        def features(self, x, u):
            z = torch.zeros_like(x)
            Phi = torch.stack([z, -self.dt * x], -2)  # (..., 2, 2)
            offset = torch.stack([x[..., 0] + self.dt * x[..., 1], x[..., 1] + self.dt * u[..., 0]], -1)
            return Phi, offset

    def one(f, g, nx, p=1):
        return StateSpaceModel(
            f,
            g,
            0.1 * torch.eye(nx, dtype=d),
            GaussianNoise(0.1 * torch.eye(p, dtype=d)),
            torch.zeros(nx, dtype=d),
            torch.eye(nx, dtype=d),
        )

    torch.manual_seed(0)
    return [
        ("paper (PaperTransition)", one(PaperTransition(0.9, 1.0), PaperObservation(1.0), 1)),
        ("generic nn.Module (a x + b u)", one(Affine(), Cosine(), 1)),
        ("2-state LinearInParameters", one(MassSpring(), LinearObservation(2, 1, 1), 2)),
        ("MLPTransition (2 states, 32x32)", one(MLPTransition(2, 1, dtype=d), LinearObservation(2, 1, 1), 2)),
    ]


def _best_pair(fn_a, fn_b, repeat: int) -> tuple[float, float]:
    """Fastest wall time of ``repeat`` alternated passes of each (after one untimed pass of each)."""
    fn_a(), fn_b()
    best_a = best_b = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        fn_a()
        t1 = time.process_time()
        fn_b()
        t2 = time.process_time()
        best_a, best_b = min(best_a, t1 - t0), min(best_b, t2 - t1)
    return best_a, best_b


def _same(a, b) -> bool:
    import torch

    if isinstance(a, tuple):
        return all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return bool(torch.equal(a, b))
    return a == b


def free_run_table(steps: int, repeat: int) -> list[dict]:
    import torch

    from torch_nssm.inference import prediction

    torch.set_num_threads(1)
    u = torch.randn(steps, 1, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rows = []

    def row(label, ref, new):
        t_ref, t_new = _best_pair(ref, new, repeat)
        same = _same(ref(), new())
        rows.append(
            {"case": label, "ref_us": 1e6 * t_ref / steps, "new_us": 1e6 * t_new / steps, "same": same}
        )
        r = rows[-1]
        print(
            f"| {label} | {r['ref_us']:.1f} | {r['new_us']:.1f} | {r['ref_us'] / r['new_us']:.1f}x | "
            f"{'yes' if same else 'NO'} |",
            flush=True,
        )

    print(
        f"\nFree run, one sequence, T = {steps:,} steps, CPU us per step "
        f"(fastest of {repeat} alternated passes)\n"
    )
    print("| case | reference (per-step module call) | now | speed-up | same values |")
    print("|---|---|---|---|---|")
    models = _models()
    for label, model in models:
        row(
            f"free_run: {label}",
            lambda m=model: reference_free_run(m, u),
            lambda m=model: prediction.free_run(m, u),
        )
    paper = models[0][1]
    row(
        "simulate (paper, 1 trajectory)",
        lambda: reference_simulate(paper, u, 1, torch.Generator().manual_seed(1)),
        lambda: prediction.simulate(paper, u, 1, torch.Generator().manual_seed(1)),
    )
    row(
        f"divergence (paper, max_steps={steps:,}, stays inside)",
        lambda: reference_divergence(paper, u, 1e6, steps),
        lambda: prediction.divergence(paper, u, 1e6, steps),
    )
    return rows


# ------------------------------------------------------------------------------------------------
# 2. the fit's fixed cost
# ------------------------------------------------------------------------------------------------


class _Timers:
    """Wraps functions of the loaded ``torch_nssm`` modules, wherever they are imported, to add up
    their wall time and calls (optionally replacing them first)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.results: dict[str, list] = {}

    def wrap(self, name: str, original, replacement=None) -> None:
        target = original if replacement is None else replacement

        def timed(*args, **kwargs):
            t0 = time.process_time()
            try:
                out = target(*args, **kwargs)
            finally:
                self.seconds[name] = self.seconds.get(name, 0.0) + time.process_time() - t0
                self.calls[name] = self.calls.get(name, 0) + 1
            if name == "run_em":  # its results: the iterations done (nothing else kept alive)
                self.results.setdefault(name, []).append(out)
            return out

        _replace_everywhere(original, timed)
        self.seconds.setdefault(name, 0.0)
        self.calls.setdefault(name, 0)


def _replace_everywhere(original, new) -> None:
    """Rebind every module-level name of the loaded ``torch_nssm`` modules that is ``original``."""
    for mod_name, mod in list(sys.modules.items()):
        if mod is None or not mod_name.startswith("torch_nssm"):
            continue
        for attr, value in list(vars(mod).items()):
            if value is original:
                setattr(mod, attr, new)


def _fit_worker(N: int, n_iter: int, smoother: str, particles: int, reference: bool, seed: int) -> dict:
    import warnings

    import torch

    import torch_nssm.estimator  # noqa: F401  (loads the pipeline's modules before wrapping)
    from torch_nssm import RobustNSSMEstimator
    from torch_nssm.datasets import make_paper_example
    from torch_nssm.models import PaperObservation, PaperTransition

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")

    def estimator(iters):
        return RobustNSSMEstimator(
            PaperTransition(0.5, 0.5),
            PaperObservation(0.5),
            x0_mean=[0.0],
            segment_length=500,
            n_iter=iters,
            tol=0.0,
            n_particles=particles,
            smoother=smoother,
            random_state=seed,
        )

    warm = make_paper_example(n_samples=2000, random_state=seed + 1)
    t0 = time.process_time()
    estimator(1).fit(warm.u, warm.y)  # untimed: the first fit's one-off costs
    first_fit_s = time.process_time() - t0

    import torch_nssm.estimation.loop as loop
    from torch_nssm.inference import prediction

    timers = _Timers()
    wrapped = [("run_em", loop.run_em, None)]
    try:
        from torch_nssm.estimation import first_stage

        wrapped.append(("simulation_error_fit", first_stage.simulation_error_fit, None))
    except (ImportError, AttributeError):
        pass
    wrapped.append(("free_run", prediction.free_run, reference_free_run if reference else None))
    wrapped.append(("divergence", prediction.divergence, reference_divergence if reference else None))
    for name, fn, repl in wrapped:
        timers.wrap(name, fn, repl)

    data = make_paper_example(n_samples=N, random_state=seed)
    est = estimator(n_iter)
    t0, w0 = time.process_time(), time.perf_counter()
    est.fit(data.u, data.y)
    fit_s, fit_wall_s = time.process_time() - t0, time.perf_counter() - w0
    iterations = sum(int(run.n_done) for runs in timers.results.get("run_em", []) for run in runs)
    em_s = timers.seconds["run_em"]
    first = getattr(est, "first_stage_", None)
    return {
        "N": N,
        "reference": reference,
        "fit_s": fit_s,
        "fit_wall_s": fit_wall_s,
        "em_s": em_s,
        "em_runs": timers.calls["run_em"],
        "iterations": iterations,
        "phases": {k: [timers.seconds[k], timers.calls[k]] for k in timers.seconds if k != "run_em"},
        "first_fit_s": first_fit_s,
        "first_stage_accepted": None if first is None else bool(getattr(first, "accepted", False)),
        "theta": [float(est.f_.a), float(est.f_.b), float(est.g_.c)],
    }


def _subprocess(args: list, timeout: float) -> dict | None:
    cmd = [sys.executable, os.path.abspath(__file__), *map(str, args)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=True, cwd=REPO)
    except subprocess.TimeoutExpired:
        print(f"  {args}: over {timeout:.0f} s, skipped", file=sys.stderr)
        return None
    except subprocess.CalledProcessError as exc:
        print(f"  {args} failed:\n{exc.stderr.strip()[-3000:]}", file=sys.stderr)
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])


def fit_table(
    sizes: list[int], n_iter: int, smoother: str, particles: int, reference: bool, seed: int
) -> None:
    print(
        f"\nThe fit's fixed cost: paper 4.1 model, segment_length=500, smoother={smoother}, "
        f"n_particles={particles}, n_iter={n_iter}, tol=0 (fresh process each; CPU seconds)\n"
    )
    print(
        "| N | free run | fit | EM loop (runs, iterations) | EM iteration | fixed cost | fixed cost in EM "
        "iterations | first stage | free_run (calls) | divergence (calls) | a, b, c |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for N in sizes:
        for ref in [True, False] if reference else [False]:
            args = ["--fit-worker", N, n_iter, smoother, particles, int(ref), seed]
            r = _subprocess(args, timeout=7200)
            if r is None:
                continue
            it_s = r["em_s"] / max(r["iterations"], 1)
            fixed = r["fit_s"] - r["em_s"]
            ph = r["phases"]
            fs = ph.get("simulation_error_fit", [float("nan"), 0])
            fr, dv = ph.get("free_run", [0.0, 0]), ph.get("divergence", [0.0, 0])
            print(
                f"| {N:,} | {'reference' if ref else 'now'} | {r['fit_s']:.2f} | {r['em_s']:.2f} "
                f"({r['em_runs']}, {r['iterations']}) | {it_s:.3f} | **{fixed:.2f}** | "
                f"**{fixed / it_s:.1f}** | "
                f"{fs[0]:.2f} | {fr[0]:.2f} ({fr[1]}) | {dv[0]:.3f} ({dv[1]}) | "
                f"{', '.join(f'{v:.4f}' for v in r['theta'])} |",
                flush=True,
            )
    print(
        "\nfixed cost = fit - time inside run_em; EM iteration = time inside run_em / iterations; phase "
        "times inclusive (the first stage's free run is also in the free_run column)."
    )


# ------------------------------------------------------------------------------------------------
# 3. import and first use
# ------------------------------------------------------------------------------------------------

_FIRST_FIT = (
    "import warnings, torch\n"
    "from torch_nssm.datasets import make_paper_example\n"
    "from torch_nssm.models import PaperObservation, PaperTransition\n"
    "warnings.simplefilter('ignore'); torch.set_num_threads(1)\n"
    "d = make_paper_example(n_samples=200, random_state=0)\n"
    "RobustNSSMEstimator(PaperTransition(0.5, 0.5), PaperObservation(0.5), x0_mean=[0.0],\n"
    "                    n_particles=50, n_iter=2, random_state=0).fit(d.u, d.y)\n"
)
_ESTIMATOR = "from torch_nssm import RobustNSSMEstimator"
_IMPORT_CODE = {
    "import torch": "import torch",
    "import torch, sklearn.base (the floor of a BaseEstimator subclass)": "import torch, sklearn.base",
    "import torch_nssm": "import torch_nssm",
    _ESTIMATOR: _ESTIMATOR,
    "+ import torch._dynamo (the first torch.optim optimizer's)": f"{_ESTIMATOR}\nimport torch._dynamo",
    "+ a first fit (N = 200, 2 iterations, 50 particles)": f"{_ESTIMATOR}\n{_FIRST_FIT}",
}


def _time_import(code: str, checkout: str, env: dict) -> tuple[float, int]:
    """CPU seconds of ``code`` in a fresh process run in ``checkout``, and the modules it left loaded."""
    prog = (
        "import time, sys\n"
        "n0 = len(sys.modules)\n"
        "t0 = time.process_time()\n"
        f"{code}\n"
        "print(time.process_time() - t0, len(sys.modules) - n0)\n"
        "mod = sys.modules.get('torch_nssm')\n"
        "assert mod is None or mod.__file__.startswith(sys.argv[1]), mod.__file__\n"
    )
    cmd = [sys.executable, "-c", prog, checkout]
    out = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True, check=True)
    seconds, modules = out.stdout.strip().splitlines()[-1].split()
    return float(seconds), int(modules)


def imports_table(repeat: int, against: str | None) -> None:
    checkouts = [("this checkout", REPO)] + ([("--against", os.path.abspath(against))] if against else [])
    cache = tempfile.mkdtemp(prefix="fixed_costs_pyc_")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update(PYTHONPYCACHEPREFIX=cache, OMP_NUM_THREADS="1")
    times = {(c, label): [] for c, _ in checkouts for label in _IMPORT_CODE}
    modules = {}
    for _, path in checkouts:  # warm-up: writes the bytecode cache
        _time_import(_IMPORT_CODE["+ a first fit (N = 200, 2 iterations, 50 particles)"], path, env)
    for _ in range(repeat):
        for label, code in _IMPORT_CODE.items():
            for c, path in checkouts:  # alternated: the same load for both
                seconds, modules[(c, label)] = _time_import(code, path, env)
                times[(c, label)].append(seconds)
    print(
        f"\nImport and first use: fresh processes, CPU seconds, median of {repeat} (min-max), and the "
        "modules loaded; bytecode cached\n"
    )
    print("| | " + " | ".join(c for c, _ in checkouts) + " |")
    print("|---|" + "---|" * len(checkouts))
    med = {key: statistics.median(v) for key, v in times.items()}
    for label in _IMPORT_CODE:
        cells = []
        for c, _ in checkouts:
            v = times[(c, label)]
            spread = f"{min(v):.2f}-{max(v):.2f}"
            cells.append(f"{med[(c, label)]:.2f} ({spread}), {modules[(c, label)]} modules loaded")
        print(f"| {label} | " + " | ".join(cells) + " |")
    floor = "import torch, sklearn.base (the floor of a BaseEstimator subclass)"
    for c, _ in checkouts:
        own = med[(c, _ESTIMATOR)] - med[(c, floor)]
        first = med[(c, "+ a first fit (N = 200, 2 iterations, 50 particles)")] - med[(c, _ESTIMATOR)]
        print(
            f"\n{c}: the estimator's import beyond torch and sklearn.base {own:.2f} s "
            f"({modules[(c, _ESTIMATOR)] - modules[(c, floor)]} modules); a first small fit {first:.2f} s"
        )


# ------------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--fit-worker", nargs=6, help=argparse.SUPPRESS)
    p.add_argument("--free-run", action="store_true", help="table 1 only (with --fit / --imports: those too)")
    p.add_argument("--fit", action="store_true", help="table 2")
    p.add_argument("--imports", action="store_true", help="table 3")
    p.add_argument("--steps", type=int, default=20_000, help="free-run steps (table 1)")
    p.add_argument("--repeat", type=int, default=5, help="passes (table 1) or processes (table 3) per case")
    p.add_argument("--N", type=int, nargs="*", default=[40_000], help="record lengths (table 2)")
    p.add_argument("--million", action="store_true", help="also N = 1,000,000 (table 2; minutes)")
    p.add_argument("--n-iter", type=int, default=5)
    p.add_argument("--smoother", default="ffbsm", help="the estimator's default: ffbsm")
    p.add_argument("--particles", type=int, default=200, help="the estimator's default: 200")
    p.add_argument("--reference", action="store_true", help="table 2: also with the reference free run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--against", default=None, help="table 3: another checkout to time beside this one")
    a = p.parse_args(argv)
    if a.fit_worker:
        N, n_iter, smoother, particles, ref, seed = a.fit_worker
        r = _fit_worker(int(N), int(n_iter), smoother, int(particles), bool(int(ref)), int(seed))
        print(json.dumps(r))
        return 0
    chosen = a.free_run or a.fit or a.imports
    if a.free_run or not chosen:
        free_run_table(a.steps, a.repeat)
    if a.fit or not chosen:
        sizes = list(a.N) + ([1_000_000] if a.million else [])
        fit_table(sizes, a.n_iter, a.smoother, a.particles, a.reference, a.seed)
    if a.imports:
        imports_table(a.repeat, a.against)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
