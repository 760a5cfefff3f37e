"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

The loop takes a finished, evaluated run and

1. **diagnoses** the residuals of every training pair driven by its best hybrid
   particle (:mod:`torchcf.diagnose.series`);
2. **attributes**: chooses effects by forward stepwise selection on their
   out-of-sample gain (:mod:`torchcf.diagnose.attribution`);
3. **re-calibrates** the run's pool plus the variants of the chosen effects
   (``m+E1``, ``m+E2``, ``m+E1+E2``...: the selection's final model; a full
   training run in ``RUN_DIR/loop/after``, evaluated on the test split);
4. **reports** ``RUN_DIR/loop.json`` (``effects_ranked``, ``chosen``, the
   ``posterior`` of the added parameters, the test metrics ``before`` and
   ``after``, the residual diagnostics before and after) and ``RUN_DIR/loop.md``
   with figures in ``RUN_DIR/loop/`` (:mod:`torchcf.diagnose.report`).

The loop never trains: :func:`plan_loop` does steps 1-2 and says which
re-calibration to run (:attr:`LoopPlan.recalibration`); the caller runs it
(:func:`torchcf.pipeline.close_loop`) and :func:`finish_loop` does step 4.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..config import (
    ConfigError,
    TrainConfig,
    apply_overrides,
    config_hash,
    validate_config,
)
from ..data import PairSet, load_split
from ..models import get_model
from ..models.effects import RoadProfile, parse_effect
from ..posterior import Posterior
from ..rundir import RunDir
from .attribution import Selection, attribute_effects, resolve_effect
from .identifiability import effect_identifiability
from .report import write_report
from .road import (
    choose_spacing,
    fit_window,
    one_step_residual,
    shares_road_frame,
)
from .series import DiagnoseError, best_particles, diagnose_residuals

FORMAT = "torchcf.loop/1"

Series = dict[str, list[np.ndarray]]


# ------------------------------------------------------------- the pool, after
def active_models(cfg: TrainConfig, posterior: Posterior) -> list[str]:
    """The pool models that get the effects: every plain model of the run
    (``diagnose.models = "all"``), or those with a share of at least
    ``diagnose.min_share`` (at least the largest)."""
    names = [spec.name for spec in cfg.models if "+" not in spec.name]
    if cfg.diagnose.models == "all":
        return names
    active = [
        n for n in names if posterior.shares.get(n, 0.0) >= cfg.diagnose.min_share
    ]
    return active or [max(names, key=lambda n: posterior.shares.get(n, 0.0))]


def recalibration_config(
    cfg: TrainConfig,
    variants: Sequence[str],
    effect_priors: dict[str, dict[str, tuple[float, float]]] | None = None,
) -> TrainConfig:
    """The run's config plus the ``variants`` (``m+E1+...``) of the selection's
    final model, for re-calibration.

    Args:
        variants: augmented model names; those already in the run are kept once.
        effect_priors: per effect token, prior boxes of its parameters replacing
            the defaults (a shared effect's value found by the attribution: the
            road is one, so its profile is not re-drawn per particle).
    """
    raw = cfg.model_dump(mode="json")
    present = {spec["name"] for spec in raw["models"]}
    for variant in variants:
        model = get_model(variant)
        if model.name in present or not hasattr(model, "effects"):
            continue
        prior = next(
            (s["prior"] for s in raw["models"] if s["name"] == model.base.name), None
        )
        for effect in model.effects:
            extra = (effect_priors or {}).get(effect.token)
            if extra:
                prior = {**(prior or {}), **{k: list(v) for k, v in extra.items()}}
        raw["models"].append({"name": model.name, "prior": prior})
        present.add(model.name)
    if cfg.diagnose.recalibrate_particles is not None:
        raw["abc"]["n_particles"] = cfg.diagnose.recalibrate_particles
    if cfg.diagnose.recalibrate_method is not None:
        raw["abc"]["method"] = cfg.diagnose.recalibrate_method
    raw["diagnose"]["run_after_training"] = False
    raw["output"] = None
    return validate_config(raw)


