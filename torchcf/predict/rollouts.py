"""Rollouts of prediction: particles of several models behind recorded leaders,
and the pairs cut in time.

A prediction simulates particles of the hybrid's models on pairs in the paired
layout (particle p on pair ``pair_index[p]``, SPEC section 2: the follower starts
from its recorded state and follows the recorded leader). :class:`Particles`
holds particles of several models at once, each with its pair, and
:func:`follow` runs every model's on its pairs and gathers the follower's
position and speed in the particles' order.

Shapes: T steps, N pairs, P particles, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..data import PairSet
from ..models import CFModel
from ..sim.rollout import simulate

#: A length bucket's longest pair is at most this many times its shortest.
BUCKET_SPREAD = 1.25


@dataclass(frozen=True)
class Particles:
    """Particles of several models, each on one pair.

    Attributes:
        models: the models.
        model_of: ``(P,)`` int64 each particle's model (its position in
            ``models``).
        theta: ``(P, K)`` float64 each particle's parameters in its model's
            order [SI], K the most any of the models has, NaN past its own.
        pair_index: ``(P,)`` int64 each particle's pair.
    """

    models: tuple[CFModel, ...]
    model_of: Tensor
    theta: Tensor
    pair_index: Tensor

    @property
    def size(self) -> int:
        return int(self.pair_index.numel())

    def rows(self, lo: int, hi: int, first_pair: int = 0) -> Particles:
        """The particles ``lo`` to ``hi`` (exclusive), their pairs counted from
        ``first_pair``."""
        return Particles(
            self.models,
            self.model_of[lo:hi],
            self.theta[lo:hi],
            self.pair_index[lo:hi] - first_pair,
        )

    def of_model(self, m: int) -> tuple[Tensor, Tensor]:
        """``(rows (P_m,), theta (P_m, K_m))`` the particles of model ``m``."""
        rows = torch.nonzero(self.model_of == m).squeeze(1)
        return rows, self.theta[rows, : len(self.models[m].param_names)]

    def names(self) -> list[str]:
        """``(P,)`` each particle's model name."""
        return [self.models[m].name for m in self.model_of.tolist()]


def padded(models: list[CFModel], thetas: list[Tensor]) -> tuple[Tensor, Tensor]:
    """``(model_of (P,), theta (P, K))`` of per-model parameter sets
    ``thetas`` (each ``(P_m, K_m)``), stacked in model order, NaN-padded."""
    width = max(len(m.param_names) for m in models)
    model_of = torch.cat(
        [torch.full((len(t),), m, dtype=torch.int64) for m, t in enumerate(thetas)]
    )
    theta = torch.full((len(model_of), width), float("nan"), dtype=torch.float64)
    row = 0
    for t in thetas:
        theta[row : row + len(t), : t.shape[1]] = t.double()
        row += len(t)
    return model_of, theta


@dataclass(frozen=True)
class Paths:
    """The simulated followers of a :class:`Particles` set.

    Attributes:
        x: ``(T, P)`` float64 position [m].
        v: ``(T, P)`` float64 speed [m/s].
        valid: ``(P,)`` bool, False where the rollout collided or blew up.
        e_p: ``(P,)`` float64 RMSE of position [m] over the pair's recorded
            steps (= the spacing RMSE), ``+inf`` where invalid.
        score: ``(P,)`` float64 SPEC section 4's score, ``+inf`` where invalid.
    """

    x: Tensor
    v: Tensor
    valid: Tensor
    e_p: Tensor
    score: Tensor


def follow(particles: Particles, pairs: PairSet, trajectories: bool = True) -> Paths:
    """Every particle of ``particles`` behind its pair's recorded leader.

    Pairs of different lengths are simulated in :func:`length_buckets`, each
    bucket on its own steps only (a ragged set's padding is not simulated; the
    scores are the same, and ``x``, ``v`` are NaN past a pair's end). With
    ``trajectories`` False, ``x`` and ``v`` are empty ``(0, P)``: only the
    scores are kept (the searches' case)."""
    size = particles.size
    steps = pairs.n_steps if trajectories else 0
    x = torch.full((steps, size), float("nan"), dtype=torch.float64)
    v = x.clone()
    valid = torch.zeros(size, dtype=torch.bool)
    e_p = torch.full((size,), float("inf"), dtype=torch.float64)
    score = e_p.clone()
    position_in = torch.full((pairs.n_pairs,), -1, dtype=torch.int64)
    for bucket, part in length_buckets(pairs):
        position_in[bucket] = torch.arange(len(bucket))
        inside = torch.isin(particles.pair_index, bucket)
        for m, model in enumerate(particles.models):
            rows = torch.nonzero(inside & (particles.model_of == m)).squeeze(1)
            if not len(rows):
                continue
            out = simulate(
                model,
                particles.theta[rows, : len(model.param_names)],
                part,
                position_in[particles.pair_index[rows]],
                dtype=torch.float64,
                return_traj=trajectories,
            )
            if trajectories:
                x[: part.n_steps, rows] = out.x.double().cpu()
                v[: part.n_steps, rows] = out.v.double().cpu()
            valid[rows] = out.valid.cpu()
            e_p[rows] = out.e_p.double().cpu()
            score[rows] = out.score.double().cpu()
    if trajectories:  # past a pair's end: nothing recorded, nothing predicted
        ended = ~pairs.mask.cpu()[:, particles.pair_index]
        x[ended], v[ended] = float("nan"), float("nan")
    return Paths(x, v, valid, e_p, score)


def length_buckets(pairs: PairSet) -> list[tuple[Tensor, PairSet]]:
    """The pairs in buckets of similar length, shortest first: ``(positions
    (B,) in ``pairs``, the bucket's pairs cut to its longest)``; a bucket's
    longest pair is at most :data:`BUCKET_SPREAD` times its shortest (its
    padding, simulated for nothing, at most that share)."""
    lengths = pairs.lengths.cpu()
    if bool((lengths == pairs.n_steps).all()):  # not ragged: the pairs as they are
        return [(torch.arange(pairs.n_pairs), pairs)]
    order = torch.argsort(lengths, stable=True)
    buckets, start = [], 0
    while start < len(order):
        stop = start + 1
        while (
            stop < len(order)
            and lengths[order[stop]] <= BUCKET_SPREAD * lengths[order[start]]
        ):
            stop += 1
        positions = order[start:stop]
        longest = int(lengths[positions].max())
        part = pairs.subset(positions)
        if longest < pairs.n_steps:
            part = steps_between(part, 0, longest)
        buckets.append((positions, part))
        start = stop
    return buckets


def steps_between(pairs: PairSet, start: int, stop: int | None = None) -> PairSet:
    """The pairs' steps ``start`` to ``stop`` (exclusive; None: the end), each
    pair's own recorded steps only; the follower starts there from its
    recorded state. Every pair must have at least two recorded steps in it.

    Raises:
        ValueError: a pair has fewer than two recorded steps in the range.
    """
    stop = pairs.n_steps if stop is None else min(stop, pairs.n_steps)
    mask = pairs.mask[start:stop]
    short = torch.nonzero(mask.sum(0) < 2).squeeze(1)
    if short.numel():
        raise ValueError(
            f"pair {pairs.pair_ids[int(short[0])]} has fewer than 2 recorded steps "
            f"in steps {start}-{stop}"
        )
    return pairs.steps(start, stop)


__all__ = [
    "BUCKET_SPREAD",
    "Particles",
    "Paths",
    "follow",
    "length_buckets",
    "padded",
    "steps_between",
]
