"""The E-step: particle filter, particle smoother and the noise model's latent-scale expectations."""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from .. import _workspace
from .._ops import time_blocks
from ..core.model import SequenceBatch, StateSpaceModel
from ..core.noise import masked_scale
from ..inference.ffbsm import SmootherOutput
from ..inference.filtering import FilterOutput, particle_filter, sample_initial_state
from ..inference.resampling import get_resampler
from ..inference.smoothers import get_smoother
from ..inference.windows import Windows, cut

__all__ = [
    "EStepOutput",
    "EStepOptions",
    "auto_segment_length",
    "e_step",
    "segmented_e_step",
    "to_records",
    "latent_scales",
    "outlier_weights",
]


@dataclass
class EStepOutput:
    """Filter, smoother and latent-scale expectations at the current parameters.

    Attributes
    ----------
    filter : FilterOutput
    smoother : SmootherOutput
    e_lam, e_log_lam : Tensor, shape (T, B, L) or (T, B, L, p)
        ``<lam>`` and ``<log lam>`` of each particle (per output component for noise families
        with one scale per component); not used where ``y_k`` is missing.
    windows : Windows, optional
        Set by the time-parallel E-step before :func:`to_records`: everything above is then per
        window ``(T_w, W, ...)``, and ``windows.owned_data`` is what the M-step must see (the
        outputs and transitions a window does not own are masked out; the log-likelihood of each
        window is that of the steps it owns).
    """

    filter: FilterOutput
    smoother: SmootherOutput
    e_lam: Tensor
    e_log_lam: Tensor
    windows: Windows | None = None

    def select(self, index) -> EStepOutput:
        """The E-step output of the sequences ``index``."""
        if self.windows is not None:
            raise ValueError("select the records after to_records()")
        return EStepOutput(
            self.filter.select(index),
            self.smoother.select(index),
            self.e_lam[:, index],
            self.e_log_lam[:, index],
        )

    @property
    def log_likelihood(self) -> Tensor:
        """Particle estimate of the log-likelihood of each sequence, shape (B,)."""
        return self.filter.log_likelihood


@dataclass
class EStepOptions:
    """Settings of the E-step: particles, smoother (by registry name, with its options), resampling,
    and the windows of the time-parallel E-step (``segment_length=None``: one exact pass)."""

    n_particles: int = 200
    smoother: str = "ffbsm"
    smoother_options: dict[str, Any] = field(default_factory=dict)
    resampling: str = "systematic"
    ess_threshold: float = 1.0
    segment_length: int | None = None
    segment_overlap: int = 100


#: ``segment_length="auto"``: windows own this many times ``segment_overlap`` samples (the useful
#: range of docs/design.md, "Long records": the arithmetic grows as ``(S + 2 O) / S``) ...
AUTO_SEGMENT_FACTOR = 10

#: ... and a record is cut only when it holds at least this many such windows.  One record runs
#: one time step at a time, each step a fixed number of small operations whose dispatch dominates
#: below a few hundred particles; the windows run as one batch in ``S + 2 O`` steps.
AUTO_SEGMENT_MIN_WINDOWS = 10


def auto_segment_length(longest: int, overlap: int) -> int | None:
    """The time-parallel E-step's window length that ``segment_length="auto"`` gives a fit whose
    longest record has ``longest`` samples: ``AUTO_SEGMENT_FACTOR * overlap`` when the record holds
    at least :data:`AUTO_SEGMENT_MIN_WINDOWS` of them, else ``None`` (one exact pass)."""
    length = AUTO_SEGMENT_FACTOR * int(overlap)
    return length if int(longest) >= AUTO_SEGMENT_MIN_WINDOWS * length else None


