"""Bootstrap particle filter, batched over sequences, for any measurement-noise family.

All weights stay in the log domain.  The filter keeps every time step's particles and normalised
weights (before resampling), which is what the smoothers need (docs/method.md §2-3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor, nn

from .. import _workspace
from .._ops import small_matmul
from ..core.model import SequenceBatch, StateSpaceModel
from ..core.noise import MaskedScale, masked_scale
from ..core.noise.base import step_views
from .random import Randomness, SequenceStreams
from .resampling import SystematicResampler, get_resampler, systematic

__all__ = ["FilterOutput", "particle_filter", "sample_initial_state", "NumericalError"]


class NumericalError(FloatingPointError):
    """Raised when the particle weights or the model produce non-finite values."""


@dataclass
class FilterOutput:
    """Everything the smoothers and the user need from one pass of the particle filter.

    Attributes
    ----------
    particles : Tensor, shape (T, B, L, nx)
        Particles at each time step (after propagation, before resampling).
    log_weights : Tensor, shape (T, B, L)
        Normalised log filter weights ``log W_k``.
    log_likelihood : Tensor, shape (B,)
        Particle estimate of ``log p(y_{0:T_b-1})`` of each sequence.
    ess : Tensor, shape (T, B)
        Effective sample size of the filter weights at each step.  Where the filter gives
        ``None`` (resampling at every step, where nothing in the pass needs it) it is taken from
        ``log_weights`` when first read.
    scale : MaskedScale
        The measurement-noise scale restricted to the observed components, per ``(T, B)``.
    ancestors : Tensor, shape (T, B, L), long
        ``ancestors[k, b, l]`` is the index at ``k - 1`` of the parent of particle ``l`` at ``k``
        (``ancestors[0]`` is the identity).
    noise_statistics : Tensor, shape (T, B, L, ...), optional
        What the noise model recorded of every particle's whitened residual (e.g. its squared
        norm); the E-step's latent scales reuse it.
    log_likelihood_steps : Tensor, shape (T, B), optional
        The increments ``log p(y_k | y_{<k})`` that sum to ``log_likelihood`` (zero where nothing
        is observed).
    resampled : Tensor, shape (T, B), bool, optional
        Whether the particles at ``k`` descend from a resampling at ``k`` (else ``ancestors[k]``
        is the identity and the weights carry over); ``None``: at every step ``k >= 1``
        (``ess_threshold >= 1``).  The MCMC backward sampler's proposals depend on it.
    """

    particles: Tensor
    log_weights: Tensor
    log_likelihood: Tensor
    ess: Tensor
    scale: MaskedScale
    ancestors: Tensor
    noise_statistics: Tensor | None = None
    log_likelihood_steps: Tensor | None = None
    resampled: Tensor | None = None

    def select(self, index) -> FilterOutput:
        """The filter output of the sequences ``index``."""
        return FilterOutput(
            self.particles[:, index],
            self.log_weights[:, index],
            self.log_likelihood[index],
            None if self._ess is None else self._ess[:, index],
            self.scale.select(index),
            self.ancestors[:, index],
            None if self.noise_statistics is None else self.noise_statistics[:, index],
            None if self.log_likelihood_steps is None else self.log_likelihood_steps[:, index],
            None if self.resampled is None else self.resampled[:, index],
        )


def _process_noise(
    model: StateSpaceModel, L: int, generator: Randomness, out: Tensor, lengths=None
) -> Tensor | None:
    """All process-noise draws ``w ~ N(0, Rw)`` at once into ``out`` ``(T - 1, B, L, nx)``; with one
    state, the standard normals and their scale ``sqrt(Rw)`` ``(B,)`` returned (the filter's step
    applies it in the multiply-add it makes anyway: one pass over the array fewer).

    Standard normals are drawn in single precision (2x faster than double on CPU; the 24-bit draws
    are more than enough for Monte Carlo noise) and shaped by ``chol(Rw)`` elementwise (tiny
    matrices) in the output's dtype.  With per-sequence streams, sequence ``b`` draws its
    ``lengths[b] - 1`` steps (zero noise on padded steps).
    """
    T1, B, _, nx = out.shape
    Cw = torch.linalg.cholesky(model.per_sequence("Rw", B)).to(out.dtype)
    noise_dtype = torch.float32 if out.dtype == torch.float64 else out.dtype
    if isinstance(generator, SequenceStreams):
        limits = [int(n) - 1 for n in lengths]
        if nx == 1:  # each sequence's draws through one small buffer, widened into ``out``: no
            # (T - 1, B, L) single-precision array (its first-touch page faults, ~10,000 per E-step
            # at the Table 1 size, cost more than the copies)
            generator.normal_steps_into(out, limits, noise_dtype)
            return Cw.reshape(B)
        noise = generator.steps(0, T1, limits, tuple(out.shape[2:]), noise_dtype, normal=True, fill=0.0)
        noise = noise.transpose(0, 1)
    else:
        noise = torch.randn(out.shape, dtype=noise_dtype, device=out.device, generator=generator)
    if nx == 1:  # widened (a product with a float32 (strided) operand is 4x slower: 39 vs 11 ms at
        out.copy_(noise)  # T = 1000, B = L = 100, one CPU thread)
        return Cw.reshape(B)
    torch.sum(noise.to(out.dtype).unsqueeze(-2) * Cw.unsqueeze(-3), dim=-1, out=out)  # noise @ Cw^T
    return None


def _lazy_ess(self: FilterOutput) -> Tensor:
    if self._ess is None:
        self._ess = torch.exp(-torch.logsumexp(2.0 * self.log_weights, dim=-1))  # 1 / sum W^2
    return self._ess


def _set_ess(self: FilterOutput, value: Tensor | None) -> None:
    self._ess = value


# Installed after the dataclass is made, so that ``ess`` stays its field (positional and keyword
# construction, ``dataclasses.replace``) while reading it computes it where it was not given.
FilterOutput.ess = property(_lazy_ess, _set_ess, doc="Effective sample size ``(T, B)``.")


def _frozen(module: nn.Module) -> Callable[[Tensor, Tensor], Tensor]:
    """``module`` for one filter pass: its ``frozen()`` evaluator where it has one (e.g.
    :meth:`LinearInParameters.frozen`, parameters gathered once), else the module."""
    frozen = getattr(module, "frozen", None)
    return frozen() if callable(frozen) else module


def _step_inputs(module: Callable, u: Tensor, L: int):
    """What ``module`` (a :func:`_frozen` evaluator) takes as its inputs at each step, from the time-major
    inputs ``u`` ``(T, B, nu)``: its own ``step_inputs(u)`` where it has one (e.g. the input term
    of all steps computed at once), else the inputs expanded over the ``L`` particles ``(B, L, nu)``,
    as :meth:`StateSpaceModel.transition` passes them."""
    own = getattr(module, "step_inputs", None)
    if own is not None:
        return own(u)
    return u.unsqueeze(-2).expand(*u.shape[:2], L, u.shape[-1]).unbind(0)


def sample_initial_state(model: StateSpaceModel, B: int, L: int, generator: Randomness = None) -> Tensor:
    """``L`` draws of the initial-state prior for each of ``B`` sequences, shape ``(B, L, nx)``."""
    m0 = model.per_sequence("x0_mean", B)
    C0 = torch.linalg.cholesky(model.per_sequence("x0_cov", B))
    if isinstance(generator, SequenceStreams):
        eps = generator.normal((L, m0.shape[-1]), m0.dtype)
    else:
        eps = torch.randn(B, L, m0.shape[-1], dtype=m0.dtype, device=m0.device, generator=generator)
    return m0.unsqueeze(1) + eps @ C0.transpose(-1, -2)


@torch.no_grad()
def particle_filter(
    model: StateSpaceModel,
    data: SequenceBatch,
    n_particles: int,
    *,
    resampling: str = "systematic",
    ess_threshold: float = 1.0,
    generator: Randomness = None,
    initial_particles: Tensor | None = None,
) -> FilterOutput:
    """Run the bootstrap particle filter over a batch of sequences.

    Parameters
    ----------
    model : StateSpaceModel
    data : SequenceBatch
    n_particles : int
        Number of particles ``L``.
    resampling : str
        ``"systematic"`` (default), ``"stratified"``, ``"residual"`` or ``"multinomial"``.
    ess_threshold : float
        Resample a sequence when its ESS falls below ``ess_threshold * L``; ``1.0`` resamples at
        every step, ``0.0`` never.
    generator : torch.Generator or SequenceStreams, optional
        Source of randomness (for reproducible runs); :class:`~torch_nssm.inference.random.SequenceStreams`
        draws each sequence's numbers from its own stream (independent fits).
    initial_particles : Tensor, shape (B, L, nx), optional
        Equally weighted draws of the first state of each sequence, in place of draws from the
        model's prior ``N(x0_mean, x0_cov)`` (the time-parallel E-step's windows start so).

    Returns
    -------
    FilterOutput

    Raises
    ------
    NumericalError
        If the model or the weights produce non-finite values (e.g. ``f`` or ``g`` return NaN).
    """
    resample = get_resampler(resampling)
    fast_systematic = resample is systematic
    T, B, L = data.n_steps, data.n_sequences, n_particles
    scale = masked_scale(model.noise.per_sequence("Rv", B).unsqueeze(0), data.obs_mask)
    streams = generator if isinstance(generator, SequenceStreams) else None
    lengths = data.lengths.tolist() if streams is not None else None
    x0 = _first_particles(model, B, L, generator, initial_particles)
    nx, dtype, device = x0.shape[-1], x0.dtype, x0.device
    always = ess_threshold >= 1.0
    particles, log_weights, ancestors, arange, noise_scale, resampled = _output_arrays(
        model, x0, T, generator, lengths, always
    )
    # Per-step terms (B, 1), listed and finished after the loop (:func:`_filter_output`): max logit
    # ``m``, ``s = sum exp(logit - m)``, ``||exp(logit - m)||``.  Resampling at every step, the next
    # step's systematic resampler sums ``exp(logit - m)`` and gives ``1 / s``: one operation a step fewer.
    inv_s = always and fast_systematic and T > 1
    ms: list[Tensor] = []
    ss: list[Tensor] = []  # s, or with ``inv_s`` 1 / s (from the resampler) and s at the last step
    norms: list[Tensor] = []  # ``||exp(logit - m)||``: the ESS, where not resampling at every step
    density = model.noise.evaluator(scale, L)  # the noise family's per-step log-density (and arrays)
    # The steps write into the outputs made above (``out=``, in place) and run in inference mode: no
    # autograd bookkeeping on their ~20 operations and ~10 views a step (measured 5-8 % of a one-record
    # E-step, 2,000 x 1,000 particles).  What is made inside (inference tensors: never saved for backward,
    # never modified in place outside) leaves it only stacked by :func:`_filter_output` (a new tensor).
    with torch.inference_mode():
        if fast_systematic:  # per-step random numbers drawn up front too: one uniform per row
            uniforms = _systematic_uniforms(generator, streams, lengths, T, B, dtype, device)
            resample_systematic = SystematicResampler(B, L, dtype, device)
        y0, C, p, cy, c1 = _observation_terms(scale, data.y, T, B, L)
        # Views of every step, made once (indexing a list is free, a tensor select is an operation).
        X, LW, A = particles.unbind(0), log_weights.unbind(0), ancestors.unbind(0)
        parents, parents_2d, X_2d, noise_scale, A_gather = _parent_views(particles, ancestors, noise_scale)
        f, g, U_f, U_g = _step_functions(model, data.u, L)
        log_uniform, e_buffer = _weight_arrays(B, L, dtype, device)
        log_w = log_uniform  # normalised log-weights (needed only without ``always``)
        e = log_uniform  # exp(logit - m) of the previous step (set at k = 0 before its first use)
        for k in range(T):
            x = X[k]
            if k > 0:
                if fast_systematic:  # straight into ``ancestors`` when resampling at every step
                    anc = resample_systematic(e, uniforms[k - 1], out=A[k] if always else None)
                    if inv_s:
                        ss.append(resample_systematic.inv_total)
                else:  # the schemes normalise (softmax): the stored logit - m will do
                    gen = generator if streams is None else streams.at_step([k < n for n in lengths])
                    anc = resample(LW[k - 1] if always else log_w, generator=gen)
                if always and not fast_systematic:
                    A[k].copy_(anc)
                elif not always:
                    ess_prev = (ss[k - 1] / norms[k - 1]).square_()
                    do = ess_prev < ess_threshold * L  # (B, 1)
                    resampled[k] = do[:, 0]
                    torch.where(do, anc, arange, out=A[k])
                    log_w = torch.where(do, log_uniform, log_w)
                if nx == 1:
                    torch.gather(X_2d[k - 1], 1, A[k], out=parents_2d)
                    torch.addcmul(f(parents, U_f[k - 1]), x, noise_scale, out=x)  # f + sqrt(Rw) eps
                else:
                    x.add_(f(torch.gather(X[k - 1], 1, A_gather[k]), U_f[k - 1]))
            gx = g(x, U_g[k])
            if p == 1:
                z = torch.addcmul(cy[k], gx, c1[k], value=-1.0)
            else:
                z = small_matmul(C[k].unsqueeze(-3), (y0[k].unsqueeze(-2) - gx).unsqueeze(-1)).squeeze(-1)
            logits = density.step(k, z)
            if not always:
                logits = logits.add_(log_w)
            m = torch.amax(logits, dim=-1, keepdim=True)
            ms.append(m)
            z = torch.sub(logits, m, out=LW[k])
            e = torch.exp(z, out=e_buffer)
            if not inv_s or k == T - 1:
                s = torch.sum(e, dim=-1, keepdim=True)
                ss.append(s)
            if not always:
                norms.append(torch.linalg.vector_norm(e, dim=-1, keepdim=True))
                log_w = z - torch.log(s)
    return _filter_output(
        particles, log_weights, ancestors, resampled, (ms, ss, norms), inv_s, always, density, scale, L
    )


def _first_particles(
    model: StateSpaceModel, B: int, L: int, generator: Randomness, initial_particles: Tensor | None
) -> Tensor:
    """The particles of the first step ``(B, L, nx)``: draws of the model's prior, or the caller's
    ``initial_particles`` (checked for their shape)."""
    if initial_particles is None:
        return sample_initial_state(model, B, L, generator)
    if initial_particles.shape[:2] != (B, L):
        raise ValueError(
            f"initial_particles must have shape ({B}, {L}, nx), got {tuple(initial_particles.shape)}"
        )
    return initial_particles


def _output_arrays(
    model: StateSpaceModel, x0: Tensor, T: int, generator: Randomness, lengths, always: bool
) -> tuple:
    """The filter's output arrays, preallocated: ``particles`` ``(T, B, L, nx)`` with the first step
    ``x0`` and the process noise of the others written in, ``log_weights`` ``(T, B, L)``,
    ``ancestors`` ``(T, B, L)`` (identity at the first step), and the identity ancestors ``(B, L)``,
    the noise's scale (one state: ``sqrt(Rw)`` per sequence, applied in the step; else ``None``),
    the ``resampled`` flags ``(T, B)`` (``None`` with ``always``)."""
    B, L, nx = x0.shape
    dtype, device = x0.dtype, x0.device
    # Every step writes into these preallocated outputs (``out=`` / in place): no per-step copies.
    particles = _workspace.empty((T, B, L, nx), dtype, device)
    log_weights = _workspace.empty((T, B, L), dtype, device)
    ancestors = _workspace.empty((T, B, L), torch.long, device)
    particles[0] = x0
    arange = torch.arange(L, device=device).expand(B, L)
    ancestors[0] = arange
    noise_scale = None
    if T > 1:  # x_k = f(.) + noise, added in place
        noise_scale = _process_noise(model, L, generator, particles[1:], lengths)
    resampled = None if always else torch.zeros(T, B, dtype=torch.bool, device=device)
    return particles, log_weights, ancestors, arange, noise_scale, resampled


def _observation_terms(scale: MaskedScale, y: Tensor, T: int, B: int, L: int) -> tuple:
    """The outputs with the missing ones filled ``y0``, the whitener ``C`` of every step (no masking
    per step), the number of outputs ``p`` and, for one output, the terms of
    :func:`_one_output_whitening` (else ``None``)."""
    y0, C = scale.fill_missing(y), scale.whitener()
    p = y0.shape[-1]
    cy = c1 = None
    if p == 1:  # whitened residual c (y - g) = c y - c g: one multiply-add per step
        cy, c1 = _one_output_whitening(y0, C, T, B, L)
    return y0, C, p, cy, c1


def _step_functions(model: StateSpaceModel, u: Tensor, L: int) -> tuple:
    """The transition and observation evaluators of one pass (:func:`_frozen`) and their inputs of
    every step (:func:`_step_inputs`)."""
    f, g = _frozen(model.f), _frozen(model.g)
    return f, g, _step_inputs(f, u, L), _step_inputs(g, u, L)


def _weight_arrays(B: int, L: int, dtype, device) -> tuple:
    """The uniform log-weights ``-log L`` ``(B, L)`` and the reused array of a step's
    ``exp(logit - m)`` ``(B, L)`` (read by the next step's resampling only)."""
    log_uniform = torch.full((B, L), -math.log(L), dtype=dtype, device=device)
    return log_uniform, torch.empty(B, L, dtype=dtype, device=device)


def _parent_views(particles: Tensor, ancestors: Tensor, noise_scale: Tensor | None) -> tuple:
    """What the step needs to gather the parents of its particles: with one state, a reused
    ``parents`` array ``(B, L, 1)``, its ``(B, L)`` view, the ``(B, L)`` views of every step's
    particles and the noise's scale expanded to the particles; else the gather index of every
    step ``(B, L, nx)`` (the others ``None``, the noise's scale as it is)."""
    T, B, L, nx = particles.shape
    if nx != 1:
        return None, None, None, noise_scale, ancestors.unsqueeze(-1).expand(T, B, L, nx).unbind(0)
    # the parents gathered from (B, L) rows into one reused array: 2.5-3x cheaper than gathering
    # (B, L, 1) rows with an expanded index
    parents = torch.empty(B, L, 1, dtype=particles.dtype, device=particles.device)
    if noise_scale is not None:  # expanded to the particles: addcmul's vectorised loop
        noise_scale = noise_scale.view(B, 1, 1).expand(B, L, 1).contiguous()
    return parents, parents[..., 0], particles[..., 0].unbind(0), noise_scale, None


def _filter_output(
    particles, log_weights, ancestors, resampled, terms: tuple, inv_s: bool, always: bool, density, scale,
    L: int,
) -> FilterOutput:
    """The :class:`FilterOutput` from the loop's per-step ``terms`` ``(ms, ss, norms)``, ``(B, 1)``
    each (listed, not written into views of ``(T, B, 1)`` arrays: a view costs as much as a small
    operation): the stored log-weights normalised in place, the log-likelihood and, where the loop
    needed it, the ESS."""
    ms, ss, norms = terms
    m_all, s_all = torch.stack(ms), torch.stack(ss)  # (T, B, 1)
    if inv_s:
        s_all[:-1].reciprocal_()
    log_s = torch.log(s_all)
    log_weights.sub_(log_s)
    # the ESS from the loop's terms where it needed them, else when first read (FilterOutput.ess)
    ess = None if always else (s_all / torch.stack(norms)).square_().squeeze(-1)
    steps, log_lik = _log_likelihood(m_all, log_s, density.const, scale, L, always, particles, log_weights)
    return FilterOutput(
        particles, log_weights, log_lik, ess, scale, ancestors, density.statistics, steps, resampled
    )


def _systematic_uniforms(generator, streams, lengths, T: int, B: int, dtype, device) -> tuple:
    """The systematic resampler's uniform of every step ``1..T-1``, ``(B, 1)`` each, drawn up front
    (with ``streams``: step ``k`` of sequence ``b`` is its draw ``k - 1``)."""
    if streams is not None:
        uniforms = streams.steps(0, max(T - 1, 0), [n - 1 for n in lengths], (1,), dtype)
        return uniforms.transpose(0, 1).contiguous().unbind(0)
    shape = (max(T - 1, 0), B, 1)
    return torch.rand(shape, dtype=dtype, device=device, generator=generator).unbind(0)


def _one_output_whitening(y0: Tensor, C: Tensor, T: int, B: int, L: int) -> tuple:
    """For one output: ``c y`` ``(B, 1, 1)`` and ``c`` of each step (the whitened residual
    ``c (y - g) = c y - c g`` is one multiply-add a step)."""
    c1 = C[..., 0]  # (T, B, 1)
    cy = (c1 * y0).unsqueeze(-1).unbind(0)  # (B, 1, 1) each
    c1 = step_views(c1.unsqueeze(-1))
    if c1[0] is c1[-1]:  # the same at every step: expanded to the particles once (addcmul with
        # one broadcast operand, not two, runs vectorised: 2.2x faster at 10^4 particles)
        c1 = [c1[0].expand(B, L, 1).contiguous()] * T
    return cy, c1


def _log_likelihood(m_all, log_s, const, scale, L: int, always: bool, particles, log_weights) -> tuple:
    """Each step's log-likelihood term ``(T, B)`` and their sum ``(B,)`` from the loop's terms.

    Raises
    ------
    NumericalError
        If the log-likelihood is not finite (naming the first step with non-finite values)."""
    # log p(y_k | y_<k) = const_k + log sum_l W_{k-1,l} exp(logit_kl) = const_k + m_k + log s_k
    # (- log L when the previous weights are uniform after resampling at every step)
    steps = const + (m_all + log_s).squeeze(-1)  # (T, B)
    if always:
        steps = steps - math.log(L)
    steps = torch.where(scale.n_obs > 0, steps, 0.0)  # unobserved steps add exactly nothing
    log_lik = steps.sum(0)
    if not torch.isfinite(log_lik).all():
        bad = (~torch.isfinite(log_weights).any(-1)) | (~torch.isfinite(particles).all(-1).all(-1))
        bad_steps = torch.nonzero(bad.any(-1)).flatten().tolist()
        where = f"first at time step {bad_steps[0]}" if bad_steps else "at an unknown step"
        raise NumericalError(
            "particle filter produced non-finite weights or states "
            f"({where}); check that f and g return finite values at the current parameters"
        )
    return steps, log_lik
