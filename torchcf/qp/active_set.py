"""BoxQP's leading-block stage: primal-dual active-set passes on leading blocks.

Each pass solves the working set exactly on its guessed active set
(:mod:`torchcf.qp.leading`), accepts the instances whose solution satisfies the KKT
conditions to round-off, and moves the guess of the others by one primal-dual
active-set step (Hintermueller, Ito & Kunisch 2002, "The primal-dual active set
strategy as a semismooth Newton method"): free the bounds with a wrong-signed
multiplier, fix the bounds ``x`` violates. An instance leaves the stage, handed on
to the general exact solves (:func:`torchcf.qp.polish.active_set_solves`) with its
current guess, once its guess is not a leading block or it runs out of passes.

Shapes: ``n`` variables, ``B`` instances of the call, ``b`` those of a pass's
working set. Imports :mod:`~torchcf.qp.kernels`, :mod:`~torchcf.qp.problem` and
:mod:`~torchcf.qp.leading`; the leading-block solves are looked up here, at call
time, as ``leading_solve`` and ``boundary_step``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .kernels import put_instances_, take_instances
from .leading import (
    LeadingSolution,
    LeadingWorkingSet,
    boundary_step,
    is_leading,
    leading_accept,
    leading_guess,
    leading_solve,
    signed_multipliers,
)
from .problem import QPSettings

#: Compact the leading-block stage's working set once less than this share runs.
_LEADING_COMPACT = 0.5


class Unfinished(NamedTuple):
    """Instances an active-set stage hands on, with its last guess of the bounds."""

    rows: Tensor  # (b,) int64 positions in the call
    lower: Tensor  # (n, b) bool
    upper: Tensor  # (n, b) bool


class LeadingOutcome(NamedTuple):
    """What :func:`leading_active_set` solved, over the call's ``B`` instances."""

    x: Tensor  # (n, B) solutions where ``solved``, garbage elsewhere
    y: Tensor  # (n, B) multipliers where ``solved``
    solved: Tensor  # (B,) bool
    constrained: Tensor  # (B,) bool, solved with at least one active bound


class _Pass(NamedTuple):
    """The stage after a pass, over its working set of ``b`` instances."""

    rows: Tensor  # (b,) int64 positions in the call
    data: LeadingWorkingSet
    lower: Tensor  # (n, b) bool, the guess ``solution`` was computed on
    upper: Tensor  # (n, b) bool
    solution: LeadingSolution
    running: Tensor  # (b,) bool, still in the stage (a leading-block guess)
    accept: Tensor  # (b,) bool, ``running`` and optimal


def _active_set_step(
    data: LeadingWorkingSet,
    solution: LeadingSolution,
    lower: Tensor,
    upper: Tensor,
) -> tuple[Tensor, Tensor]:
    """The primal-dual active-set step (Hintermueller, Ito & Kunisch 2002): free
    the bounds with a wrong-signed multiplier, fix the bounds ``x`` violates.

    Returns:
        the new guess: lower, upper (n, b) bool.
    """
    wrong_sign = solution.signed > 0
    new_lower = (lower & ~wrong_sign) | (solution.x < data.l)
    new_upper = ((upper & ~wrong_sign) | (solution.x > data.u)) & ~new_lower
    return new_lower, new_upper


def _hand_on(
    unfinished: list[Unfinished],
    rows: Tensor,
    which: Tensor,
    lower: Tensor,
    upper: Tensor,
) -> None:
    """Append the instances ``which: (b,)`` bool of a working set at ``rows: (b,)``
    to ``unfinished``, with their guess ``lower, upper: (n, b)``."""
    idx = which.nonzero().squeeze(1)
    if idx.numel():
        unfinished.append(
            Unfinished(
                rows[idx], take_instances(lower, idx), take_instances(upper, idx)
            )
        )


