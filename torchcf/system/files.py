"""Atomic writes and checked reads of the files torchcf writes.

The low level under :mod:`torchcf.runs.directory` (which knows the names and layout of a
run directory); it knows nothing of runs. Every failure is a
:class:`RunFileError` whose one-line message names the file and the reason: a
file missing, unreadable, truncated or corrupted, a directory that cannot be
created or written, a full disk.

Writes are atomic: the data go to a temporary file beside the target
(``.<name>.tmp<pid>``), are flushed to disk and replace the target in one
rename, so the target holds its old content or the new one, never a mix, whatever
interrupts the write (kill -9, Ctrl-C, a full disk); a failed write removes the
temporary file.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from .errors import TorchcfError

StrPath = str | os.PathLike[str]
#: A JSON object as a file holds it: what :func:`read_json_object` reads and
#: :func:`write_json` writes (results travel as typed records and become this
#: only at the file's edge, by their ``to_json``).
JSON = dict[str, Any]
#: A dict as :func:`atomic_torch_save` writes it and :func:`read_torch` reads it
#: back (tensors and plain data: a checkpoint, a posterior file, a state dict).
TorchPayload = dict[str, Any]


class RunFileError(TorchcfError, ValueError):
    """A file of a run that cannot be read or written (one-line message naming it).

    Missing, unreadable, truncated or corrupted, or of the wrong kind on reading;
    a directory that cannot be created or written, or a full disk on writing (the
    file then keeps its previous content). Also a ``ValueError``, as the
    posterior's read error it replaces was: the content is not what it must be.
    """


# ------------------------------------------------------------------ writing
def atomic_write_text(path: StrPath, text: str) -> None:
    """Write a UTF-8 text file atomically (module docstring).

    Raises:
        RunFileError: it cannot be written (``path`` is left as it was).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import atomic_write_text
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     atomic_write_text(Path(folder) / "notes.md", "# Notes\\n")
        ...     print(sorted(p.name for p in Path(folder).iterdir()))  # no temporary
        ['notes.md']
    """
    _atomic_write(Path(path), lambda handle: handle.write(text), binary=False)


def atomic_torch_save(obj: Any, path: StrPath) -> None:
    """``torch.save(obj)`` to ``path`` atomically (module docstring).

    A full disk is reported as such: ``torch.save`` turns the ``OSError`` of a
    failed write into a ``RuntimeError`` while closing its zip archive, which
    becomes a :class:`RunFileError` with the operating system's reason.

    Raises:
        RunFileError: any failure of the write (``path`` keeps its previous
            content, loadable; no temporary file is left).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import torch
        >>> from torchcf.system.files import atomic_torch_save, read_torch
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     atomic_torch_save({"theta": torch.ones(2, 6)}, Path(folder, "state.pt"))
        ...     loaded = read_torch(Path(folder) / "state.pt")
        >>> loaded["theta"].shape
        torch.Size([2, 6])
    """
    _atomic_write(Path(path), lambda handle: torch.save(obj, handle), binary=True)


def write_json(path: StrPath, obj: Any) -> None:
    """``obj`` as indented JSON (via :func:`json_safe`), atomically.

    Raises:
        RunFileError: it cannot be written (``path`` is left as it was).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import read_json_object, write_json
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_json(Path(folder) / "metrics.json", {"ws": float("inf"), "n": 3})
        ...     print(read_json_object(Path(folder) / "metrics.json"))
        {'ws': 'inf', 'n': 3}
    """
    text = json.dumps(json_safe(obj), indent=2, allow_nan=False) + "\n"
    atomic_write_text(path, text)


@contextlib.contextmanager
def writing(path: StrPath) -> Iterator[None]:
    """Report an ``OSError`` raised inside the block as a :class:`RunFileError`
    (``cannot write PATH: reason``), for writers that are not this module's (a
    figure's ``savefig``).

    Examples:
        >>> from torchcf.system.files import RunFileError, writing
        >>> try:
        ...     with writing("figure.png"):
        ...         raise PermissionError(13, "Permission denied")
        ... except RunFileError as error:
        ...     print(error)
        cannot write figure.png: Permission denied
    """
    try:
        yield
    except OSError as error:
        raise RunFileError(f"cannot write {path}: {_reason(error)}") from error


def ensure_directory(
    path: StrPath, what: str = "directory", *, keep: bool = True
) -> Path:
    """Create ``path`` (and its parents) and check that a file can be written in
    it, with a real probe write: a missing permission or a full disk fails here,
    before any work whose result could not be written.

    Args:
        path: the directory.
        what: how messages name it ("output directory", "report directory").
        keep: False removes again the directories created here (a check that
            leaves the file system as it was).

    Returns:
        ``path`` as a Path.

    Raises:
        RunFileError: ``path`` exists and is not a directory, cannot be created,
            or cannot be written.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import ensure_directory
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     out = ensure_directory(Path(folder, "run", "report"))
        ...     print(out.is_dir(), list(out.iterdir()))  # the probe file is gone
        True []
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunFileError(f"{what} {path} exists and is not a directory")
    missing = []  # the directories created here, deepest first
    folder = path
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    try:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise RunFileError(
                f"cannot create the {what} {path}: {_reason(error)}"
            ) from error
        probe = path / f".probe.tmp{os.getpid()}"
        try:
            # One page: a file system that cannot hold one more page is full.
            _write_synced(probe, lambda handle: handle.write(b"\0" * 4096), binary=True)
        except OSError as error:
            raise RunFileError(
                f"cannot write in the {what} {path}: {_reason(error)}"
            ) from error
        finally:
            _discard(probe)
    finally:
        if not keep:
            for created in missing:
                with contextlib.suppress(OSError):
                    created.rmdir()
    return path


