"""Effects: composable augmentations of any car-following model.

An effect adds something no candidate model has — a perception delay, an actuation
lag, a sensor offset, a road grade, a clock offset between the logs... — with its
own named parameters and uniform priors, without touching the model's equations.
It acts at one of three places of the step (:mod:`torchcf.models.base`):

- **perception** (:meth:`Effect.perceive`): edits what the follower perceives before
  the model's command (``sync``, ``offset``, ``delay``, ``timegap``,
  ``anticipation``); may
  carry memory between steps;
- **command** (:meth:`Effect.act`, or :meth:`Effect.act_with_memory`): edits the
  command after the model (``asymmetry``, ``saturation``, ``resistance``,
  ``action``, ``grade``, ``bend``);
- **realisation** (:meth:`Effect.advance`): replaces how the command becomes motion
  (``lag``).

:class:`~torchcf.models.augmented.AugmentedModel` composes a pool model with
effects; its registry name is
``"<model>+<effect>+..."`` (e.g. ``"idm+delay"``), effects in the canonical order of
:data:`EFFECTS`, so the same augmentation always has one name. Effects with options
write them in the name: ``"llctg+grade(start=0,end=600,knots=4)"``.

Adding an effect is one small class: subclass :class:`Effect`, declare ``name``,
``stage`` and ``param_specs`` (names prefixed so they cannot collide with a model's),
implement the hook of its stage, and list it in :data:`EFFECTS`.
"""

from __future__ import annotations

import math
import re
from collections import namedtuple
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from ..system.errors import did_you_mean
from .base import (
    CFModel,
    FollowerState,
    ParamSpec,
    Perception,
    first_order_lag_advance,
    rows_of,
    spec,
)

#: Standard gravity [m/s^2] (road grade -> acceleration).
GRAVITY = 9.81
#: Upper end of the perception delay's default prior [s].
DELAY_PRIOR_HIGH = 3.0
#: Time over which a driver brings its speed down to a bend's limit [s].
BEND_RELAXATION = 1.0

Stage = Literal["perception", "command", "realisation"]
Scope = Literal["driver", "recording", "road"]