def _first_pass(
    data: LeadingWorkingSet,
    lower: Tensor,
    upper: Tensor,
    running: Tensor,
    settings: QPSettings,
    unfinished: list[Unfinished],
) -> _Pass:
    """Solve every running instance whose first guess is a leading block.

    Masked (over the whole call) unless fewer than ``_LEADING_COMPACT`` of the
    instances run: then compacted to them.
    """
    batch = data.l.shape[-1]
    rows = torch.arange(batch, device=data.l.device)
    leading = is_leading(lower | upper)
    _hand_on(unfinished, rows, running & ~leading, lower, upper)
    running = running & leading
    if int(running.sum()) < _LEADING_COMPACT * batch:
        keep = running.nonzero().squeeze(1)
        rows, data, running = rows[keep], data.take(keep), running[keep]
        lower, upper = take_instances(lower, keep), take_instances(upper, keep)
    solution = leading_solve(data, lower, upper)
    accept = leading_accept(data, solution, settings) & running
    return _Pass(rows, data, lower, upper, solution, running, accept)


def _first_outcome(done: _Pass, batch: int) -> LeadingOutcome:
    """The stage's output after its first pass, over the call's ``batch``
    instances."""
    solution, accept = done.solution, done.accept
    if done.rows.numel() == batch:
        # The whole batch in order: its solutions are the output as they stand.
        return LeadingOutcome(solution.x, solution.y, accept, accept & (solution.k > 0))
    x_out = done.data.l.new_zeros(done.data.l.shape[0], batch)
    y_out = torch.zeros_like(x_out)
    solved = torch.zeros(batch, dtype=torch.bool, device=x_out.device)
    out = LeadingOutcome(x_out, y_out, solved, torch.zeros_like(solved))
    _record(out, done, whole=False)
    return out


def _record(out: LeadingOutcome, done: _Pass, whole: bool) -> None:
    """Write a pass's solutions into ``out``, in place.

    A masked pass over the ``whole`` call writes only the accepted instances (its
    working set holds finished ones); a compacted pass writes all of its own: what
    is not accepted yet is overwritten later.
    """
    solution, rows, accept = done.solution, done.rows, done.accept
    if whole:
        take = accept.nonzero().squeeze(1)
        where = rows[take]
        put_instances_(out.x, where, take_instances(solution.x, take))
        put_instances_(out.y, where, take_instances(solution.y, take))
        out.solved[where] = True
        out.constrained[where] = solution.k[take] > 0
    else:
        put_instances_(out.x, rows, solution.x)
        put_instances_(out.y, rows, solution.y)
        out.solved[rows] = accept
        out.constrained[rows] = accept & (solution.k > 0)


def _compact_to(done: _Pass, keep: Tensor) -> _Pass:
    """The instances ``keep: (b',)`` of a pass (their vectors; the factors stay
    whole). ``running`` and ``accept`` are left for the next pass to set."""
    solution = done.solution
    data = done.data.take(keep)
    x = take_instances(solution.x, keep)
    y = take_instances(solution.y, keep)
    k = solution.k[keep]
    # The guess and the signed multipliers follow from x and k: cheaper than
    # gathering them.
    lower, upper = leading_guess(data, x, k)
    sign = lower.to(x.dtype).sub_(upper.to(x.dtype))
    solution = LeadingSolution(x, y, signed_multipliers(data, y, sign), k)
    return done._replace(
        rows=done.rows[keep], data=data, lower=lower, upper=upper, solution=solution
    )


def _step_or_solve(
    done: _Pass,
    new_lower: Tensor,
    new_upper: Tensor,
    new_active: Tensor,
    running: Tensor,
) -> LeadingSolution:
    """The solution on the new guess ``new_lower, new_upper: (n, b)`` (``new_active``
    their union) of a compacted working set: a rank-one boundary step where the
    guess fixes or frees exactly the bound at the end of the block, a new solve for
    the ``running`` instances where it does more."""
    data, lower, upper, solution = done.data, done.lower, done.upper, done.solution
    changed = (new_lower != lower) | (new_upper != upper)
    grown = new_active.sum(0) - solution.k  # (b,)
    one_bound = (changed.sum(0) == 1) & (grown.abs() == 1)
    # The changed row where one_bound (clamped: garbage elsewhere).
    j = torch.where(grown > 0, solution.k, solution.k - 1)
    j = j.clamp_(0, lower.shape[0] - 1)
    solution = boundary_step(data, solution, j, new_lower, new_upper)
    resolve = (running & ~one_bound).nonzero().squeeze(1)
    if not resolve.numel():
        return solution
    sub = leading_solve(
        data.take(resolve),
        take_instances(new_lower, resolve),
        take_instances(new_upper, resolve),
    )
    return LeadingSolution(
        put_instances_(solution.x, resolve, sub.x),
        put_instances_(solution.y, resolve, sub.y),
        put_instances_(solution.signed, resolve, sub.signed),
        solution.k.index_copy(0, resolve, sub.k),
    )


