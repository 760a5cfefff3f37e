"""Steady states of a model's particles: the spacing it keeps at a speed.

A follower behind a leader driving at its own speed ``v`` settles where its
command vanishes: ``u(s, v, v_lead = v, a = 0) = 0``. The spacing ``s_e(v)`` that
solves it is the model's *equilibrium spacing*; its slope over speed is the
*time gap* the model keeps, and ``s_e`` at a speed is what a spacing-sensor
offset or a clock offset between two logs trades against (an offset of ``d``
shifts ``s_e`` by ``-d``, a leader log ``t`` ahead lengthens the time gap by
``t``). :func:`equilibrium_spacing` finds ``s_e`` by bisection for every particle
of any model, pool or augmented, from a steady past (a delay's history filled
with the steady perception).

Shapes: P particles, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .base import CFModel, Perception

#: Bisection steps of :func:`equilibrium_spacing` (error ``s_max / 2^steps``).
BISECTION_STEPS = 40


def steady_command(
    model: CFModel,
    theta: Tensor,
    spacing: Tensor,
    v: Tensor,
    *,
    leader_length: float,
    dt: float,
) -> Tensor:
    """(P,) the command [m/s^2] of particles ``theta`` (P, K) at a steady state:
    spacing ``spacing`` [m] and own speed ``v`` [m/s] (each (P,)), the leader at
    the same speed, no acceleration, the model's memory that of a steady past,
    road position 0 (a road effect reads its profile there)."""
    p = model.prepare(model.unpack(theta), dt, (theta.shape[0],))
    zero = torch.zeros_like(v)
    obs = Perception(spacing, v, v, zero, leader_length, zero)
    memory = model.initial_memory(p, obs)
    command, _ = model.command_with_memory(p, obs, memory)
    return command


def equilibrium_spacing(
    model: CFModel,
    theta: Tensor,
    v: float | Tensor,
    *,
    leader_length: float = 5.0,
    dt: float = 0.1,
    s_max: float = 500.0,
) -> Tensor:
    """(P,) float64 the spacing [m] each particle keeps behind a leader at its own
    speed ``v`` [m/s] (a number or (P,)): the root of ``u(s) = 0`` on ``[0,
    s_max]`` (the command grows with the spacing), NaN where the command keeps
    one sign there (no equilibrium at that speed: a desired speed below ``v``,
    or a model that still accelerates at standstill)."""
    theta = theta.to(torch.float64)
    n = theta.shape[0]
    v = torch.as_tensor(v, dtype=torch.float64).expand(n).clone()
    low = torch.zeros(n, dtype=torch.float64)
    high = torch.full((n,), s_max, dtype=torch.float64)

    def command(spacing: Tensor) -> Tensor:
        u = steady_command(model, theta, spacing, v, leader_length=leader_length, dt=dt)
        return torch.nan_to_num(u, nan=-math.inf)

    bracketed = (command(low) <= 0) & (command(high) > 0)
    for _ in range(BISECTION_STEPS):
        middle = 0.5 * (low + high)
        above = command(middle) > 0
        low, high = torch.where(above, low, middle), torch.where(above, middle, high)
    return torch.where(bracketed, 0.5 * (low + high), math.nan)


def time_gap(
    model: CFModel,
    theta: Tensor,
    v: float | Tensor,
    *,
    leader_length: float = 5.0,
    dt: float = 0.1,
    step: float = 1.0,
) -> Tensor:
    """(P,) float64 the time gap [s] each particle keeps at speed ``v``: the slope
    ``(s_e(v + step) - s_e(v - step)) / (2 step)`` of its equilibrium spacing
    (one-sided from 0 where ``v < step``)."""
    v = torch.as_tensor(v, dtype=torch.float64)
    run = {"leader_length": leader_length, "dt": dt}
    above, below = v + step, (v - step).clamp(min=0.0)  # no speed below 0
    upper = equilibrium_spacing(model, theta, above, **run)
    lower = equilibrium_spacing(model, theta, below, **run)
    return (upper - lower) / (above - below)


__all__ = [
    "BISECTION_STEPS",
    "equilibrium_spacing",
    "steady_command",
    "time_gap",
]