class Effect:
    """Base class of an effect (see the module docstring).

    Subclasses declare :attr:`name`, :attr:`stage`, :attr:`param_specs` and override
    the hook of their stage. ``q`` below is the tuple of the effect's own parameter
    tensors (in :attr:`param_specs` order, each broadcast to the state's shape), as
    returned by :meth:`prepare`.

    Examples:
        >>> from torchcf.models import EFFECTS
        >>> delay = EFFECTS["delay"]()
        >>> delay.name, delay.stage, [spec.name for spec in delay.param_specs]
        ('delay', 'perception', ['t_delay'])
        >>> delay.neutral  # no delay: the model itself
        (0.0,)
    """

    name: ClassVar[str]
    stage: ClassVar[Stage]
    param_specs: tuple[ParamSpec, ...] = ()
    #: True when the effect reads ``Perception.position``.
    uses_position: ClassVar[bool] = False
    #: True when the recorded acceleration becomes a state of the vehicle.
    acceleration_is_state: ClassVar[bool] = False
    #: What the parameters describe: ``"driver"`` (the follower's behaviour: a
    #: value per pair), ``"recording"`` (the measurement: one sensor, one logger,
    #: so one value for every pair of a data set) or ``"road"`` (a function of road
    #: position, the same for every pair driven there). The diagnosis fits a
    #: recording or road effect jointly over the pairs (:attr:`shared`).
    scope: ClassVar[Scope] = "driver"

    @property
    def shared(self) -> bool:
        """True when every pair shares one value (recording and road effects)."""
        return self.scope != "driver"

    @property
    def neutral(self) -> tuple[float, ...]:
        """Parameter values (K_E,) at which the effect is the model itself, or as
        close as its prior allows (:attr:`exactly_neutral` says which): the
        start of a nested search, where the augmented model is its base.

        The default: each parameter's value nearest 0 in its prior (0 where the
        prior holds it: an added term, shift or delay of zero; else the bound
        nearer 0). Effects whose identity is elsewhere (a gain of 1, a limit
        at the far end) override it."""
        return tuple(min(max(0.0, p.lower), p.upper) for p in self.param_specs)

    #: True when :attr:`neutral` gives the base model's rollout exactly.
    exactly_neutral: ClassVar[bool] = True

    def options(self) -> dict[str, float | int]:
        """Constructor options that differ from the defaults (they enter the name)."""
        return {}

    @property
    def token(self) -> str:
        """The effect's part of a model name: ``name`` or ``name(key=value,...)``."""
        options = self.options()
        if not options:
            return self.name
        items = ",".join(f"{k}={_number(v)}" for k, v in options.items())
        return f"{self.name}({items})"

    def prepare(self, q: tuple[Tensor, ...], dt: float) -> Any:
        """Per-chunk precomputation from the effect's parameters (default: none)."""
        return q

    def initial_memory(self, q: Any, first: Perception) -> Any:
        """Memory carried between steps (perception effects only; default none)."""
        return None

    def perceive(self, q: Any, obs: Perception, memory: Any) -> tuple[Perception, Any]:
        """Perception stage: the edited perception and the next memory."""
        return obs, memory

    def select(self, q: Any, memory: Any, rows: Tensor) -> tuple[Any, Any]:
        """What :meth:`prepare` and the memory hold for the particles ``rows``
        (int64, dimension 0 of the state) alone (early rejection,
        :meth:`CFModel.select_particles`). The default: tensors with the
        particle first, a 0-dimensional one shared."""
        return rows_of(q, rows), None if memory is None else rows_of(memory, rows)

    def act_with_memory(
        self, q: Any, obs: Perception, u: Tensor, memory: Any
    ) -> tuple[Tensor, Any]:
        """A command effect with memory (action points); default: :meth:`act`."""
        return self.act(q, obs, u), memory

    def act(self, q: Any, obs: Perception, u: Tensor) -> Tensor:
        """Command stage: the edited command [m/s^2]; ``obs`` is the true state."""
        return u

    def advance(
        self, q: Any, state: FollowerState, u: Tensor, dt: float
    ) -> FollowerState:
        """Realisation stage: how the command moves the vehicle over ``dt``."""
        raise NotImplementedError

    def check(self, base: CFModel) -> None:
        """Raise ValueError when the effect cannot wrap ``base``."""

    def check_bounds(self, box: Tensor) -> None:
        """Raise ValueError for prior bounds the effect cannot run ((K, 2) box)."""

    def __repr__(self) -> str:
        return self.token

    def __eq__(self, other: object) -> bool:
        """Effects are equal when they are one kind with the same options (one
        token): the identity an effect travels with."""
        if not isinstance(other, Effect):
            return NotImplemented
        return type(self) is type(other) and self.token == other.token

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.token))


def _number(value: float) -> str:
    """The shortest of ``%g``-style forms that reads back as ``value`` exactly.

    A name is the model's identity (configs, results): parsing it again must give
    the same effect, so ``1234.567`` may not become ``1234.57``.
    """
    return next(
        text for digits in range(6, 18) if float(text := f"{value:.{digits}g}") == value
    )


class Offset(Effect):
    """A constant spacing-sensor offset: the follower perceives ``s + d_offset``."""

    name = "offset"
    stage = "perception"
    scope = "recording"
    param_specs = (spec("d_offset", "m", -6.0, 6.0, "spacing-sensor offset"),)

    def perceive(self, q, obs, memory):
        (d_offset,) = q
        return obs._replace(spacing=obs.spacing + d_offset), memory


class DelayMemory(namedtuple("DelayMemory", ["spacing", "v_lead", "head"])):
    """Ring buffers ``(D, *state)`` of the two remembered series (a delay: the
    perceived spacing and leader speed; a sync: the leader's road position in
    ``spacing`` and its speed), and ``head`` (int64, 0-dim), the slot of the
    newest entry: slot ``head - k (mod D)`` holds the value ``k`` steps ago."""


