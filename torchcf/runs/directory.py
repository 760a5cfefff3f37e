"""The run directory: the one place that knows its files, their names and layout.

A run directory, as the commands leave it::

    RUN_DIR/
    ├── config.json       train     the resolved configuration (written first)
    ├── checkpoint.pt     train     ABC progress and buffers, rewritten during the
    │                               run and kept after it (``--resume``)
    ├── amortised.pt      train     abc.method "amortised" only: the estimator's
    │                               training checkpoint, its trained weights
    ├── tb/               train, evaluate, diagnose: TensorBoard event files
    ├── posterior.pt      train     the learned particle set (torchcf.posterior)
    ├── summary.json      train     written LAST by training: the run is trained
    ├── report/           evaluate  table.md, shares.png, pairwise.png,
    │                               error_evolution.png, radar.png
    ├── metrics.json      evaluate  written LAST by the evaluation: it is evaluated
    ├── loop/             diagnose  the loop's figures (*.png)
    │   └── after/        diagnose  the re-calibration, itself a run directory
    ├── loop.md           diagnose  the loop's report
    ├── loop.json         diagnose  written LAST by the loop: the loop finished
    └── .lock             train, evaluate, diagnose: held while one works here

A cross-validation (``torchcf crossval``) writes one run directory per
fold, ``OUT/fold<i>/``, then the folds' mean in ``OUT/report/table.md`` and, last,
``OUT/metrics.json``.

What ``summary.json`` and ``metrics.json`` hold is typed once, here: their
records are :mod:`torchcf.runs.summary`'s and :mod:`torchcf.runs.metrics`'s, and
:class:`RunDir` writes and reads the records (the JSON objects are the files'
edge alone).

Each step's last file marks its completion, so a directory never looks more
finished than it is: every file is written atomically (:mod:`torchcf.system.files`: a
temporary file renamed into place; a full disk keeps the previous checkpoint
intact), and a file that cannot be read or written is a
:class:`~torchcf.system.files.RunFileError` with one line naming it (a configuration
that is readable but invalid: a :class:`~torchcf.config.ConfigError`).

One command at a time works in a run directory (:meth:`RunDir.locked`): a
second training, evaluation or loop started on it while the first runs is
refused with one line, instead of both writing and one result being lost.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

try:  # POSIX; elsewhere a run directory is not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

from ..config import (
    ConfigError,
    TrainConfig,
    config_hash,
    resolved_json,
    validate_config,
)
from ..posterior import Posterior
from ..system.files import (
    JSON,
    RunFileError,
    TorchPayload,
    atomic_torch_save,
    atomic_write_text,
    ensure_directory,
    read_json_object,
    read_torch,
    remove_file,
    write_json,
)
from .metrics import CrossvalResult, Evaluation
from .summary import RecalibrationSummary, RunSummary

#: The lock file of a run directory (:meth:`RunDir.locked`).
LOCK_NAME = ".lock"
#: Run directories this process holds locked, with the depth of nesting: a
#: study locks its run and calls training and evaluation, which lock it too.
_HELD: dict[Path, int] = {}


def _write_owner(handle: Any) -> None:
    """The holder's process id in the lock file, for the message of a second
    process (informational: a disk too full for it does not stop the run)."""
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
    except OSError:
        pass


#: Entries that every ``summary.json`` holds (the evaluation reads them).
SUMMARY_KEYS = ("dataset", "pairwise")


#: Settings earlier releases wrote to ``config.json`` that no longer exist; a run
#: directory holding them is read without them (they changed nothing a finished
#: run holds).
RETIRED_KEYS = {
    "diagnose": ("recalibrate_particles", "recalibrate_method", "recalibration")
}


def _without_retired(raw: JSON) -> JSON:
    """A run's ``config.json`` object without :data:`RETIRED_KEYS`."""
    out = dict(raw)
    for section, keys in RETIRED_KEYS.items():
        if isinstance(out.get(section), dict):
            out[section] = {k: v for k, v in out[section].items() if k not in keys}
    return out


