"""``torch.compile`` for the rollout: when to compile, and the compiled block.

:func:`resolve_compile` decides (``compile: "auto"`` compiles long CPU streams);
:class:`_BlockRunner` calls a model's block of steps (:func:`torchcf.sim.step._block`)
fused whole, or for a correcting model (:attr:`~torchcf.models.CFModel.corrects`:
MPC's QP) :class:`_CorrectedBlock`'s two compiled step functions around the eager
correction; a compiler failure falls back to eager once, with a warning.

Graphs: one per model, layout and record flag, traced for the chunk's particle
count; with early rejection (``dynamic``) the particle dimension is traced
symbolic (:func:`mark_batch_dynamic`), so the shrinking batches reuse one graph.
"""

from __future__ import annotations

import functools
import os
import platform
import shutil
import sys
import warnings
from collections.abc import Callable
from typing import Any, Literal

import torch
from torch import Tensor

from ..models import CFModel, FollowerState
from .step import _Accumulators, _block, _draft_step, _finish_step

#: Below this many simulated particle-steps, ``compile="auto"`` stays eager on
#: the CPU: the one-off compilation (seconds) would cost more than it saves
#: (measured: ``reports/performance.md``, "Rollout throughput").
COMPILE_MIN_STEPS = 2e8
#: The same on CUDA, where eager rollouts are fast too, so the paper-scale study
#: runs eager there (measured: ``reports/performance.md``, "On a GPU").
COMPILE_MIN_STEPS_CUDA = 1e11


CompileMode = bool | Literal["auto", "on", "off"]


class _CorrectedBlock:
    """:func:`_block` for a correcting model, compiled around its correction:
    per step a compiled draft (:func:`_draft_step`), the eager
    :meth:`CFModel.correct`, and the compiled errors and motion
    (:func:`_finish_step`): the arithmetic of :func:`_block`.

    Two compiled calls a step, not one fused block: the MPC's step is bound by
    its memory traffic, not by the calls (fusing each step's motion with the
    next step's draft, a third graph to compile, was no faster:
    ``reports/performance.md``, "MPC and its QP solver").
    """

    def __init__(
        self,
        model: CFModel,
        paired: bool,
        dt: float,
        leader_length: float,
        record: bool,
        dynamic: bool = False,
    ) -> None:
        self.model, self.record = model, record
        self._draft_marks = _BatchMarks() if dynamic else None
        self._finish_marks = _BatchMarks() if dynamic else None
        draft = functools.partial(_draft_step, model, paired, leader_length)
        # The first step of a chunk has no memory yet: eager, so the compiled
        # draft keeps one graph (one structure of the memory).
        self._first_draft = draft
        self._draft = _compile(draft, dynamic)
        finish = functools.partial(_finish_step, model, paired, dt, record)
        self._finish = _compile(finish, dynamic)

    def __call__(
        self,
        params: Any,
        state: FollowerState,
        acc: _Accumulators,
        memory: Any,
        obs: Tensor,
        pair_index: Tensor | None,
        origin: Tensor | None,
    ) -> tuple[FollowerState, _Accumulators, Any, Tensor | None]:
        recorded = []
        dynamic = self._draft_marks is not None
        for obs_step in obs.unbind(0):
            if dynamic:
                # a copy (6 x N numbers): a view's storage offset varies by step,
                # and a graph of symbolic sizes guards on it
                obs_step = obs_step.clone()
            draft = self._first_draft if memory is None else self._draft
            if dynamic and memory is not None:
                marked = (params, state, memory, pair_index, origin)
                self._draft_marks(marked, state.x, memory)
            pending, memory = draft(params, state, memory, obs_step, pair_index, origin)
            command, memory = self.model.correct(params, pending, memory)
            if dynamic:
                marked = (params, state, acc, command, pair_index)
                self._finish_marks(marked, state.x)
            state, acc, moved = self._finish(
                params, state, acc, command, obs_step, pair_index
            )
            recorded.append(moved)
        return state, acc, memory, torch.stack(recorded) if self.record else None


