"""Attribution: which candidate effects lower the out-of-sample error (loop step 2).

The training data are split (:mod:`torchcf.diagnose.arms.validation`): in time, the
arms fitted on every pair's first ``fit_fraction`` of steps (the *fit windows*)
and judged on the rest (the *validation windows*); by pair, fitted on
``fit_fraction`` of the pairs and judged on the others, held out whole; or
cross-fitted (the default from 15 pairs), fitted on every pair and each pair
judged by a refit started from the other drivers' picks only.

**The arms** (:mod:`torchcf.diagnose.arms.arena`). The current model (at first the
active pool) is fitted on the fit windows until its search converges. Each step
of the selection then grows, from that one start, the base arm, the placebo arm
and an effect arm per candidate effect. An effect arm holds the base arm, so
**an effect cannot lose in sample**; it is judged against the placebo, which
holds the same base arm and the same extra search with common random numbers,
without the effect.

**The test.** Per validation unit, the arm's out-of-sample score
(:meth:`~torchcf.diagnose.arms.validation.Validation.scores`: a pair's ``top_n`` best,
the hybrid's picks, on its validation window, their median; a held-out
pair's best score among all the picks; or a pair's score after its refit with
and without the effect: :class:`~torchcf.diagnose.arms.validation.Judge`). Twins
that one signature points to are tested as one family (:func:`_judge`). The
effect's gain is the relative drop
of the summed score against the placebo, its p-value the one-sided sign-flip
test of the per-unit log ratios (:mod:`torchcf.diagnose.significance`).

**The order and the guard.** The residual signatures of the current model on the
fit windows (:mod:`torchcf.diagnose.signatures.families`) point to effects; the effects
of
a step are tested in the order: pointed to by a signature first, then by their
in-sample gain against the placebo (:func:`test_order`), with the fallback
procedure at the step's level (:func:`~torchcf.diagnose.significance.
fallback_levels`, :func:`~torchcf.diagnose.significance.step_levels`), and an effect
must also gain at least ``min_gain``. Among the significant effects the one of
largest gain is chosen (a recording effect only by a clear margin over a
behavioural one: :func:`choose`), its arm converges and becomes the current
model, and the others are tested again, until none is significant or
``max_effects`` are chosen. An effect whose estimate stays at its neutral value
is no effect, whatever its gain (:func:`active`).

**Absorption.** Every effect arm reports which of the model's own parameters
takes the effect up (:mod:`torchcf.diagnose.arms.absorption`).

**Resume.** Every arm is a pure function of the run, the settings and its place
in the selection (its random numbers are seeded by that place,
:func:`~torchcf.diagnose.arms.search.derive_seed`), and is written to
``RUN_DIR/loop/attribution.pt`` when done (:class:`Ledger`): an interrupted
attribution run again continues after its last finished arm, with the same
result.

Shapes: N pairs, S slots per pair, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ...config import DiagnoseConfig
from ...data import PairSet
from ...models import CFModel, require_model
from ...models.effects import Effect, RoadProfile
from ...system.files import (
    TorchPayload,
)
from ...system.records import to_json_value
from ..arms.absorption import Steady, absorbed_by, profile_absorption
from ..arms.arena import (
    Arena,
    Arm,
    Checkpoints,
    EffectArm,
    arm_units,
    base_arm,
    effect_arm,
    fit_pool,
    placebo_arm,
    placebo_units,
    pool_units,
)
from ..arms.ledger import (
    LEDGER_FORMAT,
    Ledger,
    ledger_key,
    resuming,
)
from ..arms.population import Population, population_dict, population_of
from ..arms.refit import Pin
from ..arms.search import INVALID_RATIO
from ..arms.validation import Judge, refits
from ..setup import LoopSetup
from ..signatures.families import Signature, SignatureRow, pointed_effects, signatures
from ..signatures.road import one_step_residual
from ..signatures.series import BestParticles, residual_series
from ..significance import (
    comparable,
    fallback_levels,
    level_weights,
    max_flip_test,
    sign_flip_test,
    step_levels,
)
from ..workers import ArmPool, worker_count
from ..workers import tick as worker_tick
from .power import detectable_sizes
from .tested import Detectable, EffectTest, SharedValue


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
    pairs valid on at least one side (:func:`~torchcf.diagnose.significance.
    comparable`: an invalid side counts :data:`~torchcf.diagnose.arms.search.
    INVALID_RATIO` times the valid one)."""
    usable, before, after = comparable(before, after, INVALID_RATIO)
    if not usable.any():
        return 0.0, np.empty(0)
    gain = float((before[usable] - after[usable]).sum() / before[usable].sum())
    return gain, np.log(before[usable] / after[usable])


