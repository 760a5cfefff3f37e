"""A training run: checkpoints, progress, ranks around the ABC engine.

- :mod:`torchcf.train.run`: :func:`train` (one run of a config into a directory,
  resumable, under ``torchrun`` or alone) and what it is made of;
- :mod:`torchcf.train.__main__`: ``python -m torchcf.train CONFIG``, which runs the
  study (:mod:`torchcf.pipeline`).

Re-exports only.
"""

from .run import (
    RunError,
    RunState,
    check_budget,
    open_run,
    rollout_of,
    run_device,
    train,
)

__all__ = [
    "RunError",
    "RunState",
    "check_budget",
    "open_run",
    "rollout_of",
    "run_device",
    "train",
]
