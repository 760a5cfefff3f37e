"""The run's checkpoint: its file format, resuming from it, and the
checkpointer; and the device the run's process simulates on.

``checkpoint.pt`` (:meth:`torchcf.runs.directory.RunDir.save_checkpoint`) is a dict::

    {
        "format": "torchcf.checkpoint/1",
        "config_hash": "<16 hex digits: torchcf.config.config_hash of the run>",
        "progress": {model: ModelProgress.as_dict()},   # particles offered, ...
        "buffers": {model: TopN.state_dict()},          # per-pair top-N buffers
        "smc": {model: SMCState.state_dict()},          # abc.method = "smc" only
        "refinement_before": {model: {...}},            # amortised, refined only
    }

A buffer's state holds the tensors ``score`` ``(N, B)`` (the run's distance,
ascending per pair), ``index`` ``(N, B)`` (the particle's number in its model's
stream) and ``theta`` ``(N, B, K)`` (SI units, one more column ``log r`` under
SMC and an amortised run's refinement), for ``N`` training pairs and ``B =
abc.buffer_size`` slots. ``refinement_before`` (an amortised run with
``abc.amortised.refine``, once every model's samples are scored) holds per model
its share and median best score before the refinement
(:mod:`torchcf.calibration.refinement`).

:func:`open_run` checks the output directory against ``--resume`` and, resuming,
reads the checkpoint into a :class:`RunState` (refusing one of another format,
another config or a malformed content with a :class:`RunError`);
:class:`Checkpointer` writes it (rank 0) every ``abc.checkpoint_every`` seconds
and when a stop is requested.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..abc.distributed import Group
from ..abc.rejection import ModelProgress
from ..calibration import CalibrationState
from ..config import ConfigError
from ..runs.directory import RunDir
from ..system.console import one_line
from ..system.errors import TorchcfError, first_names
from ..system.files import RunFileError, TorchPayload
from ..system.signals import StopRequest

CHECKPOINT_FORMAT = "torchcf.checkpoint/1"
#: The tensors every saved buffer must hold.
BUFFER_TENSORS = ("score", "index", "theta")


class RunError(TorchcfError, RuntimeError):
    """A run that cannot start or continue as asked (one-line message)."""


@dataclass
class RunState:
    """Everything a checkpoint holds: the config's hash and the calibration's
    state (per model, its progress, buffer and refinement state)."""

    config_hash: str
    calibration: CalibrationState = field(default_factory=CalibrationState)

    def as_checkpoint(self) -> TorchPayload:
        """The checkpoint's content (the module docstring's format)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "config_hash": self.config_hash,
            **self.calibration.as_payload(),
        }


def open_run(digest: str, out: Path, resume: bool) -> RunState:
    """Check the output directory against ``--resume``, before any data is loaded.

    Probes that the directory can be created and written (leaving nothing
    behind: a bad config or data set found next must not leave an empty run
    directory); with ``resume`` loads the checkpoint and checks it was written
    with this very config (its hash ``digest``, :func:`torchcf.config.config_hash`).

    Raises:
        RunError: a run is there and ``resume`` is not asked, or ``resume`` is
            asked and no (matching, readable) checkpoint is there, or the
            directory holds files of something else
            (:meth:`~torchcf.runs.directory.RunDir.foreign_entries`).
        RunFileError: the directory cannot be created or written.
    """
    run = RunDir(out)
    if resume:
        state = resume_state(run, digest)
        run.probe()
        return state
    if out.exists() and not out.is_dir():
        raise RunError(f"output directory {out} exists and is not a directory")
    if run.holds_run():
        raise RunError(
            f"{out} already holds a run; pass --resume to continue it, or --out "
            "for a new directory"
        )
    foreign = run.foreign_entries()
    if foreign:
        raise RunError(
            f"{out} holds files that are not a run's ({first_names(foreign)}): "
            "choose an empty or a new --out"
        )
    run.probe()
    return RunState(digest)


def resume_note(state: RunState, models: list[str], n_particles: int | None) -> str:
    """What ``--resume`` reuses from the checkpoint, in one line: the models
    finished, the one stopped part-way and how far, the ones still to run.

    Args:
        state: the checkpoint's state.
        models: the config's models, in run order.
        n_particles: particles per model (``abc.n_particles``); None where a
            model's count is not the config's (the amortised method: its
            samples of the model, then its refinement): the note gives the
            particles done alone.
    """
    progress = state.calibration.progress
    done = [m for m in models if m in progress and progress[m].done]
    partial = [
        m for m in models if m in progress and not progress[m].done and progress[m].next
    ]
    todo = [m for m in models if m not in done and m not in partial]
    parts = [f"{', '.join(done)} finished" if done else "no model finished"]
    total = "" if n_particles is None else f" of {n_particles:,}"
    parts += [f"{m} at {progress[m].next:,}{total}" for m in partial]
    if todo:
        parts.append(f"{', '.join(todo)} to run")
    return "resuming from checkpoint.pt: " + "; ".join(parts)


