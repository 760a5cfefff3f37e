"""The population model: one parameter vector per model for every driver.

Published calibrations of a population ("pooled" or "aggregate" calibration)
search one parameter vector per model that minimises the mean error over the
training pairs, typically by differential evolution over the prior box. A run
has already simulated millions of particles and kept the best of each pair: the
pooled optimum lies near some of them. So :func:`pooled_fit` searches from the
kept particles:

1. every kept particle of the model (the hybrid's, each pair's best) is
   simulated on every training pair and scored by its **pooled objective**: the
   mean over the pairs of the per-pair spacing RMSE [m] (``objective =
   "spacing"``, the published studies' measure of performance) or of SPEC
   section 4's score (``"score"``);
2. for the :data:`REFINED` models of the best kept particles, a local search
   refines the best ``ELITE``: ``rounds`` times, each elite gets
   ``copies`` perturbed copies (normal steps of ``SCALES[c % 3]`` times each
   parameter's prior width, clipped to the box), all scored on every training
   pair, and the best ``ELITE`` of elites and copies go on (elitist: the best
   never gets worse); it stops after ``PATIENCE`` rounds that lower the best
   objective by less than ``SETTLED`` of it.

A vector that collides on a training pair is ranked after every vector that
collides on fewer (a pooled calibration must drive every driver it stands for);
among equals the lower objective over the pairs it drives wins.

The population model of a run is the model whose pooled vector has the lowest
objective (:func:`population_model`).

Shapes: C candidate vectors, N training pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..data import PairSet
from ..models import CFModel
from ..sim.rollout import simulate
from ..system.records import Record
from .rollouts import length_buckets

#: Vectors carried from round to round of the local search.
ELITE = 4
#: Models whose pooled vector is refined by the local search (those of the
#: best kept particles).
REFINED = 3
#: Steps of the local search, as fractions of each parameter's prior width.
SCALES = (0.1, 0.03, 0.01)
#: A round settles when it lowers the best objective by less than this share;
#: the search stops after ``PATIENCE`` settled rounds in a row.
SETTLED = 1e-3
PATIENCE = 3
#: The pooled objectives (module docstring).
OBJECTIVES = ("spacing", "score")


@dataclass(frozen=True)
class PooledFit(Record):
    """One model's pooled vector (module docstring).

    Attributes:
        model: the model's name.
        params: parameter name -> value [SI].
        objective: its pooled objective on the training pairs (mean spacing
            RMSE [m], or mean score).
        collided: training pairs it collides on.
        kept: the kept particles it was searched from.
        evaluated: vectors scored in all (kept particles and copies).
        rounds: local-search rounds run.
    """

    model: str
    params: dict[str, float]
    objective: float
    collided: int
    kept: int
    evaluated: int
    rounds: int

    def theta(self) -> Tensor:
        """``(1, K)`` float64 the vector in the model's order."""
        return torch.tensor([list(self.params.values())], dtype=torch.float64)


