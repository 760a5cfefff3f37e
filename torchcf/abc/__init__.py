"""The one ABC engine: prior streams -> rollouts -> per-pair top-N -> the hybrid.

Used alike by training (:mod:`torchcf.train`), cross-validation and the diagnosis
loop (:mod:`torchcf.diagnose`). Layers, each importing only those above it:

- :mod:`~torchcf.abc.streams`: counter-based prior streams (particle j of model m,
  and its pair, is a pure function of ``(seed, m, j)``);
- :mod:`~torchcf.abc.topn`: :class:`TopN`, the streaming per-pair buffer of the
  ``n`` best ``(score, particle index)``;
- :mod:`~torchcf.abc.distributed`: :class:`Group`, the processes of a ``torchrun``
  that share a stream (shards of a round, buffers merged after it);
- :mod:`~torchcf.abc.screen`: the plausibility filter's screen of a chunk;
- :mod:`~torchcf.abc.rounds`: the round loop both methods share (shard ->
  simulate -> screen -> push -> end of round), fed by a method's proposals;
- :mod:`~torchcf.abc.rejection`: :class:`Rollout` (how particles are simulated)
  and :func:`run_rejection`, whose proposals are the prior stream's;
- :mod:`~torchcf.abc.kernel`: :class:`~torchcf.abc.kernel.SMCKernel`, the
  refinement's proposal (a Gaussian mixture per pair around its population);
- :mod:`~torchcf.abc.smc`: :func:`~torchcf.abc.smc.run_smc`, the sequential
  refinement (proposals per round, the population between rounds);
- :mod:`~torchcf.abc.hybrid`: the hybrid's selection with the one tie rule (score,
  then particle index, then the model's position), shares, the pairwise table and
  the learned set (:func:`hybrid_posterior`);
- :mod:`~torchcf.abc.particles`: :class:`Particles`, particle sets kept as tensors
  outside a buffer (a local search), and :func:`best_per_pair` over them.

Re-exports only.
"""

from .distributed import SINGLE, Group, GroupError, init_from_env
from .hybrid import (
    Selection,
    hybrid_posterior,
    pairwise_table,
    rank_per_pair,
    select,
    select_global,
    select_per_pair,
)
from .particles import Particles, best_per_pair
from .rejection import (
    CUDA_CHUNK_CELLS,
    ModelProgress,
    Rollout,
    RoundHooks,
    prior_stream,
    run_rejection,
)
from .smc import SMCSettings
from .streams import ParticleStream
from .topn import TopN, lexsort

__all__ = [
    "CUDA_CHUNK_CELLS",
    "SINGLE",
    "Group",
    "GroupError",
    "ModelProgress",
    "ParticleStream",
    "Particles",
    "RoundHooks",
    "Rollout",
    "SMCSettings",
    "Selection",
    "TopN",
    "best_per_pair",
    "hybrid_posterior",
    "init_from_env",
    "lexsort",
    "pairwise_table",
    "prior_stream",
    "rank_per_pair",
    "run_rejection",
    "select",
    "select_global",
    "select_per_pair",
]