class Delay(Effect):
    """Perception delay: spacing and leader speed are perceived ``t_delay`` late.

    The model sees ``s(t - t_delay)`` and ``v_lead(t - t_delay)`` (own speed and
    acceleration are current), linearly interpolated between the recorded steps:
    with ``t_delay / dt = k + f``, ``(1 - f) h[k] + f h[k + 1]`` where ``h[k]`` is the
    value ``k`` steps ago. Before the first step the history is the first
    perception (a steady past).

    Args:
        max_delay: longest delay the history holds [s]; priors must stay below it.
    """

    name = "delay"
    stage = "perception"
    #: the option naming the history's length in a name, and its default [s]
    option: ClassVar[str] = "max_delay"
    default_history: ClassVar[float] = 3.0

    def __init__(self, max_delay: float = 3.0) -> None:
        if not max_delay > 0:
            raise ValueError(f"{self.name}: {self.option} must be > 0, got {max_delay}")
        self.max_delay = float(max_delay)
        # Reaction times of drivers and ACC controllers: 0.5-2.5 s (commercial ACC
        # response times of 1.7-2.5 s are reported); the prior covers 0-3 s, or
        # the history the effect holds.
        high = min(DELAY_PRIOR_HIGH, self.max_delay)
        self.param_specs = (spec("t_delay", "s", 0.0, high, "perception delay"),)

    def options(self):
        if self.max_delay == self.default_history:
            return {}
        return {self.option: self.max_delay}

    def check_bounds(self, box):
        low, high = float(box[0, 0]), float(box[0, 1])
        if low < 0 or high > self.max_delay:
            param = self.param_specs[0].name
            raise ValueError(
                f"{self.name}: {param} prior [{low:g}, {high:g}] s must lie in "
                f"[0, {self.option} = {self.max_delay:g}] (raise it with "
                f"'{self.name}({self.option}=...)')"
            )

    def depth(self, dt: float) -> int:
        """History entries: 0 .. ceil(max_delay / dt) steps ago, and one spare."""
        return math.ceil(self.max_delay / dt) + 2

    def prepare(self, q, dt):
        (t_delay,) = q
        if bool(((t_delay < 0) | (t_delay > self.max_delay)).any()):
            param = self.param_specs[0].name
            raise ValueError(f"{self.name}: {param} outside [0, {self.max_delay:g}] s")
        steps = t_delay / dt
        whole = torch.floor(steps)
        depth = torch.full((), self.depth(dt), dtype=torch.int64, device=steps.device)
        # k = whole steps ago (int64), f = the fraction towards k + 1, the depth
        return (whole.long(), steps - whole, depth)

    def remembered(self, obs: Perception) -> tuple[Tensor, Tensor]:
        """What the history holds of a perception: spacing and leader speed."""
        return obs.spacing, obs.v_lead

    def recalled(self, obs: Perception, first: Tensor, second: Tensor) -> Perception:
        """The perception with the history's values of ``t_delay`` ago."""
        return obs._replace(spacing=first, v_lead=second)

    def initial_memory(self, q, first):
        _, _, depth = q
        values = self.remembered(first)
        shape = torch.broadcast_shapes(*(v.shape for v in values))
        return DelayMemory(
            *(
                value.expand(shape)
                .unsqueeze(0)
                .expand((int(depth), *shape))
                .contiguous()
                for value in values
            ),
            torch.zeros((), dtype=torch.int64, device=first.spacing.device),
        )

    def select(self, q, memory, rows):
        # the history is (depth, *state): its particles are dimension 1
        if memory is None:
            return rows_of(q, rows), None
        return rows_of(q, rows), rows_of(memory, rows, dim=1)

    def perceive(self, q, obs, memory):
        whole, fraction, depth = q
        # A ring buffer: the newest entry at `head`, the one j steps ago at
        # head - j (mod depth); each step writes one entry and reads two, whatever
        # the depth (a shifted copy of the whole history would cost depth x more).
        head = torch.remainder(memory.head + 1, depth)
        # The leader's speed arrives broadcast over particles in the full layout.
        shape = memory.spacing.shape[1:]
        # index_copy_ with a tensor index: no host sync, one graph when compiled
        slot = head.reshape(1)
        now_first, now_second = self.remembered(obs)
        memory.spacing.index_copy_(0, slot, now_first.expand(shape)[None])
        memory.v_lead.index_copy_(0, slot, now_second.expand(shape)[None])
        newer = torch.remainder(head - whole, depth).expand(shape)[None]
        older = torch.remainder(head - whole - 1, depth).expand(shape)[None]

        def past(history: Tensor) -> Tensor:
            recent, earlier = history.gather(0, newer)[0], history.gather(0, older)[0]
            return (1.0 - fraction) * recent + fraction * earlier

        delayed = self.recalled(obs, past(memory.spacing), past(memory.v_lead))
        return delayed, DelayMemory(memory.spacing, memory.v_lead, head)


