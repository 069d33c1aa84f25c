"""Newton-type steps for the parameters of ``f`` and ``g``: EM accelerated by the observed information.

EM converges linearly, at a rate set by the fraction of the information that the unobserved states
carry: for the manipulator it is about 0.9, so each iteration removes only ~10 % of the distance to
the maximum (docs/design.md, "Accelerated EM").  Louis' identity gives the observed information
``I = I_c - Var(score)`` from the same E-step; with the EM step ``d = theta_EM - theta`` (which
for a quadratic ``Q`` is ``I_c^{-1}`` times the score), the Newton step on the log-likelihood is::

    theta_new = theta + I^{-1} I_c d

for the free parameters of ``f`` and ``g`` together, given the noise parameters, whose own M-step
updates stand.  (Newton steps for the noise parameters too, block by block, were tried on the
manipulator and made the fit unstable: their information is noisier and often not positive
definite far from the maximum.)

Safeguards: the EM step where ``I`` is not positive definite; a step at most ``MAX_FACTOR`` times
the EM step (in the ``I_c`` norm); a step after which the log-likelihood estimate falls by more
than :func:`newton_tolerance` is undone (the EM step is taken) and ends the acceleration; and
a Newton step that points back against the previous one (that one overshot) is replaced by the EM
step and halves the cap, and once a Newton step is within one standard error (``delta' I delta <
1``: the particle noise of the information would dominate) or the cap falls below 2, the
acceleration ends and the fit goes on with plain EM.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..core.model import SequenceBatch, StateSpaceModel
from .estep import EStepOutput
from .uncertainty import observed_information

__all__ = [
    "InformationAt",
    "NewtonStep",
    "information_at",
    "newton_step",
    "newton_tolerance",
    "MAX_FACTOR",
    "TRAJECTORIES",
]

#: Largest Newton step, as a multiple of the EM step (in the ``I_c`` norm): the acceleration a
#: missing-information fraction of 0.9 calls for.
MAX_FACTOR = 10.0

#: Backward-simulated trajectories for the score variance of each accelerated iteration.
TRAJECTORIES = 300


@dataclass
class NewtonStep:
    """What an accelerated iteration did.

    Attributes
    ----------
    taken : bool
        Whether the Newton step replaced the EM step.
    done : bool
        The step was within one standard error (or the parameters changed): acceleration ends
        for this fit.
    factor : float
        Length of the step taken over the EM step's (``I_c`` norm; 1 for an EM step).
    reason : str
    delta : ndarray or None
        The step taken.
    """

    taken: bool
    done: bool
    factor: float
    reason: str
    delta: np.ndarray | None = None


@dataclass
class InformationAt:
    """The observed and complete information of ``f``'s and ``g``'s free parameters (noise held)
    at the parameters before an M-step, and those parameters (flattened, ``f`` then ``g``)."""

    information: np.ndarray
    complete: np.ndarray
    theta: np.ndarray
    excluded: list[str]


def _free(model: StateSpaceModel, excluded: list[str]) -> list[torch.Tensor]:
    """The free module parameters in the information's order (modules in ``excluded`` left out)."""
    return [
        p
        for label, module in (("f", model.f), ("g", model.g))
        if label not in excluded
        for p in module.parameters()
        if p.requires_grad
    ]


def information_at(model: StateSpaceModel, data: SequenceBatch, est: EStepOutput, generator):
    """:class:`InformationAt` ``model`` from its E-step ``est`` (``None``: nothing to accelerate)."""
    unc = observed_information(
        model,
        data,
        est,
        fit_Rw=False,
        fit_Rv=False,
        fit_dof=False,
        n_trajectories=TRAJECTORIES,
        generator=generator,
    )
    with torch.no_grad():
        params = _free(model, unc.excluded)
        theta = np.concatenate([p.detach().cpu().numpy().reshape(-1) for p in params]) if params else None
    if theta is None or theta.shape[0] != unc.information.shape[0]:
        return None
    return InformationAt(unc.information, unc.complete_information, theta.astype(float), unc.excluded)


def newton_step(
    at: InformationAt,
    new: StateSpaceModel,
    previous: np.ndarray | None = None,
    max_factor: float = MAX_FACTOR,
) -> NewtonStep:
    """Replace the M-step's module parameters in ``new`` (in place) by the Newton step from the
    parameters ``at`` describes (``previous``: the last Newton step taken; ``max_factor``: the
    cap of the step over the EM step); returns what was done."""
    params = _free(new, at.excluded)
    theta_em = np.concatenate([p.detach().cpu().numpy().reshape(-1) for p in params]).astype(float)
    if theta_em.shape != at.theta.shape:
        return NewtonStep(False, True, 1.0, "the parameters changed shape")
    info, complete, d = at.information, at.complete, theta_em - at.theta
    try:
        eig = np.linalg.eigvalsh(info)
        if not np.all(np.isfinite(info)) or eig.min() <= 1e-12 * max(abs(eig.max()), 1e-300):
            return NewtonStep(False, False, 1.0, "observed information not positive definite")
        delta = np.linalg.solve(info, complete @ d)
    except np.linalg.LinAlgError:
        return NewtonStep(False, False, 1.0, "observed information singular")
    if float(delta @ info @ delta) < 1.0:  # within one standard error: EM from here
        return NewtonStep(False, True, 1.0, "within one standard error")
    if previous is not None and previous.shape == delta.shape and float(delta @ complete @ previous) < 0:
        # it points back: the last step overshot (the information's particle noise); the EM step
        return NewtonStep(False, False, 1.0, "reversed")
    norm_em = float(np.sqrt(max(d @ complete @ d, 0.0)))
    norm = float(np.sqrt(max(delta @ complete @ delta, 0.0)))
    if not np.isfinite(norm) or norm_em == 0.0:
        return NewtonStep(False, False, 1.0, "no EM step to scale")
    if norm > max_factor * norm_em:
        delta, norm = delta * (max_factor * norm_em / norm), max_factor * norm_em
    value, start = at.theta + delta, 0
    with torch.no_grad():
        for p in params:
            n = p.numel()
            entries = torch.as_tensor(value[start : start + n], dtype=p.dtype, device=p.device)
            p.copy_(entries.reshape(p.shape))
            start += n
    return NewtonStep(True, False, norm / norm_em, "newton", delta)


def newton_tolerance(n_obs: int) -> float:
    """How far the log-likelihood estimate may fall after a Newton step before it is undone: a few
    units of the particle estimate's own noise (measured 1-3 at 500 samples and 1,000 particles),
    growing with the record."""
    return 5.0 + 0.005 * n_obs