def estimate(population: Population, effect: Effect, n: int) -> dict[str, float]:
    """Median of the effect's parameters over the ``n`` best per pair that carry
    it."""
    names = [p.name for p in effect.param_specs]
    picks = population.best(n)
    values = []
    for model in picks.models:
        if effect.name not in model.effect_kinds:
            continue
        pair, slot = picks.model_slots(model)
        columns = [model.param_names.index(p) for p in names]
        values.append(picks.theta[pair, slot][:, columns])
    if not values or not sum(v.shape[0] for v in values):
        return {}
    median = torch.cat(values).median(dim=0).values
    return dict(zip(names, median.tolist(), strict=True))


def pinned(effect: Effect, result: EffectArm, estimate: dict[str, float]) -> Pin:
    """The value an effect is held at on the held-out pairs (validation
    ``"refit"``): a shared effect's one value, a driver effect's estimate (the
    median over the arm's picks that carry it; neutral where none does)."""
    if result.value is not None:
        return Pin(effect, result.value.to(torch.float64))
    value = [
        estimate.get(p.name, neutral)
        for p, neutral in zip(effect.param_specs, effect.neutral, strict=True)
    ]
    return Pin(effect, torch.tensor(value, dtype=torch.float64))


def effect_row(
    arena: Arena,
    effect: Effect,
    result: EffectArm,
    base: Population,
    placebo: Population,
    judge: Judge,
) -> EffectTest:
    """The effect's test against the placebo: in-sample and validation gain,
    sign-flip test, scores, estimate, absorption (the order and the verdict come
    later, :func:`_judge`)."""
    n = arena.top_n
    mine = _fit_statistic(result.population, n).numpy()
    fit_gain, _ = _relative_drop(_fit_statistic(placebo, n).numpy(), mine)
    base_fit_gain, _ = _relative_drop(_fit_statistic(base, n).numpy(), mine)
    found = estimate(result.population, effect, n)
    pin = pinned(effect, result, found)
    placebo_validation, after = judge(result.population, result.lifted_from, pin)
    gain, drops = _relative_drop(placebo_validation, after)
    statistic, p_value = sign_flip_test(drops, arena.settings.permutations)
    usable, placebo_validation, after = comparable(
        placebo_validation, after, INVALID_RATIO
    )
    names = [p.name for p in effect.param_specs]
    row = EffectTest(
        effect=effect,
        fit_gain=fit_gain,
        base_fit_gain=base_fit_gain,
        gain=gain,
        statistic=statistic,
        p_value=p_value,
        score_before=float(placebo_validation[usable].mean()) if usable.any() else None,
        score_after=float(after[usable].mean()) if usable.any() else None,
        n_pairs=int(usable.sum()),
        pairs_changed=int(np.count_nonzero(drops)),
        pinned=dict(zip(names, pin.value.tolist(), strict=True))
        if refits(judge.validation.kind)
        else None,
        variants=sorted(m.name for m in result.lifted_from),
        estimate=found,
        per_pair={
            "before": [_finite_or_none(v) for v in placebo_validation.tolist()],
            "after": [_finite_or_none(v) for v in after.tolist()],
        },
    )
    if result.value is not None:
        row.shared = SharedValue(
            value=dict(zip(names, result.value.tolist(), strict=True)),
            prior={
                k: tuple(b)
                for k, b in zip(names, result.shared_prior.tolist(), strict=True)
            },
            interval=None
            if result.interval is None
            else {names[0]: result.interval.tolist()},
        )
        row.estimate = row.shared.value
    row.active = active(effect, row.estimate)
    if result.design is not None:
        values, fits = result.design
        found = result.value
        if found is None and row.estimate:  # a driver effect: the picks' median
            found = torch.tensor(list(row.estimate.values()), dtype=torch.float64)
        row.absorbed_by = profile_absorption(
            effect, values, fits, result.lifted_from, base, found, _steady(arena)
        )
    elif not effect.shared:
        row.absorbed_by = absorbed_by(
            effect, result.population, base, result.lifted_from
        )
    return row