def latent_scales(
    model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput, *, overwrite: bool = False
) -> tuple[Tensor, Tensor]:
    """``<lam>`` and ``<log lam>`` of every particle at every step (docs/method.md §1).

    ``overwrite``: ``<log lam>`` is written over the filter's ``noise_statistics`` (block by block,
    each after it is read), which are then no longer valid: the E-step's, which drops them
    anyway (one fresh ``(T, B, L)`` array fewer per E-step; its first-touch page faults were
    ~20,000 per E-step at the Table 1 size).
    """
    stats = filt.noise_statistics
    mine = stats is None
    if mine:  # a filter output built by hand: evaluate the noise on its particles
        stats = _noise_statistics(model, data, filt)
    e_lam = _workspace.empty(stats.shape, stats.dtype, stats.device)
    e_log = stats if overwrite or mine else _workspace.empty(stats.shape, stats.dtype, stats.device)
    rows = stats[0].numel()
    into = _writes_into(model.noise)
    for sl in time_blocks(stats.shape[0], rows):  # block by block: the temporaries stay in cache
        if into:  # the same values, written in place (no copies)
            model.noise.latent_expectations(stats, filt.scale, sl, out=(e_lam[sl], e_log[sl]))
        else:
            e_lam[sl], e_log[sl] = model.noise.latent_expectations(stats, filt.scale, sl)
    return e_lam, e_log


def _writes_into(noise) -> bool:
    """Whether ``noise.latent_expectations`` takes ``out`` (arrays of the block to write into)."""
    return "out" in inspect.signature(noise.latent_expectations).parameters


@torch.no_grad()
def _noise_statistics(model: StateSpaceModel, data: SequenceBatch, filt: FilterOutput) -> Tensor:
    T, B, L, _ = filt.particles.shape
    density = model.noise.evaluator(filt.scale, L)
    g = model.observation_steps(filt.particles, data.u)  # (T, B, L, p)
    r = filt.scale.fill_missing(data.y).unsqueeze(2) - g
    z = (filt.scale.whitener().unsqueeze(2) @ r.unsqueeze(-1)).squeeze(-1)
    for k in range(T):
        density.step(k, z[k])
    return density.statistics


def e_step(
    model: StateSpaceModel,
    data: SequenceBatch,
    options: EStepOptions,
    generator: torch.Generator | None = None,
    previous: EStepOutput | None = None,
    *,
    records: bool = True,
    recycle: EStepOutput | None = None,
) -> EStepOutput:
    """Filter, smooth and compute the latent-scale expectations at the model's parameters.

    With ``options.segment_length`` set, records longer than it are cut into overlapping windows
    that run as one batch (:func:`segmented_e_step`); ``previous``, the last E-step on the same
    data, then gives the windows their starting particles.  ``records=False`` keeps that output
    per window (what the EM loop's M-step takes; :func:`to_records` converts it).

    ``recycle``: an E-step output that nothing reads any more (the EM loop's from two iterations
    back); its arrays are overwritten with this E-step's (:mod:`torch_nssm._workspace`: fresh
    arrays cost their first-touch page faults, about a third of an iteration on a CPU).
    """
    _workspace.tune_allocator()
    if options.segment_length is not None and int(data.lengths.max()) > options.segment_length:
        estep_out = segmented_e_step(model, data, options, generator, previous)
        return to_records(estep_out, model, data) if records else estep_out
    with _workspace.recycling(_arrays(recycle)):
        filt = _filter(model, data, options, generator)
        smooth = _smooth(model, data, filt, options, generator)
        e_lam, e_log = latent_scales(model, data, filt, overwrite=True)
    filt.noise_statistics = None  # consumed: one (T, B, L) tensor less held by the output
    return EStepOutput(filt, smooth, e_lam, e_log)


def _arrays(estep_out: EStepOutput | None) -> list:
    """The large arrays of an E-step output (for :func:`e_step`'s ``recycle``)."""
    if estep_out is None or estep_out.windows is not None:
        return []
    f, s = estep_out.filter, estep_out.smoother
    return [  # (views, e.g. transition weights that are the weights' first steps, are skipped)
        f.particles, f.log_weights, f.ancestors,  # (f.noise_statistics: dropped, now e_log_lam)
        s._log_weights, s.weights, s.next_mean, s.transition_weights, estep_out.e_lam, estep_out.e_log_lam,
    ]  # fmt: skip