class Sync(Delay):
    """A clock offset between the leader's and the follower's logs: the data show
    the leader ``t_sync`` early, so the follower, reacting to the leader's state
    at the same time, perceives the leader's *recorded* position and speed
    ``t_sync`` ago and its own current position:

    ``s' = x_lead(t - t_sync) - x(t)``, ``v_lead' = v_lead(t - t_sync)``

    (a ``delay`` also delays the follower's own position in the spacing; two
    logs out of step do not). A measurement effect of the data, so it acts first
    in a name. Interpolation and history as in :class:`Delay`; the history holds
    the leader's road position, which needs the follower's (``uses_position``).

    Args:
        max_sync: longest offset the history holds [s].
    """

    name = "sync"
    scope = "recording"
    uses_position = True
    option = "max_sync"
    default_history = 1.5

    def __init__(self, max_sync: float = 1.5) -> None:
        super().__init__(max_delay=max_sync)
        self.param_specs = (
            spec("t_sync", "s", 0.0, self.max_delay, "leader log ahead of follower's"),
        )

    def remembered(self, obs):
        if obs.position is None:
            raise ValueError("sync: the rollout gave no road position")
        return obs.spacing + obs.position, obs.v_lead

    def recalled(self, obs, first, second):
        return obs._replace(spacing=first - obs.position, v_lead=second)


class TimeGap(Effect):
    """A time gap that changes with speed: the follower perceives ``s - c_gap
    v^2`` (``v`` its own speed).

    A model that keeps the spacing ``s_e(v)`` in equilibrium (IDM: ``s0 + T v``)
    then keeps ``s_e(v) + c_gap v^2``: its time gap ``s / v`` grows by ``c_gap v``
    (c_gap = 0.02 s^2/m: +0.4 s at 20 m/s), shrinks for ``c_gap < 0``. The
    family the residual's ``gap vs speed`` signature names (the spacing error
    trending with the speed within pairs), which no pool model's constant time
    gap can follow. Own speed as measured (before ``anticipation``
    extrapolates it).
    """

    name = "timegap"
    stage = "perception"
    param_specs = (spec("c_gap", "s^2/m", -0.05, 0.05, "time gap per unit speed"),)

    def perceive(self, q, obs, memory):
        (c_gap,) = q
        return obs._replace(spacing=obs.spacing - c_gap * obs.v * obs.v), memory


class Anticipation(Effect):
    """Temporal anticipation (Treiber, Kesting & Helbing 2006, the Human Driver
    Model): the driver extrapolates what it perceives ``t_ant`` ahead at constant
    speeds and own acceleration:

    ``s' = s + t_ant (v_lead - v)``, ``v' = max(v + t_ant a, 0)`` (``v_lead``
    unchanged).

    After a perception delay it extrapolates the delayed spacing, which is how a
    driver compensates part of its reaction time. ``t_ant = 0`` is the model
    itself.
    """

    name = "anticipation"
    stage = "perception"
    param_specs = (spec("t_ant", "s", 0.0, 2.0, "anticipation time"),)

    def perceive(self, q, obs, memory):
        (t_ant,) = q
        return (
            obs._replace(
                spacing=obs.spacing + t_ant * (obs.v_lead - obs.v),
                # a speed extrapolated below zero is a stop, not reversing
                v=torch.clamp(obs.v + t_ant * obs.a, min=0.0),
            ),
            memory,
        )


class Asymmetry(Effect):
    """Separate gains when closing in and when falling back.

    ``u' = g_close u`` while the follower closes in (``v_lead < v``), else
    ``u' = g_open u``.
    """

    name = "asymmetry"
    stage = "command"
    param_specs = (
        spec("g_close", "1", 0.5, 2.0, "command gain while closing in"),
        spec("g_open", "1", 0.5, 2.0, "command gain while falling back"),
    )

    @property
    def neutral(self):
        return (1.0, 1.0)

    def act(self, q, obs, u):
        g_close, g_open = q
        return u * torch.where(obs.v_lead < obs.v, g_close, g_open)


