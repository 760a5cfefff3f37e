"""The batched rollout: the time loop and the streaming errors, nothing model-specific.

SPEC sections 2 (simulation) and 4 (score). The leader is replayed from data; the
follower starts from its observed state and is driven by a
:class:`~torchcf.models.CFModel`.
Errors are accumulated step by step, so a rollout never stores ``(T, P, N)`` unless the
caller asks for the trajectory.

Two layouts share one code path:

- **full**: every particle on every pair, state ``(P, N)``;
- **paired**: particle ``j`` on pair ``pair_index[j]``, state ``(P,)`` (the paper's
  down-sampled ABC). The observations of step ``t`` are gathered per particle inside
  the step, never materialised as ``(T, P)``.

Numerics worth knowing:

- Positions are simulated relative to each pair's initial follower position. Spacing
  and errors are differences, so this changes nothing mathematically, but it keeps
  float32 positions small (a 2 km road in float32 has a 1e-4 m resolution).
- Time is processed in blocks of ``BLOCK_STEPS`` steps; the series is padded with
  masked steps to a multiple of the block. One block is one call of the (optionally
  ``torch.compile``-fused) block function, which keeps the state in registers over
  the whole block.
- The last chunk of particles is padded to the chunk size so every chunk has one
  shape: no recompilation, and each particle's arithmetic is independent of the
  chunk size.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from torch import Tensor

from ..models import CFModel, FollowerState, Perception, require_model
from .compiled import (  # noqa: F401 - resolve_compile and the rest: sim's API
    COMPILE_MIN_STEPS,
    COMPILE_MIN_STEPS_CUDA,
    CompileMode,
    _BlockRunner,
    _compiled_block,
    resolve_compile,
)
from .step import (  # noqa: F401 - realise: sim's API
    _A_FOLLOW,
    _MASK,
    _V_FOLLOW,
    _V_LEAD,
    _X_FOLLOW,
    _X_LEAD,
    _Accumulators,
    _not_finite,
    realise,
)

#: Steps per block function call (the unit that ``torch.compile`` fuses). The
#: compile time grows with the steps unrolled, the throughput with fewer trips
#: to memory: 8 steps compile sooner than 16 at the same throughput, 4 only a
#: little sooner at less (measured: ``reports/performance.md``, "Rollout
#: throughput"); compiled results do not depend on it.
BLOCK_STEPS = 8
#: With compilation or early rejection, chunks are a multiple of this: every
#: element then takes the vectorised path of a kernel, never a scalar tail
#: (whose transcendental functions can round differently: seen for ``sigmoid``
#: on an AMD EPYC), so results do not depend on the chunk size, or on which
#: particles early rejection left beside a particle.
COMPILE_CHUNK_MULTIPLE = 64
#: Simulated cells per chunk on CUDA (at least): a GPU runs one kernel per
#: operation and step whatever the chunk, so larger chunks amortise the launches.
#: Every model's CPU budget (:attr:`CFModel.chunk_cells`) is below it, so on CUDA
#: every model gets this one. Results do not depend on it (chunk-size invariance).
CUDA_CHUNK_CELLS = 2**21
#: Score weights of position, speed and acceleration RMSE (SPEC section 4).
DEFAULT_WEIGHTS = (0.5, 0.3, 0.2)
#: Early rejection (a ``ceiling``): blocks between two looks at the scores so
#: far. A look is a few operations on the chunk and one host sync, against
#: ``PRUNE_EVERY * BLOCK_STEPS`` model steps.
PRUNE_EVERY = 2
#: Early rejection drops the finished particles from the chunk once they are at
#: least this share of those still simulated: every drop copies the live state,
#: so dropping a few at a time would cost more than simulating them.
PRUNE_SHARE = 0.2


if TYPE_CHECKING:
    from ..data import PairSet


class SimOutput(NamedTuple):
    """Result of :func:`simulate`.

    Attributes:
        score: ``(P, N)`` full layout or ``(P,)`` paired;
            ``0.5 e_p + 0.3 e_v + 0.2 e_a`` by default, ``+inf`` when invalid.
        e_p: RMSE of position [m] over the valid steps (``+inf`` when invalid).
        e_v: RMSE of speed [m/s].
        e_a: RMSE of acceleration [m/s^2].
        valid: bool, False when the rollout was invalid (non-finite value or
            non-positive spacing on a valid step).
        x: ``(T, P, N)`` or ``(T, P)`` simulated position [m] if ``return_traj``.
        v: same shape, speed [m/s].
        a: same shape, recorded acceleration [m/s^2] (HL: the realised state).
        pruned: bool, the score's shape: True where early rejection stopped the
            rollout, its score sure to exceed the ceiling given to
            :func:`simulate` (:attr:`Execution.ceiling`; score and errors
            ``+inf``; ``valid`` as far as it ran); None without a ceiling.

    Examples:
        >>> import torch
        >>> from torchcf import get_model, simulate
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=3, n_steps=50)
        >>> other = [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]
        >>> theta = torch.tensor([idm, other], dtype=torch.float64)
        >>> out = simulate(get_model("idm"), theta, pairs)  # every particle, every pair
        >>> out.score.shape, out.x, out.pruned
        (torch.Size([2, 3]), None, None)
        >>> round(float(out.e_p[0].max()), 3)  # the particle that drove them [m]
        0.0
    """

    score: Tensor
    e_p: Tensor
    e_v: Tensor
    e_a: Tensor
    valid: Tensor
    x: Tensor | None = None
    v: Tensor | None = None
    a: Tensor | None = None
    pruned: Tensor | None = None


class _Prune(NamedTuple):
    """Early rejection of one chunk (:attr:`Execution.ceiling`).

    Attributes:
        ceiling: float64, the state's shape: a cell whose score is sure to exceed
            it is stopped.
        counts: int64 valid steps of each cell (at least 1), broadcastable to the
            state: the denominators of its RMSE.
        weights: score weights of (position, speed, acceleration).
    """

    ceiling: Tensor
    counts: Tensor
    weights: tuple[float, float, float]


def score_so_far(
    acc: _Accumulators, counts: Tensor, weights: Sequence[float]
) -> Tensor:
    """The score of the steps run so far, over the cell's *whole* count of valid
    steps: ``sum_c w_c sqrt(S_c(t) / n)`` with ``S_c(t)`` the squared errors of
    channel c summed up to step t and ``n`` the valid steps of the whole rollout.

    A lower bound of the final score, in floating point too: the sums only grow
    (a non-negative term is added at every step), and the rounded division,
    square root, product with a positive weight and sum are each monotone, so the
    final score (the same expression of the final sums, :func:`simulate`) is at
    least this value.

    Examples:
        >>> from types import SimpleNamespace
        >>> import torch
        >>> from torchcf.sim.rollout import score_so_far
        >>> sums = SimpleNamespace(  # squared errors summed over the steps run so far
        ...     sq_x=torch.tensor([4.0]), sq_v=torch.tensor([1.0]), sq_a=torch.zeros(1)
        ... )
        >>> bound = score_so_far(sums, torch.tensor([4.0]), weights=(0.5, 0.3, 0.2))
        >>> round(float(bound), 3)  # 0.5 sqrt(4 / 4) + 0.3 sqrt(1 / 4)
        0.65
    """
    w_p, w_v, w_a = (float(w) for w in weights)
    return (
        w_p * torch.sqrt(acc.sq_x / counts)
        + w_v * torch.sqrt(acc.sq_v / counts)
        + w_a * torch.sqrt(acc.sq_a / counts)
    )


class _Course(NamedTuple):
    """What every chunk of one rollout runs over.

    Attributes:
        model: the simulated model.
        block_fn: runs one block of steps (:class:`_BlockRunner`).
        blocks: ``(BLOCK_STEPS, 6, N)`` observation blocks covering the padded
            time axis (:func:`_observation_table`).
        origin: ``(N,)`` road position of each pair's relative frame [m].
        n_valid: ``(N,)`` valid steps of each pair.
        dt: time step [s].
        leader_length: the leader's length [m].
    """

    model: CFModel
    block_fn: Callable[..., Any]
    blocks: list[Tensor]
    origin: Tensor
    n_valid: Tensor
    dt: float
    leader_length: float


def _course(
    model: CFModel,
    pairs: PairSet,
    dtype: torch.dtype,
    device: torch.device,
    record: bool,
    chunking: _Chunking,
) -> _Course:
    """The observation blocks of ``pairs`` (:func:`_observation_table`) and the
    block function that runs a chunk over them, recording the trajectory or
    not."""
    table, origin, n_valid = _observation_table(pairs, dtype, device)
    # Contiguous blocks: a compiled block then sees the same layout at every call.
    blocks = [block.clone() for block in table.split(BLOCK_STEPS)]
    block_fn = _BlockRunner(
        model,
        chunking.paired,
        pairs.dt,
        pairs.leader_length,
        record,
        chunking.compiled,
        dynamic=chunking.prunes,
    )
    return _Course(
        model, block_fn, blocks, origin, n_valid, pairs.dt, pairs.leader_length
    )


def _rollout_chunk(
    course: _Course,
    theta: Tensor,
    pair_index: Tensor | None,
    prune: _Prune | None = None,
) -> tuple[_Accumulators, Tensor | None, Tensor | None]:
    """Run one chunk of particles over every block; returns sums and trajectory.

    Args:
        theta: ``(P, K)`` chunk of parameters.
        pair_index: ``(P,)`` (paired layout) or None (full layout).
        prune: stop the particles whose score is sure to exceed their ceiling
            (:func:`_run_pruned`); None runs every particle to the end.

    Returns:
        the sums over valid steps (of the steps run, for a stopped particle),
        if recording the ``(T_pad, 3, *state)`` trajectory, and with ``prune``
        the state-shaped bool of the cells stopped by it.
    """
    params, state, memory, cell_origin = _chunk_start(course, theta, pair_index)
    zeros = torch.zeros_like(state.x)
    acc = _Accumulators(
        zeros, zeros.clone(), zeros.clone(), torch.zeros_like(zeros, dtype=torch.bool)
    )
    if prune is not None:
        rollout = _Live(params, state, acc, memory, pair_index, cell_origin, prune)
        sums, pruned = _run_pruned(
            course.block_fn, course.model, rollout, course.blocks
        )
        return sums, None, pruned
    recorded = []
    for block in course.blocks:
        state, acc, memory, block_traj = course.block_fn(
            params, state, acc, memory, block, pair_index, cell_origin
        )
        if block_traj is not None:
            recorded.append(block_traj)
    return acc, torch.cat(recorded) if recorded else None, None


def _chunk_start(
    course: _Course, theta: Tensor, pair_index: Tensor | None
) -> tuple[Any, FollowerState, Any, Tensor | None]:
    """A chunk at its first step: the model's parameters prepared for the
    step, the followers' observed state, the model's initial memory and, for a
    model that reads the position, each cell's road origin [m] (else None)."""
    model = course.model
    first = course.blocks[0][0]  # (6, N)
    cell_origin = None
    if model.uses_position:
        origin = course.origin
        cell_origin = origin[pair_index] if pair_index is not None else origin[None]
    if pair_index is not None:
        params = model.unpack(theta, state_ndim=1)  # fields (P,)
        initial = first.index_select(1, pair_index)  # (6, P)
    else:
        params = model.unpack(theta, state_ndim=2)  # fields (P, 1)
        initial = first[:, None, :].expand(-1, theta.shape[0], -1)  # (6, P, N)
    # clones, not views: a compiled block guards on the storage offset
    state = FollowerState(
        x=initial[_X_FOLLOW].clone(),
        v=initial[_V_FOLLOW].clone(),
        a=initial[_A_FOLLOW].clone(),
    )
    params = model.prepare(params, course.dt, tuple(state.x.shape))
    x_lead, v_lead = initial[_X_LEAD], initial[_V_LEAD]
    first_perception = Perception(
        spacing=x_lead - state.x,
        v=state.v,
        v_lead=v_lead.contiguous(),
        a=state.a,
        leader_length=course.leader_length,
        position=state.x + cell_origin if cell_origin is not None else None,
    )
    memory = model.initial_memory(params, first_perception)
    return params, state, memory, cell_origin


