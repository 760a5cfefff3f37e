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

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

FORMAT = "torchcf.posterior/1"


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
        """Read a ``posterior.pt``; ValueError if it is not one."""
        raw = torch.load(Path(path), map_location="cpu", weights_only=True)
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise ValueError(f"{path}: not a torchcf posterior ({FORMAT})")
        hybrid = {
            name: ModelParticles(
                tuple(p["param_names"]),
                p["theta"],
                p["score"],
                p["pair_ids"],
                p["particle_index"],
            )
            for name, p in raw["hybrid"].items()
        }
        return cls(
            dataset=raw["dataset"],
            selection=raw["selection"],
            top_n=int(raw["top_n"]),
            models=tuple(raw["models"]),
            shares=dict(raw["shares"]),
            train_pair_ids=raw["train_pair_ids"],
            hybrid=hybrid,
            buffers=raw["buffers"],
        )


def atomic_torch_save(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` so that a crash never leaves a partial file."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as handle:
        torch.save(obj, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def atomic_write_text(path: Path, text: str) -> None:
    """Write a text file atomically."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


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
    "atomic_torch_save",
    "atomic_write_text",
    "json_safe",
]
