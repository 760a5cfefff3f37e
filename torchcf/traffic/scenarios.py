"""Small PyTorch traffic models driven by the learned hybrid (:class:`HybridSampler`).

Two single-lane scenes, each batched over ``S`` scenarios of ``n`` vehicles (the
sampler's ``vehicle_shape`` is ``(S, n)``; draw it with
``sampler.sample((S, n), generator)`` first):

- :func:`platoon`: ``n`` followers behind a given leader trajectory ``(T, S)`` —
  a measured pair's leader (:func:`pair_leader`) or a synthetic one
  (:func:`torchcf.sim.synthetic.leader_profiles`). Follower 0 follows the leader,
  follower ``j`` follows follower ``j - 1``.
- :func:`ring_road`: ``n`` vehicles on a circle of length ``L``; vehicle ``i``
  follows vehicle ``i + 1``, and the last follows the first across the wrap
  (Sugiyama et al. 2008's experiment).

Every step is the calibration rollout's (SPEC section 2): each vehicle perceives
its spacing to the vehicle ahead, its own speed and acceleration and the leader's
speed at step t; the sampler returns every command in one call; the commands are
realised by each model's own update (:func:`torchcf.sim.rollout.realise`); then
all vehicles move at once. A one-vehicle platoon behind a measured leader,
without the safety layer, is exactly :func:`torchcf.simulate`'s rollout of that pair.

**Safety layer.** By default every vehicle's step is bounded by a safe speed
(:class:`~torchcf.traffic.safety.SafetyLayer`: Gipps' bound, an emergency
brake where the learned model would not stop in time); ``output.interventions``
counts, per vehicle, the steps it overrode. ``safety=None`` runs the learned
models alone.

**Collisions.** Beyond the safety layer the dynamics are never altered: a
vehicle whose spacing drops to ``<= 0`` (or is not a number: a state that blew
up, whose spacing turns NaN at the latest one step later) is flagged in
``collision_step`` (the first step it happened, ``-1`` if never) and keeps
being simulated by the same rules (speed ``>= 0``, no reversing: it brakes as
hard as its model commands at a non-positive spacing; vehicles may pass
through each other). As in calibration, where such a rollout is invalid, a
scenario with a collision is physically meaningless from that step on:
``output.valid`` is False for it.

**Precision.** The ring keeps each vehicle's spacing as a state and moves it by the
step's displacements, ``s_i += dx_{i+1} - dx_i``, each ``dx`` computed by the
realisation from ``x = 0``: float32 then stays accurate on a ring of any length
(absolute positions would lose centimetres at 1e5 m). The platoon works, as the
rollout does, relative to follower 0's starting point.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from torch import Tensor

from ..models import FollowerState
from ..sim.compiled import configure_compiler
from .safety import DEFAULT_SAFETY, SafetyLayer
from .sampler import HybridSampler, increasing_root

#: Speed [m/s] above which a vehicle counts as moving for the safety layer's
#: intervention count (``TrafficOutput.interventions_moving``).
MOVING_SPEED = 0.1

if TYPE_CHECKING:
    from ..data import PairSet


class RingState(NamedTuple):
    """The vehicles on a ring, each ``(S, n)``.

    Attributes:
        spacing: front-to-front spacing to the vehicle ahead [m].
        v: speed [m/s].
        a: realised acceleration [m/s^2].
        position: ring coordinate in ``[0, L)`` [m].

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> from torchcf.traffic import ring_initial_state
        >>> state = ring_initial_state(sampler, 120.0)  # a 120 m ring
        >>> state.spacing.shape, [round(s, 3) for s in state.spacing.sum(1).tolist()]
        (torch.Size([2, 3]), [120.0, 120.0])
    """

    spacing: Tensor
    v: Tensor
    a: Tensor
    position: Tensor


@dataclass(frozen=True, eq=False)
class RingStart:
    """A ring's start at equilibrium, plus one small disturbance
    (:func:`ring_initial_state`).

    Attributes:
        v_init: None: the mixed ring's own equilibrium (every vehicle at the
            common speed with its own steady spacing); a speed [m/s], a number
            or ``(S,)``: equal spacings ``L / n`` at that speed.
        perturbation: vehicle 0 moved this far back [m].

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> from torchcf.traffic import RingStart, ring_road
        >>> start = RingStart(v_init=5.0, perturbation=2.0)  # [m/s], [m]
        >>> out = ring_road(sampler, 120.0, n_steps=10, initial=start)
        >>> [round(v, 3) for v in out.v[0, 0].tolist()]  # at t = 0 [m/s]
        [5.0, 5.0, 5.0]
        >>> [round(s, 3) for s in out.spacing[0, 0].tolist()]  # 120 m / 3, shifted 2 m
        [42.0, 40.0, 38.0]
    """

    v_init: float | Tensor | None = None
    perturbation: float = 1.0


class TrafficOutput(NamedTuple):
    """What :func:`platoon` and :func:`ring_road` return.

    Recorded every ``record_every`` steps from t = 0 (``T'`` records; None when
    not recording); the acceleration recorded at t is, as in the rollout, the
    command at t (the realised state for HL and ``+lag``).

    Attributes:
        time: ``(T',)`` time of each record [s].
        x: ``(T', S, n)`` position [m]: along the road (platoon) or the ring
            coordinate in ``[0, L)`` (ring).
        v: ``(T', S, n)`` speed [m/s].
        a: ``(T', S, n)`` recorded acceleration [m/s^2].
        spacing: ``(T', S, n)`` front-to-front spacing to the vehicle ahead [m].
        collision_step: ``(S, n)`` int64, first step with a spacing ``<= 0`` or
            NaN, ``-1`` if none.
        final: the state after the last step (:class:`RingState`, or the
            platoon's ``FollowerState`` of ``(S, n)`` road positions), to continue.
        interventions: ``(S, n)`` int64, the steps at which the safety layer
            overrode the vehicle's model (zeros without a layer).
        interventions_moving: ``(S, n)`` int64, those of them taken while the
            vehicle moved (speed over :data:`MOVING_SPEED` before the step);
            the rest held a standing vehicle back (a model that creeps forward
            at a stop, as SPEC's IDM with its front-to-front ``s0`` does).

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> from torchcf.traffic import ring_road
        >>> out = ring_road(sampler, 120.0, n_steps=100, record_every=10)
        >>> out.time.shape, out.x.shape, out.collision_step.shape  # (T', S, n)
        (torch.Size([10]), torch.Size([10, 2, 3]), torch.Size([2, 3]))
        >>> out.valid.tolist(), int(out.interventions.sum())
        ([True, True], 0)
    """

    time: Tensor | None
    x: Tensor | None
    v: Tensor | None
    a: Tensor | None
    spacing: Tensor | None
    collision_step: Tensor
    final: Any
    interventions: Tensor
    interventions_moving: Tensor

    @property
    def collided(self) -> Tensor:
        """``(S, n)`` bool: the vehicle collided at some step."""
        return self.collision_step >= 0

    @property
    def valid(self) -> Tensor:
        """``(S,)`` bool: no vehicle of the scenario collided."""
        return ~self.collided.any(-1)


def _scenario_shape(sampler: HybridSampler) -> tuple[int, int]:
    if len(sampler.vehicle_shape) != 2 or sampler.n_vehicles == 0:
        raise ValueError(
            "the sampler's vehicles must be laid out as (S, n): call "
            f"sampler.sample((S, n)) first (now {sampler.vehicle_shape})"
        )
    return sampler.vehicle_shape  # type: ignore[return-value]


def _check_record_every(record_every: int | None) -> None:
    if record_every is not None and (
        not isinstance(record_every, int) or record_every < 1
    ):
        raise ValueError(
            f"record_every must be a positive int or None, got {record_every}"
        )


class _Recorder:
    """Keeps every ``record_every``-th step's ``(S, n)`` fields, and collisions."""

    def __init__(self, every: int | None, n_steps: int, shape, dtype, device) -> None:
        self.every = every
        self.n_records = 0 if every is None else -(-n_steps // every)
        self.fields = (
            torch.empty((4, self.n_records, *shape), dtype=dtype, device=device)
            if self.n_records
            else None
        )  # x, v, a, spacing: (4, T', S, n)
        # No collision yet, and the number of steps checked while none was seen:
        # three cheap in-place operations per step, no host synchronisation.
        self.clear = torch.ones(shape, dtype=torch.bool, device=device)
        self.clear_steps = torch.zeros(shape, dtype=torch.long, device=device)
        self.interventions = torch.zeros(shape, dtype=torch.long, device=device)
        self.interventions_moving = torch.zeros_like(self.interventions)

    def count(self, overridden: Tensor | None, v: Tensor) -> None:
        """Add the layer's overrides of a step; ``v``: speeds before it."""
        if overridden is None:
            return
        self.interventions += overridden
        self.interventions_moving += overridden & (v > MOVING_SPEED)

    def due(self, t: int) -> bool:
        return self.fields is not None and t % self.every == 0

    def check(self, spacing: Tensor) -> None:
        """Count one more step, flagging a spacing ``<= 0`` or not a number."""
        # NaN compares False: a blown-up state (its spacing turns NaN at the
        # latest one step later) counts as a collision.
        self.clear &= spacing > 0
        self.clear_steps += self.clear

    def record(self, t: int, x, v, a, spacing) -> None:
        self.fields[:, t // self.every] = torch.stack((x, v, a, spacing))

    def output(self, dt: float, final: Any) -> TrafficOutput:
        collision_step = torch.where(
            self.clear, torch.full_like(self.clear_steps, -1), self.clear_steps
        )
        if self.fields is None:
            empty = (None,) * 5
            return TrafficOutput(
                *empty,
                collision_step,
                final,
                self.interventions,
                self.interventions_moving,
            )
        steps = torch.arange(self.n_records, device=self.fields.device) * self.every
        time = steps.to(self.fields.dtype) * dt
        x, v, a, spacing = self.fields.unbind(0)
        return TrafficOutput(
            time,
            x,
            v,
            a,
            spacing,
            collision_step,
            final,
            self.interventions,
            self.interventions_moving,
        )


def _maybe_compile(fn: Callable[..., Any], compile: bool) -> Callable[..., Any]:
    if not compile:
        return fn
    # Each sampler (its groups), a fresh or carried memory and each piece around
    # MPC's eager solver is a separate graph of the same step function: the
    # raised recompile limits of configure_compiler.
    configure_compiler()
    # dynamic=None: the groups' sizes change when the vehicles are redrawn, and
    # after the first change dynamo compiles shape-generic graphs.
    return torch.compile(fn, dynamic=None)


# ----------------------------------------------------------------------- platoon
def pair_leader(
    pairs: PairSet, index: int | Sequence[int] | Tensor
) -> tuple[Tensor, Tensor, FollowerState]:
    """Measured leaders and their followers' starting states, for :func:`platoon`.

    Args:
        pairs: the pairs ``(T, N)`` (ragged pairs are padded with their last value:
            the leader then stands still; simulate their valid steps only).
        index: ``(S,)`` the pair of each scenario; an int is one scenario
            (``S = 1``).

    Returns:
        leader position ``(T, S)`` [m] and speed ``(T, S)`` [m/s], and follower 0's
        observed initial state (each ``(S,)``), all in the pairs' dtype.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> from torchcf.traffic import pair_leader
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> x_leader, v_leader, start = pair_leader(pairs, [0, 2])  # two scenarios
        >>> x_leader.shape, v_leader.shape, start.x.shape
        (torch.Size([50, 2]), torch.Size([50, 2]), torch.Size([2]))
        >>> bool((start.x == pairs.x_follow[0, [0, 2]]).all())
        True
    """
    index = torch.as_tensor(index, dtype=torch.long)
    if index.ndim == 0:  # one pair: one scenario
        index = index[None]
    if index.ndim != 1 or index.numel() == 0:
        raise ValueError(f"index must be a non-empty 1-D list of pairs, got {index}")
    if int(index.min()) < 0 or int(index.max()) >= pairs.n_pairs:
        raise ValueError(f"pair index out of range [0, {pairs.n_pairs})")
    start = FollowerState(
        pairs.x_follow[0, index], pairs.v_follow[0, index], pairs.a_follow[0, index]
    )
    return pairs.x_lead[:, index], pairs.v_lead[:, index], start


def _platoon_step(
    sampler: HybridSampler,
    safety: SafetyLayer | None,
    x_lead: Tensor,
    v_lead: Tensor,
    state: FollowerState,
    origin: Tensor,
    last: bool,
) -> tuple[Tensor, Tensor, FollowerState, Tensor | None]:
    """One step of the platoon: spacing, commands, realisation (bounded by the
    safety layer, whose overrides are returned). ``(S, n)`` each."""
    x_ahead = torch.cat((x_lead[:, None], state.x[:, :-1]), dim=1)  # (S, n)
    v_ahead = torch.cat((v_lead[:, None], state.v[:, :-1]), dim=1)  # (S, n)
    spacing = x_ahead - state.x
    u = sampler(spacing, state.v, v_ahead, state.a, state.x + origin)
    if last:
        return spacing, u, state, None
    moved = sampler.advance(state.x, state.v, state.a, u)
    if safety is None:
        return spacing, u, moved, None
    moved, overridden = safety.apply(
        state, moved, spacing, v_ahead, sampler.dt, sampler.leader_length
    )
    return spacing, u, moved, overridden


def platoon(
    sampler: HybridSampler,
    x_leader: Tensor,
    v_leader: Tensor,
    *,
    start: FollowerState | None = None,
    initial_spacing: float | Tensor | None = None,
    record_every: int | None = 1,
    compile: bool = False,
    safety: SafetyLayer | None = DEFAULT_SAFETY,
) -> TrafficOutput:
    """``n`` sampled followers behind a given leader, for ``S`` scenarios at once.

    At every step t = 0 .. T-1, follower 0 perceives the leader at t and follower
    ``j`` follower ``j - 1`` at t; all commands come from one sampler call and all
    followers move at once (SPEC section 2; the leader is replayed). Follower 0
    starts from ``start``; follower ``j`` starts ``j`` initial spacings behind it,
    with the same speed and acceleration. The sampler's clock ticks once per step
    (redraws, if asked for at ``sample``).

    Args:
        sampler: drawn with ``vehicle_shape == (S, n)``.
        x_leader: ``(T, S)`` leader position [m] (any float dtype; the frame shift
            is taken in it, then the sampler's dtype is used).
        v_leader: ``(T, S)`` leader speed [m/s].
        start: follower 0's initial ``(x, v, a)``, each ``(S,)`` (a measured one:
            :func:`pair_leader`); default: ``initial_spacing`` behind the leader,
            at its speed, ``a = 0``.
        initial_spacing: ``(S,)`` or a number [m]; only without ``start``;
            default ``10 m + 1.5 s * v_leader(0)``.
        record_every: keep every this many steps' states (None: keep none).
        compile: fuse the step with ``torch.compile``.
        safety: the collision-avoidance bound on every follower's step
            (:mod:`torchcf.traffic.safety`; on by default); None: the learned
            models alone (the calibration rollout exactly).

    Returns:
        :class:`TrafficOutput` with ``(T', S, n)`` road positions; ``final`` is
        the followers' state at T-1.

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
        >>> from torchcf.traffic import platoon
        >>> out = platoon(sampler, x_leader, v_leader)  # 3 followers in each
        >>> out.x.shape, out.valid.tolist()  # (T, S, n) positions [m]
        (torch.Size([50, 2, 3]), [True, True])
        >>> bool((out.spacing > 0).all())
        True
    """
    n_scenarios, n_followers = _scenario_shape(sampler)
    _check_record_every(record_every)
    if x_leader.ndim != 2 or x_leader.shape[1] != n_scenarios:
        raise ValueError(
            f"x_leader must be (T, S) with S = {n_scenarios}, "
            f"got {tuple(x_leader.shape)}"
        )
    if v_leader.shape != x_leader.shape:
        raise ValueError(
            f"v_leader must have x_leader's shape {tuple(x_leader.shape)}, "
            f"got {tuple(v_leader.shape)}"
        )
    if x_leader.shape[0] < 1:
        raise ValueError("the leader trajectory needs at least one step")
    dtype, device = sampler.dtype, sampler.device
    if start is None:
        if initial_spacing is None:
            initial_spacing = 10.0 + 1.5 * v_leader[0]
        gap0 = torch.as_tensor(
            initial_spacing, dtype=x_leader.dtype
        ) + torch.zeros_like(x_leader[0])
        start = FollowerState(x_leader[0] - gap0, v_leader[0], torch.zeros_like(gap0))
    elif initial_spacing is not None:
        raise ValueError("give start or initial_spacing, not both")
    origin = start.x  # (S,) in the leader's dtype
    gap0 = x_leader[0] - origin  # (S,)
    if not bool((gap0 > 0).all()):
        raise ValueError("follower 0 must start behind the leader (spacing > 0)")
    behind = torch.arange(n_followers, dtype=gap0.dtype, device=gap0.device)
    # Shift to follower 0's frame in the given dtype first, as the rollout does:
    # follower 0 then starts at exactly 0 and its arithmetic is the rollout's.
    x_lead = (x_leader - origin[None, :]).to(device=device, dtype=dtype)  # (T, S)
    v_lead = v_leader.to(device=device, dtype=dtype)
    state = FollowerState(
        x=(-behind[None, :] * gap0[:, None]).to(device=device, dtype=dtype),
        v=start.v.to(device=device, dtype=dtype)[:, None].expand(-1, n_followers),
        a=start.a.to(device=device, dtype=dtype)[:, None].expand(-1, n_followers),
    )  # (S, n) each
    state = FollowerState(*(t.contiguous() for t in state))
    shift = origin.to(device=device, dtype=dtype)[:, None]  # (S, 1)

    n_steps = x_leader.shape[0]
    recorder = _Recorder(
        record_every, n_steps, (n_scenarios, n_followers), dtype, device
    )
    step = _maybe_compile(functools.partial(_platoon_step, sampler, safety), compile)
    for t in range(n_steps):
        last = t == n_steps - 1
        spacing, u, moved, overridden = step(x_lead[t], v_lead[t], state, shift, last)
        recorder.check(spacing)
        recorder.count(overridden, state.v)
        if recorder.due(t):
            recorded = torch.where(sampler.acceleration_is_state, state.a, u)
            recorder.record(t, state.x + shift, state.v, recorded, spacing)
        if not last:
            state = moved
            sampler.tick()
    final = FollowerState(state.x + shift, state.v, state.a)
    return recorder.output(sampler.dt, final)


# --------------------------------------------------------------------- ring road
def _ring_step(
    sampler: HybridSampler,
    safety: SafetyLayer | None,
    state: RingState,
    length: Tensor,
) -> tuple[RingState, Tensor, Tensor | None]:
    """One step on the ring: commands, realisation (bounded by the safety
    layer, whose overrides are returned), spacing update. ``(S, n)``."""
    v_ahead = torch.roll(state.v, -1, dims=-1)  # vehicle i follows i + 1
    u = sampler(state.spacing, state.v, v_ahead, state.a, state.position)
    # From x = 0 the realised position is the displacement over the step.
    here = FollowerState(torch.zeros_like(state.v), state.v, state.a)
    moved = sampler.advance(here.x, here.v, here.a, u)
    overridden = None
    if safety is not None:
        moved, overridden = safety.apply(
            here, moved, state.spacing, v_ahead, sampler.dt, sampler.leader_length
        )
    dx = moved.x  # (S, n), >= 0
    spacing = state.spacing + torch.roll(dx, -1, dims=-1) - dx
    position = torch.remainder(state.position + dx, length)
    return RingState(spacing, moved.v, moved.a, position), u, overridden


def ring_initial_state(
    sampler: HybridSampler,
    length: float | Tensor,
    *,
    v_init: float | Tensor | None = None,
    perturbation: float = 1.0,
    v_max: float = 40.0,
) -> RingState:
    """A start at equilibrium, plus one small disturbance; ``a = 0``.

    Default (``v_init=None``): the mixed ring's own equilibrium. Vehicle ``i``
    keeps a steady spacing ``s_i(v)`` at speed ``v``
    (:meth:`HybridSampler.equilibrium_spacing`; ``s_i`` grows with ``v``), so
    the ring is at rest in its moving frame at the common speed ``v*`` with
    ``sum_i s_i(v*) = L``, found by bisection per scenario. A steady spacing is
    at least one vehicle length ``L_veh`` (the sampler's leader length): a
    vehicle whose model still accelerates there (OVM, GFM, FVDM with
    ``V(0) > v``) has no steady spacing and starts ``L_veh`` behind its leader.
    At most ``L``: a vehicle that cannot reach ``v`` at any spacing (OVM's,
    GFM's, FVDM's bounded optimal velocity, IDM's ``v0``) is the ring's
    bottleneck: ``v*`` is its top speed and it takes the rest of the ring (the
    bisection's final bracket ``[v-, v+]`` is closed by interpolating each
    vehicle between ``s_i(v-)`` and ``s_i(v+)``, which puts the remainder where
    ``s_i`` jumps). Every vehicle starts at ``v*``. Where even at standstill the
    steady spacings exceed ``L``, ``v* = 0`` and they are shrunk equally; where
    they fall short at ``v_max``, ``v* = v_max`` and the rest is shared equally.
    With ``v_init``: equal spacings ``L / n`` at that speed (an equilibrium only
    for identical vehicles).

    Then vehicle 0 is moved ``perturbation`` metres back (its spacing grows, the
    spacing of the vehicle behind it across the wrap shrinks by as much): the
    small disturbance a string-unstable flow amplifies. Vehicle ``i`` is
    ``sum_{j < i} s_j`` along the ring from vehicle 0.

    Args:
        sampler: drawn with ``vehicle_shape == (S, n)``.
        length: ring length ``L`` [m], a number or ``(S,)``.
        v_init: initial speed [m/s], a number or ``(S,)``; default: the ring's
            equilibrium speed ``v*``.
        perturbation: backward shift of vehicle 0 [m], less than the spacings
            it changes.
        v_max: upper end of the search for ``v*`` [m/s].

    Returns:
        :class:`RingState`, ``(S, n)`` fields in the sampler's dtype.

    Raises:
        ValueError: a spacing would be ``<= 0`` (the ring is too short for its
            vehicles, or the perturbation too large).

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> from torchcf.traffic import ring_initial_state
        >>> state = ring_initial_state(sampler, 120.0, perturbation=1.0)  # [m]
        >>> [round(s, 3) for s in state.spacing.sum(1).tolist()]  # the ring's length
        [120.0, 120.0]
        >>> bool((state.v == state.v[:, :1]).all())  # one speed per ring
        True
    """
    n_scenarios, n_vehicles = _scenario_shape(sampler)
    dtype, device = sampler.dtype, sampler.device
    ring = _ring_length(length, n_scenarios, dtype, device)  # (S, 1)
    if not perturbation >= 0:
        raise ValueError(f"perturbation must be >= 0 m, got {perturbation}")
    shape = (n_scenarios, n_vehicles)
    if v_init is None:
        s_min, s_max = sampler.leader_length, ring.expand(shape)

        def excess(speed: Tensor) -> Tensor:  # (S,) -> (S,): sum_i s_i(v) - L
            steady = sampler.equilibrium_spacing(
                speed[:, None].expand(shape), s_min=s_min, s_max=s_max
            )
            return steady.sum(dim=1) - ring[:, 0]

        v_low, v_high = increasing_root(
            excess,
            torch.zeros(n_scenarios, dtype=dtype, device=device),
            torch.full((n_scenarios,), v_max, dtype=dtype, device=device),
            iterations=32,  # v* to 1e-8 m/s; the ring is closed exactly below
            bracket=True,
        )  # (S,) each, sum_i s_i(v_low) <= L < sum_i s_i(v_high)
        low, high = (
            sampler.equilibrium_spacing(
                speed[:, None].expand(shape), s_min=s_min, s_max=s_max
            )
            for speed in (v_low, v_high)
        )  # (S, n) each
        total_low = low.sum(dim=1, keepdim=True)  # (S, 1)
        total_high = high.sum(dim=1, keepdim=True)
        share = torch.where(
            total_high > total_low,
            (ring - total_low) / (total_high - total_low),
            torch.zeros_like(total_low),
        ).clamp(0.0, 1.0)
        spacing = low + share * (high - low)
        # Zero unless v* sits at an end of [0, v_max] (see above).
        spacing = spacing + (ring - spacing.sum(dim=1, keepdim=True)) / n_vehicles
        v0 = v_low + share[:, 0] * (v_high - v_low)  # (S,); exactly 0 in a jam
    else:
        v0 = torch.as_tensor(v_init, dtype=dtype, device=device)
        if v0.ndim > 1 or (v0.ndim == 1 and v0.shape[0] != n_scenarios):
            raise ValueError(f"v_init must be a number or (S,) = ({n_scenarios},)")
        if not bool((v0 >= 0).all()):
            raise ValueError("v_init must be >= 0 m/s")
        spacing = (ring / n_vehicles).expand(shape).clone()
    spacing = spacing.clone()
    spacing[:, 0] += perturbation
    spacing[:, -1] -= perturbation
    if not bool((spacing > 0).all()):
        raise ValueError(
            "a starting spacing would be <= 0: the ring is too short for its "
            "vehicles or the perturbation too large"
        )
    # Vehicle 0 at -perturbation, each next one its spacing further on.
    position = torch.cumsum(spacing, dim=1) - spacing - perturbation  # (S, n)
    position = torch.remainder(position, ring)
    v = (v0.reshape(-1, 1) + torch.zeros_like(spacing)).contiguous()  # (S, n)
    return RingState(spacing.contiguous(), v, torch.zeros_like(spacing), position)


def _ring_length(length: float | Tensor, n_scenarios: int, dtype, device) -> Tensor:
    length = torch.as_tensor(length, dtype=dtype, device=device)
    if length.ndim > 1 or (length.ndim == 1 and length.shape[0] != n_scenarios):
        raise ValueError(f"length must be a number or (S,) = ({n_scenarios},)")
    if not bool((length > 0).all()) or not bool(torch.isfinite(length).all()):
        raise ValueError("the ring length must be a positive number of metres")
    return length.reshape(-1, 1) + torch.zeros(
        n_scenarios, 1, dtype=dtype, device=device
    )


def ring_road(
    sampler: HybridSampler,
    length: float | Tensor,
    n_steps: int,
    *,
    initial: RingState | RingStart = RingStart(),
    record_every: int | None = 1,
    compile: bool = False,
    safety: SafetyLayer | None = DEFAULT_SAFETY,
) -> TrafficOutput:
    """``n`` sampled vehicles on a single-lane ring, ``S`` rings at once.

    Vehicle ``i`` follows vehicle ``i + 1`` (``n - 1`` follows 0 across the wrap);
    its spacing is ``x_{i+1} - x_i`` (mod ``L``). Each step: one sampler call for
    every command, each vehicle's realisation from ``x = 0`` giving its
    displacement ``dx``, then ``s_i += dx_{i+1} - dx_i`` (so ``sum_i s_i = L``
    to round-off). The sampler's clock ticks once per step.

    Args:
        sampler: drawn with ``vehicle_shape == (S, n)``.
        length: ring length ``L`` [m], a number or ``(S,)`` (several densities).
        n_steps: steps of ``sampler.dt``.
        initial: start from this state (e.g. a previous run's ``final``), or
            from :func:`ring_initial_state` with a :class:`RingStart`'s
            ``v_init`` and ``perturbation``; default ``RingStart()``: the mixed
            ring's equilibrium, vehicle 0 moved 1 m back.
        record_every: keep every this many steps' states (None: keep none).
        compile: fuse the step with ``torch.compile``.
        safety: the collision-avoidance bound on every vehicle's step
            (:mod:`torchcf.traffic.safety`; on by default); None: the learned
            models alone.

    Returns:
        :class:`TrafficOutput`; ``x`` is the ring coordinate in ``[0, L)``,
        ``final`` the :class:`RingState` after ``n_steps`` steps.

    Examples:
        >>> import torch
        >>> from torchcf import HybridSampler, get_model
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> sampler = HybridSampler([get_model("idm")], [idm], dt=0.1)
        >>> _ = sampler.sample((2, 3), generator=torch.Generator().manual_seed(0))
        >>> from torchcf.traffic import ring_road
        >>> out = ring_road(sampler, length=120.0, n_steps=100)  # 10 s on a 120 m ring
        >>> out.x.shape, out.valid.tolist()
        (torch.Size([100, 2, 3]), [True, True])
        >>> [round(s, 3) for s in out.final.spacing.sum(1).tolist()]  # [m]
        [120.0, 120.0]
    """
    n_scenarios, n_vehicles = _scenario_shape(sampler)
    _check_record_every(record_every)
    if not isinstance(n_steps, int) or n_steps < 0:
        raise ValueError(f"n_steps must be an int >= 0, got {n_steps!r}")
    dtype, device = sampler.dtype, sampler.device
    ring = _ring_length(length, n_scenarios, dtype, device)  # (S, 1)
    if isinstance(initial, RingStart):
        state = ring_initial_state(
            sampler,
            length,
            v_init=initial.v_init,
            perturbation=initial.perturbation,
        )
    else:
        state = RingState(*(t.to(device=device, dtype=dtype) for t in initial))
        if any(tuple(t.shape) != (n_scenarios, n_vehicles) for t in state):
            raise ValueError(f"initial must hold ({n_scenarios}, {n_vehicles}) fields")
    recorder = _Recorder(
        record_every, n_steps, (n_scenarios, n_vehicles), dtype, device
    )
    step = _maybe_compile(functools.partial(_ring_step, sampler, safety), compile)
    for t in range(n_steps):
        previous = state
        state, u, overridden = step(previous, ring)
        recorder.check(previous.spacing)
        recorder.count(overridden, previous.v)
        if recorder.due(t):
            recorded = torch.where(sampler.acceleration_is_state, previous.a, u)
            recorder.record(
                t, previous.position, previous.v, recorded, previous.spacing
            )
        sampler.tick()
    recorder.check(state.spacing)
    return recorder.output(sampler.dt, state)


__all__ = [
    "MOVING_SPEED",
    "RingStart",
    "RingState",
    "TrafficOutput",
    "pair_leader",
    "platoon",
    "ring_initial_state",
    "ring_road",
]