@contextlib.contextmanager
def no_empty_folder_left(path: StrPath) -> Iterator[None]:
    """A command that writes under ``path`` and fails leaves no empty folder
    there: on any failure, the directories under ``path`` (and ``path``) that
    hold no file are removed, if ``path`` did not exist before. A folder that
    holds a file (a checkpoint to resume from) stays as it is.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import no_empty_folder_left
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     out = Path(folder) / "run"
        ...     try:
        ...         with no_empty_folder_left(out):
        ...             (out / "tensorboard").mkdir(parents=True)
        ...             raise ValueError("bad config")
        ...     except ValueError:
        ...         pass
        ...     print(out.exists())
        False
    """
    path = Path(path)
    existed = path.exists()
    try:
        yield
    except BaseException:
        if not existed and path.is_dir():
            for folder, _, _ in sorted(os.walk(path), key=lambda w: -len(w[0])):
                with contextlib.suppress(OSError):
                    Path(folder).rmdir()  # refuses a folder that holds anything
        raise


def remove_file(path: StrPath) -> None:
    """Remove ``path`` if it exists.

    Raises:
        RunFileError: it exists and cannot be removed.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import remove_file
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "stale.lock"
        ...     _ = path.write_text("")
        ...     remove_file(path)
        ...     remove_file(path)  # already gone: nothing to do
        ...     print(path.exists())
        False
    """
    try:
        Path(path).unlink(missing_ok=True)
    except OSError as error:
        raise RunFileError(f"cannot remove {path}: {_reason(error)}") from error


def _atomic_write(path: Path, write: Callable[[IO[Any]], Any], *, binary: bool) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        _write_synced(tmp, write, binary=binary)
        os.replace(tmp, path)
    except Exception as error:
        # OSError, and whatever a serialiser makes of one (torch.save: a
        # RuntimeError while closing its archive on a full disk).
        _discard(tmp)
        raise RunFileError(f"cannot write {path}: {_reason(error)}") from error
    except BaseException:
        _discard(tmp)  # interrupted (Ctrl-C): no stray temporary file
        raise
    _sync_directory(path.parent)


