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

import os
from dataclasses import dataclass

from torch import Tensor

from ..system.files import (
    RunFileError,
    TorchPayload,
    atomic_torch_save,
    read_torch,
)

FORMAT = "torchcf.posterior/1"


@dataclass(frozen=True)
class ModelParticles:
    """One model's particles in the hybrid.

    Examples:
        >>> import torch
        >>> from torchcf.posterior import ModelParticles
        >>> idm = ModelParticles(
        ...     param_names=("a", "b", "v0", "T", "s0", "delta"),
        ...     theta=torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 2).double(),
        ...     score=torch.tensor([0.4, 0.6], dtype=torch.float64),
        ...     pair_ids=torch.tensor([0, 1]),  # the training pair each was kept for
        ...     particle_index=torch.tensor([7, 3]),
        ... )
        >>> len(idm), idm.theta.shape
        (2, torch.Size([2, 6]))
    """

    param_names: tuple[str, ...]
    theta: Tensor  # (h, K) float64
    score: Tensor  # (h,) float64
    pair_ids: Tensor  # (h,) int64
    particle_index: Tensor  # (h,) int64

    def __len__(self) -> int:
        return self.theta.shape[0]


@dataclass(frozen=True)
class Posterior:
    """``Theta_hybrid`` with the shares and the buffers it came from.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import torch
        >>> from torchcf.posterior import ModelParticles
        >>> idm = ModelParticles(
        ...     param_names=("a", "b", "v0", "T", "s0", "delta"),
        ...     theta=torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 2).double(),
        ...     score=torch.tensor([0.4, 0.6], dtype=torch.float64),
        ...     pair_ids=torch.tensor([0, 1]),  # the training pair each was kept for
        ...     particle_index=torch.tensor([7, 3]),
        ... )
        >>> from torchcf.posterior import Posterior
        >>> posterior = Posterior(
        ...     dataset="demo", selection="per_pair", top_n=1, models=("idm",),
        ...     shares={"idm": 1.0}, train_pair_ids=torch.tensor([0, 1]),
        ...     hybrid={"idm": idm}, buffers={"idm": {}},
        ... )
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     posterior.save(Path(folder) / "posterior.pt")
        ...     back = Posterior.load(Path(folder) / "posterior.pt")
        >>> back.models, len(back.hybrid["idm"]), back.shares
        (('idm',), 2, {'idm': 1.0})
    """

    dataset: str
    selection: str
    top_n: int
    models: tuple[str, ...]
    shares: dict[str, float]
    train_pair_ids: Tensor
    hybrid: dict[str, ModelParticles]
    buffers: dict[str, dict[str, Tensor]]

    def to_dict(self) -> TorchPayload:
        """The content of ``posterior.pt``."""
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
        """Write atomically (temporary file, then rename).

        Raises:
            RunFileError: it cannot be written (a full disk: the previous file is
                kept intact).
        """
        atomic_torch_save(self.to_dict(), path)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Posterior:
        """Read a ``posterior.pt``.

        Raises:
            RunFileError: the file is missing, unreadable, truncated, or not a
                torchcf posterior of this format (one-line message).
        """
        raw = read_torch(path)
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise RunFileError(f"{path}: not a torchcf posterior ({FORMAT})")
        try:
            return cls._from_dict(raw)
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            reason = " ".join(str(error).split())
            raise RunFileError(
                f"{path}: malformed torchcf posterior ({type(error).__name__}: "
                f"{reason})"
            ) from None

    @classmethod
    def _from_dict(cls, raw: TorchPayload) -> Posterior:
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


__all__ = ["FORMAT", "ModelParticles", "Posterior"]
