"""Attribution: which candidate effects lower the out-of-sample error (loop step 2).

Every training pair is split in time (:func:`split_in_time`): the arms are fitted
on its first ``fit_fraction`` of steps (the *fit windows*) and judged on the rest
(the *validation windows*), out of sample.

**Nested arms with common random numbers.** The current model (at first the
active pool) is fitted once (:func:`fit_pool`: a small ABC run per model, then
local search, :mod:`torchcf.diagnose.search`), giving a population of ``S``
particles per pair. Each step of the selection then compares, for every
candidate effect E, two arms grown from that one start:

- the **base arm**: the start, searched ``rounds`` more rounds by itself
  (:func:`base_arm`);
- the **effect arm**: the start lifted to the variants ``m+E`` with E neutral
  (:attr:`~torchcf.models.effects.Effect.neutral`: the same particles) and
  spread over E's prior (``explore`` values per particle), searched ``rounds``
  rounds with the *same random numbers* as the base arm, and merged with the
  base arm (:func:`effect_arm`).

The effect arm holds every particle of the base arm, so per pair its k-th best
fit score is never worse than the base arm's: **an effect cannot lose in
sample**, and where E adds nothing the two arms pick the same particles and the
pair's difference is exactly zero. What differs between the arms is the effect,
not the luck of two independent searches. A shared effect (a recording's sensor
or clock offset, a road profile) has one value for all pairs, found jointly over
the pairs first (:func:`~torchcf.diagnose.search.shared_value`) and pinned.

**The test.** Per pair, the arm's ``top_n`` best (the hybrid's picks) are scored
on the validation window; the pair's value is their median. The effect's gain is
the relative drop of the summed validation score, its p-value the one-sided
sign-flip test of the per-pair log ratios (:mod:`torchcf.diagnose.testing`).

**The order and the guard.** The residual signatures of the current model on the
fit windows (:mod:`torchcf.diagnose.signatures`) point to effects; the effects of
a step are tested in the order: pointed to by a signature first, then by their
in-sample (fit-window) gain (:func:`test_order`), with the fallback procedure at
the step's level (:func:`~torchcf.diagnose.testing.fallback_levels`,
:func:`~torchcf.diagnose.testing.step_levels`), and an effect must also gain at
least ``min_gain``. Among the significant effects the one of largest gain is
chosen, its arm becomes the current model, and the others are tested again,
until none is significant or ``max_effects`` are chosen.

**Absorption.** Every effect arm reports which of the model's own parameters
takes the effect up (:mod:`torchcf.diagnose.absorption`).

**Resume.** Every arm is a pure function of the run, the settings and its place
in the selection (its random numbers are seeded by that place,
:func:`~torchcf.diagnose.search.derive_seed`), and is written to
``RUN_DIR/loop/attribution.pt`` when done (:class:`Ledger`): an interrupted
attribution run again continues after its last finished arm, with the same
result.

Shapes: N pairs, S slots per pair, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..abc.rejection import Rollout
from ..abc.smc import SMCSettings
from ..config import DiagnoseConfig, TrainConfig, config_hash
from ..data import PairSet
from ..files import RunFileError, atomic_torch_save, read_torch
from ..models import get_model
from ..models.effects import RoadProfile, parse_effect
from .absorption import absorbed_by, profile_absorption, profile_values
from .candidates import attribution_rollout, attribution_seed, prior_particles
from .population import Population, merge, pick_scores, rescore
from .road import one_step_residual
from .search import (
    INVALID_RATIO,
    Noise,
    converge,
    effect_prior,
    explore,
    lift,
    local_search,
    model_bounds,
    search_round,
    shared_value,
)
from .series import BestParticles, DiagnoseError, residual_series
from .signatures import Signature, pointed_effects, signatures
from .testing import fallback_levels, sign_flip_test, step_levels

#: Shortest out-of-sample window that counts for a pair [steps].
MIN_VALIDATION_STEPS = 20
#: Ledger format (``RUN_DIR/loop/attribution.pt``).
LEDGER_FORMAT = "torchcf.attribution/5"


# ------------------------------------------------------------------- the data
def split_in_time(pairs: PairSet, fraction: float) -> tuple[PairSet, PairSet]:
    """The first ``fraction`` of the steps and the rest, for the same pairs.

    Pairs with fewer than :data:`MIN_VALIDATION_STEPS` valid steps in the second
    part are dropped from both, so both sets hold the same pairs.

    Returns:
        ``(fit, validation)``; the validation set starts from the observed state at
        the split step.

    Raises:
        DiagnoseError: a window would be too short, or fewer than 2 pairs are
            long enough.
    """
    split = int(round(fraction * pairs.n_steps))
    if split < MIN_VALIDATION_STEPS or pairs.n_steps - split < MIN_VALIDATION_STEPS:
        raise DiagnoseError(
            f"diagnose.fit_fraction={fraction}: {pairs.n_steps} steps leave a fit "
            f"or validation window under {MIN_VALIDATION_STEPS} steps"
        )
    keep = pairs.mask[split:].sum(0) >= MIN_VALIDATION_STEPS
    if int(keep.sum()) < 2:
        raise DiagnoseError(
            "fewer than 2 training pairs are long enough for out-of-sample "
            "validation; lower diagnose.fit_fraction"
        )
    pairs = pairs.subset(keep)

    def window(rows: slice) -> PairSet:
        return dataclasses.replace(
            pairs,
            **{field: t[rows] for field, t in pairs.series().items()},
            mask=pairs.mask[rows],
        )

    return window(slice(0, split)), window(slice(split, None))


def resolve_effect(token: str, pairs: PairSet) -> str:
    """The effect's name token; a bare road effect (``grade``, ``bend``) spans
    the pairs' road section (its knots: see :mod:`torchcf.diagnose.road`)."""
    effect = parse_effect(token)
    if isinstance(effect, RoadProfile) and "(" not in token:
        x = pairs.x_follow[pairs.mask]
        start, end = math.floor(float(x.min())), math.ceil(float(x.max()))
        effect = type(effect)(start=start, end=max(end, start + 1), knots=effect.knots)
    return effect.token


