"""Attribution: which candidate effects lower the out-of-sample error (loop step 2).

**Forward stepwise selection.** The current model starts as the active pool B.
At every step, for every candidate effect E not yet chosen, two arms are fitted
on the first ``fit_fraction`` of every training pair's steps
(:func:`split_in_time`) at equal budgets — the *current* arm (its models alone)
and the current arm with the variants ``m+E`` of each of its models — each by a
small ABC run (:func:`~torchcf.diagnose.candidates.prior_particles`) followed by
local search (:func:`~torchcf.diagnose.search.local_search`). Per pair the N best
particles of each arm (the hybrid's selection, so the models without E compete)
are scored on the rest of the pair, out of sample. The gain of E is the relative
drop of the summed per-pair validation score; its p-value is a one-sided
sign-flip permutation test of the per-pair log score ratios
(:func:`sign_flip_test`). Among the significant effects the one with the
largest gain is chosen; its variants join the current model (refitted at the
same budget per model), and the remaining effects are tested again against it,
until none is significant or ``max_effects`` are chosen.

**The family-wise guard** counts every test the selection can make: with ``E``
candidates and at most ``S = min(max_effects, E)`` steps, step s tests ``E - s``
effects, ``T = E + (E - 1) + ... + (E - S + 1)`` tests in all, and an effect is
significant when its p-value is below ``alpha / T`` (Bonferroni over all of
them) and its gain at least ``min_gain``. So with no effect present the answer
is "none" with probability >= 1 - alpha, however many steps run.

Shapes: N pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..abc.particles import Particles, best_per_pair
from ..abc.rejection import Rollout
from ..abc.smc import SMCSettings
from ..config import DiagnoseConfig, TrainConfig
from ..data import PairSet
from ..models.effects import RoadProfile, parse_effect
from .candidates import (
    attribution_rollout,
    attribution_seed,
    augmented_variants,
    effect_estimate,
    pinned_box,
    prior_particles,
    validation_scores,
)
from .search import local_search, shared_value
from .series import DiagnoseError

#: Shortest out-of-sample window that counts for a pair [steps].
MIN_VALIDATION_STEPS = 20


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


# ------------------------------------------------------------------- the test
def sign_flip_test(
    drops: np.ndarray, permutations: int, seed: int = 0
) -> tuple[float, float]:
    """One-sided test of a positive mean per-pair drop by random sign flips.

    Under "the effect does not help", each pair's drop is as likely negative as
    positive; the p-value is ``(1 + #{flipped mean >= observed}) / (1 + n_perm)``.

    Returns:
        ``(t statistic, p-value)``; the t statistic ``mean / (sd / sqrt(n))`` is
        reported for scale only.
    """
    drops = np.asarray(drops, dtype=np.float64)
    n = drops.size
    observed = drops.mean()
    rng = np.random.default_rng(seed)
    signs = rng.choice(np.array([-1.0, 1.0]), size=(permutations, n))
    flipped = (signs * drops).mean(axis=1)
    p_value = (1.0 + np.count_nonzero(flipped >= observed - 1e-15)) / (
        1.0 + permutations
    )
    sd = drops.std(ddof=1) if n > 1 else 0.0
    statistic = observed / (sd / math.sqrt(n)) if sd > 0 else 0.0
    return float(statistic), float(min(p_value, 1.0))


# ------------------------------------------------------------------- the arms
@dataclass(frozen=True)
class Arena:
    """What every arm of an attribution shares.

    Attributes:
        settings: the run's ``diagnose`` section (budgets, search, test).
        fit: simulates on the fit windows; validation: on the validation windows.
        seed: the prior streams' seed (:func:`attribution_seed`).
        priors: the run's prior box (K, 2) per pool model.
        keep: particles kept per pair by a small ABC run.
        top_n: N, the particles per pair an arm is judged by.
        smc: the refinement's settings when the small ABC runs are SMC
            (``diagnose.method = "smc"``), else None (rejection).
        seeds: per shared effect token, a first candidate of its value.
        generator: the local search's random numbers, consumed in a fixed order
            (the pool arm, then the effects in the order given).
    """

    settings: DiagnoseConfig
    fit: Rollout
    validation: Rollout
    seed: int
    priors: dict[str, Tensor]
    keep: int
    top_n: int
    generator: torch.Generator
    smc: SMCSettings | None = None
    seeds: dict[str, Tensor] = dataclasses.field(default_factory=dict)

    @classmethod
    def of(cls, cfg: TrainConfig, train_pairs: PairSet) -> Arena:
        """The arena of the run's config on its training pairs, split in time."""
        settings = cfg.diagnose
        fit, validation = split_in_time(train_pairs, settings.fit_fraction)
        return cls(
            settings=settings,
            fit=attribution_rollout(cfg, fit),
            validation=attribution_rollout(cfg, validation),
            seed=attribution_seed(cfg),
            priors={spec.name: spec.bounds(torch.float64) for spec in cfg.models},
            keep=max(settings.population, cfg.abc.top_n),
            top_n=cfg.abc.top_n,
            generator=torch.Generator().manual_seed(attribution_seed(cfg)),
            smc=SMCSettings(**cfg.abc.smc.model_dump())
            if settings.method == "smc"
            else None,
        )

    def small_abc(
        self,
        name: str,
        budgets: tuple[int, ...],
        bounds: Tensor,
        fixed: Tensor | None = None,
    ) -> list[Particles]:
        """:func:`prior_particles` of ``name`` on the fit windows."""
        return prior_particles(
            name, self.fit, budgets, self.keep, bounds, self.seed, fixed, self.smc
        )

    def refine(
        self, start: list[Particles], bounds: dict[str, Tensor]
    ) -> list[Particles]:
        """:func:`local_search` of an arm on the fit windows."""
        return local_search(start, bounds, self.fit, self.settings, self.generator)

    def judge(self, members: list[Particles]) -> tuple[list[Particles], np.ndarray]:
        """An arm's per-pair N best (the hybrid's selection) and their median
        validation score per pair (N,)."""
        picks = best_per_pair(members, self.top_n)
        return picks, validation_scores(picks, self.validation)


@dataclass(frozen=True)
class Arm:
    """A set of models fitted on the fit windows: the pool, or the pool with the
    effects chosen so far (the selection's current model).

    Attributes:
        models: pool models, then their variants with the chosen effects.
        effects: the chosen effect tokens (none for the pool).
        shared: per chosen shared (road) effect name, its one value (K_E,).
        bounds: prior box per model (shared values pinned).
        half: per model, its small ABC run's first ``n`` draws (the arm's part
            of every candidate arm of the next test).
        members: the arm's final population after local search.
        scores: (N,) its per-pair validation score.
    """

    models: list[str]
    effects: tuple[str, ...]
    shared: dict[str, Tensor]
    bounds: dict[str, Tensor]
    half: list[Particles]
    members: list[Particles]
    scores: np.ndarray


def fit_arm(
    arena: Arena,
    models: list[str],
    effects: tuple[str, ...],
    shared: dict[str, Tensor],
    bar: tqdm,
) -> Arm:
    """The models alone: ``2 n`` prior draws per model, then local search."""
    n = arena.settings.n_particles
    half, full, bounds = [], [], {}
    for name in models:
        bar.set_postfix_str(f"ABC {name}", refresh=True)
        box, fixed = pinned_box(name, arena.priors, shared)
        bounds[name] = box
        first, both = arena.small_abc(name, (n, 2 * n), _drawn(box, fixed), fixed)
        half.append(first)
        full.append(both)
    bar.set_postfix_str("+".join(effects) or "pool", refresh=True)
    members = arena.refine(full, bounds)
    _, scores = arena.judge(members)
    bar.update()
    return Arm(list(models), effects, dict(shared), bounds, half, members, scores)


def _drawn(box: Tensor, fixed: Tensor | None) -> Tensor:
    """The rows of a box drawn by the small ABC runs (all but the pinned ones)."""
    return box if fixed is None else box[: box.shape[0] - fixed.numel()]


def shared_effect(effect: str, arena: Arena, arm: Arm) -> tuple[Tensor, dict[str, Any]]:
    """A shared effect's one value (K_E,) over the arm's population, and its
    report: ``value`` and the re-calibration ``prior`` per parameter."""
    value, box = shared_value(
        effect,
        arm.members,
        arm.bounds,
        arena.fit,
        arena.generator,
        start=arena.seeds.get(effect),
    )
    names = [p.name for p in parse_effect(effect).param_specs]
    return value, {
        "value": dict(zip(names, value.tolist(), strict=True)),
        "prior": {k: tuple(b) for k, b in zip(names, box.tolist(), strict=True)},
    }


def effect_arm(
    effect: str,
    variants: list[str],
    arena: Arena,
    arm: Arm,
    shared: dict[str, Tensor],
) -> list[Particles]:
    """The arm with E: the arm's first ``n`` draws per model plus ``n`` of each
    variant (shared effects pinned at their values), then local search.

    Returns:
        the arm's final population.
    """
    n = arena.settings.n_particles
    bounds = dict(arm.bounds)
    start = list(arm.half)
    for variant in variants:
        box, fixed = pinned_box(variant, arena.priors, shared)
        bounds[variant] = box
        start += arena.small_abc(variant, (n,), _drawn(box, fixed), fixed)
    return arena.refine(start, bounds)


def try_effect(
    effect: str, arena: Arena, arm: Arm, bar: tqdm
) -> tuple[dict[str, Any], Tensor | None]:
    """One test: the arm against the arm with ``effect`` (:func:`effect_row`).

    Returns:
        the effect's report row and, for a shared effect, its value.
    """
    bar.set_postfix_str("+".join([*arm.effects, effect]), refresh=True)
    variants = augmented_variants(arm.models, effect)
    value, report = None, None
    if parse_effect(effect).shared and variants:
        value, report = shared_effect(effect, arena, arm)
    shared = dict(arm.shared)
    if value is not None:
        shared[parse_effect(effect).name] = value
    members = effect_arm(effect, variants, arena, arm, shared)
    if variants:
        picks, after = arena.judge(members)
    else:  # the arm is the current model alone
        picks, after = best_per_pair(members, arena.top_n), arm.scores
    bar.update()
    row = effect_row(
        effect, variants, arm.scores, after, picks, arena.settings.permutations
    )
    if report is not None:
        row["shared"] = report
    return row, value


def effect_row(
    effect: str,
    variants: list[str],
    before: np.ndarray,
    after: np.ndarray,
    picks: list[Particles],
    permutations: int,
) -> dict[str, Any]:
    """The effect's report row: gain, sign-flip test, scores, estimate.

    The test takes each pair's log score ratio, so that every pair weighs alike
    (scores differ by an order of magnitude between pairs); the gain is the drop
    of the summed score.
    """
    usable = np.isfinite(before) & np.isfinite(after) & (after > 0)
    drops = np.log(before[usable] / after[usable])
    if drops.size < 2 or not variants:
        statistic, p_value, gain = 0.0, 1.0, 0.0
    else:
        statistic, p_value = sign_flip_test(drops, permutations)
        gain = float((before[usable] - after[usable]).sum() / before[usable].sum())
    return {
        "name": effect.split("(")[0],
        "effect": effect,
        "statistic": statistic,
        "gain": gain,
        "p_value": p_value,
        "score_before": float(before[usable].mean()) if usable.any() else None,
        "score_after": float(after[usable].mean()) if usable.any() else None,
        "n_pairs": int(usable.sum()),
        "variants": variants,
        "estimate": effect_estimate(picks, effect),
        "per_pair": {
            "before": [_finite_or_none(v) for v in before.tolist()],
            "after": [_finite_or_none(v) for v in after.tolist()],
        },
    }


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def planned_tests(n_effects: int, max_effects: int) -> int:
    """Tests the selection can make (module docstring): ``E + (E - 1) + ...`` over
    ``min(max_effects, E)`` steps."""
    return sum(n_effects - step for step in range(min(max_effects, n_effects)))


@dataclass(frozen=True)
class Selection:
    """The forward selection's result (:func:`attribute_effects`).

    Attributes:
        steps: per step, the rows of the effects tested, largest gain first,
            each marked ``significant``.
        chosen: the chosen effect tokens, in the order chosen.
        models: the final model: the pool and the variants of the chosen
            effects (what the re-calibration trains).
        steps_at_most: the selection's steps at most, ``min(max_effects, E)``.
        tests: ``T``, the tests the guard counts; threshold: ``alpha / T``.
    """

    steps: list[list[dict[str, Any]]]
    chosen: list[str]
    models: list[str]
    steps_at_most: int
    tests: int
    threshold: float

    @property
    def shared_priors(self) -> dict[str, dict[str, tuple[float, float]]]:
        """Per chosen shared effect, its re-calibration prior."""
        return {
            row["effect"]: row["shared"]["prior"]
            for rows in self.steps
            for row in rows
            if row["effect"] in self.chosen and "shared" in row
        }


def attribute_effects(
    cfg: TrainConfig,
    pool: list[str],
    effects: list[str],
    train_pairs: PairSet,
    *,
    seeds: dict[str, Tensor] | None = None,
    progress: bool = True,
) -> Selection:
    """Choose effects by forward stepwise selection (module docstring).

    Every arm refines its per-pair best by sequential local search (the same
    budget for all), so that arms are compared near their best fits rather than
    at the luck of prior draws. A shared effect's variants are fitted with E
    fixed at the one value :func:`~torchcf.diagnose.search.shared_value` finds
    over the current arm (the road is one for all pairs).

    Args:
        cfg: the run's config (its ``diagnose`` section sets the budget).
        pool: the pool models that get the effects.
        effects: effect tokens (options resolved, see :func:`resolve_effect`).
        train_pairs: the run's training pairs.
        seeds: per shared effect token, a first candidate of its value.

    Returns:
        the :class:`Selection`; each row holds ``name, effect, statistic, gain,
        p_value, significant, score_before, score_after, n_pairs, variants,
        estimate`` (the median of the effect's parameters over the picks that
        carry it), ``per_pair`` and, for a shared effect, ``shared`` (its value
        and re-calibration prior).
    """
    arena = Arena.of(cfg, train_pairs)
    if seeds:
        arena = dataclasses.replace(arena, seeds=dict(seeds))
    settings = arena.settings
    tests = planned_tests(len(effects), settings.max_effects)
    threshold = settings.alpha / tests
    steps_at_most = min(settings.max_effects, len(effects))
    bar = tqdm(
        total=tests + steps_at_most,
        desc="attribution",
        unit="arm",
        disable=not progress,
    )
    arm = fit_arm(arena, list(pool), (), {}, bar)
    steps: list[list[dict[str, Any]]] = []
    chosen: list[str] = []
    models = list(pool)
    remaining = list(effects)
    while remaining and len(chosen) < settings.max_effects:
        tested = [try_effect(effect, arena, arm, bar) for effect in remaining]
        for row, _ in tested:
            row["significant"] = bool(
                row["p_value"] < threshold and row["gain"] >= settings.min_gain
            )
        tested.sort(key=lambda item: -item[0]["gain"])
        steps.append([row for row, _ in tested])
        best = next(((r, v) for r, v in tested if r["significant"]), None)
        if best is None:
            break
        row, value = best
        chosen.append(row["effect"])
        remaining.remove(row["effect"])
        models = arm.models + row["variants"]
        if remaining and len(chosen) < settings.max_effects:
            shared = dict(arm.shared)
            if value is not None:
                shared[parse_effect(row["effect"]).name] = value
            arm = fit_arm(arena, models, tuple(chosen), shared, bar)
    bar.close()
    return Selection(steps, chosen, models, steps_at_most, tests, threshold)


__all__ = [
    "MIN_VALIDATION_STEPS",
    "Arena",
    "Arm",
    "Selection",
    "attribute_effects",
    "effect_arm",
    "effect_row",
    "fit_arm",
    "planned_tests",
    "resolve_effect",
    "shared_effect",
    "sign_flip_test",
    "split_in_time",
    "try_effect",
]