def reference_config(
    cfg: TrainConfig, recalibration: TrainConfig
) -> TrainConfig | None:
    """The run's pool alone, searched as ``recalibration`` is (its method and
    budget), or None when that is the run's own search: the 'before' that the
    re-calibration is fairly compared with (a refined search alone lowers the
    error; the effect must do better than that)."""
    if (
        recalibration.abc.method == cfg.abc.method
        and recalibration.abc.n_particles == cfg.abc.n_particles
    ):
        return None
    raw = cfg.model_dump(mode="json")
    raw["abc"]["method"] = recalibration.abc.method
    raw["abc"]["n_particles"] = recalibration.abc.n_particles
    raw["diagnose"]["run_after_training"] = False
    raw["output"] = None
    return validate_config(raw)


def reuse_recalibration(after_dir: Path, after_cfg: TrainConfig | None) -> bool:
    """Whether ``after_dir`` holds (part of) this very re-calibration, to resume.

    A loop run again may choose another effect, another shared-effect prior or
    nothing at all; a re-calibration left from an earlier loop is then removed, so
    that ``RUN_DIR/loop/after`` never shows a run that ``loop.json`` does not
    describe, and training does not refuse the directory.

    Args:
        after_dir: ``RUN_DIR/loop/after``, written only by the loop.
        after_cfg: this loop's re-calibration config; None when nothing is chosen.
    """
    after = RunDir(after_dir)
    if not after.path.exists():
        return False
    if after_cfg is not None and after.has_checkpoint():
        try:
            if config_hash(after.read_config()) == config_hash(after_cfg):
                return True
        except (OSError, ValueError):  # RunFileError and ConfigError included
            pass  # unreadable: it cannot be resumed, so it is stale as well
    shutil.rmtree(after.path)
    print(f"note: removed the earlier re-calibration in {after_dir}", file=sys.stderr)
    return False


def effect_posterior(posterior: Posterior, chosen: list[str]) -> dict[str, Any]:
    """Summary of each chosen effect's parameters over the hybrid's particles:
    ``{effect: {"share", "params": {name: {n, median, q05, q95, mean}}}}``."""
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
        params = {
            n: _quantiles(torch.cat(parts) if parts else torch.empty(0))
            for n, parts in columns.items()
        }
        result[effect] = {"share": share, "params": params}
    return result


def _quantiles(values: Tensor) -> dict[str, Any]:
    if values.numel() == 0:
        return {"n": 0}
    q = torch.quantile(values, torch.tensor([0.05, 0.5, 0.95], dtype=values.dtype))
    return {
        "n": int(values.numel()),
        "median": float(q[1]),
        "q05": float(q[0]),
        "q95": float(q[2]),
        "mean": float(values.mean()),
    }


# ------------------------------------------------------------- the candidates
def candidate_effects(
    cfg: TrainConfig, train_pairs: PairSet, series: Series
) -> tuple[list[str], dict[str, Any], dict[str, Tensor]]:
    """The effects the attribution tries, resolved on the training pairs.

    Args:
        series: the one-step residual (:func:`~torchcf.diagnose.road.
            one_step_residual`) of the run's best particle per pair.

    Road effects (``shared``) only where the pairs share one road frame
    (:func:`~torchcf.diagnose.road.shares_road_frame`); a bare ``grade`` or
    ``bend`` spans the pairs' road section with its knot spacing chosen by
    cross-validation on the fit windows' one-step residuals
    (:func:`~torchcf.diagnose.road.choose_spacing`).

    Returns:
        the effect tokens; the road report (``frame``, ``reason``, ``skipped``,
        ``profiles``: the spacing chosen and the error of each); per road
        token, a first candidate of its value.
    """
    frame, reason = shares_road_frame(train_pairs)
    fit_steps = int(round(cfg.diagnose.fit_fraction * train_pairs.n_steps))
    fit_series = fit_window(series, fit_steps)
    effects, skipped, profiles, seeds = [], [], [], {}
    for token in cfg.diagnose.effects:
        effect = parse_effect(token)
        if effect.shared and not frame:
            skipped.append(effect.token)
            continue
        if isinstance(effect, RoadProfile) and "(" not in token:
            section = parse_effect(resolve_effect(token, train_pairs))
            choice = choose_spacing(effect.name, section.start, section.end, fit_series)
            effects.append(choice.token)
            profiles.append(choice.report())
            if choice.seed is not None:
                seeds[choice.token] = choice.seed
            continue
        effects.append(resolve_effect(token, train_pairs))
    road = {"frame": frame, "reason": reason, "skipped": skipped}
    road["profiles"] = profiles
    return effects, road, seeds