class _Live(NamedTuple):
    """The particles of a chunk still simulated under early rejection; every
    field over their rows (dimension 0 of the state)."""

    params: Any
    state: FollowerState
    acc: _Accumulators
    memory: Any
    pair_index: Tensor | None
    cell_origin: Tensor | None
    prune: _Prune

    def take(self, model: CFModel, rows: Tensor) -> _Live:
        """The same rollout for the particles ``rows`` alone."""
        paired = self.pair_index is not None
        params, memory = model.select_particles(self.params, self.memory, rows)
        counts = self.prune.counts
        return _Live(
            params=params,
            state=FollowerState(*(t.index_select(0, rows) for t in self.state)),
            acc=_Accumulators(*(t.index_select(0, rows) for t in self.acc)),
            memory=memory,
            pair_index=self.pair_index[rows] if paired else None,
            cell_origin=(
                self.cell_origin[rows]
                if paired and self.cell_origin is not None
                else self.cell_origin
            ),
            prune=self.prune._replace(
                ceiling=self.prune.ceiling.index_select(0, rows),
                counts=counts.index_select(0, rows) if paired else counts,
            ),
        )


def _run_pruned(
    block_fn: Callable[..., Any], model: CFModel, live: _Live, blocks: list[Tensor]
) -> tuple[_Accumulators, Tensor]:
    """Run the blocks with early rejection: every :data:`PRUNE_EVERY` blocks, a
    cell whose score so far (:func:`score_so_far`, a lower bound of its final
    score) exceeds its ceiling, or that is invalid, is finished; once the
    particles all of whose cells are finished (a row of the state) are
    :data:`PRUNE_SHARE` of those still simulated, they leave the chunk and the
    rest go on.

    Exact: a stopped cell's final score would have exceeded its ceiling; every
    other cell runs to the end with the arithmetic of an unpruned rollout
    (elementwise, so independent of its neighbours).

    Returns:
        the sums of every row of the chunk (of the steps each ran) and the
        state-shaped bool of the cells stopped above their ceiling (invalid ones
        are not: they are in the sums' ``invalid``).
    """
    sums = _Accumulators(*(t.clone() for t in live.acc))
    stopped = torch.zeros_like(live.acc.invalid)
    rows = torch.arange(live.state.x.shape[0], device=live.state.x.device)
    for number, block in enumerate(blocks, start=1):
        state, acc, memory, _ = block_fn(
            live.params,
            live.state,
            live.acc,
            live.memory,
            block,
            live.pair_index,
            live.cell_origin,
        )
        live = live._replace(state=state, acc=acc, memory=memory)
        if number % PRUNE_EVERY or number == len(blocks):
            continue
        over = score_so_far(acc, live.prune.counts, live.prune.weights).double()
        over = over > live.prune.ceiling
        finished = acc.invalid | over
        row_finished = finished if finished.ndim == 1 else finished.all(1)
        n_finished = int(row_finished.sum())
        if not n_finished or n_finished < PRUNE_SHARE * rows.numel():
            continue
        gone = (row_finished & (rows >= 0)).nonzero().squeeze(1)
        for total, part in zip(sums, acc, strict=True):
            total[rows[gone]] = part[gone]
        stopped[rows[gone]] = over[gone] & ~acc.invalid[gone]
        kept = (~row_finished & (rows >= 0)).nonzero().squeeze(1)
        if not kept.numel():
            return sums, stopped
        # whole vector lanes again (COMPILE_CHUNK_MULTIPLE), with copies of a
        # kept particle whose results are dropped (row -1)
        fill = -kept.numel() % COMPILE_CHUNK_MULTIPLE
        rows = torch.cat((rows[kept], rows.new_full((fill,), -1)))
        live = live.take(model, torch.cat((kept, kept[:1].expand(fill))))
    real = rows >= 0
    for total, part in zip(sums, live.acc, strict=True):
        total[rows[real]] = part[real]
    return sums, stopped