def _steady(arena: Arena) -> Steady:
    """Where the pool's steady state is read for absorption: the fit pairs'
    median follower speed."""
    pairs = arena.fit.pairs
    speed = float(pairs.v_follow[pairs.mask].double().median())
    return Steady(max(speed, 1.0), pairs.dt, pairs.leader_length)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def test_order(
    rows: list[EffectTest], pointed: dict[str, list[str]]
) -> list[EffectTest]:
    """The order of a step's tests, fixed by the fit windows: the effects a
    found signature points to first, then the others; within each, the larger
    in-sample gain first (then the token)."""
    return sorted(
        rows,
        key=lambda r: (r.name not in pointed, -r.fit_gain, r.token),
    )


# ---------------------------------------------------------- the signatures
def best_of(population: Population) -> BestParticles:
    """Each pair's best particle, grouped by model (the residuals' input)."""
    best: BestParticles = {}
    for m, model in enumerate(population.models):
        held = (population.model[:, 0] == m) & population.filled[:, 0]
        position = held.nonzero().squeeze(1)
        if position.numel():
            k = model.n_params
            best[model] = (population.theta[position, 0, :k], position)
    return best


def arm_signatures(arena: Arena, population: Population) -> list[Signature]:
    """The residual signatures of a population's best particle per pair on the
    fit windows (:mod:`torchcf.diagnose.signatures.families`)."""
    best = best_of(population)
    pairs = arena.fit.pairs
    closed = residual_series(best, pairs)
    one_step = one_step_residual(best, pairs)
    return signatures(closed, one_step, pairs.dt, arena.road_profile, arena.seed)


# ------------------------------------------------------------- the selection
@dataclass(frozen=True)
class RoadStart:
    """How road effects enter an attribution.

    Attributes:
        seeds: per road effect, a first candidate of its value.
        profile: the road profile of the road signature (None: none).
    """

    seeds: dict[Effect, Tensor] = dataclasses.field(default_factory=dict)
    profile: RoadProfile | None = None


@dataclass(frozen=True)
class JudgedOn:
    """How the arms of a selection were judged out of sample.

    Attributes:
        kind: ``"time"``, ``"pairs"`` or ``"refit"``
            (:mod:`torchcf.diagnose.arms.validation`).
        units: the validation units (pair windows or held-out pairs).
        fit_pairs: the pairs the arms were fitted on.
    """

    kind: str
    units: int
    fit_pairs: int