def _write_synced(path: Path, write: Callable[[IO[Any]], Any], *, binary: bool) -> None:
    mode, encoding = ("wb", None) if binary else ("w", "utf-8")
    with open(path, mode, encoding=encoding) as handle:
        write(handle)
        handle.flush()
        os.fsync(handle.fileno())


def _sync_directory(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: not every system can)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _discard(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink()


# ------------------------------------------------------------------ reading
def read_json_object(path: StrPath) -> JSON:
    """The JSON object in ``path``.

    Raises:
        RunFileError: missing, unreadable, not UTF-8, not JSON (truncated) or not
            a JSON object.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.system.files import RunFileError, read_json_object
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "summary.json"
        ...     _ = path.write_text('{"pairs": 4')  # truncated
        ...     try:
        ...         read_json_object(path)
        ...     except RunFileError as error:
        ...         print(type(error).__name__)
        RunFileError
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RunFileError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise RunFileError(f"{path} is corrupted: not UTF-8 text") from None
    except OSError as error:
        raise RunFileError(f"cannot read {path}: {_reason(error)}") from error
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as error:
        raise RunFileError(
            f"{path} is corrupted: {error.msg} at line {error.lineno} column "
            f"{error.colno}"
        ) from None
    if not isinstance(raw, dict):
        raise RunFileError(f"{path} is corrupted: not a JSON object")
    return raw


def read_torch(path: StrPath) -> Any:
    """``torch.load(path, map_location="cpu", weights_only=True)``.

    Raises:
        RunFileError: missing, unreadable, truncated or corrupted, or holding
            more than tensors and plain data.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import torch
        >>> from torchcf.system.files import read_torch
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     torch.save({"step": torch.tensor(3)}, Path(folder) / "checkpoint.pt")
        ...     print(int(read_torch(Path(folder) / "checkpoint.pt")["step"]))
        3
    """
    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise RunFileError(f"{path}: no such file") from None
    except OSError as error:
        raise RunFileError(f"cannot read {path}: {_reason(error)}") from error
    except Exception as error:  # noqa: BLE001 - unpickling raises anything
        reason = _one_line(error)
        # weights_only refusals come with a page of advice; keep the cause.
        _, found, cause = reason.partition("WeightsUnpickler error:")
        raise RunFileError(
            f"{path}: unreadable or corrupted ({cause.strip() if found else reason})"
        ) from None


# ------------------------------------------------------------------- helpers
def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as the strings "inf", "-inf", "nan" (JSON has
    no such numbers) and numpy scalars as Python numbers, recursively.

    Examples:
        >>> import numpy as np
        >>> from torchcf.system.files import json_safe
        >>> json_safe({"ws": float("inf"), "e_p": np.float64(0.5), "e": [float("nan")]})
        {'ws': 'inf', 'e_p': 0.5, 'e': ['nan']}
    """
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


def from_json_safe(value: Any) -> Any:
    """The inverse of :func:`json_safe` for what JSON read back: the strings
    "inf", "-inf", "nan" as floats again, recursively."""
    if isinstance(value, dict):
        return {k: from_json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [from_json_safe(v) for v in value]
    if value in ("inf", "-inf", "nan"):
        return float(value)
    return value


def _reason(error: BaseException) -> str:
    """The operating system's reason behind ``error`` ("No space left on device"),
    also where a library wrapped the ``OSError`` in an error of its own; else
    ``error``'s message on one line."""
    seen: set[int] = set()
    cause: BaseException | None = error
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, OSError) and cause.strerror:
            return cause.strerror
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return _one_line(error)


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


__all__ = [
    "JSON",
    "RunFileError",
    "TorchPayload",
    "atomic_torch_save",
    "atomic_write_text",
    "ensure_directory",
    "json_safe",
    "no_empty_folder_left",
    "read_json_object",
    "read_torch",
    "remove_file",
    "write_json",
    "writing",
]
