"""Does the fitted process noise carry model error?  A check the fit's warnings can call.

EM can explain what ``f`` gets wrong by a large process noise: the smoothed states then follow the
data one step at a time, the log-likelihood is fine, and the noise-free simulation (``predict``,
``score``) is poor.  The fitted model itself says whether that happened: simulated *with* its
process noise, the model predicts how far the outputs wander from its noise-free simulation.  If
``Rw`` were a real disturbance, the record's own free-run errors (the measured outputs minus the
noise-free simulation) would be about that large (plus the measurement noise); if ``Rw`` carries
model error, the predicted wander is far larger than the errors the simulation actually makes.

:func:`process_noise_check` compares the two (robust scales, so outliers in ``y`` do not count):
``ratio = predicted wander / free-run errors``, about 1 or less for a consistent model, and
returns a warning message when it exceeds ``threshold`` (default 2).  On the suite's pendulum an
``MLPTransition`` left near its linear start had ``Rw`` of 0.11-0.13 on the angular rate (true
4e-4): a ratio far above the threshold; the physical model and a network trained by simulation
error stay below 1 (``tests/estimation/test_process_noise_check.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._stats import MAD_TO_STD
from ..core.model import SequenceBatch, StateSpaceModel

__all__ = ["ProcessNoiseCheck", "process_noise_check", "WANDER_RATIO"]

#: The check warns when the process noise's predicted wander exceeds this many times the free-run
#: errors' robust scale.
WANDER_RATIO = 2.0


@dataclass
class ProcessNoiseCheck:
    """The outcome of :func:`process_noise_check`.

    Attributes
    ----------
    wander : float
        Robust scale (1.4826 MAD) of the outputs' deviations from the noise-free simulation that the
        fitted process noise alone causes (Monte Carlo, no measurement noise).
    free_run_error : float
        Robust scale of the records' free-run output errors ``y - noise-free simulation``.
    ratio : float
        ``wander / free_run_error`` (about 1 or less when ``Rw`` describes real disturbances).
    absorbs : bool
        Whether ``ratio`` exceeds the threshold.
    message : str or None
        The warning's words when ``absorbs`` (else ``None``).
    """

    wander: float
    free_run_error: float
    ratio: float
    absorbs: bool
    message: str | None = None


def _robust_scale(values: Tensor) -> float:
    v = values.reshape(-1)
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return math.nan
    return float(MAD_TO_STD * v.abs().median())


@torch.no_grad()
def process_noise_check(
    model: StateSpaceModel,
    data: SequenceBatch,
    *,
    threshold: float = WANDER_RATIO,
    n_trajectories: int = 32,
    max_samples: int = 5000,
    generator: torch.Generator | None = None,
) -> ProcessNoiseCheck:
    """Compare the output wander the fitted process noise predicts with the free run's errors.

    Parameters
    ----------
    model : StateSpaceModel
        The fitted model (one shared model for all records).
    data : SequenceBatch
        The training records.
    threshold : float
        ``ratio`` above which the process noise is said to carry model error.
    n_trajectories : int
        Monte Carlo trajectories per record.
    max_samples : int
        Only the first ``max_samples`` samples of each record are simulated (the wander settles
        within a few time constants).
    generator : torch.Generator, optional
        Random stream of the process noise (on the model's device).

    Returns
    -------
    ProcessNoiseCheck
    """
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0, got {threshold!r}")
    if int(n_trajectories) < 2:
        raise ValueError(f"n_trajectories must be >= 2, got {n_trajectories!r}")
    T = min(data.n_steps, int(max_samples))
    u, y = data.u[:T], data.y[:T]
    B, K, nx = data.n_sequences, int(n_trajectories), model.state_dim
    x0 = model.per_sequence("x0_mean", B)
    Rw = model.per_sequence("Rw", B)
    lam, V = torch.linalg.eigh(Rw)
    L = V * lam.clamp_min(0).sqrt().unsqueeze(-2)  # (B, nx, nx): L L^T = Rw, also for a singular Rw
    clean = x0.unsqueeze(1)  # (B, 1, nx): the noise-free simulation
    noisy = x0.unsqueeze(1).expand(B, K, nx).clone()  # (B, K, nx): with process noise
    y_clean, y_noisy = [], []
    for k in range(T):
        y_clean.append(model.observation(clean, u[k]))
        y_noisy.append(model.observation(noisy, u[k]))
        if k + 1 < T:
            clean = model.transition(clean, u[k])
            w = torch.randn(B, K, nx, dtype=noisy.dtype, device=noisy.device, generator=generator)
            noisy = model.transition(noisy, u[k]) + w @ L.transpose(-1, -2)
    y_clean = torch.stack(y_clean)  # (T, B, 1, p)
    y_noisy = torch.stack(y_noisy)  # (T, B, K, p)
    inside = data.step_mask[:T].unsqueeze(-1).unsqueeze(-1)  # (T, B, 1, 1)
    wander = _robust_scale(torch.where(inside, y_noisy - y_clean, torch.full_like(y_noisy, math.nan)))
    observed = data.obs_mask[:T]
    errors = torch.where(observed, y - y_clean[:, :, 0], torch.full_like(y, math.nan))
    free = _robust_scale(errors)
    ratio = wander / free if free > 0 else (math.inf if wander > 0 else math.nan)
    absorbs = bool(math.isfinite(wander) and ratio > threshold)
    message = None
    if absorbs:
        diag = np.array2string(torch.diagonal(model.Rw, dim1=-2, dim2=-1).cpu().numpy(), precision=3)
        message = (
            f"the fitted process noise (Rw diagonal {diag}) would move the outputs {wander:.3g} (robust "
            f"s.d.) away from the noise-free simulation, {ratio:.1f} times the simulation's actual errors on "
            f"the training data ({free:.3g}): the process noise carries model error (what f gets wrong one "
            "step at a time), not random disturbances of the plant, and the noise-free simulation "
            "(predict, score) is what f learned. Start f from a simulation-error fit (a network: "
            "torch_nssm.estimation.neural_first_stage), or hold the process noise small for a simulation "
            "model (fit_Rw=False with a small Rw_init)"
        )
    return ProcessNoiseCheck(wander, free, ratio, absorbs, message)