@dataclass(frozen=True)
class EffectSelection:
    """The forward selection's result (:func:`attribute_effects`); not
    :class:`torchcf.abc.hybrid.Selection`, the hybrid's members.

    Attributes:
        steps: per step, the effects tested, in the order tested, each with
            its verdict.
        signatures: per step, the residual signatures of the current model
            (the first: the pool's; one more after the last step: the final
            model's).
        chosen: the chosen effects, in the order chosen.
        models: the final model: the pool and the variants of the chosen
            effects.
        shared: per chosen shared effect name, its one value.
        steps_at_most: the selection's steps at most, ``min(max_effects, E)``.
        levels: the level of each step (they sum to ``alpha``).
        validation: how the arms were judged.
        start: the pool's converged fit on the fit part (the model class
            without effects); final: the final model's (with the chosen
            effects); both for the test split's class judgement
            (:mod:`torchcf.diagnose.selection.on_test`), not written to ``loop.json``.
    """

    steps: list[list[EffectTest]]
    signatures: list[list[SignatureRow]]
    chosen: list[Effect]
    models: list[CFModel]
    shared: dict[str, list[float]]
    steps_at_most: int
    levels: list[float]
    validation: JudgedOn
    start: Population | None = None
    final: Population | None = None

    @property
    def shared_priors(self) -> dict[str, dict[str, tuple[float, float]]]:
        """Per chosen shared effect's token, its box of the last search round."""
        return {
            row.token: row.shared.prior
            for rows in self.steps
            for row in rows
            if row.effect in self.chosen and row.shared is not None
        }

    @property
    def estimates(self) -> dict[str, dict[str, float]]:
        """Per chosen effect's token, its estimate at the step it was chosen."""
        return {
            row.token: row.estimate
            for rows in self.steps
            for row in rows
            if row.effect in self.chosen and row.chosen
        }