# ------------------------------------------------------------------ the arena
@dataclass(frozen=True)
class Arena:
    """What every arm of an attribution shares.

    Attributes:
        settings: the run's ``diagnose`` section (budgets, search, test).
        fit: simulates on the fit windows; validation: on the validation windows.
        seed: the seed every random draw of the attribution derives from
            (:func:`attribution_seed`).
        priors: the run's prior box (K, 2) per pool model.
        top_n: N, the particles per pair an arm is judged by.
        smc: the small ABC's refinement when ``diagnose.method = "smc"``, else
            None (rejection).
        road_seeds: per road effect token, a first candidate of its value.
        road_profile: the road profile whose signature is tested (None: the
            pairs have a frame each).
    """

    settings: DiagnoseConfig
    fit: Rollout
    validation: Rollout
    seed: int
    priors: dict[str, Tensor]
    top_n: int
    smc: SMCSettings | None = None
    road_seeds: dict[str, Tensor] = dataclasses.field(default_factory=dict)
    road_profile: RoadProfile | None = None

    @classmethod
    def of(cls, cfg: TrainConfig, train_pairs: PairSet, **extra: Any) -> Arena:
        """The arena of the run's config on its training pairs, split in time."""
        settings = cfg.diagnose
        fit, validation = split_in_time(train_pairs, settings.fit_fraction)
        return cls(
            settings=settings,
            fit=attribution_rollout(cfg, fit),
            validation=attribution_rollout(cfg, validation),
            seed=attribution_seed(cfg),
            priors={spec.name: spec.bounds(torch.float64) for spec in cfg.models},
            top_n=cfg.abc.top_n,
            smc=SMCSettings(**cfg.abc.smc.model_dump())
            if settings.method == "smc"
            else None,
            **extra,
        )

    @property
    def size(self) -> int:
        """S, the slots per pair of every arm (at least ``top_n``)."""
        return max(self.settings.population, self.top_n)

    def bounds(self, models: Any, shared: dict[str, Tensor]) -> dict[str, Tensor]:
        """Prior box of each model, shared effects pinned at their values."""
        return {m: model_bounds(m, self.priors, shared) for m in models}

    def converge(
        self,
        population: Population,
        shared: dict[str, Tensor],
        label: tuple,
        tick: Callable[[], None],
    ) -> Population:
        """Local search on the fit windows until it converges (at most
        ``max_rounds`` rounds): the start of a step's comparisons."""
        converged, _ = converge(
            population,
            self.fit,
            self.bounds(population.models, shared),
            Noise((self.seed, "converge", *label), _current(population)),
            {m: m for m in population.models},
            copies=self.settings.local_copies,
            max_rounds=self.settings.max_rounds,
            progress=tick,
        )
        return converged

    def search(
        self,
        start: Population,
        noise: Noise,
        parents: dict[str, str],
        shared: dict[str, Tensor],
        tick: Callable[[], None],
    ) -> Population:
        """``rounds`` rounds of local search on the fit windows."""
        return local_search(
            start,
            self.fit,
            self.bounds(start.models, shared),
            noise,
            parents,
            rounds=self.settings.rounds,
            copies=self.settings.local_copies,
            progress=tick,
        )