class _BlockRunner:
    """Calls the block function, compiled when asked; falls back to eager once."""

    def __init__(
        self,
        model: CFModel,
        paired: bool,
        dt: float,
        leader_length: float,
        record: bool,
        use_compile: bool,
        dynamic: bool = False,
    ) -> None:
        self._static = (model, paired, float(dt), float(leader_length), record)
        self._eager = functools.partial(_block, *self._static)
        self._marks = _BatchMarks() if dynamic and not model.corrects else None
        self._compiled = (
            _compiled_block(*self._static, dynamic) if use_compile else None
        )

    def __call__(self, *args: Any) -> Any:
        if self._compiled is None:
            return self._eager(*args)
        if self._marks is not None:
            params, state, acc, memory, _, pair_index, origin = args
            marked = (params, state, acc, memory, pair_index, origin)
            self._marks(marked, state.x, memory)
        try:
            return self._compiled(*args)
        except Exception as error:  # noqa: BLE001 - any compiler failure
            key = self._static[0].name
            if key not in _COMPILE_FAILED:
                _COMPILE_FAILED.add(key)
                warnings.warn(
                    f"torch.compile failed for {key} ({type(error).__name__}: "
                    f"{error}); running eager",
                    RuntimeWarning,
                    stacklevel=3,
                )
            self._compiled = None
            return self._eager(*args)


def compiler_available() -> bool:
    """Whether a C++ compiler is on the PATH (inductor's CPU kernels need one)."""
    return shutil.which("g++") is not None or shutil.which("c++") is not None


@functools.cache
def _compiled_block(
    model: CFModel,
    paired: bool,
    dt: float,
    leader_length: float,
    record: bool,
    dynamic: bool = False,
) -> Callable[..., Any]:
    """The block function of ``model``, compiled: :func:`_block` fused whole, or
    for a correcting model (:attr:`CFModel.corrects`) a :class:`_CorrectedBlock`
    whose steps are fused around the correction. ``dynamic``: one graph for every
    number of particles (:func:`mark_batch_dynamic`), as early rejection needs."""
    if model.corrects:
        return _CorrectedBlock(model, paired, dt, leader_length, record, dynamic)
    block = functools.partial(_block, model, paired, dt, leader_length, record)
    return _compile(block, dynamic)


def mark_batch_dynamic(tree: Any, state: Tensor) -> None:
    """Mark the particle dimensions of every tensor in ``tree`` (nested tuples)
    dynamic for ``torch.compile``: each dimension as long as the state's first
    (particles) or as its cells (particles x pairs, a flattened batch). A graph
    traced so takes any number of particles: early rejection's shrinking chunks
    reuse it instead of compiling a graph per size."""
    sizes = {state.shape[0], state.numel()}
    if isinstance(tree, Tensor):
        for dim, size in enumerate(tree.shape):
            if size in sizes:
                torch._dynamo.maybe_mark_dynamic(tree, dim)
    elif isinstance(tree, (tuple, list)):
        for item in tree:
            mark_batch_dynamic(item, state)


class _BatchMarks:
    """Marks a compiled function's particle dimensions dynamic
    (:func:`mark_batch_dynamic`) when the number of particles changes: the graph
    traced from marked inputs takes unmarked ones of any size (a dimension mark
    is guarded on only where a tensor carries one), so marking every call would
    only cost time."""

    def __init__(self) -> None:
        self._key: tuple[int, int] = (-1, -1)

    def __call__(self, tree: Any, state: Tensor, memory: Any = None) -> None:
        # a controller's memory can gain parts (an augmented model's base memory
        # starts as None): a new structure is traced anew, so marked anew
        key = (state.shape[0], _count_none(memory))
        if key != self._key:
            mark_batch_dynamic(tree, state)
            self._key = key


def _count_none(tree: Any) -> int:
    """How many leaves of ``tree`` (nested tuples) are None."""
    if tree is None:
        return 1
    if isinstance(tree, (tuple, list)):
        return sum(_count_none(item) for item in tree)
    return 0


def _compile(function: Callable[..., Any], dynamic: bool = False) -> Callable[..., Any]:
    configure_compiler()
    # dynamic: None lets the marked dimensions (mark_batch_dynamic) be symbolic
    # and the rest static; False would ignore the marks.
    return torch.compile(function, dynamic=None if dynamic else False, fullgraph=True)


