"""Predict pairs from a trained run: drivers the run never saw, scored as the
field scores calibrations.

* :mod:`torchcf.predict.trained`: :class:`TrainedRun`, what prediction reads
  from a run directory, and the check of the pairs against it.
* :mod:`torchcf.predict.population`: the population model (a pooled
  calibration searched from the kept particles).
* :mod:`torchcf.predict.bands`: the hybrid's predictive median and bands.
* :mod:`torchcf.predict.history`: a driver's own posterior from the first
  seconds of its pair, predicting the rest.
* :mod:`torchcf.predict.scores`: spacing RMSE, ADE / FDE, coverage.
* :mod:`torchcf.predict.predict`: :func:`predict`, the three predictions and
  their scores.
* :mod:`torchcf.predict.files`: ``predict.json``, ``predict.md``, the
  per-pair table and the trajectories.

Examples:
    >>> from torchcf.predict import PredictSettings, TrainedRun, predict
    >>> run = TrainedRun.load("runs/carII")  # doctest: +SKIP
    >>> found = predict(run, run.train, PredictSettings(draws=50))  # doctest: +SKIP
    >>> found.summary.population.spacing_rmse.mean  # doctest: +SKIP
"""

from .predict import (
    BandsResult,
    HistoryResult,
    PopulationResult,
    Prediction,
    PredictionSummary,
    PredictSettings,
    predict,
)
from .trained import PredictError, TrainedRun

__all__ = [
    "BandsResult",
    "HistoryResult",
    "PopulationResult",
    "PredictError",
    "Prediction",
    "PredictSettings",
    "PredictionSummary",
    "TrainedRun",
    "predict",
]
