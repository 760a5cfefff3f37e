"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

``python -m torchcf.diagnose RUN_DIR [--set diagnose.key=VALUE ...]`` (or
``diagnose.run_after_training`` in the run's config) takes a finished, evaluated run
and

1. **diagnoses** the residuals ``observed - simulated`` (spacing [m], speed [m/s],
   acceleration [m/s^2]) of every training pair driven by its best hybrid particle:
   :mod:`torchcf.residuals` tests them for autocorrelation (Ljung-Box), lagged
   cross-correlation with the leader's acceleration and the speed difference
   (0-3 s), dependence on own speed and speed squared, on the sign of the speed
   difference, on the spacing level, on the road position and on time;
2. **attributes**: for every candidate effect E of :mod:`torchcf.models.effects`
   two arms are fitted on the first ``fit_fraction`` of every training pair's
   steps at equal budgets — the *active* pool models B alone, and B with their
   augmented variants ``m+E`` — each by a small ABC run followed by local search
   (:func:`attribute_effects`); per pair the N best particles of each arm (the
   hybrid's per-pair selection, so the originals compete) are scored on the rest
   of the pair, out of sample. The gain of E is the relative drop of the summed
   per-pair validation score; its p-value is a one-sided sign-flip permutation
   test of the per-pair log score ratios. An effect is chosen when its p-value
   is below ``alpha / n_effects`` (Bonferroni: with no effect present the answer
   is "none" with probability >= 1 - alpha) and its gain at least ``min_gain``;
3. **re-calibrates** the run's pool plus ``m+E`` for the chosen effects (a full
   training run in ``RUN_DIR/loop/after``) and evaluates it on the test split;
4. **reports** ``RUN_DIR/loop.json`` (``effects_ranked``, ``chosen``, the
   ``posterior`` of the added parameters, the test metrics ``before`` and
   ``after``, the residual diagnostics before and after) and ``RUN_DIR/loop.md``
   with figures in ``RUN_DIR/loop/``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..abc.streams import ParticleStream
from ..abc.topn import TopN
from ..config import (
    ConfigError,
    TrainConfig,
    apply_overrides,
    config_hash,
    validate_config,
)
from ..data import PairSet, load_split
from ..evaluate import load_run
from ..evaluation.plots import loop_figures, save_figure
from ..evaluation.report import METRIC_COLUMNS
from ..models import UnknownModelError, get_model
from ..models.effects import Grade, parse_effect
from ..posterior import Posterior, atomic_write_text, json_safe
from ..sim import simulate
from ..tblog import RunLogger
from . import residuals as rt

FORMAT = "torchcf.loop/1"
#: Particles simulated per call in the attribution runs.
ATTRIBUTION_CHUNK = 1 << 16
#: Standard deviations of the local search's perturbations, as fractions of each
#: parameter's prior width (copy c uses entry c % 3).
LOCAL_SCALES = (0.1, 0.03, 0.01)
#: Search rounds, and values per round, for the one value of a shared (road)
#: effect.
SHARED_ROUNDS = 3
SHARED_VALUES = 64
#: Relative fit score counted for a pair whose candidates are all invalid.
INVALID_RATIO = 10.0
#: Shortest out-of-sample window that counts for a pair [steps].
MIN_VALIDATION_STEPS = 20
#: Which residual structure points to which effect (for the report only).
EFFECT_HINTS = {
    "delay": "cross-correlation with the leader's acceleration / speed difference "
    "at a lag > 0, autocorrelation",
    "lag": "autocorrelation, cross-correlation with the speed difference",
    "offset": "dependence on the spacing level, a constant spacing residual",
    "asymmetry": "dependence on the sign of the speed difference",
    "resistance": "dependence on own speed squared",
    "grade": "dependence on the position along the road",
    "saturation": "residuals concentrated at large accelerations",
}


class DiagnoseError(RuntimeError):
    """A run that cannot be diagnosed (one-line message)."""


# ------------------------------------------------------------------ residuals
def best_particles(
    posterior: Posterior, pairs: PairSet
) -> dict[str, tuple[Tensor, Tensor]]:
    """The hybrid's best particle on every training pair, grouped by model.

    Returns:
        ``{model: (theta (k, K) float64, pair position (k,) int64)}``; every pair
        with a hybrid particle appears under exactly one model.
    """
    position_of = {int(pid): i for i, pid in enumerate(pairs.pair_ids)}
    best_score = torch.full((pairs.n_pairs,), math.inf, dtype=torch.float64)
    best: dict[int, tuple[str, Tensor]] = {}
    for name in posterior.models:  # run order: ties go to the model listed first
        particles = posterior.hybrid[name]
        for theta, score, pid in zip(
            particles.theta, particles.score, particles.pair_ids.tolist(), strict=True
        ):
            j = position_of.get(int(pid))
            if j is not None and float(score) < float(best_score[j]):
                best_score[j] = float(score)
                best[j] = (name, theta)
    grouped: dict[str, tuple[list[Tensor], list[int]]] = {}
    for j, (name, theta) in sorted(best.items()):
        thetas, positions = grouped.setdefault(name, ([], []))
        thetas.append(theta)
        positions.append(j)
    return {
        name: (torch.stack(thetas), torch.tensor(positions, dtype=torch.int64))
        for name, (thetas, positions) in grouped.items()
    }


def residual_series(
    best: dict[str, tuple[Tensor, Tensor]],
    pairs: PairSet,
    dtype: torch.dtype = torch.float64,
) -> dict[str, list[np.ndarray]]:
    """Residuals and covariates of every pair driven by its particle, valid steps only.

    Returns:
        lists (one float64 array per pair, pairs in position order) under
        ``spacing, speed, acceleration`` (observed - simulated, [m], [m/s],
        [m/s^2]) and the covariates ``v`` (observed own speed), ``dv`` (leader -
        follower speed), ``s`` (observed spacing), ``x`` (road position),
        ``a_lead`` (leader acceleration).
    """
    sim_x = torch.full((pairs.n_steps, pairs.n_pairs), math.nan, dtype=torch.float64)
    sim_v, sim_a = sim_x.clone(), sim_x.clone()
    for name, (theta, position) in best.items():
        out = simulate(
            name, theta.to(dtype), pairs, position, dtype=dtype, return_traj=True
        )
        sim_x[:, position] = out.x.double().cpu()
        sim_v[:, position] = out.v.double().cpu()
        sim_a[:, position] = out.a.double().cpu()
    obs = {k: t.double().cpu() for k, t in pairs.series().items()}
    columns = {
        # s_obs - s_sim = (x_lead - x_obs) - (x_lead - x_sim) = x_sim - x_obs
        "spacing": sim_x - obs["x_follow"],
        "speed": obs["v_follow"] - sim_v,
        "acceleration": obs["a_follow"] - sim_a,
        "v": obs["v_follow"],
        "dv": obs["v_lead"] - obs["v_follow"],
        "s": obs["x_lead"] - obs["x_follow"],
        "x": obs["x_follow"],
        "a_lead": obs["a_lead"],
    }
    mask = pairs.mask.cpu()
    covered = torch.isfinite(sim_x).all(0)  # pairs with a particle
    out: dict[str, list[np.ndarray]] = {key: [] for key in columns}
    for j in range(pairs.n_pairs):
        if not bool(covered[j]):
            continue
        valid = mask[:, j]
        for key, table in columns.items():
            out[key].append(table[valid, j].numpy())
    return out


def residual_tests(series: dict[str, list[np.ndarray]], dt: float) -> list[dict]:
    """The structure tests of every residual channel, as JSON rows.

    Returns:
        one row per (channel, test): ``channel, test, statistic, p_value, effect,
        n, n_pairs`` (pooled over pairs).
    """
    rows = []
    for channel in ("spacing", "speed", "acceleration"):
        e = series[channel]
        tests = {
            "autocorrelation": lambda e=e: rt.ljung_box(e, lags=10),
            "xcorr leader acceleration": lambda e=e: rt.cross_correlation(
                e, series["a_lead"], dt
            ),
            "xcorr speed difference": lambda e=e: rt.cross_correlation(
                e, series["dv"], dt
            ),
            "own speed": lambda e=e: rt.speed_dependence(e, series["v"]),
            "asymmetry": lambda e=e: rt.asymmetry(e, series["dv"]),
            "spacing level": lambda e=e: rt.spacing_dependence(e, series["s"]),
            "road position": lambda e=e: rt.position_dependence(e, series["x"]),
            "drift": lambda e=e: rt.drift(e, dt),
        }
        for test, run in tests.items():
            result = run()
            (row,) = rt.summarize([result])
            rows.append(
                {
                    "channel": channel,
                    "test": test,
                    "statistic": row["statistic"],
                    "p_value": row["p_value"],
                    "effect": row["effect"],
                    "n": row["n"],
                    "n_pairs": row["n_pairs"],
                }
            )
    return rows


def diagnose_residuals(
    posterior: Posterior, pairs: PairSet, dtype: torch.dtype = torch.float64
) -> tuple[list[dict], dict[str, list[np.ndarray]]]:
    """Residual series of the hybrid's best particle per pair and their tests."""
    series = residual_series(best_particles(posterior, pairs), pairs, dtype)
    if not series["spacing"]:
        raise DiagnoseError("no training pair has a hybrid particle to diagnose")
    return residual_tests(series, pairs.dt), series


# ---------------------------------------------------------------- attribution
def split_in_time(pairs: PairSet, fraction: float) -> tuple[PairSet, PairSet]:
    """The first ``fraction`` of the steps and the rest, for the same pairs.

    Pairs with fewer than :data:`MIN_VALIDATION_STEPS` valid steps in the second
    part are dropped from both, so both sets hold the same pairs.

    Returns:
        ``(fit, validation)``; the validation set starts from the observed state at
        the split step.
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


@dataclasses.dataclass
class _Candidates:
    """Particles of one model (or variant) on the fit windows, with their scores.

    ``theta`` (Q, n_params) float64; ``pair`` (Q,) training-pair index of each;
    ``score`` (Q,) float64 fit-window score (``inf`` for an invalid rollout).
    """

    name: str
    theta: Tensor
    pair: Tensor
    score: Tensor


def _model_bounds(name: str, priors: dict[str, Tensor]) -> Tensor:
    """Prior box (n_params, 2) of a model or variant, with the run's prior
    overrides of its pool model."""
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    base = model.base.name if hasattr(model, "base") else model.name
    if base in priors:
        bounds[: priors[base].shape[0]] = priors[base]
    return bounds


def _fit_scores(
    name: str, theta: Tensor, pair: Tensor, pairs: PairSet, cfg: TrainConfig
) -> Tensor:
    """Scores (Q,) float64 of particles ``theta`` (Q, n_params), each simulated on
    its own pair ``pair`` (Q,) of ``pairs`` (the paired layout)."""
    dtype = getattr(torch, cfg.dtype)
    scores = []
    for first in range(0, theta.shape[0], ATTRIBUTION_CHUNK):
        rows = slice(first, first + ATTRIBUTION_CHUNK)
        out = simulate(
            name,
            theta[rows].to(dtype),
            pairs,
            pair[rows],
            dtype=dtype,
            device=cfg.device,
            weights=cfg.abc.weights,
        )
        scores.append(out.score.double().cpu())
    return torch.cat(scores) if scores else torch.empty(0, dtype=torch.float64)


def _attribution_seed(cfg: TrainConfig) -> int:
    """``diagnose.seed``, or the run's ``abc.seed`` when it is not set."""
    return cfg.abc.seed if cfg.diagnose.seed is None else cfg.diagnose.seed


def _small_abc(
    name: str,
    fit: PairSet,
    budgets: Sequence[int],
    keep: int,
    cfg: TrainConfig,
    bounds: Tensor,
    fixed: Tensor | None = None,
) -> list[_Candidates]:
    """Paired ABC rejection of one model (or variant) on the fit windows.

    Args:
        budgets: increasing particle counts; result ``i`` holds the ``keep`` best
            per pair of the first ``budgets[i]`` prior draws of the model's
            stream (top-N streamed, nothing else stored).
        bounds: the prior box of the drawn parameters (n_drawn, 2).
        fixed: values (n_params - n_drawn,) of the last parameters, the same for
            every particle (a shared effect's value).
    """
    model = get_model(name)
    stream = ParticleStream(model.name, bounds, _attribution_seed(cfg), fit.n_pairs)
    buffer = TopN(fit.n_pairs, keep, model.n_params)
    results, start = [], 0
    for budget in budgets:
        for first in range(start, budget, ATTRIBUTION_CHUNK):
            stop = min(first + ATTRIBUTION_CHUNK, budget)
            theta, pair = stream.draw(first, stop)
            if fixed is not None:
                theta = torch.cat((theta, fixed.expand(theta.shape[0], -1)), dim=1)
            score = _fit_scores(model.name, theta, pair, fit, cfg)
            buffer.push(pair, score, torch.arange(first, stop), theta)
        start = budget
        score, _, theta = buffer.first(keep)  # (n_pairs, keep), (.., n_params)
        results.append(
            _Candidates(
                model.name,
                theta.reshape(-1, model.n_params).clone(),
                torch.arange(fit.n_pairs).repeat_interleave(keep),
                score.reshape(-1).clone(),
            )
        )
    return results


Picks = list[list[tuple[str, Tensor, float]]]


def _select(candidates: Sequence[_Candidates], n_pairs: int, top_n: int) -> Picks:
    """Per pair, the N best finite-score candidates over all sets: the hybrid's
    per-pair selection (ties go to the earlier set, then the earlier row)."""
    score = torch.cat([c.score for c in candidates])
    pair = torch.cat([c.pair for c in candidates])
    which = torch.cat(
        [torch.full((c.score.numel(),), k) for k, c in enumerate(candidates)]
    )
    row = torch.cat([torch.arange(c.score.numel()) for c in candidates])
    order = torch.sort(score, stable=True).indices
    order = order[torch.sort(pair[order], stable=True).indices]  # pair, then score
    chosen: Picks = [[] for _ in range(n_pairs)]
    for flat in order.tolist():
        j, value = int(pair[flat]), float(score[flat])
        if len(chosen[j]) < top_n and math.isfinite(value):
            c = candidates[int(which[flat])]
            chosen[j].append((c.name, c.theta[int(row[flat])], value))
    return chosen


def _validation_scores(picks: Picks, validation: PairSet, cfg: TrainConfig):
    """Median out-of-sample score of each pair's picks on its validation window.

    Returns:
        (n_pairs,) float64 ndarray; ``inf`` where more than half the picks are
        invalid or a pair has no pick.
    """
    grouped: dict[str, tuple[list[Tensor], list[int], list[tuple[int, int]]]] = {}
    for j, pair_picks in enumerate(picks):
        for slot, (name, theta, _) in enumerate(pair_picks):
            thetas, positions, where = grouped.setdefault(name, ([], [], []))
            thetas.append(theta)
            positions.append(j)
            where.append((j, slot))
    width = max((len(p) for p in picks), default=0)
    table = np.full((len(picks), max(width, 1)), np.inf)
    for name, (thetas, positions, where) in grouped.items():
        scores = _fit_scores(
            name, torch.stack(thetas), torch.tensor(positions), validation, cfg
        ).tolist()
        for (j, slot), score in zip(where, scores, strict=True):
            table[j, slot] = score
    return np.array(
        [
            np.median(table[j, : len(picks[j])]) if picks[j] else np.inf
            for j in range(len(picks))
        ]
    )


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


def augmented_variants(pool: Sequence[str], effect: str) -> list[str]:
    """Canonical names of ``m+effect`` for the pool models the effect can wrap.

    (``lag`` cannot wrap HL, which has its own actuation lag.)
    """
    names = []
    for model in pool:
        try:
            names.append(get_model(f"{model}+{effect}").name)
        except UnknownModelError:
            continue
    return names


# ------------------------------------------------------------ the local stage
def _jitter(
    theta: Tensor, bounds: Tensor, copies: int, generator: torch.Generator
) -> Tensor:
    """``copies`` perturbations of every member ``theta`` (S, d): (S, copies, d).

    Copy c moves each parameter by a normal step whose standard deviation is
    ``LOCAL_SCALES[c % 3]`` times the parameter's prior width, clipped to the prior
    box ``bounds`` (d, 2): a coarse-to-fine mix around the member, as the kernel of
    sequential ABC. A zero-width row (a fixed parameter) stays fixed.
    """
    s, d = theta.shape
    width = bounds[:, 1] - bounds[:, 0]
    scale = torch.tensor(LOCAL_SCALES, dtype=torch.float64)[
        torch.arange(copies) % len(LOCAL_SCALES)
    ]
    noise = torch.randn(s, copies, d, generator=generator, dtype=torch.float64)
    moved = theta[:, None, :] + noise * scale[None, :, None] * width
    return torch.maximum(torch.minimum(moved, bounds[:, 1]), bounds[:, 0])


def _uniform(bounds: Tensor, shape: tuple[int, ...], generator: torch.Generator):
    """Uniform draws (*shape, K) float64 in the box ``bounds`` (K, 2)."""
    u = torch.rand(*shape, bounds.shape[0], generator=generator, dtype=torch.float64)
    return bounds[:, 0] + u * (bounds[:, 1] - bounds[:, 0])


def _as_sets(picks: Picks) -> list[_Candidates]:
    """Per-pair picks regrouped by model name into candidate sets."""
    grouped: dict[str, tuple[list[Tensor], list[int], list[float]]] = {}
    for j, pair_picks in enumerate(picks):
        for name, theta, score in pair_picks:
            thetas, pairs, scores = grouped.setdefault(name, ([], [], []))
            thetas.append(theta)
            pairs.append(j)
            scores.append(score)
    return [
        _Candidates(
            name,
            torch.stack(thetas).double(),
            torch.tensor(pairs),
            torch.tensor(scores, dtype=torch.float64),
        )
        for name, (thetas, pairs, scores) in grouped.items()
    ]


def _refine(
    start: list[_Candidates],
    bounds: dict[str, Tensor],
    fit: PairSet,
    cfg: TrainConfig,
    generator: torch.Generator,
) -> list[_Candidates]:
    """Sequential local search of one arm: ``rounds`` times, every pair's
    ``population`` best members (over the arm's models) get ``local_copies``
    perturbed copies each (:func:`_jitter`), scored on the fit windows.

    Every arm spends the same budget per pair and round, so arms differ by their
    models only.

    Returns:
        the arm's final population (per pair its ``population`` best) as sets.
    """
    settings = cfg.diagnose
    n_pairs = fit.n_pairs
    members = _as_sets(_select(start, n_pairs, settings.population))
    for _ in range(settings.rounds):
        copies = []
        for member in members:
            moved = _jitter(
                member.theta, bounds[member.name], settings.local_copies, generator
            )
            theta = moved.reshape(-1, moved.shape[-1])
            pair = member.pair.repeat_interleave(settings.local_copies)
            score = _fit_scores(member.name, theta, pair, fit, cfg)
            copies.append(_Candidates(member.name, theta, pair, score))
        members = _as_sets(_select(members + copies, n_pairs, settings.population))
    return members


def _variant_of(model: str, effect: str) -> str | None:
    names = augmented_variants([model], effect)
    return names[0] if names else None


def _shared_value(
    effect: str,
    members: list[_Candidates],
    bounds: dict[str, Tensor],
    fit: PairSet,
    cfg: TrainConfig,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor]:
    """The one value of a shared (road) effect's parameters for all pairs.

    Searched over the pool arm's final population (``members``):
    ``SHARED_ROUNDS`` rounds of ``SHARED_VALUES`` values, the first uniform over the
    effect's prior, each later one uniform in a box around the best so far with
    half the width. Value c is tried with every member's c-th coarse perturbation
    (the base parameters may have absorbed part of the effect). A value's
    objective is the sum over pairs of its best fit score relative to the pair's
    best member, so every pair weighs alike.

    Returns:
        the value (K,) and the box (K, 2) of the last round's resolution around
        it (the effect's prior in the arm and the re-calibration).
    """
    spec = parse_effect(effect)
    prior = torch.tensor(
        [[p.lower, p.upper] for p in spec.param_specs], dtype=torch.float64
    )  # (K, 2)
    m, n_pairs = SHARED_VALUES, fit.n_pairs
    reference = torch.full((n_pairs,), math.inf, dtype=torch.float64)
    for member in members:
        reference = reference.scatter_reduce(0, member.pair, member.score, "amin")
    usable = torch.isfinite(reference) & (reference > 0)
    low, high = prior[:, 0], prior[:, 1]
    best, best_objective, half = None, math.inf, (high - low) / 2
    for _ in range(SHARED_ROUNDS):
        box = prior
        if best is not None:
            box = torch.stack(
                (torch.maximum(best - half, low), torch.minimum(best + half, high)), 1
            )
        values = _uniform(box, (m,), generator)  # (M, K)
        per_pair = torch.full((n_pairs, m), math.inf, dtype=torch.float64)
        for member in members:
            variant = _variant_of(member.name, effect)
            if variant is None:
                continue
            s = member.theta.shape[0]
            base = _jitter(member.theta, bounds[member.name], m, generator)
            theta = torch.cat((base, values[None].expand(s, m, -1)), dim=-1)
            pair = member.pair.repeat_interleave(m)
            score = _fit_scores(
                variant, theta.reshape(s * m, -1), pair, fit, cfg
            ).reshape(s, m)
            index = member.pair[:, None].expand(s, m)
            per_pair = per_pair.scatter_reduce(0, index, score, "amin")
        ratio = per_pair[usable] / reference[usable, None]
        ratio = torch.where(torch.isfinite(ratio), ratio, INVALID_RATIO)
        objective = ratio.sum(0)  # (M,)
        k = int(torch.argmin(objective))
        if float(objective[k]) < best_objective:
            best, best_objective = values[k], float(objective[k])
        half = half / 2
    box = torch.stack(
        (torch.maximum(best - half, low), torch.minimum(best + half, high)), 1
    )
    return best, box


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _estimate(picks: Picks, effect: str) -> dict[str, float]:
    """Median of the effect's parameters over the picks of its variants."""
    names = [p.name for p in parse_effect(effect).param_specs]
    token = effect.split("(")[0]
    values = [
        theta[-len(names) :]
        for pair_picks in picks
        for name, theta, _ in pair_picks
        if token in [t.split("(")[0] for t in name.split("+")[1:]]
    ]
    if not values:
        return {}
    median = torch.stack(values).median(dim=0).values
    return dict(zip(names, median.tolist(), strict=True))


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

    - the pool alone: a small ABC run of ``2 n`` prior draws per pool model;
    - the pool with E: the pool's first ``n`` draws plus ``n`` of each ``m+E``
      (for a shared effect, ``m+E`` with E fixed at the value
      :func:`_shared_value` finds, as the road is one for all pairs).

    Each arm then refines its per-pair best by sequential local search
    (:func:`_refine`, the same budget for both), so that the arms are compared
    near their best fits rather than at the luck of prior draws. Per pair the N
    best particles of each arm (the hybrid's selection: the originals compete
    with the variants) are scored on the validation windows, out of sample; the
    per-pair drops of the median score are tested by sign flips over pairs.

    Args:
        cfg: the run's config (its ``diagnose`` section sets the budget).
        pool: the pool models that get each effect.
        effects: effect tokens (options resolved, see :func:`resolve_effect`).
        train_pairs: the run's training pairs.

    Returns:
        rows sorted by the statistic: ``name, effect, statistic, gain, p_value,
        significant, score_before, score_after, n_pairs, variants, estimate`` (the
        median of the effect's parameters over the picks that carry it) and, for
        a shared effect, ``shared`` (its value and re-calibration prior).
    """
    settings = cfg.diagnose
    fit, validation = split_in_time(train_pairs, settings.fit_fraction)
    top_n, n_pairs, n = cfg.abc.top_n, train_pairs.n_pairs, settings.n_particles
    keep = max(settings.population, top_n)
    priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
    bounds = {name: _model_bounds(name, priors) for name in pool}
    generator = torch.Generator().manual_seed(_attribution_seed(cfg))
    bar = tqdm(
        total=len(pool) + 1 + len(effects),
        desc="attribution",
        unit="stage",
        disable=not progress,
    )
    half, full = [], []
    for name in pool:
        bar.set_postfix_str(f"ABC {name}", refresh=True)
        first, both = _small_abc(name, fit, (n, 2 * n), keep, cfg, bounds[name])
        half.append(first)
        full.append(both)
        bar.update()
    bar.set_postfix_str("pool", refresh=True)
    pool_members = _refine(full, bounds, fit, cfg, generator)
    before = _validation_scores(_select(pool_members, n_pairs, top_n), validation, cfg)
    bar.update()
    rows = []
    for effect in effects:
        bar.set_postfix_str(effect, refresh=True)
        variants = augmented_variants(pool, effect)
        shared = None
        arm_bounds = dict(bounds)
        if parse_effect(effect).shared and variants:
            value, box = _shared_value(
                effect, pool_members, bounds, fit, cfg, generator
            )
            names = [p.name for p in parse_effect(effect).param_specs]
            shared = {
                "value": dict(zip(names, value.tolist(), strict=True)),
                "prior": {
                    k: tuple(b) for k, b in zip(names, box.tolist(), strict=True)
                },
            }
        start = list(half)
        for variant in variants:
            box = _model_bounds(variant, priors)
            fixed = None
            if shared is not None:  # the road's value, the same for every particle
                d = get_model(variant).base.n_params
                box[d:] = value[:, None].expand(-1, 2)
                fixed = value
            arm_bounds[variant] = box
            draw = box if fixed is None else box[: box.shape[0] - fixed.numel()]
            start += _small_abc(variant, fit, (n,), keep, cfg, draw, fixed)
        members = _refine(start, arm_bounds, fit, cfg, generator)
        picks = _select(members, n_pairs, top_n)
        after = _validation_scores(picks, validation, cfg) if variants else before
        bar.update()
        usable = np.isfinite(before) & np.isfinite(after) & (after > 0)
        # The test takes each pair's log score ratio, so that every pair weighs
        # alike (scores differ by an order of magnitude between pairs); the gain
        # is the drop of the summed score.
        drops = np.log(before[usable] / after[usable])
        if drops.size < 2 or not variants:
            statistic, p_value, gain = 0.0, 1.0, 0.0
        else:
            statistic, p_value = sign_flip_test(drops, settings.permutations)
            gain = float((before[usable] - after[usable]).sum() / before[usable].sum())
        row = {
            "name": effect.split("(")[0],
            "effect": effect,
            "statistic": statistic,
            "gain": gain,
            "p_value": p_value,
            "score_before": float(before[usable].mean()) if usable.any() else None,
            "score_after": float(after[usable].mean()) if usable.any() else None,
            "n_pairs": int(usable.sum()),
            "variants": variants,
            "estimate": _estimate(picks, effect),
            "per_pair": {
                "before": [_finite_or_none(v) for v in before.tolist()],
                "after": [_finite_or_none(v) for v in after.tolist()],
            },
        }
        if shared is not None:
            row["shared"] = shared
        rows.append(row)
    bar.close()
    threshold = settings.alpha / len(effects)
    for row in rows:
        row["significant"] = bool(
            row["p_value"] < threshold and row["gain"] >= settings.min_gain
        )
    # Ranked by the consistency of the gain over pairs (its t statistic), which
    # unlike the permutation p-value does not saturate.
    return sorted(rows, key=lambda r: -r["statistic"])


# ------------------------------------------------------------- re-calibration
def _active_models(cfg: TrainConfig, posterior: Posterior) -> list[str]:
    names = [spec.name for spec in cfg.models if "+" not in spec.name]
    if cfg.diagnose.models == "all":
        return names
    active = [
        n for n in names if posterior.shares.get(n, 0.0) >= cfg.diagnose.min_share
    ]
    return active or [max(names, key=lambda n: posterior.shares.get(n, 0.0))]


def _recalibration_config(
    cfg: TrainConfig,
    pool: list[str],
    chosen: list[str],
    effect_priors: dict[str, dict[str, tuple[float, float]]] | None = None,
) -> TrainConfig:
    """The run's config plus ``m+E`` of every chosen effect E, for re-calibration.

    Args:
        effect_priors: per effect token, prior boxes of its parameters replacing
            the defaults (a shared effect's value found by the attribution: the
            road is one, so its profile is not re-drawn per particle).
    """
    raw = cfg.model_dump(mode="json")
    present = {spec["name"] for spec in raw["models"]}
    for effect in chosen:
        for variant in augmented_variants(pool, effect):
            name = get_model(variant).base.name
            if variant not in present:
                prior = next(
                    (s["prior"] for s in raw["models"] if s["name"] == name), None
                )
                extra = (effect_priors or {}).get(effect)
                if extra:
                    prior = {**(prior or {}), **{k: list(v) for k, v in extra.items()}}
                raw["models"].append({"name": variant, "prior": prior})
                present.add(variant)
    if cfg.diagnose.recalibrate_particles is not None:
        raw["abc"]["n_particles"] = cfg.diagnose.recalibrate_particles
    raw["diagnose"]["run_after_training"] = False
    raw["output"] = None
    return validate_config(raw)


def effect_posterior(posterior: Posterior, chosen: list[str]) -> dict[str, Any]:
    """Summary of each chosen effect's parameters over the hybrid's particles."""
    result: dict[str, Any] = {}
    for effect in chosen:
        names = [p.name for p in parse_effect(effect).param_specs]
        columns: dict[str, list[Tensor]] = {n: [] for n in names}
        share = 0.0
        for model, particles in posterior.hybrid.items():
            tokens = model.split("+")[1:]
            if effect.split("(")[0] not in [t.split("(")[0] for t in tokens]:
                continue
            share += posterior.shares.get(model, 0.0)
            for n in names:
                columns[n].append(particles.theta[:, particles.param_names.index(n)])
        params = {}
        for n, parts in columns.items():
            values = torch.cat(parts) if parts else torch.empty(0)
            if values.numel() == 0:
                params[n] = {"n": 0}
                continue
            q = torch.quantile(
                values, torch.tensor([0.05, 0.5, 0.95], dtype=values.dtype)
            )
            params[n] = {
                "n": int(values.numel()),
                "median": float(q[1]),
                "q05": float(q[0]),
                "q95": float(q[2]),
                "mean": float(values.mean()),
            }
        result[effect] = {"share": share, "params": params}
    return result


# -------------------------------------------------------------------- the loop
def diagnose_run(
    run_dir: str | Path,
    overrides: Sequence[str] = (),
    *,
    pairs: tuple[PairSet, PairSet] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the whole loop on a finished, evaluated run (module docstring).

    Args:
        run_dir: a trainer output directory holding ``metrics.json``.
        overrides: ``diagnose.key=VALUE`` items applied to the run's config.
        pairs: optional ``(train, test)`` instead of loading the run's data.
        progress: show progress bars.

    Returns:
        the loop result (also in ``run_dir/loop.json``).
    """
    from ..train import train  # not at the top: the trainer imports this module

    began = time.perf_counter()
    run_dir = Path(run_dir)
    cfg, posterior, _ = load_run(run_dir)
    if overrides:
        bad = [o for o in overrides if not o.strip().startswith("diagnose.")]
        if bad:
            raise ConfigError(f"--set only takes diagnose.* keys here, got {bad[0]!r}")
        cfg = validate_config(apply_overrides(cfg.model_dump(mode="json"), overrides))
    if not (run_dir / "metrics.json").exists():
        raise DiagnoseError(f"{run_dir} is not evaluated (no metrics.json)")
    before_metrics = json.loads((run_dir / "metrics.json").read_text())
    train_pairs, test_pairs = load_split(cfg.data) if pairs is None else pairs
    if tuple(train_pairs.pair_ids) != tuple(posterior.train_pair_ids.tolist()):
        raise DiagnoseError("the training pairs differ from the run's posterior")

    residuals_before, series_before = diagnose_residuals(posterior, train_pairs)
    pool = _active_models(cfg, posterior)
    effects = [resolve_effect(t, train_pairs) for t in cfg.diagnose.effects]
    ranked = attribute_effects(cfg, pool, effects, train_pairs, progress=progress)
    chosen = [r["effect"] for r in ranked if r["significant"]][
        : cfg.diagnose.max_effects
    ]

    result: dict[str, Any] = {
        "format": FORMAT,
        "run": str(run_dir),
        "dataset": before_metrics.get("dataset"),
        "pool": pool,
        "effects_ranked": ranked,
        "chosen": chosen,
        "alpha": cfg.diagnose.alpha,
        "fit_fraction": cfg.diagnose.fit_fraction,
        "min_gain": cfg.diagnose.min_gain,
        "before": before_metrics["hybrid"],
        "residuals_before": residuals_before,
    }
    series_after = None
    after_dir = run_dir / "loop" / "after"
    if chosen:
        effect_priors = {
            r["effect"]: r["shared"]["prior"] for r in ranked if "shared" in r
        }
        after_cfg = _recalibration_config(cfg, pool, chosen, effect_priors)
        train(
            after_cfg,
            after_dir,
            resume=_reuse_recalibration(after_dir, after_cfg),
            pairs=(train_pairs, test_pairs),
        )
        after_posterior = Posterior.load(after_dir / "posterior.pt")
        after_metrics = json.loads((after_dir / "metrics.json").read_text())
        residuals_after, series_after = diagnose_residuals(after_posterior, train_pairs)
        result |= {
            "after": after_metrics["hybrid"],
            "after_run": str(after_dir),
            "shares_after": after_posterior.shares,
            "posterior": effect_posterior(after_posterior, chosen),
            "residuals_after": residuals_after,
        }
    else:
        _reuse_recalibration(after_dir, None)
        result |= {
            "after": before_metrics["hybrid"],
            "after_run": None,
            "shares_after": posterior.shares,
            "posterior": {},
            "residuals_after": residuals_before,
        }
    result["seconds"] = time.perf_counter() - began
    _write_report(run_dir, result, series_before, series_after, train_pairs.dt)
    return result


def _write_report(
    run_dir: Path,
    result: dict[str, Any],
    series_before: dict[str, list[np.ndarray]],
    series_after: dict[str, list[np.ndarray]] | None,
    dt: float,
) -> None:
    folder = run_dir / "loop"
    folder.mkdir(parents=True, exist_ok=True)
    figures = loop_figures(result, series_before, series_after, dt)
    for name, figure in figures.items():
        save_figure(figure, folder / f"{name}.png")
    markdown = loop_markdown(result, {name: f"loop/{name}.png" for name in figures})
    with RunLogger(run_dir / "tb") as logger:
        logger.text("loop", markdown)
    atomic_write_text(run_dir / "loop.md", markdown)
    # loop.json last: its presence says the loop finished.
    atomic_write_text(
        run_dir / "loop.json", json.dumps(json_safe(result), indent=2) + "\n"
    )


def _metric(value: Any) -> float | None:
    """A metric from ``metrics.json`` as a float (non-finite ones are stored as the
    strings "inf" / "nan")."""
    if isinstance(value, (int, float, str)):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _fmt(value: Any, digits: int = 3) -> str:
    if isinstance(value, str) and _metric(value) is not None:
        value = _metric(value)
    if value is None:
        return "—"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "inf"
        return (
            f"{value:.{digits}g}"
            if abs(value) < 1e-3 and value
            else f"{value:.{digits}f}"
        )
    return str(value)


def loop_markdown(result: dict[str, Any], figures: dict[str, str]) -> str:
    """``loop.md``: diagnostics, ranking, chosen effects, before/after table."""
    lines = [
        f"# Closing the loop: {result.get('dataset')}",
        "",
        f"Pool models that got the effects: {', '.join(result['pool'])}. "
        f"Significance: p < alpha / n_effects = {result['alpha']} / "
        f"{len(result['effects_ranked'])}, gain >= {result['min_gain']:.0%}.",
        "",
        "## Candidate effects, ranked by the consistency of their out-of-sample gain",
        "",
        "gain: relative drop of the summed validation score (last "
        f"{1 - result['fit_fraction']:.0%} of every training pair) when the pool "
        "models' variants with the effect join the pool, at equal particle budget "
        "(small ABC, then local search); statistic: t of the per-pair log score "
        "ratios; p-value: one-sided sign-flip test; estimate: median of the "
        "effect's parameters over the picks that carry it (a road effect: its one "
        "profile, fitted jointly over the pairs).",
        "",
        "| effect | gain | statistic | p-value | score before | score after "
        "| pairs | estimate | chosen |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in result["effects_ranked"]:
        estimate = row.get("shared", {}).get("value") or row.get("estimate") or {}
        lines.append(
            f"| {row['effect']} | {row['gain']:+.1%} | {_fmt(row['statistic'], 2)} | "
            f"{row['p_value']:.2g} | {_fmt(row['score_before'])} | "
            f"{_fmt(row['score_after'])} | {row['n_pairs']} | "
            + ", ".join(f"{k} {_fmt(v)}" for k, v in estimate.items())
            + f" | {'**yes**' if row['effect'] in result['chosen'] else ''} |"
        )
    lines += ["", f"![effects]({figures['effects']})", ""]
    if result["chosen"]:
        lines += ["## Chosen effects and their learned parameters", ""]
        for effect, summary in result["posterior"].items():
            lines.append(
                f"**{effect}** (share of the new hybrid: {summary['share']:.1%}; "
                f"residual signature: {EFFECT_HINTS.get(effect.split('(')[0], '')})"
            )
            lines += [
                "",
                "| parameter | median | 5 % | 95 % | particles |",
                "|---|---|---|---|---|",
            ]
            for name, stats in summary["params"].items():
                if stats["n"]:
                    lines.append(
                        f"| {name} | {_fmt(stats['median'])} | {_fmt(stats['q05'])} | "
                        f"{_fmt(stats['q95'])} | {stats['n']} |"
                    )
            lines.append("")
        shares = ", ".join(
            f"{k} {v:.1%}" for k, v in result["shares_after"].items() if v > 0
        )
        lines += [f"Shares after: {shares}.", ""]
    else:
        lines += [
            "**No effect chosen**: none has a significant out-of-sample gain, so "
            "nothing is re-calibrated ('after' = 'before').",
            "",
        ]
    lines += [
        "## Test-split error of the hybrid, before and after",
        "",
        "| | " + " | ".join(label for _, label in METRIC_COLUMNS) + " |",
        "|---|" + "---|" * len(METRIC_COLUMNS),
    ]
    for label in ("before", "after"):
        metrics = result[label]
        lines.append(
            f"| {label} | "
            + " | ".join(_fmt(metrics.get(key)) for key, _ in METRIC_COLUMNS)
            + " |"
        )
    for key, label in (("ws", "WS"), ("min", "Minimum distance")):
        before, after = (
            _metric(result["before"].get(key)),
            _metric(result["after"].get(key)),
        )
        if before and after is not None and math.isfinite(before):
            lines += ["", f"{label} change: {(after - before) / before:+.1%}."]
        elif key == "ws":
            lines += [
                "",
                "WS: not finite (a hybrid particle is invalid on every "
                "test pair, SPEC); see the minimum distance.",
            ]
    lines += ["", f"![before and after]({figures['before_after']})", ""]
    lines += [
        "## Residual diagnostics (training pairs, best hybrid particle per pair)",
        "",
        "| residual | test | p before | effect before | p after | effect after |",
        "|---|---|---|---|---|---|",
    ]
    after = {(r["channel"], r["test"]): r for r in result["residuals_after"]}
    for row in result["residuals_before"]:
        other = after.get((row["channel"], row["test"]), {})
        lines.append(
            f"| {row['channel']} | {row['test']} | {_fmt(row['p_value'], 2)} | "
            f"{_effect_text(row['effect'])} | {_fmt(other.get('p_value'), 2)} | "
            f"{_effect_text(other.get('effect'))} |"
        )
    lines += ["", f"![residuals]({figures['residuals']})", ""]
    lines.append(f"Loop time: {result['seconds']:.0f} s.")
    return "\n".join(lines) + "\n"


def _effect_text(effect: Any) -> str:
    if isinstance(effect, dict):
        return ", ".join(f"{k} {_fmt(v)}" for k, v in list(effect.items())[:2])
    return _fmt(effect)


def _reuse_recalibration(after_dir: Path, after_cfg: TrainConfig | None) -> bool:
    """Whether ``after_dir`` holds (part of) this very re-calibration, to resume.

    A loop run again may choose another effect, another shared-effect prior or
    nothing at all; a re-calibration left from an earlier loop is then removed, so
    that ``RUN_DIR/loop/after`` never shows a run that ``loop.json`` does not
    describe, and training does not refuse the directory.

    Args:
        after_dir: ``RUN_DIR/loop/after``, written only by the loop.
        after_cfg: this loop's re-calibration config; None when nothing is chosen.
    """
    if not after_dir.exists():
        return False
    if after_cfg is not None and (after_dir / "checkpoint.pt").exists():
        try:
            raw = json.loads((after_dir / "config.json").read_text(encoding="utf-8"))
            if config_hash(validate_config(raw)) == config_hash(after_cfg):
                return True
        except (OSError, ValueError):  # ConfigError and JSONDecodeError included
            pass  # unreadable: it cannot be resumed, so it is stale as well
    shutil.rmtree(after_dir)
    print(f"note: removed the earlier re-calibration in {after_dir}", file=sys.stderr)
    return False


# --------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.diagnose",
        description="Close the loop on a finished run: residual diagnosis, effect "
        "attribution, re-calibration; writes RUN_DIR/loop.json and loop.md.",
    )
    parser.add_argument("run_dir", help="a trained and evaluated run directory")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="diagnose.KEY=VALUE",
        help="override a diagnose setting (repeatable), e.g. diagnose.n_particles=1e5",
    )
    parser.add_argument("--threads", type=int, default=None, help="CPU threads")
    args = parser.parse_args(argv)
    from ..train import USER_ERRORS

    if args.threads is not None:
        if args.threads < 1:
            print("error: --threads must be >= 1", file=sys.stderr)
            return 2
        torch.set_num_threads(args.threads)
    try:
        result = diagnose_run(args.run_dir, args.overrides)
    except USER_ERRORS as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    print(f"effects ranked ({result['dataset']}):")
    for row in result["effects_ranked"]:
        mark = "  <- chosen" if row["effect"] in result["chosen"] else ""
        gain, p_value = row["gain"], row["p_value"]
        print(f"  {row['effect']:<28} gain {gain:+7.1%}  p {p_value:.4f}{mark}")
    ws_before, ws_after = result["before"].get("ws"), result["after"].get("ws")
    print(f"test WS: before {_fmt(ws_before)}, after {_fmt(ws_after)}")
    print(f"wrote {Path(args.run_dir) / 'loop.json'} and loop.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
