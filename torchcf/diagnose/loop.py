"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

The loop takes a finished, evaluated run and

1. **diagnoses** the residuals of every training pair driven by its best hybrid
   particle (:mod:`torchcf.diagnose.signatures.series`);
2. **attributes**: traces the residual's signatures to the effects they point
   to and chooses effects by forward selection of nested arms on their
   out-of-sample gain (:mod:`torchcf.diagnose.signatures.families`,
   :mod:`torchcf.diagnose.selection.attribution`);
3. **re-calibrates** the run's particles with the chosen effects on the whole
   training windows, beside the run's particles searched the same way without
   them (:mod:`torchcf.diagnose.recalibration`; ``RUN_DIR/loop/after`` and
   ``RUN_DIR/loop/reference``, each evaluated on the test split);
4. **reports** ``RUN_DIR/loop.json`` and ``RUN_DIR/loop.md`` with figures in
   ``RUN_DIR/loop/`` (:mod:`torchcf.diagnose.report.markdown`).

:func:`plan_loop` does steps 1-2, :func:`run_recalibration` step 3 (the caller,
:func:`torchcf.study.pipeline.close_loop`, evaluates its runs) and :func:`finish_loop`
step 4.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..abc.screen import PlausibilityScreen
from ..config import (
    ConfigError,
    TrainConfig,
    apply_overrides,
    config_hash,
    load_index,
    load_split,
    validate_config,
)
from ..data import PairSet
from ..models import CFModel, get_model
from ..models.effects import Effect, RoadProfile, parse_effect
from ..posterior import Posterior
from ..runs.directory import RunDir
from ..runs.metrics import Evaluation
from .arms.arena import spanning
from .arms.identifiability import effect_identifiability
from .arms.refit import Pin
from .arms.validation import fit_part, pair_groups
from .recalibration import (
    Buffers,
    FinalModel,
    buffers_in_order,
    recalibration_config,
    retrain,
    variants_of,
    wrapped,
    write_run,
)
from .report.markdown import write_report
from .report.outcome import (
    ChangeOnTest,
    EffectPosterior,
    LoopResult,
    ParamSpread,
    Recalibrated,
    SearchBudget,
    Unexplained,
)
from .selection.attribution import EffectSelection, RoadStart, attribute_effects
from .selection.on_test import ClassOnTest, chosen_value, class_on_test
from .setup import LoopSetup
from .signatures.families import family_of
from .signatures.response import ResponseTimes, response_times
from .signatures.road import (
    RoadOffer,
    choose_spacing,
    one_step_residual,
    shares_road_frame,
)
from .signatures.series import (
    DiagnoseError,
    ResidualRow,
    best_particles,
    diagnose_residuals,
)
from .significance import paired_change

Series = dict[str, list[np.ndarray]]


# ------------------------------------------------------------- the pool, after
def active_models(cfg: TrainConfig, posterior: Posterior) -> list[CFModel]:
    """The pool models that get the effects, as the config's model objects:
    every plain model of the run (``diagnose.models = "all"``), or those with a
    share of at least ``diagnose.min_share`` (at least the largest)."""
    plain = [spec.model for spec in cfg.models if spec.plain]
    if cfg.diagnose.models == "all":
        return plain

    def share(model: CFModel) -> float:
        return posterior.shares.get(model.name, 0.0)

    active = [m for m in plain if share(m) >= cfg.diagnose.min_share]
    return active or [max(plain, key=share)]


def reusable(directory: Path, cfg: TrainConfig | None) -> bool:
    """Whether ``directory`` holds this very re-calibration, evaluated: a loop run
    again reads it back. Anything else there (an earlier loop's, which chose
    another effect or value, or one cut short) is removed, so that
    ``RUN_DIR/loop/after`` never shows a run that ``loop.json`` does not
    describe.

    Args:
        directory: ``RUN_DIR/loop/after`` or ``RUN_DIR/loop/reference``, written
            only by the loop.
        cfg: this loop's config of it; None when nothing is chosen.
    """
    run = RunDir(directory)
    if not run.path.exists():
        return False
    if cfg is not None and run.is_evaluated():
        try:
            if config_hash(run.read_config()) == config_hash(cfg):
                return True
        except (OSError, ValueError):  # RunFileError and ConfigError included
            pass  # unreadable: stale as well
    shutil.rmtree(run.path)
    print(f"note: removed the earlier re-calibration in {directory}", file=sys.stderr)
    return False