def cell_budget(model: CFModel, device: torch.device) -> int:
    """Simulated cells (particles x pairs) per chunk by default: the model's CPU
    budget, at least :data:`CUDA_CHUNK_CELLS` on CUDA.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.sim.rollout import cell_budget
        >>> cell_budget(get_model("idm"), torch.device("cpu")), 2**18
        (262144, 262144)
    """
    if device.type == "cuda":
        return max(model.chunk_cells, CUDA_CHUNK_CELLS)
    return model.chunk_cells


def _observation_table(pairs: PairSet, dtype: torch.dtype, device: torch.device):
    """The ``(T_pad, 6, N)`` table, the ``(N,)`` origins and valid-step counts.

    Positions are shifted by each pair's initial follower position; ``T`` is padded to
    ``T_pad``, a multiple of ``BLOCK_STEPS``, with copies of the last row, marked
    invalid.
    """
    origin = pairs.x_follow[0]  # (N,)
    table = torch.stack(
        (
            pairs.x_lead - origin[None, :],
            pairs.v_lead,
            pairs.x_follow - origin[None, :],
            pairs.v_follow,
            pairs.a_follow,
            pairs.mask.to(pairs.x_lead.dtype),
        ),
        dim=1,
    )  # (T, 6, N): a step's gather along N gives six contiguous rows
    n_pad = -pairs.n_steps % BLOCK_STEPS
    if n_pad:
        tail = table[-1:].expand(n_pad, -1, -1).clone()
        tail[:, _MASK] = 0.0
        table = torch.cat((table, tail))
    n_valid = pairs.mask.sum(0)  # (N,)
    return (
        table.to(device=device, dtype=dtype).contiguous(),
        origin.to(device=device, dtype=dtype),
        n_valid.to(device=device),
    )


