"""One step of the rollout (SPEC section 2), and a block of steps: the arithmetic
:func:`torchcf.sim.rollout.simulate` runs, eager or fused by ``torch.compile``
(:mod:`torchcf.sim.compiled`).

A step gathers each cell's observations from the ``(6, N)`` table row of its time
step, perceives (spacing, speeds, the leader's length), asks the model for its
command, scores the position, speed and acceleration errors of the valid steps,
flags invalid rollouts and moves the follower (:func:`realise`: a point mass, or
the model's own update where its acceleration is a state).

Shapes: the state ``(P,)`` (paired layout) or ``(P, N)`` (full); P particles, N
pairs (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from ..models import CFModel, FollowerState, Perception

# Rows of the observation table (T, 6, N).
_X_LEAD, _V_LEAD, _X_FOLLOW, _V_FOLLOW, _A_FOLLOW, _MASK = range(6)


class _Accumulators(NamedTuple):
    """Streaming sums over valid steps, each the state's shape."""

    sq_x: Tensor
    sq_v: Tensor
    sq_a: Tensor
    invalid: Tensor  # bool


def _block(
    model: CFModel,
    paired: bool,
    dt: float,
    leader_length: float,
    record: bool,
    params: Any,
    state: FollowerState,
    acc: _Accumulators,
    memory: Any,
    obs: Tensor,
    pair_index: Tensor | None,
    origin: Tensor | None,
) -> tuple[FollowerState, _Accumulators, Any, Tensor | None]:
    """Advance ``BLOCK_STEPS`` (= ``obs.shape[0]``) steps of SPEC section 2.

    Args:
        model, paired, dt, leader_length, record: static for a compiled block.
        params: the model's prepared Params, fields broadcast to the state.
        state: follower state at the block's first step, ``(P,)`` or ``(P, N)``.
        acc: streaming sums.
        memory: what a stateful controller carries between steps (usually None).
        obs: ``(BLOCK_STEPS, 6, N)`` observation table of the block's steps.
        pair_index: ``(P,)`` pair of each particle in the paired layout, else None.
        origin: road position [m] of each cell's relative frame, broadcastable to
            the state, for models that perceive their road position
            (``model.uses_position``); else None.

    Returns:
        the state after the block, the sums, the memory, and if ``record`` the
        ``(BLOCK_STEPS, 3, *state)`` stack of simulated x, v and recorded a.
    """
    recorded = []
    for obs_step in obs.unbind(0):
        row = _observed(paired, obs_step, pair_index)
        perception = _perceive(leader_length, state, row, origin)
        command, memory = model.command_with_memory(params, perception, memory)
        state, acc, moved = _score_and_move(
            model, dt, record, params, state, acc, command, row
        )
        recorded.append(moved)
    return state, acc, memory, torch.stack(recorded) if record else None


def _observed(paired: bool, obs_step: Tensor, pair_index: Tensor | None) -> Tensor:
    """One step's observations per cell: paired, the columns of each particle's
    pair ``(6, P)``; full, the pairs broadcast over particles ``(6, 1, N)``."""
    return obs_step.index_select(1, pair_index) if paired else obs_step[:, None]


def _perceive(
    leader_length: float, state: FollowerState, row: Tensor, origin: Tensor | None
) -> Perception:
    """What the follower perceives at a step (``row``: :func:`_observed`)."""
    position = state.x + origin if origin is not None else None
    return Perception(
        row[_X_LEAD] - state.x, state.v, row[_V_LEAD], state.a, leader_length, position
    )


