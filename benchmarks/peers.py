"""Timing functions for the *peer* libraries that torch_nssm's E-step is compared against.

Model (paper §4.1, see docs/method.md §6 and §7 for the time convention)::

    x_0 ~ N(x0_mean, x0_var)                      (default N(0, 1))
    x_{k+1} = a x_k + b u_k + w_k,   w_k ~ N(0, Rw)
    y_k     = c cos(x_k) + v_k,      v_k ~ N(0, Rv)          (nu=None)
                                     v_k ~ St(0, Rv, nu)       (nu=float; Rv is the squared scale)

True values a=0.9, b=1, c=1, Rw=Rv=0.1 (variances); u is Gaussian white noise; N = 500;
10 % of the outputs get an additive outlier drawn uniformly in [-5, 5].

Peers (see benchmarks/README_peers.md for versions, install command and measured times):

* ``particles`` 0.4 (N. Chopin): bootstrap filter ``particles.SMC(fk=Bootstrap(...),
  store_history=True)``, then one of the backward samplers of
  ``particles.smoothing.ParticleHistory``:
  ``backward_sampling_ON2(M)`` (exact FFBS, O(N·L·M)), ``backward_sampling_mcmc(M)``
  (independent-Metropolis backward kernel, O(N·M)) and ``backward_sampling_reject(M)``
  (hybrid rejection FFBS, Dau & Chopin 2022).
* ``pyParticleEst`` 1.1.4 (J. Nordh): ``ParticleTrajectory`` (the forward pass that
  ``Simulator.simulate`` runs) with ``filter='PF'``, then ``perform_smoothing(M, method)``,
  ``method`` in ``'full'`` (FFBSi, O(N·L·M); it is also the default E-step smoother of
  ``pyparticleest.paramest.ParamEstimation``, i.e. its PS-EM), ``'rs'`` (rejection FFBSi with
  fall-back to 'full'), ``'mcmc'`` (Metropolis-Hastings FFBSi, R=30 steps by default) and
  ``'ancestor'`` (filter genealogy only; no backward pass).
* ``numpy-ffbsm``: not a peer but a reference: a plain numpy bootstrap filter + the exact
  marginal FFBSm of docs/method.md §3 (O(N·L²)), vectorised per time step. It gives a low-variance
  smoothed mean to check the peers against, and a "naive numpy" time.

Every runner has the signature ``fn(u, y, params=None (TRUE_PARAMS), L=100, seed=0, *, M=None,
nu=None, x0_mean=0.0, x0_var=1.0, resample_threshold=1.0, measure_memory=True, repeat=1,
...)`` and returns a dict with keys ``peer, smoother, L, M, N, noise, seconds_filter,
seconds_smoother, seconds_total, cpu_seconds_*, peak_mem_mb, smoothed_mean`` (+ extras).

Timing: ``time.perf_counter`` (and ``time.process_time``) around the filter and around the
smoother of an untraced run (the fastest of ``repeat`` runs).
Memory: ``peak_mem_mb`` is the ``tracemalloc`` peak (MiB, numpy buffers included) of a *second*
run with the same seed, because tracing slows these pure-Python loops down by a large factor;
``measure_memory=False`` skips that second run and reports NaN.

This module does not import torch_nssm or torch.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import time
import tracemalloc
import types
from typing import Any, Callable

import numpy as np

TRUE_PARAMS: dict[str, float] = {"a": 0.9, "b": 1.0, "c": 1.0, "Rw": 0.1, "Rv": 0.1}


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------
def simulate_41(
    N: int = 500,
    seed: int = 0,
    params: dict[str, float] | None = None,
    outlier_frac: float = 0.1,
    outlier_half_width: float = 5.0,
    x0_mean: float = 0.0,
    x0_var: float = 1.0,
) -> dict[str, np.ndarray]:
    """Simulate the §4.1 system. Returns ``{"u", "y", "x", "outliers"}`` (all shape (N,)).

    ``round(outlier_frac * N)`` distinct samples get ``y += U[-h, h]``; ``outliers`` is the mask.
    """
    p = dict(TRUE_PARAMS if params is None else params)
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(N)
    x = np.empty(N)
    x[0] = x0_mean + math.sqrt(x0_var) * rng.standard_normal()
    w = math.sqrt(p["Rw"]) * rng.standard_normal(N)
    for k in range(N - 1):
        x[k + 1] = p["a"] * x[k] + p["b"] * u[k] + w[k]
    y = p["c"] * np.cos(x) + math.sqrt(p["Rv"]) * rng.standard_normal(N)
    n_out = int(round(outlier_frac * N))
    idx = rng.choice(N, size=n_out, replace=False)
    y[idx] += rng.uniform(-outlier_half_width, outlier_half_width, size=n_out)
    mask = np.zeros(N, dtype=bool)
    mask[idx] = True
    return {"u": u, "y": y, "x": x, "outliers": mask}


# --------------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------------
def _noise_name(nu: float | None) -> str:
    return "gaussian" if nu is None else f"student-t(nu={nu:g})"


def _log_obs_density(y: float, x: np.ndarray, c: float, Rv: float, nu: float | None) -> np.ndarray:
    """log p(y | x) for the §4.1 output equation (Gaussian or Student-t with squared scale Rv)."""
    r2 = (y - c * np.cos(x)) ** 2 / Rv
    if nu is None:
        return -0.5 * r2 - 0.5 * math.log(2.0 * math.pi * Rv)
    const = (
        math.lgamma((nu + 1.0) / 2.0)
        - math.lgamma(nu / 2.0)
        - 0.5 * math.log(nu * math.pi * Rv)
    )
    return const - 0.5 * (nu + 1.0) * np.log1p(r2 / nu)


def _run_measured(
    one_pass: Callable[[], dict[str, Any]],
    measure_memory: bool,
    repeat: int = 1,
    repeat_budget_s: float = 2.0,
) -> dict[str, Any]:
    """Run ``one_pass`` untraced for the times, then once more under tracemalloc for the peak.

    ``one_pass`` must reseed itself so that every pass does the same work. With ``repeat > 1``
    the timed pass is repeated (while the time spent stays under ``repeat_budget_s``) and the
    fastest pass is kept; ``seconds_total_all`` lists every pass.
    """
    res = None
    all_totals = []
    spent = 0.0
    for i in range(max(1, int(repeat))):
        if i > 0 and spent >= repeat_budget_s:
            break
        r = one_pass()
        tot = r["seconds_filter"] + r["seconds_smoother"]
        all_totals.append(tot)
        spent += tot
        if res is None or tot < res["seconds_filter"] + res["seconds_smoother"]:
            res = r
    peak = float("nan")
    if measure_memory:
        was_tracing = tracemalloc.is_tracing()
        if not was_tracing:
            tracemalloc.start()
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        one_pass()
        peak = (tracemalloc.get_traced_memory()[1] - base) / 2**20
        if not was_tracing:
            tracemalloc.stop()
    res["peak_mem_mb"] = peak
    res["seconds_total"] = res["seconds_filter"] + res["seconds_smoother"]
    res["cpu_seconds_total"] = res["cpu_seconds_filter"] + res["cpu_seconds_smoother"]
    res["seconds_total_all"] = all_totals
    return res


def _check_inputs(u, y, L, M):
    u = np.ascontiguousarray(u, dtype=np.float64).reshape(-1)
    y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
    if u.shape != y.shape:
        raise ValueError(f"u and y must have the same length, got {u.shape} and {y.shape}")
    L = int(L)
    M = L if M is None else int(M)
    return u, y, L, M


# --------------------------------------------------------------------------------------------
# particles (Chopin)
# --------------------------------------------------------------------------------------------
@functools.cache
def _particles_model_class():
    import particles.distributions as dists
    import particles.state_space_models as ssm

    class NSSM41(ssm.StateSpaceModel):
        """§4.1 model; ``PX(t, xp)`` is the law of x_t given x_{t-1}, so it uses u[t-1]."""

        default_params = {
            "a": 0.9, "b": 1.0, "c": 1.0, "sigmaw": math.sqrt(0.1), "sigmav": math.sqrt(0.1),
            "nu": None, "x0_mean": 0.0, "x0_sd": 1.0, "u": None,
        }

        def PX0(self):
            return dists.Normal(loc=self.x0_mean, scale=self.x0_sd)

        def PX(self, t, xp):
            return dists.Normal(loc=self.a * xp + self.b * self.u[t - 1], scale=self.sigmaw)

        def PY(self, t, xp, x):
            loc = self.c * np.cos(x)
            if self.nu is None:
                return dists.Normal(loc=loc, scale=self.sigmav)
            return dists.Student(df=self.nu, loc=loc, scale=self.sigmav)

        def upper_bound_log_pt(self, t):
            # max_x N(x; m, sigmaw^2), needed by backward_sampling_reject
            return -0.5 * math.log(2.0 * math.pi) - math.log(self.sigmaw)

    return NSSM41


def _particles_runner(method: str):
    def run(
        u, y, params=None, L=100, seed=0, *, M=None, nu=None, x0_mean=0.0, x0_var=1.0,
        resample_threshold=1.0, measure_memory=True, repeat=1, **options,
    ) -> dict[str, Any]:
        import particles
        import particles.state_space_models as ssm

        u, y, L, M = _check_inputs(u, y, L, M)
        p = dict(TRUE_PARAMS if params is None else params)
        NSSM41 = _particles_model_class()
        data = list(y)  # Bootstrap.logG reads data[t]

        def one_pass():
            np.random.seed(seed)  # noqa: NPY002 -- particles/scipy.stats use the global state
            model = NSSM41(
                a=p["a"], b=p["b"], c=p["c"], sigmaw=math.sqrt(p["Rw"]),
                sigmav=math.sqrt(p["Rv"]), nu=nu, x0_mean=x0_mean, x0_sd=math.sqrt(x0_var), u=u,
            )
            fk = ssm.Bootstrap(ssm=model, data=data)
            pf = particles.SMC(fk=fk, N=L, store_history=True, ESSrmin=resample_threshold)
            t0 = time.perf_counter()
            c0 = time.process_time()
            pf.run()
            t1 = time.perf_counter()
            c1 = time.process_time()
            extra: dict[str, Any] = {}
            if method == "ON2":
                paths = pf.hist.backward_sampling_ON2(M)
            elif method == "mcmc":
                paths = pf.hist.backward_sampling_mcmc(M, nsteps=options.get("nsteps", 1))
            elif method == "reject":
                paths = pf.hist.backward_sampling_reject(M, max_trials=options.get("max_trials"))
            else:
                raise ValueError(method)
            smoothed_mean = np.array([np.mean(np.atleast_1d(xt)) for xt in paths])
            t2 = time.perf_counter()
            c2 = time.process_time()
            if method == "reject":
                extra["mean_acceptance_rate"] = float(np.mean(pf.hist.acc_rate))
            return {
                "peer": "particles",
                "smoother": {"ON2": "backward_sampling_ON2",
                             "mcmc": "backward_sampling_mcmc",
                             "reject": "backward_sampling_reject"}[method],
                "L": L, "M": M, "N": len(y), "noise": _noise_name(nu),
                "seconds_filter": t1 - t0, "seconds_smoother": t2 - t1,
                "cpu_seconds_filter": c1 - c0, "cpu_seconds_smoother": c2 - c1,
                "smoothed_mean": smoothed_mean, "loglik": float(pf.logLt), **extra,
            }

        return _run_measured(one_pass, measure_memory, repeat)

    run.__name__ = f"particles_ffbs_{method.lower()}"
    run.__qualname__ = run.__name__
    run.__doc__ = (
        f"particles 0.4: bootstrap SMC (store_history=True) + ParticleHistory backward sampler "
        f"'{method}' with M (default L) trajectories; smoothed_mean = mean over the M paths."
    )
    return run


particles_ffbs_on2 = _particles_runner("ON2")
particles_ffbs_mcmc = _particles_runner("mcmc")
particles_ffbs_reject = _particles_runner("reject")


# --------------------------------------------------------------------------------------------
# pyParticleEst (Nordh)
# --------------------------------------------------------------------------------------------
class _NumpyCompat(types.ModuleType):
    """pyParticleEst 1.1.4 uses ``numpy.int`` / ``numpy.float`` / ``numpy.Inf`` (removed in
    numpy 1.24 / 2.0). We hand its modules this proxy as their ``numpy`` instead of patching
    numpy itself."""

    int = int
    float = float
    Inf = np.inf

    def __init__(self):
        super().__init__("numpy")

    def __getattr__(self, name):
        return getattr(np, name)


class _ScalarSampleCompat(types.ModuleType):
    """Stands in for ``pyparticleest.filter`` (imported there as ``pf``) inside a copy of
    ``pyparticleest.smoother.bsi_full`` only.

    ``bsi_full`` does ``res[j] = pf.sample(w_norm, 1)``: a length-1 array put into one array
    element, which numpy 2.x refuses ("setting an array element with a sequence"). For that
    function ``sample(w, 1)`` returns the index as a scalar; everything else is forwarded."""

    def __init__(self, mod):
        super().__init__(mod.__name__)
        self._mod = mod

    def sample(self, w, n):
        idx = self._mod.sample(w, n)
        return idx[0] if n == 1 else idx

    def __getattr__(self, name):
        return getattr(self._mod, name)


@functools.cache
def _import_pyparticleest():
    import pyparticleest.filter as ppf
    import pyparticleest.interfaces as ppi
    import pyparticleest.smoother as pps

    shim = _NumpyCompat()
    ppf.numpy = shim
    pps.numpy = shim
    if not getattr(pps.bsi_full, "_nssm_compat", False):
        # same code object, globals in which `pf` is the scalar-sample proxy; bsi_rs, bsi_rsas
        # and perform_bsi look bsi_full up in the module, so they get this one
        g = dict(pps.__dict__, pf=_ScalarSampleCompat(ppf))
        fixed = types.FunctionType(pps.bsi_full.__code__, g, "bsi_full")
        fixed._nssm_compat = True
        pps.bsi_full = fixed
    try:  # only needed if the caller uses ParamEstimation; harmless otherwise
        import pyparticleest.paramest.paramest as ppp

        ppp.numpy = shim
    except Exception:  # pragma: no cover
        pass

    class PPEModel41(ppi.ParticleFiltering, ppi.FFBSiRS):
        """§4.1 model for pyParticleEst; particles are (L, 1) arrays."""

        def __init__(self, a, b, c, Rw, Rv, nu, x0_mean, x0_var):
            self.a, self.b, self.c, self.Rw, self.Rv, self.nu = a, b, c, Rw, Rv, nu
            self.x0_mean, self.x0_sd = x0_mean, math.sqrt(x0_var)
            self.sw = math.sqrt(Rw)
            self.logpt_max = -0.5 * math.log(2.0 * math.pi * Rw)

        def create_initial_estimate(self, N):
            return self.x0_mean + self.x0_sd * np.random.randn(N, 1)  # noqa: NPY002

        def sample_process_noise(self, particles, u, t):
            return self.sw * np.random.randn(len(particles), 1)  # noqa: NPY002

        def update(self, particles, u, t, noise):
            # must work in place: ParticleFilter.update ignores the return value
            particles *= self.a
            particles += self.b * u + noise

        def measure(self, particles, y, t):
            return _log_obs_density(float(y), particles[:, 0], self.c, self.Rv, self.nu)

        def logp_xnext(self, particles, next_part, u, t):
            d = next_part[:, 0] - self.a * particles[:, 0] - self.b * u
            return -0.5 * d * d / self.Rw + self.logpt_max

        def logp_xnext_max(self, particles, u, t):
            return self.logpt_max

    return ppf, PPEModel41


def pyparticleest_ffbsi(
    u, y, params=None, L=100, seed=0, *, M=None, nu=None, x0_mean=0.0, x0_var=1.0,
    resample_threshold=1.0, measure_memory=True, repeat=1, smoother="full",
    smoother_options=None,
) -> dict[str, Any]:
    """pyParticleEst 1.1.4: bootstrap PF (``filter='PF'``, the first measurement on x_0, as
    ``Simulator.simulate(..., meas_first=True)``) + ``perform_smoothing(M, method=smoother)``.

    ``smoother``: ``'full'`` (FFBSi, also ParamEstimation's PS-EM default), ``'rs'``, ``'mcmc'``,
    ``'rsas'``, ``'ancestor'``. smoothed_mean = mean over the M backward trajectories.
    """
    u, y, L, M = _check_inputs(u, y, L, M)
    p = dict(TRUE_PARAMS if params is None else params)
    ppf, PPEModel41 = _import_pyparticleest()

    def one_pass():
        np.random.seed(seed)  # noqa: NPY002 -- pyParticleEst uses numpy's global state
        model = PPEModel41(p["a"], p["b"], p["c"], p["Rw"], p["Rv"], nu, x0_mean, x0_var)
        t0 = time.perf_counter()
        c0 = time.process_time()
        # == Simulator.simulate(L, M, filter='PF', smoother=..., res=..., meas_first=True),
        # split so that the filter and the smoother are timed apart
        pt = ppf.ParticleTrajectory(model, L, resample_threshold, filter="PF")
        pt.measure(y[0])
        for i in range(1, len(y)):
            pt.forward(u[i - 1], y[i])
        t1 = time.perf_counter()
        c1 = time.process_time()
        straj = pt.perform_smoothing(M, method=smoother, smoother_options=smoother_options)
        smoothed_mean = straj.get_smoothed_estimates()[:, :, 0].mean(axis=1)
        t2 = time.perf_counter()
        c2 = time.process_time()
        return {
            "peer": "pyParticleEst", "smoother": smoother, "L": L, "M": M, "N": len(y),
            "noise": _noise_name(nu), "seconds_filter": t1 - t0, "seconds_smoother": t2 - t1,
            "cpu_seconds_filter": c1 - c0, "cpu_seconds_smoother": c2 - c1,
            "smoothed_mean": smoothed_mean,
        }

    return _run_measured(one_pass, measure_memory, repeat)


def pyparticleest_full(u, y, params=None, L=100, seed=0, **kw) -> dict[str, Any]:
    """pyParticleEst full FFBSi (``smoother='full'``), O(N·L·M)."""
    return pyparticleest_ffbsi(u, y, params, L, seed, smoother="full", **kw)


def pyparticleest_rs(u, y, params=None, L=100, seed=0, **kw) -> dict[str, Any]:
    """pyParticleEst rejection-sampling FFBSi (``smoother='rs'``, R = 0.1·L tries, then 'full')."""
    return pyparticleest_ffbsi(u, y, params, L, seed, smoother="rs", **kw)


def pyparticleest_mcmc(u, y, params=None, L=100, seed=0, **kw) -> dict[str, Any]:
    """pyParticleEst Metropolis-Hastings FFBSi (``smoother='mcmc'``, R = 30 MH steps)."""
    return pyparticleest_ffbsi(u, y, params, L, seed, smoother="mcmc", **kw)


# --------------------------------------------------------------------------------------------
# reference: plain numpy PF + exact marginal FFBSm (docs/method.md §3), not a peer
# --------------------------------------------------------------------------------------------
def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    m = np.max(a, axis=axis, keepdims=True)
    return np.squeeze(m, axis=axis) + np.log(np.sum(np.exp(a - m), axis=axis))


def numpy_ffbsm(
    u, y, params=None, L=100, seed=0, *, M=None, nu=None, x0_mean=0.0, x0_var=1.0,
    resample_threshold=1.0, measure_memory=True, repeat=1,
) -> dict[str, Any]:
    """Reference: numpy bootstrap PF (systematic resampling when ESS < threshold·L) + exact
    marginal FFBSm smoothing weights W_{k|N} (O(N·L²), one L×L block per step). ``M`` unused."""
    u, y, L, _ = _check_inputs(u, y, L, M)
    p = dict(TRUE_PARAMS if params is None else params)
    a, b, c, Rw, Rv = p["a"], p["b"], p["c"], p["Rw"], p["Rv"]
    N = len(y)

    def one_pass():
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        c0 = time.process_time()
        X = np.empty((N, L))
        logW = np.empty((N, L))
        x = x0_mean + math.sqrt(x0_var) * rng.standard_normal(L)
        lw = np.full(L, -math.log(L))
        loglik = 0.0
        sw = math.sqrt(Rw)
        for k in range(N):
            if k > 0:
                W = np.exp(lw)
                if 1.0 / np.sum(W * W) < resample_threshold * L:
                    cw = np.cumsum(W)
                    cw[-1] = 1.0
                    anc = np.searchsorted(cw, (rng.random() + np.arange(L)) / L)
                    x = x[anc]
                    lw = np.full(L, -math.log(L))
                x = a * x + b * u[k - 1] + sw * rng.standard_normal(L)
            lw = lw + _log_obs_density(y[k], x, c, Rv, nu)
            lse = _logsumexp(lw, 0)
            loglik += float(lse)
            lw = lw - lse
            X[k] = x
            logW[k] = lw
        t1 = time.perf_counter()
        c1 = time.process_time()
        Ws = np.exp(logW[N - 1])
        mean = np.empty(N)
        mean[N - 1] = Ws @ X[N - 1]
        for k in range(N - 2, -1, -1):
            # backward kernel K[i, j] = softmax_i(log W_k^i - (x_{k+1}^j - f_k^i)^2 / (2 Rw));
            # the x_{k+1}^j-only term cancels, leaving a rank-1 cross term (docs/method.md §7)
            f = a * X[k] + b * u[k]
            z = np.multiply.outer(f / Rw, X[k + 1])
            z += (logW[k] - (0.5 / Rw) * f * f)[:, None]
            z -= z.max(axis=0, keepdims=True)
            np.maximum(z, -700.0, out=z)  # avoid denormal exp (docs/method.md §7)
            np.exp(z, out=z)
            Ws = z @ (Ws / z.sum(axis=0))
            mean[k] = Ws @ X[k]
        t2 = time.perf_counter()
        c2 = time.process_time()
        return {
            "peer": "numpy-ffbsm", "smoother": "exact marginal FFBSm (reference)", "L": L,
            "M": L, "N": N, "noise": _noise_name(nu), "seconds_filter": t1 - t0,
            "cpu_seconds_filter": c1 - c0, "cpu_seconds_smoother": c2 - c1,
            "seconds_smoother": t2 - t1, "smoothed_mean": mean, "loglik": loglik,
        }

    return _run_measured(one_pass, measure_memory, repeat)


# --------------------------------------------------------------------------------------------
# registry
# --------------------------------------------------------------------------------------------
PEERS: dict[str, Callable[..., dict[str, Any]]] = {
    "particles-ON2": particles_ffbs_on2,
    "particles-mcmc": particles_ffbs_mcmc,
    "particles-reject": particles_ffbs_reject,
    "pyParticleEst-full": pyparticleest_full,
    "pyParticleEst-rs": pyparticleest_rs,
    "pyParticleEst-mcmc": pyparticleest_mcmc,
    "numpy-ffbsm": numpy_ffbsm,
}


def peer_versions() -> dict[str, str]:
    """Installed versions of the peers (``'missing'`` if not importable)."""
    import importlib.metadata as md

    out = {}
    for dist in ("particles", "pyParticleEst", "numpy", "scipy", "numba"):
        try:
            out[dist] = md.version(dist)
        except md.PackageNotFoundError:
            out[dist] = "missing"
    return out


def rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------
def _main(argv=None) -> None:
    ap = argparse.ArgumentParser(description="Time the peer particle smoothers on §4.1.")
    ap.add_argument("--N", type=int, default=500)
    ap.add_argument("--L", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--peers", nargs="+", default=list(PEERS), choices=list(PEERS))
    ap.add_argument("--nu", type=float, default=None,
                    help="Student-t DOF for the peers' measurement density (default: Gaussian)")
    ap.add_argument("--seed", type=int, default=0, help="data seed (the filters use seed+1)")
    ap.add_argument("--resample-threshold", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3,
                    help="timed passes per run (fastest kept; stops after 2 s of passes)")
    ap.add_argument("--no-memory", action="store_true", help="skip the tracemalloc pass")
    ap.add_argument("--no-check", action="store_true", help="skip the smoothed-mean comparison")
    ap.add_argument("--json", default=None, help="write all results (without arrays) here")
    args = ap.parse_args(argv)

    print("versions:", peer_versions())
    data = simulate_41(N=args.N, seed=args.seed)
    u, y, x_true = data["u"], data["y"], data["x"]
    print(f"N={args.N}, noise model for the peers: {_noise_name(args.nu)}, "
          f"resample when ESS < {args.resample_threshold}·L, memory: "
          f"{'off' if args.no_memory else 'tracemalloc (second pass)'}, "
          f"times: fastest of up to {args.repeat} passes")

    # warm-up: numba JIT of particles' resamplers, imports, scipy first calls
    small = simulate_41(N=20, seed=123)
    for name in args.peers:
        PEERS[name](small["u"], small["y"], TRUE_PARAMS, 20, 0, nu=args.nu,
                    measure_memory=False)

    header = (f"{'peer':<20}{'N':>5}{'L':>6}{'filter s':>10}{'smoother s':>12}{'total s':>10}"
              f"{'total cpu s':>12}{'peak MiB':>10}{'RMS vs x':>10}")
    print(header)
    print("-" * len(header))
    results = []
    for L in args.L:
        by_name = {}
        for name in args.peers:
            r = PEERS[name](u, y, TRUE_PARAMS, L, args.seed + 1, nu=args.nu,
                            resample_threshold=args.resample_threshold,
                            measure_memory=not args.no_memory, repeat=args.repeat)
            r["name"] = name
            r["rms_vs_true_x"] = rms(r["smoothed_mean"], x_true)
            by_name[name] = r
            results.append(r)
            print(f"{name:<20}{args.N:>5}{L:>6}{r['seconds_filter']:>10.3f}"
                  f"{r['seconds_smoother']:>12.3f}{r['seconds_total']:>10.3f}"
                  f"{r['cpu_seconds_total']:>12.3f}{r['peak_mem_mb']:>10.1f}"
                  f"{r['rms_vs_true_x']:>10.3f}", flush=True)
        if args.no_check:
            continue
        # noise floor: the exact-FFBSm reference with an independent random stream
        rep = numpy_ffbsm(u, y, TRUE_PARAMS, L, args.seed + 1001, nu=args.nu,
                          resample_threshold=args.resample_threshold, measure_memory=False)
        by_name["numpy-ffbsm(seed')"] = rep
        names = list(by_name)
        print(f"  pairwise RMS of the smoothed means at L={L} (particles and pyParticleEst given "
              f"the same seed draw the same random numbers in the forward pass, so they share "
              f"their filter; numpy-ffbsm vs numpy-ffbsm(seed') is the RMS between two "
              f"independent runs of one method):")
        print("  " + " " * 20 + "".join(f"{n[:13]:>14}" for n in names))
        for n1 in names:
            row = "".join(
                f"{rms(by_name[n1]['smoothed_mean'], by_name[n2]['smoothed_mean']):>14.4f}"
                for n2 in names)
            print(f"  {n1:<20}{row}")
        print(flush=True)

    if args.json:
        with open(args.json, "w") as fh:
            json.dump([{k: v for k, v in r.items() if not isinstance(v, np.ndarray)}
                       for r in results], fh, indent=1)


if __name__ == "__main__":
    _main()