def check_theta(model: CFModel, theta: Tensor, what: str = "theta") -> None:
    """ValueError (one line, naming ``what``) unless ``theta`` is a finite
    (P, K) particle matrix of ``model`` (K = ``model.n_params``).

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.sim.rollout import check_theta
        >>> check_theta(get_model("idm"), torch.ones(3, 6))  # (P, K): fine
        >>> check_theta(get_model("idm"), torch.ones(3, 4))
        Traceback (most recent call last):
            ...
        ValueError: theta must be (P, 6) for idm (a, b, v0, T, s0, delta), got (3, 4)
    """
    if theta.ndim != 2 or theta.shape[1] != model.n_params:
        raise ValueError(
            f"{what} must be (P, {model.n_params}) for {model.name} "
            f"({', '.join(model.param_names)}), got {tuple(theta.shape)}"
        )
    if not bool(torch.isfinite(theta).all()):
        raise ValueError(f"{what} for {model.name} holds non-finite values")


@dataclass(frozen=True, eq=False)
class Execution:
    """How a rollout runs: where, in chunks of how many particles, compiled or
    not, and whether it may stop a hopeless cell early. None of these changes
    the result of a cell that runs to the end: ``chunk_size`` and ``ceiling``
    exactly, ``device`` and ``compile`` to floating-point rounding.

    Attributes:
        device: where the rollout runs; None: theta's device.
        chunk_size: particles per chunk; None: :func:`cell_budget` simulated
            cells (``2**18``, MPC ``2**16``; at least :data:`CUDA_CHUNK_CELLS` on
            CUDA).
        compile: fuse the time step with ``torch.compile``: True, False,
            ``"on"``, ``"off"`` or ``"auto"`` (only for long CPU runs with a C++
            compiler, or CUDA). Falls back to eager with a warning if
            compilation fails.
        ceiling: early rejection: a tensor of the score's shape, a cell is of no
            use above it (a buffer's threshold). Every :data:`PRUNE_EVERY` blocks
            a cell whose score so far (:func:`score_so_far`, a lower bound of its
            final score) exceeds its ceiling is stopped, ``pruned`` in the output
            with score ``+inf``; the other cells' results are exactly those of a
            run without it. Applied on the eager path of a model that can select
            its particles (:attr:`CFModel.prunable`), without ``return_traj``;
            elsewhere every cell runs to the end (``pruned`` all False). None:
            no early rejection (``pruned`` None).

    Examples:
        >>> import torch
        >>> from torchcf import Execution, get_model, simulate
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=3, n_steps=50)
        >>> other = [1.0, 1.5, 30.0, 1.6, 2.5, 4.0]
        >>> theta = torch.tensor([idm, other], dtype=torch.float64)
        >>> one_by_one = Execution(chunk_size=1, compile=False)
        >>> a = simulate(get_model("idm"), theta, pairs, execution=one_by_one)
        >>> b = simulate(get_model("idm"), theta, pairs)
        >>> torch.equal(a.score, b.score)  # chunking does not change a result
        True
    """

    device: torch.device | str | None = None
    chunk_size: int | None = None
    compile: CompileMode = "auto"
    ceiling: Tensor | None = None


