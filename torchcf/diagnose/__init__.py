"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

``torchcf diagnose RUN_DIR [--set diagnose.key=VALUE ...]`` (or
``diagnose.run_after_training`` in the run's config) takes a finished, evaluated
run through the loop (:func:`torchcf.study.pipeline.close_loop`). Its rooms,
by the loop's stage:

- :mod:`.signatures` (step 1, what the residual points to): :mod:`.series`
  (the best hybrid particle per pair, its residual series and their structure
  tests, :mod:`.residuals`' statistics), :mod:`.families` (the signatures and
  the effects each points to), :mod:`.road` (road effects at the data's
  resolution), :mod:`.response` (response times, data and models);
- :mod:`.arms` (step 2, fitting an effect beside the pool): :mod:`.candidates`
  (the attribution's start, drawn by the ABC engine), :mod:`.population`
  (an arm's particles, per pair S slots), :mod:`.search` (local search with
  common random numbers), :mod:`.refit` (per-pair refits), :mod:`.arena` (the
  base, placebo and effect arms of a step), :mod:`.absorption` (which of a
  model's own parameters takes an effect up), :mod:`.identifiability`,
  :mod:`.validation` (how an arm is judged out of sample), :mod:`.ledger`
  (finished fits kept for a resume);
- :mod:`.selection` (step 2, the decisions): :mod:`.attribution` (forward
  selection of nested arms), :mod:`.tested` (one effect's test at one step),
  :mod:`.power` (the detectable sizes), :mod:`.on_test` (the model class
  judged on the test pairs);
- :mod:`.recalibration` (step 3): the chosen effects on the whole training
  windows, trained by the run's own sampler, and the run directories of the
  re-calibration;
- :mod:`.report` (step 4): :mod:`.outcome` (the loop's result,
  :class:`LoopResult`, ``loop.json``), :mod:`.markdown` (``loop.md`` and its
  figures), :mod:`.method` (the method's text);
- shared: :mod:`.significance` (the sign-flip test, the fallback procedure,
  the paired comparison of two runs), :mod:`.workers` (the process pool),
  :mod:`.loop` (the steps: :func:`plan_loop`, :func:`run_recalibration`,
  :func:`finish_loop`);
- the command line: :mod:`torchcf.cli.diagnose` (``torchcf diagnose``).

Re-exports only.
"""

from .arms.arena import resolve_effect
from .arms.population import Population, merge
from .arms.validation import split_by_pair, split_in_time
from .loop import (
    Candidates,
    LoopPlan,
    active_models,
    candidate_effects,
    effect_posterior,
    finish_loop,
    plan_loop,
    reusable,
    run_recalibration,
)
from .report.markdown import loop_markdown
from .report.outcome import LoopResult, Recalibrated
from .selection.attribution import EffectSelection, attribute_effects
from .selection.tested import EffectTest
from .signatures.series import (
    DiagnoseError,
    best_particles,
    diagnose_residuals,
    residual_series,
    residual_tests,
)
from .significance import fallback_levels, paired_change, sign_flip_test, step_levels

__all__ = [
    "Candidates",
    "DiagnoseError",
    "EffectTest",
    "LoopPlan",
    "LoopResult",
    "Population",
    "EffectSelection",
    "Recalibrated",
    "active_models",
    "attribute_effects",
    "best_particles",
    "candidate_effects",
    "diagnose_residuals",
    "effect_posterior",
    "fallback_levels",
    "finish_loop",
    "loop_markdown",
    "merge",
    "plan_loop",
    "residual_series",
    "residual_tests",
    "resolve_effect",
    "reusable",
    "run_recalibration",
    "paired_change",
    "sign_flip_test",
    "split_by_pair",
    "split_in_time",
    "step_levels",
]
