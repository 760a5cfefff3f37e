"""The learned model in traffic: :class:`HybridSampler` and small scenes that drive it.

- :mod:`torchcf.traffic.sampler`: :class:`HybridSampler`, the learned hybrid as an
  ``nn.Module`` (one call gives every vehicle's command, whatever its model);
- :mod:`torchcf.traffic.scenarios`: :func:`platoon` and :func:`ring_road`, batched
  over scenarios, with collision flags.

Re-exports only.
"""

from .sampler import HybridSampler
from .scenarios import (
    RingState,
    TrafficOutput,
    pair_leader,
    platoon,
    ring_initial_state,
    ring_road,
)

__all__ = [
    "HybridSampler",
    "RingState",
    "TrafficOutput",
    "pair_leader",
    "platoon",
    "ring_initial_state",
    "ring_road",
]
