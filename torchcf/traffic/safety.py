"""A safety layer for simulation: the learned model, bounded by a safe speed.

A particle is faithful where it was measured; embedded in traffic it also
meets emergencies no calibration pair showed, and some particles (string-
unstable ones, ACC controllers whose deceleration is bounded by design) would
collide there. Real drivers and cars brake hard when the gap closes (the
driver's panic stop, automatic emergency braking). :class:`SafetyLayer` adds
that reflex on top of any model, in simulation only (never in calibration:
the scores are the model's own):

**The bound** is Gipps' (1981) safe speed, in the form SUMO uses for its
Krauss and Gipps models: the highest speed ``v'`` the follower may have after
the step such that, if the leader then brakes at ``b_lead`` to a stop, the
follower braking at ``b`` stops at least ``stop_spacing`` behind the leader's
front. With the step's displacement ``(v + v') dt / 2`` and the stopping
distances ``v'^2 / (2 b)``, ``v_lead^2 / (2 b_lead)``:

``v_safe = -b dt / 2 + sqrt(b^2 dt^2 / 4 + b (2 (s - stop_spacing) - v dt
+ v_lead^2 / b_lead))``, at least 0 (0 where the root's argument is
negative: too close to stop at all).

**The intervention.** Where the model's realised step would end faster than
``v_safe``, the layer replaces it: the follower brakes to
``max(v_safe, v - b dt, 0)`` over the step as a point mass (an emergency brake
overrides the actuator, so HL's and ``+lag``'s lag is bypassed for that step;
the acceleration state becomes the braking). Elsewhere the model's step is
untouched, so the layer changes nothing where the learned model keeps a safe
gap on its own.

Why Gipps: its bound is derived from stopping distances, has one physical
parameter per vehicle (the hardest braking), keeps collisions out whenever the
leader brakes no harder than assumed, and is the bound SUMO's users know
(Krauss is the same bound with a random dawdling term, which a learned model
already has in its particles). The defaults: ``b = b_lead = 8 m/s^2`` (an
emergency stop of a passenger car on dry asphalt; ACC systems are limited to
about 3-5 m/s^2 and leave harder braking to automatic emergency braking) and
``stop_spacing`` = the leader length (bumper contact: spacing is
front-to-front, SPEC section 1).

Shapes: the vehicles' shape, whatever it is (``(S, n)`` in the scenes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..models import FollowerState


@dataclass(frozen=True)
class SafetyLayer:
    """Gipps' safe-speed bound on the realised step (module docstring).

    Attributes:
        max_decel: ``b``, the follower's hardest braking [m/s^2].
        leader_decel: ``b_lead``, the hardest braking it assumes of its
            leader [m/s^2].
        stop_spacing: front-to-front spacing [m] kept behind a stopped leader;
            None: the leader length (bumper contact).

    Examples:
        >>> import torch
        >>> from torchcf.traffic import SafetyLayer
        >>> layer = SafetyLayer(max_decel=8.0, leader_decel=8.0)  # [m/s^2]
        >>> spacing = torch.tensor([30.0, 20.0])  # [m]
        >>> v, v_leader = torch.tensor([20.0, 20.0]), torch.tensor([20.0, 0.0])
        >>> v_safe = layer.safe_speed(spacing, v, v_leader, dt=0.1, leader_length=5.0)
        >>> [round(s, 3) for s in v_safe.tolist()]  # [m/s]; the second must brake
        [27.603, 14.572]
    """

    max_decel: float = 8.0
    leader_decel: float = 8.0
    stop_spacing: float | None = None

    def __post_init__(self) -> None:
        for name in ("max_decel", "leader_decel"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"safety {name} must be > 0 m/s^2, got {value}")
        if self.stop_spacing is not None and not (
            math.isfinite(self.stop_spacing) and self.stop_spacing >= 0
        ):
            raise ValueError(
                f"safety stop_spacing must be >= 0 m, got {self.stop_spacing}"
            )

    def spacing_kept(self, leader_length: float) -> float:
        """The stop spacing [m] in force for this leader length."""
        return leader_length if self.stop_spacing is None else self.stop_spacing

    def safe_speed(
        self,
        spacing: Tensor,
        v: Tensor,
        v_leader: Tensor,
        dt: float,
        leader_length: float,
    ) -> Tensor:
        """``v_safe`` [m/s] after a step of ``dt`` from spacing ``s`` [m], own
        speed ``v`` and the leader's ``v_leader`` [m/s] (same shapes)."""
        b = self.max_decel
        gap = spacing - self.spacing_kept(leader_length)
        root = (b * dt / 2) ** 2 + b * (
            2.0 * gap - v * dt + v_leader * v_leader / self.leader_decel
        )
        return torch.clamp(
            -b * dt / 2 + torch.sqrt(torch.clamp(root, min=0.0)), min=0.0
        )

    def apply(
        self,
        state: FollowerState,
        moved: FollowerState,
        spacing: Tensor,
        v_leader: Tensor,
        dt: float,
        leader_length: float,
    ) -> tuple[FollowerState, Tensor]:
        """The step the vehicles take: the model's (``moved``, from ``state``
        at spacing ``spacing`` behind leaders at ``v_leader``) where it ends at
        or under the safe speed, else the layer's braking.

        Returns:
            the state after the step, and a bool mask of the vehicles the
            layer overrode.
        """
        v_safe = self.safe_speed(spacing, state.v, v_leader, dt, leader_length)
        # NaN compares False: a blown-up state is left to the collision check.
        intervene = moved.v > v_safe
        v_next = torch.clamp(
            torch.maximum(v_safe, state.v - self.max_decel * dt), min=0.0
        )
        braking = (v_next - state.v) / dt
        braked = FollowerState(
            x=state.x + 0.5 * (state.v + v_next) * dt,
            v=v_next,
            a=braking,
        )
        return (
            FollowerState(
                *(
                    torch.where(intervene, forced, own)
                    for forced, own in zip(braked, moved, strict=True)
                )
            ),
            intervene,
        )