def attribute_effects(
    setup: LoopSetup,
    pool: Sequence[CFModel],
    effects: list[Effect],
    train_pairs: PairSet,
    *,
    road: RoadStart | None = None,
    groups: Tensor | None = None,
    ledger: Path | None = None,
    progress: bool = True,
) -> EffectSelection:
    """Choose effects by forward selection of nested arms (module docstring).

    Args:
        setup: the loop's setup (its ``diagnose`` settings set the budgets).
        pool: the pool models that get the effects (model objects; the
            ledger is keyed by their names).
        effects: the candidate effects (options resolved, see
            :func:`~torchcf.diagnose.arms.arena.resolve_effect`).
        train_pairs: the run's training pairs.
        road: how road effects start (:class:`RoadStart`; None: no seeds, no
            road signature).
        groups: (N,) int64 each training pair's driver or run (cross-fitting
            never refits a pair from its own group's picks; None: each pair
            its own group).
        ledger: where finished arms are kept (None: nowhere, no resume).
        progress: show a progress bar (it moves every search round).

    Returns:
        the :class:`EffectSelection`.
    """
    arena = Arena.of(
        setup,
        train_pairs,
        groups,
        road_seeds=dict(road.seeds) if road else {},
        road_profile=road.profile if road else None,
    )
    settings = arena.settings
    steps_at_most = min(settings.max_effects, len(effects))
    levels = step_levels(settings.alpha, steps_at_most)
    models = [require_model(m, "attribute_effects") for m in pool]
    book = Ledger(ledger, ledger_key(setup, [m.name for m in models], effects))
    if progress and book.entries:
        print(resuming(book), file=sys.stderr, flush=True)
    units = {effect: arm_units(arena, effect) for effect in effects}
    per_step = arm_units(arena, None) + placebo_units(arena) + settings.max_rounds
    tested = sum(len(effects) - s for s in range(steps_at_most))  # effect arms
    bar = tqdm(
        total=pool_units(arena, models)
        + steps_at_most * per_step
        + round(tested * sum(units.values()) / max(1, len(units))),
        desc="attribution",
        unit="round",
        disable=not progress,
    )

    def tick(amount: float = 1.0) -> None:
        bar.update(amount)

    counted: set[str] = set()  # stages the bar counted already (in workers)

    def cached(
        name: str, label: str, size: int, compute: Callable[..., Any], *args: Any
    ) -> Any:
        """The ledger's entry ``name``, or ``compute(*args)`` kept there; the
        bar advances by the stage's ``size`` in search rounds either way."""
        bar.set_postfix_str(label, refresh=True)
        began = bar.n
        value = book.get(name)
        if value is None:
            value = compute(*args)
            book.put(name, value)
        if name not in counted and bar.n - began < size:
            bar.update(size - (bar.n - began))
        return value

    raw = cached(
        "pool",
        "pool",
        pool_units(arena, models),
        _pool_entry,
        arena,
        models,
        tick,
        book.within("pool"),
    )
    arm = Arm((), population_of(raw), {})
    start = arm.population
    steps: list[list[EffectTest]] = []
    found: list[list[SignatureRow]] = []
    remaining = list(effects)
    processes: ArmPool | None = None  # worker processes, where they pay
    with contextlib.ExitStack() as stack:
        for step, level in enumerate(levels, start=1):
            marks = arm_signatures(arena, arm.population)
            found.append([s.report() for s in marks])
            pointed = pointed_effects([s for s in marks if s.found])
            raw = cached(
                f"{step}/base",
                f"step {step}: base",
                arm_units(arena, None),
                _base_entry,
                arena,
                arm,
                step,
                tick,
            )
            base = population_of(raw)
            raw = cached(
                f"{step}/placebo",
                f"step {step}: placebo",
                placebo_units(arena),
                _placebo_entry,
                arena,
                arm,
                base,
                step,
                tick,
            )
            placebo = population_of(raw)
            judge = arena.validation.judge(placebo, arena.top_n, step, arm.shared)
            todo = [e for e in remaining if book.get(f"{step}/{e}") is None]
            count = worker_count(settings.workers, len(todo), round_steps(arena))
            if count > 1:
                if processes is None:
                    processes = stack.enter_context(ArmPool(count, tick))
                bar.set_postfix_str(f"step {step}: {len(todo)} arms", refresh=True)
                began = bar.n
                tasks = [
                    (e, (arena, arm, base, placebo, judge, e, step, worker_tick))
                    for e in todo
                ]
                for effect, entry in processes.results(_arm_entry, tasks):
                    book.put(f"{step}/{effect}", entry)
                    counted.add(f"{step}/{effect}")
                due = sum(units[e] for e in todo)
                if bar.n - began < due:
                    bar.update(due - (bar.n - began))
            rows, arms = [], {}
            for effect in remaining:
                entry = cached(
                    f"{step}/{effect}",
                    f"step {step}: {effect.name}",
                    units[effect],
                    _arm_entry,
                    arena,
                    arm,
                    base,
                    placebo,
                    judge,
                    effect,
                    step,
                    tick,
                )
                rows.append(EffectTest.from_json(entry["row"]))
                arms[effect] = entry
            rows = _judge(test_order(rows, pointed), pointed, level, settings)
            steps.append(rows)
            best = choose(rows, settings.min_gain)
            if best is None and step == 1 and settings.detectable:
                # nothing chosen at all: what the data could have shown (after
                # a choice the chosen effect's own test says what was seen)
                sizes = book.get(f"{step}/detectable")
                if sizes is None:
                    detectable_sizes(
                        judge,
                        rows,
                        rows[0].level if rows else level,
                        settings.min_gain,
                        settings.permutations,
                        lambda label: bar.set_postfix_str(
                            f"step 1: detectable sizes, {label}", refresh=True
                        ),
                    )
                    sizes = {row.token: to_json_value(row.detectable) for row in rows}
                    book.put(f"{step}/detectable", sizes)
                else:  # an interrupted run's sizes, as the ledger keeps them
                    for row in rows:
                        kept = sizes.get(row.token)
                        row.detectable = (
                            None if kept is None else Detectable.from_json(kept)
                        )
            if best is None:
                break
            best.chosen = True
            chosen = best.effect
            entry = arms[chosen]
            shared = dict(arm.shared)
            if entry["value"] is not None:
                shared[chosen.name] = entry["value"]
            raw = cached(
                f"{step}/converged",
                f"step {step}: {best.name} converges",
                settings.max_rounds,
                _converged_entry,
                arena,
                population_of(entry["population"]),
                shared,
                step,
                tick,
                book.within(f"{step}/converged"),
            )
            arm = Arm((*arm.effects, chosen), population_of(raw), shared)
            remaining.remove(chosen)
            if not remaining:
                break
    if arm.effects:  # the final model's signatures: what the effects left
        found.append([s.report() for s in arm_signatures(arena, arm.population)])
    bar.total = bar.n  # a selection that stops early: done
    bar.close()
    return EffectSelection(
        steps=steps,
        signatures=found,
        chosen=list(arm.effects),
        models=list(dict.fromkeys([*models, *_variants(arm, models)])),
        shared={k: v.tolist() for k, v in arm.shared.items()},
        steps_at_most=steps_at_most,
        levels=levels,
        validation=JudgedOn(
            arena.validation.kind, arena.validation.n_units, arena.fit.pairs.n_pairs
        ),
        start=start,
        final=arm.population,
    )