def resume_state(run: RunDir, digest: str) -> RunState:
    """The state of the checkpoint in ``run``, written with the config of hash
    ``digest``.

    Raises:
        RunError: no checkpoint, an unreadable one, one of another format or
            config, or a malformed content.
    """
    if not run.checkpoint.exists():
        raise RunError(f"--resume: no checkpoint.pt in {run.path}")
    try:
        raw = run.load_checkpoint()
    except RunFileError as error:
        raise RunError(
            f"--resume: {one_line(error)}; start again with another --out"
        ) from None
    check_header(raw, digest, run)
    return checkpoint_state(raw, digest, run.checkpoint)


def check_header(raw: Any, digest: str, run: RunDir) -> None:
    """RunError unless ``raw`` is a torchcf checkpoint of the config ``digest``."""
    if not isinstance(raw, Mapping) or raw.get("format") != CHECKPOINT_FORMAT:
        raise RunError(f"--resume: {run.checkpoint} is not a torchcf checkpoint")
    if raw.get("config_hash") != digest:
        raise RunError(
            f"--resume: {run.path} was run with a different config (hash "
            f"{raw.get('config_hash')}, this config {digest}); use another --out"
        )


def checkpoint_state(raw: Mapping[str, Any], digest: str, path: Path) -> RunState:
    """The RunState of a loaded checkpoint; RunError if its content is malformed.

    Checks the shape of the content only (progress records, the buffers'
    tensors); whether the buffers fit this run is checked when they are loaded
    (:func:`torchcf.calibration.state.build_buffers`).
    """
    state = RunState(digest)
    kept = state.calibration
    try:
        for name, progress in raw["progress"].items():
            kept.progress[name] = ModelProgress(**progress)
            if not 0 <= kept.progress[name].next:
                raise ValueError(f"{name}: negative progress")
        buffers = raw["buffers"]
        for name, buffer in buffers.items():
            if not all(
                isinstance(buffer.get(key), torch.Tensor) for key in BUFFER_TENSORS
            ):
                raise ValueError(f"{name}: buffer tensors missing")
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise RunError(
            f"--resume: {path} is corrupted ({type(error).__name__}: {error}); "
            "start again with another --out"
        ) from None
    kept.saved_buffers = buffers
    kept.saved_smc = raw.get("smc", {})
    before = raw.get("refinement_before")
    if before is not None:
        kept.refinement_before = {k: dict(v) for k, v in before.items()}
    return state


def run_device(device: str, group: Group) -> torch.device:
    """The device this process simulates on (the config's ``device``, under
    ``torchrun`` this rank's GPU); ConfigError if it is not there."""
    chosen = group.run_device(device)
    if chosen.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device: {device!r} asked for but CUDA is not available")
        if chosen.index is not None and chosen.index >= torch.cuda.device_count():
            raise ConfigError(
                f"device: {str(chosen)!r} asked for but only "
                f"{torch.cuda.device_count()} CUDA device(s) are visible"
            )
    return chosen


class Checkpointer:
    """Saves the run state on rank 0, every ``every`` seconds when asked, and at
    once when a stop was requested (Ctrl-C or SIGTERM: :mod:`torchcf.system.signals`),
    after which it stops the run."""

    def __init__(
        self,
        run: RunDir,
        state: RunState,
        every: float,
        group: Group,
        stop: StopRequest | None = None,
    ):
        self.run, self.state, self.every, self.group = run, state, every, group
        self.stop = stop
        self.last = time.perf_counter()

    def due(self) -> bool:
        """A save is due: ``every`` seconds have passed, or a stop was asked."""
        if self.stop is not None and self.stop.requested:
            return True
        return time.perf_counter() - self.last >= self.every

    def save(self) -> None:
        """Every rank holds the merged buffers: rank 0 saves them; then a
        requested stop raises :class:`~torchcf.system.signals.Stopped`."""
        self.group.on_main(self.run.save_checkpoint, self.state.as_checkpoint())
        self.last = time.perf_counter()
        if self.stop is not None:
            self.stop.stop(checkpointed=True)


__all__ = [
    "CHECKPOINT_FORMAT",
    "Checkpointer",
    "RunError",
    "RunState",
    "checkpoint_state",
    "open_run",
    "resume_state",
    "run_device",
]