def _current(population: Population) -> dict[str, tuple[str, ...]]:
    """Every model of a population as a current model (its own step columns)."""
    return {m: get_model(m).param_names for m in population.models}


# ------------------------------------------------------------------- the arms
@dataclass(frozen=True)
class Arm:
    """A model of the selection fitted on the fit windows: the pool, or the pool
    with the effects chosen so far.

    Attributes:
        effects: the chosen effect tokens, in the order chosen.
        population: its particles (S per pair).
        shared: per chosen shared effect name, its one value (K_E,).
    """

    effects: tuple[str, ...]
    population: Population
    shared: dict[str, Tensor]


def fit_pool(arena: Arena, pool: list[str], tick: Callable[[], None]) -> Arm:
    """The pool alone: a small ABC run of ``n_particles`` per model on the fit
    windows, its ``S`` best per pair, then local search until it converges."""
    sets = []
    for name in pool:
        box = model_bounds(name, arena.priors)
        (particles,) = prior_particles(
            name,
            arena.fit,
            (arena.settings.n_particles,),
            arena.size,
            box,
            arena.seed,
            smc=arena.smc,
        )
        sets.append(particles)
    tick()
    start = Population.from_particles(sets, arena.fit.pairs.n_pairs, arena.size)
    return Arm((), arena.converge(start, {}, ("pool",), tick), {})


def base_arm(arena: Arena, arm: Arm, step: int, tick: Callable[[], None]) -> Population:
    """The current model searched ``rounds`` more rounds by itself: the part of
    every arm of step ``step`` that has no effect (an effect can never lose
    against it)."""
    population = arm.population
    noise = Noise((arena.seed, "step", step, "base"), _current(population))
    parents = {m: m for m in population.models}
    return arena.search(population, noise, parents, arm.shared, tick)


def extra_noise(arena: Arena, arm: Arm, step: int, effect: str | None) -> Noise:
    """The random numbers of a step's second search: the placebo's, and every
    effect arm's (the same common columns, the effect's own besides)."""
    key = (arena.seed, "step", step, "extra")
    return Noise(key, _current(arm.population), effect)


def placebo_arm(
    arena: Arena, arm: Arm, base: Population, step: int, tick: Callable[[], None]
) -> Population:
    """The base arm merged with a second search of the current model alone, as
    every effect arm is merged with its search with the effect: the same start
    (half the slots the current model's best, half the best of ``explore``
    coarse steps of every particle, where an effect arm spreads its half over
    the effect's prior) and the same random numbers. The effect arms are judged
    against it: both hold the base arm and one more search of equal budget, so
    that their difference is the effect, not a second search."""
    start = arm.population
    noise = extra_noise(arena, arm, step, None)
    parents = {m: m for m in start.models}
    bounds = arena.bounds(start.models, arm.shared)
    steps = noise.steps(-1, (start.n_pairs, start.size, arena.settings.explore))
    spread = search_round(start, arena.fit, bounds, steps, _own_columns)
    kept = arena.size - arena.size // 2
    begin = merge(
        [start.best(kept), merge([spread], arena.size).best(arena.size - kept)],
        arena.size,
    )
    tick()
    searched = arena.search(begin, noise, parents, arm.shared, tick)
    return merge([base, searched], arena.size)


def _own_columns(model: str) -> Tensor:
    """A current model's step columns: its own parameters, in order."""
    return torch.arange(get_model(model).n_params)


@dataclass(frozen=True)
class EffectArm:
    """An effect arm's result.

    Attributes:
        population: per pair its S best of the base arm and the search with E.
        lifted_from: per variant carrying E, the model it was lifted from.
        value: a shared effect's one value (K_E,), else None.
        shared_prior: a shared effect's box (K_E, 2) of the last search round.
        profile: a one-parameter shared effect's profile: the values (G, 1) and
            the fit at each, else None.
    """

    population: Population
    lifted_from: dict[str, str]
    value: Tensor | None = None
    shared_prior: Tensor | None = None
    profile: tuple[Tensor, list[Population]] | None = None


