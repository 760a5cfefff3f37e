"""One calibration API: ``calibrate(pairs, models, method) -> Calibration``.

- :mod:`torchcf.calibration.methods`: the samplers (:class:`Rejection`,
  :class:`SMC`, :class:`Amortised` with its :class:`Refinement`) and how the
  hybrid is read (:class:`SelectionRule`);
- :mod:`torchcf.calibration.calibrate`: :func:`calibrate` and the
  :class:`Tracker` of its state, progress and checkpoints;
- :mod:`torchcf.calibration.results`: the :class:`Calibration` record;
- :mod:`torchcf.calibration.budget`: the budget checked before any simulation;
- :mod:`torchcf.calibration.priors`: the models' prior boxes, held parameters;
- :mod:`torchcf.calibration.state`: the resumable state;
- :mod:`torchcf.calibration.estimator_samples`, :mod:`torchcf.calibration.refinement`:
  the amortised sampler's estimator and samples, and their refinement.

A training run (:func:`torchcf.train.train`) is this calibration with a run
directory around it (checkpoints, TensorBoard, the summary); the diagnosis
loop's re-calibration is this calibration of the chosen effects.
"""

from .budget import CalibrationError, check_budget
from .calibrate import CalibrationSetup, Tracker, calibrate
from .methods import SMC, Amortised, Method, Refinement, Rejection, SelectionRule
from .priors import prior_boxes
from .results import Calibration
from .state import CalibrationState

__all__ = [
    "SMC",
    "Amortised",
    "Calibration",
    "CalibrationError",
    "CalibrationSetup",
    "CalibrationState",
    "Method",
    "Refinement",
    "Rejection",
    "SelectionRule",
    "Tracker",
    "calibrate",
    "check_budget",
    "prior_boxes",
]