def segmented_e_step(
    model: StateSpaceModel,
    data: SequenceBatch,
    options: EStepOptions,
    generator: torch.Generator | None = None,
    previous: EStepOutput | None = None,
) -> EStepOutput:
    """The time-parallel E-step: overlapping windows of every record filtered and smoothed as one
    batch; each window's statistics count only the steps it owns.  Returns the per-window output
    (``windows`` set; :func:`to_records` gives the records').

    A window that starts at its record's first sample draws its first state from the model's
    prior.  Every other window starts from the one-step prediction of the sequential filter at its
    first step: the filter particles of the step before it, from ``previous`` (the last E-step on
    these data), resampled by their weights and moved by the current ``f`` and ``Rw``.  Without
    ``previous`` a filter-only pass over the windows (each from the prior, the burn-in absorbing
    it) provides them.
    """
    if model.Rw.dim() != 2:
        raise ValueError("segment_length needs one model for all records (not independent fits)")
    windows = cut(data, options.segment_length, options.segment_overlap)
    # the model with its first states' prior per window (a per-record prior, e.g. from
    # ``smooth(..., x0=...)``, taken by record)
    B = data.n_sequences
    prior = replace(
        model,
        x0_mean=model.per_sequence("x0_mean", B)[windows.record],
        x0_cov=model.per_sequence("x0_cov", B)[windows.record],
    )
    later = torch.nonzero(~windows.first).flatten()
    t, b = windows.start[later] - 1, windows.record[later]  # the step before each later window
    if previous is not None and _same_records(previous, windows, data):
        X, logW = _filter_rows(previous.filter, previous.windows, t, b)
    else:  # a filter-only pass from the prior; the step's owning window has passed its burn-in
        X, logW = _filter_rows(_filter(prior, windows.data, options, generator), windows, t, b)
    x0 = sample_initial_state(prior, windows.n_windows, options.n_particles, generator)
    if later.numel():
        x0[later] = _predicted(model, X, logW, data.u[t, b], options.n_particles, generator)
    filt = _filter(model, windows.data, options, generator, initial_particles=x0)
    smooth = _smooth(model, windows.data, filt, options, generator)
    e_lam, e_log = latent_scales(model, windows.data, filt, overwrite=True)
    filt.noise_statistics = None  # consumed
    # what the M-step sees: the steps and transitions each window owns
    owned = windows.owned()
    filt.log_likelihood = torch.where(owned, filt.log_likelihood_steps, 0.0).sum(0)
    noise_scale = model.noise.per_sequence("Rv", windows.n_windows).unsqueeze(0)
    filt.scale = masked_scale(noise_scale, windows.owned_data.obs_mask)
    smooth.residual_scatter = windows.owned_scatter(filt.particles, smooth)
    # not in place: the trajectory smoothers' transition weights may be a view of their weights
    smooth.transition_weights = smooth.transition_weights * windows.owned_data.transition_mask.unsqueeze(-1)
    return EStepOutput(filt, smooth, e_lam, e_log, windows)


def _same_records(previous: EStepOutput, windows: Windows, data: SequenceBatch) -> bool:
    """Whether ``previous`` is an E-step output on ``data`` that :func:`_filter_rows` can read."""
    if previous.windows is None:
        return tuple(previous.filter.particles.shape[:2]) == (data.n_steps, data.n_sequences)
    return previous.windows.window_of.shape == windows.window_of.shape


