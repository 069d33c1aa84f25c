"""Computing standard errors raises no ``DeprecationWarning``.

The Jacobian of a module that is not linear in its parameters was computed by forward-mode
autograd (``torch.func.jacfwd``), whose first use in a process loads torch's jvp decompositions
through the deprecated ``torch.jit.script`` (18 warnings).  It runs in a fresh process: the warnings
come once per process.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

CODE = """
import json, warnings
import torch
from torch import nn
from torch_nssm import RobustNSSMEstimator
from torch_nssm.datasets import make_paper_example
from torch_nssm.datasets.paper import PaperTransition

class CosObservation(nn.Module):  # c cos(x), not a LinearInParameters: its Jacobian by autograd
    def __init__(self):
        super().__init__()
        self.c = nn.Parameter(torch.tensor(1.0, dtype=torch.float64))
    def forward(self, x, u):
        return self.c * torch.cos(x)

d = make_paper_example(n_samples=80, random_state=0)
est = RobustNSSMEstimator(PaperTransition(0.9, 1.0), CosObservation(), x0_mean=[0.0], n_particles=30,
                          n_iter=2, random_state=0)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    est.fit(d.u, d.y)
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    se = est.standard_errors_
found = [str(w.message)[:100] for w in caught if issubclass(w.category, DeprecationWarning)]
print(json.dumps([found, sorted(se)]))
"""


def test_standard_errors_raise_no_deprecation_warning():
    res = subprocess.run(
        [sys.executable, "-W", "error::DeprecationWarning", "-c", CODE],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    found, keys = json.loads(res.stdout.strip().splitlines()[-1])
    assert "g.c" in keys  # g's Jacobian by autograd was computed
    assert found == []
