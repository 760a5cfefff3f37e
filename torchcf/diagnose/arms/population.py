"""An arm's members: per pair, S slots of particles over several models.

The attribution (:mod:`torchcf.diagnose.selection.attribution`) and its local search
(:mod:`torchcf.diagnose.arms.search`) hold the particles they search as a
:class:`Population`: for every pair, ``S`` slots sorted best first by the one tie
rule of torchcf (score, then the lower particle index, then the source: the
position of the population a candidate came from in :func:`merge`), each slot a
particle of one of the population's models (a pool model or a variant
``m+E...``). Slots are per pair, so that two arms searched from one start can
draw the *same* random numbers for the same slot (:mod:`torchcf.diagnose.arms.search`).

Shapes: N pairs, S slots per pair, K parameters (the widest model's; a slot of a
model with fewer holds NaN past its own), Q particles of a flat set
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ...abc.particles import Particles, best_per_pair
from ...abc.rejection import Rollout
from ...models import CFModel, get_model


@dataclass(frozen=True)
class Population:
    """Per pair, ``S`` slots of particles, best first.

    Attributes:
        models: the models the slots refer to (pool models and variants).
        model: (N, S) int64 position in :attr:`models` of each slot's model;
            -1 = an empty slot.
        theta: (N, S, K) float64 parameters in each slot's model's order; NaN past
            its own K and in empty slots.
        score: (N, S) float64 score on the pair (``+inf``: empty or invalid),
            ascending per pair.
        index: (N, S) int64 particle index, the tie-breaker (the stream index of
            the prior draw a particle descends from).
    """

    models: tuple[CFModel, ...]
    model: Tensor
    theta: Tensor
    score: Tensor
    index: Tensor

    @property
    def n_pairs(self) -> int:
        return self.score.shape[0]

    @property
    def size(self) -> int:
        """S, slots per pair."""
        return self.score.shape[1]

    @property
    def filled(self) -> Tensor:
        """(N, S) bool: the slot holds a valid particle (finite score)."""
        return (self.model >= 0) & torch.isfinite(self.score)

    def best(self, n: int) -> Population:
        """The first ``n`` slots of every pair (its ``n`` best)."""
        return Population(
            self.models,
            self.model[:, :n],
            self.theta[:, :n],
            self.score[:, :n],
            self.index[:, :n],
        )

    def model_slots(self, model: CFModel) -> tuple[Tensor, Tensor]:
        """Pair and slot (Q,) int64 each of the filled slots of ``model``."""
        if model not in self.models:
            empty = torch.empty(0, dtype=torch.int64)
            return empty, empty
        held = (self.model == self.models.index(model)) & torch.isfinite(self.score)
        pair, slot = held.nonzero(as_tuple=True)
        return pair, slot

    def particles(self) -> list[Particles]:
        """The filled slots as one :class:`Particles` set per model (pair-major,
        best first within a pair), models in :attr:`models` order."""
        sets = []
        for model in self.models:
            pair, slot = self.model_slots(model)
            if pair.numel() == 0:
                continue
            k = model.n_params
            sets.append(
                Particles(
                    model,
                    self.theta[pair, slot, :k],
                    pair,
                    self.score[pair, slot],
                    self.index[pair, slot],
                )
            )
        return sets

    @classmethod
    def from_particles(
        cls, sets: Sequence[Particles], n_pairs: int, size: int
    ) -> Population:
        """Per pair, the ``size`` best of ``sets`` (the hybrid's selection and tie
        rule, :func:`~torchcf.abc.particles.best_per_pair`)."""
        chosen = best_per_pair(list(sets), size)
        models = tuple(dict.fromkeys(s.model for s in sets))
        width = max([m.n_params for m in models], default=0)
        model = torch.full((n_pairs, size), -1, dtype=torch.int64)
        theta = torch.full((n_pairs, size, width), math.nan, dtype=torch.float64)
        score = torch.full((n_pairs, size), math.inf, dtype=torch.float64)
        index = torch.full((n_pairs, size), -1, dtype=torch.int64)
        flat = _flatten(chosen, models, width)
        if flat is not None:
            f_model, f_theta, f_pair, f_score, f_index = flat
            order = _tie_order(f_pair, f_score, f_index, f_model)
            f_pair = f_pair[order]
            count = torch.bincount(f_pair, minlength=n_pairs)
            rank = (
                torch.arange(order.numel()) - (torch.cumsum(count, 0) - count)[f_pair]
            )
            model[f_pair, rank] = f_model[order]
            theta[f_pair, rank] = f_theta[order]
            score[f_pair, rank] = f_score[order]
            index[f_pair, rank] = f_index[order]
        return cls(models, model, theta, score, index)


def _flatten(
    sets: Sequence[Particles], models: tuple[CFModel, ...], width: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
    """(Q,) model position, (Q, K) padded theta, pair, score, index of ``sets``."""
    if not sets:
        return None
    parts = []
    for s in sets:
        pad = torch.full((len(s), width), math.nan, dtype=torch.float64)
        pad[:, : s.theta.shape[1]] = s.theta.double()
        parts.append(pad)
    return (
        torch.cat(
            [
                torch.full((len(s),), models.index(s.model), dtype=torch.int64)
                for s in sets
            ]
        ),
        torch.cat(parts),
        torch.cat([s.pair for s in sets]),
        torch.cat([s.score.double() for s in sets]),
        torch.cat([s.index for s in sets]),
    )


def _tie_order(pair: Tensor, score: Tensor, index: Tensor, source: Tensor) -> Tensor:
    """Permutation (Q,) sorting by pair, score, index, source (stable sorts)."""
    order = torch.arange(pair.numel())
    for key in (source, index, score, pair):
        order = order[torch.sort(key[order], stable=True).indices]
    return order


def merge(populations: Sequence[Population], size: int) -> Population:
    """Per pair, the ``size`` best slots over ``populations`` (the tie rule: score,
    index, then the earlier population). A slot equal to one before it in this
    order (same model, score and index: the same particle reached twice) is
    dropped, so a population merged with a copy of itself is unchanged.
    """
    models = tuple(dict.fromkeys(m for p in populations for m in p.models))
    width = max([p.theta.shape[2] for p in populations], default=0)
    n_pairs = populations[0].n_pairs
    moved, thetas = [], []
    for p in populations:
        table = torch.tensor([models.index(m) for m in p.models] + [-1])
        moved.append(torch.where(p.model >= 0, table[p.model], -1))
        pad = torch.full((*p.score.shape, width), math.nan, dtype=torch.float64)
        pad[..., : p.theta.shape[2]] = p.theta
        thetas.append(pad)
    model = torch.cat(moved, dim=1)  # (N, S_total)
    theta = torch.cat(thetas, dim=1)
    score = torch.cat([p.score for p in populations], dim=1)
    index = torch.cat([p.index for p in populations], dim=1)
    # empty slots last whatever their index; the source is the column order
    score = torch.where(model >= 0, score, math.inf)
    order = torch.arange(score.shape[1]).expand_as(score)
    for key in (index, score):
        key = key.gather(1, order)
        order = order.gather(1, torch.sort(key, dim=1, stable=True).indices)
    model, score, index = (t.gather(1, order) for t in (model, score, index))
    theta = theta.gather(1, order[..., None].expand_as(theta))
    repeat = torch.zeros_like(score, dtype=torch.bool)
    repeat[:, 1:] = (
        (model[:, 1:] == model[:, :-1])
        & (score[:, 1:] == score[:, :-1])
        & (index[:, 1:] == index[:, :-1])
        & torch.isfinite(score[:, 1:])
    )
    if bool(repeat.any()):
        # the repeated slots go last (empty), the others keep their order
        score = torch.where(repeat, math.inf, score)
        model = torch.where(repeat, -1, model)
        keep = torch.sort(repeat.to(torch.int8), dim=1, stable=True).indices
        model, score, index = (t.gather(1, keep) for t in (model, score, index))
        theta = theta.gather(1, keep[..., None].expand_as(theta))
    model, theta, score, index = (t[:, :size] for t in (model, theta, score, index))
    empty = ~torch.isfinite(score)
    model = torch.where(empty, -1, model)
    theta = torch.where(empty[..., None], math.nan, theta)
    index = torch.where(empty, -1, index)
    del n_pairs
    return Population(models, model, theta, score, index)


def rescore(population: Population, rollout: Rollout) -> Population:
    """The population with every filled slot scored on ``rollout``'s pairs (slot
    order unchanged: call :func:`merge` to sort)."""
    score = torch.full_like(population.score, math.inf)
    for model in population.models:
        pair, slot = population.model_slots(model)
        if pair.numel():
            k = model.n_params
            score[pair, slot] = score_on(
                rollout, model, population.theta[pair, slot, :k], pair
            )
    return Population(
        population.models, population.model, population.theta, score, population.index
    )


def score_on(
    rollout: Rollout,
    model: CFModel,
    theta: Tensor,
    pair: Tensor,
    ceiling: Tensor | None = None,
) -> Tensor:
    """Scores (Q,) float64 on the CPU of particles ``theta`` (Q, K) of ``model``,
    each on its own pair ``pair`` (Q,) of the rollout's pairs (``+inf``:
    invalid, or stopped early above its ``ceiling`` (Q,) float64 where one is
    given: :attr:`torchcf.sim.rollout.Execution.ceiling`)."""
    if theta.shape[0] == 0:
        return torch.empty(0, dtype=torch.float64)
    score, _ = rollout.score(model, theta, pair, ceiling=ceiling)
    return score.cpu()


def pick_scores(population: Population, n: int, rollout: Rollout) -> Tensor:
    """(N,) float64: per pair, the median score on ``rollout``'s pairs of the
    population's ``n`` best (the hybrid's picks); ``+inf`` where more than half
    of them are invalid there or the pair has none."""
    picks = rescore(population.best(n), rollout)
    held = population.best(n).filled
    values = torch.where(held, picks.score, math.inf)
    # the median with invalid picks counted as the worst (+inf)
    values = torch.sort(values, dim=1).values
    count = held.sum(1)
    middle = torch.clamp((count - 1) // 2, min=0)
    upper = torch.clamp(count // 2, min=0)
    low = values.gather(1, middle[:, None])[:, 0]
    high = values.gather(1, upper[:, None])[:, 0]
    median = torch.where(torch.isfinite(high), (low + high) / 2, math.inf)
    return torch.where(count > 0, median, math.inf)


def population_dict(population: Population) -> dict:
    """A population as a checkpoint keeps it (plain types and tensors: each
    model by its name)."""
    return {
        "models": [m.name for m in population.models],
        "model": population.model,
        "theta": population.theta,
        "score": population.score,
        "index": population.index,
    }


def population_of(raw: dict) -> Population:
    """The population :func:`population_dict` kept (its models looked up by
    name, where they enter from the file)."""
    models = tuple(get_model(name) for name in raw["models"])
    return Population(models, raw["model"], raw["theta"], raw["score"], raw["index"])


def particles_dict(particles: Particles) -> dict:
    """A particle set as a checkpoint keeps it (plain types and tensors: its
    model by name; :func:`particles_of` reads it)."""
    return {
        "model": particles.model.name,
        "theta": particles.theta,
        "pair": particles.pair,
        "score": particles.score,
        "index": particles.index,
    }


def particles_of(raw: dict) -> Particles:
    """The particle set :func:`particles_dict` kept (its model looked up by
    name, where it enters from the file)."""
    return Particles(
        get_model(raw["model"]), raw["theta"], raw["pair"], raw["score"], raw["index"]
    )


__all__ = [
    "Population",
    "merge",
    "particles_dict",
    "particles_of",
    "pick_scores",
    "population_dict",
    "population_of",
    "rescore",
    "score_on",
]
