"""Co-simulation: SUMO vehicles driven by the learned hybrid, step by step.

:class:`CoSimulation` hands chosen vehicles of a running libsumo simulation to a
:class:`~torchcf.traffic.HybridSampler`: every model and effect (MPC, delays,
grades, HL's lag) then drives inside SUMO networks, SUMO keeping the routes, the
lanes and every other vehicle. One step, for all ``V`` controlled vehicles at once:

1. **perceive** (SUMO at t): own speed ``v`` and lane position; the leader from
   ``vehicle.getLeader`` (``dist``: the bumper-to-bumper gap less the follower's
   ``minGap``) gives SPEC's front-to-front spacing
   ``s = dist + minGap_ego + length_leader`` and the leader's speed; and the free
   road: a ghost leader driving at the vehicle's allowed speed ``v_free`` (the
   lane's limit, ``vehicle.getAllowedSpeed``) at the particle's own equilibrium
   spacing for that speed (:meth:`HybridSampler.equilibrium_spacing`, capped at
   ``lookahead``; one bisection per speed limit, cached). Without a leader
   within ``lookahead`` metres the vehicle sees only the ghost;
2. **decide** (torchcf, one sampler call for both): the command towards the
   leader and the command towards the ghost, ``u = min(u_leader, u_free)`` --
   SUMO's own rule, the minimum of its ``followSpeed`` and ``freeSpeed``. A
   spacing controller (LLCTG, HL, MPC) thus closes to ``v_free`` at its own pace
   instead of reading a far leader (or an empty road) as a huge spacing error;
   where the leader binds, as in every calibration pair, ``u = u_leader``
   exactly. ``u`` is realised by :meth:`HybridSampler.advance` (SPEC section 2: a
   point mass, or HL's / ``+lag``'s exact first-order lag; then ``v >= 0``, no
   reversing) and, by default as in :mod:`torchcf.traffic`, bounded by the
   :class:`~torchcf.traffic.SafetyLayer` (Gipps' safe speed towards the leader).
   This gives the step's displacement ``d`` and the next speed ``v'``;
3. **act** (SUMO): ``vehicle.setSpeed(v')`` with speed mode 0 (SUMO's own bounds
   off: torchcf's safety layer stands in for them), then ``simulationStep``.

**Kinematics.** SUMO must run with ``--step-method.ballistic true``: it then moves
a vehicle by ``(v + v') dt / 2``, which is SPEC's ``v dt + a dt^2 / 2`` for a
point mass. Where torchcf's displacement ``d`` is not that trapezoid (HL's and
``+lag``'s exact lag; a step in which SPEC's point mass would stop and is held at
``x(t+1) = max(x, .)``), the vehicle is moved along its lane by the difference
*before* SUMO's step (``vehicle.moveTo``; ``exact_positions=True``, the default),
so that SUMO's step ends at torchcf's position and SUMO's outputs record it. The
price: during that one step SUMO's other vehicles see the shifted position (by
the difference: millimetres for HL at 0.1 s).
The co-simulated positions then equal torchcf's own rollout
(:func:`torchcf.traffic.platoon`, :func:`torchcf.simulate`) to rounding:
``tests/sumo/test_sumo_cosim.py`` measures the largest difference.

**Vehicles.** ``vehicles`` is fixed at construction, in the sampler's vehicle
order (``sampler.vehicle_shape == (V,)`` given; the co-simulation then lays the
sampler out as ``(2, V)``, row 0 following the leaders and row 1 the ghosts, so
that one call gives both commands and each row keeps its own memory: a delay's
history, MPC's plan). A vehicle not (or no longer) in the network is fed neutral
inputs and its command ignored; its acceleration state starts at
``initial_acceleration`` (default 0) when it appears. Lane changes stay SUMO's.

Shapes: ``(V,)`` per-vehicle tensors in the sampler's dtype (float64 for
co-simulations compared at 1e-6 m); the sampler's calls ``(2, V)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import ModuleType
from typing import NamedTuple

import torch
from torch import Tensor

from ..models import FollowerState
from ..traffic import DEFAULT_SAFETY, HybridSampler, SafetyLayer
from .backend import SumoError

#: Corrections below this [m] are not applied (SUMO's own rounding).
POSITION_TOLERANCE = 1e-12


class Perceived(NamedTuple):
    """What the controlled vehicles perceive at one step, ``(V,)`` each.

    Attributes:
        present: bool, the vehicle is in the network.
        spacing: front-to-front spacing to its leader [m].
        v: own speed [m/s].
        v_leader: the leader's speed [m/s].
        position: lane position plus ``position_offset`` [m].
        free_spacing: the free-road ghost's spacing [m].
        v_free: the ghost's speed, the allowed speed [m/s].

    Examples:
        >>> import torch
        >>> from torchcf.sumo import Perceived
        >>> seen = Perceived(
        ...     present=torch.tensor([True]), spacing=torch.tensor([30.0]),  # [m]
        ...     v=torch.tensor([20.0]), v_leader=torch.tensor([19.0]),  # [m/s]
        ...     position=torch.tensor([100.0]), free_spacing=torch.tensor([1000.0]),
        ...     v_free=torch.tensor([33.3]),
        ... )
        >>> seen._fields[:3]
        ('present', 'spacing', 'v')
    """

    present: Tensor
    spacing: Tensor
    v: Tensor
    v_leader: Tensor
    position: Tensor
    free_spacing: Tensor
    v_free: Tensor


class CoSimulation:
    """SUMO vehicles driven by a :class:`HybridSampler` (module docstring).

    Use::

        with backend.running([... "--step-method.ballistic", "true"]) as sumo:
            sumo.simulationStep()                     # insert the vehicles
            cosim = CoSimulation(sumo, sampler, ["veh0", "veh1"])
            for _ in range(n_steps):
                cosim.step()                          # decide, act, SUMO's step

    or :meth:`command`, your own ``sumo.simulationStep()`` (and other vehicles'
    commands), then :meth:`settle`.

    Args:
        sumo: the running ``libsumo`` module.
        sampler: with ``vehicle_shape == (V,)``, one particle per vehicle.
        vehicles: the ``V`` SUMO vehicle ids, in the sampler's order.
        safety: the bound on every step (:mod:`torchcf.traffic.safety`; on by
            default); None: the learned models alone (the calibration rollout).
        lookahead: how far a leader is looked for [m]; the farthest a free
            road's ghost leader is placed.
        exact_positions: move a vehicle by torchcf's own displacement where
            SUMO's ballistic trapezoid differs from it (module docstring).
        position_offset: ``(V,)`` or a number [m], added to the lane position
            for models that read their road position (``grade``).
        initial_acceleration: ``(V,)`` or a number [m/s^2]: each vehicle's
            acceleration state when it appears (HL and ``+lag`` read it).

    Attributes:
        interventions: ``(V,)`` int64, steps the safety layer overrode.
        corrections: ``(V,)`` int64, steps whose position was corrected.
        steps: steps taken.

    Raises:
        SumoError: the sampler's vehicles or step do not match SUMO's, or SUMO
            does not run the ballistic update.

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> from torchcf.sumo import CoSimulation
        >>> from torchcf.sumo.backend import running
        >>> idm = torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]])
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample(2)  # one particle per SUMO vehicle
        >>> options = ["-n", "net.xml", "-r", "routes.xml", "--step-length", "0.1"]
        >>> options += ["--step-method.ballistic", "true"]
        >>> with running(options) as sumo:  # doctest: +SKIP
        ...     sumo.simulationStep()  # insert the vehicles
        ...     cosim = CoSimulation(sumo, sampler, ["veh0", "veh1"])
        ...     for _ in range(100):
        ...         perceived = cosim.step()  # decide, act, SUMO's step
    """

    def __init__(
        self,
        sumo: ModuleType,
        sampler: HybridSampler,
        vehicles: Sequence[str],
        *,
        safety: SafetyLayer | None = DEFAULT_SAFETY,
        lookahead: float = 1000.0,
        exact_positions: bool = True,
        position_offset: float | Tensor = 0.0,
        initial_acceleration: float | Tensor = 0.0,
    ) -> None:
        self.sumo = sumo
        self.sampler = sampler
        self.vehicles = tuple(str(v) for v in vehicles)
        if len(set(self.vehicles)) != len(self.vehicles):
            raise SumoError("a vehicle is listed twice")
        if sampler.vehicle_shape != (len(self.vehicles),):
            raise SumoError(
                f"the sampler drives vehicle shape {sampler.vehicle_shape}, not the "
                f"{len(self.vehicles)} vehicles given: sampler.assign(...) or "
                f"sampler.sample({len(self.vehicles)}) first"
            )
        step = float(sumo.simulation.getDeltaT())
        if abs(step - sampler.dt) > 1e-9 * sampler.dt:
            raise SumoError(
                f"SUMO steps {step} s but the sampler's particles were learned at "
                f"dt = {sampler.dt} s: start SUMO with --step-length {sampler.dt}"
            )
        if sumo.simulation.getOption("step-method.ballistic") != "true":
            raise SumoError(
                "the co-simulation needs SUMO's ballistic position update "
                "(torchcf's kinematics): start SUMO with --step-method.ballistic true"
            )
        if not (math.isfinite(lookahead) and lookahead > 0):
            raise SumoError(f"lookahead must be > 0 m, got {lookahead}")
        self._pair_rows()
        self.safety = safety
        self.lookahead = float(lookahead)
        self.exact_positions = exact_positions
        n = len(self.vehicles)
        dtype, device = sampler.dtype, sampler.device
        zeros = torch.zeros(n, dtype=dtype, device=device)
        self.position_offset = zeros + torch.as_tensor(
            position_offset, dtype=dtype, device=device
        )
        self._initial_acceleration = zeros + torch.as_tensor(
            initial_acceleration, dtype=dtype, device=device
        )
        self.acceleration = self._initial_acceleration.clone()  # (V,)
        self.interventions = torch.zeros(n, dtype=torch.long)
        self.corrections = torch.zeros(n, dtype=torch.long)
        self.steps = 0
        self._known: set[str] = set()
        self._lengths: dict[str, float] = {}
        self._next_acceleration: Tensor | None = None
        self._ghost: dict[float, list[float]] = {}  # v_free -> (V,) spacing

    def _pair_rows(self) -> None:
        """Lay the sampler out as ``(2, V)``: row 0 follows the leaders, row 1
        the free-road ghosts, each vehicle's particle in both (module doc)."""
        particle = self.sampler.vehicle_particle.reshape(-1, len(self.vehicles))[0]
        self.sampler.assign(particle.reshape(1, -1).expand(2, -1))

    # ------------------------------------------------------------- perception
    def _length(self, vehicle: str) -> float:
        length = self._lengths.get(vehicle)
        if length is None:
            length = self._lengths[vehicle] = float(
                self.sumo.vehicle.getLength(vehicle)
            )
        return length

    def _ghost_spacing(self, v_free: float) -> list[float]:
        """Every vehicle's equilibrium spacing [m] at ``v_free`` [m/s], capped at
        ``lookahead`` (one bisection per distinct speed limit, then cached)."""
        spacing = self._ghost.get(v_free)
        if spacing is None:
            with torch.no_grad():
                found = self.sampler.equilibrium_spacing(
                    v_free, s_max=self.lookahead
                )  # (V,)
            spacing = self._ghost[v_free] = found[0].tolist()  # (2, V) -> (V,)
        return spacing

    def perceive(self) -> Perceived:
        """Every controlled vehicle's perception in SUMO now (module docstring)."""
        vehicle = self.sumo.vehicle
        present_ids = set(vehicle.getIDList())
        n = len(self.vehicles)
        present = [False] * n
        spacing, v, v_leader, position, free, v_free = ([0.0] * n for _ in range(6))
        for i, vid in enumerate(self.vehicles):
            if vid not in present_ids:
                spacing[i] = free[i] = self.lookahead
                continue
            present[i] = True
            if vid not in self._known:
                # SUMO's bounds off: the safety layer stands in for them.
                vehicle.setSpeedMode(vid, 0)
                self._known.add(vid)
                self.acceleration[i] = self._initial_acceleration[i]
            v[i] = vehicle.getSpeed(vid)
            position[i] = vehicle.getLanePosition(vid)
            v_free[i] = float(vehicle.getAllowedSpeed(vid))
            free[i] = self._ghost_spacing(v_free[i])[i]
            leader = vehicle.getLeader(vid, self.lookahead)
            if leader is None or not leader[0]:
                spacing[i], v_leader[i] = free[i], v_free[i]
                continue
            spacing[i] = leader[1] + vehicle.getMinGap(vid) + self._length(leader[0])
            v_leader[i] = vehicle.getSpeed(leader[0])
        dtype, device = self.sampler.dtype, self.sampler.device

        def tensor(values: list[float]) -> Tensor:
            return torch.tensor(values, dtype=dtype, device=device)  # (V,)

        return Perceived(
            torch.tensor(present, device=device),
            tensor(spacing),
            tensor(v),
            tensor(v_leader),
            tensor(position) + self.position_offset,
            tensor(free),
            tensor(v_free),
        )

    # -------------------------------------------------------------- one step
    def command(self) -> Perceived:
        """Decide every controlled vehicle's step and set its speed in SUMO
        (before ``simulationStep``). One sampler call for all vehicles.

        Returns:
            the perception the decision was taken on.
        """
        seen = self.perceive()
        sampler = self.sampler
        a = torch.where(seen.present, self.acceleration, 0.0)  # (V,)
        position = (
            seen.position if any(m.uses_position for m in sampler.models) else None
        )

        def rows(follow: Tensor, free: Tensor) -> Tensor:
            return torch.stack((follow, free))  # (2, V)

        with torch.no_grad():
            both = sampler(
                rows(seen.spacing, seen.free_spacing),
                rows(seen.v, seen.v),
                rows(seen.v_leader, seen.v_free),
                rows(a, a),
                None if position is None else rows(position, position),
            )  # (2, V)
            # SUMO's rule: the lower of following and free driving.
            u = both.amin(0)  # (V,)
            start = FollowerState(torch.zeros_like(seen.v), seen.v, a)
            moved = FollowerState(
                *(
                    t[0]
                    for t in sampler.advance(
                        rows(start.x, start.x),
                        rows(start.v, start.v),
                        rows(a, a),
                        rows(u, u),
                    )
                )
            )  # (V,) each
            if self.safety is not None:
                moved, overridden = self.safety.apply(
                    start,
                    moved,
                    seen.spacing,
                    seen.v_leader,
                    sampler.dt,
                    sampler.leader_length,
                )
                self.interventions += (overridden & seen.present).long().cpu()
        dt = sampler.dt
        # SUMO's ballistic step moves (v + v') dt / 2; torchcf moved d.
        trapezoid = 0.5 * (seen.v + moved.v) * dt
        gap = (moved.x - trapezoid).tolist()
        v_next = moved.v.tolist()
        present = seen.present.tolist()
        vehicle = self.sumo.vehicle
        for i, vid in enumerate(self.vehicles):
            if not present[i]:
                continue
            vehicle.setSpeed(vid, v_next[i])
            if self.exact_positions and abs(gap[i]) > POSITION_TOLERANCE:
                self._shift(vid, i, gap[i])
        self._next_acceleration = torch.where(seen.present, moved.a, self.acceleration)
        return seen

    def _shift(self, vid: str, i: int, difference: float) -> None:
        """Move a vehicle along its lane by ``difference`` [m] before SUMO's
        step, so that SUMO's trapezoid ends where torchcf's step does (and the
        FCD SUMO writes in the step records it)."""
        vehicle = self.sumo.vehicle
        lane = vehicle.getLaneID(vid)
        target = vehicle.getLanePosition(vid) + difference
        if lane and 0.0 <= target <= self.sumo.lane.getLength(lane):
            vehicle.moveTo(vid, lane, target)
            self.corrections[i] += 1

    def settle(self) -> None:
        """After SUMO's step: the acceleration state, the sampler's clock."""
        if self._next_acceleration is not None:
            self.acceleration = self._next_acceleration
            self._next_acceleration = None
        if self.sampler.tick():
            # A redraw gave the two rows different particles: row 0's in both.
            self._pair_rows()
            self._ghost.clear()
        self.steps += 1

    def step(self) -> Perceived:
        """:meth:`command`, SUMO's ``simulationStep``, :meth:`settle`.

        Returns:
            the perception of the step's start.
        """
        seen = self.command()
        self.sumo.simulationStep()
        self.settle()
        return seen


__all__ = ["POSITION_TOLERANCE", "CoSimulation", "Perceived"]