def effect_posterior(
    posterior: Posterior, chosen: list[Effect]
) -> dict[str, EffectPosterior]:
    """Per chosen effect's token, its parameters over the hybrid's particles."""
    result: dict[str, EffectPosterior] = {}
    for effect in chosen:
        names = [p.name for p in effect.param_specs]
        columns: dict[str, list[Tensor]] = {n: [] for n in names}
        share = 0.0
        for model, particles in posterior.hybrid.items():
            # the after run's posterior names its models: they enter here
            if effect.name not in get_model(model).effect_kinds:
                continue
            share += posterior.shares.get(model, 0.0)
            for n in names:
                columns[n].append(particles.theta[:, particles.param_names.index(n)])
        params = {
            n: _quantiles(torch.cat(parts) if parts else torch.empty(0))
            for n, parts in columns.items()
        }
        result[effect.token] = EffectPosterior(share=share, params=params)
    return result


def _quantiles(values: Tensor) -> ParamSpread:
    if values.numel() == 0:
        return ParamSpread(n=0)
    q = torch.quantile(values, torch.tensor([0.05, 0.5, 0.95], dtype=values.dtype))
    return ParamSpread(
        n=int(values.numel()),
        median=float(q[1]),
        q05=float(q[0]),
        q95=float(q[2]),
        mean=float(values.mean()),
    )


# ------------------------------------------------------------- the candidates
@dataclass(frozen=True)
class Candidates:
    """The effects the attribution tries, resolved on the training pairs.

    Attributes:
        effects: the candidate effects, parsed from ``diagnose.effects`` (where
            they enter the loop) and resolved on the pairs.
        road: how road effects were offered.
        seeds: per road effect, a first candidate of its value.
        profile: the road profile whose residual signature is tested (None: the
            pairs have a frame each, or no road effect is a candidate).
    """

    effects: list[Effect]
    road: RoadOffer
    seeds: dict[Effect, Tensor]
    profile: RoadProfile | None


def candidate_effects(
    setup: LoopSetup, train_pairs: PairSet, series: Series
) -> Candidates:
    """The effects the attribution tries, resolved on the training pairs.

    Args:
        series: the one-step residual (:func:`~torchcf.diagnose.signatures.road.
            one_step_residual`) of the run's best particle per pair.

    Road effects (``scope = "road"``) only where the pairs share one road frame
    (:func:`~torchcf.diagnose.signatures.road.shares_road_frame`); a bare ``grade`` or
    ``bend`` spans the pairs' road section with its knot spacing chosen by
    cross-validation on the one-step residuals of the part the arms are fitted
    on (:func:`~torchcf.diagnose.arms.validation.fit_part`)
    (:func:`~torchcf.diagnose.signatures.road.choose_spacing`).
    """
    frame, reason = shares_road_frame(train_pairs)
    fit_series = fit_part(setup, setup.seed, train_pairs.n_steps, series)
    effects, skipped, profiles, seeds = [], [], [], {}
    profile = None
    for token in setup.settings.effects:
        effect = parse_effect(token)  # where the configured effects enter
        if effect.scope == "road" and not frame:
            skipped.append(effect)
            continue
        if isinstance(effect, RoadProfile) and "(" not in token:
            section = spanning(effect, train_pairs)
            choice = choose_spacing(
                type(effect),
                section.start,
                section.end,
                fit_series,
                period=section.period,
            )
            effects.append(choice.effect)
            profiles.append(choice)
            if choice.seed is not None:
                seeds[choice.effect] = choice.seed
            if profile is None:
                profile = choice.effect
            continue
        effects.append(effect)
        if profile is None and isinstance(effect, RoadProfile):
            profile = effect
    road = RoadOffer(frame, reason, skipped, profiles)
    return Candidates(effects, road, seeds, profile)


