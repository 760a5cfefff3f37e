"""Synthetic leader-follower pairs: known models and effects, for testing the method.

:func:`synthetic_pairs` draws smooth leader speed profiles (a cruise speed, random
sinusoidal fluctuations and braking/re-acceleration events) and drives followers
with a given model — pool model or effect-augmented, e.g. ``"idm+delay"`` — through
:func:`torchcf.simulate`. Calibrating a pool *without* the effect on such data is
how the close-the-loop tests check that the effect is found.

:class:`Gipps` is a follower *outside* the pool (not in the model registry):
data it drives test the loop where no candidate model is the truth, as with a
user's data.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .data import PairSet
from .models import CFModel, get_model
from .models.base import Perception, spec
from .sim import simulate


class GippsParams(NamedTuple):
    a: Tensor
    b: Tensor
    b_lead: Tensor
    v0: Tensor
    tau: Tensor
    size: Tensor


class Gipps(CFModel):
    """Gipps (1981) safe-speed follower, written as an acceleration command.

    Over one reaction time ``tau`` the driver reaches the smaller of a free-road
    speed and the largest speed from which it can still stop behind a leader that
    brakes at ``b_lead``:

    ``v_free = v + 2.5 a tau (1 - v / v0) sqrt(0.025 + v / v0)``,
    ``v_safe = -b tau + sqrt(b^2 tau^2 + b (2 (s - size) - v tau
    + v_lead^2 / b_lead))``,
    ``u = (max(0, min(v_free, v_safe)) - v) / tau`` [m/s^2],

    ``s`` the front-to-front spacing [m] and ``size`` the leader's effective
    length with the standstill margin [m]; a negative root argument (a spacing
    too short to stop) reads 0. Not in the registry: no pool model is Gipps, so
    it stands for the unknown truth of measured data.
    """

    name = "gipps"
    Params = GippsParams
    param_specs = (
        spec("a", "m/s^2", 0.5, 3.0, "maximum acceleration"),
        spec("b", "m/s^2", 1.0, 5.0, "most severe braking the driver plans"),
        spec("b_lead", "m/s^2", 1.0, 5.0, "the driver's estimate of the leader's"),
        spec("v0", "m/s", 15.0, 40.0, "desired speed"),
        spec("tau", "s", 0.3, 1.5, "reaction time (the update period)"),
        spec("size", "m", 4.0, 10.0, "leader length plus standstill margin"),
    )

    def command(self, p: GippsParams, obs: Perception) -> Tensor:
        v = obs.v
        ratio = torch.clamp(v / p.v0, min=0.0)
        v_free = v + 2.5 * p.a * p.tau * (1.0 - ratio) * torch.sqrt(0.025 + ratio)
        root = (p.b * p.tau) ** 2 + p.b * (
            2.0 * (obs.spacing - p.size) - v * p.tau + obs.v_lead**2 / p.b_lead
        )
        v_safe = -p.b * p.tau + torch.sqrt(torch.clamp(root, min=0.0))
        target = torch.clamp(torch.minimum(v_free, v_safe), min=0.0)
        return (target - v) / p.tau


def leader_profiles(
    n_pairs: int,
    n_steps: int,
    dt: float = 0.1,
    *,
    seed: int = 0,
    cruise: tuple[float, float] = (10.0, 22.0),
    start: tuple[float, float] = (0.0, 0.0),
) -> tuple[Tensor, Tensor, Tensor]:
    """Leader position, speed and acceleration, ``(T, N)`` float64 each (T =
    ``n_steps``, N = ``n_pairs``).

    Speed = cruise + three random sinusoids (periods 8-40 s, amplitudes 0.5-2.5
    m/s) + two braking events (a 1.5-3 m/s^2 deceleration for 1-2.5 s, then
    recovery over three times as long), clamped at 0. Position is integrated with
    the trapezoidal rule.

    Args:
        cruise: range of the cruise speed [m/s].
        start: range of the leader's initial road position [m].
    """
    g = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float, *shape: int) -> Tensor:
        return low + (high - low) * torch.rand(*shape, generator=g, dtype=torch.float64)

    t = torch.arange(n_steps, dtype=torch.float64)[:, None] * dt  # (T, 1)
    speed = uniform(*cruise, 1, n_pairs).expand(n_steps, n_pairs).clone()
    for _ in range(3):
        period = uniform(8.0, 40.0, 1, n_pairs)
        amplitude = uniform(0.5, 2.5, 1, n_pairs)
        phase = uniform(0.0, 2 * math.pi, 1, n_pairs)
        speed += amplitude * torch.sin(2 * math.pi * t / period + phase)
    duration_total = n_steps * dt
    for _ in range(2):
        onset = uniform(0.15, 0.75, 1, n_pairs) * duration_total
        length = uniform(1.0, 2.5, 1, n_pairs)
        rate = uniform(1.5, 3.0, 1, n_pairs)
        # Speed drop ramps down over `length` s, recovers over 3x as long.
        down = torch.clamp((t - onset) / length, 0.0, 1.0)
        up = torch.clamp((t - onset - length) / (3.0 * length), 0.0, 1.0)
        speed -= rate * length * (down - up)
    speed = speed.clamp(min=0.0)
    acceleration = torch.gradient(speed, spacing=dt, dim=0)[0]
    position = uniform(*start, 1, n_pairs) + torch.cat(
        (
            torch.zeros(1, n_pairs, dtype=torch.float64),
            torch.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt, dim=0),
        )
    )
    return position, speed, acceleration


def synthetic_pairs(
    model: str | CFModel,
    theta: Tensor | Sequence[float],
    n_pairs: int,
    n_steps: int = 500,
    dt: float = 0.1,
    *,
    seed: int = 0,
    initial_gap: tuple[float, float] = (1.0, 2.0),
    noise: float = 0.0,
    start: tuple[float, float] = (0.0, 0.0),
    name: str = "synthetic",
) -> PairSet:
    """Pairs whose followers are driven by ``model`` with parameters ``theta``.

    Args:
        model: registry name, effects allowed (``"idm+delay"``), or a model
            object (e.g. :class:`Gipps`, or one wrapped by effects:
            ``AugmentedModel(Gipps(), [parse_effect("delay")])``).
        theta: ``(K,)`` one particle for every pair, or ``(N, K)`` (N = ``n_pairs``),
            one per pair.
        initial_gap: range of the initial time gap [s]; the follower starts at
            the leader's speed, ``gap * v + 8`` m behind it.
        noise: standard deviation of white noise added to the recorded follower
            position [m] (speed and acceleration get ``noise / dt`` and
            ``noise / dt^2`` scaled by 0.1 and 0.01: measurement-like, small).
        start: range of the leaders' initial road positions [m].

    Returns:
        A PairSet named ``name``; ``notes`` record the generating model.
    """
    cf_model = get_model(model)
    theta = torch.as_tensor(theta, dtype=torch.float64)
    if theta.ndim == 1:
        theta = theta[None].expand(n_pairs, -1)
    x_lead, v_lead, a_lead = leader_profiles(
        n_pairs, n_steps, dt, seed=seed, start=start
    )
    g = torch.Generator().manual_seed(seed + 1)
    gap = initial_gap[0] + (initial_gap[1] - initial_gap[0]) * torch.rand(
        n_pairs, generator=g, dtype=torch.float64
    )
    x_follow0 = x_lead[0] - gap * v_lead[0] - 8.0
    # A leader-only placeholder set: the follower's first row is its start state.
    seed_set = PairSet.from_arrays(
        x_lead,
        v_lead,
        a_lead,
        x_follow0[None].expand(n_steps, -1),
        v_lead[0][None].expand(n_steps, -1),
        torch.zeros(n_steps, n_pairs, dtype=torch.float64),
        dt=dt,
    )
    out = simulate(
        cf_model,
        theta,
        seed_set,
        torch.arange(n_pairs),
        dtype=torch.float64,
        return_traj=True,
    )
    if not bool(out.valid.all()):
        raise ValueError(
            f"{cf_model.name}: some synthetic followers crash; change theta"
        )
    x, v, a = out.x, out.v, out.a
    if noise > 0:
        x = x + noise * torch.randn(x.shape, generator=g, dtype=torch.float64)
        v = v + 0.1 * noise / dt * torch.randn(x.shape, generator=g, dtype=x.dtype)
        a = a + 0.01 * noise / dt**2 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    return PairSet.from_arrays(
        x_lead,
        v_lead,
        a_lead,
        x,
        v,
        a,
        dt=dt,
        name=name,
        notes=(f"followers: {cf_model.name} theta={theta[0].tolist()}",),
    )