def round_steps(arena: Arena) -> float:
    """Simulated steps of one search round of an arm (its cost)."""
    pairs = arena.fit.pairs
    return float(pairs.mask.sum()) * arena.size * arena.settings.local_copies


def _pool_entry(
    arena: Arena,
    pool: list[CFModel],
    tick: Callable[..., None],
    checkpoints: Checkpoints,
) -> TorchPayload:
    """The pool's fit, as the ledger keeps it (its state kept as it goes)."""
    return population_dict(fit_pool(arena, pool, tick, checkpoints).population)


def _converged_entry(
    arena: Arena,
    population: Population,
    shared: dict[str, Tensor],
    step: int,
    tick: Callable[[], None],
    checkpoints: Checkpoints,
) -> TorchPayload:
    """A chosen arm converged, the next step's start, as the ledger keeps it."""
    converged = arena.converge(population, shared, ("step", step), tick, checkpoints)
    return population_dict(converged)


def _base_entry(
    arena: Arena, arm: Arm, step: int, tick: Callable[[], None]
) -> TorchPayload:
    """A step's base arm, as the ledger keeps it."""
    return population_dict(base_arm(arena, arm, step, tick))


def _variants(arm: Arm, pool: list[CFModel]) -> list[CFModel]:
    """The variants the final model holds (pool models with chosen effects)."""
    return [m for m in arm.population.models if m not in pool]


def _placebo_entry(
    arena: Arena, arm: Arm, base: Population, step: int, tick: Callable[[], None]
) -> TorchPayload:
    """A step's placebo arm, as the ledger keeps it."""
    return population_dict(placebo_arm(arena, arm, base, step, tick))


def _arm_entry(
    arena: Arena,
    arm: Arm,
    base: Population,
    placebo: Population,
    judge: Judge,
    effect: Effect,
    step: int,
    tick: Callable[[], None],
) -> TorchPayload:
    """An effect arm and its row, as the ledger keeps them."""
    result = effect_arm(arena, arm, base, effect, step, tick)
    row = effect_row(arena, effect, result, base, placebo, judge)
    return {
        "row": row.to_json(),
        "population": population_dict(result.population),
        "value": result.value,
    }


#: Distance from the neutral value, as a share of the prior's width, from which
#: an effect's estimate is active (:func:`active`).
ACTIVE = 0.05


def active(effect: Effect, estimate: dict[str, float]) -> bool:
    """Whether an effect's estimate (its parameters' median over the arm's picks
    that carry it, or a shared effect's one value) lies at least
    :data:`ACTIVE` of its prior's width from the neutral value in some
    parameter. An effect arm whose best particles keep the effect neutral owes
    its gain to the search (a changed landscape that led it elsewhere), not to
    the effect."""
    for p, neutral in zip(effect.param_specs, effect.neutral, strict=True):
        value = estimate.get(p.name)
        if value is not None and abs(value - neutral) >= ACTIVE * (p.upper - p.lower):
            return True
    return False


def choose(rows: list[EffectTest], margin: float) -> EffectTest | None:
    """The effect a step chooses among its significant ones: the largest gain,
    except that a recording effect (a claim that the data are faulty: a sensor
    or clock offset) is chosen over a significant driver or road effect only
    when its gain is larger by more than ``margin`` (``diagnose.min_gain``).

    A clock offset and a reaction delay, a sensor offset and a standstill gap,
    explain much the same residual; where the validation cannot tell them
    apart, the behaviour is the explanation, and the recording one must earn
    its place by a clear gain."""
    significant = [r for r in rows if r.significant]
    if not significant:
        return None
    best = max(significant, key=lambda r: r.gain)
    behaviour = [r for r in significant if r.scope != "recording"]
    if best.scope == "recording" and behaviour:
        other = max(behaviour, key=lambda r: r.gain)
        if best.gain - other.gain <= margin:
            return other
    return best


