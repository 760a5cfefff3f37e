"""Plausibility of learned particles: a battery of closed-loop scenarios.

A particle fitted to 35-58 s of one measured pair is constrained only where
that pair drove. Embedded in traffic it meets situations the data never
showed: a leader braking hard to a stop, stop-and-go waves, a car cutting in
close, a start from standstill, a platoon of its own kind. This module drives
every particle of a model through such scenarios at once, on the traffic
engine (:func:`torchcf.traffic.platoon` without its safety layer: the
calibration rollout's step, one sampler call per step for all particles), and
reports per particle what happened:

================  =====================================================================
scenario          what the leader does (the follower starts at its own equilibrium
                  spacing at ``speed``, or at the end of its search where it has none)
================  =====================================================================
``brake_<d>``     cruises at ``speed`` for ``CRUISE`` s, brakes at ``d`` m/s^2 to a
                  stop and stands (one scenario per deceleration in ``decelerations``)
``stop_and_go``   ``v(t) = speed / 2 (1 - cos(2 pi t / STOP_GO_PERIOD))``: from
                  ``speed`` to a stop and back, ``STOP_GO_CYCLES`` times
``cut_in``        a car cuts in ``CUT_IN_GAP`` s (net time gap) ahead of the follower
                  at ``speed``, ``CUT_IN_DV`` m/s slower, and keeps that speed
``standstill``    both stand ``STANDSTILL_GAP`` m apart (net); the leader pulls away
                  at 2 m/s^2 to ``speed``
``string``        ``platoon_size`` vehicles of the particle at its equilibrium follow
                  a leader whose speed dips by ``STRING_DIP`` m/s and recovers
================  =====================================================================

Outcomes per particle (:class:`Plausibility`): whether it **collided** in any
scenario but ``string`` (the spacing fell to ``collision_spacing`` or below, or
the state blew up), the **minimum time to collision** ``(s - s_c) / (v -
v_lead)`` over the steps where it closed in, the **string-stability ratio**
``(max_t |v_n - speed| / max_t |v_1 - speed|)^(1 / (n - 1))`` of the platoon
(the mean amplification per vehicle: above 1 a disturbance grows down the
string), whether it has an **equilibrium** (a spacing where the steady command
``u(s, v, v, 0)`` crosses zero) at every speed of ``EQUILIBRIUM_SPEEDS`` up to
``speed``, and whether it **started** from standstill (reached half the
leader's speed within the scenario).

**Spacing.** As everywhere in torchcf, spacing is front-to-front (SPEC section
1); ``collision_spacing`` 0 is the traffic module's collision (the follower's
front reaches the leader's front). Bumper contact happens a vehicle length
earlier: pass ``collision_spacing = leader_length`` for it. (IDM as SPEC writes
it keeps ``s0`` of 0.5-3 m front-to-front at standstill: it would "touch" in
every stop by that criterion.)

Shapes: P particles, T steps of the data's ``dt``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from ..models import CFModel, FollowerState, require_model
from ..runs.summary import PlausibilitySettings, PlausibilitySummary
from .sampler import HybridSampler
from .scenarios import platoon

#: Seconds of cruising before a braking event.
CRUISE = 5.0
#: Seconds the leader stands after stopping (the follower must stop too).
STAND = 15.0
#: Period [s] and number of stop-and-go cycles.
STOP_GO_PERIOD, STOP_GO_CYCLES = 30.0, 3
#: Net time gap [s] at which the car cuts in, and how much slower it is [m/s].
CUT_IN_GAP, CUT_IN_DV = 0.5, 3.0
#: Net gap [m] of the standstill start.
STANDSTILL_GAP = 2.0
#: Speed dip [m/s] of the string-stability leader, its duration [s].
STRING_DIP, STRING_DIP_SECONDS = 1.0, 4.0
#: Seconds every single-follower scenario runs after its event.
SETTLE = 20.0
#: Speeds [m/s] (up to the battery's ``speed``) at which an equilibrium must exist.
EQUILIBRIUM_SPEEDS = (1.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0)
#: Upper end [m] of the equilibrium search, in net gap over the speed: ``10 +
#: 4 s * v`` (a follower that keeps more at equilibrium is not following).
EQUILIBRIUM_REACH = (10.0, 4.0)


@dataclass(frozen=True)
class Battery:
    """The scenarios' settings.

    Attributes:
        speed: cruise speed [m/s] of the scenarios (from the data:
            :func:`battery_speed`).
        decelerations: the emergency-braking leader's decelerations [m/s^2].
        collision_spacing: front-to-front spacing [m] at or below which a
            follower has collided (0: the traffic module's criterion).
        platoon_size: vehicles in the string-stability platoon (>= 2).
        dt: step [s] (the data's).
        leader_length: the leader length [m] the models perceive (net gaps
            above are added to it).

    Examples:
        >>> from torchcf.traffic import Battery
        >>> battery = Battery(speed=10.0, decelerations=(4.0, 8.0))  # [m/s], [m/s^2]
        >>> battery.scenarios
        ['brake_4', 'brake_8', 'stop_and_go', 'cut_in', 'standstill']
    """

    speed: float = 25.0
    decelerations: tuple[float, ...] = (4.0, 6.0, 8.0)
    collision_spacing: float = 0.0
    platoon_size: int = 10
    dt: float = 0.1
    leader_length: float = 5.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed) and self.speed > 0):
            raise ValueError(f"speed must be > 0 m/s, got {self.speed}")
        if not self.decelerations or not all(
            math.isfinite(d) and d > 0 for d in self.decelerations
        ):
            raise ValueError(
                f"decelerations must be positive m/s^2, got {self.decelerations}"
            )
        if not (math.isfinite(self.collision_spacing) and self.collision_spacing >= 0):
            raise ValueError(
                f"collision_spacing must be >= 0 m, got {self.collision_spacing}"
            )
        if not (isinstance(self.platoon_size, int) and self.platoon_size >= 2):
            raise ValueError(
                f"platoon_size must be an int >= 2, got {self.platoon_size}"
            )
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be > 0 s, got {self.dt}")

    @property
    def scenarios(self) -> list[str]:
        """The collision scenarios' names, in order."""
        brakes = [f"brake_{d:g}" for d in self.decelerations]
        return [*brakes, "stop_and_go", "cut_in", "standstill"]


@dataclass
class Plausibility:
    """A model's particles through the battery; every tensor is ``(P,)``.

    Attributes:
        collided: collided in some scenario (``string`` excluded).
        scenario_collided: per scenario name, collided there.
        min_ttc: least time to collision [s] over the collision scenarios
            (inf: never closed in).
        min_spacing: least front-to-front spacing [m] there.
        string_ratio: the platoon's amplification per vehicle (NaN: no
            equilibrium at ``speed`` to start from, or the platoon collided).
        equilibrium: an equilibrium at every speed of the grid.
        started: pulled away from standstill.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.traffic import Battery, check_plausibility
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> battery = Battery(speed=10.0, decelerations=(6.0,), platoon_size=3)
        >>> found = check_plausibility(get_model("idm"), idm, battery)
        >>> found.n_particles, found.collided.tolist(), found.equilibrium.tolist()
        (2, [False, False], [True, True])
        >>> found.string_unstable().tolist()  # a 3-vehicle platoon at 10 m/s
        [False, False]
    """

    collided: Tensor
    scenario_collided: dict[str, Tensor]
    min_ttc: Tensor
    min_spacing: Tensor
    string_ratio: Tensor
    equilibrium: Tensor
    started: Tensor
    settings: Battery = field(default_factory=Battery)

    @property
    def n_particles(self) -> int:
        return int(self.collided.numel())

    def string_unstable(self) -> Tensor:
        """``(P,)`` bool: a disturbance grows down the platoon (ratio > 1)."""
        return self.string_ratio > 1.0

    def string_untested(self) -> Tensor:
        """``(P,)`` bool: no ratio (no equilibrium at the speed to start the
        platoon from, or the platoon collided)."""
        return torch.isnan(self.string_ratio)

    def summary(self) -> PlausibilitySummary:
        """The shares over the particles (fractions in [0, 1])."""
        n = max(self.n_particles, 1)

        def share(flags: Tensor) -> float:
            return float(flags.sum()) / n

        finite_ttc = self.min_ttc[torch.isfinite(self.min_ttc)]
        ratio = self.string_ratio[torch.isfinite(self.string_ratio)]
        return PlausibilitySummary(
            n_particles=self.n_particles,
            collided=share(self.collided),
            per_scenario={k: share(v) for k, v in self.scenario_collided.items()},
            string_unstable=share(self.string_unstable()),
            string_untested=share(self.string_untested()),
            no_equilibrium=share(~self.equilibrium),
            not_started=share(~self.started),
            min_ttc_median=float(finite_ttc.median()) if finite_ttc.numel() else None,
            string_ratio_median=float(ratio.median()) if ratio.numel() else None,
            settings=PlausibilitySettings(
                speed=self.settings.speed,
                decelerations=tuple(self.settings.decelerations),
                collision_spacing=self.settings.collision_spacing,
                platoon_size=self.settings.platoon_size,
            ),
        )


def battery_speed(v_lead: Tensor, mask: Tensor | None = None) -> float:
    """The battery's cruise speed from the data: the 95th percentile of the
    leaders' speeds [m/s] (``v_lead`` (T, N), over ``mask``'s valid steps),
    at least 5 m/s.

    Examples:
        >>> import torch
        >>> from torchcf.traffic import battery_speed
        >>> v_lead = torch.tensor([[10.0, 20.0], [15.0, 25.0]])  # (T, N) [m/s]
        >>> round(battery_speed(v_lead), 3)  # the 95th percentile [m/s]
        24.25
    """
    speeds = v_lead[mask] if mask is not None else v_lead.reshape(-1)
    speeds = speeds[torch.isfinite(speeds)].double()
    if speeds.numel() == 0:
        raise ValueError("no leader speed to set the battery's speed from")
    return max(5.0, float(torch.quantile(speeds, 0.95)))


# -------------------------------------------------------------------- leaders
def _steps(seconds: float, dt: float) -> int:
    return int(round(seconds / dt))


def _times(seconds: float, dt: float) -> Tensor:
    """(T,) float64 times [s] of the steps from 0 to ``seconds``."""
    return torch.arange(_steps(seconds, dt) + 1, dtype=torch.float64) * dt


def leader_positions(v: Tensor, dt: float) -> Tensor:
    """Leader positions (T,) [m] from speeds (T,), trapezoidal, from 0."""
    step = 0.5 * (v[1:] + v[:-1]) * dt
    return torch.cat((v.new_zeros(1), torch.cumsum(step, 0)))


def braking_leader(
    speed: float, decel: float, dt: float, cruise: float = CRUISE, stand: float = STAND
) -> Tensor:
    """(T,) float64 speed [m/s]: ``cruise`` s at ``speed``, braking at
    ``decel`` to 0, ``stand`` s standing."""
    t = _times(cruise + speed / decel + stand, dt)
    return torch.clamp(speed - decel * torch.clamp(t - cruise, min=0.0), min=0.0)


def stop_and_go_leader(speed: float, dt: float) -> Tensor:
    """(T,) speed [m/s]: from ``speed`` to 0 and back, ``STOP_GO_CYCLES`` times."""
    t = _times(STOP_GO_CYCLES * STOP_GO_PERIOD, dt)
    return speed / 2 * (1 + torch.cos(2 * math.pi * t / STOP_GO_PERIOD))


def string_leader(speed: float, dt: float) -> Tensor:
    """(T,) speed [m/s]: ``speed`` with a smooth dip of ``STRING_DIP``."""
    t = _times(CRUISE + STRING_DIP_SECONDS + 3 * SETTLE, dt)
    phase = torch.clamp((t - CRUISE) / STRING_DIP_SECONDS, 0.0, 1.0)
    return speed - STRING_DIP * torch.sin(math.pi * phase) ** 2


def standstill_leader(speed: float, dt: float) -> Tensor:
    """(T,) speed [m/s]: stands 2 s, then 2 m/s^2 up to ``speed``."""
    t = _times(2.0 + speed / 2.0 + SETTLE, dt)
    return torch.clamp(2.0 * (t - 2.0), 0.0, speed)


# ------------------------------------------------------------------ the battery
def check_plausibility(
    model: CFModel,
    theta: Tensor,
    battery: Battery = Battery(),
    *,
    chunk: int = 1 << 14,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Plausibility:
    """Every particle of one model through the battery.

    Args:
        model: the model object (``torchcf.get_model("idm")``, effects
            allowed); a name raises :class:`TypeError`.
        theta: ``(P, K)`` particles in the model's parameter order (SI).
        battery: the scenarios' settings.
        chunk: particles simulated at once (memory: about ``chunk x T``
            values per recorded field).
        dtype: float64 (default) or float32.
        device: where to simulate (default: ``theta``'s).

    Returns:
        :class:`Plausibility`, ``(P,)`` per outcome, on the CPU.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.traffic import Battery, check_plausibility
        >>> idm = torch.tensor(
        ...     [[1.5, 2.0, 33.0, 1.2, 2.0, 4.0], [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]]
        ... )
        >>> battery = Battery(speed=10.0, decelerations=(6.0,), platoon_size=3)
        >>> found = check_plausibility(get_model("idm"), idm, battery)
        >>> found.collided.tolist(), found.started.tolist()
        ([False, False], [True, True])
        >>> summary = found.summary()
        >>> summary.n_particles, summary.collided, summary.per_scenario["brake_6"]
        (2, 0.0, 0.0)
    """
    model = require_model(model, "check_plausibility")
    theta = _particles(model, theta, chunk)
    device = theta.device if device is None else torch.device(device)
    parts = [
        _chunk(model, theta[i : i + chunk].to(device, dtype), battery)
        for i in range(0, theta.shape[0], chunk)
    ]
    if not parts:
        empty = torch.zeros(0, dtype=torch.bool)
        return Plausibility(
            empty,
            {k: empty for k in battery.scenarios},
            torch.zeros(0, dtype=torch.float64),
            torch.zeros(0, dtype=torch.float64),
            torch.zeros(0, dtype=torch.float64),
            empty,
            empty,
            battery,
        )
    return Plausibility(
        collided=torch.cat([p.collided for p in parts]),
        scenario_collided={
            k: torch.cat([p.scenario_collided[k] for p in parts])
            for k in battery.scenarios
        },
        min_ttc=torch.cat([p.min_ttc for p in parts]),
        min_spacing=torch.cat([p.min_spacing for p in parts]),
        string_ratio=torch.cat([p.string_ratio for p in parts]),
        equilibrium=torch.cat([p.equilibrium for p in parts]),
        started=torch.cat([p.started for p in parts]),
        settings=battery,
    )


def _particles(model: CFModel, theta: Tensor, chunk: int) -> Tensor:
    """The ``(P, K)`` particles of a battery call, checked against the model."""
    theta = torch.as_tensor(theta)
    if theta.ndim != 2 or theta.shape[1] != model.n_params:
        raise ValueError(
            f"{model.name}: theta must be (P, {model.n_params}), "
            f"got {tuple(theta.shape)}"
        )
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    return theta


def _sampler(model: CFModel, theta: Tensor, battery: Battery, n: int) -> HybridSampler:
    """A sampler whose row p of ``(P, n)`` vehicles all drive particle p."""
    sampler = HybridSampler(
        [model],
        [theta],
        dt=battery.dt,
        leader_length=battery.leader_length,
        dtype=theta.dtype,
    ).to(theta.device)
    rows = torch.arange(theta.shape[0], device=theta.device)
    sampler.assign(rows[:, None].expand(-1, n))
    return sampler


def equilibrium_gap(sampler: HybridSampler, speed: float) -> tuple[Tensor, Tensor]:
    """Each row's steady spacing at ``speed`` ``(P,)`` [m], and whether it is
    one (the command crosses zero inside the search)."""
    low = 0.1
    high = EQUILIBRIUM_REACH[0] + sampler.leader_length + EQUILIBRIUM_REACH[1] * speed
    spacing = sampler.equilibrium_spacing(speed, s_min=low, s_max=high)[:, 0]
    tol = 1e-6 * high
    found = (spacing > low + tol) & (spacing < high - tol)
    return spacing, found


def _run(
    sampler: HybridSampler, v_leader: Tensor, gap: Tensor, v0: float
) -> tuple[Tensor, Tensor, Tensor]:
    """One single-follower scenario: the leader ``(T,)`` for every row,
    follower 0 ``gap`` ``(P,)`` behind at ``v0``. Returns spacing, follower
    speed and leader speed, ``(T, P)`` each."""
    n_rows = gap.shape[0]
    v_lead = v_leader.to(gap)[:, None].expand(-1, n_rows)
    x_lead = leader_positions(v_leader.to(gap), sampler.dt)[:, None].expand(-1, n_rows)
    start = FollowerState(-gap, torch.full_like(gap, v0), torch.zeros_like(gap))
    sampler.reset_memory()
    out = platoon(
        sampler, x_lead.contiguous(), v_lead.contiguous(), start=start, safety=None
    )
    return out.spacing[:, :, 0], out.v[:, :, 0], v_lead


def _closing(spacing: Tensor, v: Tensor, v_lead: Tensor, s_c: float) -> tuple:
    """(collided, min time to collision, min spacing), ``(P,)`` each."""
    collided = ~(spacing > s_c).all(0)  # NaN counts
    closing = v - v_lead
    ttc = torch.where(
        closing > 0, (spacing - s_c) / closing, torch.full_like(spacing, math.inf)
    )
    ttc = torch.where(torch.isnan(ttc), torch.zeros_like(ttc), ttc.clamp(min=0.0))
    least = torch.where(
        torch.isnan(spacing), torch.full_like(spacing, -math.inf), spacing
    )
    return collided, ttc.min(0).values, least.min(0).values


class _Scenario(NamedTuple):
    """A single-follower collision scenario: the leader's speed ``(T,)`` [m/s],
    the follower's start gap ``(P,)`` [m] (front to front) and speed [m/s]."""

    name: str
    v_leader: Tensor
    start_gap: Tensor
    v0: float


def _collision_scenarios(battery: Battery, gap: Tensor) -> list[_Scenario]:
    """The battery's collision scenarios in :attr:`Battery.scenarios` order;
    ``gap`` ``(P,)`` is each particle's equilibrium spacing at the speed."""
    speed, dt = battery.speed, battery.dt
    brakes = [
        _Scenario(f"brake_{d:g}", braking_leader(speed, d, dt), gap, speed)
        for d in battery.decelerations
    ]
    cut_in = torch.full(
        (_steps(SETTLE, dt) + 1,), speed - CUT_IN_DV, dtype=torch.float64
    )
    cut_in_gap = torch.full_like(gap, battery.leader_length + CUT_IN_GAP * speed)
    standstill_gap = torch.full_like(gap, battery.leader_length + STANDSTILL_GAP)
    return [
        *brakes,
        _Scenario("stop_and_go", stop_and_go_leader(speed, dt), gap, speed),
        _Scenario("cut_in", cut_in, cut_in_gap, speed),
        _Scenario("standstill", standstill_leader(speed, dt), standstill_gap, 0.0),
    ]


def collides(
    model: CFModel,
    theta: Tensor,
    battery: Battery = Battery(),
    *,
    chunk: int = 1 << 14,
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """``(P,)`` bool: the particles that collide in some scenario of the
    battery, as ``check_plausibility(...).collided`` says, for the calibration's
    filter at a fraction of its cost.

    It runs the collision scenarios alone (no string-stability platoon, no
    equilibrium sweep, no time to collision), the hardest first (the largest
    braking deceleration), and each scenario only for the particles that have
    not collided yet: a model whose particles mostly fail the first scenario
    (MPC, whose deceleration limit is 3-5 m/s^2) costs about one scenario.
    """
    model = require_model(model, "collides")
    theta = _particles(model, theta, chunk)
    parts = [
        _collides_chunk(model, theta[i : i + chunk].to(dtype), battery)
        for i in range(0, theta.shape[0], chunk)
    ]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.bool)


def _collides_chunk(model: CFModel, theta: Tensor, battery: Battery) -> Tensor:
    gap, _ = equilibrium_gap(_sampler(model, theta, battery, 1), battery.speed)
    scenarios = _collision_scenarios(battery, gap)
    # Hardest braking first: it removes the most particles from the rest.
    hardest = sorted(battery.decelerations, reverse=True)
    brakes = {f"brake_{d:g}": rank for rank, d in enumerate(hardest)}
    scenarios.sort(key=lambda s: brakes.get(s.name, len(brakes)))
    collided = torch.zeros(theta.shape[0], dtype=torch.bool, device=theta.device)
    for scenario in scenarios:
        alive = (~collided).nonzero().squeeze(1)
        if alive.numel() == 0:
            break
        sampler = _sampler(model, theta[alive], battery, 1)
        spacing, v, v_lead = _run(
            sampler, scenario.v_leader, scenario.start_gap[alive], scenario.v0
        )
        collided[alive] = _closing(spacing, v, v_lead, battery.collision_spacing)[0]
    return collided.cpu()


def _chunk(model: CFModel, theta: Tensor, battery: Battery) -> Plausibility:
    """One chunk of particles through the battery."""
    speed = battery.speed
    single = _sampler(model, theta, battery, 1)
    gap, has_gap = equilibrium_gap(single, speed)
    scenario: dict[str, Tensor] = {}
    ttc, least = [], []
    for name, v_leader, start_gap, v0 in _collision_scenarios(battery, gap):
        spacing, v, v_lead = _run(single, v_leader, start_gap, v0)
        collided, t, s = _closing(spacing, v, v_lead, battery.collision_spacing)
        scenario[name] = collided.cpu()
        ttc.append(t)
        least.append(s)
    # v: the standstill scenario's follower, the last one run
    started = (v.nan_to_num(0.0).max(0).values >= 0.5 * speed).cpu()

    equilibrium = torch.ones_like(has_gap)
    for v_eq in (s for s in EQUILIBRIUM_SPEEDS if s <= speed):
        equilibrium &= equilibrium_gap(single, v_eq)[1]

    collided = torch.stack(list(scenario.values())).any(0)
    return Plausibility(
        collided=collided,
        scenario_collided=scenario,
        min_ttc=torch.stack(ttc).min(0).values.double().cpu(),
        min_spacing=torch.stack(least).min(0).values.double().cpu(),
        string_ratio=_string_ratio(model, theta, battery, gap, has_gap),
        equilibrium=equilibrium.cpu(),
        started=started,
        settings=battery,
    )


def _string_unstable(
    model: CFModel, theta: Tensor, battery: Battery, chunk: int = 1 << 14
) -> Tensor:
    """``(P,)`` bool: the string-stability ratio is over 1 (in chunks of
    ``chunk`` particles: the platoon records every vehicle's speed)."""
    parts = []
    for i in range(0, theta.shape[0], chunk):
        part = theta[i : i + chunk].to(torch.float64)
        gap, has_gap = equilibrium_gap(_sampler(model, part, battery, 1), battery.speed)
        parts.append(_string_ratio(model, part, battery, gap, has_gap) > 1.0)
    return torch.cat(parts)


def _string_ratio(
    model: CFModel, theta: Tensor, battery: Battery, gap: Tensor, has_gap: Tensor
) -> Tensor:
    """``(P,)`` amplification per vehicle of the speed dip down the platoon."""
    n = battery.platoon_size
    sampler = _sampler(model, theta, battery, n)
    v_leader = string_leader(battery.speed, battery.dt).to(gap)
    rows = gap.shape[0]
    x_lead = (
        leader_positions(v_leader, battery.dt)[:, None].expand(-1, rows).contiguous()
    )
    v_lead = v_leader[:, None].expand(-1, rows).contiguous()
    start = FollowerState(
        -gap, torch.full_like(gap, battery.speed), torch.zeros_like(gap)
    )
    out = platoon(sampler, x_lead, v_lead, start=start, safety=None)
    deviation = (out.v - battery.speed).abs().amax(0)  # (P, n)
    first, last = deviation[:, 0], deviation[:, -1]
    ratio = (last / first.clamp(min=1e-9)) ** (1.0 / (n - 1))
    ok = has_gap & out.valid & torch.isfinite(ratio)
    return torch.where(ok, ratio, torch.full_like(ratio, math.nan)).double().cpu()


def plausibility_by_model(
    particles: Mapping[CFModel, Tensor], battery: Battery
) -> dict[str, PlausibilitySummary]:
    """:meth:`Plausibility.summary` per model of a learned set (model ->
    ``(P_m, K_m)`` particles), by model name; models without particles left
    out."""
    return {
        model.name: check_plausibility(model, theta, battery).summary()
        for model, theta in particles.items()
        if theta.shape[0]
    }


def rejects(battery: Battery, reject_string_unstable: bool = False):
    """``(model, theta (Q, K)) -> (Q,) bool``: the particles that collide in
    the battery (or, if asked, are string-unstable), for the calibration's
    plausibility filter (:class:`torchcf.abc.screen.PlausibilityScreen`)."""

    def implausible(model: CFModel, theta: Tensor) -> Tensor:
        collided = collides(model, theta, battery)
        if reject_string_unstable and not collided.all():
            rest = (~collided).nonzero().squeeze(1)
            collided[rest] = _string_unstable(model, theta[rest], battery)
        return collided

    return implausible


__all__ = [
    "Battery",
    "Plausibility",
    "battery_speed",
    "braking_leader",
    "check_plausibility",
    "collides",
    "equilibrium_gap",
    "leader_positions",
    "plausibility_by_model",
    "rejects",
    "stop_and_go_leader",
    "standstill_leader",
    "string_leader",
]
