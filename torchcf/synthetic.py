"""Synthetic leader-follower pairs: known models and effects, for testing the method.

:func:`synthetic_pairs` draws smooth leader speed profiles (a cruise speed, random
sinusoidal fluctuations and braking/re-acceleration events) and drives followers
with a given model — pool model or effect-augmented, e.g. ``"idm+delay"`` — through
:func:`torchcf.simulate`. Calibrating a pool *without* the effect on such data is
how the close-the-loop tests check that the effect is found.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from .data import PairSet
from .models import get_model
from .sim import simulate


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
    model: str,
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
        model: registry name, effects allowed (``"idm+delay"``).
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
        raise ValueError(f"{model}: some synthetic followers crash; change theta")
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
