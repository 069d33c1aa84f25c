"""Section 4.1 of the paper: Fig. 2, the comparison with Gopaluni (Figs. 4, 6) and Table 1."""

from __future__ import annotations

import csv
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from ..datasets import make_gopaluni_example, make_huang_example, make_paper_example
from ..estimator import RobustNSSMEstimator, fit_independent
from ..models import PaperObservation, PaperTransition
from ._common import (
    PAPER,
    PAPER_INIT,
    _fit,
    _iterations_to,
    _out,
    _progress,
    _pyplot,
    _savefig,
    _scalar,
    _write_settings,
    _write_table,
    torch_threads,
)

__all__ = ["fig2", "gopaluni", "table1"]


def _paper_estimator(noise: str, n_particles: int, n_iter: int, seed: int, **kw) -> RobustNSSMEstimator:
    # the paper's algorithm: EM from the paper's initial values, without the first stage, process
    # noise estimated (the library's defaults add the first stage: docs/design.md)
    kw = {"first_stage": None, "fit_Rw": True, **kw}
    return RobustNSSMEstimator(
        PaperTransition(PAPER_INIT["a"], PAPER_INIT["b"], dtype=torch.float64),
        PaperObservation(PAPER_INIT["c"], dtype=torch.float64),
        x0_mean=[0.0],
        noise=noise,
        n_particles=n_particles,
        n_iter=n_iter,
        tol=0.0,
        random_state=seed,
        **kw,
    )



# --------------------------------------------------------------------------------------------
# Fig. 2
# --------------------------------------------------------------------------------------------


@torch_threads(1)
def fig2(fast: bool = False, out_dir="reproduction", seed: int = 0, progress: bool = True) -> dict:
    """Section 4.1, Fig. 2: parameter trajectories of the robust EM (10% outliers in [-5, 5]).

    Parameters
    ----------
    fast : bool, default=False
        Tiny setting (N = 150, 10 iterations, 50 particles) instead of the paper's scale
        (N = 500, 200 iterations; 100 particles growing to 300, last 20 iterates averaged).
    out_dir : str or Path
        Where ``fig2.png``, ``fig2.md``, ``fig2.csv`` and ``fig2_settings.json`` go.
    seed : int, default=0
        Seed of the data and of the particle methods.
    progress : bool, default=True
        Show progress bars.

    Returns
    -------
    dict
        ``estimator``, ``data``, ``table`` (Markdown), ``files``, ``settings``, ``seconds``.
    """
    out = _out(out_dir)
    s = (
        dict(n_samples=150, n_iter=10, n_particles=50, n_particles_final=None, average_last=0)
        if fast
        else dict(n_samples=500, n_iter=200, n_particles=100, n_particles_final=300, average_last=20)
    )
    settings = dict(
        experiment="fig2",
        fast=fast,
        seed=seed,
        outlier_fraction=0.1,
        outlier_range=(-5, 5),
        init=PAPER_INIT,
        smoother="ffbsm",
        noise="student-t",
        dof_init=5.0,
        **s,
    )
    data = make_paper_example(n_samples=s["n_samples"], outlier_fraction=0.1, random_state=seed)
    est = _paper_estimator(
        "student-t",
        s["n_particles"],
        s["n_iter"],
        seed,
        n_particles_final=s["n_particles_final"],
        average_last=s["average_last"],
        verbose=int(progress),
    )
    est, secs = _fit(est, data.u, data.y)
    settings["seconds"] = round(secs, 1)
    h = est.history_
    plt = _pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(11, 5.5), sharex=True)
    truth = data.params
    panels = [
        ("f.a", "a", truth["a"]),
        ("f.b", "b", truth["b"]),
        ("g.c", "c", truth["c"]),
        ("Rw", "Rw", truth["Rw"]),
        ("Rv", "Rv (Student-t scale)", None),
        ("dof", "dof r", None),
    ]
    for ax, (key, label, true) in zip(axes.ravel(), panels):
        ax.plot(_scalar(h[key]), lw=1.2)
        if true is not None:
            ax.axhline(float(np.ravel(true)[0]), ls="--", color="k", lw=0.8, label="true")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("EM iteration")
    axes[1, 2].set_yscale("log")
    fig.suptitle(f"Fig. 2: robust EM, N={s['n_samples']}, 10% outliers, init a=b=c=0.5")
    files = [_savefig(fig, out / "fig2.png")]
    final = {
        "a": est.f_.a.item(),
        "b": est.f_.b.item(),
        "c": est.g_.c.item(),
        "Rw": float(est.Rw_[0, 0]),
        "Rv": float(est.Rv_[0, 0]),
        "dof": float(est.dof_),
    }
    keys = {"a": "f.a", "b": "f.b", "c": "g.c", "Rw": "Rw", "Rv": "Rv", "dof": "dof"}
    rows = []
    for name, val in final.items():
        true = truth.get(name) if name != "Rv" else None
        true_s = "-" if true is None else float(np.ravel(true)[0])
        rows.append([name, true_s, float(val), _iterations_to(_scalar(h[keys[name]]), val)])
    note = (
        f"N = {s['n_samples']}, {s['n_iter']} EM iterations, {s['n_particles']}"
        f"{'->' + str(s['n_particles_final']) if s['n_particles_final'] else ''} particles (FFBSm), "
        f"init a=b=c=0.5, seed {seed}, {secs:.0f} s. Rv is the Student-t scale, not a variance. "
        "'iterations' = first iteration after which the estimate stays within 1% of its final value."
    )
    table = _write_table(out, "fig2", ["parameter", "true", "estimate", "iterations to 1%"], rows, note)
    files += [str(out / "fig2.md"), str(out / "fig2.csv")]
    _write_settings(out, "fig2", settings)
    return dict(
        estimator=est, data=data, final=final, table=table, files=files, settings=settings, seconds=secs
    )


