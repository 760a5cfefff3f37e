"""Close the loop: residual -> missing effect -> augmented models -> error before/after.

``python -m torchcf.diagnose RUN_DIR [--set diagnose.key=VALUE ...]`` (or
``diagnose.run_after_training`` in the run's config) takes a finished, evaluated
run through the loop (:func:`torchcf.pipeline.close_loop`). Its concerns:

- :mod:`.series`: the best hybrid particle per pair, its residual series and
  their structure tests (:mod:`.residuals`, the statistics);
- :mod:`.candidates`: particles of the attribution drawn by the ABC engine
  (:mod:`torchcf.abc.rejection`), scored and summarised as tensors;
- :mod:`.search`: the local search and a shared (road) effect's one value;
- :mod:`.attribution`: the effects ranked by their out-of-sample gain;
- :mod:`.loop`: the loop up to the re-calibration (:func:`plan_loop`) and after
  it (:func:`finish_loop`);
- :mod:`.road`: road effects at the data's resolution (frame, knot spacing);
- :mod:`.report`: ``loop.md``, its figures and ``loop.json``;
- :mod:`.__main__`: the command line.

Re-exports only.
"""

from .attribution import (
    Selection,
    attribute_effects,
    planned_tests,
    resolve_effect,
    sign_flip_test,
    split_in_time,
)
from .candidates import augmented_variants
from .loop import (
    LoopPlan,
    active_models,
    candidate_effects,
    effect_posterior,
    finish_loop,
    plan_loop,
    recalibration_config,
    reference_config,
    reuse_recalibration,
)
from .report import loop_markdown
from .series import (
    DiagnoseError,
    best_particles,
    diagnose_residuals,
    residual_series,
    residual_tests,
)

__all__ = [
    "DiagnoseError",
    "LoopPlan",
    "Selection",
    "active_models",
    "attribute_effects",
    "candidate_effects",
    "augmented_variants",
    "best_particles",
    "diagnose_residuals",
    "effect_posterior",
    "finish_loop",
    "loop_markdown",
    "plan_loop",
    "planned_tests",
    "recalibration_config",
    "reference_config",
    "resolve_effect",
    "residual_series",
    "residual_tests",
    "reuse_recalibration",
    "sign_flip_test",
    "split_in_time",
]
