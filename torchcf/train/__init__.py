"""A training run: a calibration (:mod:`torchcf.calibration`) with a run
directory around it (checkpoints, progress, TensorBoard, the summary), alone
or across the processes of a ``torchrun`` group.

- :mod:`torchcf.train.run`: :func:`train` (one run of a config into a
  directory, resumable), the config translated once and the calibration
  tracked;
- :mod:`torchcf.train.checkpoint`: the checkpoint's format, resuming, the
  checkpointer, the device;
- :mod:`torchcf.train.summary`: ``summary.json``'s record of a calibration.

Re-exports only.
"""

from .checkpoint import RunError, RunState, open_run, run_device
from .run import check_setup, train

__all__ = ["RunError", "RunState", "check_setup", "open_run", "run_device", "train"]