# -------------------------------------------------------------------- the loop
@dataclass(frozen=True)
class LoopPlan:
    """The loop up to its re-calibration (:func:`plan_loop`).

    Attributes:
        run: the diagnosed run.
        cfg: its config with the ``diagnose.*`` overrides.
        posterior: its posterior.
        dataset: its data set's label (``summary.json``'s; the re-calibration's
            summaries carry it).
        before: its evaluation (``metrics.json``).
        train_pairs, test_pairs: its split.
        pool: the pool models that got the effects (model objects;
            ``loop.json`` lists their names).
        road: how road effects were offered (:class:`Candidates`).
        selection: the forward selection (:func:`attribute_effects`).
        residuals_before: the residual tests of the run; series_before: its
            residual series.
        recalibration: the config of the re-calibration (the run's models and
            the chosen variants; None: nothing chosen).
        resume_recalibration: ``RUN_DIR/loop/after`` and ``.../reference`` hold
            this re-calibration, evaluated (a loop run again reads them back).
        began: ``time.perf_counter()`` at the start of the loop.
        response_before: the data's and the run's response times.
        class_on_test: the model class with and without the chosen effects,
            every test pair refitted (None: nothing chosen).
    """

    run: RunDir
    cfg: TrainConfig
    posterior: Posterior
    dataset: str
    before: Evaluation
    train_pairs: PairSet
    test_pairs: PairSet
    pool: tuple[CFModel, ...]
    road: RoadOffer
    selection: EffectSelection
    residuals_before: list[ResidualRow]
    series_before: Series
    recalibration: TrainConfig | None
    resume_recalibration: bool
    began: float
    response_before: ResponseTimes | None = None
    class_on_test: ClassOnTest | None = None

    @property
    def chosen(self) -> list[Effect]:
        """The chosen effects, in the order chosen."""
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
    run_dir: str | Path | RunDir,
    overrides: Sequence[str] = (),
    *,
    pairs: tuple[PairSet, PairSet] | None = None,
    groups: Tensor | None = None,
    progress: bool = True,
) -> LoopPlan:
    """Steps 1-2 of the loop on a finished, evaluated run (module docstring), and
    the re-calibration it asks for (a stale one in ``RUN_DIR/loop`` is removed).

    Args:
        run_dir: a trainer output directory holding ``metrics.json``.
        overrides: ``diagnose.key=VALUE`` items applied to the run's config.
        pairs: optional ``(train, test)`` instead of loading the run's data.
        groups: (N,) each training pair's driver or run, which cross-fitting
            keeps apart (None: from the data's ``index.csv`` where the run
            loads its data, else each pair its own).
        progress: show progress bars.

    Raises:
        RunFileError: a file of the run is missing, unreadable or corrupted (the
            run is not trained or not evaluated, or its ``metrics.json`` is not
            an evaluation this release reads).
        ConfigError: an override is not a ``diagnose.*`` key or not valid.
        DiagnoseError: the run cannot be diagnosed (other training pairs than
            the posterior's, none with a particle, windows too short).
    """
    began = time.perf_counter()
    run = RunDir(run_dir)
    cfg, posterior, summary = run.load_run()
    cfg = _with_overrides(cfg, overrides)
    before = run.read_metrics()
    train_pairs, test_pairs = load_split(cfg.data) if pairs is None else pairs
    if tuple(train_pairs.pair_ids) != tuple(posterior.train_pair_ids.tolist()):
        raise DiagnoseError("the training pairs differ from the run's posterior")

    residuals_before, series_before = diagnose_residuals(posterior, train_pairs)
    pool = tuple(active_models(cfg, posterior))
    best_before = best_particles(posterior, train_pairs)
    one_step = one_step_residual(best_before, train_pairs)
    setup = LoopSetup.of(cfg)  # the config, once, for the stages below
    candidates = candidate_effects(setup, train_pairs, one_step)
    selection = attribute_effects(
        setup,
        pool,
        candidates.effects,
        train_pairs,
        road=RoadStart(candidates.seeds, candidates.profile),
        groups=groups
        if groups is not None
        else pair_groups(train_pairs, load_index(cfg.data) if pairs is None else None),
        ledger=run.loop_dir / "attribution.pt",
        progress=progress,
    )
    recalibration, on_test = None, None
    if selection.chosen and selection.start is not None and selection.final is not None:
        pins = [
            Pin(e, chosen_value(e, selection.shared, selection.estimates))
            for e in selection.chosen
        ]
        on_test = class_on_test(
            setup, selection.start, selection.final, pins, test_pairs
        )
    if selection.chosen:
        run_models = [spec.model for spec in cfg.models]
        variants = [m for m in selection.models if m not in run_models]
        recalibration = recalibration_config(cfg, variants, selection.shared_priors)
    resume = reusable(run.recalibration_dir, recalibration)
    resume = reusable(run.reference_dir, recalibration) and resume
    return LoopPlan(
        run=run,
        cfg=cfg,
        posterior=posterior,
        dataset=summary.dataset,
        before=before,
        train_pairs=train_pairs,
        test_pairs=test_pairs,
        pool=pool,
        road=candidates.road,
        selection=selection,
        residuals_before=residuals_before,
        series_before=series_before,
        recalibration=recalibration,
        resume_recalibration=resume,
        began=began,
        response_before=response_times(best_before, series_before, train_pairs),
        class_on_test=on_test,
    )