class Saturation(Effect):
    """Acceleration limits: ``u' = min(max(u, a_low), a_high)``."""

    name = "saturation"
    stage = "command"
    param_specs = (
        spec("a_low", "m/s^2", -8.0, -1.0, "strongest deceleration"),
        spec("a_high", "m/s^2", 0.5, 4.0, "strongest acceleration"),
    )

    #: the widest limits of the prior: the model itself wherever it commands
    #: within them
    exactly_neutral = False

    @property
    def neutral(self):
        return (self.param_specs[0].lower, self.param_specs[1].upper)

    def act(self, q, obs, u):
        a_low, a_high = q
        return torch.minimum(torch.maximum(u, a_low), a_high)


class Resistance(Effect):
    """Speed-dependent drag the driver does not compensate: ``u' = u - c_drag v^2``."""

    name = "resistance"
    stage = "command"
    param_specs = (spec("c_drag", "1/m", 0.0, 2e-3, "quadratic drag coefficient"),)

    def act(self, q, obs, u):
        (c_drag,) = q
        return u - c_drag * obs.v * obs.v


class ActionMemory(namedtuple("ActionMemory", ["held", "dv", "spacing"])):
    """The command held since the last action point (NaN before the first) and
    the relative speed and spacing at that point, each the state's shape."""


class ActionPoints(Effect):
    """Perception thresholds and action points (Todosiev 1963; Wiedemann 1974):
    the driver changes its command only when the situation has changed enough
    since its last action, and holds the command chosen then in between.

    A new action point at step t when ``|dv(t) - dv_k| > ap_dv`` or
    ``|s(t) - s_k| > ap_ds s_k`` (``dv = v_lead - v``; ``dv_k, s_k`` at the last
    action point; the first step is one). Two thresholds, as in Wiedemann's
    psycho-physical models reduced to their perception limits; zero thresholds
    give the model itself (every step is an action point).
    """

    name = "action"
    stage = "command"
    param_specs = (
        spec("ap_dv", "m/s", 0.0, 1.0, "relative-speed change that triggers action"),
        spec("ap_ds", "1", 0.0, 0.2, "relative spacing change that triggers action"),
    )

    #: zero thresholds act at every step where the situation changed at all (a
    #: spacing and speed difference unchanged to the last bit hold the command)
    exactly_neutral = False

    def initial_memory(self, q, first):
        shape = torch.broadcast_shapes(first.spacing.shape, first.v_lead.shape)
        spacing = first.spacing.expand(shape).contiguous()
        return ActionMemory(
            torch.full_like(spacing, math.nan),
            (first.v_lead - first.v).expand(shape).contiguous(),
            spacing,
        )

    def act_with_memory(self, q, obs, u, memory):
        ap_dv, ap_ds = q
        dv = obs.v_lead - obs.v
        act = (
            torch.isnan(memory.held)
            | (torch.abs(dv - memory.dv) > ap_dv)
            | (torch.abs(obs.spacing - memory.spacing) > ap_ds * memory.spacing)
        )
        command = torch.where(act, u, memory.held)
        return command, ActionMemory(
            command,
            torch.where(act, dv, memory.dv),
            torch.where(act, obs.spacing, memory.spacing),
        )


