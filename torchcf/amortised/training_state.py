"""The amortised training's checkpoint: what it holds, writing and reading it.

A checkpoint is a dict written atomically by ``torch.save``::

    {
        "format": "torchcf.amortised.checkpoint/2",
        "fingerprint": {...},        # what the run trains: models, sizes, settings
        "estimator": state_dict,     # the networks' weights
        "optimiser": state_dict,     # Adam's moments and step counts
        "best": state_dict | None,   # the weights of the best validation loss
        "progress": {...},           # TrainingProgress.as_dict()
    }

The fingerprint is plain data (lists, numbers, and the settings' dataclasses
as dicts: ``"noise": {"position": .., "speed": .., "acceleration": ..}``,
read back by :func:`~torchcf.amortised.fingerprint_noise`). A checkpoint of
format ``/1`` (its settings written as their ``repr``) is refused with a
one-line error.

No random generator's state is saved: every random number of the training (a
simulated set, the order of an epoch's batches) is a function of the seed and
the epoch, drawn again on resume, so a resumed run ends identical to an
uninterrupted one.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..system.errors import TorchcfError
from ..system.files import atomic_torch_save, read_torch

CHECKPOINT_FORMAT = "torchcf.amortised.checkpoint/2"
#: Formats no longer read, and why.
FORMER_FORMATS = {
    "torchcf.amortised.checkpoint/1": "its fingerprint holds settings as text",
}


class CheckpointError(TorchcfError, ValueError):
    """A checkpoint that does not belong to the training asked to resume."""


@dataclass
class EpochRecord:
    """One finished epoch.

    Attributes:
        epoch: its number, from 0.
        train_loss: mean negative log density of its batches (the flows'
            unbounded space).
        validation_loss: the same over the validation set.
        validation_accuracy: share of validation examples whose most probable
            model is the true one.
        seconds: training time when it ended [s].

    Examples:
        >>> EpochRecord(epoch=0, train_loss=1.25, validation_loss=1.5,
        ...             validation_accuracy=0.75, seconds=3.0)
        EpochRecord(epoch=0, train_loss=1.25, validation_loss=1.5,
                    validation_accuracy=0.75, seconds=3.0)
    """

    epoch: int
    train_loss: float
    validation_loss: float
    validation_accuracy: float
    seconds: float


@dataclass
class TrainingProgress:
    """Where a training stands (all of it plain data).

    Attributes:
        epoch: the epoch in progress (or next), from 0.
        batch: the next batch of that epoch.
        loss_sum, loss_count: the epoch's training loss so far (sum over
            examples, examples).
        best_loss: the lowest validation loss so far (inf before the first).
        since_best: epochs ended since it.
        simulations: examples simulated (drawn, valid or not), validation
            included.
        invalid: of them, discarded.
        seconds: training time spent [s], over every session.
        history: the finished epochs.
        finished: why it ended ("" while it runs: "epochs", "patience",
            "seconds").

    Examples:
        >>> first = EpochRecord(0, 1.2, 1.5, 0.6, 2.0)
        >>> second = EpochRecord(1, 1.0, 1.4, 0.7, 4.0)
        >>> progress = TrainingProgress(epoch=2, history=[first, second])
        >>> progress.best_accuracy  # the epoch of the lowest validation loss
        0.7
        >>> TrainingProgress.from_dict(progress.as_dict()) == progress
        True
    """

    epoch: int = 0
    batch: int = 0
    loss_sum: float = 0.0
    loss_count: int = 0
    best_loss: float = float("inf")
    since_best: int = 0
    simulations: int = 0
    invalid: int = 0
    seconds: float = 0.0
    history: list[EpochRecord] = field(default_factory=list)
    finished: str = ""

    @property
    def best_accuracy(self) -> float:
        """The validation model accuracy of the epoch with the lowest
        validation loss (the weights kept); NaN before the first epoch."""
        best = min(self.history, key=lambda r: r.validation_loss, default=None)
        return best.validation_accuracy if best is not None else math.nan

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> TrainingProgress:
        known = {f.name for f in fields(cls)}
        if set(raw) != known:
            raise CheckpointError(
                f"progress holds {sorted(raw)}, needs {sorted(known)}"
            )
        values = dict(raw)
        values["history"] = [EpochRecord(**record) for record in raw["history"]]
        return cls(**values)


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """``payload`` (module docstring, without its format) to ``path``,
    atomically."""
    atomic_torch_save({"format": CHECKPOINT_FORMAT, **payload}, path)


def load_checkpoint(path: Path, fingerprint: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint at ``path``, checked against the training that resumes it.

    Raises:
        RunFileError: the file is missing, unreadable or corrupted.
        CheckpointError: another format, or another training's (its
            fingerprint differs: the first differing entry is named).
    """
    raw = _read(path)
    saved = raw.get("fingerprint", {})
    if saved != fingerprint:
        keys = sorted(set(saved) | set(fingerprint))
        differing = [k for k in keys if saved.get(k) != fingerprint.get(k)]
        raise CheckpointError(
            f"{path}: another training's checkpoint ({differing[0]}: "
            f"{saved.get(differing[0])!r} saved, {fingerprint.get(differing[0])!r} "
            "now)"
        )
    missing = {"estimator", "optimiser", "best", "progress"} - set(raw)
    if missing:
        raise CheckpointError(f"{path}: no {', '.join(sorted(missing))}")
    return raw


def load_trained(path: Path, estimator: dict[str, Any]) -> dict[str, Any]:
    """The finished checkpoint at ``path``, its estimator reused by another
    training run: the estimator's part of its fingerprint (models, boxes,
    networks' sizes) must be ``estimator``, the rest (leaders, noise, budget)
    may differ.

    Raises:
        RunFileError: the file is missing, unreadable or corrupted.
        CheckpointError: another format, another estimator (the first
            differing entry named) or a training not finished.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> finished = {"fingerprint": {"models": ["idm"], "pairs": ["carII", 500]},
        ...     "estimator": {}, "best": None, "progress": {"finished": "epochs"}}
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     save_checkpoint(Path(tmp) / "amortised.pt", finished)
        ...     raw = load_trained(Path(tmp) / "amortised.pt", {"models": ["idm"]})
        >>> raw["progress"]["finished"]  # other leaders: the estimator is reused
        'epochs'
    """
    raw = _read(path)
    saved = raw.get("fingerprint", {})
    for key, value in estimator.items():
        if saved.get(key) != value:
            raise CheckpointError(
                f"{path}: another estimator ({key}: {saved.get(key)!r} there, "
                f"{value!r} in this config)"
            )
    missing = {"estimator", "best", "progress"} - set(raw)
    if missing:
        raise CheckpointError(f"{path}: no {', '.join(sorted(missing))}")
    if not raw["progress"].get("finished"):
        raise CheckpointError(
            f"{path}: its training has not finished; resume its run first"
        )
    return raw


def _read(path: Path) -> dict[str, Any]:
    """The checkpoint at ``path``, of this format (CheckpointError if not)."""
    raw = read_torch(path)
    found = raw.get("format") if isinstance(raw, dict) else None
    if found in FORMER_FORMATS:
        raise CheckpointError(
            f"{path}: an amortised training checkpoint of an older torchcf "
            f"({found}: {FORMER_FORMATS[found]}); train the estimator again"
        )
    if found != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not an amortised training checkpoint")
    return raw


def copy_state(state: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of a state dict (the best weights, kept apart from the
    weights being trained)."""
    return copy.deepcopy(state)


__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "EpochRecord",
    "TrainingProgress",
    "copy_state",
    "load_checkpoint",
    "load_trained",
    "save_checkpoint",
]