def _next_pass(
    done: _Pass,
    rejected: Tensor,
    whole: bool,
    settings: QPSettings,
    unfinished: list[Unfinished],
) -> _Pass:
    """One active-set step and solve on the ``rejected: (b,)`` instances of the
    last pass: masked over the ``whole`` call, else compacted to them."""
    if not whole:
        keep = rejected.nonzero().squeeze(1)
        done, rejected = _compact_to(done, keep), rejected[keep]
    data, rows = done.data, done.rows
    new_lower, new_upper = _active_set_step(data, done.solution, done.lower, done.upper)
    new_active = new_lower | new_upper
    leading = is_leading(new_active)
    _hand_on(unfinished, rows, rejected & ~leading, new_lower, new_upper)
    running = rejected & leading
    if whole:
        # Most of the batch still runs (a cold start): another masked pass.
        solution = leading_solve(data, new_lower, new_upper)
    else:
        solution = _step_or_solve(done, new_lower, new_upper, new_active, running)
    accept = leading_accept(data, solution, settings) & running
    return _Pass(rows, data, new_lower, new_upper, solution, running, accept)


def leading_active_set(
    data: LeadingWorkingSet,
    lower: Tensor,
    upper: Tensor,
    running: Tensor,
    settings: QPSettings,
    passes: int,
) -> tuple[LeadingOutcome, Unfinished]:
    """Primal-dual active-set steps (Hintermueller, Ito & Kunisch 2002) on leading
    blocks, for as long as the guessed active set is one.

    On the MPC QPs it nearly always is: the bounds that bind are the first inputs of
    the plan. The first pass solves every running instance (:func:`leading_solve`,
    masked: the finished ones' solves are wasted unless fewer than half run); the
    later ones only the instances still running, compacted: where the active-set
    step fixes or frees one bound at the end of the block (most of them: the block
    grew or shrank by one since the guess) by a rank-one update
    (:func:`boundary_step`), otherwise by a new solve. An instance leaves for the
    general stage (:func:`~torchcf.qp.polish.active_set_solves`) with its current
    guess once the guess is not a leading block, or after ``passes`` solves. A
    first guess with no active bound makes the first pass the unconstrained
    minimiser (BoxQP's fast path).

    Args:
        data: the problems (:func:`~torchcf.qp.leading.leading_data`, positive
            definite ``P``), ``B`` instances.
        lower, upper: (n, B) bool, the first guess.
        running: (B,) bool, the instances to solve.
        settings: for the tolerances of the acceptance test.
        passes: solves per instance at most.

    Returns:
        what the stage solved, and the instances it hands on with their guesses.
    """
    batch = data.l.shape[-1]
    unfinished: list[Unfinished] = []
    done = _first_pass(data, lower, upper, running, settings, unfinished)
    out = _first_outcome(done, batch)
    for _ in range(passes - 1):
        rejected = done.running & ~done.accept
        count = int(rejected.sum())
        if not count:
            break
        whole = done.rows.numel() == batch and count >= _LEADING_COMPACT * batch
        done = _next_pass(done, rejected, whole, settings, unfinished)
        _record(out, done, whole)
    else:
        _hand_on(
            unfinished, done.rows, done.running & ~done.accept, done.lower, done.upper
        )
    left = (
        Unfinished(*(torch.cat(parts, -1) for parts in zip(*unfinished, strict=True)))
        if unfinished
        else Unfinished(done.rows[:0], done.lower[:, :0], done.upper[:, :0])
    )
    return out, left