def _filter_rows(filt: FilterOutput, windows: Windows | None, t: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """The filter particles and log-weights at record steps ``t`` of records ``b``."""
    if windows is None:
        return filt.particles[t, b], filt.log_weights[t, b]
    w, k = windows.window_of[t, b], windows.local_of[t, b]
    return filt.particles[k, w], filt.log_weights[k, w]


def _filter(model, data, options: EStepOptions, generator, initial_particles=None) -> FilterOutput:
    return particle_filter(
        model,
        data,
        options.n_particles,
        resampling=options.resampling,
        ess_threshold=options.ess_threshold,
        generator=generator,
        initial_particles=initial_particles,
    )


@torch.no_grad()
def _predicted(model: StateSpaceModel, X: Tensor, logW: Tensor, u: Tensor, L: int, generator) -> Tensor:
    """``L`` draws of the one-step prediction from filter particles ``X`` ``(J, L', nx)`` with
    log-weights ``logW`` ``(J, L')`` and inputs ``u`` ``(J, nu)``: resample, ``f``, add ``w``."""
    idx = get_resampler("systematic")(logW, L, generator=generator)
    x = model.transition(torch.gather(X, 1, idx.unsqueeze(-1).expand(*idx.shape, X.shape[-1])), u)
    chol = torch.linalg.cholesky(model.Rw).to(x.dtype)
    noise = torch.randn(x.shape, dtype=x.dtype, device=x.device, generator=generator)
    return x + noise @ chol.transpose(-1, -2)


def to_records(estep_out: EStepOutput, model: StateSpaceModel, data: SequenceBatch) -> EStepOutput:
    """A per-window E-step output (:func:`segmented_e_step`) as the records' ``(T, B, ...)``: each
    step from the window that owns it (the filter's ancestors across a window boundary index the
    owning window's particles).  Other outputs are returned as they are."""
    windows = estep_out.windows
    if windows is None:
        return estep_out
    filt, smooth = estep_out.filter, estep_out.smoother
    g = windows.gather
    steps = torch.where(data.step_mask, g(filt.log_likelihood_steps), 0.0)
    scale = masked_scale(model.noise.per_sequence("Rv", data.n_sequences).unsqueeze(0), data.obs_mask)
    record_filter = FilterOutput(
        g(filt.particles),
        g(filt.log_weights),
        windows.to_records(filt.log_likelihood),
        None if filt._ess is None else g(filt._ess),  # (lazy: from the log-weights when read)
        scale,
        g(filt.ancestors),
        None,
        steps,
        None if filt.resampled is None else g(filt.resampled),
    )
    trans = data.transition_mask.unsqueeze(-1)
    record_smoother = SmootherOutput(
        g(smooth.log_weights),
        g(smooth.next_mean, transitions=True),
        torch.where(trans, g(smooth.transition_weights, transitions=True), 0.0),
        windows.to_records(smooth.residual_scatter),
    )
    return EStepOutput(record_filter, record_smoother, g(estep_out.e_lam), g(estep_out.e_log_lam))


def _smooth(model, data, filt, options: EStepOptions, generator) -> SmootherOutput:
    smoother = get_smoother(options.smoother)
    kwargs = dict(options.smoother_options)
    if options.smoother != "ffbsm":  # the backward samplers draw random numbers
        kwargs["generator"] = generator
    return smoother(model, data, filt, **kwargs)


def outlier_weights(
    log_weights: Tensor, e_lam: Tensor, data: SequenceBatch, *, per_component: bool = False
) -> list:
    """``E[lam_k | y]`` per record under the weights ``log_weights`` ``(T, B, L)``, as NumPy arrays
    ``(T_b,)`` (or ``(T_b, p)`` for a noise family with one latent scale per component,
    ``per_component``); NaN where nothing is observed."""
    w = torch.exp(log_weights)
    if per_component:
        ow = (w.unsqueeze(-1) * e_lam).sum(2)
        ow = torch.where(data.obs_mask, ow, torch.full_like(ow, math.nan))
    else:
        ow = (w * e_lam).sum(-1)
        ow = torch.where(data.obs_mask.any(-1), ow, torch.full_like(ow, math.nan))
    return [a.detach().cpu().numpy() for a in data.unpad(ow)]
