"""The rejection engine: draw -> simulate -> keep the n best per pair (SPEC section 5).

One engine serves every caller — training (:mod:`torchcf.train`), cross-validation
and the diagnosis loop's attribution (:mod:`torchcf.diagnose.selection.attribution`):

- :class:`Rollout`: how particles are simulated and scored (the pairs, the
  layout, the precision, the chunk);
- :func:`run_rejection`: a model's prior stream through its per-pair buffer.
  Rejection supplies its proposals alone (:func:`prior_proposals`): particles
  ``start .. stop - 1`` of the model's counter-based prior stream
  (:class:`~torchcf.abc.streams.ParticleStream`: a particle, and in the paired
  layout its training pair, is a pure function of ``(seed, model, index)``). The
  round loop (:mod:`torchcf.abc.rounds`) simulates them, screens them and pushes
  them into the buffer (:class:`~torchcf.abc.topn.TopN`, exactly the ``n`` best
  by ``(score, index)``), one chunk per process and round; the buffers after
  particle ``j`` are therefore the same whatever the chunk size, the number of
  processes or where a run was cut and resumed.

The engine knows nothing of checkpoints, progress bars or run directories: a
caller passes :class:`~torchcf.abc.rounds.ModelProgress` (where to continue, what
was counted) and :class:`~torchcf.abc.rounds.RoundHooks` (the processes, the
screen, and callbacks that run between rounds). A round is the unit of
progress and of checkpoints (nothing is reported or saved inside one), which is
why a model's cell budget (:attr:`CFModel.chunk_cells`) is a few seconds of
simulation, not a whole stream: a million MPC particles are 16 rounds on the CPU.
The chunk is set by the plan (the budget, or :attr:`Rollout.chunk_size`), never by
the clock, so that the rounds, like the results, do not depend on timing.

Shapes: P particles, N pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from ..data import PairSet
from ..models import CFModel, require_model
from ..sim.rollout import (
    COMPILE_CHUNK_MULTIPLE,
    CUDA_CHUNK_CELLS,
    DEFAULT_WEIGHTS,
    Execution,
    SimOutput,
    cell_budget,
    resolve_compile,
    simulate,
)
from .rounds import (
    NO_HOOKS,
    Chunk,
    ModelProgress,
    Plan,
    Propose,
    RoundHooks,
    Sink,
    Stretch,
    run_rounds,
)
from .streams import ParticleStream
from .topn import TopN

CompileChoice = Literal["auto", "on", "off"]


@dataclass(frozen=True)
class Rollout:
    """How particles are simulated and scored: the pairs, the layout, the precision.

    Attributes:
        pairs: the pairs particles are fitted to ``(T, N)``.
        paired: particle j is simulated on its own pair (the paper's layout); False:
            on every pair (the full layout, ``(P, N)`` scores).
        dtype: simulation precision (scores are kept in float64).
        device: where the rollout runs.
        weights: score weights of (position, speed, acceleration).
        compile: ``"on"``, ``"off"`` or ``"auto"`` (fuse the time loop with
            ``torch.compile`` when a model's whole stream is long enough to pay).
        chunk_size: particles per simulate call; None: the model's cell budget
            (:func:`torchcf.sim.rollout.cell_budget`).
        early_rejection: the round loop hands every chunk its buffers'
            thresholds as a ceiling (:func:`torchcf.abc.rounds.offer_chunk`): a
            rollout stops once its score is sure to exceed it.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm, truth = get_model("idm"), [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> rollout = Rollout(synthetic_pairs(idm, truth, n_pairs=4, n_steps=50))
        >>> theta = torch.tensor([truth, [0.5, 1.0, 20.0, 2.5, 3.0, 2.0]])
        >>> score, valid = rollout.score(idm, theta, pair=torch.tensor([0, 1]))
        >>> score.round(decimals=2), valid
        (tensor([0.0000, 2.3400], dtype=torch.float64), tensor([True, True]))
    """

    pairs: PairSet
    paired: bool = True
    dtype: torch.dtype = torch.float32
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    weights: tuple[float, float, float] = DEFAULT_WEIGHTS
    compile: CompileChoice = "auto"
    chunk_size: int | None = None
    early_rejection: bool = False

    @property
    def cells_per_particle(self) -> int:
        """Rollouts per particle: 1 (paired) or N (full)."""
        return 1 if self.paired else self.pairs.n_pairs

    def compiled(self, model: CFModel, n_particles: int) -> bool:
        """Whether a stream of ``n_particles`` of ``model`` runs compiled."""
        if self.compile == "auto" and self.early_rejection and model.prunable:
            # "auto" with early rejection stays eager: compiled blocks can drop
            # particles ("on", a dynamic particle dimension), but on the
            # paper-scale study compiling saves little on a warm compile cache
            # and costs far more on an empty one, on 2 CPU cores and on one
            # H100 (reports/bench/train_carII*.md, reports/performance.md)
            return False
        cells = n_particles * self.cells_per_particle * self.pairs.n_steps
        return resolve_compile(model, self.compile, self.device, cells)

    def chunk(self, model: CFModel, n_particles: int, compiled: bool) -> int:
        """Particles per simulate call for a stream of ``n_particles``."""
        budget = cell_budget(model, self.device)
        chunk = self.chunk_size or max(1, budget // self.cells_per_particle)
        chunk = min(chunk, n_particles)
        if (
            compiled
        ):  # compiled blocks want whole vector lanes (see torchcf.sim.rollout)
            chunk = -(-chunk // COMPILE_CHUNK_MULTIPLE) * COMPILE_CHUNK_MULTIPLE
        return chunk

    def score(
        self,
        model: CFModel,
        theta: Tensor,
        pair: Tensor | None,
        *,
        chunk: int | None = None,
        compiled: bool = False,
        ceiling: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Scores of particles ``theta (P, K)`` (float64) on their pairs.

        Args:
            pair: (P,) pair of each particle (paired layout), None for the full one.
            chunk: particles per simulate call (default: :meth:`chunk`).
            ceiling: early rejection
                (:attr:`torchcf.sim.rollout.Execution.ceiling`): the score's
                shape; a particle stopped above it scores ``+inf`` and is valid.

        Returns:
            ``score`` (P,) or (P, N) float64 on the rollout's device, ``+inf`` for an
            invalid or stopped rollout, and ``valid`` of the same shape.
        """
        out = self.rollouts(
            model, theta, pair, chunk=chunk, compiled=compiled, ceiling=ceiling
        )
        return out.score.double(), out.valid

    def rollouts(
        self,
        model: CFModel,
        theta: Tensor,
        pair: Tensor | None,
        *,
        chunk: int | None = None,
        compiled: bool = False,
        ceiling: Tensor | None = None,
    ) -> SimOutput:
        """The rollouts :meth:`score` reads: score, the RMSE of each channel and
        validity, shaped and chunked as there
        (:class:`torchcf.sim.rollout.SimOutput`)."""
        if chunk is None:
            chunk = self.chunk(model, max(theta.shape[0], 1), compiled)
        pairs = self.pairs
        if pair is not None and theta.shape[0]:
            # Only the pairs the particles go to: a simulate call prepares the
            # observations of every pair it is given, so a chunk on a slice of
            # 10 000 pairs (a refinement round's) would otherwise pay for all
            # of them, and the calls of a run for pairs squared. A particle's
            # rollout reads its own pair alone: the scores are the same.
            used = torch.unique(pair)
            if used.numel() < pairs.n_pairs:
                pairs = pairs.subset(used)
                pair = torch.searchsorted(used, pair)
        return simulate(
            model,
            theta.to(self.dtype),
            pairs,
            pair,
            dtype=self.dtype,
            weights=self.weights,
            execution=Execution(self.device, chunk, compiled, ceiling),
        )


def prior_stream(
    model: CFModel,
    bounds: Tensor,
    seed: int,
    rollout: Rollout,
    fixed: Tensor | None = None,
) -> ParticleStream:
    """The model's prior stream for the rollout's layout (a pair per particle when
    paired); ``fixed``: the values of its last parameters where they are held
    (:class:`~torchcf.abc.streams.ParticleStream`).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = get_model("idm")
        >>> pairs = synthetic_pairs(idm, [1.5, 2.0, 33.0, 1.2, 2.0, 4.0], 4, n_steps=50)
        >>> stream = prior_stream(idm, idm.prior_bounds(), 0, Rollout(pairs))  # seed 0
        >>> stream.n_pairs, stream.draw(0, 3)[1].shape  # a pair per particle
        (4, torch.Size([3]))
    """
    model = require_model(model, "prior_stream")
    n_pairs = rollout.pairs.n_pairs if rollout.paired else None
    return ParticleStream(model, bounds, seed, n_pairs, fixed)


def run_rejection(
    stream: ParticleStream,
    buffer: TopN,
    rollout: Rollout,
    n_particles: int,
    progress: ModelProgress,
    *,
    plan_particles: int | None = None,
    hooks: RoundHooks = NO_HOOKS,
) -> None:
    """Stream particles ``progress.next .. n_particles - 1`` through ``buffer``.

    Args:
        stream: the model's prior stream (:func:`prior_stream`): the simulated
            model, the box of the ``K_drawn`` parameters it draws and the
            values of the others where they are held (``stream.fixed``,
            appended to every drawn particle: a shared effect's one value for
            all pairs).
        buffer: the model's per-pair buffer (every rank holds a replica; merged
            after every round).
        rollout: how particles are simulated.
        n_particles: where the stream stops.
        progress: where to start; updated after every round.
        plan_particles: the stream length that sets the chunk and the compile
            choice (default ``n_particles``; a caller that stops a stream at
            several budgets passes one of them, the same at every call: the
            smallest wastes no simulation at the earlier stops).
        hooks: the processes sharing the stream, the plausibility filter and
            what runs between rounds (:class:`~torchcf.abc.rounds.RoundHooks`).

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = get_model("idm")
        >>> pairs = synthetic_pairs(idm, [1.5, 2.0, 33.0, 1.2, 2.0, 4.0], 4, n_steps=50)
        >>> rollout, buffer, progress = Rollout(pairs), TopN(4, 5, 6), ModelProgress()
        >>> stream = prior_stream(idm, idm.prior_bounds(), seed=0, rollout=rollout)
        >>> run_rejection(stream, buffer, rollout, n_particles=200, progress=progress)
        >>> progress.next, buffer.score.shape, bool(buffer.score.isfinite().all())
        (200, torch.Size([4, 5]), True)
    """
    simulated = stream.model
    planned = plan_particles if plan_particles is not None else n_particles
    compiled = rollout.compiled(simulated, planned)
    chunk = rollout.chunk(simulated, planned, compiled)
    run_rounds(
        prior_proposals(stream),
        [Sink(buffer)],
        Plan(rollout, simulated, chunk, compiled, stream.fixed),
        progress,
        Stretch(progress.next, n_particles),
        hooks=hooks,
    )


def prior_proposals(stream: ParticleStream) -> Propose:
    """Rejection's proposals: the stream's particles ``start .. stop - 1``
    (particle index = stream index). Padded to a batch with the stream's next
    particles, which cost a draw and are the same whatever the chunking."""

    def propose(start: int, stop: int, batch: int | None) -> Chunk:
        drawn = batch if batch is not None else stop - start
        theta, pair = stream.draw(start, start + drawn)  # (drawn, K_drawn), (drawn,)
        return Chunk(theta, pair, torch.arange(start, stop))

    return propose


__all__ = [
    "CUDA_CHUNK_CELLS",
    "ModelProgress",
    "RoundHooks",
    "Rollout",
    "prior_proposals",
    "prior_stream",
    "run_rejection",
]
