"""torchcf: stochastic hybrid car-following models learned with ABC, in PyTorch.

Public API (re-exports only; see the modules for the details):

- :func:`load_pairs` / :class:`PairSet` / :class:`DataError` (``torchcf.data``),
- :data:`MODELS` / :func:`get_model` / :class:`CFModel` (``torchcf.models``),
- :func:`simulate` / :class:`SimOutput` / :class:`Execution` (``torchcf.sim.rollout``),
- :func:`calibrate` / :class:`Calibration` / :class:`Rejection` / :class:`SMC` /
  :class:`Amortised` (``torchcf.calibration``): calibrate models on pairs;
- :class:`HybridSampler` (``torchcf.traffic.sampler``): the learned model as an
  ``nn.Module``; traffic models that use it are in ``torchcf.traffic``.
"""

from . import traffic
from .calibration import SMC, Amortised, Calibration, Rejection, calibrate
from .data import DATASETS, DataError, PairSet, load_pairs
from .models import MODELS, CFModel, UnknownModelError, get_model
from .sim.rollout import Execution, SimOutput, simulate
from .system.version import __version__
from .traffic.sampler import HybridSampler

__all__ = [
    "DATASETS",
    "MODELS",
    "SMC",
    "Amortised",
    "CFModel",
    "Calibration",
    "DataError",
    "Execution",
    "HybridSampler",
    "PairSet",
    "Rejection",
    "SimOutput",
    "UnknownModelError",
    "__version__",
    "calibrate",
    "get_model",
    "load_pairs",
    "simulate",
    "traffic",
]