# --------------------------------------------------------------------------------------------
# Figs. 4 and 6
# --------------------------------------------------------------------------------------------


@torch_threads(1)
def gopaluni(fast: bool = False, out_dir="reproduction", seed: int = 0, progress: bool = True) -> dict:
    """Figs. 4 and 6: Gaussian particle EM (Gopaluni 2008) vs robust EM, 0% and 5% outliers.

    Parameters
    ----------
    fast : bool, default=False
        Tiny setting (N = 150, 8 iterations, 50 particles) instead of N = 400, 80 iterations,
        100 particles (FFBSm), last 10 iterates averaged.
    out_dir : str or Path
        Where ``gopaluni.png``, ``gopaluni.md``/``.csv`` and the settings go.
    seed : int, default=0
    progress : bool, default=True

    Returns
    -------
    dict
        ``fits`` (``{(fraction, noise): estimator}``), ``table``, ``files``, ``settings``, ``seconds``.
    """
    out = _out(out_dir)
    s = (
        dict(n_samples=150, n_iter=8, n_particles=50, average_last=0)
        if fast
        else dict(n_samples=400, n_iter=80, n_particles=100, average_last=10)
    )
    settings = dict(
        experiment="gopaluni",
        fast=fast,
        seed=seed,
        outlier_fractions=(0.0, 0.05),
        outlier_range=(-6, 6),
        init=PAPER_INIT,
        smoother="ffbsm",
        **s,
    )
    fits, secs_all, rows = {}, {}, []
    jobs = [(frac, noise) for frac in (0.0, 0.05) for noise in ("gaussian", "student-t")]
    t_start = time.perf_counter()
    for frac, noise in _progress(jobs, "gopaluni fits", progress):
        data = make_gopaluni_example(n_samples=s["n_samples"], outlier_fraction=frac, random_state=seed)
        est = _paper_estimator(noise, s["n_particles"], s["n_iter"], seed, average_last=s["average_last"])
        est, secs = _fit(est, data.u, data.y)
        fits[(frac, noise)], secs_all[(frac, noise)] = est, secs
        a, b, c = est.f_.a.item(), est.f_.b.item(), est.g_.c.item()
        err = float(np.linalg.norm(np.array([a, b, c]) - np.array([0.9, 1.0, 1.0])))
        rows.append(
            [
                f"{frac:.0%}",
                "Gaussian (Gopaluni)" if noise == "gaussian" else "robust (Student-t)",
                a,
                b,
                c,
                float(est.Rv_[0, 0]),
                err,
                f"{secs:.1f}",
            ]
        )
    total = time.perf_counter() - t_start
    settings["seconds"] = round(total, 1)
    plt = _pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(11, 5.5), sharex=True)
    for i, frac in enumerate((0.0, 0.05)):
        for j, (key, label, true) in enumerate((("f.a", "a", 0.9), ("f.b", "b", 1.0), ("g.c", "c", 1.0))):
            ax = axes[i, j]
            for noise, style in (("gaussian", "-"), ("student-t", "-")):
                ax.plot(
                    _scalar(fits[(frac, noise)].history_[key]),
                    style,
                    label="Gaussian" if noise == "gaussian" else "robust",
                )
            ax.axhline(true, ls="--", color="k", lw=0.8)
            ax.set_title(f"{label}, {frac:.0%} outliers")
            ax.grid(alpha=0.3)
    axes[0, 0].legend()
    for ax in axes[1]:
        ax.set_xlabel("EM iteration")
    fig.suptitle(f"Figs. 4/6: Gaussian vs robust EM, N={s['n_samples']}")
    files = [_savefig(fig, out / "gopaluni.png")]
    note = (
        f"N = {s['n_samples']}, {s['n_iter']} EM iterations, {s['n_particles']} particles (FFBSm), "
        f"init a=b=c=0.5, seed {seed}. error = ||(a,b,c) - (0.9,1,1)||. "
        "Rv: variance (Gaussian) or Student-t scale (robust)."
    )
    table = _write_table(
        out, "gopaluni", ["outliers", "method", "a", "b", "c", "Rv", "error", "seconds"], rows, note
    )
    files += [str(out / "gopaluni.md"), str(out / "gopaluni.csv")]
    _write_settings(out, "gopaluni", settings)
    return dict(fits=fits, table=table, files=files, settings=settings, seconds=total)


