"""Attribution: which candidate effect lowers the out-of-sample error (loop step 2).

For every candidate effect E of :mod:`torchcf.models.effects` two arms are fitted
on the first ``fit_fraction`` of every training pair's steps
(:func:`split_in_time`) at equal budgets — the *active* pool models B alone, and B
with their augmented variants ``m+E`` — each by a small ABC run
(:func:`~torchcf.diagnose.candidates.prior_particles`) followed by local search
(:func:`~torchcf.diagnose.search.local_search`). Per pair the N best particles of
each arm (the hybrid's per-pair selection, so the originals compete) are scored on
the rest of the pair, out of sample. The gain of E is the relative drop of the
summed per-pair validation score; its p-value is a one-sided sign-flip
permutation test of the per-pair log score ratios (:func:`sign_flip_test`). An
effect is significant when its p-value is below ``alpha / n_effects``
(Bonferroni: with no effect present the answer is "none" with probability
>= 1 - alpha) and its gain at least ``min_gain``.

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
from ..models import get_model
from ..models.effects import Grade, parse_effect
from .candidates import (
    attribution_rollout,
    attribution_seed,
    augmented_variants,
    effect_estimate,
    model_bounds,
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
    """The effect's name token; a bare ``grade`` spans the pairs' road section."""
    effect = parse_effect(token)
    if isinstance(effect, Grade) and "(" not in token:
        x = pairs.x_follow[pairs.mask]
        start, end = math.floor(float(x.min())), math.ceil(float(x.max()))
        effect = Grade(start=start, end=max(end, start + 1), knots=effect.knots)
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
class PoolArm:
    """The pool alone, fitted.

    Attributes:
        bounds: prior box per pool model.
        half: per pool model, its small ABC run's first ``n`` draws (the pool's
            part of every effect arm).
        members: the arm's final population after local search.
        scores: (N,) its per-pair validation score.
    """

    bounds: dict[str, Tensor]
    half: list[Particles]
    members: list[Particles]
    scores: np.ndarray


def pool_arm(arena: Arena, pool: list[str], bar: tqdm) -> PoolArm:
    """The pool alone: ``2 n`` prior draws per pool model, then local search."""
    n = arena.settings.n_particles
    bounds = {name: model_bounds(name, arena.priors) for name in pool}
    half, full = [], []
    for name in pool:
        bar.set_postfix_str(f"ABC {name}", refresh=True)
        first, both = arena.small_abc(name, (n, 2 * n), bounds[name])
        half.append(first)
        full.append(both)
        bar.update()
    bar.set_postfix_str("pool", refresh=True)
    members = arena.refine(full, bounds)
    _, scores = arena.judge(members)
    bar.update()
    return PoolArm(bounds, half, members, scores)


def shared_effect(
    effect: str, arena: Arena, pool: PoolArm
) -> tuple[Tensor, dict[str, Any]]:
    """A shared effect's one value (K_E,) over the pool arm's population, and its
    report: ``value`` and the re-calibration ``prior`` per parameter."""
    value, box = shared_value(
        effect, pool.members, pool.bounds, arena.fit, arena.generator
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
    pool: PoolArm,
    shared: Tensor | None,
) -> list[Particles]:
    """The pool with E: the pool's first ``n`` draws plus ``n`` of each variant
    ``m+E`` (E fixed at ``shared``, a shared effect's value), then local search.

    Returns:
        the arm's final population.
    """
    n = arena.settings.n_particles
    bounds = dict(pool.bounds)
    start = list(pool.half)
    for variant in variants:
        box = model_bounds(variant, arena.priors)
        if shared is not None:  # the road's value, the same for every particle
            box[get_model(variant).base.n_params :] = shared[:, None].expand(-1, 2)
        bounds[variant] = box
        drawn = box if shared is None else box[: box.shape[0] - shared.numel()]
        start += arena.small_abc(variant, (n,), drawn, shared)
    return arena.refine(start, bounds)


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


def rank_effects(
    rows: list[dict[str, Any]], settings: DiagnoseConfig
) -> list[dict[str, Any]]:
    """Rows marked ``significant`` (p < alpha / n_effects, gain >= min_gain),
    ranked by the consistency of the gain over pairs (its t statistic, which
    unlike the permutation p-value does not saturate)."""
    threshold = settings.alpha / len(rows) if rows else 0.0
    for row in rows:
        row["significant"] = bool(
            row["p_value"] < threshold and row["gain"] >= settings.min_gain
        )
    return sorted(rows, key=lambda r: -r["statistic"])


def attribute_effects(
    cfg: TrainConfig,
    pool: list[str],
    effects: list[str],
    train_pairs: PairSet,
    *,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Rank the candidate effects by their out-of-sample gain (module docstring).

    Two *arms* per effect E, fitted on the fit windows at equal budgets:

    - the pool alone: a small ABC run of ``2 n`` prior draws per pool model
      (:func:`pool_arm`);
    - the pool with E: the pool's first ``n`` draws plus ``n`` of each ``m+E``
      (for a shared effect, ``m+E`` with E fixed at the value
      :func:`~torchcf.diagnose.search.shared_value` finds, as the road is one for
      all pairs; :func:`effect_arm`).

    Each arm then refines its per-pair best by sequential local search (the same
    budget for both), so that the arms are compared near their best fits rather
    than at the luck of prior draws. Per pair the N best particles of each arm
    (the hybrid's selection: the originals compete with the variants) are scored
    on the validation windows, out of sample; the per-pair drops of the median
    score are tested by sign flips over pairs (:func:`effect_row`).

    Args:
        cfg: the run's config (its ``diagnose`` section sets the budget).
        pool: the pool models that get each effect.
        effects: effect tokens (options resolved, see :func:`resolve_effect`).
        train_pairs: the run's training pairs.

    Returns:
        rows sorted by the statistic: ``name, effect, statistic, gain, p_value,
        significant, score_before, score_after, n_pairs, variants, estimate`` (the
        median of the effect's parameters over the picks that carry it),
        ``per_pair`` and, for a shared effect, ``shared`` (its value and
        re-calibration prior).
    """
    arena = Arena.of(cfg, train_pairs)
    bar = tqdm(
        total=len(pool) + 1 + len(effects),
        desc="attribution",
        unit="stage",
        disable=not progress,
    )
    base = pool_arm(arena, pool, bar)
    rows = []
    for effect in effects:
        bar.set_postfix_str(effect, refresh=True)
        variants = augmented_variants(pool, effect)
        value, shared = None, None
        if parse_effect(effect).shared and variants:
            value, shared = shared_effect(effect, arena, base)
        members = effect_arm(effect, variants, arena, base, value)
        if variants:
            picks, after = arena.judge(members)
        else:  # the arm is the pool alone
            picks, after = best_per_pair(members, arena.top_n), base.scores
        bar.update()
        row = effect_row(
            effect, variants, base.scores, after, picks, arena.settings.permutations
        )
        if shared is not None:
            row["shared"] = shared
        rows.append(row)
    bar.close()
    return rank_effects(rows, arena.settings)


__all__ = [
    "MIN_VALIDATION_STEPS",
    "Arena",
    "PoolArm",
    "attribute_effects",
    "effect_arm",
    "effect_row",
    "pool_arm",
    "rank_effects",
    "resolve_effect",
    "shared_effect",
    "sign_flip_test",
    "split_in_time",
]