def effect_arm(
    arena: Arena,
    arm: Arm,
    base: Population,
    effect: str,
    step: int,
    tick: Callable[[], None],
) -> EffectArm:
    """The current model with E (module docstring), merged with the base arm.

    A one-parameter effect is first profiled (:func:`profile_search`: fixed at
    values over its prior, the model's own parameters refitted at each); a
    shared one takes its best value (pinned), a driver one starts from every
    pair's best particles over the profile (each pair its own value). An effect
    of several parameters starts from the current model lifted with E neutral
    and spread over E's prior; a road profile of several knots from its one
    value searched jointly over the pairs (:func:`~torchcf.diagnose.search.
    shared_value`), pinned. Every arm is then searched with the placebo's
    budget and random numbers and merged with the base arm.
    """
    start = arm.population
    spec = parse_effect(effect)
    key = (arena.seed, "step", step)
    noise = extra_noise(arena, arm, step, effect)
    shared = dict(arm.shared)
    value = box = profile = None
    if len(spec.param_specs) == 1:
        value, values, fits, lifted_from = profile_search(
            arena, arm, effect, step, tick
        )
        profile = (values, fits)
        if spec.shared:
            box = _box_around(values, value)
            shared[spec.name] = value
            best = int(torch.argmin((values[:, 0] - value[0]).abs()))
            begin = fits[best]
        else:
            value = None  # each pair its own: the best over the profile
            begin = merge(fits, arena.size)
    elif spec.shared:
        value, box, _ = shared_value(
            effect,
            start,
            arena.fit,
            arena.bounds(start.models, shared),
            effect_prior(effect),
            (*key, effect),
            start=[arena.road_seeds[effect]] if effect in arena.road_seeds else [],
        )
        shared[spec.name] = value
        lifted, lifted_from = lift(start, effect, value, arena.fit)
        begin = merge([lifted], arena.size)
    else:
        neutral = torch.tensor(spec.neutral, dtype=torch.float64)
        lifted, lifted_from = lift(
            start, effect, neutral, None if spec.exactly_neutral else arena.fit
        )
        spread, _ = explore(
            start,
            effect,
            effect_prior(effect),
            arena.settings.explore,
            (*key, effect),
            arena.fit,
        )
        # Half the slots keep the neutral start, half the best of the spread:
        # an effect that needs the model's own parameters to move as well is
        # not crowded out before the search can move them.
        kept = arena.size - arena.size // 2
        begin = merge(
            [
                merge([lifted], arena.size).best(kept),
                merge([spread], arena.size).best(arena.size - kept),
            ],
            arena.size,
        )
    tick()
    parents = {m: m for m in start.models} | lifted_from
    searched = arena.search(begin, noise, parents, shared, tick)
    population = merge([base, searched], arena.size)
    return EffectArm(population, lifted_from, value, box, profile)