# -------------------------------------------------------------------- the loop
@dataclass(frozen=True)
class LoopPlan:
    """The loop up to its re-calibration (:func:`plan_loop`).

    Attributes:
        run: the diagnosed run.
        cfg: its config with the ``diagnose.*`` overrides.
        posterior: its posterior.
        before: its ``metrics.json``.
        train_pairs, test_pairs: its split.
        pool: the pool models that got the effects.
        road: how road effects were offered (:func:`candidate_effects`).
        selection: the forward selection's steps and choice
            (:func:`attribute_effects`).
        residuals_before: the residual tests of the run; series_before: its
            residual series.
        recalibration: the re-calibration's config (None: nothing chosen, nothing
            to train) to run in :attr:`recalibration_dir`.
        resume_recalibration: that directory holds a part of this very
            re-calibration, to resume.
        reference: the pool alone searched as the re-calibration
            (:func:`reference_config`), to run in :attr:`reference_dir`; None
            when nothing is chosen or the search is the run's.
        resume_reference: that directory holds a part of it, to resume.
        began: ``time.perf_counter()`` at the start of the loop.
    """

    run: RunDir
    cfg: TrainConfig
    posterior: Posterior
    before: dict[str, Any]
    train_pairs: PairSet
    test_pairs: PairSet
    pool: list[str]
    road: dict[str, Any]
    selection: Selection
    residuals_before: list[dict]
    series_before: Series
    recalibration: TrainConfig | None
    resume_recalibration: bool
    reference: TrainConfig | None
    resume_reference: bool
    began: float

    @property
    def chosen(self) -> list[str]:
        """The chosen effect tokens, in the order chosen."""
        return self.selection.chosen

    @property
    def recalibration_dir(self) -> Path:
        """``RUN_DIR/loop/after``."""
        return self.run.recalibration_dir

    @property
    def reference_dir(self) -> Path:
        """``RUN_DIR/loop/reference``."""
        return self.run.reference_dir


def plan_loop(
    run_dir: str | Path,
    overrides: Sequence[str] = (),
    *,
    pairs: tuple[PairSet, PairSet] | None = None,
    progress: bool = True,
) -> LoopPlan:
    """Steps 1-2 of the loop on a finished, evaluated run (module docstring), and
    the re-calibration it asks for (a stale one in ``RUN_DIR/loop/after`` is
    removed).

    Args:
        run_dir: a trainer output directory holding ``metrics.json``.
        overrides: ``diagnose.key=VALUE`` items applied to the run's config.
        pairs: optional ``(train, test)`` instead of loading the run's data.
        progress: show progress bars.

    Raises:
        RunFileError: a file of the run is missing, unreadable or corrupted (the
            run is not trained or not evaluated).
        ConfigError: an override is not a ``diagnose.*`` key or not valid.
        DiagnoseError: the run cannot be diagnosed (other training pairs than
            the posterior's, none with a particle, windows too short).
    """
    began = time.perf_counter()
    run = RunDir(run_dir)
    cfg, posterior, _ = run.load_run()
    cfg = _with_overrides(cfg, overrides)
    before = run.read_metrics()
    train_pairs, test_pairs = load_split(cfg.data) if pairs is None else pairs
    if tuple(train_pairs.pair_ids) != tuple(posterior.train_pair_ids.tolist()):
        raise DiagnoseError("the training pairs differ from the run's posterior")

    residuals_before, series_before = diagnose_residuals(posterior, train_pairs)
    pool = active_models(cfg, posterior)
    one_step = one_step_residual(best_particles(posterior, train_pairs), train_pairs)
    effects, road, seeds = candidate_effects(cfg, train_pairs, one_step)
    selection = attribute_effects(
        cfg, pool, effects, train_pairs, seeds=seeds, progress=progress
    )
    recalibration, reference = None, None
    if selection.chosen:
        variants = [m for m in selection.models if m not in pool]
        recalibration = recalibration_config(cfg, variants, selection.shared_priors)
        reference = reference_config(cfg, recalibration)
    return LoopPlan(
        run=run,
        cfg=cfg,
        posterior=posterior,
        before=before,
        train_pairs=train_pairs,
        test_pairs=test_pairs,
        pool=pool,
        road=road,
        selection=selection,
        residuals_before=residuals_before,
        series_before=series_before,
        recalibration=recalibration,
        resume_recalibration=reuse_recalibration(run.recalibration_dir, recalibration),
        reference=reference,
        resume_reference=reuse_recalibration(run.reference_dir, reference),
        began=began,
    )