class RunDir:
    """One run directory (module docstring): its paths, and its files read and
    written.

    Args:
        path: the directory; nothing is touched until a method reads or writes.

    Examples:
        >>> import tempfile
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.runs.directory import RunDir
        >>> from torchcf.runs.summary import Pairwise, RecalibrationSummary
        >>> pairwise = Pairwise(("idm",), ((1.0,),))
        >>> summary = RecalibrationSummary("demo", {"idm": 1.0}, 5, pairwise, "smc")
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     run = RunDir(folder).fold(0).prepare()
        ...     run.write_config(TrainConfig(data={"path": "demo"}, models=["idm"]))
        ...     run.write_summary(summary)
        ...     print(run.is_trained(), run.read_config().models[0].name,
        ...           run.read_summary() == summary, run.summary_json.name)
        True idm True summary.json
    """

    __slots__ = ("_path",)

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._path = Path(path)

    def __fspath__(self) -> str:
        return os.fspath(self._path)

    def __repr__(self) -> str:
        return f"RunDir({str(self._path)!r})"

    def __str__(self) -> str:
        return str(self._path)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RunDir) and other._path == self._path

    def __hash__(self) -> int:
        return hash(self._path)

    # ------------------------------------------------------------------ paths
    @property
    def path(self) -> Path:
        """The directory."""
        return self._path

    @property
    def config_json(self) -> Path:
        return self._path / "config.json"

    @property
    def checkpoint(self) -> Path:
        return self._path / "checkpoint.pt"

    @property
    def amortised_checkpoint(self) -> Path:
        """The amortised estimator's training checkpoint and trained weights
        (``abc.method = "amortised"`` only)."""
        return self._path / "amortised.pt"

    @property
    def posterior_pt(self) -> Path:
        return self._path / "posterior.pt"

    @property
    def summary_json(self) -> Path:
        return self._path / "summary.json"

    @property
    def metrics_json(self) -> Path:
        return self._path / "metrics.json"

    @property
    def report_dir(self) -> Path:
        return self._path / "report"

    @property
    def tb_dir(self) -> Path:
        return self._path / "tb"

    @property
    def data_dir(self) -> Path:
        """Where a run on a raw source keeps its extraction record."""
        return self._path / "data"

    @property
    def loop_json(self) -> Path:
        return self._path / "loop.json"

    @property
    def loop_md(self) -> Path:
        return self._path / "loop.md"

    @property
    def loop_dir(self) -> Path:
        return self._path / "loop"

    @property
    def recalibration_dir(self) -> Path:
        """``loop/after``: the diagnosis loop's re-calibration (a run directory)."""
        return self.loop_dir / "after"

    @property
    def reference_dir(self) -> Path:
        """``loop/reference``: the pool alone searched as the re-calibration (a
        run directory), when that search differs from the run's."""
        return self.loop_dir / "reference"

    def fold(self, index: int) -> RunDir:
        """The run directory of fold ``index`` of a cross-validation in this one."""
        return RunDir(self._path / f"fold{index}")

    # ------------------------------------------------------------------ state
    def prepare(self) -> RunDir:
        """Create the directory and check, with a real write, that files can be
        written in it: a full disk or a missing permission fails here, before any
        data is loaded.

        Returns:
            self.

        Raises:
            RunFileError: the path exists and is not a directory, cannot be
                created, or cannot be written.
        """
        ensure_directory(self._path, "output directory")
        return self

    def probe(self) -> None:
        """Check as :meth:`prepare` does (the same errors), then remove the
        directories it created: a command checks its output before it loads any
        data, and leaves nothing behind if the data then fail.

        Raises:
            RunFileError: as :meth:`prepare`.
        """
        ensure_directory(self._path, "output directory", keep=False)

    @contextmanager
    def locked(self) -> Iterator[RunDir]:
        """Hold the run directory for this process while the block runs.

        An exclusive ``flock`` on ``RUN_DIR/.lock`` (released by the operating
        system if the process dies, so a killed run leaves no stale lock); the
        file holds the owner's process id. Re-entrant within a process. A
        directory created here for the lock is removed again if the block
        leaves nothing else in it (a command that fails before writing leaves
        no empty run directory behind); in a directory that was there, a lock
        file made here goes again if no run started (no ``config.json``).

        Raises:
            RunFileError: another process holds it (naming its process id), or
                the directory cannot be created or written.
        """
        key = self._path.resolve()
        if key in _HELD or fcntl is None:
            _HELD[key] = _HELD.get(key, 0) + 1
            try:
                yield self
            finally:
                _HELD[key] -= 1
                if not _HELD[key]:
                    del _HELD[key]
            return
        created = not self._path.exists()
        # The probe write fails on a full disk or a missing permission before
        # anything is created (and leaves nothing behind then).
        ensure_directory(self._path, "output directory", keep=False)
        self._path.mkdir(parents=True, exist_ok=True)
        lock = self._path / LOCK_NAME
        lock_existed = lock.exists()
        try:
            try:
                handle = open(lock, "a+")  # noqa: SIM115 - held across the block
            except OSError as error:
                raise RunFileError(f"cannot lock {lock}: {error.strerror}") from None
            with handle:  # closing it releases the lock
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    handle.seek(0)
                    owner = handle.read().strip() or "unknown"
                    raise RunFileError(
                        f"{self._path} is in use by another torchcf process (pid "
                        f"{owner}); wait for it to end, or use another directory"
                    ) from None
                _write_owner(handle)
                _HELD[key] = 1
                try:
                    yield self
                finally:
                    del _HELD[key]
        finally:
            if created and [p.name for p in self._path.iterdir()] in ([], [LOCK_NAME]):
                lock.unlink(missing_ok=True)
                self._path.rmdir()
            elif not lock_existed and not self.config_json.exists():
                # a folder that was there and took no run keeps nothing of ours
                lock.unlink(missing_ok=True)

    def holds_run(self) -> bool:
        """Whether a run started here (a checkpoint) or finished (a summary)."""
        return self.checkpoint.exists() or self.summary_json.exists()

    def foreign_entries(self) -> list[str]:
        """The names in the directory when it is someone else's: it exists,
        holds entries (hidden ones aside) and no run ever started here (no
        ``config.json``, the first file a run writes); else ``[]``. A pair
        extraction, a project folder or the home directory is not a place to
        write a run into."""
        if not self._path.is_dir() or self.config_json.exists():
            return []
        return sorted(
            p.name for p in self._path.iterdir() if not p.name.startswith(".")
        )

    def has_checkpoint(self) -> bool:
        return self.checkpoint.exists()

    def is_trained(self) -> bool:
        """Whether training finished (``summary.json``, its last file)."""
        return self.summary_json.exists()

    def is_evaluated(self) -> bool:
        """Whether the evaluation finished (``metrics.json``, its last file)."""
        return self.metrics_json.exists()

    def is_looped(self) -> bool:
        """Whether the diagnosis loop finished (``loop.json``, its last file)."""
        return self.loop_json.exists()

    # ----------------------------------------------------------------- config
    def write_config(self, cfg: TrainConfig | JSON) -> None:
        """``config.json``: the resolved configuration (a TrainConfig, or its
        :func:`~torchcf.config.resolved_json` object)."""
        raw = resolved_json(cfg) if isinstance(cfg, TrainConfig) else cfg
        write_json(self.config_json, raw)

    def read_config(self) -> TrainConfig:
        """The run's validated configuration.

        Raises:
            RunFileError: ``config.json`` missing, unreadable or corrupted.
            ConfigError: not a valid configuration (message naming the file).
        """
        raw = _without_retired(self.read_config_json())
        try:
            return validate_config(raw)
        except ConfigError as error:
            raise ConfigError(f"{self.config_json}: {error}") from None

    def read_config_json(self) -> JSON:
        """``config.json`` as a JSON object, not validated.

        Raises:
            RunFileError: missing, unreadable or corrupted.
        """
        self._require(self.config_json, f"{self._path} holds no run (no config.json)")
        return read_json_object(self.config_json)

    # ------------------------------------------------------------- checkpoint
    def save_checkpoint(self, obj: TorchPayload) -> None:
        """``checkpoint.pt`` (a full disk keeps the previous one intact)."""
        atomic_torch_save(obj, self.checkpoint)

    def load_checkpoint(self) -> TorchPayload:
        """The checkpoint as saved (its format is the trainer's to check).

        Raises:
            RunFileError: missing, unreadable, truncated, corrupted, or not a
                dictionary.
        """
        self._require(self.checkpoint, f"no checkpoint.pt in {self._path}")
        raw = read_torch(self.checkpoint)
        if not isinstance(raw, dict):
            raise RunFileError(
                f"{self.checkpoint} is corrupted: a {type(raw).__name__}, not a "
                "checkpoint"
            )
        return raw

    # -------------------------------------------------------------- posterior
    def save_posterior(self, posterior: Posterior) -> None:
        """``posterior.pt``."""
        posterior.save(self.posterior_pt)

    def load_posterior(self) -> Posterior:
        """The learned particle set.

        Raises:
            RunFileError: missing, unreadable, truncated or not a posterior.
        """
        self._require(self.posterior_pt, self._unfinished("posterior.pt"))
        return Posterior.load(self.posterior_pt)

    # ---------------------------------------------------------------- summary
    def write_summary(self, summary: RunSummary | RecalibrationSummary) -> None:
        """``summary.json``, the last file of training (a training's
        :class:`~torchcf.runs.summary.RunSummary`) or of a re-calibration
        (:class:`~torchcf.runs.summary.RecalibrationSummary`)."""
        write_json(self.summary_json, summary.to_json())

    def read_summary(self) -> RunSummary | RecalibrationSummary:
        """The summary: a training's :class:`~torchcf.runs.summary.RunSummary`,
        or a re-calibration's :class:`~torchcf.runs.summary.RecalibrationSummary`
        (the one whose file holds a ``recalibration`` entry).

        Raises:
            RunFileError: missing (the run is not trained), unreadable,
                truncated, not an object, without its ``dataset`` or
                ``pairwise`` entry, or not a summary this release reads.
        """
        self._require(self.summary_json, self._unfinished("summary.json"))
        raw = read_json_object(self.summary_json)
        for key in SUMMARY_KEYS:
            if key not in raw:
                raise RunFileError(f"{self.summary_json}: no {key!r} entry")
        kind = RecalibrationSummary if "recalibration" in raw else RunSummary
        try:
            return kind.from_json(raw)
        except ValueError as error:
            raise RunFileError(f"{self.summary_json}: {error}") from None

    # ---------------------------------------------------------------- metrics
    def write_metrics(self, metrics: Evaluation | CrossvalResult) -> None:
        """``metrics.json``, the last file of the evaluation (an
        :class:`~torchcf.runs.metrics.Evaluation`) or of a cross-validation
        (its :class:`~torchcf.runs.metrics.CrossvalResult`, in its folder)."""
        write_json(self.metrics_json, metrics.to_json())

    def read_metrics(self) -> Evaluation:
        """The run's evaluation (:class:`~torchcf.runs.metrics.Evaluation`).

        Raises:
            RunFileError: missing (not evaluated), unreadable, truncated, not an
                object, without its ``hybrid`` entry, or not an evaluation this
                release reads (one written by another release: evaluate the
                run again).
        """
        self._require(
            self.metrics_json,
            f"{self._path} is not evaluated (no metrics.json); run "
            f"torchcf evaluate {self._path}",
        )
        raw = read_json_object(self.metrics_json)
        if not isinstance(raw.get("hybrid"), dict):
            raise RunFileError(f"{self.metrics_json} is corrupted: no 'hybrid' entry")
        try:
            return Evaluation.from_json(raw)
        except ValueError as error:
            raise RunFileError(
                f"{self.metrics_json}: {error}; evaluate the run again "
                f"(torchcf evaluate {self._path})"
            ) from None

    def read_crossval(self) -> CrossvalResult:
        """A cross-validation's mean over its folds (its folder's
        ``metrics.json``: :class:`~torchcf.runs.metrics.CrossvalResult`).

        Raises:
            RunFileError: missing (the cross-validation has not finished),
                unreadable, truncated, not an object, or not a
                cross-validation's.
        """
        self._require(
            self.metrics_json,
            f"{self._path}: the cross-validation has not finished (no metrics.json)",
        )
        raw = read_json_object(self.metrics_json)
        try:
            return CrossvalResult.from_json(raw)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise RunFileError(
                f"{self.metrics_json}: not a cross-validation's metrics "
                f"({type(error).__name__}: {error})"
            ) from None

    def discard_metrics(self) -> None:
        """Remove ``metrics.json``: a stale evaluation must not outlive a failure
        of the next one and pass for its result.

        Raises:
            RunFileError: it cannot be removed.
        """
        remove_file(self.metrics_json)

    # ------------------------------------------------------------------- loop
    def write_loop(self, result: JSON, markdown: str) -> None:
        """``loop.md``, then ``loop.json`` last: its presence says the loop
        finished."""
        atomic_write_text(self.loop_md, markdown)
        write_json(self.loop_json, result)

    def read_loop(self) -> JSON:
        """The diagnosis loop's result.

        Raises:
            RunFileError: missing (the loop has not finished), unreadable,
                truncated or not an object.
        """
        self._require(
            self.loop_json, f"{self._path}: the loop has not finished (no loop.json)"
        )
        return read_json_object(self.loop_json)

    # --------------------------------------------------------------- the run
    def load_run(
        self,
    ) -> tuple[TrainConfig, Posterior, RunSummary | RecalibrationSummary]:
        """The configuration, posterior and summary of a finished run (a
        re-calibration's summary in the diagnosis loop's run directories).

        ``config.json`` must be the configuration the run was trained with:
        its hash (:func:`~torchcf.config.config_hash`, which leaves out what
        does not change the result, ``eval`` and ``output`` among them) must be
        the one ``summary.json`` recorded (a training's), so that an edited
        config cannot evaluate or diagnose the particles on other data under
        its label.

        Raises:
            RunFileError: one of the three missing (the run is not finished),
                unreadable or corrupted (one line naming it), or ``config.json``
                changed since training.
            ConfigError: ``config.json`` is not a valid configuration.
        """
        for path in (self.config_json, self.posterior_pt, self.summary_json):
            self._require(path, self._unfinished(path.name))
        cfg, summary = self.read_config(), self.read_summary()
        if isinstance(summary, RunSummary) and config_hash(cfg) != summary.config_hash:
            raise RunFileError(
                f"{self.config_json} is not the config {self._path} was trained "
                f"with (hash {config_hash(cfg)}, trained {summary.config_hash}): it "
                "was edited after training (or written by another torchcf "
                "version); restore it, or train a new run"
            )
        return cfg, self.load_posterior(), summary

    # ---------------------------------------------------------------- helpers
    def _unfinished(self, name: str) -> str:
        return f"{self._path} holds no finished run (no {name}); train it first"

    @staticmethod
    def _require(path: Path, message: str) -> None:
        if not path.exists():
            raise RunFileError(message)


__all__ = ["LOCK_NAME", "SUMMARY_KEYS", "RunDir"]
