"""What the loop takes from a run's config, built once (:meth:`LoopSetup.of`).

The loop's stages read the ``diagnose`` section, the run's prior boxes, its
top-N, its seeds and how it simulated; :class:`LoopSetup` carries exactly
these, so that below :func:`torchcf.diagnose.loop.plan_loop` (and the
re-calibration, which trains as the run trained) nothing takes the whole
config.

Units: SI throughout (m, s, m/s).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..abc.rejection import Rollout
from ..abc.smc import SMCSettings
from ..config import DiagnoseConfig, TrainConfig, config_hash
from ..data import PairSet


@dataclass(frozen=True)
class LoopSetup:
    """The loop's settings and the run's, as objects.

    Attributes:
        settings: the ``diagnose`` section.
        priors: per run model name, its prior box ``(K, 2)`` float64.
        top_n: the run's N (``abc.top_n``).
        seed: the attribution's prior draws and local search (``diagnose.seed``,
            else the run's ``abc.seed``).
        smc: the run's SMC settings where ``diagnose.method = "smc"``, else None.
        dtype: the run's simulation precision.
        device: where it simulated.
        weights: its score weights of (position, speed, acceleration).
        compile: its compile choice.
        run_hash: the run config's hash (a ledger's key).

    Examples:
        >>> from torchcf.config import TrainConfig
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm"],
        ...                   abc={"seed": 4})
        >>> setup = LoopSetup.of(cfg)
        >>> setup.seed, setup.top_n, tuple(setup.priors["idm"].shape)
        (4, 5, (6, 2))
    """

    settings: DiagnoseConfig
    priors: dict[str, Tensor]
    top_n: int
    seed: int
    smc: SMCSettings | None
    dtype: torch.dtype
    device: torch.device
    weights: tuple[float, float, float]
    compile: str
    run_hash: str

    @classmethod
    def of(cls, cfg: TrainConfig) -> LoopSetup:
        """The setup of a run's config."""
        settings = cfg.diagnose
        return cls(
            settings=settings,
            priors={spec.name: spec.bounds(torch.float64) for spec in cfg.models},
            top_n=cfg.abc.top_n,
            seed=cfg.abc.seed if settings.seed is None else settings.seed,
            smc=SMCSettings(**cfg.abc.smc.model_dump())
            if settings.method == "smc"
            else None,
            dtype=getattr(torch, cfg.dtype),
            device=torch.device(cfg.device),
            weights=tuple(cfg.abc.weights),
            compile=cfg.compile,
            run_hash=config_hash(cfg),
        )

    def rollout(self, pairs: PairSet) -> Rollout:
        """How the loop simulates particles on ``pairs``: the run's precision,
        device, score weights and compile choice, each particle on its own
        pair."""
        return Rollout(pairs, True, self.dtype, self.device, self.weights, self.compile)


__all__ = ["LoopSetup"]