#: The layer torchcf.traffic's scenes use unless told otherwise.
DEFAULT_SAFETY = SafetyLayer()


def interventions_per_model(
    vehicle_model: Tensor,
    interventions: Tensor,
    model_names: tuple[str, ...],
    moving: Tensor | None = None,
) -> dict[str, dict[str, float]]:
    """Per model: vehicles, interventions per vehicle and the share of its
    vehicles the layer overrode at least once; with ``moving``, also the
    interventions per vehicle taken while it moved and the share of vehicles
    overridden while moving.

    Args:
        vehicle_model: the sampler's ``vehicle_model`` (each vehicle's model
            index), the vehicles' shape.
        interventions: steps overridden per vehicle, the same shape.
        model_names: the sampler's ``model_names``.
        moving: ``TrafficOutput.interventions_moving``, the same shape.

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> t = torch.arange(50)[:, None] * 0.1  # (T, 1) [s]
        >>> x_leader = (100.0 + 20.0 * t).expand(50, 2)  # (T, S) [m]: 20 m/s
        >>> v_leader = torch.full((50, 2), 20.0)  # [m/s]
        >>> from torchcf.traffic import interventions_per_model, platoon
        >>> out = platoon(sampler, x_leader, v_leader)
        >>> counts = interventions_per_model(
        ...     sampler.vehicle_model, out.interventions, sampler.model_names
        ... )
        >>> counts["idm"]["vehicles"], counts["idm"]["per_vehicle"]
        (6, 0.0)
    """
    out: dict[str, dict[str, float]] = {}
    flat_model = vehicle_model.reshape(-1).cpu()
    flat_count = interventions.reshape(-1).cpu()
    flat_moving = None if moving is None else moving.reshape(-1).cpu()
    for m, name in enumerate(model_names):
        mine = flat_model == m
        n = int(mine.sum())
        if n == 0:
            continue
        counts = flat_count[mine].double()
        out[name] = {
            "vehicles": n,
            "per_vehicle": float(counts.mean()),
            "vehicles_overridden": float((counts > 0).double().mean()),
        }
        if flat_moving is not None:
            in_motion = flat_moving[mine].double()
            out[name]["per_vehicle_moving"] = float(in_motion.mean())
            out[name]["vehicles_overridden_moving"] = float(
                (in_motion > 0).double().mean()
            )
    return out


__all__ = ["DEFAULT_SAFETY", "SafetyLayer", "interventions_per_model"]