def _score_and_move(
    model: CFModel,
    dt: float,
    record: bool,
    params: Any,
    state: FollowerState,
    acc: _Accumulators,
    command: Tensor,
    row: Tensor,
) -> tuple[FollowerState, _Accumulators, Tensor | None]:
    """The step's squared errors and validity added to the sums, then the
    command realised; with ``record`` the step's ``(3, *state)`` x, v, a."""
    x_lead, _, x_obs, v_obs, a_obs, step_valid = row.unbind(0)
    on_valid_step = step_valid > 0.5
    zero = torch.zeros((), dtype=state.x.dtype, device=state.x.device)
    acc_recorded = state.a if model.acceleration_is_state else command
    not_finite = _not_finite(state.x, state.v, acc_recorded)
    # spacing <= 0 is False for NaN, so both tests are needed.
    broken = not_finite | (x_lead - state.x <= 0)
    acc = _Accumulators(
        sq_x=acc.sq_x + torch.where(on_valid_step, (state.x - x_obs) ** 2, zero),
        sq_v=acc.sq_v + torch.where(on_valid_step, (state.v - v_obs) ** 2, zero),
        sq_a=acc.sq_a + torch.where(on_valid_step, (acc_recorded - a_obs) ** 2, zero),
        invalid=acc.invalid | (on_valid_step & broken),
    )
    moved = torch.stack((state.x, state.v, acc_recorded)) if record else None
    return realise(model, params, state, command, dt), acc, moved


def _draft_step(
    model: CFModel,
    paired: bool,
    leader_length: float,
    params: Any,
    state: FollowerState,
    memory: Any,
    obs_step: Tensor,
    pair_index: Tensor | None,
    origin: Tensor | None,
) -> tuple[Any, Any]:
    """A correcting model's step up to its correction (:attr:`CFModel.corrects`):
    the perception and the model's draft."""
    row = _observed(paired, obs_step, pair_index)
    perception = _perceive(leader_length, state, row, origin)
    return model.draft_with_memory(params, perception, memory)


def _finish_step(
    model: CFModel,
    paired: bool,
    dt: float,
    record: bool,
    params: Any,
    state: FollowerState,
    acc: _Accumulators,
    command: Tensor,
    obs_step: Tensor,
    pair_index: Tensor | None,
) -> tuple[FollowerState, _Accumulators, Tensor | None]:
    """A correcting model's step after its correction: :func:`_score_and_move`
    (the step's observations gathered again: inside a fused call, that costs
    less than handing them over)."""
    row = _observed(paired, obs_step, pair_index)
    return _score_and_move(model, dt, record, params, state, acc, command, row)


def _not_finite(x: Tensor, v: Tensor, a: Tensor) -> Tensor:
    """Where any of ``x, v, a`` (same shape) is NaN or +-inf.

    Eager: ``x - x`` is 0 for a finite x and NaN otherwise, so the sum is nonzero
    exactly where one is not finite, at a third of three ``isfinite`` calls on
    small batches. Fused, the compiler may contract ``a*b - a*b`` (the command of a
    model ending in a product: OVM, IDM) into ``fma(a, b, -(a*b))``, the product's
    rounding error, which is nonzero for finite values: on CUDA every such rollout
    came out invalid. A fused block therefore asks ``isfinite``.
    """
    if torch.compiler.is_compiling():
        return ~(torch.isfinite(x) & torch.isfinite(v) & torch.isfinite(a))
    return (x - x) + (v - v) + (a - a) != 0


def realise(
    model: CFModel, params: Any, state: FollowerState, command: Tensor, dt: float
) -> FollowerState:
    """One step of SPEC section 2's state update: the command becomes motion.

    The model's own realisation (``model.advance``: a point mass, HL's or the
    ``lag`` effect's exact first-order lag), then no reversing:
    ``v(t+1) = max(v(t+1), 0)``, ``x(t+1) = max(x(t+1), x(t))``. The rollout and
    :class:`torchcf.HybridSampler` both step through this function.

    Args:
        model: the model.
        params: its prepared parameters (:meth:`CFModel.prepare`), broadcast to
            the state.
        state: the follower at t; position [m], speed [m/s], acceleration [m/s^2].
        command: the command ``u(t)`` [m/s^2], the state's shape.
        dt: step [s].

    Returns:
        the follower at t + 1, the state's shape.
    """
    moved = model.advance(params, state, command, dt)
    # torch.maximum/clamp propagate NaN, so an exploding rollout stays non-finite
    # and is caught as invalid.
    return FollowerState(
        x=torch.maximum(moved.x, state.x),
        v=torch.clamp(moved.v, min=0.0),
        a=moved.a,
    )