def _with_overrides(cfg: TrainConfig, overrides: Sequence[str]) -> TrainConfig:
    """``cfg`` with ``diagnose.key=VALUE`` overrides (no other section)."""
    if not overrides:
        return cfg
    bad = [o for o in overrides if not o.strip().startswith("diagnose.")]
    if bad:
        raise ConfigError(f"--set only takes diagnose.* keys here, got {bad[0]!r}")
    return validate_config(apply_overrides(cfg.model_dump(mode="json"), overrides))


def run_recalibration(
    plan: LoopPlan,
    progress: bool = True,
    screen: PlausibilityScreen | None = None,
) -> None:
    """Loop step 3: the reference and after, written as run directories
    (evaluation is the caller's: :func:`torchcf.study.pipeline.close_loop`), by the
    run's own sampler (:mod:`torchcf.diagnose.recalibration`, with the run's
    plausibility filter ``screen``, built by the caller). Nothing to do when
    nothing is chosen or both are there already."""
    if plan.recalibration is None or plan.resume_recalibration:
        return
    models = [spec.model for spec in plan.recalibration.models]
    reference_cfg = recalibration_config(plan.cfg, [], {})
    run_models = [spec.model for spec in reference_cfg.models]
    names, run_names = [m.name for m in models], [m.name for m in run_models]
    reference, after = _trained_buffers(plan, progress, screen)
    references = buffers_in_order(reference, run_names)
    afters = buffers_in_order(after, names)
    how = "the run's buffers, then the pool's variants trained by the run's "
    how += "sampler (torchcf.diagnose.recalibration)"
    for directory in (plan.reference_dir, plan.recalibration_dir):
        if directory.exists():
            shutil.rmtree(directory)
    write_run(
        plan.reference_dir,
        reference_cfg,
        plan.posterior,
        references,
        plan.dataset,
        how,
    )
    write_run(
        plan.recalibration_dir,
        plan.recalibration,
        plan.posterior,
        afters,
        plan.dataset,
        how,
    )


def _trained_buffers(
    plan: LoopPlan, progress: bool, screen: PlausibilityScreen | None
) -> tuple[Buffers, Buffers]:
    """:func:`~torchcf.diagnose.recalibration.retrain` with a progress bar in
    particles (the reference's and every variant's)."""
    final = FinalModel.of(plan.selection)
    variants = variants_of(final.models, plan.posterior.models)
    models = len(variants) + len(wrapped(variants, plan.pool))
    total = plan.cfg.abc.n_particles * models
    with tqdm(
        total=total, desc="re-calibration", unit="particle", disable=not progress
    ) as bar:
        return retrain(
            plan.cfg,
            plan.posterior,
            final,
            plan.pool,
            plan.train_pairs,
            screen=screen,
            ledger=plan.run.loop_dir / "retrain.pt",
            tick=bar.update,
        )


