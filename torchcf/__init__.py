"""torchcf: stochastic hybrid car-following models learned with ABC, in PyTorch.

Public API (re-exports only; see the modules for the details):

- :func:`load_pairs` / :class:`PairSet` / :class:`DataError` (``torchcf.data``),
- :data:`MODELS` / :func:`get_model` / :class:`CFModel` (``torchcf.models``),
- :func:`simulate` / :class:`SimOutput` / :class:`Execution` (``torchcf.sim.rollout``),
- :class:`HybridSampler` (``torchcf.traffic.sampler``): the learned model as an
  ``nn.Module``; traffic models that use it are in ``torchcf.traffic``.
"""

from . import traffic
from .data import DATASETS, DataError, PairSet, load_pairs
from .models import MODELS, CFModel, UnknownModelError, get_model
from .sim.rollout import Execution, SimOutput, simulate
from .traffic.sampler import HybridSampler

__version__ = "0.1.0"

__all__ = [
    "DATASETS",
    "MODELS",
    "CFModel",
    "DataError",
    "Execution",
    "HybridSampler",
    "PairSet",
    "SimOutput",
    "UnknownModelError",
    "__version__",
    "get_model",
    "load_pairs",
    "simulate",
    "traffic",
]
