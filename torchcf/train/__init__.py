"""A training run: checkpoints, progress, ranks around the ABC engine.

- :mod:`torchcf.train.run`: :func:`train` (one run of a config into a directory,
  resumable, under ``torchrun`` or alone), the orchestration;
- :mod:`torchcf.train.checkpoint`: the checkpoint's format, resuming, the
  checkpointer;
- :mod:`torchcf.train.engine`: the config translated for the ABC engine (device,
  budgets, buffers, the rollout);
- :mod:`torchcf.train.summary`: the results and ``summary.json``
  (:class:`RunSummary`);
- :mod:`torchcf.train.amortised`: the amortised method's estimator in a run
  (:func:`trained_estimator`: the one a finished run trained);
- :mod:`torchcf.train.__main__`: ``python -m torchcf.train CONFIG``, which runs the
  study (:mod:`torchcf.study.pipeline`).

Re-exports only.
"""

from .amortised import trained_estimator
from .checkpoint import RunError, RunState, open_run
from .engine import check_budget, run_device
from .run import train
from .summary import ModelResult, RunSummary

__all__ = [
    "ModelResult",
    "RunError",
    "RunState",
    "RunSummary",
    "check_budget",
    "open_run",
    "run_device",
    "train",
    "trained_estimator",
]
