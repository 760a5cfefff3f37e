"""The learned particle set, as written to ``posterior.pt`` by the trainer.

A plain ``torch.save`` of tensors, strings and numbers (loadable with
``torch.load(path, weights_only=True)``), so a user needs neither the training
config nor torchcf's classes to read it:

    {
      "format": "torchcf.posterior/1",
      "dataset": str, "selection": "per_pair" | "global", "top_n": int,
      "train_pair_ids": (n_train,) int64,      # full-set column of each pair
      "models": [name, ...],                   # run order
      "shares": {name: float},
      "hybrid": {name: {                       # Theta_hybrid, per model
          "param_names": [str, ...],
          "theta": (h_m, K_m) float64,         # SI units, the model's order
          "score": (h_m,) float64,
          "pair_ids": (h_m,) int64,            # the training pair it was kept for
          "particle_index": (h_m,) int64,      # j in the model's stream
      }},
      "buffers": {name: {"param_names", "score": (n_train, C), "index": (n_train, C),
                         "theta": (n_train, C, K_m)}},   # per-pair top-C, for reuse
    }
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from torch import Tensor

FORMAT = "torchcf.posterior/1"


class WriteError(RuntimeError):
    """An output file could not be written (disk full, no permission...).

    The message is one line naming the file and the operating system's reason;
    the file is left as it was before the write (see :func:`atomic_torch_save`).
    """


class PosteriorError(ValueError):
    """A file that is not a readable ``posterior.pt`` (one-line message)."""


@dataclass(frozen=True)
class ModelParticles:
    """One model's particles in the hybrid."""

    param_names: tuple[str, ...]
    theta: Tensor  # (h, K) float64
    score: Tensor  # (h,) float64
    pair_ids: Tensor  # (h,) int64
    particle_index: Tensor  # (h,) int64

    def __len__(self) -> int:
        return self.theta.shape[0]


@dataclass(frozen=True)
class Posterior:
    """``Theta_hybrid`` with the shares and the buffers it came from."""

    dataset: str
    selection: str
    top_n: int
    models: tuple[str, ...]
    shares: dict[str, float]
    train_pair_ids: Tensor
    hybrid: dict[str, ModelParticles]
    buffers: dict[str, dict[str, Any]]

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "dataset": self.dataset,
            "selection": self.selection,
            "top_n": self.top_n,
            "train_pair_ids": self.train_pair_ids,
            "models": list(self.models),
            "shares": dict(self.shares),
            "hybrid": {
                name: {
                    "param_names": list(p.param_names),
                    "theta": p.theta,
                    "score": p.score,
                    "pair_ids": p.pair_ids,
                    "particle_index": p.particle_index,
                }
                for name, p in self.hybrid.items()
            },
            "buffers": self.buffers,
        }

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write atomically (temporary file, then rename)."""
        atomic_torch_save(self.to_dict(), Path(path))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Posterior:
        """Read a ``posterior.pt``.

        Raises:
            PosteriorError: the file is missing, unreadable, truncated, or not a
                torchcf posterior of this format (one-line message).
        """
        try:
            raw = torch.load(Path(path), map_location="cpu", weights_only=True)
        except FileNotFoundError:
            raise PosteriorError(f"{path}: no such file") from None
        except Exception as error:  # noqa: BLE001 - unpickling raises anything
            raise PosteriorError(
                f"{path}: unreadable or corrupted ({_one_line(error)})"
            ) from None
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise PosteriorError(f"{path}: not a torchcf posterior ({FORMAT})")
        try:
            return cls._from_dict(raw)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise PosteriorError(
                f"{path}: malformed torchcf posterior ({type(error).__name__}: "
                f"{_one_line(error)})"
            ) from None

    @classmethod
    def _from_dict(cls, raw: dict[str, Any]) -> Posterior:
        hybrid = {}
        for name, p in raw["hybrid"].items():
            particles = ModelParticles(
                tuple(p["param_names"]),
                p["theta"],
                p["score"],
                p["pair_ids"],
                p["particle_index"],
            )
            n, k = len(particles), len(particles.param_names)
            fields = (particles.score, particles.pair_ids, particles.particle_index)
            if particles.theta.shape != (n, k) or any(t.shape != (n,) for t in fields):
                raise ValueError(f"hybrid[{name!r}]: inconsistent shapes")
            hybrid[name] = particles
        models = tuple(raw["models"])
        if set(hybrid) != set(models) or set(raw["buffers"]) != set(models):
            raise ValueError("hybrid and buffers do not list the run's models")
        return cls(
            dataset=str(raw["dataset"]),
            selection=str(raw["selection"]),
            top_n=int(raw["top_n"]),
            models=models,
            shares={str(k): float(v) for k, v in raw["shares"].items()},
            train_pair_ids=raw["train_pair_ids"],
            hybrid=hybrid,
            buffers=raw["buffers"],
        )


def atomic_torch_save(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` so that a crash never leaves a partial file.

    The data goes to a temporary file beside ``path``, is flushed to disk, and
    replaces ``path`` in one rename: ``path`` holds either its old content or the
    new one, never a mix, whatever interrupts the write (kill -9, a full disk).

    Raises:
        WriteError: the write failed (the temporary file is removed and ``path``
            keeps its previous content).
    """
    _atomic_write(Path(path), lambda handle: torch.save(obj, handle), "wb")


def atomic_write_text(path: Path, text: str) -> None:
    """Write a text file atomically (as :func:`atomic_torch_save`)."""
    _atomic_write(Path(path), lambda handle: handle.write(text), "w")


def _atomic_write(path: Path, write: Callable[[IO[Any]], Any], mode: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        encoding = None if "b" in mode else "utf-8"
        with open(tmp, mode, encoding=encoding) as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as error:
        with contextlib.suppress(OSError):
            tmp.unlink()
        reason = error.strerror or _one_line(error)
        raise WriteError(f"cannot write {path}: {reason}") from None
    except BaseException:
        # Interrupted (Ctrl-C) or failed otherwise: no stray temporary file.
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as the strings "inf", "-inf", "nan" (JSON has
    no such numbers) and numpy scalars as Python numbers, recursively."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


__all__ = [
    "FORMAT",
    "ModelParticles",
    "Posterior",
    "PosteriorError",
    "WriteError",
    "atomic_torch_save",
    "atomic_write_text",
    "json_safe",
]