def simulate(
    model: CFModel,
    theta: Tensor,
    pairs: PairSet,
    pair_index: Tensor | Sequence[int] | None = None,
    *,
    dtype: torch.dtype | None = None,
    return_traj: bool = False,
    weights: Sequence[float] = DEFAULT_WEIGHTS,
    execution: Execution = Execution(),
) -> SimOutput:
    """Simulate particles of one model on leader-follower pairs and score them.

    SPEC sections 2 and 4: the follower starts from its observed state, the model's
    command drives it (point mass or HL's lag), speed is clamped at zero and position
    never decreases; a rollout with a non-finite value or non-positive spacing on a
    valid step is invalid and scores ``+inf``. The score is
    ``w_p e_p + w_v e_v + w_a e_a`` of the RMSE of position, speed and acceleration over
    the valid steps.

    The steps: check the inputs, plan the chunks (:func:`_chunking`), build the
    observation blocks (:class:`_Course`), run every chunk of particles through
    them (:func:`_run_chunks`) into the outputs, then score them
    (:meth:`_Filled.result`).

    Args:
        model: the model object (``torchcf.get_model("idm")``, effects allowed:
            ``get_model("idm+delay")``); a name raises :class:`TypeError`.
        theta: ``(P, K)`` parameters in the model's order (``model.param_names``).
        pairs: the observed pairs ``(T, N)``.
        pair_index: ``(P,)`` pair of each particle (paired layout); None simulates
            every particle on every pair (full layout).
        dtype: float32 or float64; default: theta's float dtype, else float32.
        return_traj: also return the simulated ``x, v, a``, time-first.
        weights: score weights of (position, speed, acceleration).
        execution: where and how it runs (:class:`Execution`: device, chunk
            size, compilation, early rejection); its choices do not change the
            result of a cell that runs to the end.

    Returns:
        :class:`SimOutput` with ``(P, N)`` (full) or ``(P,)`` (paired) fields.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model, simulate
        >>> t = torch.arange(50, dtype=torch.float64)[:, None] * 0.1
        >>> x_lead, v = 35.0 + 20.0 * t, torch.full_like(t, 20.0)
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 35.0, v, a], dt=0.1)
        >>> theta = torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]])  # one IDM
        >>> out = simulate(get_model("idm"), theta, pairs, [0], return_traj=True)
        >>> out.score.shape, out.x.shape, bool(out.valid[0])
        (torch.Size([1]), torch.Size([50, 1]), True)
    """
    model = require_model(model, "simulate")
    theta, dtype, device = _checked_theta(model, theta, dtype, execution.device)
    if len(weights) != 3:
        raise ValueError(f"weights must be 3 numbers (p, v, a), got {weights!r}")
    theta = theta.to(device=device, dtype=dtype)
    n_particles = theta.shape[0]
    pair_index = _checked_pair_index(pair_index, n_particles, pairs.n_pairs, device)
    paired = pair_index is not None
    chunking = _chunking(
        model, execution, device, n_particles, pairs, paired, return_traj
    )
    course = _course(model, pairs, dtype, device, return_traj, chunking)
    shape = (n_particles,) if paired else (n_particles, pairs.n_pairs)
    ceiling = _checked_ceiling(execution.ceiling, shape, device)
    filled = _Filled.empty(shape, pairs.n_steps, dtype, device, return_traj, ceiling)
    _run_chunks(course, theta, pair_index, chunking, ceiling, weights, filled)
    shift = None
    if return_traj:  # back from per-pair relative positions to road positions
        shift = course.origin[pair_index] if paired else course.origin[None, :]
    return filled.result(weights, shift)