def profile_search(
    arena: Arena, arm: Arm, effect: str, step: int, tick: Callable[[], None]
) -> tuple[Tensor, Tensor, list[Population], dict[str, str]]:
    """A one-parameter effect's profile over its prior, and its best value.

    The effect is fixed at each value of its profile
    (:func:`~torchcf.diagnose.absorption.profile_values`) and every pair's
    particles refitted (``rounds / 2`` rounds of ``local_copies / 2`` copies,
    the model's own parameters free to take the effect up). The profile is
    followed from the effect's neutral value outwards, each value starting from
    the fit of its neighbour nearer to neutral (a continuation: a parameter
    that absorbs the effect follows it along the ridge, step by step, instead
    of jumping from its neutral fit). The value whose fit is best (the mean
    over pairs of the best score relative to the start's) and the two values
    half a grid step on either side of it (each from the best's fit) give the
    effect's value.

    Returns:
        the value (1,), every value fitted (G, 1) ascending, their populations,
        and per variant the model it was lifted from.
    """
    spec = parse_effect(effect)
    start = arm.population
    reference = start.score[:, 0]
    usable = torch.isfinite(reference) & (reference > 0)
    copies = max(1, arena.settings.local_copies // 2)
    rounds = max(1, arena.settings.rounds // 2)
    fitted: dict[float, tuple[Population, float]] = {}
    neutral = torch.tensor(spec.neutral, dtype=torch.float64)
    lifted, lifted_from = lift(
        start, effect, neutral, None if spec.exactly_neutral else arena.fit
    )
    parents = {m: m for m in start.models} | lifted_from

    def fit_at(value: float, origin: Population) -> None:
        at = torch.tensor([value], dtype=torch.float64)
        shared = dict(arm.shared) | {spec.name: at}
        begin = merge([repin(origin, effect, at, arena.fit)], arena.size)
        noise = Noise(
            (arena.seed, "step", step, "profile", effect, value),
            _current(start),
            effect,
        )
        population = local_search(
            begin,
            arena.fit,
            arena.bounds(begin.models, shared),
            noise,
            parents,
            rounds=rounds,
            copies=copies,
        )
        ratio = population.score[usable, 0] / reference[usable]
        ratio = torch.where(torch.isfinite(ratio), ratio, INVALID_RATIO)
        fitted[value] = (population, float(ratio.mean()))
        tick()

    grid = profile_values(effect)[:, 0].tolist()
    centre = min(range(len(grid)), key=lambda i: abs(grid[i] - float(neutral[0])))
    fit_at(grid[centre], lifted)
    for side in (range(centre - 1, -1, -1), range(centre + 1, len(grid))):
        previous = grid[centre]
        for i in side:
            fit_at(grid[i], fitted[previous][0])
            previous = grid[i]
    best = min(fitted, key=lambda v: fitted[v][1])
    half = (grid[1] - grid[0]) / 2
    low, high = spec.param_specs[0].lower, spec.param_specs[0].upper
    for value in (best - half, best + half):
        if low <= value <= high and value not in fitted:
            fit_at(value, fitted[best][0])
    best = min(fitted, key=lambda v: fitted[v][1])
    values = sorted(fitted)
    return (
        torch.tensor([best], dtype=torch.float64),
        torch.tensor(values, dtype=torch.float64)[:, None],
        [fitted[v][0] for v in values],
        lifted_from,
    )


def repin(
    population: Population, effect: str, value: Tensor, rollout: Rollout
) -> Population:
    """The population with the effect's parameters of every slot that carries
    it set to ``value`` (K_E,), re-scored on the rollout's pairs (slot order
    unchanged)."""
    names = [p.name for p in parse_effect(effect).param_specs]
    token = effect.split("(")[0]
    theta = population.theta.clone()
    for m, name in enumerate(population.models):
        if token not in [t.split("(")[0] for t in name.split("+")[1:]]:
            continue
        held = population.model == m
        columns = [get_model(name).param_names.index(n) for n in names]
        rows = theta[held]
        rows[:, columns] = value.to(torch.float64)
        theta[held] = rows
    return rescore(
        Population(
            population.models,
            population.model,
            theta,
            population.score,
            population.index,
        ),
        rollout,
    )


def _box_around(values: Tensor, value: Tensor) -> Tensor:
    """(1, 2) the box between the profile values next to ``value``."""
    grid = values[:, 0]
    i = int(torch.argmin((grid - value[0]).abs()))
    low = grid[max(i - 1, 0)]
    high = grid[min(i + 1, grid.numel() - 1)]
    if not high > low:
        high = low + 1e-6
    return torch.stack((low, high))[None, :]


# ---------------------------------------------------------------- the report
def _fit_statistic(population: Population, n: int) -> Tensor:
    """(N,) per pair the median fit score of the population's ``n`` best."""
    values = torch.where(population.best(n).filled, population.best(n).score, math.inf)
    count = population.best(n).filled.sum(1)
    low = values.gather(1, torch.clamp((count - 1) // 2, min=0)[:, None])[:, 0]
    high = values.gather(1, torch.clamp(count // 2, min=0)[:, None])[:, 0]
    return torch.where(count > 0, (low + high) / 2, math.inf)


def _relative_drop(before: np.ndarray, after: np.ndarray) -> tuple[float, np.ndarray]:
    """The relative drop of the summed score and the per-pair log ratios, over the
    pairs finite on both sides."""
    usable = np.isfinite(before) & np.isfinite(after) & (after > 0) & (before > 0)
    if not usable.any():
        return 0.0, np.empty(0)
    gain = float((before[usable] - after[usable]).sum() / before[usable].sum())
    return gain, np.log(before[usable] / after[usable])


def estimate(population: Population, effect: str, n: int) -> dict[str, float]:
    """Median of the effect's parameters over the ``n`` best per pair that carry
    it."""
    names = [p.name for p in parse_effect(effect).param_specs]
    token = effect.split("(")[0]
    picks = population.best(n)
    values = []
    for name in picks.models:
        if token not in [t.split("(")[0] for t in name.split("+")[1:]]:
            continue
        pair, slot = picks.model_slots(name)
        columns = [get_model(name).param_names.index(p) for p in names]
        values.append(picks.theta[pair, slot][:, columns])
    if not values or not sum(v.shape[0] for v in values):
        return {}
    median = torch.cat(values).median(dim=0).values
    return dict(zip(names, median.tolist(), strict=True))


def effect_row(
    arena: Arena,
    effect: str,
    result: EffectArm,
    base: Population,
    placebo: Population,
    placebo_validation: np.ndarray,
) -> dict[str, Any]:
    """The effect's report row, against the placebo: in-sample and validation
    gain, sign-flip test, scores, estimate, absorption (the order and the
    verdict come later). ``base_fit_gain`` is the in-sample gain against the
    base arm, which the effect arm holds (never negative)."""
    n = arena.top_n
    mine = _fit_statistic(result.population, n).numpy()
    fit_gain, _ = _relative_drop(_fit_statistic(placebo, n).numpy(), mine)
    base_fit_gain, _ = _relative_drop(_fit_statistic(base, n).numpy(), mine)
    after = pick_scores(result.population, n, arena.validation).numpy()
    gain, drops = _relative_drop(placebo_validation, after)
    statistic, p_value = sign_flip_test(drops, arena.settings.permutations)
    usable = np.isfinite(placebo_validation) & np.isfinite(after)
    spec = parse_effect(effect)
    row: dict[str, Any] = {
        "name": spec.name,
        "effect": effect,
        "scope": spec.scope,
        "fit_gain": fit_gain,
        "base_fit_gain": base_fit_gain,
        "gain": gain,
        "statistic": statistic,
        "p_value": p_value,
        "score_before": float(placebo_validation[usable].mean())
        if usable.any()
        else None,
        "score_after": float(after[usable].mean()) if usable.any() else None,
        "n_pairs": int(usable.sum()),
        "pairs_changed": int(np.count_nonzero(drops)),
        "variants": sorted(result.lifted_from),
        "estimate": estimate(result.population, effect, n),
        "per_pair": {
            "before": [_finite_or_none(v) for v in placebo_validation.tolist()],
            "after": [_finite_or_none(v) for v in after.tolist()],
        },
    }
    if result.value is not None:
        names = [p.name for p in spec.param_specs]
        row["shared"] = {
            "value": dict(zip(names, result.value.tolist(), strict=True)),
            "prior": {
                k: tuple(b)
                for k, b in zip(names, result.shared_prior.tolist(), strict=True)
            },
        }
        row["estimate"] = row["shared"]["value"]
    if result.profile is not None:
        values, fits = result.profile
        found = result.value
        if found is None and row["estimate"]:  # a driver effect: the picks' median
            found = torch.tensor(list(row["estimate"].values()), dtype=torch.float64)
        row["absorbed_by"] = profile_absorption(
            effect, values, fits, result.lifted_from, base, found
        )
    elif not spec.shared:
        row["absorbed_by"] = absorbed_by(
            effect, result.population, base, result.lifted_from
        )
    else:
        row["absorbed_by"] = None
    return row


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def test_order(
    rows: list[dict[str, Any]], pointed: dict[str, list[str]]
) -> list[dict[str, Any]]:
    """The order of a step's tests, fixed by the fit windows: the effects a
    found signature points to first, then the others; within each, the larger
    in-sample gain first (then the name)."""
    return sorted(
        rows,
        key=lambda r: (r["name"] not in pointed, -r["fit_gain"], r["effect"]),
    )


# ---------------------------------------------------------- the signatures
def best_of(population: Population) -> BestParticles:
    """Each pair's best particle, grouped by model (the residuals' input)."""
    best: BestParticles = {}
    for m, name in enumerate(population.models):
        held = (population.model[:, 0] == m) & population.filled[:, 0]
        position = held.nonzero().squeeze(1)
        if position.numel():
            k = get_model(name).n_params
            best[name] = (population.theta[position, 0, :k], position)
    return best


def arm_signatures(arena: Arena, population: Population) -> list[Signature]:
    """The residual signatures of a population's best particle per pair on the
    fit windows (:mod:`torchcf.diagnose.signatures`)."""
    best = best_of(population)
    pairs = arena.fit.pairs
    closed = residual_series(best, pairs)
    one_step = one_step_residual(best, pairs)
    return signatures(closed, one_step, pairs.dt, arena.road_profile, arena.seed)


# ----------------------------------------------------------------- the ledger
class Ledger:
    """The attribution's finished arms, in ``RUN_DIR/loop/attribution.pt``.

    Keyed by the run's config hash, the diagnose settings and the candidate
    effects: an attribution run again with the same ones reads its finished
    arms back (their random numbers are seeded by their place, so the result
    is the one an uninterrupted run gives); any other key starts afresh.
    """

    def __init__(self, path: Path | None, key: str) -> None:
        self.path, self.key = path, key
        self.entries: dict[str, Any] = {}
        if path is not None and path.exists():
            try:
                raw = read_torch(path)
            except RunFileError:
                raw = None  # unreadable: computed again
            if (
                isinstance(raw, dict)
                and raw.get("format") == LEDGER_FORMAT
                and raw.get("key") == key
            ):
                self.entries = raw["entries"]

    def get(self, name: str) -> Any:
        return self.entries.get(name)

    def put(self, name: str, value: Any) -> None:
        self.entries[name] = value
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic_torch_save(
                {"format": LEDGER_FORMAT, "key": self.key, "entries": self.entries},
                self.path,
            )


def _to_dict(population: Population) -> dict[str, Any]:
    return {
        "models": list(population.models),
        "model": population.model,
        "theta": population.theta,
        "score": population.score,
        "index": population.index,
    }


def _from_dict(raw: dict[str, Any]) -> Population:
    return Population(
        tuple(raw["models"]), raw["model"], raw["theta"], raw["score"], raw["index"]
    )


def ledger_key(cfg: TrainConfig, pool: list[str], effects: list[str]) -> str:
    """What the attribution's result depends on (its ledger's key): the run, the
    diagnose settings, the pool and the candidate effects."""
    settings = cfg.diagnose.model_dump(mode="json", exclude={"run_after_training"})
    text = json.dumps(settings, sort_keys=True)
    return f"{config_hash(cfg)}|{text}|{','.join(pool)}|{','.join(effects)}"


# ------------------------------------------------------------- the selection
@dataclass(frozen=True)
class Selection:
    """The forward selection's result (:func:`attribute_effects`).

    Attributes:
        steps: per step, the rows of the effects tested, in the order tested,
            each with its ``order``, ``level`` and ``significant``.
        signatures: per step, the residual signatures of the current model
            (the first: the pool's; one more after the last step: the final
            model's).
        chosen: the chosen effect tokens, in the order chosen.
        models: the final model: the pool and the variants of the chosen
            effects.
        shared: per chosen shared effect name, its one value.
        steps_at_most: the selection's steps at most, ``min(max_effects, E)``.
        levels: the level of each step (they sum to ``alpha``).
    """

    steps: list[list[dict[str, Any]]]
    signatures: list[list[dict[str, Any]]]
    chosen: list[str]
    models: list[str]
    shared: dict[str, list[float]]
    steps_at_most: int
    levels: list[float]

    @property
    def shared_priors(self) -> dict[str, dict[str, tuple[float, float]]]:
        """Per chosen shared effect, its box of the last search round."""
        return {
            row["effect"]: row["shared"]["prior"]
            for rows in self.steps
            for row in rows
            if row["effect"] in self.chosen and "shared" in row
        }

    @property
    def estimates(self) -> dict[str, dict[str, float]]:
        """Per chosen effect, its estimate at the step it was chosen."""
        return {
            row["effect"]: row["estimate"]
            for rows in self.steps
            for row in rows
            if row["effect"] in self.chosen and row.get("chosen")
        }


def attribute_effects(
    cfg: TrainConfig,
    pool: list[str],
    effects: list[str],
    train_pairs: PairSet,
    *,
    road_seeds: dict[str, Tensor] | None = None,
    road_profile: RoadProfile | None = None,
    ledger: Path | None = None,
    progress: bool = True,
) -> Selection:
    """Choose effects by forward selection of nested arms (module docstring).

    Args:
        cfg: the run's config (its ``diagnose`` section sets the budgets).
        pool: the pool models that get the effects.
        effects: effect tokens (options resolved, see :func:`resolve_effect`).
        train_pairs: the run's training pairs.
        road_seeds: per road effect token, a first candidate of its value.
        road_profile: the road profile of the road signature (None: none).
        ledger: where finished arms are kept (None: nowhere, no resume).
        progress: show a progress bar (it moves every search round).

    Returns:
        the :class:`Selection`.
    """
    arena = Arena.of(
        cfg,
        train_pairs,
        road_seeds=dict(road_seeds or {}),
        road_profile=road_profile,
    )
    settings = arena.settings
    steps_at_most = min(settings.max_effects, len(effects))
    levels = step_levels(settings.alpha, steps_at_most)
    book = Ledger(ledger, ledger_key(cfg, pool, effects))
    per_arm = settings.rounds + 1
    bar = tqdm(
        total=per_arm * (1 + steps_at_most * (2 + len(effects))),
        desc="attribution",
        unit="round",
        disable=not progress,
    )

    def tick() -> None:
        bar.update()

    def cached(name: str, label: str, compute: Callable[..., Any], *args: Any) -> Any:
        """The ledger's entry ``name``, or ``compute(*args)`` kept there."""
        bar.set_postfix_str(label, refresh=True)
        hit = book.get(name)
        if hit is not None:
            bar.update(per_arm)
            return hit
        value = compute(*args)
        book.put(name, value)
        return value

    raw = cached("pool", "pool", _pool_entry, arena, pool, tick)
    arm = Arm((), _from_dict(raw), {})
    steps: list[list[dict[str, Any]]] = []
    found: list[list[dict[str, Any]]] = []
    remaining = list(effects)
    for step, level in enumerate(levels, start=1):
        marks = arm_signatures(arena, arm.population)
        found.append([s.report() for s in marks])
        pointed = pointed_effects([s for s in marks if s.found])
        raw = cached(
            f"{step}/base", f"step {step}: base", _base_entry, arena, arm, step, tick
        )
        base = _from_dict(raw)
        raw = cached(
            f"{step}/placebo",
            f"step {step}: placebo",
            _placebo_entry,
            arena,
            arm,
            base,
            step,
            tick,
        )
        placebo = _from_dict(raw)
        placebo_validation = pick_scores(placebo, arena.top_n, arena.validation).numpy()
        rows, arms = [], {}
        for effect in remaining:
            entry = cached(
                f"{step}/{effect}",
                f"step {step}: {effect.split('(')[0]}",
                _arm_entry,
                arena,
                arm,
                base,
                placebo,
                placebo_validation,
                effect,
                step,
                tick,
            )
            rows.append(dict(entry["row"]))
            arms[effect] = entry
        rows = _judge(test_order(rows, pointed), pointed, level, settings)
        steps.append(rows)
        best = max(
            (r for r in rows if r["significant"]), key=lambda r: r["gain"], default=None
        )
        if best is None:
            break
        best["chosen"] = True
        entry = arms[best["effect"]]
        shared = dict(arm.shared)
        if entry["value"] is not None:
            shared[parse_effect(best["effect"]).name] = entry["value"]
        raw = cached(
            f"{step}/converged",
            f"step {step}: {best['name']} converges",
            _converged_entry,
            arena,
            _from_dict(entry["population"]),
            shared,
            step,
            tick,
        )
        arm = Arm((*arm.effects, best["effect"]), _from_dict(raw), shared)
        remaining.remove(best["effect"])
        if not remaining:
            break
    if arm.effects:  # the final model's signatures: what the effects left
        found.append([s.report() for s in arm_signatures(arena, arm.population)])
    bar.close()
    models = list(dict.fromkeys([*pool, *_variants(arm, pool)]))
    return Selection(
        steps=steps,
        signatures=found,
        chosen=list(arm.effects),
        models=models,
        shared={k: v.tolist() for k, v in arm.shared.items()},
        steps_at_most=steps_at_most,
        levels=levels,
    )


def _pool_entry(arena: Arena, pool: list[str], tick: Callable[[], None]) -> dict:
    """The pool's fit, as the ledger keeps it."""
    return _to_dict(fit_pool(arena, pool, tick).population)


def _converged_entry(
    arena: Arena,
    population: Population,
    shared: dict[str, Tensor],
    step: int,
    tick: Callable[[], None],
) -> dict[str, Any]:
    """A chosen arm converged, the next step's start, as the ledger keeps it."""
    return _to_dict(arena.converge(population, shared, ("step", step), tick))


def _base_entry(
    arena: Arena, arm: Arm, step: int, tick: Callable[[], None]
) -> dict[str, Any]:
    """A step's base arm, as the ledger keeps it."""
    return _to_dict(base_arm(arena, arm, step, tick))


def _variants(arm: Arm, pool: list[str]) -> list[str]:
    """The variants the final model holds (pool models with chosen effects)."""
    return [m for m in arm.population.models if m not in pool]


def _placebo_entry(
    arena: Arena, arm: Arm, base: Population, step: int, tick: Callable[[], None]
) -> dict[str, Any]:
    """A step's placebo arm, as the ledger keeps it."""
    return _to_dict(placebo_arm(arena, arm, base, step, tick))


def _arm_entry(
    arena: Arena,
    arm: Arm,
    base: Population,
    placebo: Population,
    placebo_validation: np.ndarray,
    effect: str,
    step: int,
    tick: Callable[[], None],
) -> dict[str, Any]:
    """An effect arm and its row, as the ledger keeps them."""
    result = effect_arm(arena, arm, base, effect, step, tick)
    row = effect_row(arena, effect, result, base, placebo, placebo_validation)
    return {
        "row": row,
        "population": _to_dict(result.population),
        "value": result.value,
    }


def _judge(
    rows: list[dict[str, Any]],
    pointed: dict[str, list[str]],
    level: float,
    settings: DiagnoseConfig,
) -> list[dict[str, Any]]:
    """The fallback procedure over the rows in their order: each row's
    ``order``, ``pointed_by``, ``level`` and ``significant``."""
    levels, significant = fallback_levels(
        [r["p_value"] for r in rows],
        [r["gain"] >= settings.min_gain for r in rows],
        level,
    )
    for i, (row, at, yes) in enumerate(zip(rows, levels, significant, strict=True)):
        row["order"] = i + 1
        row["pointed_by"] = pointed.get(row["name"], [])
        row["level"] = at
        row["significant"] = yes
        row["chosen"] = False
    return rows


__all__ = [
    "MIN_VALIDATION_STEPS",
    "Arena",
    "Arm",
    "EffectArm",
    "Ledger",
    "Selection",
    "arm_signatures",
    "attribute_effects",
    "base_arm",
    "effect_arm",
    "effect_row",
    "estimate",
    "fit_pool",
    "resolve_effect",
    "split_in_time",
    "test_order",
]