def pooled_objective(
    model: CFModel, theta: Tensor, pairs: PairSet, objective: str = "spacing"
) -> tuple[Tensor, Tensor]:
    """``(collided (C,) int64, objective (C,) float64)`` of vectors ``theta``
    (C, K), each simulated on every pair of ``pairs`` (module docstring; the
    objective over the pairs a vector drives, ``+inf`` where it drives none)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    error = torch.empty((len(theta), pairs.n_pairs), dtype=torch.float64)
    for positions, part in length_buckets(pairs):  # a ragged set's padding skipped
        out = simulate(model, theta.double(), part, dtype=torch.float64)
        error[:, positions] = (
            out.e_p if objective == "spacing" else out.score
        ).double()
    driven = torch.isfinite(error)
    collided = (~driven).sum(1)
    total = torch.where(driven, error, torch.zeros_like(error)).sum(1)
    mean = total / driven.sum(1).clamp(min=1)
    return collided, torch.where(
        driven.any(1), mean, torch.full_like(mean, float("inf"))
    )


@dataclass(frozen=True)
class Start:
    """A model's kept particles, scored: where its local search starts.

    Attributes:
        elite: ``(E, K)`` the best :data:`ELITE` kept particles, best first.
        collided, value: ``(E,)`` their pooled rank keys (module docstring).
        kept: the kept particles scored.
    """

    elite: Tensor
    collided: Tensor
    value: Tensor
    kept: int

    @property
    def rank(self) -> tuple[int, float]:
        return int(self.collided[0]), float(self.value[0])


def kept_start(
    model: CFModel, kept: Tensor, pairs: PairSet, objective: str = "spacing"
) -> Start:
    """Step 1 of the module docstring: every kept particle (Q, K) of ``model``
    scored on ``pairs``, the best :data:`ELITE` kept."""
    kept = torch.unique(kept.double(), dim=0)
    collided, value = pooled_objective(model, kept, pairs, objective)
    order = _ranked(collided, value)[:ELITE]
    return Start(kept[order], collided[order], value[order], len(kept))


def pooled_fit(
    model: CFModel,
    kept: Tensor | Start,
    prior: Tensor,
    pairs: PairSet,
    *,
    objective: str = "spacing",
    rounds: int = 40,
    copies: int = 24,
    seed: int = 0,
) -> PooledFit:
    """The pooled vector of ``model`` on ``pairs``, searched from its ``kept``
    particles (Q, K; or their :func:`kept_start`) inside ``prior`` (K, 2)
    (module docstring)."""
    start = (
        kept if isinstance(kept, Start) else kept_start(model, kept, pairs, objective)
    )
    elite, elite_collided, elite_value = start.elite, start.collided, start.value
    generator = torch.Generator().manual_seed(seed)
    width = (prior[:, 1] - prior[:, 0]).double()
    evaluated, settled, ran = start.kept, 0, 0
    for r in range(rounds):
        ran = r + 1
        scale = torch.tensor([SCALES[c % len(SCALES)] for c in range(copies)])
        steps = torch.randn(
            (len(elite), copies, elite.shape[1]),
            generator=generator,
            dtype=torch.float64,
        )
        moved = elite[:, None, :] + steps * scale[None, :, None].double() * width
        moved = torch.maximum(torch.minimum(moved, prior[:, 1]), prior[:, 0])
        moved = moved.reshape(-1, elite.shape[1])
        c, v = pooled_objective(model, moved, pairs, objective)
        evaluated += len(moved)
        best_before = (int(elite_collided[0]), float(elite_value[0]))
        pool = torch.cat([elite, moved])
        pool_c, pool_v = torch.cat([elite_collided, c]), torch.cat([elite_value, v])
        order = _ranked(pool_c, pool_v)[:ELITE]
        elite, elite_collided, elite_value = pool[order], pool_c[order], pool_v[order]
        best_now = (int(elite_collided[0]), float(elite_value[0]))
        gained = best_now[0] < best_before[0] or (
            best_now[1] < best_before[1] * (1 - SETTLED)
        )
        settled = 0 if gained else settled + 1
        if settled >= PATIENCE:
            break
    return PooledFit(
        model=model.name,
        params=dict(zip(model.param_names, elite[0].tolist(), strict=True)),
        objective=float(elite_value[0]),
        collided=int(elite_collided[0]),
        kept=start.kept,
        evaluated=evaluated,
        rounds=ran,
    )


def pooled_fits(
    models: list[CFModel],
    kept: dict[str, Tensor],
    priors: dict[str, Tensor],
    pairs: PairSet,
    *,
    objective: str = "spacing",
    seed: int = 0,
) -> list[PooledFit]:
    """Every model's pooled vector: each from its best kept particle, the
    :data:`REFINED` models of the best kept particles refined by the local
    search (the others' searches could not reach the population model; on
    long pairs each round costs a simulation of every training pair)."""
    starts = {m.name: kept_start(m, kept[m.name], pairs, objective) for m in models}
    ranked = sorted(models, key=lambda m: starts[m.name].rank)
    refined = {m.name for m in ranked[:REFINED]}
    return [
        pooled_fit(
            m,
            starts[m.name],
            priors[m.name],
            pairs,
            objective=objective,
            rounds=40 if m.name in refined else 0,
            seed=seed,
        )
        for m in models
    ]


def population_model(fits: list[PooledFit]) -> PooledFit:
    """The pooled vector of the lowest objective over the models (fewer
    collisions first; ties: the first listed)."""
    return min(fits, key=lambda f: (f.collided, f.objective))


def _ranked(collided: Tensor, value: Tensor) -> Tensor:
    """Positions by (collided, value) ascending, stable."""
    by_value = torch.argsort(value, stable=True)
    return by_value[torch.argsort(collided[by_value], stable=True)]


__all__ = [
    "ELITE",
    "OBJECTIVES",
    "PooledFit",
    "pooled_fit",
    "pooled_fits",
    "pooled_objective",
    "population_model",
]