def _run_chunks(
    course: _Course,
    theta: Tensor,
    pair_index: Tensor | None,
    chunking: _Chunking,
    ceiling: Tensor | None,
    weights: Sequence[float],
    filled: _Filled,
) -> None:
    """Every chunk of particles through the blocks, its results into
    ``filled``."""
    # Inference mode: no autograd bookkeeping per op (about 11 % of an eager
    # rollout of a few thousand cells); the outputs were made outside it and
    # stay ordinary tensors.
    with torch.inference_mode():
        # Every chunk's inputs inference tensors alike (a padded chunk's are made
        # here): a compiled block guards on the kind, and would otherwise trace
        # a second graph for the last chunk.
        theta = theta.clone()
        if chunking.paired:
            pair_index = pair_index.clone()
        n_particles = theta.shape[0]
        for start in range(0, n_particles, chunking.size):
            stop = min(start + chunking.size, n_particles)
            chunk = _Chunk.of(theta, pair_index, start, stop, chunking.size)
            n_valid = course.n_valid
            counts = (
                n_valid[chunk.pair_index]
                if pair_index is not None
                else n_valid[None, :]
            ).clamp(min=1)
            prune = None
            if chunking.prunes:
                prune = _Prune(chunk.ceiling(ceiling), counts, tuple(weights))
            sums, traj, pruned = _rollout_chunk(
                course, chunk.theta, chunk.pair_index, prune
            )
            filled.store(chunk, sums, counts, traj, pruned)


