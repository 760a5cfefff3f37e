"""The learned model in traffic: :class:`HybridSampler` and small scenes that drive it.

- :mod:`torchcf.traffic.sampler`: :class:`HybridSampler`, the learned hybrid as an
  ``nn.Module`` (one call gives every vehicle's command, whatever its model);
- :mod:`torchcf.traffic.scenarios`: :func:`platoon` and :func:`ring_road`, batched
  over scenarios, with collision flags;
- :mod:`torchcf.traffic.safety`: :class:`SafetyLayer`, the collision-avoidance
  bound the scenes put on every vehicle by default (simulation only);
- :mod:`torchcf.traffic.battery`: :func:`check_plausibility`, a model's particles
  through emergency braking, stop-and-go, a cut-in, a standstill start and a
  platoon of their own kind.

Re-exports only.
"""

from .battery import (
    Battery,
    Plausibility,
    battery_speed,
    check_plausibility,
)
from .safety import DEFAULT_SAFETY, SafetyLayer, interventions_per_model
from .sampler import HybridSampler
from .scenarios import (
    RingStart,
    RingState,
    TrafficOutput,
    pair_leader,
    platoon,
    ring_initial_state,
    ring_road,
)

__all__ = [
    "DEFAULT_SAFETY",
    "Battery",
    "HybridSampler",
    "Plausibility",
    "RingStart",
    "RingState",
    "SafetyLayer",
    "TrafficOutput",
    "battery_speed",
    "check_plausibility",
    "interventions_per_model",
    "pair_leader",
    "platoon",
    "ring_initial_state",
    "ring_road",
]