def families(
    rows: list[EffectTest], pointed: dict[str, list[str]], scheme: str
) -> list[list[EffectTest]]:
    """The step's tests grouped in families, in the order of their first
    member: the effects that one found signature points to first (their
    twins: a response lag points to a delay, a clock offset and an actuation
    lag) form one family (``diagnose.families = "signature"``); every other
    effect, and every effect with ``"none"``, is a family of its own."""
    out: dict[str, list[EffectTest]] = {}
    for row in rows:
        signature = pointed.get(row.name, [None])[0]
        key = (
            f"signature:{signature}"
            if scheme == "signature" and signature
            else row.token
        )
        out.setdefault(key, []).append(row)
    return list(out.values())


def _unit_drops(row: EffectTest) -> np.ndarray:
    """(U,) the row's per-unit log ratio ``log(before / after)``, 0 where a
    side is invalid (the per-unit scores as :func:`effect_row` kept them)."""
    before = np.array([np.nan if v is None else v for v in row.per_pair["before"]])
    after = np.array([np.nan if v is None else v for v in row.per_pair["after"]])
    usable = np.isfinite(before) & np.isfinite(after) & (before > 0) & (after > 0)
    out = np.zeros(before.shape)
    out[usable] = np.log(before[usable] / after[usable])
    return out


def _judge(
    rows: list[EffectTest],
    pointed: dict[str, list[str]],
    level: float,
    settings: DiagnoseConfig,
) -> list[EffectTest]:
    """The fallback procedure over the step's families in their order: each
    row's ``order``, ``pointed_by``, ``family``, ``family_p_value``,
    ``level`` and ``significant``.

    A family of one is its effect's own test. A family of twins is tested by
    the largest statistic over its members under common sign flips
    (:func:`~torchcf.diagnose.significance.max_flip_test`) at the level of its
    place; where it is rejected, the member it stands for is the one
    :func:`choose` takes among those that gain ``min_gain`` with an active
    estimate, and that member alone is significant."""
    groups = families(rows, pointed, settings.families)
    p_values, passes = [], []
    for members in groups:
        ok = [r for r in members if r.gain >= settings.min_gain and r.active]
        if len(members) == 1:
            p_values.append(members[0].p_value)
        else:
            p, _ = max_flip_test(
                [_unit_drops(r) for r in members], settings.permutations
            )
            p_values.append(p)
        passes.append(bool(ok))
    weights = level_weights([m[0].name in pointed for m in groups], settings.levels)
    levels, significant = fallback_levels(p_values, passes, level, weights)
    order = 0
    for members, p, at, yes in zip(groups, p_values, levels, significant, strict=True):
        for row in members:
            order += 1
            row.order = order
            row.pointed_by = pointed.get(row.name, [])
            row.family = [r.token for r in members] if len(members) > 1 else []
            row.family_p_value = p if len(members) > 1 else None
            row.level = at
            row.significant = False
            row.chosen = False
        if yes:
            for row in members:  # choose() reads them as the candidates
                row.significant = row.gain >= settings.min_gain and row.active
            stands_for = choose(members, settings.min_gain)
            for row in members:
                row.significant = row is stands_for
    return [row for members in groups for row in members]


__all__ = [
    "ACTIVE",
    "LEDGER_FORMAT",
    "Ledger",
    "active",
    "EffectSelection",
    "JudgedOn",
    "RoadStart",
    "arm_signatures",
    "attribute_effects",
    "choose",
    "effect_row",
    "estimate",
    "families",
    "ledger_key",
    "test_order",
]
