"""The model class judged on the test split.

**The class on the test pairs** (:func:`class_on_test`). The hybrid's test
metrics (WS, minimum distance) score the pooled particles of the training
drivers on drivers the run never saw: with drivers who differ they measure how
well training drivers stand in for new ones, and an effect's gain drowns in it.
A user asks another question: for a new driver of this population, does the
model *with* the chosen effects fit better than without them? So every test
pair is refitted by a short search of its own (the held-out refit of
:mod:`torchcf.diagnose.arms.refit`: ``refit_slots`` particles, until it settles),
once from the picks of the pool's converged fit on the training pairs (the
model class without the effects) and once from the picks of the final model
(with them, each effect pinned at the value the training gave: a shared
effect's one value, a driver effect's median estimate), with common random
numbers. The per-pair change is tested by one-sided sign flips of the log
ratios (exact: the test pairs took no part in the attribution, and both refits
move the models' own parameters only).

The response times of the data and of the calibrated models are
:mod:`torchcf.diagnose.signatures.response`'s.

Shapes: V test pairs, Q candidates (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ...data import PairSet
from ...models.effects import Effect
from ...system.records import Record
from ..arms.population import Population
from ..arms.refit import Pin, candidates, lifted, refit_scores
from ..arms.search import INVALID_RATIO
from ..arms.validation import refit_budget
from ..setup import LoopSetup
from ..significance import comparable, sign_flip_test


@dataclass(frozen=True)
class ClassOnTest(Record):
    """The model class with and without the chosen effects, every test pair
    refitted (module docstring).

    Attributes:
        pairs: test pairs valid on at least one side.
        better: those the class with the effects fits better.
        change: the geometric mean of ``with / without`` minus 1 (negative:
            the effects fit new drivers better).
        p_value: one-sided sign flips of the per-pair log ratios, "the effects
            fit no better".
        mean_without, mean_with: mean refitted score (SPEC section 4's
            weighted RMSE, dimensionless).
        median_without, median_with: their medians.
        pinned: per chosen effect's token, the values it was held at.
        per_pair: ``{"without": [...], "with": [...]}`` per test pair (None:
            invalid on both sides).
    """

    pairs: int
    better: int
    change: float
    p_value: float
    mean_without: float
    mean_with: float
    median_without: float
    median_with: float
    pinned: dict[str, dict[str, float]]
    per_pair: dict[str, list[float | None]]


def chosen_value(
    effect: Effect,
    shared: dict[str, list[float]],
    estimates: dict[str, dict[str, float]],
) -> Tensor:
    """(K_E,) float64 the value a chosen effect is held at: a shared effect's
    one value, else its estimate (neutral where a parameter has none)."""
    if effect.name in shared:
        return torch.tensor(shared[effect.name], dtype=torch.float64)
    found = estimates.get(effect.token, {})
    return torch.tensor(
        [
            found.get(p.name, neutral)
            for p, neutral in zip(effect.param_specs, effect.neutral, strict=True)
        ],
        dtype=torch.float64,
    )


def class_on_test(
    setup: LoopSetup,
    without: Population,
    final: Population,
    pins: list[Pin],
    test_pairs: PairSet,
) -> ClassOnTest:
    """Every test pair refitted without and with the chosen effects.

    Args:
        setup: the loop's setup (its ``diagnose`` settings set the refit).
        without: the pool's converged fit on the training pairs (pool models).
        final: the final model's converged fit (the chosen variants).
        pins: the chosen effects in the order chosen, each at its value.
        test_pairs: the run's test pairs.
    """
    settings = setup.settings
    seed, n = setup.seed, setup.top_n
    rollout = setup.rollout(test_pairs)
    budget = refit_budget(settings)
    priors = setup.priors
    key = (seed, "class-on-test")
    plain = candidates(without, n, {}, seed)
    pool_of = {m: m.pool_model for m in final.models}
    mine = candidates(final, n, pool_of, seed)
    for pin in pins[:-1]:  # earlier effects held through ``shared``
        mine = lifted(mine, pin)
    shared = {pin.effect.name: pin.value for pin in pins[:-1]}
    before = refit_scores(plain, rollout, budget, priors, {}, key).numpy()
    after = refit_scores(mine, rollout, budget, priors, shared, key, pins[-1]).numpy()
    usable, before, after = comparable(before, after, INVALID_RATIO)
    ratios = np.log(after[usable] / before[usable])
    _, p_value = sign_flip_test(-ratios, settings.permutations, seed)
    return ClassOnTest(
        pairs=int(usable.sum()),
        better=int(np.count_nonzero(ratios < 0)),
        change=float(math.expm1(ratios.mean())) if ratios.size else 0.0,
        p_value=p_value,
        mean_without=_stat(np.mean, before[usable]),
        mean_with=_stat(np.mean, after[usable]),
        median_without=_stat(np.median, before[usable]),
        median_with=_stat(np.median, after[usable]),
        pinned={
            pin.effect.token: dict(
                zip(
                    [p.name for p in pin.effect.param_specs],
                    pin.value.tolist(),
                    strict=True,
                )
            )
            for pin in pins
        },
        per_pair={
            "without": [
                _finite(v) if u else None for v, u in zip(before, usable, strict=True)
            ],
            "with": [
                _finite(v) if u else None for v, u in zip(after, usable, strict=True)
            ],
        },
    )


def _stat(fn, values: np.ndarray) -> float:
    return float(fn(values)) if values.size else math.nan


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


__all__ = [
    "ClassOnTest",
    "chosen_value",
    "class_on_test",
]
