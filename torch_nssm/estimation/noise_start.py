"""The process noise a simulation model's EM starts from: raised while the filter's likelihood grows.

A simulation model's EM (``f`` and ``g`` held, :func:`.start.plan_start`) estimates the noise alone,
and where it ends depends on where the process noise starts.  Started too small for what the
model gets wrong, the bootstrap filter degenerates: its particles descend from a few, the smoothed
increments reproduce the starting ``Rw``, EM hardly moves it, the measurement noise and the degrees
of freedom carry the model error, and the log-likelihood estimate swings by thousands of units
between seeds (the suite's tanks at the scaled start: 2148, 1654, -1840, 2165; EM stopped on a
collapse with 17 % of the regular samples flagged).  Started above the likeliest scale, EM shrinks
it: the suite's other simulation models end where they ended from the scaled start.

:func:`likeliest_process_noise` scores the scaled start and ``10**k`` times it for ``k = 1, 2, ...``
(up to :data:`LADDER_TOP`) by the mean log-likelihood estimate of :data:`LADDER_REPLICAS`
particle-filter passes (run as one batch, the same random numbers at every rung so that the rungs
differ by their noise, not their draws), and stops at the first rung that scores lower.  The log
of an unbiased estimate is biased low by about half its variance, so the mean ranks a rung where
the filter degenerates below a steady one.  Walking down as well (the likeliest scale below the
scaled start) was measured and not taken: on the pendulum and the Wiener-Hammerstein plant the
smaller start took 28-46 EM iterations instead of 6-40 for the same log-likelihood, and flagged
more regular samples (``benchmarks/README.md``, "Suite of plants").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from ..core.model import SequenceBatch, StateSpaceModel
from ..inference.filtering import NumericalError, particle_filter

__all__ = ["LADDER_TOP", "LADDER_PARTICLES", "LADDER_REPLICAS", "NoiseLadder", "likeliest_process_noise"]

#: The largest power ``k`` of the factors ``10**k`` of the scaled start that the walk may reach
#: (the scaled start is 0.01 of the variance of a state's step along the simulation: at the top the
#: process noise is that variance itself).
LADDER_TOP = 2

#: Particles of each replica: the rungs' log-likelihoods differ by tens to thousands of units, a
#: steady filter's Monte Carlo error at 100 particles by a few.
LADDER_PARTICLES = 100

#: Filter passes per rung (one batch of replicated records: about the cost of one pass where the
#: per-step overhead dominates, 0.60 against 0.65 s for 1 and 4 on the pendulum's 2,000 samples).
#: The tanks' scaled start and the rungs above it over four seeds: 2148, 1654, -1840, 2165 / 2263,
#: 2236, 66, 2264 / 2248, 2248, 2208, 2246: a single pass could rank them either way.
LADDER_REPLICAS = 4


@dataclass
class NoiseLadder:
    """What the walk found: the factor taken and every rung's score (``{k: mean log-likelihood
    estimate}`` of the process noise ``10**k`` times the scaled start)."""

    factor: float
    log_likelihoods: dict[int, float]


@torch.no_grad()
def likeliest_process_noise(
    model: StateSpaceModel, data: SequenceBatch, seed: int
) -> tuple[torch.Tensor, NoiseLadder]:
    """``10**k * model.Rw`` for the ``k >= 0`` where the walk up the ladder stops (see the
    module's docstring), and the rungs it scored."""
    scores: dict[int, float] = {}

    def score(k: int) -> float:
        if k not in scores:
            scores[k] = _mean_log_likelihood(replace(model, Rw=model.Rw * 10.0**k), data, seed)
        return scores[k]

    k = 0
    while k < LADDER_TOP and score(k + 1) > score(k):
        k += 1
    return model.Rw * 10.0**k, NoiseLadder(10.0**k, dict(sorted(scores.items())))


def _mean_log_likelihood(model: StateSpaceModel, data: SequenceBatch, seed: int) -> float:
    """The mean over :data:`LADDER_REPLICAS` filter passes of the log-likelihood estimate of
    ``data``; ``-inf`` where a pass fails or is not finite."""
    R = LADDER_REPLICAS
    shared = model.Rw.dim() == 2 and model.x0_mean.dim() == 1 and model.x0_cov.dim() == 2
    if shared and not model.noise.batched:  # the replicas as one batch of copies of the records
        batches = [data.select(torch.arange(data.n_sequences, device=data.y.device).repeat(R))]
    else:  # one model per record (independent fits): one pass per replica
        batches = [data] * R
    values = []
    for r, batch in enumerate(batches):
        generator = torch.Generator(device=data.y.device).manual_seed(seed + r)
        try:
            out = particle_filter(model, batch, LADDER_PARTICLES, generator=generator)
        except NumericalError:
            return -math.inf
        values.append(out.log_likelihood.reshape(-1, data.n_sequences).sum(-1))
    value = float(torch.cat(values).mean())
    return value if math.isfinite(value) else -math.inf
