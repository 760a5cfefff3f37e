"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

``python -m torchcf.diagnose RUN_DIR [--set diagnose.key=VALUE ...]`` (or
``diagnose.run_after_training`` in the run's config) takes a finished, evaluated
run through the loop (:func:`torchcf.study.pipeline.close_loop`). Its concerns:

- :mod:`.series`: the best hybrid particle per pair, its residual series and
  their structure tests (:mod:`.residuals`, the statistics);
- :mod:`.signatures`: what the residual of the fit windows points to;
- :mod:`.candidates`: the attribution's start, drawn by the ABC engine
  (:mod:`torchcf.abc.rejection`);
- :mod:`.population`: an arm's particles, per pair S slots;
- :mod:`.search`: local search with common random numbers, nested starts, a
  shared effect's one value;
- :mod:`.significance`: the sign-flip test, the fallback procedure and the
  paired comparison of two runs on the test pairs;
- :mod:`.absorption`: which of a model's own parameters takes an effect up;
- :mod:`.arms`: the base, placebo and effect arms of a step;
- :mod:`.attribution`: forward selection of nested arms;
- :mod:`.tested`: one effect's test at one step (a row of the selection);
- :mod:`.retrain`: the chosen effects on the whole training windows, trained by
  the run's own sampler (``diagnose.recalibration = "train"``);
- :mod:`.recalibrate`: the same by local search (``"search"``), and the run
  directories of a re-calibration;
- :mod:`.loop`: the loop's steps (:func:`plan_loop`, :func:`run_recalibration`,
  :func:`finish_loop`);
- :mod:`.outcome`: the loop's result (:class:`LoopResult`, ``loop.json``);
- :mod:`.road`: road effects at the data's resolution (frame, knot spacing);
- :mod:`.validation`: how an arm is judged out of sample (in time, or on
  held-out pairs);
- :mod:`.report`: ``loop.md``, its figures and ``loop.json``;
- :mod:`.__main__`: the command line.

Re-exports only.
"""

from .arms import resolve_effect
from .attribution import EffectSelection, attribute_effects
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
from .outcome import LoopResult, Recalibrated
from .population import Population, merge
from .report import loop_markdown
from .series import (
    DiagnoseError,
    best_particles,
    diagnose_residuals,
    residual_series,
    residual_tests,
)
from .significance import fallback_levels, paired_change, sign_flip_test, step_levels
from .tested import EffectTest
from .validation import split_by_pair, split_in_time

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
