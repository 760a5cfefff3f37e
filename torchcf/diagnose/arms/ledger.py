"""The attribution's ledger: its finished arms in ``RUN_DIR/loop/attribution.pt``,
written as they finish and read back by an interrupted attribution run again
(:func:`torchcf.diagnose.selection.attribution.attribute_effects`), and the key that
says whether a ledger belongs to this run, these settings and these effects.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...models.effects import Effect
from ...system.files import RunFileError, TorchPayload, atomic_torch_save, read_torch
from ..setup import LoopSetup
from .arena import Checkpoints

#: Ledger format (``RUN_DIR/loop/attribution.pt``).
LEDGER_FORMAT = "torchcf.attribution/11"
#: A fit's state is written to the ledger at least this often while it runs
#: [s] (the pool's search, a converging search), besides every finished arm.
CHECKPOINT_SECONDS = 30.0


class Ledger:
    """The attribution's finished arms, in ``RUN_DIR/loop/attribution.pt``.

    Keyed by the run's config hash, the diagnose settings and the candidate
    effects: an attribution run again with the same ones reads its finished
    arms back (their random numbers are seeded by their place, so the result
    is the one an uninterrupted run gives); any other key starts afresh.
    """

    def __init__(self, path: Path | None, key: str) -> None:
        self.path, self.key = path, key
        self.entries: TorchPayload = {}  # the file's content: tensors, plain data
        self.written = -math.inf
        if path is not None and path.exists():
            try:
                raw = read_torch(path)
            except RunFileError:
                raw = None  # unreadable: computed again
            if (
                isinstance(raw, dict)
                and raw.get("format") == LEDGER_FORMAT
                and raw.get("key") == key
            ):
                self.entries = raw["entries"]

    def get(self, name: str) -> Any:
        return self.entries.get(name)

    def put(self, name: str, value: Any) -> None:
        """Keep a finished result, written to disk now."""
        self.keep(name, value, now=True)

    def keep(self, name: str, value: Any, *, now: bool = False) -> None:
        """Keep ``value`` under ``name``: written now, or where the last write is
        less than :data:`CHECKPOINT_SECONDS` old, with the next one (a state
        that a later round replaces)."""
        self.entries[name] = value
        if self.path is None:
            return
        if not now and time.monotonic() - self.written < CHECKPOINT_SECONDS:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_torch_save(
            {"format": LEDGER_FORMAT, "key": self.key, "entries": self.entries},
            self.path,
        )
        self.written = time.monotonic()

    def within(self, prefix: str) -> Checkpoints:
        """The ledger's entries under ``prefix/``, as a fit keeps its state."""
        return _Prefixed(self, prefix)


def resuming(book: Ledger) -> str:
    """One line saying what an interrupted attribution reuses: its finished
    stages (``pool``, ``1/base``, ``1/<effect>`` ...) and those it resumes
    midway (the state kept under a stage's prefix: ``pool/...``,
    ``1/converged/...``)."""
    finished = [n for n in book.entries if n.count("/") <= 1]
    midway = set()
    for name in book.entries:
        if name.count("/") > 1:
            parts = name.split("/")
            stage = parts[0] if parts[0] == "pool" else "/".join(parts[:2])
            if stage not in book.entries:
                midway.add(stage)
    kept = ", ".join(finished[:6]) + (" ..." if len(finished) > 6 else "")
    return (
        f"attribution: resuming from {book.path}: "
        + (f"{len(finished)} stages kept ({kept})" if finished else "")
        + (", " if finished and midway else "")
        + (f"{', '.join(sorted(midway))} midway" if midway else "")
    )


class _Prefixed:
    """A ledger seen through a prefix (:class:`~torchcf.diagnose.arms.arena.
    Checkpoints`)."""

    def __init__(self, ledger: Ledger, prefix: str) -> None:
        self.ledger, self.prefix = ledger, prefix

    def get(self, name: str) -> Any:
        return self.ledger.get(f"{self.prefix}/{name}")

    def keep(self, name: str, value: Any, *, now: bool = False) -> None:
        self.ledger.keep(f"{self.prefix}/{name}", value, now=now)


def ledger_key(
    setup: LoopSetup, pool: list[str], tested: Sequence[Effect] | Sequence[str]
) -> str:
    """What a ledger's content depends on (its key): the run, the diagnose
    settings, the pool and what is tested, by name (the attribution's candidate
    effects, or the models a re-calibration trains)."""
    settings = setup.settings.model_dump(mode="json", exclude={"run_after_training"})
    text = json.dumps(settings, sort_keys=True)
    names = ",".join(map(str, tested))  # an effect's str is its token
    return f"{setup.run_hash}|{text}|{','.join(pool)}|{names}"


__all__ = [
    "CHECKPOINT_SECONDS",
    "LEDGER_FORMAT",
    "Ledger",
    "ledger_key",
    "resuming",
]
