"""The round loop both ABC methods share: propose -> simulate -> screen -> push.

Rejection (:mod:`torchcf.abc.rejection`) and SMC (:mod:`torchcf.abc.smc`) differ
only in where their particles come from: the prior stream, or a round's kernel
around its population. Everything else is this loop's (as sbi's ``ABCBASE`` owns
the batching and the distance, and its methods only propose), run over one
*stretch* of proposals (a rejection stream, an SMC round):

1. **shard**: the stretch is cut in *rounds* of one chunk per process
   (:meth:`Group.shard <torchcf.abc.distributed.Group.shard>`);
2. **propose**: the method hands the loop its proposals ``start .. stop - 1`` as
   a :class:`Chunk` (a :data:`Propose` function), padded to the plan's batch where
   the batch size matters (:attr:`Plan.batch`);
3. **simulate** them (:meth:`Rollout.score <torchcf.abc.rejection.Rollout.score>`),
   the plan's fixed parameters appended;
4. **screen and push** into each :class:`Sink` in turn: a per-pair top-N buffer
   (:class:`~torchcf.abc.topn.TopN`), optionally only below a per-pair ceiling
   (SMC's accepted set), the plausibility screen
   (:mod:`torchcf.abc.screen`) testing its candidates first;
5. **end the round**: the ranks' buffers merged and their counts summed
   (:meth:`Group.end_round <torchcf.abc.distributed.Group.end_round>`), the
   progress advanced, the caller's ``after_round`` called (its progress bar and
   checkpoints; rank 0's clock says whether one is due: :class:`RoundHooks`).

A round is the unit of progress and of checkpoints: nothing is reported or saved
inside one. The chunk is set by the plan, never by the clock, so the rounds, like
the results, do not depend on timing; and since every buffer keeps exactly the
best by ``(score, particle index)``, the buffers after a stretch do not depend
on the chunk, the number of processes or where a run was cut and resumed.

Shapes: P particles of a chunk (R real ones, then padding), N pairs, K
parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor

from ..models import CFModel
from .distributed import SINGLE, Group
from .screen import PlausibilityScreen
from .topn import TopN


@dataclass
class ModelProgress:
    """How far one model's stream went (a checkpoint holds it).

    Attributes:
        next: particles ``0 .. next - 1`` have been offered to the buffer.
        invalid: invalid rollouts among them (cells, in the full layout).
        seconds: simulation and selection time spent on them.
        done: the stream is finished.
        implausible: particles the plausibility filter rejected, scored
            ``+inf`` like invalid rollouts; only particles that would otherwise
            have entered the buffer are tested, so this counts those
            (:mod:`torchcf.abc.screen`).
        stopped: rollouts (cells) early rejection stopped because their score
            was sure to exceed their buffer's threshold
            (:attr:`Rollout.early_rejection <torchcf.abc.rejection.Rollout>`);
            ``invalid`` then counts the invalid rollouts among the others.

    Examples:
        >>> progress = ModelProgress(next=4096, invalid=3)
        >>> progress.as_dict()
        {'next': 4096, 'invalid': 3, 'seconds': 0.0, 'done': False, 'implausible': 0,
         'stopped': 0}
    """

    next: int = 0
    invalid: int = 0
    seconds: float = 0.0
    done: bool = False
    implausible: int = 0
    stopped: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "next": self.next,
            "invalid": self.invalid,
            "seconds": self.seconds,
            "done": self.done,
            "implausible": self.implausible,
            "stopped": self.stopped,
        }


@dataclass(frozen=True)
class Chunk:
    """One process's proposals of one round, as a method hands them to the loop.

    Attributes:
        theta: (P, K_drawn) float64 parameters to simulate: the R proposals, then
            ``P - R`` rows of padding (simulated, never offered).
        pair: (P,) int64 pair of each row (paired layout), or None (full layout:
            every particle on every pair).
        index: (R,) int64 particle index of each proposal, unique per model (the
            buffers' tie rule).
        rows: (R, K_buffer) what the buffers hold for each proposal; None: the
            simulated parameters (``theta`` with the fixed ones appended).
    """

    theta: Tensor
    pair: Tensor | None
    index: Tensor
    rows: Tensor | None = None

    @property
    def size(self) -> int:
        """R, the proposals (padding aside)."""
        return self.index.shape[0]


#: What a method supplies: ``propose(start, stop, batch)``, its proposals
#: ``start .. stop - 1`` of the stretch, padded to ``batch`` rows where ``batch``
#: is not None (:attr:`Plan.batch`).
Propose = Callable[[int, int, int | None], Chunk]


class Scorer(Protocol):
    """What the loop needs of a :class:`~torchcf.abc.rejection.Rollout`."""

    def score(
        self,
        model: CFModel,
        theta: Tensor,
        pair: Tensor | None,
        *,
        chunk: int | None = None,
        compiled: bool = False,
        ceiling: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]: ...


@dataclass(frozen=True)
class Plan:
    """How a stretch's chunks are simulated, set by the plan alone.

    Attributes:
        rollout: simulates and scores (a :class:`~torchcf.abc.rejection.Rollout`).
        model: the simulated model.
        chunk: particles per process and round, and per simulate call.
        compiled: whether the rollout runs compiled.
        fixed: ``(K - K_drawn,)`` values appended to every proposal before it is
            simulated (a shared effect's one value for all pairs), or None.
    """

    rollout: Scorer
    model: CFModel
    chunk: int
    compiled: bool
    fixed: Tensor | None = None

    @property
    def batch(self) -> int | None:
        """Rows of every simulate call where the batch size matters (the chunk),
        else None (the proposals alone): a compiled block sees one shape per
        model, and a model whose rollout rounds by batch size
        (:attr:`CFModel.batch_size_invariant`, the MPC) one batch size whatever
        the chunking."""
        fixed_size = self.compiled or not self.model.batch_size_invariant
        return self.chunk if fixed_size else None


@dataclass(frozen=True)
class Sink:
    """A buffer a chunk's proposals are offered to.

    Attributes:
        buffer: the per-pair top-N buffer (every rank holds a replica; merged
            after every round).
        ceiling: (N,) a proposal enters only at or under its pair's value
            (SMC's threshold for its accepted set); None: no ceiling.
    """

    buffer: TopN
    ceiling: Tensor | None = None


@dataclass(frozen=True)
class RoundHooks:
    """What a caller adds to the round loop: the processes that share the
    rounds, the plausibility screen before a push, and what runs between
    rounds (a progress bar, checkpoints).

    Attributes:
        group: the processes sharing the stretch (:data:`SINGLE`: this one).
        screen: the plausibility filter (:mod:`torchcf.abc.screen`), or None.
        checkpoint_due: asked on rank 0's clock after every round (every rank
            learns rank 0's answer); None: never due.
        after_round: called after every round with the progress and whether a
            checkpoint is due; None: nothing.

    Examples:
        >>> hooks = RoundHooks(after_round=lambda progress, due: print(progress.next))
        >>> hooks.group is SINGLE, hooks.screen is None  # one process, no screen
        (True, True)
        >>> hooks.after_round(ModelProgress(next=512), False)
        512
    """

    group: Group = SINGLE
    screen: PlausibilityScreen | None = None
    checkpoint_due: Callable[[], bool] | None = None
    after_round: Callable[[ModelProgress, bool], None] | None = None


#: No hooks: one process, no screen, nothing between rounds.
NO_HOOKS = RoundHooks()


@dataclass(frozen=True)
class Stretch:
    """The proposals a round loop offers: ``start .. stop - 1`` of a stretch
    (a rejection stream, an SMC round).

    Attributes:
        start: where the stretch continues (0, or a checkpoint's place).
        stop: the stretch's length.
        offset: the model's particles before the stretch (an SMC round's first
            particle index): the progress counts ``offset +`` the proposals
            offered.
    """

    start: int
    stop: int
    offset: int = 0


#: With early rejection, a stretch that starts from nothing begins with a pilot
#: round of ``1 / PILOT_ROUND`` of a round: its buffers' thresholds then stop
#: the rollouts of the first full round early, which would otherwise run whole.
PILOT_ROUND = 16


def round_bounds(
    plan: Plan, start: int, stop: int, world_size: int
) -> list[tuple[int, int, int]]:
    """The rounds of the stretch ``start .. stop - 1``: ``(first, end, chunk)``
    each, ``chunk`` proposals per process. Set by the plan alone: a round of
    ``plan.chunk`` per process, after a pilot round (:data:`PILOT_ROUND`) where
    early rejection is on and the stretch starts at 0. The buffers after a
    stretch do not depend on its rounds (module docstring)."""
    size = plan.chunk * world_size
    rounds, first = [], start
    if early_rejection(plan) and start == 0 and plan.chunk >= PILOT_ROUND:
        pilot = plan.chunk // PILOT_ROUND
        end = min(pilot * world_size, stop)
        rounds.append((0, end, pilot))
        first = end
    rounds += [(f, min(f + size, stop), plan.chunk) for f in range(first, stop, size)]
    return rounds


def run_rounds(
    propose: Propose,
    sinks: Sequence[Sink],
    plan: Plan,
    progress: ModelProgress,
    stretch: Stretch,
    *,
    reached: Callable[[int], None] | None = None,
    hooks: RoundHooks = NO_HOOKS,
) -> None:
    """Offer a stretch's proposals ``start .. stop - 1`` to ``sinks``, round by
    round (module docstring).

    Args:
        propose: the method's proposals (:data:`Propose`).
        sinks: the buffers, offered to in this order.
        plan: how chunks are simulated.
        progress: updated after every round: counts, time, and ``next = offset +``
            the proposals of the stretch offered so far.
        stretch: the proposals to offer, and the particles before them.
        reached: told after every round how far into the stretch it went,
            before ``hooks.after_round`` (SMC keeps it in its state).
        hooks: the processes sharing the stretch, the screen, and what runs
            between rounds (:class:`RoundHooks`).
    """
    group, screen = hooks.group, hooks.screen
    checkpoint_due, after_round = hooks.checkpoint_due, hooks.after_round
    buffers = [sink.buffer for sink in sinks]
    start, stop = stretch.start, stretch.stop
    for first, end, chunk_size in round_bounds(plan, start, stop, group.world_size):
        began = time.perf_counter()
        lo, hi = group.shard(first, end, chunk_size)
        counts = Offered(0, 0, 0)
        if lo < hi:
            chunk = propose(lo, hi, plan.batch)
            counts = offer_chunk(chunk, sinks, plan, screen)
        due = checkpoint_due() if checkpoint_due is not None else False
        invalid, due = group.end_round(buffers, counts.invalid, due)
        implausible, stopped = counts.implausible, counts.stopped
        if screen is not None:
            implausible = group.sum(implausible)
        if early_rejection(plan):
            stopped = group.sum(stopped)
        done = end
        if reached is not None:
            reached(done)
        progress.invalid += invalid
        progress.implausible += implausible
        progress.stopped += stopped
        progress.next = stretch.offset + done
        progress.seconds += time.perf_counter() - began
        if after_round is not None:
            after_round(progress, due)


class Offered(NamedTuple):
    """What became of a chunk's proposals (:func:`offer_chunk`): invalid
    rollouts, proposals the screen rejected, rollouts early rejection stopped."""

    invalid: int
    implausible: int
    stopped: int


def early_rejection(plan: Plan) -> bool:
    """Whether the plan's rollout stops rollouts above their buffers' threshold
    (asked for, and possible: a model that can select its particles,
    :func:`torchcf.sim.rollout.simulate`; compiled, its blocks then take any number of
    particles)."""
    asked = bool(getattr(plan.rollout, "early_rejection", False))
    return asked and plan.model.prunable


def ceiling_of(sinks: Sequence[Sink], pair: Tensor | None, rows: int) -> Tensor:
    """The score above which a proposal can enter no sink: per pair the largest,
    over the sinks, of the buffer's threshold (its worst kept score, ``+inf``
    while it has room) capped by the sink's own ceiling; float64, (P,) for the
    paired layout (``pair`` (P,)) or (P, N) for the full one (``rows`` = P).

    A proposal scoring above it now will do so when the chunk is pushed: a
    buffer's threshold only falls.
    """
    tops = []
    for sink in sinks:
        top = sink.buffer.threshold()  # (N,)
        if sink.ceiling is not None:
            top = torch.minimum(top, sink.ceiling.to(top))
        tops.append(top)
    top = torch.stack(tops).amax(0)
    if pair is None:
        return top.expand(rows, -1).clone()
    return top[pair.to(top.device)]


def offer_chunk(
    chunk: Chunk,
    sinks: Sequence[Sink],
    plan: Plan,
    screen: PlausibilityScreen | None = None,
) -> Offered:
    """Simulate a chunk and offer its proposals to every sink in turn; their
    invalid count, the number the screen rejected and the rollouts early
    rejection stopped.

    A proposal the screen rejects for one sink is out of the later ones too, and
    one it found plausible is not tested again (``cleared``)."""
    real = chunk.size
    if not real:
        return Offered(0, 0, 0)
    theta = chunk.theta
    if plan.fixed is not None:  # the searched parameters, then the fixed ones
        theta = torch.cat((theta, plan.fixed.expand(theta.shape[0], -1)), dim=1)
    extra = {}
    if early_rejection(plan):
        ceiling = ceiling_of(sinks, chunk.pair, theta.shape[0])
        ceiling[real:] = -math.inf  # the padding stops at the first look
        extra["ceiling"] = ceiling
    score, valid = plan.rollout.score(
        plan.model, theta, chunk.pair, chunk=plan.chunk, compiled=plan.compiled, **extra
    )
    # The screen and the pushes read the scores where the buffers live (the CPU).
    device = sinks[0].buffer.score.device
    score, valid = score[:real].to(device), valid[:real].to(device)
    # a valid rollout scoring +inf was stopped (early rejection)
    stopped = int((valid & ~torch.isfinite(score)).sum()) if extra else 0
    whole = theta[:real]  # the simulated parameters, fixed ones too
    pair = chunk.pair[:real] if chunk.pair is not None else None
    rows = chunk.rows if chunk.rows is not None else whole
    rejected = 0
    cleared = torch.zeros(real, dtype=torch.bool)  # tested, plausible
    for sink in sinks:
        offered = score
        if sink.ceiling is not None:
            offered = torch.where(score <= sink.ceiling[pair], score, math.inf)
        if screen is not None:
            candidates = offered
            offered, count = screen.screen(
                plan.model, sink.buffer, offered, chunk.index, whole, pair, cleared
            )
            rejected += count
            if count:  # out of the later sinks too
                out = torch.isfinite(candidates) & ~torch.isfinite(offered)
                score = torch.where(out, math.inf, score)
        if pair is None:
            sink.buffer.push_full(offered, chunk.index, rows)
        else:
            sink.buffer.push(pair, offered, chunk.index, rows)
    return Offered(int((~valid).sum()), rejected, stopped)


__all__ = [
    "Chunk",
    "ModelProgress",
    "NO_HOOKS",
    "Offered",
    "Plan",
    "Propose",
    "RoundHooks",
    "Scorer",
    "Sink",
    "Stretch",
    "offer_chunk",
    "run_rounds",
]