class RoadProfile(Effect):
    """A function of road position, piecewise linear between ``knots`` equally
    spaced points from ``start`` to ``end`` [m] (constant beyond), its values
    there the parameters ``<prefix>_0 ...``. A function of the position only, so
    every pair recorded on the road sees the same profile (``shared``).

    On a closed track (``period`` > 0, the lap length) the profile is periodic:
    the knots lie ``period / knots`` apart from ``start`` round the lap, the
    last joined to the first, and a position ``x`` reads the profile at
    ``start + (x - start) mod period`` (positions are odometers, growing over
    laps; ``end`` is then ``start + period``).

    Args:
        start, end: the road section the profile covers [m] (data frame).
        knots: number of profile points (>= 1; 1 is a constant).
        period: lap length [m] of a closed track; 0 (default) for an open road.
    """

    stage = "command"
    uses_position = True
    scope = "road"
    #: parameter name prefix, unit, prior, what a knot value is
    prefix: ClassVar[str]
    unit: ClassVar[str]
    prior: ClassVar[tuple[float, float]]
    meaning: ClassVar[str]

    def __init__(
        self,
        start: float = 0.0,
        end: float = 2000.0,
        knots: int = 3,
        period: float = 0.0,
    ):
        if knots != int(knots) or knots < 1:
            raise ValueError(
                f"{self.name}: knots must be an integer >= 1, got {knots:g}"
            )
        knots = int(knots)
        if not (math.isfinite(period) and period >= 0):
            raise ValueError(
                f"{self.name}: period must be a lap length > 0 [m] or 0 (an "
                f"open road), got {period:g}"
            )
        if period > 0:
            end = start + period
        if knots > 1 and not end > start:
            raise ValueError(
                f"{self.name}: needs end > start, got [{start:g}, {end:g}]"
            )
        self.start, self.end, self.knots = float(start), float(end), knots
        self.period = float(period)
        self.param_specs = tuple(
            spec(
                f"{self.prefix}_{k}",
                self.unit,
                *self.prior,
                f"{self.meaning} at {x:g} m",
            )
            for k, x in enumerate(self.knot_positions)
        )

    @property
    def spacing(self) -> float:
        """Distance between neighbouring knots [m] (inf for a constant)."""
        if self.knots == 1:
            return math.inf
        if self.period:
            return self.period / self.knots
        return (self.end - self.start) / (self.knots - 1)

    @property
    def knot_positions(self) -> list[float]:
        return [self.start + k * self.spacing for k in range(self.knots)]

    def options(self):
        defaults = {"start": 0.0, "end": 2000.0, "knots": 3, "period": 0.0}
        current = {
            "start": self.start,
            "end": self.end,
            "knots": self.knots,
            "period": self.period,
        }
        if self.period:
            del current["end"]  # start + period
        return {k: v for k, v in current.items() if v != defaults[k]}

    def road_position(self, position: Tensor) -> Tensor:
        """Where on the profile's section ``position`` [m] reads it: clamped to
        ``[start, end]`` on an open road, wrapped into ``[start, start +
        period)`` on a closed track."""
        if self.period:
            return self.start + torch.remainder(position - self.start, self.period)
        return torch.clamp(position, self.start, self.end)

    def distance_to(self, position: Tensor, at: float | Tensor) -> Tensor:
        """|position - at| [m] along the road (round the lap on a closed track,
        the shorter way)."""
        gap = torch.abs(position - at)
        if self.period:
            gap = torch.remainder(gap, self.period)
            gap = torch.minimum(gap, self.period - gap)
        return gap

    def prepare(self, q, dt):
        # The knot values stacked (knots, *param shape): the profile is then two
        # gathers per step, whatever the number of knots.
        return (torch.stack(tuple(q)),)

    def select(self, q, memory, rows):
        # the knot values are (knots, *param shape): particles in dimension 1
        return rows_of(q, rows, dim=1), memory

    def profile(self, q: tuple[Tensor, ...], position: Tensor) -> Tensor:
        """The profile at ``position`` (linear interpolation of the knots; ``q``
        as :meth:`prepare` returns it)."""
        (values,) = q
        if self.knots == 1:
            return values[0] + 0.0 * position
        u = (self.road_position(position) - self.start) / self.spacing
        # The last interval: knots - 2 -> knots - 1 on an open road, knots - 1
        # -> 0 (round the lap) on a closed track.
        last = self.knots - 1 if self.period else self.knots - 2
        # A NaN position (an exploding rollout) reads knot 0; its NaN fraction
        # keeps the value NaN, so the rollout is still caught as invalid.
        left = torch.nan_to_num(torch.clamp(torch.floor(u), 0, last), nan=0.0)
        fraction = u - left
        shape = torch.broadcast_shapes(values.shape[1:], position.shape)
        values = values.expand((self.knots, *shape))
        index = left.long().expand(shape)[None]
        low = values.gather(0, index)[0]
        high = values.gather(0, torch.remainder(index + 1, self.knots))[0]
        return low + fraction * (high - low)

    def basis(self, position: Tensor) -> Tensor:
        """(..., knots) the hat functions at ``position``: the profile is
        ``basis @ values`` (a linear model of the knot values)."""
        if self.knots == 1:
            return torch.ones((*position.shape, 1), dtype=position.dtype)
        x = self.road_position(position)[..., None]
        knots = torch.tensor(self.knot_positions, dtype=position.dtype)
        return torch.clamp(1.0 - self.distance_to(x, knots) / self.spacing, min=0.0)

    def position_of(self, obs: Perception) -> Tensor:
        if obs.position is None:
            raise ValueError(f"{self.name}: the rollout gave no road position")
        return obs.position


