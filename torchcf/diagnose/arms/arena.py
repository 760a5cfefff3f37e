"""The arms of the attribution: the current model, the placebo, and the current
model with one effect, each fitted on the fit windows (:mod:`torchcf.diagnose.
attribution` compares them).

Every step of the selection grows three kinds of arm from one start (the current
model, converged: :meth:`Arena.converge`):

- the **base arm** (:func:`base_arm`): the start searched ``rounds`` more
  rounds by itself;
- an **effect arm** per candidate effect E (:func:`effect_arm`): the start
  lifted to the variants ``m+E``, searched, and merged with the base arm, so it
  can never lose against it in sample;
- the **placebo arm** (:func:`placebo_arm`): the base arm merged with the same
  search of the current model alone. The effect arms are judged against it:
  both hold the base arm and one more search of equal budget and common random
  numbers, so their difference is the effect, not a second search (which alone
  lowers the error of a model short of its optimum).

An effect arm's search begins from **design points**: E fixed at ``G`` values
over its prior (:func:`design_values`: evenly for one parameter, followed from
the neutral value outwards; a Latin hypercube with the neutral point for
several), every pair's particles refitted at each (:func:`design_fits`: the
model's own parameters free to take E up, a continuation whose first step is
halved, :func:`first_steps_halved`, and whose later refits also start from the
secant's prediction, :func:`predicted`); a driver effect then searches from
each pair's best over the design points (each pair its own value), a
one-parameter shared effect from its best value (:func:`profile_search`), a road
profile of several knots from its one value searched jointly
(:func:`~torchcf.diagnose.arms.search.shared_value`). The placebo refits the start
``G`` times with the same budget and random numbers, without E (the
predictor's re-scorings, a fraction of one round, are the effect arm's own).

Shapes: N pairs, S slots, K parameters, G design points (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from ...abc.rejection import Rollout, prior_stream
from ...abc.smc import SMCSettings
from ...config import DiagnoseConfig
from ...data import PairSet
from ...models import CFModel
from ...models.effects import Effect, RoadProfile, parse_effect
from ..setup import LoopSetup
from .absorption import PROFILE_VALUES, profile_values
from .candidates import prior_particles
from .population import (
    Population,
    merge,
    particles_dict,
    particles_of,
    population_dict,
    population_of,
    rescore,
)
from .search import (
    INVALID_RATIO,
    Converging,
    Limits,
    Noise,
    converge,
    effect_prior,
    generator,
    lift,
    local_search,
    model_bounds,
    shared_value,
)
from .validation import Validation, design

#: Multiples of the secant the continuation's predictor tries (each a re-scoring
#: of the start, far cheaper than a search round): the refit before is short of
#: the ridge, so its secant is too.
PREDICTOR_REACH = (0.5, 1.0, 2.0)
#: Design points of a driver effect (and of the placebo's refits).
DESIGN_POINTS = 5


class Checkpoints(Protocol):
    """Where a long fit keeps its state as it goes (the attribution's ledger)."""

    def get(self, name: str) -> Any:
        """The state kept under ``name``, or None."""

    def keep(self, name: str, value: Any, *, now: bool = False) -> None:
        """Keep ``value`` under ``name``: written to disk now, or with the next
        write when the last was recent (:data:`torchcf.diagnose.arms.ledger.
        CHECKPOINT_SECONDS`)."""


def resolve_effect(token: str, pairs: PairSet) -> Effect:
    """The effect of a configured token (where effects enter the loop); a bare
    road effect (``grade``, ``bend``) spans the pairs' road section (its knots:
    see :mod:`torchcf.diagnose.signatures.road`), or the whole lap, periodic, when the
    pairs' road is a closed track (``pairs.road_period``)."""
    effect = parse_effect(token)
    if isinstance(effect, RoadProfile) and "(" not in token:
        return spanning(effect, pairs)
    return effect


def spanning(effect: RoadProfile, pairs: PairSet) -> RoadProfile:
    """The road profile of ``effect``'s kind and knots over the pairs' road
    section, or over the whole lap, periodic, on a closed track."""
    if pairs.road_period:
        # A closed track: the lap from its reference point, periodic.
        return type(effect)(period=pairs.road_period, knots=effect.knots)
    x = pairs.x_follow[pairs.mask]
    start, end = math.floor(float(x.min())), math.ceil(float(x.max()))
    return type(effect)(start=start, end=max(end, start + 1), knots=effect.knots)


# ------------------------------------------------------------------ the arena
@dataclass(frozen=True)
class Arena:
    """What every arm of an attribution shares.

    Attributes:
        settings: the run's ``diagnose`` section (budgets, search, test).
        fit: simulates on the fit windows (or the fit pairs' whole windows).
        validation: judges an arm out of sample (:mod:`torchcf.diagnose.
            validation`).
        seed: the seed every random draw of the attribution derives from
            (:attr:`LoopSetup.seed <torchcf.diagnose.setup.LoopSetup>`).
        priors: the run's prior box (K, 2) per pool model.
        top_n: N, the particles per pair an arm is judged by.
        smc: the small ABC's refinement when ``diagnose.method = "smc"``, else
            None (rejection).
        road_seeds: per road effect, a first candidate of its value.
        road_profile: the road profile whose signature is tested (None: the
            pairs have a frame each).
    """

    settings: DiagnoseConfig
    fit: Rollout
    validation: Validation
    seed: int
    priors: dict[str, Tensor]
    top_n: int
    smc: SMCSettings | None = None
    road_seeds: dict[Effect, Tensor] = dataclasses.field(default_factory=dict)
    road_profile: RoadProfile | None = None

    @classmethod
    def of(
        cls,
        setup: LoopSetup,
        train_pairs: PairSet,
        groups: Tensor | None = None,
        **extra: Any,
    ) -> Arena:
        """The arena of the loop's setup on the training pairs, split as
        ``diagnose.validation`` asks (``groups``: (N,) the pairs' drivers or
        runs, which cross-fitting keeps apart; None: each pair its own)."""
        fit, validation = design(setup, train_pairs, setup.seed, groups)
        return cls(
            settings=setup.settings,
            fit=fit,
            validation=validation,
            seed=setup.seed,
            priors=setup.priors,
            top_n=setup.top_n,
            smc=setup.smc,
            **extra,
        )

    @property
    def size(self) -> int:
        """S, the slots per pair of every arm (at least ``top_n``)."""
        return max(self.settings.population, self.top_n)

    def bounds(self, models: Any, shared: dict[str, Tensor]) -> dict[CFModel, Tensor]:
        """Prior box of each model, shared effects pinned at their values."""
        return {m: model_bounds(m, self.priors, shared) for m in models}

    def converge(
        self,
        population: Population,
        shared: dict[str, Tensor],
        label: tuple,
        tick: Callable[[], None],
        checkpoints: Checkpoints | None = None,
    ) -> Population:
        """Local search on the fit windows until it converges (at most
        ``max_rounds`` rounds): the start of a step's comparisons. With
        ``checkpoints``, its state after a round is kept under the label (and a
        search interrupted there resumes from it); ``tick`` is called for every
        round, and for the rounds it stops short of ``max_rounds``, so that a
        progress bar counts ``max_rounds``."""
        key = "/".join(map(str, ("converge", *label)))
        saved = checkpoints.get(key) if checkpoints is not None else None
        resume = None
        if saved is not None:
            resume = Converging(
                population_of(saved["population"]), saved["rounds"], saved["calm"]
            )
            for _ in range(resume.rounds):
                tick()

        def keep(state: Converging) -> None:
            tick()
            if checkpoints is not None:
                entry = {
                    "population": population_dict(state.population),
                    "rounds": state.rounds,
                    "calm": state.calm,
                }
                checkpoints.keep(key, entry)

        converged, rounds = converge(
            population,
            self.fit,
            self.bounds(population.models, shared),
            Noise((self.seed, "converge", *label), _current(population)),
            {m: m for m in population.models},
            Limits.of(self.settings),
            resume=resume,
            after_round=keep,
        )
        for _ in range(self.settings.max_rounds - rounds):
            tick()
        return converged

    def search(
        self,
        start: Population,
        noise: Noise,
        parents: dict[CFModel, CFModel],
        shared: dict[str, Tensor],
        tick: Callable[[], None] | None = None,
        depth: int = 1,
    ) -> Population:
        """Local search on the fit windows: ``rounds / depth`` rounds of
        ``local_copies / depth`` copies (at least one of each)."""
        return local_search(
            start,
            self.fit,
            self.bounds(start.models, shared),
            noise,
            parents,
            rounds=max(1, self.settings.rounds // depth),
            copies=max(1, self.settings.local_copies // depth),
            progress=tick,
        )


def _current(population: Population) -> dict[CFModel, tuple[str, ...]]:
    """Every model of a population as a current model (its own step columns)."""
    return {m: m.param_names for m in population.models}


# ------------------------------------------------------------------- the arms
@dataclass(frozen=True)
class Arm:
    """A model of the selection fitted on the fit windows: the pool, or the pool
    with the effects chosen so far.

    Attributes:
        effects: the chosen effects, in the order chosen.
        population: its particles (S per pair).
        shared: per chosen shared effect name, its one value (K_E,).
    """

    effects: tuple[Effect, ...]
    population: Population
    shared: dict[str, Tensor]


def fit_pool(
    arena: Arena,
    pool: list[CFModel],
    tick: Callable[..., None],
    checkpoints: Checkpoints | None = None,
) -> Arm:
    """The pool alone: a small ABC run of ``n_particles`` per model on the fit
    windows, its ``S`` best per pair, then local search until it converges.

    Args:
        tick: progress, in search rounds: each model's ABC run counts one
            (``tick(share)`` as it streams), the search ``max_rounds``.
        checkpoints: where each model's ABC result and the search's state are
            kept as they finish (a fit interrupted resumes from them).
    """
    sets = []
    for model in pool:
        key = f"abc/{model.name}"
        kept = checkpoints.get(key) if checkpoints is not None else None
        if kept is None:
            box = model_bounds(model, arena.priors)
            stream = prior_stream(model, box, arena.seed, arena.fit)
            (particles,) = prior_particles(
                stream,
                arena.fit,
                (arena.settings.n_particles,),
                arena.size,
                smc=arena.smc,
                progress=tick,
            )
            if checkpoints is not None:
                checkpoints.keep(key, particles_dict(particles), now=True)
        else:
            particles = particles_of(kept)
            tick(1.0)
        sets.append(particles)
    start = Population.from_particles(sets, arena.fit.pairs.n_pairs, arena.size)
    return Arm((), arena.converge(start, {}, ("pool",), tick, checkpoints), {})


def pool_units(arena: Arena, pool: list[CFModel]) -> int:
    """The pool's fit in the units of its progress (:func:`fit_pool`)."""
    return len(pool) + arena.settings.max_rounds


def arm_units(arena: Arena, effect: Effect | None) -> int:
    """An arm's search rounds, the units of its progress (at most: a shared
    value's refinements may skip a value outside the prior): the base arm
    (``effect`` None), or an effect arm's design points (and a one-parameter
    shared effect's refinements) and rounds."""
    rounds = max(1, arena.settings.rounds)
    if effect is None:
        return rounds
    if len(effect.param_specs) == 1:
        points = PROFILE_VALUES if effect.shared else DESIGN_POINTS
        design = first_steps_halved(effect, profile_values(effect, points)).shape[0]
        refine = LOCAL_POINTS if effect.shared else 0
        return design + refine + rounds
    return (0 if effect.shared else DESIGN_POINTS) + rounds


def placebo_units(arena: Arena) -> int:
    """The placebo arm's search rounds (:func:`placebo_arm`)."""
    return DESIGN_POINTS + 1 + max(1, arena.settings.rounds)


def base_arm(arena: Arena, arm: Arm, step: int, tick: Callable[[], None]) -> Population:
    """The current model searched ``rounds`` more rounds by itself: the part of
    every arm of step ``step`` that has no effect (an effect can never lose
    against it)."""
    population = arm.population
    noise = Noise((arena.seed, "step", step, "base"), _current(population))
    parents = {m: m for m in population.models}
    return arena.search(population, noise, parents, arm.shared, tick)


def extra_noise(arena: Arena, arm: Arm, step: int, effect: Effect | None) -> Noise:
    """The random numbers of a step's search after the design points: the
    placebo's, and every effect arm's (the same common columns, the effect's
    own besides)."""
    key = (arena.seed, "step", step, "extra")
    return Noise(key, _current(arm.population), effect)


def design_noise(
    arena: Arena, arm: Arm, step: int, g: int, effect: Effect | None
) -> Noise:
    """The random numbers of design point ``g``'s refit (the placebo's g-th
    refit draws the same common columns)."""
    key = (arena.seed, "step", step, "design", g)
    return Noise(key, _current(arm.population), effect)


def design_values(effect: Effect, key: tuple, points: int = DESIGN_POINTS) -> Tensor:
    """(G, K_E) the design points of an effect: a one-parameter effect's profile
    values (:func:`~torchcf.diagnose.arms.absorption.profile_values`, evenly over its
    prior), or, for several parameters, the neutral point and ``points - 1``
    points of a Latin hypercube over the prior."""
    if len(effect.param_specs) == 1:
        return first_steps_halved(effect, profile_values(effect, points))
    box = effect_prior(effect)
    k_e = box.shape[0]
    g = generator(*key, "design", effect)
    strata = torch.argsort(torch.rand(k_e, points - 1, generator=g), dim=-1)
    u = (strata + torch.rand(strata.shape, generator=g, dtype=torch.float64)) / (
        points - 1
    )
    spread = box[:, 0] + u.T * (box[:, 1] - box[:, 0])  # (G - 1, K_E)
    return torch.cat((torch.tensor([effect.neutral], dtype=torch.float64), spread))


def first_steps_halved(effect: Effect, values: Tensor) -> Tensor:
    """(G', 1) one-parameter design points ``values`` (G, 1, ascending) with a
    point added halfway between the neutral value and each neighbour: the
    continuation's first step from the neutral fit is the one without a
    predictor (:func:`predicted`), so it is kept short, and from the second on
    the secant carries the parameters that take the effect up."""
    neutral = effect.neutral[0]
    centre = int(torch.argmin((values[:, 0] - neutral).abs()))
    halves = [
        (values[centre, 0] + values[g, 0]) / 2
        for g in (centre - 1, centre + 1)
        if 0 <= g < values.shape[0]
    ]
    joined = torch.cat((values[:, 0], torch.stack(halves)))
    return torch.sort(joined).values[:, None]


def _refit(
    arena: Arena,
    arm: Arm,
    begin: Population,
    noise: Noise,
    parents: dict[CFModel, CFModel],
    shared: dict[str, Tensor],
) -> Population:
    """A design point's refit: ``rounds / 2`` rounds of ``local_copies / 2``
    copies."""
    return arena.search(begin, noise, parents, shared, depth=2)


def design_fits(
    arena: Arena,
    arm: Arm,
    effect: Effect,
    step: int,
    tick: Callable[[], None],
    values: Tensor,
) -> tuple[list[Population], dict[CFModel, CFModel]]:
    """The start refitted with E fixed at each design point ``values`` (G, K_E).

    A chain (a continuation): the first fit starts from the start lifted to
    E's neutral value, every later one from the fit before it, so that a
    parameter that absorbs E follows it along the ridge instead of jumping from
    its neutral fit. One parameter: from the neutral value outwards (both ways
    where it lies inside the prior); several: the points in their order (the
    neutral point first). The placebo's refits form the same chain.

    Returns:
        per point, its population, and per variant the model lifted from.
    """
    start = arm.population
    neutral = torch.tensor(effect.neutral, dtype=torch.float64)
    lifted, lifted_from = lift(
        start, effect, neutral, None if effect.exactly_neutral else arena.fit
    )
    parents = {m: m for m in start.models} | lifted_from
    fits: list[Population | None] = [None] * values.shape[0]

    def fit(g: int, origin: Population, before: int | None = None) -> None:
        shared = dict(arm.shared) | {effect.name: values[g]}
        starts = [repin(origin, effect, values[g], arena.fit)]
        if before is not None and values.shape[1] == 1:  # points on one line
            bounds = arena.bounds(origin.models, shared)
            for reach in PREDICTOR_REACH:
                ahead = predicted(
                    origin, fits[before], values, g, before, bounds, reach
                )
                starts.append(repin(ahead, effect, values[g], arena.fit))
        begin = merge(starts, arena.size)
        noise = design_noise(arena, arm, step, g, effect)
        fits[g] = _refit(arena, arm, begin, noise, parents, shared)
        tick()

    centre = int(torch.argmin((values - neutral).abs().sum(1)))
    fit(centre, lifted)
    for side in (range(centre - 1, -1, -1), range(centre + 1, values.shape[0])):
        previous, before = centre, None
        for g in side:
            fit(g, fits[previous], before)
            previous, before = g, previous
    return fits, lifted_from


def predicted(
    origin: Population,
    before: Population,
    values: Tensor,
    g: int,
    b: int,
    bounds: dict[CFModel, Tensor],
    reach: float = 1.0,
) -> Population:
    """The continuation's predictor: ``origin`` (the fit at the design point
    before g) moved along the secant of the two fits before g.

    Where a pair's best particle has the same model in ``before`` (the fit at
    point ``b``) and ``origin`` (at the point between b and g), every slot of
    that model is moved by the best particle's change per unit of E times the
    step to g, and clipped to its prior box: a parameter that takes E up keeps
    following it, so a long ridge (a standstill gap that traded for a sensor
    offset, a time gap for a delay) is followed in a few refits instead of
    being re-found by jitter. Slots of pairs without a common best model stay
    where they are; the scores are stale (the caller re-scores).
    """
    o = b + (1 if g > b else -1)  # origin's design point
    ratio = float((values[g, 0] - values[o, 0]) / (values[o, 0] - values[b, 0]))
    theta = origin.theta.clone()
    best_model = origin.model[:, 0]
    same = (best_model >= 0) & (before.model[:, 0] >= 0)
    models_before = list(before.models)
    for m, model in enumerate(origin.models):
        if model not in models_before:
            continue
        pairs = (
            same
            & (best_model == m)
            & (before.model[:, 0] == models_before.index(model))
        )
        if not bool(pairs.any()):
            continue
        k = model.n_params
        change = origin.theta[pairs, 0, :k] - before.theta[pairs, 0, :k]  # (Q, K)
        change = torch.nan_to_num(change) * ratio * reach
        held = (origin.model[pairs] == m)[..., None]  # (Q, S, 1)
        box = bounds[model]
        moved = theta[pairs, :, :k] + held * change[:, None, :]
        moved = torch.maximum(torch.minimum(moved, box[:, 1]), box[:, 0])
        theta[pairs, :, :k] = torch.where(held, moved, theta[pairs, :, :k])
    return Population(origin.models, origin.model, theta, origin.score, origin.index)


def placebo_arm(
    arena: Arena, arm: Arm, base: Population, step: int, tick: Callable[[], None]
) -> Population:
    """The base arm merged with the search a driver effect's arm makes, of the
    current model alone: a chain of ``DESIGN_POINTS + 1`` refits of the start (each
    from the one before, as a driver effect's design points from its neutral
    value) with the design points' budgets and common random numbers, each
    pair's best over them, then ``rounds`` rounds with the effect arms' random
    numbers."""
    start = arm.population
    parents = {m: m for m in start.models}
    fits = []
    for g in range(DESIGN_POINTS + 1):  # as a one-parameter effect's chain
        noise = design_noise(arena, arm, step, g, None)
        origin = fits[-1] if fits else start
        fits.append(_refit(arena, arm, origin, noise, parents, arm.shared))
        tick()
    begin = merge(fits, arena.size)
    noise = extra_noise(arena, arm, step, None)
    searched = arena.search(begin, noise, parents, arm.shared, tick)
    return merge([base, searched], arena.size)


@dataclass(frozen=True)
class EffectArm:
    """An effect arm's result.

    Attributes:
        population: per pair its S best of the base arm and the search with E.
        lifted_from: per variant carrying E, the model it was lifted from.
        value: a shared effect's one value (K_E,), else None.
        shared_prior: a shared effect's box (K_E, 2) around its value.
        design: a one-parameter effect's design points (G, 1) and the fit at
            each (its profile), else None.
        interval: a one-parameter shared effect's 90 % interval (2,) over
            pairs (:func:`profile_interval`), else None.
    """

    population: Population
    lifted_from: dict[CFModel, CFModel]
    value: Tensor | None = None
    shared_prior: Tensor | None = None
    design: tuple[Tensor, list[Population]] | None = None
    interval: Tensor | None = None


def effect_arm(
    arena: Arena,
    arm: Arm,
    base: Population,
    effect: Effect,
    step: int,
    tick: Callable[[], None],
) -> EffectArm:
    """The current model with E (module docstring), merged with the base arm."""
    start = arm.population
    key = (arena.seed, "step", step)
    noise = extra_noise(arena, arm, step, effect)
    shared = dict(arm.shared)
    value = box = design = None
    interval = None
    if effect.shared and len(effect.param_specs) == 1:
        value, values, fits, lifted_from, interval = profile_search(
            arena, arm, effect, step, tick
        )
        design, box = (values, fits), _box_around(values, value)
        shared[effect.name] = value
        begin = fits[int(torch.argmin((values[:, 0] - value[0]).abs()))]
    elif effect.shared:
        value, box, _ = shared_value(
            effect,
            start,
            arena.fit,
            arena.bounds(start.models, shared),
            effect_prior(effect),
            (*key, effect),
            start=[arena.road_seeds[effect]] if effect in arena.road_seeds else [],
        )
        shared[effect.name] = value
        lifted, lifted_from = lift(start, effect, value, arena.fit)
        begin = merge([lifted], arena.size)
    else:
        values = design_values(effect, key)
        fits, lifted_from = design_fits(arena, arm, effect, step, tick, values)
        if len(effect.param_specs) == 1:
            design = (values, fits)
        begin = merge(fits, arena.size)
    parents = {m: m for m in start.models} | lifted_from
    searched = arena.search(begin, noise, parents, shared, tick)
    population = merge([base, searched], arena.size)
    return EffectArm(population, lifted_from, value, box, design, interval)


def profile_search(
    arena: Arena, arm: Arm, effect: Effect, step: int, tick: Callable[[], None]
) -> tuple[Tensor, Tensor, list[Population], dict[CFModel, CFModel], Tensor]:
    """A one-parameter shared effect's profile over its prior, and its value.

    The effect is fixed at the :data:`~torchcf.diagnose.arms.absorption.
    PROFILE_VALUES` values of its profile and the pairs refitted
    (:func:`design_fits`). Around the value whose fit is best (the mean over
    pairs of each pair's best score relative to the start's), a *local
    profile* of :data:`LOCAL_POINTS` values half a grid step apart is refitted,
    every value from the best's fit with the same budget (a comparison at equal
    depth: a value refitted once more would look better for that alone). The
    value is the minimum of the least-squares parabola through the local
    profile (:func:`parabola_minimum`): an estimate between the values tried,
    and its interval that of the same minimum over the pairs resampled
    (:func:`profile_interval`): wide where the profile is flat along a ridge.

    Returns:
        the value (1,), every value fitted (G, 1) ascending, their latest fits,
        per variant the model lifted from, and the value's 90 % interval (2,).
    """
    start = arm.population
    reference = start.score[:, 0]
    usable = torch.isfinite(reference) & (reference > 0)
    values = first_steps_halved(effect, profile_values(effect))
    fits, lifted_from = design_fits(arena, arm, effect, step, tick, values)
    parents = {m: m for m in start.models} | lifted_from

    def ratios(population: Population) -> Tensor:
        """(N',) each usable pair's best score relative to the start's."""
        ratio = population.score[usable, 0] / reference[usable]
        return torch.where(torch.isfinite(ratio), ratio, INVALID_RATIO)

    fitted = {
        float(v): (fit, ratios(fit))
        for v, fit in zip(values[:, 0].tolist(), fits, strict=True)
    }
    best = min(fitted, key=lambda v: float(fitted[v][1].mean()))
    half = float(values[-1, 0] - values[0, 0]) / (PROFILE_VALUES - 1) / 2
    low, high = effect.param_specs[0].lower, effect.param_specs[0].upper
    reach = (LOCAL_POINTS - 1) // 2
    local = {}
    origin = fitted[best][0]
    for k in range(-reach, reach + 1):
        value = best + k * half
        if not low <= value <= high:
            continue
        at = torch.tensor([value], dtype=torch.float64)
        begin = merge([repin(origin, effect, at, arena.fit)], arena.size)
        noise = Noise(
            (arena.seed, "step", step, "local", effect, k), _current(start), effect
        )
        shared = dict(arm.shared) | {effect.name: at}
        refit = _refit(arena, arm, begin, noise, parents, shared)
        local[value] = (refit, ratios(refit))
        tick()
    grid = sorted(local)
    table = torch.stack([local[v][1] for v in grid])  # (G', N')
    x = torch.tensor(grid, dtype=torch.float64)
    value = parabola_minimum(x, table.mean(1), best)
    interval = profile_interval(x, table, best, (arena.seed, "interval", effect))
    nearest = grid[int(torch.argmin((x - value).abs()))]
    fitted |= {v: local[v] for v in grid}
    fitted[value] = (local[nearest][0], local[nearest][1])  # its start: the nearest
    order = sorted(fitted)
    return (
        torch.tensor([value], dtype=torch.float64),
        torch.tensor(order, dtype=torch.float64)[:, None],
        [fitted[v][0] for v in order],
        lifted_from,
        interval,
    )


#: Values of a one-parameter shared effect's local profile around the grid's
#: best, half a grid step apart (odd: the best in the middle).
LOCAL_POINTS = 7
#: Resamples of the pairs for a shared value's interval.
BOOTSTRAP = 200


def parabola_minimum(x: Tensor, y: Tensor, best: float) -> float:
    """The minimum over ``[x.min(), x.max()]`` of the least-squares parabola
    through the points (x, y) (G,); ``best`` where there are fewer than three.
    Without a minimum inside (a profile that keeps falling), the lower end.
    (The normal equations solved in float64 by numpy: the same digits whatever
    the threads.)"""
    if x.numel() < 3:
        return best
    xs, ys = x.double().numpy(), y.double().numpy()
    centre = float(xs.mean())
    scale = float(xs.max() - xs.min()) / 2 or 1.0
    u = (xs - centre) / scale
    design = np.stack((u * u, u, np.ones_like(u)), axis=1)
    a, b, _ = np.linalg.solve(design.T @ design, design.T @ ys)
    lowest, highest = float(u.min()), float(u.max())
    if a > 0:
        vertex = min(max(-b / (2 * a), lowest), highest)
    else:
        left = a * lowest * lowest + b * lowest
        right = a * highest * highest + b * highest
        vertex = lowest if left <= right else highest
    return centre + scale * float(vertex)


def profile_interval(x: Tensor, ratios: Tensor, best: float, key: tuple) -> Tensor:
    """(2,) the 90 % interval of a shared value over pairs: the pairs resampled
    :data:`BOOTSTRAP` times, each resample's local profile (the mean of its
    pairs' relative scores ``ratios`` (G', N') at the values ``x``) minimised
    as the value itself was (:func:`parabola_minimum`)."""
    g = generator(*key)
    n = ratios.shape[1]
    found = [
        parabola_minimum(
            x, ratios[:, torch.randint(n, (n,), generator=g)].mean(1), best
        )
        for _ in range(BOOTSTRAP)
    ]
    quantiles = torch.tensor([0.05, 0.95], dtype=torch.float64)
    return torch.quantile(torch.tensor(found, dtype=torch.float64), quantiles)


def repin(
    population: Population, effect: Effect, value: Tensor, rollout: Rollout
) -> Population:
    """The population with the effect's parameters of every slot that carries
    it set to ``value`` (K_E,), re-scored on the rollout's pairs (slot order
    unchanged)."""
    names = [p.name for p in effect.param_specs]
    theta = population.theta.clone()
    for m, model in enumerate(population.models):
        if effect.name not in model.effect_kinds:
            continue
        held = population.model == m
        columns = [model.param_names.index(n) for n in names]
        rows = theta[held]
        rows[:, columns] = value.to(torch.float64)
        theta[held] = rows
    return rescore(
        Population(
            population.models, population.model, theta, population.score,
            population.index,
        ),
        rollout,
    )  # fmt: skip


def _box_around(values: Tensor, value: Tensor) -> Tensor:
    """(1, 2) the box between the profile values next to ``value``."""
    grid = values[:, 0]
    i = int(torch.argmin((grid - value[0]).abs()))
    low = grid[max(i - 1, 0)]
    high = grid[min(i + 1, grid.numel() - 1)]
    if not high > low:
        high = low + 1e-6
    return torch.stack((low, high))[None, :]


__all__ = [
    "Checkpoints",
    "DESIGN_POINTS",
    "PREDICTOR_REACH",
    "first_steps_halved",
    "predicted",
    "LOCAL_POINTS",
    "Arena",
    "Arm",
    "EffectArm",
    "base_arm",
    "design_fits",
    "design_values",
    "effect_arm",
    "arm_units",
    "fit_pool",
    "placebo_units",
    "pool_units",
    "placebo_arm",
    "profile_search",
    "repin",
    "resolve_effect",
    "spanning",
]