def _with_overrides(cfg: TrainConfig, overrides: Sequence[str]) -> TrainConfig:
    """``cfg`` with ``diagnose.key=VALUE`` overrides (no other section)."""
    if not overrides:
        return cfg
    bad = [o for o in overrides if not o.strip().startswith("diagnose.")]
    if bad:
        raise ConfigError(f"--set only takes diagnose.* keys here, got {bad[0]!r}")
    return validate_config(apply_overrides(cfg.model_dump(mode="json"), overrides))


def finish_loop(plan: LoopPlan) -> dict[str, Any]:
    """Step 4 of the loop, after the re-calibration ran in
    :attr:`LoopPlan.recalibration_dir` (or nothing was chosen): the residuals
    after, the chosen effects' posterior, ``loop.md`` with its figures, the
    TensorBoard text and, last, ``loop.json``.

    Returns:
        the loop result (also in ``RUN_DIR/loop.json``).

    Raises:
        RunFileError: the re-calibration left no posterior or metrics.
    """
    result: dict[str, Any] = {
        "format": FORMAT,
        "run": str(plan.run),
        "dataset": plan.before.get("dataset"),
        "pool": plan.pool,
        "road": plan.road,
        "effects_ranked": plan.selection.steps[0],
        "steps": plan.selection.steps,
        "chosen": plan.chosen,
        "models_after": plan.selection.models,
        "steps_at_most": plan.selection.steps_at_most,
        "tests": plan.selection.tests,
        "threshold": plan.selection.threshold,
        "alpha": plan.cfg.diagnose.alpha,
        "fit_fraction": plan.cfg.diagnose.fit_fraction,
        "min_gain": plan.cfg.diagnose.min_gain,
        "before": plan.before["hybrid"],
        "residuals_before": plan.residuals_before,
    }
    after, series_after = _after(plan)
    result |= after
    result["seconds"] = time.perf_counter() - plan.began
    write_report(
        plan.run, result, plan.series_before, series_after, plan.train_pairs.dt
    )
    return result


def _after(plan: LoopPlan) -> tuple[dict[str, Any], Series | None]:
    """The result's "after" entries and the residual series after (None: nothing
    was re-calibrated, "after" is "before")."""
    if plan.recalibration is None:
        return {
            "after": plan.before["hybrid"],
            "after_run": None,
            "shares_after": plan.posterior.shares,
            "before_same_search": None,
            "reference_run": None,
            "posterior": {},
            "identifiability": {},
            "residuals_after": plan.residuals_before,
        }, None
    after = RunDir(plan.recalibration_dir)
    posterior = after.load_posterior()
    metrics = after.read_metrics()
    residuals, series = diagnose_residuals(posterior, plan.train_pairs)
    reference = None
    if plan.reference is not None:
        reference = RunDir(plan.reference_dir).read_metrics()["hybrid"]
    return {
        "after": metrics["hybrid"],
        "after_run": str(after),
        "before_same_search": reference,
        "reference_run": str(plan.reference_dir) if reference else None,
        "shares_after": posterior.shares,
        "posterior": effect_posterior(posterior, plan.chosen),
        "identifiability": effect_identifiability(posterior, plan.chosen),
        "residuals_after": residuals,
    }, series


__all__ = [
    "FORMAT",
    "LoopPlan",
    "active_models",
    "candidate_effects",
    "effect_posterior",
    "finish_loop",
    "plan_loop",
    "recalibration_config",
    "reference_config",
    "reuse_recalibration",
]
