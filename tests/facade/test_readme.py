"""The README's Python examples run as written (with a few EM iterations), in order, in one namespace.

Only the sizes are shrunk (``n_iter``, ``n_particles``, ``max_iter_mstep``, the pendulum's
``n_samples``, the distilled start's reference fit and the simulation-error training), so the README and
the code cannot drift apart unnoticed.
"""

from __future__ import annotations

import functools
import re
import warnings
from pathlib import Path

import matplotlib
import torch

import torch_nssm

README = Path(__file__).resolve().parents[2] / "README.md"

#: (pattern, replacement): small settings for the test, everything else as written
SHRINK = [
    (r"\bn_samples=2000", "n_samples=300"),
    (r"\bn_iter=\d+", "n_iter=2"),
    (r"\bn_particles=\d+", "n_particles=20"),
    (r"\bmax_iter_mstep=\d+", "max_iter_mstep=5"),
]


def python_blocks(text: str) -> list[str]:
    """The contents of the README's ```python fenced blocks, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def shrink(code: str) -> str:
    for pattern, repl in SHRINK:
        code = re.sub(pattern, repl, code)
    return code


def test_readme_has_the_examples():
    text = README.read_text()
    blocks = python_blocks(text)
    assert len(blocks) >= 2
    assert any("plot_history(est, true_values=data.params)" in b for b in blocks)
    # the idiom for a fitted scalar without the requires-grad UserWarning is documented
    assert any("est.f_.a.item()" in b for b in blocks)
    assert all(shrink(b) != b for b in blocks if ".fit(" in b)  # every fit is shrunk


def test_readme_python_blocks_run(monkeypatch):
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torch_nssm.blocks import starts as ws

    # the distilled start's reference fit and distillation, shrunk like the fits above
    small = functools.partial(ws.distilled_start, n_iter=2, distill_iter=10)
    monkeypatch.setattr(torch_nssm, "distilled_start", small, raising=False)
    # and the networks' simulation-error training (a few LBFGS iterations over short windows)
    from torch_nssm.estimation.neural_first_stage import NeuralFirstStageOptions

    short = NeuralFirstStageOptions(horizon=20, max_horizon=20, max_iter=5)
    small_sim = functools.partial(ws.simulation_start, options=short)
    monkeypatch.setattr(torch_nssm, "simulation_start", small_sim, raising=False)
    # ... also where fit runs it (first_stage="auto" on a network)
    from torch_nssm.estimation import start as start_module

    monkeypatch.setattr(start_module, "default_options", lambda noise_name: short)
    namespace: dict = {"__name__": "readme"}
    n_threads = torch.get_num_threads()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ConvergenceWarning after 2 iterations is expected
            # ... but reading a fitted scalar the README's way must not warn about requires_grad
            warnings.filterwarnings("error", message=".*requires_grad")
            for i, block in enumerate(python_blocks(README.read_text())):
                exec(compile(shrink(block), f"README.md python block {i}", "exec"), namespace)
    finally:
        plt.close("all")
    assert torch.get_num_threads() == n_threads
    assert isinstance(namespace["a_hat"], float)
    assert hasattr(namespace["est"], "f_")  # the started estimator was fitted
    assert hasattr(namespace["refined"], "f_")  # the explicit neural recipe ran too
