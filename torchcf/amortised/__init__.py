"""Amortised calibration: one network maps a pair's series to its posterior.

Trained once on torchcf's own simulations behind the data set's own leaders,
the estimator gives every pair's models' probabilities and samples of
(model, parameters) in batched forward passes, where rejection and SMC
simulate afresh for every pair. Modules, each importing only those above it:

- :mod:`~torchcf.amortised.space`: the models and their prior boxes, the map
  of a box onto an unbounded space (:class:`ParameterSpace`);
- :mod:`~torchcf.amortised.features`: the encoder's input channels of a pair,
  normalised with fixed scales;
- :mod:`~torchcf.amortised.simulations`: the training set, followers simulated
  behind leader windows of the data (:class:`TrainingSimulator`);
- :mod:`~torchcf.amortised.encoder`: the trajectory encoder, a masked 1-D CNN
  with global pooling (:class:`TrajectoryEncoder`);
- :mod:`~torchcf.amortised.estimator`: the model head and one zuko flow per
  model (:class:`AmortisedEstimator`);
- :mod:`~torchcf.amortised.training_state`: the training's checkpoint;
- :mod:`~torchcf.amortised.training`: the training loop, its budget, early
  stopping, checkpoints and resume (:func:`train_estimator`);
- :mod:`~torchcf.amortised.inference`: every pair of a pair set, in chunks
  (:func:`infer`);
- :mod:`~torchcf.amortised.proposals`: a model's samples scored and kept as
  ABC particles in its per-pair top-N buffer (:func:`run_amortised`).

Re-exports only.
"""

from .encoder import EncoderSettings, TrajectoryEncoder
from .estimator import AmortisedEstimator, Draws, EstimatorSettings, new_estimator
from .features import CHANNELS, channel_features, pair_features
from .inference import PairPosteriors, infer
from .proposals import run_amortised
from .simulations import (
    NoiseLevels,
    SimulatedSet,
    SimulationSettings,
    TrainingSimulator,
)
from .space import ParameterSpace
from .training import (
    Session,
    TrainingResult,
    TrainingSettings,
    estimator_fingerprint,
    fingerprint_noise,
    train_estimator,
    validation_scores,
)
from .training_state import CheckpointError, EpochRecord, TrainingProgress, load_trained

__all__ = [
    "CHANNELS",
    "AmortisedEstimator",
    "CheckpointError",
    "Draws",
    "EncoderSettings",
    "EpochRecord",
    "EstimatorSettings",
    "NoiseLevels",
    "PairPosteriors",
    "ParameterSpace",
    "Session",
    "SimulatedSet",
    "SimulationSettings",
    "TrainingProgress",
    "TrainingResult",
    "TrainingSettings",
    "TrainingSimulator",
    "TrajectoryEncoder",
    "channel_features",
    "estimator_fingerprint",
    "fingerprint_noise",
    "infer",
    "load_trained",
    "new_estimator",
    "pair_features",
    "run_amortised",
    "train_estimator",
    "validation_scores",
]
