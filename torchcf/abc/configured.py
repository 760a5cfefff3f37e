"""The engine's pieces as a run config sets them: how particles are simulated
(:func:`rollout_of`) and the refinement's settings (:func:`smc_settings`).

Training (:mod:`torchcf.train`) and the loop's re-calibration
(:mod:`torchcf.diagnose.retrain`), which trains models as the run did, both
build them here, so that they cannot drift apart.
"""

from __future__ import annotations

import torch

from ..config import TrainConfig
from ..data import PairSet
from .rejection import Rollout
from .smc import SMCSettings


def rollout_of(cfg: TrainConfig, pairs: PairSet, device: torch.device) -> Rollout:
    """How the run's particles are simulated (layout, precision, chunks)."""
    return Rollout(
        pairs,
        paired=cfg.abc.layout == "paired",
        dtype=getattr(torch, cfg.dtype),
        device=device,
        weights=tuple(cfg.abc.weights),
        compile=cfg.compile,
        chunk_size=cfg.abc.chunk_size,
        early_rejection=cfg.abc.early_rejection,
    )


def smc_settings(cfg: TrainConfig) -> SMCSettings:
    """The refinement's settings of a config (section ``abc.smc``)."""
    return SMCSettings(**cfg.abc.smc.model_dump())


__all__ = ["rollout_of", "smc_settings"]
