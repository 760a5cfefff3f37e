"""The round loop (torchcf.abc.rounds) as a unit: a fake proposal source and a
fake simulator. Rounds and shards, the batch a simulate call sees, the order of
the pushes, progress and checkpoints once per round, the screen across sinks."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import pytest
import torch

from torchcf.abc.distributed import SINGLE, Group
from torchcf.abc.rounds import (
    Chunk,
    ModelProgress,
    Plan,
    RoundHooks,
    Sink,
    Stretch,
    run_rounds,
)
from torchcf.abc.screen import PlausibilityScreen
from torchcf.abc.topn import TopN

N_PAIRS = 3


def _theta(start: int, stop: int) -> torch.Tensor:
    """(Q, 2) parameters of particles start .. stop - 1: a pure function of the
    index (particle j's score is its first parameter)."""
    j = torch.arange(start, stop, dtype=torch.float64)
    return torch.stack((torch.remainder(j * 7.3, 11.0), j), dim=1)


class Source:
    """Proposals ``start .. stop - 1``, particle j on pair j mod N, padded with
    the next indices' parameters; it logs every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, int, int | None]] = []

    def __call__(self, start: int, stop: int, batch: int | None) -> Chunk:
        self.calls.append((start, stop, batch))
        drawn = batch if batch is not None else stop - start
        theta = _theta(start, start + drawn)
        pair = torch.arange(start, start + drawn) % N_PAIRS
        return Chunk(theta, pair, torch.arange(start, stop))


class Scorer:
    """score = the first parameter, invalid (``+inf``) where it exceeds 9; logs
    the rows of every call."""

    def __init__(self) -> None:
        self.rows: list[int] = []

    def score(self, model, theta, pair, *, chunk=None, compiled=False):
        self.rows.append(theta.shape[0])
        valid = theta[:, 0] <= 9.0
        return torch.where(valid, theta[:, 0], math.inf), valid


@dataclass(frozen=True)
class OneOfTwo(Group):
    """Rank 0 of two processes, its collectives recorded instead of run (the
    other rank's replica is empty)."""

    log: list = None  # type: ignore[assignment]

    def end_round(self, buffers, invalid, due):
        self.log.append(("end_round", len(buffers)))
        return invalid, due

    def sum(self, value):
        return value


def _plan(chunk: int, invariant: bool = True, scorer=None) -> Plan:
    model = SimpleNamespace(name="fake", batch_size_invariant=invariant)
    return Plan(scorer or Scorer(), model, chunk, compiled=False)


def _run(
    chunk: int,
    stop: int = 10,
    start: int = 0,
    offset: int = 0,
    group: Group = SINGLE,
    **kwargs,
):
    source, buffer, progress = Source(), TopN(N_PAIRS, 2, 2), ModelProgress()
    plan = _plan(chunk, kwargs.pop("invariant", True))
    seen = []

    def after_round(state: ModelProgress, due: bool) -> None:
        seen.append((state.next, state.invalid, due))

    dues = iter([False, True] * 50)
    run_rounds(
        source,
        [Sink(buffer)],
        plan,
        progress,
        Stretch(start, stop, offset),
        hooks=RoundHooks(
            group, checkpoint_due=lambda: next(dues), after_round=after_round
        ),
        **kwargs,
    )
    return source, buffer, progress, seen, plan


def test_rounds_cover_the_stretch_once_with_progress_after_each():
    source, _, progress, seen, plan = _run(4)
    assert source.calls == [(0, 4, None), (4, 8, None), (8, 10, None)]
    assert plan.rollout.rows == [4, 4, 2]  # batch-size invariant: no padding
    invalid = [int((_theta(0, n)[:, 0] > 9).sum()) for n in (4, 8, 10)]
    assert seen == [
        (4, invalid[0], False),
        (8, invalid[1], True),
        (10, invalid[2], False),
    ]
    assert progress.next == 10 and progress.invalid == invalid[-1]


def test_the_buffers_do_not_depend_on_the_chunk():
    buffers = [_run(chunk, stop=40)[1] for chunk in (1, 3, 7, 40)]
    reference = TopN(N_PAIRS, 2, 2)
    theta = _theta(0, 40)
    score = torch.where(theta[:, 0] <= 9, theta[:, 0], math.inf)
    reference.push(torch.arange(40) % N_PAIRS, score, torch.arange(40), theta)
    for buffer in buffers:
        for key in ("score", "index", "theta"):
            assert torch.equal(getattr(buffer, key), getattr(reference, key)), key


def test_a_batch_is_padded_but_only_the_proposals_are_offered():
    """A model that rounds by batch size: every call simulates a whole chunk,
    the padding (here better scores) never enters the buffer."""
    source, buffer, _, _, plan = _run(4, stop=10, invariant=False)
    assert source.calls == [(0, 4, 4), (4, 8, 4), (8, 10, 4)]
    assert plan.rollout.rows == [4, 4, 4]
    held = buffer.index[buffer.index >= 0]
    assert int(held.max()) < 10


def test_a_resumed_stretch_starts_at_its_place_and_counts_from_the_offset():
    reached = []
    source, _, progress, seen, _ = _run(
        4, stop=10, start=4, offset=100, reached=reached.append
    )
    assert source.calls == [(4, 8, None), (8, 10, None)]
    assert reached == [8, 10]
    assert [s[0] for s in seen] == [108, 110] and progress.next == 110


def test_two_processes_take_a_chunk_each_per_round():
    """Rank 0 of two: the first chunk of each round, the progress of the whole
    round, one merge per round."""
    log: list = []
    group = OneOfTwo(rank=0, world_size=2, log=log)
    source, _, progress, seen, _ = _run(3, stop=14, group=group)
    assert source.calls == [(0, 3, None), (6, 9, None), (12, 14, None)]
    assert [s[0] for s in seen] == [6, 12, 14]
    assert log == [("end_round", 1)] * 3
    rank1 = OneOfTwo(rank=1, world_size=2, log=[])
    source, *_ = _run(3, stop=14, group=rank1)
    assert source.calls == [(3, 6, None), (9, 12, None)]  # its third shard is empty


def test_sinks_are_offered_in_turn_below_their_ceilings():
    """Every proposal goes to the first sink, those at or under their pair's
    ceiling to the second; pushes in sink order, once per chunk."""
    order = []

    class Logged(TopN):
        def push(self, pair, score, index, theta):
            order.append(self.name)
            return super().push(pair, score, index, theta)

    first, second = Logged(N_PAIRS, 5, 2), Logged(N_PAIRS, 5, 2)
    first.name, second.name = "buffer", "accepted"
    ceiling = torch.tensor([3.0, math.inf, 0.0], dtype=torch.float64)
    run_rounds(
        Source(),
        [Sink(first), Sink(second, ceiling)],
        _plan(5),
        ModelProgress(),
        Stretch(0, 15),
    )
    assert order == ["buffer", "accepted"] * 3
    theta = _theta(0, 15)
    pair = torch.arange(15) % N_PAIRS
    valid = theta[:, 0] <= 9
    under = valid & (theta[:, 0] <= ceiling[pair])
    assert set(first.index[first.index >= 0].tolist()) <= set(
        torch.arange(15)[valid].tolist()
    )
    assert set(second.index[second.index >= 0].tolist()) == set(
        torch.arange(15)[under].tolist()
    )


def test_a_screened_proposal_is_out_of_every_sink_and_counted_once():
    tested = []

    def implausible(model, theta):
        tested.extend(theta[:, 1].long().tolist())
        return torch.remainder(theta[:, 1], 2) == 0  # even particles

    buffer, accepted = TopN(N_PAIRS, 2, 2), TopN(N_PAIRS, 2, 2)
    ceiling = torch.full((N_PAIRS,), math.inf, dtype=torch.float64)
    progress = ModelProgress()
    run_rounds(
        Source(),
        [Sink(accepted, ceiling), Sink(buffer)],
        _plan(10),
        progress,
        Stretch(0, 10),
        hooks=RoundHooks(screen=PlausibilityScreen(implausible)),
    )
    for held in (buffer, accepted):
        kept = held.index[held.index >= 0]
        assert kept.numel() and bool((kept % 2 == 1).all())
    assert len(tested) == len(set(tested))  # no particle tested twice
    assert progress.implausible == sum(1 for j in tested if j % 2 == 0)


def test_an_empty_chunk_simulates_nothing():
    scorer = Scorer()

    def nothing(start, stop, batch):
        return Chunk(
            torch.zeros(0, 2).double(), torch.zeros(0).long(), torch.zeros(0).long()
        )

    seen = []
    run_rounds(
        nothing,
        [Sink(TopN(N_PAIRS, 2, 2))],
        _plan(4, scorer=scorer),
        ModelProgress(),
        Stretch(0, 8),
        hooks=RoundHooks(after_round=lambda state, due: seen.append(state.next)),
    )
    assert scorer.rows == [] and seen == [4, 8]


def test_the_full_layout_pushes_every_cell():
    class Full(Scorer):
        def score(self, model, theta, pair, *, chunk=None, compiled=False):
            assert pair is None
            score = theta[:, :1] + torch.arange(N_PAIRS, dtype=torch.float64)
            return score, torch.ones_like(score, dtype=torch.bool)

    def full(start, stop, batch):
        return Chunk(_theta(start, stop), None, torch.arange(start, stop))

    buffer = TopN(N_PAIRS, 2, 2)
    run_rounds(
        full, [Sink(buffer)], _plan(3, scorer=Full()), ModelProgress(), Stretch(0, 9)
    )
    best = torch.argsort(_theta(0, 9)[:, 0], stable=True)[:2]
    for p in range(N_PAIRS):
        assert buffer.index[p].tolist() == best.tolist()


@pytest.mark.parametrize("chunk", [2, 5])
def test_checkpoint_due_is_asked_once_per_round(chunk):
    asked = []
    run_rounds(
        Source(),
        [Sink(TopN(N_PAIRS, 2, 2))],
        _plan(chunk),
        ModelProgress(),
        Stretch(0, 10),
        hooks=RoundHooks(checkpoint_due=lambda: asked.append(1) or False),
    )
    assert len(asked) == math.ceil(10 / chunk)