class Grade(RoadProfile):
    """A road grade: ``u' = u - g G(x)`` (``g = 9.81 m/s^2``), ``G`` the profile of
    :class:`RoadProfile` (rise over run; 0.03 is a 3 % uphill). As an acceleration
    offset along the road it also stands for any position-bound push or drag.
    """

    name = "grade"
    prefix, unit, prior, meaning = "grade", "1", (-0.08, 0.08), "road grade"

    def act(self, q, obs, u):
        return u - GRAVITY * self.profile(q, self.position_of(obs))


class Bend(RoadProfile):
    """A speed limit along the road (bends, curvature, a work zone): the driver
    does not exceed ``V(x)``, the profile of :class:`RoadProfile`, and brakes
    towards it over ``BEND_RELAXATION`` s:

    ``u' = min(u, (V(x) - v) / BEND_RELAXATION)``.

    With ``V`` above every speed driven it is the model itself. (Curvature
    ``k`` and a lateral acceleration limit ``a_lat`` give ``V = sqrt(a_lat / k)``;
    the data rarely carry curvature, so ``V`` is learned directly.)
    """

    name = "bend"
    prefix, unit, prior, meaning = "v_bend", "m/s", (3.0, 40.0), "speed limit"
    #: the highest limit of the prior: the model itself below it
    exactly_neutral = False

    @property
    def neutral(self):
        return (self.prior[1],) * self.knots

    def act(self, q, obs, u):
        limit = self.profile(q, self.position_of(obs))
        return torch.minimum(u, (limit - obs.v) / BEND_RELAXATION)


class Lag(Effect):
    """First-order actuation lag: ``da/dt = (u - a) / t_lag`` (exact zero-order hold).

    The recorded acceleration becomes the realised state ``a``. Not for HL, which
    has its own lag.
    """

    name = "lag"
    stage = "realisation"
    acceleration_is_state = True
    param_specs = (spec("t_lag", "s", 0.05, 1.5, "actuation time constant"),)
    #: the shortest lag of the prior, 0.05 s: nearly the point mass
    exactly_neutral = False

    def check(self, base):
        if base.acceleration_is_state:
            raise ValueError(f"lag: {base.name} already has an actuation lag")

    def check_bounds(self, box):
        if float(box[0, 0]) <= 0:
            raise ValueError("lag: t_lag prior must be > 0 (it divides)")

    def advance(self, q, state, u, dt):
        (t_lag,) = q
        return first_order_lag_advance(state, u, t_lag, dt)


#: Registered effects, in the canonical order of a composite name (perception
#: effects first, then command effects in the order they apply, then realisation).
EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    # Road effects last: a road profile is then always the trailing parameters
    # of a name, which the engines append to every particle.
    for cls in (
        Sync,
        Offset,
        Delay,
        TimeGap,
        Anticipation,
        Asymmetry,
        Saturation,
        Resistance,
        ActionPoints,
        Lag,
        Grade,
        Bend,
    )
}


_TOKEN = re.compile(r"^([a-z_]+)(?:\((.*)\))?$")


def parse_effect(token: str) -> Effect:
    """One effect from its name token: ``"delay"`` or ``"grade(end=600,knots=4)"``."""
    match = _TOKEN.match(token.strip().lower())
    if match is None or match.group(1) not in EFFECTS:
        name = match.group(1) if match else token.strip().lower()
        raise ValueError(
            f"unknown effect {token!r}{did_you_mean(name, EFFECTS)}; valid "
            f"effects: {', '.join(EFFECTS)}"
        )
    cls = EFFECTS[match.group(1)]
    options: dict[str, float] = {}
    for item in filter(None, (match.group(2) or "").split(",")):
        key, sep, value = item.partition("=")
        try:
            options[key.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep:
            raise ValueError(f"effect {token!r}: options are key=number, got {item!r}")
    try:
        return cls(**options)
    except TypeError as error:
        raise ValueError(f"effect {token!r}: {error}") from None
