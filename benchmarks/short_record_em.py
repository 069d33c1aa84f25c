"""One EM iteration on one short record (the paper's example, N = 500) against pyParticleEst.

Ours: the E-step (MCMC backward smoother, from the previous E-step's particles as in the EM loop)
plus the M-step on its output, exact and with windows of 100 samples (``segment_length=100``,
``segment_overlap=25``), fastest of 5.  pyParticleEst 1.1.4: its filter plus its rejection-sampling
FFBSi (``peers.pyparticleest_rs``), fastest of 3 -- only its E-step, so a lower bound of its EM
iteration (its M-step, a numerical optimisation over the trajectories, comes on top).  Same record
(``peers.simulate_41``, Gaussian noise, 10 % outliers), one thread, one process.

    python benchmarks/short_record_em.py            # needs the bench extra (README_peers.md)
"""

from __future__ import annotations

import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import peers  # noqa: E402
from long_records import paper_model  # noqa: E402

from torch_nssm.core.model import SequenceBatch  # noqa: E402
from torch_nssm.estimation.estep import EStepOptions, e_step  # noqa: E402
from torch_nssm.estimation.mstep import MStepOptions, m_step  # noqa: E402


def em_iteration(batch: SequenceBatch, L: int, segment_length: int | None, repeat: int = 5) -> float:
    model = paper_model
    opts = EStepOptions(L, "mcmc", segment_length=segment_length, segment_overlap=25)
    gen = torch.Generator().manual_seed(0)
    previous = e_step(model(), batch, opts, gen, records=False)
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        est = e_step(model(), batch, opts, gen, previous, records=False)
        data = batch if est.windows is None else est.windows.owned_data
        m_step([model()], data, est, MStepOptions(fit_shape=False))
        best, previous = min(best, time.perf_counter() - t0), est
    return best


def main() -> None:
    torch.set_num_threads(1)
    N = 500
    d = peers.simulate_41(N=N, seed=0)
    t = lambda v: torch.tensor(v, dtype=torch.float64).reshape(-1, 1)  # noqa: E731
    batch = SequenceBatch.from_sequences([t(d["u"])], [t(d["y"])])
    print(
        "| N | L | pyParticleEst E-step (rs) s | ours, EM iteration s (exact / windows of 100) "
        "| ours faster by |"
    )
    print("|---|---|---|---|---|")
    for L in (100, 300):
        peer = peers.pyparticleest_rs(d["u"], d["y"], L=L, seed=0, measure_memory=False, repeat=3)[
            "seconds_total"
        ]
        exact, windows = em_iteration(batch, L, None), em_iteration(batch, L, 100)
        print(
            f"| {N} | {L} | {peer:.4f} | {exact:.4f} / {windows:.4f} "
            f"| {peer / exact:.1f}x / {peer / windows:.1f}x |"
        )


if __name__ == "__main__":
    main()