def compile_any_batch(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` compiled with torchcf's settings (:func:`configure_compiler`)
    for inputs whose sizes vary from call to call (dynamic shapes: one graph,
    not one per size); graph breaks allowed, as a library's code (zuko's flows)
    is traced as it comes."""
    configure_compiler()
    return torch.compile(function, dynamic=True)


def configure_compiler() -> None:
    """Settings every ``torch.compile`` of torchcf needs (idempotent).

    Every model, layout and chunk shape is a separate graph of the same function
    (:func:`torchcf.sim.step._block`); dynamo's default of 8 graphs per function
    would silently drop the ninth to eager, so the limit is raised to what a
    full run can need. And the CPU's vector instruction set is probed once,
    for the set the kernels will use (:func:`_probe_vector_isa`).
    """
    dynamo_config = torch._dynamo.config
    dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 256)
    dynamo_config.accumulated_recompile_limit = max(
        dynamo_config.accumulated_recompile_limit, 1024
    )
    _probe_vector_isa()


@functools.cache
def _probe_vector_isa() -> str | None:
    """Probe the one vector ISA inductor's CPU kernels will use; returns its name
    (None: inductor is left to probe as it does).

    Inductor checks every ISA the CPU reports (e.g. AVX2, AVX-512, AVX-512
    VNNI): it builds a test library per ISA and loads each in a child Python, so
    that an ISA the compiler or the OS cannot run never reaches a kernel. The
    kernels then use the first of the list alone (``pick_vec_isa``). So that
    first ISA is probed here, with inductor's own check; where it passes,
    ``vec_isa_ok`` tells inductor not to probe the others, which are never used.
    The kernels are the same, and a process's probe is shorter (measured:
    ``reports/performance.md``, "The whole study").

    Where the first ISA fails, or the user chose an ISA (``ATEN_CPU_CAPABILITY``,
    inductor's ``cpp.simdlen`` or ``cpp.vec_isa_ok``), or the CPU is not x86,
    nothing is changed.
    """
    if platform.machine() not in ("x86_64", "AMD64") or sys.platform != "linux":
        return None
    try:
        from torch._inductor import config as inductor_config
        from torch._inductor import cpu_vec_isa
    except ImportError:  # pragma: no cover - a torch without inductor
        return None
    cpp = inductor_config.cpp
    if (
        os.environ.get("ATEN_CPU_CAPABILITY")
        or cpp.simdlen is not None
        or cpp.vec_isa_ok is not None
    ):
        return None
    try:
        flags = cpu_vec_isa.x86_isa_checker()
        reported = [
            isa
            for isa in cpu_vec_isa.supported_vec_isa_list
            if all(flag in flags for flag in str(isa).split())
        ]
        # bool(isa) is inductor's check: build the test library, load it apart
        if not reported or not bool(reported[0]):
            return None
    except Exception:  # noqa: BLE001 - inductor's internals moved: probe as it does
        return None
    cpp.vec_isa_ok = True
    return str(reported[0])


_COMPILE_FAILED: set[str] = set()


def resolve_compile(
    model: CFModel, compile: CompileMode, device: torch.device, cells: int
) -> bool:
    """Whether a rollout of ``cells`` simulated steps in all (particles x pairs x
    steps) of ``model`` runs compiled: ``compile`` True/False (or "on"/"off") as
    asked (a model that cannot compile never does; a correcting model compiles
    around its correction, :class:`_CorrectedBlock`); "auto" from
    :data:`COMPILE_MIN_STEPS` cells on where a C++ compiler is there (CPU), from
    :data:`COMPILE_MIN_STEPS_CUDA` on CUDA."""
    if compile == "on" or compile == "off":  # the config's spelling
        compile = compile == "on"
    if compile != "auto" and not isinstance(compile, bool):
        # a truthy string such as "no" must not silently compile
        raise ValueError(
            f'compile must be True, False, "auto", "on" or "off", got {compile!r}'
        )
    if not (model.compilable or model.corrects):
        return False
    if compile == "auto":
        # Compilation costs seconds; it pays on long runs only.
        if device.type == "cuda":
            return cells >= COMPILE_MIN_STEPS_CUDA
        return cells >= COMPILE_MIN_STEPS and compiler_available()
    return bool(compile)