def finish_loop(plan: LoopPlan) -> LoopResult:
    """Step 4 of the loop, after the re-calibration was written and evaluated in
    :attr:`LoopPlan.recalibration_dir` and :attr:`LoopPlan.reference_dir` (or
    nothing was chosen): the residuals after, the chosen effects' posterior,
    ``loop.md`` with its figures, the TensorBoard text and, last, ``loop.json``.

    Returns:
        the loop result (:meth:`~torchcf.diagnose.report.outcome.LoopResult.to_json`
        is ``RUN_DIR/loop.json``).

    Raises:
        RunFileError: the re-calibration left no posterior or metrics.
    """
    settings = plan.cfg.diagnose
    recalibrated, series_after = _recalibrated(plan)
    result = LoopResult(
        run=plan.run.path,
        dataset=plan.before.dataset,
        pool=[model.name for model in plan.pool],
        road=plan.road,
        selection=plan.selection,
        unexplained=unexplained(plan.selection),
        settings=settings,
        search=SearchBudget(
            population=max(settings.population, plan.cfg.abc.top_n),
            local_copies=settings.local_copies,
            rounds=settings.rounds,
            refit_rounds=settings.refit_rounds,
            validation_warmup=settings.validation_warmup,
            n_particles=settings.n_particles,
            run_particles=plan.cfg.abc.n_particles,
            n_train=plan.train_pairs.n_pairs,
            refit_slots=settings.refit_slots,
            refit_stop=settings.refit_stop,
        ),
        before=plan.before.hybrid,
        shares_before=plan.posterior.shares,
        residuals_before=plan.residuals_before,
        recalibrated=recalibrated,
        seconds=time.perf_counter() - plan.began,
        response_before=plan.response_before,
        class_on_test=plan.class_on_test,
    )
    write_report(
        plan.run,
        result.to_json(),
        plan.series_before,
        series_after,
        plan.train_pairs.dt,
    )
    return result


def unexplained(selection: EffectSelection) -> list[Unexplained]:
    """Structure the library does not explain: every signature still found in
    the final model's residual (the last signatures of the selection) with the
    family it suggests, and whether an effect it points to was tested and not
    chosen."""
    if not selection.signatures:
        return []
    tested = {row.name for rows in selection.steps for row in rows}
    chosen = {effect.name for effect in selection.chosen}
    out = []
    for mark in selection.signatures[-1]:
        if not mark.found:
            continue
        pointed = [e for e in mark.points_to if e not in chosen]
        if mark.points_to and not pointed:
            continue  # explained by an effect chosen but left some structure
        out.append(
            Unexplained(
                signature=mark.signature,
                mean=mark.mean,
                unit=mark.unit,
                p_value=mark.p_value,
                tested_not_chosen=tuple(e for e in pointed if e in tested),
                family=family_of(mark.signature, mark.mean),
            )
        )
    return out


def _recalibrated(plan: LoopPlan) -> tuple[Recalibrated | None, Series | None]:
    """The re-calibration's results and the residual series after (None, None:
    nothing was chosen, "after" is "before")."""
    if plan.recalibration is None:
        return None, None
    after = RunDir(plan.recalibration_dir)
    posterior = after.load_posterior()
    metrics = after.read_metrics()
    residuals, series = diagnose_residuals(posterior, plan.train_pairs)
    best = best_particles(posterior, plan.train_pairs)
    reference = RunDir(plan.reference_dir).read_metrics()
    return Recalibrated(
        after_run=after.path,
        reference_run=plan.reference_dir,
        after=metrics.hybrid,
        shares=posterior.shares,
        before_same_search=reference.hybrid,
        test_pairs=_paired_on_test(plan, reference, metrics),
        posterior=effect_posterior(posterior, plan.chosen),
        identifiability=effect_identifiability(posterior, plan.chosen),
        residuals_after=residuals,
        response_after=response_times(best, series, plan.train_pairs),
    ), series


def _paired_on_test(
    plan: LoopPlan, reference: Evaluation, after: Evaluation
) -> ChangeOnTest:
    """After against the run and against the reference, test pair by test pair
    (their hybrids' minimum distance per pair: :func:`~torchcf.diagnose.
    significance.paired_change`)."""
    now = after.hybrid_min_by_pair
    permutations, seed = plan.cfg.diagnose.permutations, LoopSetup.of(plan.cfg).seed
    return ChangeOnTest(
        *(
            paired_change(metrics.hybrid_min_by_pair, now, permutations, seed)
            for metrics in (plan.before, reference)
        )
    )


__all__ = [
    "Candidates",
    "LoopPlan",
    "active_models",
    "candidate_effects",
    "effect_posterior",
    "finish_loop",
    "plan_loop",
    "reusable",
    "run_recalibration",
    "unexplained",
]
