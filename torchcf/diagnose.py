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
2. **attributes**: for every candidate effect E of :mod:`torchcf.models.effects`,
   a small ABC run fits the *active* pool models B and their augmented variants
   ``m+E`` on the first ``fit_fraction`` of every training pair's steps; per pair
   the N best particles of B alone and of B together with the ``m+E`` (the
   hybrid's per-pair selection, so the originals compete) are then scored on the
   rest of the pair, out of sample. The gain of E is the relative drop of the
   summed per-pair validation score; its p-value is a one-sided sign-flip
   permutation test of the per-pair drops. An effect is chosen when its p-value
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
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from . import residuals as rt
from .config import ConfigError, TrainConfig, apply_overrides, validate_config
from .data import PairSet, load_split
from .evaluate import load_run
from .models import UnknownModelError, get_model
from .models.effects import Grade, parse_effect
from .plots import loop_figures, save_figure
from .posterior import Posterior, atomic_write_text, json_safe
from .report import METRIC_COLUMNS
from .sim import simulate
from .streams import ParticleStream
from .tblog import RunLogger
from .topn import TopN

FORMAT = "torchcf.loop/1"
#: Particles simulated per call in the attribution runs.
ATTRIBUTION_CHUNK = 1 << 16
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
class _Fit:
    """The per-pair top-N of one model variant on the fit windows."""

    name: str
    score: Tensor  # (n_pairs, N)
    theta: Tensor  # (n_pairs, N, K)


def _small_abc(
    name: str,
    pairs: PairSet,
    budgets: Sequence[int],
    top_n: int,
    cfg: TrainConfig,
    bounds: Tensor,
) -> list[_Fit]:
    """Paired ABC rejection of one model variant on ``pairs`` (streamed top-N).

    Args:
        budgets: increasing particle counts; the result holds the top-N after
            the first ``budgets[i]`` particles of the model's stream, for each i.
    """
    model = get_model(name)
    stream = ParticleStream(model.name, bounds, cfg.abc.seed, pairs.n_pairs)
    buffer = TopN(pairs.n_pairs, top_n, model.n_params)
    dtype = getattr(torch, cfg.dtype)
    fits, start = [], 0
    for budget in budgets:
        for first in range(start, budget, ATTRIBUTION_CHUNK):
            stop = min(first + ATTRIBUTION_CHUNK, budget)
            theta, pair = stream.draw(first, stop)
            out = simulate(
                model,
                theta.to(dtype),
                pairs,
                pair,
                dtype=dtype,
                device=cfg.device,
                weights=cfg.abc.weights,
            )
            score = out.score.double().cpu()
            buffer.push(pair, score, torch.arange(first, stop), theta)
        start = budget
        score, _, theta = buffer.first(top_n)
        fits.append(_Fit(model.name, score.clone(), theta.clone()))
    return fits


def _select(fits: list[_Fit], top_n: int) -> list[list[tuple[str, Tensor, float]]]:
    """Per pair, the N best particles over the variants (ties: variant order)."""
    scores = torch.cat([f.score for f in fits], dim=1)  # (n_pairs, V N)
    order = torch.sort(scores, dim=1, stable=True).indices[:, :top_n]
    chosen = []
    for j in range(scores.shape[0]):
        picks = []
        for flat in order[j].tolist():
            fit = fits[flat // top_n]
            slot = flat % top_n
            if math.isfinite(float(fit.score[j, slot])):
                picks.append((fit.name, fit.theta[j, slot], float(fit.score[j, slot])))
        chosen.append(picks)
    return chosen


def _validation_scores(
    picks: list[list[tuple[str, Tensor, float]]],
    validation: PairSet,
    cfg: TrainConfig,
) -> np.ndarray:
    """Median out-of-sample score of each pair's picks on its validation window.

    Returns:
        (n_pairs,) float64; ``inf`` where more than half the picks are invalid or
        a pair has no pick.
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
    dtype = getattr(torch, cfg.dtype)
    for name, (thetas, positions, where) in grouped.items():
        out = simulate(
            name,
            torch.stack(thetas).to(dtype),
            validation,
            torch.tensor(positions),
            dtype=dtype,
            device=cfg.device,
            weights=cfg.abc.weights,
        )
        scores = out.score.double().cpu().tolist()
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


def attribute_effects(
    cfg: TrainConfig,
    pool: list[str],
    effects: list[str],
    train_pairs: PairSet,
    *,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Rank the candidate effects by their out-of-sample gain (module docstring).

    Args:
        cfg: the run's config (its ``diagnose`` section sets the budget).
        pool: the pool models B that get each effect.
        effects: effect tokens (options resolved, see :func:`resolve_effect`).
        train_pairs: the run's training pairs.

    Returns:
        rows sorted by the statistic: ``name, statistic, gain, p_value, significant,
        score_before, score_after, n_pairs, variants``.
    """
    settings = cfg.diagnose
    fit, validation = split_in_time(train_pairs, settings.fit_fraction)
    top_n = cfg.abc.top_n
    priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
    n = settings.n_particles
    variants = {e: augmented_variants(pool, e) for e in effects}
    names = pool + [name for group in variants.values() for name in group]
    # Equal budgets: the pool with an effect is the pool's n particles plus n of
    # each variant, so the pool alone gets 2 n, or any extra flexibility would
    # look like a gain.
    fits: dict[str, _Fit] = {}
    doubled: dict[str, _Fit] = {}
    bar = tqdm(names, desc="attribution", unit="variant", disable=not progress)
    for name in bar:
        bar.set_postfix_str(name, refresh=True)
        model = get_model(name)
        bounds = model.prior_bounds(torch.float64)
        base = model.base.name if hasattr(model, "base") else model.name
        if base in priors:  # the run's prior overrides of the pool model
            bounds[: priors[base].shape[0]] = priors[base]
        budgets = (n, 2 * n) if name in pool else (n,)
        result = _small_abc(name, fit, budgets, top_n, cfg, bounds)
        fits[name] = result[0]
        if name in pool:
            doubled[name] = result[1]
    before = _validation_scores(
        _select([doubled[m] for m in pool], top_n), validation, cfg
    )
    rows = []
    for effect in effects:
        group = [fits[m] for m in pool] + [fits[v] for v in variants[effect]]
        after = _validation_scores(_select(group, top_n), validation, cfg)
        if not variants[effect]:  # no pool model can take the effect
            after = before.copy()
        usable = np.isfinite(before) & np.isfinite(after)
        drops = before[usable] - after[usable]
        if drops.size < 2:
            statistic, p_value, gain = 0.0, 1.0, 0.0
        else:
            statistic, p_value = sign_flip_test(drops, settings.permutations)
            gain = float(drops.sum() / before[usable].sum())
        rows.append(
            {
                "name": effect.split("(")[0],
                "effect": effect,
                "statistic": statistic,
                "gain": gain,
                "p_value": p_value,
                "score_before": float(before[usable].mean()) if usable.any() else None,
                "score_after": float(after[usable].mean()) if usable.any() else None,
                "n_pairs": int(usable.sum()),
                "variants": variants[effect],
            }
        )
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
    cfg: TrainConfig, pool: list[str], chosen: list[str]
) -> TrainConfig:
    raw = cfg.model_dump(mode="json")
    present = {spec["name"] for spec in raw["models"]}
    for effect in chosen:
        for variant in augmented_variants(pool, effect):
            name = get_model(variant).base.name
            if variant not in present:
                prior = next(
                    (s["prior"] for s in raw["models"] if s["name"] == name), None
                )
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
    from .train import train  # not at the top: the trainer imports this module

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
    if chosen:
        after_cfg = _recalibration_config(cfg, pool, chosen)
        after_dir = run_dir / "loop" / "after"
        train(
            after_cfg,
            after_dir,
            resume=(after_dir / "config.json").exists(),
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


def _fmt(value: Any, digits: int = 3) -> str:
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
        "models' variants with the effect join the pool, at equal particle budget; "
        "statistic: t of the per-pair drops; p-value: one-sided sign-flip test.",
        "",
        "| effect | gain | statistic | p-value | score before | score after "
        "| pairs | chosen |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in result["effects_ranked"]:
        lines.append(
            f"| {row['effect']} | {row['gain']:+.1%} | {_fmt(row['statistic'], 2)} | "
            f"{_fmt(row['p_value'], 2)} | {_fmt(row['score_before'])} | "
            f"{_fmt(row['score_after'])} | {row['n_pairs']} | "
            f"{'**yes**' if row['effect'] in result['chosen'] else ''} |"
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
    ws_before, ws_after = result["before"].get("ws"), result["after"].get("ws")
    if ws_before and ws_after is not None and math.isfinite(ws_before):
        lines += ["", f"WS change: {(ws_after - ws_before) / ws_before:+.1%}."]
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
    from .train import USER_ERRORS

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
