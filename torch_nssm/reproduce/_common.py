"""Shared helpers of the reproduction: output files, figures, timing, the published numbers."""

from __future__ import annotations

import csv
import json
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..estimator import RobustNSSMEstimator

#: The paper's published numbers (Liu & Yang 2019, Table 1 and Table 2).
PAPER = {
    "table1": {
        "a": (0.8998, 0.0017),
        "b": (1.0215, 0.0088),
        "c": (1.0018, 0.0062),
        "bias_norm": 0.0216,
        "bias_norm_huang": 0.0662,
        "iterations": 250,
    },
    "table2": {  # outlier fraction: (theta1, error %, theta2, error %), after 200 iterations
        0.05: (1.0014, 0.14, 1.0032, 0.32),
        0.10: (0.9953, 0.47, 0.9967, 0.33),
        0.20: (1.0050, 0.50, 0.9936, 0.64),
        0.40: (1.0074, 0.74, 0.9925, 0.75),
    },
}

#: Initial values of ``a, b, c`` in the Section 4.1 experiments (docs/method.md §7: 0.2 sticks at c -> 0,
#: c < 0 finds a mirror/wrong optimum; 0.5 with the default ``Rv_init`` reaches the truth).
PAPER_INIT = {"a": 0.5, "b": 0.5, "c": 0.5}


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _out(out_dir) -> Path:
    path = Path(out_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path


def _write_table(out: Path, name: str, header: list[str], rows: list[list], note: str = "") -> str:
    """Write ``name.md`` and ``name.csv``; return the Markdown text."""
    with open(out / f"{name}.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)

    def fmt(v):
        return f"{v:.4f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    text = "\n".join(lines) + "\n"
    if note:
        text += "\n" + note.strip() + "\n"
    (out / f"{name}.md").write_text(text)
    return text


def _write_settings(out: Path, name: str, settings: dict) -> None:
    (out / f"{name}_settings.json").write_text(json.dumps(settings, indent=2, default=str) + "\n")


def _savefig(fig, path: Path, dpi: int = 90) -> str:
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return str(path)


def _pyplot():
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "module://matplotlib_inline.backend_inline"):
        try:
            import IPython  # noqa: F401

            if IPython.get_ipython() is None:
                matplotlib.use("Agg")
        except ImportError:
            matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@contextmanager
def torch_threads(n: int = 1):
    """Run with ``n`` torch CPU threads and restore the caller's setting afterwards.

    The experiments run many small per-step kernels, for which one thread is the fastest on a
    shared CPU; the caller's thread count is theirs to keep.  Also a decorator.
    """
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _progress(iterable, desc: str, progress: bool):
    """``iterable`` with a progress bar when asked; ``tqdm.auto`` (which warns in a notebook
    without ipywidgets) is imported only then."""
    if not progress:
        return iterable
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc)


def _fit(est: RobustNSSMEstimator, u, y) -> tuple[RobustNSSMEstimator, float]:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(u, y)
    return est, time.perf_counter() - t0


def _iterations_to(history: np.ndarray, final: float, rel: float = 0.01) -> int:
    """First iteration after which the trajectory stays within ``rel`` (relative) of ``final``."""
    h = np.asarray(history, dtype=float)
    outside = np.nonzero(np.abs(h - final) > rel * max(abs(final), 1e-12))[0]
    return 0 if outside.size == 0 else int(outside[-1] + 1)


def _scalar(h) -> np.ndarray:
    h = np.asarray(h, dtype=float)
    return h.reshape(h.shape[0], -1)[:, 0]
