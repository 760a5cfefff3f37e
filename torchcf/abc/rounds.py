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
   checkpoints; rank 0's clock says whether one is due).

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
from typing import Any, Protocol

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
    """

    next: int = 0
    invalid: int = 0
    seconds: float = 0.0
    done: bool = False
    implausible: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "next": self.next,
            "invalid": self.invalid,
            "seconds": self.seconds,
            "done": self.done,
            "implausible": self.implausible,
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


def run_rounds(
    propose: Propose,
    sinks: Sequence[Sink],
    plan: Plan,
    progress: ModelProgress,
    start: int,
    stop: int,
    *,
    offset: int = 0,
    reached: Callable[[int], None] | None = None,
    group: Group = SINGLE,
    screen: PlausibilityScreen | None = None,
    checkpoint_due: Callable[[], bool] | None = None,
    after_round: Callable[[ModelProgress, bool], None] | None = None,
) -> None:
    """Offer a stretch's proposals ``start .. stop - 1`` to ``sinks``, round by
    round (module docstring).

    Args:
        propose: the method's proposals (:data:`Propose`).
        sinks: the buffers, offered to in this order.
        plan: how chunks are simulated.
        progress: updated after every round: counts, time, and ``next = offset +``
            the proposals of the stretch offered so far.
        start: where the stretch continues (0, or a checkpoint's place).
        stop: the stretch's length.
        offset: the model's particles before the stretch (an SMC round's first
            index).
        reached: told after every round how far into the stretch it went,
            before ``after_round`` (SMC keeps it in its state).
        group: the processes sharing the stretch.
        screen: the plausibility filter, or None.
        checkpoint_due: asked on rank 0's clock after every round (every rank
            learns rank 0's answer).
        after_round: called after every round with the progress and whether a
            checkpoint is due.
    """
    buffers = [sink.buffer for sink in sinks]
    round_size = plan.chunk * group.world_size
    for first in range(start, stop, round_size):
        began = time.perf_counter()
        lo, hi = group.shard(first, stop, plan.chunk)
        invalid = implausible = 0
        if lo < hi:
            chunk = propose(lo, hi, plan.batch)
            invalid, implausible = offer_chunk(chunk, sinks, plan, screen)
        due = checkpoint_due() if checkpoint_due is not None else False
        invalid, due = group.end_round(buffers, invalid, due)
        if screen is not None:
            implausible = group.sum(implausible)
        done = min(first + round_size, stop)
        if reached is not None:
            reached(done)
        progress.invalid += invalid
        progress.implausible += implausible
        progress.next = offset + done
        progress.seconds += time.perf_counter() - began
        if after_round is not None:
            after_round(progress, due)


def offer_chunk(
    chunk: Chunk,
    sinks: Sequence[Sink],
    plan: Plan,
    screen: PlausibilityScreen | None = None,
) -> tuple[int, int]:
    """Simulate a chunk and offer its proposals to every sink in turn; their
    invalid count and the number the screen rejected.

    A proposal the screen rejects for one sink is out of the later ones too, and
    one it found plausible is not tested again (``cleared``)."""
    real = chunk.size
    if not real:
        return 0, 0
    theta = chunk.theta
    if plan.fixed is not None:  # the searched parameters, then the fixed ones
        theta = torch.cat((theta, plan.fixed.expand(theta.shape[0], -1)), dim=1)
    score, valid = plan.rollout.score(
        plan.model, theta, chunk.pair, chunk=plan.chunk, compiled=plan.compiled
    )
    # The screen and the pushes read the scores where the buffers live (the CPU).
    device = sinks[0].buffer.score.device
    score, valid = score[:real].to(device), valid[:real].to(device)
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
    return int((~valid).sum()), rejected


__all__ = [
    "Chunk",
    "ModelProgress",
    "Plan",
    "Propose",
    "Scorer",
    "Sink",
    "offer_chunk",
    "run_rounds",
]