def _checked_theta(
    model: CFModel,
    theta: Tensor,
    dtype: torch.dtype | None,
    device: torch.device | str | None,
) -> tuple[Tensor, torch.dtype, torch.device]:
    """``theta`` as a tensor, checked (:func:`check_theta`); the rollout's dtype
    (default: theta's float dtype, else float32) and device (default:
    theta's)."""
    theta = torch.as_tensor(theta)
    if dtype is None:
        dtype = theta.dtype if theta.is_floating_point() else torch.float32
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    device = torch.device(device) if device is not None else theta.device
    check_theta(model, theta)
    return theta, dtype, device


def _checked_pair_index(
    pair_index: Tensor | Sequence[int] | None,
    n_particles: int,
    n_pairs: int,
    device: torch.device,
) -> Tensor | None:
    """The ``(P,)`` int64 pair of each particle on ``device`` (ValueError unless
    each is a pair, ``0 <= pair < N``); None for the full layout."""
    if pair_index is None:
        return None
    pair_index = torch.as_tensor(pair_index, device=device).long()
    if pair_index.shape != (n_particles,):
        raise ValueError(
            f"pair_index must have shape ({n_particles},), "
            f"got {tuple(pair_index.shape)}"
        )
    if n_particles and (int(pair_index.min()) < 0 or int(pair_index.max()) >= n_pairs):
        raise ValueError(f"pair_index out of range [0, {n_pairs})")
    return pair_index


class _Chunking(NamedTuple):
    """How a rollout's particles are cut (:func:`_chunking`).

    Attributes:
        paired: the paired layout (a pair per particle), else the full one.
        size: particles per chunk (the last one padded to it).
        compiled: the blocks run compiled.
        prunes: early rejection applies (a ceiling, no trajectory, a model
            that can select its particles).
    """

    paired: bool
    size: int
    compiled: bool
    prunes: bool