# --------------------------------------------------------------------------------------------
# Table 1
# --------------------------------------------------------------------------------------------


@torch_threads(1)
def table1(
    fast: bool = False,
    out_dir="reproduction",
    seed: int = 0,
    progress: bool = True,
    n_sets: int | None = None,
    n_iter: int | None = None,
) -> dict:
    """Table 1: Monte Carlo study with Cauchy measurement noise ``St(0, 0.01, 1)``, N = 1000.

    All data sets are fitted in one batched pass (:func:`~torch_nssm.fit_independent`).
    The reported estimate of each data set is the average of its last ``n_avg`` EM iterates
    (Polyak-Ruppert averaging, computed from ``history_``; the last iterate is reported too).

    Parameters
    ----------
    fast : bool, default=False
        Tiny setting (4 data sets, N = 300, 6 iterations, 50 particles) instead of the paper's
        100 data sets, N = 1000, 250 iterations, with 100 particles, the MCMC smoother and the last
        50 iterates averaged.  The bias norm after 50 iterations (last 10 averaged) is reported too.
    out_dir : str or Path
    seed : int, default=0
        Data set ``i`` uses seed ``seed + i`` (data and particles).
    progress : bool, default=True
    n_sets, n_iter : int, optional
        Override the number of data sets / EM iterations.

    Returns
    -------
    dict
        ``estimates`` (``(n_sets, 3)``, averaged iterates), ``last`` (last iterates), ``mean``,
        ``std``, ``standard_errors`` (``(n_sets, 3)``: each fit's observed-information standard errors
        of its last iterate), ``bias_norm``, ``bias_norm_last``; ``bias_norm_50`` and ``std_50`` (after 50
        iterations, the last 10 averaged); ``bias_norm_path`` (after each iteration, the last 10
        iterates averaged) and ``iterations_to_target`` (the iteration from which it stays
        <= 0.010, None if it ends above); ``table``, ``files``, ``settings``, ``seconds``.
    """
    out = _out(out_dir)
    s, settings = _table1_settings(fast, seed, n_sets, n_iter)
    datas = [make_huang_example(n_samples=s["n_samples"], random_state=seed + i) for i in range(s["n_sets"])]
    proto = _paper_estimator(
        "student-t", s["n_particles"], s["n_iter"], seed, smoother="mcmc", verbose=int(progress)
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits = fit_independent(proto, [d.u for d in datas], [d.y for d in datas], show_progress=progress)
    secs = time.perf_counter() - t0
    settings["seconds"] = round(secs, 1)
    keys = ("f.a", "f.b", "g.c")
    hist = np.stack([np.stack([_scalar(e.history_[k]) for k in keys], 1) for e in fits])  # (B, K+1, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        se = np.array([[float(e.standard_errors_[k]) for k in keys] for e in fits])  # docs/uncertainty.md
    last = hist[:, -1]
    est = hist[:, -s["n_avg"] :].mean(1)
    theta = np.array([0.9, 1.0, 1.0])
    mean, std = est.mean(0), est.std(0, ddof=1) if len(est) > 1 else np.zeros(3)
    bias_norm = float(np.linalg.norm(theta - mean))
    bias_norm_last = float(np.linalg.norm(theta - last.mean(0)))
    window = 10
    bn_path, k50, bias_norm_50, std_50, iters_to_target = _bias_norm_path(hist, theta, window)
    p = PAPER["table1"]
    rows = _table1_rows(p, mean, std, last, se, bias_norm, bias_norm_last)
    note = _table1_note(s, seed, secs, window, iters_to_target, k50, bias_norm_50, std_50, bn_path[-1])
    header = [
        "parameter", "true", "paper (250 it.)", f"ours (avg last {s['n_avg']})", "ours (last iterate)",
        "mean s.e. (ours)",
    ]
    table = _write_table(out, "table1", header, rows, note)
    _write_table1_estimates(out / "table1_estimates.csv", seed, est, last)
    fig = _table1_figure(est, mean, std, bn_path, p["bias_norm"], window, s)
    files = [
        _savefig(fig, out / "table1.png"),
        str(out / "table1.md"),
        str(out / "table1.csv"),
        str(out / "table1_estimates.csv"),
    ]
    _write_settings(out, "table1", settings)
    return dict(
        fits=fits,
        estimates=est,
        last=last,
        mean=mean,
        std=std,
        standard_errors=se,
        bias_norm=bias_norm,
        bias_norm_last=bias_norm_last,
        bias_norm_path=bn_path,
        bias_norm_50=bias_norm_50,
        std_50=std_50,
        iterations_to_target=iters_to_target,
        table=table,
        files=files,
        settings=settings,
        seconds=secs,
    )


def _table1_settings(fast: bool, seed: int, n_sets: int | None, n_iter: int | None) -> tuple[dict, dict]:
    """Table 1's sizes (``n_sets``, ``n_samples``, ``n_iter``, ``n_particles``, ``n_avg``) and the
    settings written beside its results."""
    s = (
        dict(n_sets=4, n_samples=300, n_iter=6, n_particles=50, n_avg=3)
        if fast
        else dict(n_sets=100, n_samples=1000, n_iter=250, n_particles=100, n_avg=50)
    )
    if n_sets is not None:
        s["n_sets"] = int(n_sets)
    if n_iter is not None:
        s["n_iter"] = int(n_iter)
        s["n_avg"] = min(s["n_avg"], max(1, s["n_iter"] // 4))
    settings = dict(
        experiment="table1",
        fast=fast,
        seed=seed,
        noise_true="St(0, 0.01, 1) (Cauchy)",
        init=PAPER_INIT,
        smoother="mcmc",
        batched=True,
        **s,
    )
    return s, settings


def _write_table1_estimates(path: Path, seed: int, est: np.ndarray, last: np.ndarray) -> None:
    """Each data set's averaged and last estimates of ``(a, b, c)`` as a CSV file, one row a seed."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["seed", "a", "b", "c", "a_last", "b_last", "c_last"])
        for i in range(len(est)):
            w.writerow([seed + i, *est[i], *last[i]])


def _bias_norm_path(hist: np.ndarray, theta: np.ndarray, window: int) -> tuple:
    """The bias norm after each iteration ``k`` of the estimates averaged over iterates
    ``max(1, k - window + 1)..k`` (index 0 = the initial values; a 50-iterate window would drag the
    early iterates along); the iteration ``k50`` of the issue's budget (50 iterations, the last 10
    averaged), the bias norm and the s.d. there, and the iteration from which the bias norm stays
    at most 0.010 (``None`` if it does not end there)."""

    def averaged(k: int) -> np.ndarray:
        return hist[:, max(1, k - window + 1) : k + 1].mean(1) if k > 0 else hist[:, 0]

    bn_path = np.array([np.linalg.norm(theta - averaged(k).mean(0)) for k in range(hist.shape[1])])
    k50 = min(50, hist.shape[1] - 1)
    bias_norm_50 = float(bn_path[k50])
    std_50 = averaged(k50).std(0, ddof=1) if len(hist) > 1 else np.zeros(3)
    below = np.nonzero(bn_path > 0.010)[0]
    iters_to_target = None if bn_path[-1] > 0.010 else int(below[-1] + 1 if below.size else 0)
    return bn_path, k50, bias_norm_50, std_50, iters_to_target


def _table1_note(
    s: dict, seed: int, secs: float, window: int, iters_to_target, k50, bias_norm_50, std_50,
    final_bias_norm: float,
):
    """The note under Table 1: the settings and how the bias norm evolved (``iters_to_target``
    ``None``: the bias norm does not end at or below 0.010)."""
    if iters_to_target is None:
        target = (
            f"Bias norm <= 0.010 (last {window} iterates averaged) not reached in {s['n_iter']} "
            f"iterations: it ends at {final_bias_norm:.4f}. "
        )
    else:
        target = f"Bias norm <= 0.010 (last {window} iterates averaged) from iteration {iters_to_target} on. "
    return (
        f"{s['n_sets']} data sets (seeds {seed}..{seed + s['n_sets'] - 1}), N = {s['n_samples']}, "
        f"{s['n_iter']} EM iterations (paper: 250), {s['n_particles']} particles, MCMC smoother, "
        f"init a=b=c=0.5, batched fit_independent, {secs:.0f} s. 'ours' = mean of the last "
        f"{s['n_avg']} iterates of each fit; bias norm = ||theta - mean(theta_hat)||. "
        f"{target}After {k50} iterations "
        f"(last 10 averaged): bias norm {bias_norm_50:.4f}, s.d. "
        f"{', '.join(f'{v:.4f}' for v in std_50)} (a, b, c). 'mean s.e.' = the mean over the data sets of "
        "each fit's observed-information standard error (docs/uncertainty.md), to set beside the "
        "s.d. of the estimates over the data sets."
    )


def _table1_rows(p: dict, mean, std, last, se, bias_norm: float, bias_norm_last: float) -> list:
    """Table 1's rows: each parameter beside the paper's, and the bias norm."""
    rows = [
        [
            name,
            true,
            f"{p[name][0]:.4f} ± {p[name][1]:.4f}",
            f"{mean[i]:.4f} ± {std[i]:.4f}",
            f"{last[:, i].mean():.4f} ± {last[:, i].std(ddof=1) if len(last) > 1 else 0.0:.4f}",
            f"{se[:, i].mean():.4f}",
        ]
        for i, (name, true) in enumerate((("a", 0.9), ("b", 1.0), ("c", 1.0)))
    ]
    rows.append(
        [
            "bias norm",
            0.0,
            f"{p['bias_norm']:.4f} (Huang: {p['bias_norm_huang']:.4f})",
            f"{bias_norm:.4f}",
            f"{bias_norm_last:.4f}",
            "",
        ]
    )
    return rows


def _table1_figure(est, mean, std, bn_path, paper_bias_norm: float, window: int, s: dict):
    """Histograms of the estimates and the bias norm along the iterations."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(13, 3))
    for i, (name, true) in enumerate((("a", 0.9), ("b", 1.0), ("c", 1.0))):
        axes[i].hist(est[:, i], bins=min(20, max(3, len(est) // 4)))
        axes[i].axvline(true, color="k", ls="--")
        axes[i].set_title(f"{name}: {mean[i]:.4f} ± {std[i]:.4f}")
    axes[3].semilogy(bn_path)
    axes[3].axhline(paper_bias_norm, color="r", ls="--", lw=0.8, label="paper 0.0216")
    axes[3].axhline(0.010, color="g", ls=":", lw=0.8, label="target 0.010")
    axes[3].set_xlabel("EM iteration")
    axes[3].set_title(f"bias norm (last {window} iterates averaged)", fontsize=9)
    axes[3].legend(fontsize=7)
    fig.suptitle(f"Table 1: {s['n_sets']} Monte Carlo runs, Cauchy noise, N={s['n_samples']}")
    fig.tight_layout()
    return fig
