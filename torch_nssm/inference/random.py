"""Random numbers of the particle methods: one generator for a batch, or one stream per sequence.

The filter, the smoothers and the M-step's minibatches take ``generator``: a ``torch.Generator``
(or ``None``), whose draws are made for the whole batch at once (single fits, ``smooth``,
``simulate``: unchanged), or :class:`SequenceStreams`, one ``torch.Generator`` per sequence, for
independent fits (:func:`torch_nssm.fit_independent`).  With streams, every draw is made per
sequence and stacked over the batch, and each sequence draws the same numbers in the same order
whatever it is batched with, so its fit depends on its own seed alone, not on the other data sets
of its batch, the number of chunks or workers, nor on when the others converge (docs/design.md,
"Many fits on many machines").  The rules that make the draw count batch-free:

* a sequence draws only for its own time steps (a padded batch has steps past its end: those get
  a constant, not a draw);
* a pass over many steps draws a sequence's block for all of its steps of that block in one call,
  and backward passes draw their rows in reverse time order, so that how the steps are grouped
  into blocks (which depends on the batch size) does not change which number goes to which step
  (``torch.rand`` is sequential: ``rand(a + b)`` equals ``rand(a)`` followed by ``rand(b)``);
* adaptive loops (rejection sampling) draw their whole budget up front.

The per-sequence calls cost one ``torch.rand``/``randn`` call per sequence and site instead of
one per site; ``benchmarks/parallel.py --overhead`` measures it on the Table 1 workload
(figures in ``benchmarks/HISTORY.md``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Union

import numpy as np
import torch
from torch import Tensor

__all__ = ["SequenceStreams", "Randomness", "sequence_seed", "sequence_seeds", "uniform", "multinomial"]

#: Value of the uniforms of padded time steps (never used: those steps are masked).
_PAD_UNIFORM = 0.5


class SequenceStreams:
    """One random stream per sequence of a batch: a ``torch.Generator`` each.

    Parameters
    ----------
    seeds : sequence of int
        One seed per sequence (e.g. :func:`sequence_seeds`).
    device : str or torch.device
        Where the particle methods' numbers are drawn.

    Notes
    -----
    :meth:`select` returns streams of some of the sequences that *share* the generators' states:
    the EM loop selects the data sets still active at each iteration, and each keeps its place in
    its own stream.  The M-step's minibatch permutations come from a second CPU generator per
    sequence (:meth:`cpu_generator`), so that they do not move the particle methods' streams.
    """

    def __init__(self, seeds: Sequence[int], device: torch.device | str = "cpu"):
        self.seeds = [int(s) for s in seeds]
        self.device = torch.device(device)
        self.generators = [torch.Generator(device=self.device).manual_seed(s) for s in self.seeds]
        self._cpu: list[torch.Generator | None] = [None] * len(self.seeds)
        self._owner: SequenceStreams = self
        self._index = list(range(len(self.seeds)))
        self.live: list[bool] | None = None  # rows allowed to draw at this step (per-step resampling)

    def __len__(self) -> int:
        return len(self.generators)

    def select(self, index: Sequence[int]) -> SequenceStreams:
        """The streams of the sequences ``index`` (sharing their generators' states)."""
        new = object.__new__(SequenceStreams)
        new.seeds = [self.seeds[i] for i in index]
        new.device = self.device
        new.generators = [self.generators[i] for i in index]
        new._owner = self._owner
        new._index = [self._index[i] for i in index]
        new._cpu = []
        new.live = None
        return new

    def cpu_generator(self, i: int) -> torch.Generator:
        """A CPU generator of sequence ``i``, apart from its particle stream (minibatch orders)."""
        owner, j = self._owner, self._index[i]
        if owner._cpu[j] is None:
            seed = int(np.random.SeedSequence(owner.seeds[j], spawn_key=(1,)).generate_state(1)[0])
            owner._cpu[j] = torch.Generator().manual_seed(seed)
        return owner._cpu[j]

    def at_step(self, live: Sequence[bool]) -> SequenceStreams:
        """These streams drawing only for the rows marked ``live`` (the others get constants)."""
        new = self.select(range(len(self)))
        new.live = list(live)
        return new

    # ------------------------------------------------------------------ draws
    def _draw(self, fn, b: int, shape: tuple[int, ...], dtype, out: Tensor | None = None) -> Tensor:
        return fn(shape, dtype=dtype, device=self.device, generator=self.generators[b], out=out)

    def normal(self, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
        """Standard normals ``(B, *shape)``, row ``b`` from stream ``b``."""
        out = torch.empty(len(self), *shape, dtype=dtype, device=self.device)
        for b in range(len(self)):
            self._draw(torch.randn, b, shape, dtype, out[b])
        return out

    def steps(
        self,
        start: int,
        stop: int,
        limits: Sequence[int],
        shape: tuple[int, ...],
        dtype: torch.dtype,
        *,
        normal: bool = False,
        reverse: bool = False,
        fill: float = _PAD_UNIFORM,
    ) -> Tensor:
        """Draws of the time steps ``start <= k < stop``: ``(B, stop - start, *shape)``.

        Sequence ``b`` draws ``shape`` numbers for each of its steps ``k < limits[b]`` (the others
        are ``fill``), in increasing ``k`` (row ``j``: step ``start + j``) or, with ``reverse``, in
        decreasing ``k`` (row ``j``: step ``stop - 1 - j``; backward passes: consecutive blocks then
        continue one another).  Each sequence's rows are drawn straight into the result, in one
        call.  ``normal`` draws are made for all of a sequence's steps at once (``randn`` is not
        sequential): call it once per pass.
        """
        t = stop - start
        out = torch.empty((len(self), t, *shape), dtype=dtype, device=self.device)
        fn = torch.randn if normal else torch.rand
        for b in range(len(self)):
            n = max(0, min(t, int(limits[b]) - start))
            rows, pad = (slice(t - n, t), slice(0, t - n)) if reverse else (slice(0, n), slice(n, t))
            if n:
                self._draw(fn, b, (n, *shape), dtype, out[b, rows])
            if n < t:
                out[b, pad] = fill
        return out

    def normal_steps_into(self, out: Tensor, limits: Sequence[int], dtype: torch.dtype) -> None:
        """Standard normals of the steps ``k < limits[b]`` of each sequence into ``out`` ``(t, B,
        ...)`` (time-major, any dtype; zero elsewhere): the numbers of :meth:`steps` with
        ``normal=True, fill=0``, each sequence's drawn in ``dtype`` into one reused buffer and
        widened into its column of ``out``."""
        t, shape = out.shape[0], tuple(out.shape[2:])
        buffer = torch.empty((t, *shape), dtype=dtype, device=self.device)
        for b in range(len(self)):
            n = max(0, min(t, int(limits[b])))
            if n:
                self._draw(torch.randn, b, (n, *shape), dtype, buffer[:n])
                out[:n, b].copy_(buffer[:n])
            if n < t:
                out[n:, b] = 0.0

    def rows(self, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
        """Uniforms ``(B, *shape)`` for the live rows (``fill`` elsewhere)."""
        out = torch.full((len(self), *shape), _PAD_UNIFORM, dtype=dtype, device=self.device)
        for b in range(len(self)):
            if self.live is None or self.live[b]:
                self._draw(torch.rand, b, shape, dtype, out[b])
        return out


Randomness = Union[torch.Generator, SequenceStreams, None]


def sequence_seed(entropy: int, index: int) -> int:
    """The seed of sequence ``index``'s stream: a function of ``(entropy, index)`` only
    (``numpy.random.SeedSequence(entropy).spawn(n)[index]``, whatever ``n``)."""
    state = np.random.SeedSequence(int(entropy), spawn_key=(int(index),)).generate_state(1, dtype=np.uint64)
    return int(state[0] >> np.uint64(1))  # torch seeds are below 2^64; keep them in int64 too


def sequence_seeds(entropy: int, n: int) -> list[int]:
    """The seeds of ``n`` sequences' streams (:func:`sequence_seed` of ``0, ..., n - 1``)."""
    return [sequence_seed(entropy, i) for i in range(n)]


def uniform(generator: Randomness, shape: tuple[int, ...], dtype: torch.dtype, device) -> Tensor:
    """Uniforms of ``shape`` ``(B, ...)``: one draw for the batch, or per row with streams."""
    if isinstance(generator, SequenceStreams):
        return generator.rows(tuple(shape[1:]), dtype)
    return torch.rand(shape, dtype=dtype, device=device, generator=generator)


def multinomial(probs: Tensor, n: int, generator: Randomness) -> Tensor:
    """``n`` draws with replacement per row of ``probs`` ``(B, L)``: ``(B, n)``."""
    if not isinstance(generator, SequenceStreams):
        return torch.multinomial(probs, n, replacement=True, generator=generator)
    out = torch.zeros(probs.shape[0], n, dtype=torch.long, device=probs.device)
    for b in range(probs.shape[0]):
        if generator.live is None or generator.live[b]:
            out[b] = torch.multinomial(probs[b], n, replacement=True, generator=generator.generators[b])
    return out
