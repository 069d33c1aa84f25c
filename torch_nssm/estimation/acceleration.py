"""Newton-type steps for the parameters of ``f`` and ``g``: EM accelerated by the observed information.

EM converges linearly, at a rate set by the fraction of the information that the unobserved states
carry: for the manipulator it is about 0.9, so each iteration removes only ~10 % of the distance to
the maximum (docs/design.md, "Accelerated EM").  Louis' identity gives the observed information
``I = I_c - Var(score)`` from the same E-step; with the EM step ``d = theta_EM - theta`` (which
for a quadratic ``Q`` is ``I_c^{-1}`` times the score), the Newton step on the log-likelihood is::

    theta_new = theta + I^{-1} I_c d

for the free parameters of ``f`` and ``g`` together, given the noise parameters.  (Newton steps
for the noise parameters too, block by block, make the manipulator's fit unstable: their
information is noisier and often not positive definite far from the maximum.)
The noise parameters jump along their own EM path by squared extrapolation
(:class:`NoiseExtrapolation`), which needs no information: the measurement noise's from the start,
the process noise's once the Newton steps end.  (Jumping ``Rw`` while the Newton steps run moves
the maximum over ``f`` and ``g`` under those steps; benchmarks/HISTORY.md, "Accelerated EM", has
the variants measured on six manipulator records.)

The EM loop sees the acceleration through :class:`Acceleration`'s hooks (before and after the
M-step, after the E-step); :class:`NewtonAcceleration` is ``acceleration="newton"``.

Safeguards: the EM step where ``I`` is not positive definite; a step at most ``MAX_FACTOR`` times
the EM step (in the ``I_c`` norm); a step after which the log-likelihood estimate falls by more
than :func:`newton_tolerance` is undone (the EM step is taken) and ends the acceleration; and
a Newton step that points back against the previous one (that one overshot) is replaced by the EM
step and halves the cap, and once a Newton step is within one standard error (``delta' I delta <
1``: the particle noise of the information would dominate) or the cap falls below 2, the Newton
steps end and the fit goes on with EM and the noise's extrapolation (``Rw``'s too from then on).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from ..core.model import SequenceBatch, StateSpaceModel
from ..core.scales import LOG_CHOLESKY
from .estep import EStepOutput
from .snapshot import restore, snapshot
from .uncertainty import observed_information

__all__ = [
    "Acceleration",
    "NewtonAcceleration",
    "acceleration_for",
    "InformationAt",
    "NoiseExtrapolation",
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


def information_at(model: StateSpaceModel, data: SequenceBatch, estep_out: EStepOutput, generator):
    """:class:`InformationAt` ``model`` from its E-step ``estep_out`` (``None``: nothing to accelerate)."""
    unc = observed_information(
        model,
        data,
        estep_out,
        fit_Rw=False,
        fit_Rv=False,
        fit_shape=False,
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
    reason = "newton"
    if previous is not None and previous.shape == delta.shape and float(delta @ complete @ previous) < 0:
        # it points back: the last step overshot (the information's particle noise, or the noise
        # parameters' own moves): back with half the cap, and the EM step once that is below 2
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
    return NewtonStep(True, False, norm / norm_em, reason, delta)


def newton_tolerance(n_obs: int) -> float:
    """How far the log-likelihood estimate may fall after a Newton step before it is undone: a few
    units of the particle estimate's own noise (measured 1-3 at 500 samples and 1,000 particles),
    growing with the record."""
    return 5.0 + 0.005 * n_obs


# --------------------------------------------------------------------------- squared extrapolation
#: First cap of the noise extrapolation's step length ``alpha`` (1: the plain EM step); it grows by
#: :data:`SQUAREM_GROWTH` each time a step reaches it (up to :data:`SQUAREM_STEP_LIMIT`) and
#: shrinks by as much after an undone step.
SQUAREM_STEP_MAX = 4.0
SQUAREM_GROWTH = 4.0
SQUAREM_STEP_LIMIT = 16.0
#: Least cosine between two successive EM steps of a block for an extrapolation.
SQUAREM_MIN_COSINE = 0.5
#: Least EM step (root mean square over the block's log-scale coordinates) for an extrapolation,
#: in units of ``sqrt(2 / n_obs)`` (a variance's complete-data standard error on the log scale):
#: smaller steps are the particle noise of the M-step, which extrapolation would amplify.
SQUAREM_MIN_STEP = 0.5


class NoiseExtrapolation:
    """Squared extrapolation (SQUAREM, Varadhan & Roland 2008) of the noise parameters.

    The Newton steps move ``f``'s and ``g``'s parameters; the noise parameters converge at EM's
    own linear rate (on the manipulator the measurement-noise scale starts 25x too large and EM
    shrinks it by 5-15 % per iteration).  From three successive EM iterates of a block
    (``Rw`` and each parameter of the measurement noise), ``t0 -> t1 -> t2``, this jumps to::

        t' = t0 + 2 alpha r + alpha^2 v,   r = t1 - t0,  v = t2 - 2 t1 + t0,  alpha = |r| / |v|

    (``alpha = 1`` gives ``t2``; for a linear rate ``rho``, ``alpha = 1 / (1 - rho)``: the whole
    remaining distance).  Coordinates: those of each parameter's working scale
    (:meth:`~torch_nssm.core.scales.WorkingScale.extrapolation`; the noise family declares them in
    ``WORKING``): the matrix logarithms of ``Rw`` and ``Rv``, the logarithm of positive parameters
    such as the degrees of freedom (clipped to the family's bounds), so every jump is a valid
    model; the next cycle starts at the jump, whose own M-step is SQUAREM's stabilising step.  It
    needs no information: an extrapolated iteration costs an EM iteration.

    Against the particle noise: a block is extrapolated only when its two EM steps agree in
    direction (cosine >= ``SQUAREM_MIN_COSINE``) and are not smaller than ``SQUAREM_MIN_STEP``
    complete-data standard errors; ``alpha`` is capped (``SQUAREM_STEP_MAX``, growing by
    ``SQUAREM_GROWTH`` when reached, up to ``SQUAREM_STEP_LIMIT``); and the loop undoes a jump
    after which the log-likelihood estimate falls (:func:`newton_tolerance`), which shrinks the cap.
    """

    def __init__(self, n_obs: int):
        self.min_step = SQUAREM_MIN_STEP * float(np.sqrt(2.0 / max(n_obs, 1)))
        self.step_max = SQUAREM_STEP_MAX
        self.points: list[dict[str, np.ndarray]] = []

    def _coordinates(self, model: StateSpaceModel) -> dict[str, np.ndarray]:
        """The extrapolation coordinates of each noise block that has them (not a singular ``Rw``)."""
        values = {"Rw": model.Rw, **model.noise.parameters()}
        scales = {"Rw": LOG_CHOLESKY, **model.noise.WORKING}
        out = {}
        for name, value in values.items():
            a = scales[name].extrapolation(value.detach().cpu().double().numpy())
            if a is not None:
                out[name] = a
        return out

    def start(self, model: StateSpaceModel) -> None:
        """A new cycle at ``model`` (the point whose E-step runs next)."""
        self.points = [self._coordinates(model)]

    def propose(
        self, model: StateSpaceModel, rejected: bool, held: tuple[str, ...] = ()
    ) -> StateSpaceModel | None:
        """After the M-step that produced ``model``: the model with its noise extrapolated (the
        blocks named in ``held`` left at EM's iterate), or ``None`` (the EM iterate stands)."""
        if rejected or not self.points:
            self.start(model)
            return None
        self.points.append(self._coordinates(model))
        if len(self.points) < 3:
            return None
        jumps, alphas = {}, []
        for name in set.intersection(*(set(p) for p in self.points)) - set(held):
            t0, t1, t2 = (p[name] for p in self.points)
            r, r2 = t1 - t0, t2 - t1
            v = r2 - r
            nr, nr2, nv = (float(np.linalg.norm(x)) for x in (r, r2, v))
            if min(nr, nr2) / np.sqrt(r.size) < self.min_step or nv == 0.0:
                continue
            if float(np.sum(r * r2)) / (nr * nr2) < SQUAREM_MIN_COSINE:
                continue
            alpha = min(nr / nv, self.step_max)
            if alpha > 1.0:
                alphas.append(alpha)
                jumps[name] = t0 + 2 * alpha * r + alpha**2 * v
        if not jumps:
            self.points = self.points[1:]  # slide: the last two are still successive EM iterates
            return None
        if max(alphas) >= self.step_max:
            self.step_max = min(self.step_max * SQUAREM_GROWTH, SQUAREM_STEP_LIMIT)
        out = self._apply(model, jumps)
        self.start(out)
        return out

    def undone(self, model: StateSpaceModel) -> None:
        """The jump lost likelihood and the loop went back to ``model`` (EM's iterate)."""
        self.step_max = max(self.step_max / SQUAREM_GROWTH, 1.0)
        self.start(model)

    def _apply(self, model: StateSpaceModel, jumps: dict[str, np.ndarray]) -> StateSpaceModel:
        noise = model.noise

        def value(name: str, a: np.ndarray, like: torch.Tensor) -> torch.Tensor:
            if name == "Rw":
                a = LOG_CHOLESKY.from_extrapolation(a, None)
            else:
                a = noise.WORKING[name].from_extrapolation(a, noise.bounds(name))
            return torch.as_tensor(a, dtype=like.dtype, device=like.device).reshape(like.shape)

        Rw = value("Rw", jumps["Rw"], model.Rw) if "Rw" in jumps else model.Rw
        params = {n: value(n, a, getattr(noise, n)) for n, a in jumps.items() if n != "Rw"}
        return dataclasses.replace(model, Rw=Rw, noise=noise.replace(**params))


# --------------------------------------------------------------------------- the EM loop's hooks
class Acceleration:
    """The EM loop's hooks for an acceleration; this base class is plain EM (the hooks do nothing).

    The loop calls :meth:`start` after the first E-step, :meth:`before_mstep` with the E-step at the
    current parameters, :meth:`after_mstep` with the M-step's iterate (the model returned is the
    one whose E-step runs next), and :meth:`after_estep` once that E-step has run or failed (a
    model returned is the M-step's iterate to go back to: the loop runs its E-step instead).
    """

    def start(self, model: StateSpaceModel) -> None:
        """EM starts at ``model`` (its E-step has run)."""

    def before_mstep(self, model: StateSpaceModel, data: SequenceBatch, estep: EStepOutput, generator):
        """``estep`` is the E-step at ``model``, whose M-step runs next."""

    def after_mstep(self, model: StateSpaceModel, rejected: bool) -> StateSpaceModel:
        """The model whose E-step runs next, from the M-step's iterate ``model`` (``rejected``: the
        M-step undid a module's step)."""
        return model

    def after_estep(self, log_likelihood: float, estep: EStepOutput | None) -> StateSpaceModel | None:
        """After the E-step at :meth:`after_mstep`'s model (``estep``; ``None``: it failed), with
        ``log_likelihood`` the estimate before the M-step: the M-step's iterate to go back to, or
        ``None`` to keep the step."""
        return None


class NewtonAcceleration(Acceleration):
    """``acceleration="newton"``: Newton steps for ``f``'s and ``g``'s parameters (:func:`newton_step`)
    until a step is within one standard error, and squared extrapolation of the noise parameters
    (:class:`NoiseExtrapolation`: the measurement noise's from the start, the process noise's once
    the Newton steps end).  An accelerated step after which the log-likelihood estimate falls by
    more than :func:`newton_tolerance` (or whose E-step fails) is undone and ends the Newton steps.

    Parameters
    ----------
    n_obs : int
        Observed samples (the extrapolation's least step, the tolerance of a lost step).
    flags : list of bool
        ``history["accelerated"]``: one flag per iterate, appended after each M-step.
    """

    def __init__(self, n_obs: int, flags: list):
        self.newton = True  # Newton steps go on (each needs the information before the M-step)
        self.previous_step: np.ndarray | None = None  # the last Newton step taken
        self.max_factor = MAX_FACTOR  # the cap of the next Newton step
        self.extrapolation = NoiseExtrapolation(n_obs)
        self.tolerance = newton_tolerance(n_obs)
        self.flags = flags
        self.at: InformationAt | None = None
        self.em_iterate: tuple | None = None  # while an accelerated step replaces the M-step's

    def start(self, model: StateSpaceModel) -> None:
        self.extrapolation.start(model)

    def before_mstep(self, model: StateSpaceModel, data: SequenceBatch, estep: EStepOutput, generator):
        """The information at the current parameters, before the M-step moves them."""
        self.at, self.em_iterate = None, None
        if self.newton:
            try:
                self.at = information_at(model, data, estep, generator)
            except (RuntimeError, ValueError, NotImplementedError, torch.linalg.LinAlgError):
                self.at = None
            self.newton = self.at is not None

    def after_mstep(self, model: StateSpaceModel, rejected: bool) -> StateSpaceModel:
        if self.at is not None and not rejected:
            kept = snapshot(model)
            step = newton_step(self.at, model, self.previous_step, self.max_factor)
            if step.reason == "reversed":  # the last Newton step overshot: shorter ones from now
                self.max_factor /= 2.0
            self.newton = not step.done and self.max_factor >= 2.0
            if step.taken:
                self.em_iterate, self.previous_step = kept, step.delta
        # the measurement noise jumps from the start, the process noise once the Newton steps end
        # (its jumps moved their maximum)
        extrapolated = self.extrapolation.propose(model, rejected, ("Rw",) if self.newton else ())
        if extrapolated is not None:
            self.em_iterate = snapshot(model) if self.em_iterate is None else self.em_iterate
            model = extrapolated
        self.flags.append(self.em_iterate is not None)
        return model

    def after_estep(self, log_likelihood: float, estep: EStepOutput | None) -> StateSpaceModel | None:
        if self.em_iterate is None:
            return None
        if estep is not None and log_likelihood - float(estep.log_likelihood.sum()) <= self.tolerance:
            return None
        # the accelerated step lost likelihood or failed: the M-step's iterate, EM from here for f
        # and g, and for the noise shorter jumps in a new cycle
        model, self.newton = restore(self.em_iterate), False
        self.flags[-1] = False
        self.extrapolation.undone(model)
        return model


class SquaremAcceleration(NewtonAcceleration):
    """``acceleration="squarem"``: squared extrapolation of the noise parameters only
    (:class:`NoiseExtrapolation`), no Newton steps and so no information computation: an
    extrapolated iteration costs an EM iteration.  Where ``f`` and ``g`` converge fast (or are held:
    a simulation model) and the noise parameters slowly, at EM's linear rate."""

    def __init__(self, n_obs: int, flags: list):
        super().__init__(n_obs, flags)
        self.newton = False


def acceleration_for(name: str | None, *, n_obs: int, history: dict):
    """The loop's :class:`Acceleration` for ``acceleration=name`` (``None``: plain EM); ``history``
    receives the ``"accelerated"`` flags."""
    if name not in ("newton", "squarem"):
        return Acceleration()
    history["accelerated"] = []
    kind = NewtonAcceleration if name == "newton" else SquaremAcceleration
    return kind(n_obs, history["accelerated"])