def _chunking(
    model: CFModel,
    execution: Execution,
    device: torch.device,
    n_particles: int,
    pairs: PairSet,
    paired: bool,
    return_traj: bool,
) -> _Chunking:
    """The chunk size, whether the blocks run compiled and whether early
    rejection applies. Compiled or pruned, the chunk is a multiple of
    :data:`COMPILE_CHUNK_MULTIPLE` (whole vector lanes)."""
    cells_per_particle = 1 if paired else pairs.n_pairs
    chunk_size = execution.chunk_size
    if chunk_size is None:
        chunk_size = max(1, cell_budget(model, device) // cells_per_particle)
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    chunk_size = min(chunk_size, max(n_particles, 1))
    use_compile = resolve_compile(
        model,
        execution.compile,
        device,
        n_particles * cells_per_particle * pairs.n_steps,
    )
    prunes = execution.ceiling is not None and not return_traj and model.prunable
    if use_compile or prunes:
        chunk_size = -(-chunk_size // COMPILE_CHUNK_MULTIPLE) * COMPILE_CHUNK_MULTIPLE
    return _Chunking(paired, chunk_size, use_compile, prunes)


def _checked_ceiling(
    ceiling: Tensor | None, shape: tuple[int, ...], device: torch.device
) -> Tensor | None:
    """The float64 ceiling on ``device`` (ValueError unless it has the score's
    ``shape``), or None."""
    if ceiling is None:
        return None
    ceiling = torch.as_tensor(ceiling, device=device).to(torch.float64)
    if ceiling.shape != shape:
        raise ValueError(
            f"ceiling must have the score's shape {shape}, got {tuple(ceiling.shape)}"
        )
    return ceiling


class _Chunk(NamedTuple):
    """Particles ``start .. stop - 1`` of a rollout, padded to the chunk size
    with copies of the first (one shape for a compiled block; the padding's
    results are dropped).

    Attributes:
        start, stop: the real particles.
        theta: ``(size, K)`` their parameters, then the padding.
        pair_index: ``(size,)`` their pairs (paired layout), or None.
        n_fill: rows of padding.
    """

    start: int
    stop: int
    theta: Tensor
    pair_index: Tensor | None
    n_fill: int

    @classmethod
    def of(
        cls, theta: Tensor, pair_index: Tensor | None, start: int, stop: int, size: int
    ) -> _Chunk:
        chunk_theta = theta[start:stop]
        chunk_index = pair_index[start:stop] if pair_index is not None else None
        n_fill = size - (stop - start)
        if n_fill:
            chunk_theta = torch.cat((chunk_theta, chunk_theta[:1].expand(n_fill, -1)))
            if chunk_index is not None:
                chunk_index = torch.cat((chunk_index, chunk_index[:1].expand(n_fill)))
        return cls(start, stop, chunk_theta, chunk_index, n_fill)

    def ceiling(self, ceiling: Tensor) -> Tensor:
        """The chunk's rows of ``ceiling``; the padding's ``-inf``, so that it
        is stopped at the first look."""
        fill = ceiling.new_full((self.n_fill, *ceiling.shape[1:]), -math.inf)
        return torch.cat((ceiling[self.start : self.stop], fill))


@dataclass(frozen=True, eq=False)
class _Filled:
    """A rollout's outputs, filled chunk by chunk (:meth:`store`), then scored
    (:meth:`result`).

    Attributes:
        errors: ``e_p, e_v, e_a`` by name, the score's shape, the RMSE of each
            channel over the valid steps.
        invalid: bool, the score's shape.
        pruned: bool, the score's shape, the cells early rejection stopped;
            None without a ceiling.
        traj: ``(T, 3, *shape)`` the trajectory relative to each pair's start,
            if recorded.
    """

    errors: dict[str, Tensor]
    invalid: Tensor
    pruned: Tensor | None
    traj: Tensor | None

    @classmethod
    def empty(
        cls,
        shape: tuple[int, ...],
        n_steps: int,
        dtype: torch.dtype,
        device: torch.device,
        return_traj: bool,
        ceiling: Tensor | None,
    ) -> _Filled:
        """Outputs of the score's ``shape``, made outside inference mode."""
        return cls(
            errors={
                name: torch.empty(shape, dtype=dtype, device=device)
                for name in ("e_p", "e_v", "e_a")
            },
            invalid=torch.empty(shape, dtype=torch.bool, device=device),
            pruned=(
                torch.zeros(shape, dtype=torch.bool, device=device)
                if ceiling is not None
                else None
            ),
            traj=(
                torch.empty((n_steps, 3, *shape), dtype=dtype, device=device)
                if return_traj
                else None
            ),
        )

    def store(
        self,
        chunk: _Chunk,
        sums: _Accumulators,
        counts: Tensor,
        traj: Tensor | None,
        pruned: Tensor | None,
    ) -> None:
        """A chunk's RMSEs (its sums over ``counts`` valid steps), validity,
        stopped cells and trajectory, its padding dropped."""
        start, stop = chunk.start, chunk.stop
        keep = slice(0, stop - start)
        self.errors["e_p"][start:stop] = torch.sqrt(sums.sq_x / counts)[keep]
        self.errors["e_v"][start:stop] = torch.sqrt(sums.sq_v / counts)[keep]
        self.errors["e_a"][start:stop] = torch.sqrt(sums.sq_a / counts)[keep]
        if pruned is not None:
            self.pruned[start:stop] = pruned[keep]
        self.invalid[start:stop] = sums.invalid[keep]
        if self.traj is not None:
            self.traj[:, :, start:stop] = traj[: self.traj.shape[0], :, keep]

    def result(self, weights: Sequence[float], shift: Tensor | None) -> SimOutput:
        """The scores ``w_p e_p + w_v e_v + w_a e_a``, ``+inf`` (and the errors
        too) where a cell is invalid or was stopped; with a trajectory, its
        positions shifted by ``shift`` back to the road's."""
        e = self.errors
        inf = torch.tensor(math.inf, dtype=e["e_p"].dtype, device=e["e_p"].device)
        unscored = self.invalid if self.pruned is None else self.invalid | self.pruned
        e_p, e_v, e_a = (
            torch.where(unscored, inf, e[k]) for k in ("e_p", "e_v", "e_a")
        )
        w_p, w_v, w_a = (float(w) for w in weights)
        score = torch.where(unscored, inf, w_p * e_p + w_v * e_v + w_a * e_a)
        result = SimOutput(
            score=score,
            e_p=e_p,
            e_v=e_v,
            e_a=e_a,
            valid=~self.invalid,
            pruned=self.pruned,
        )
        if self.traj is None:
            return result
        traj = self.traj
        return result._replace(x=traj[:, 0] + shift, v=traj[:, 1], a=traj[:, 2])
