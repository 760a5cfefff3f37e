"""The one translation from a run config to a calibration's objects.

A run config (:class:`~torchcf.config.TrainConfig`) names its calibration in
sections ``models``, ``abc``, ``device``, ``dtype``, ``compile`` and
``plausibility``; :func:`setup_of` turns them into a
:class:`~torchcf.calibration.CalibrationSetup` (the rollout, the prior boxes,
the sampler, the selection, the seed), the objects :func:`~torchcf.
calibration.calibrate` takes. Training (:mod:`torchcf.train`) and the loop's
re-calibration (:mod:`torchcf.diagnose`) both build theirs here, so they cannot
drift apart; below them nothing reads the config.

Units: SI throughout (m, s, m/s).
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..abc.rejection import Rollout
from ..abc.screen import PlausibilityScreen
from ..abc.smc import SMCSettings
from ..amortised import (
    EncoderSettings,
    EstimatorSettings,
    NoiseLevels,
    TrainingSettings,
)
from ..config import AmortisedConfig, AmortisedNetworkConfig, TrainConfig
from ..data import PairSet
from .calibrate import CalibrationSetup
from .methods import SMC, Amortised, Method, Refinement, Rejection, SelectionRule


def setup_of(
    cfg: TrainConfig,
    pairs: PairSet,
    device: torch.device | None = None,
    screen: PlausibilityScreen | None = None,
) -> CalibrationSetup:
    """The calibration of ``cfg`` on ``pairs``, simulated on ``device``
    (default: ``cfg.device``), with the plausibility filter ``screen``.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 40.0 + 15.0 * t, torch.full_like(t, 15.0)  # [m], [m/s]
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 30.0, v, a], dt=0.1)
        >>> from torchcf.config import TrainConfig
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm", "ovm"],
        ...                   abc={"n_particles": 5000})
        >>> setup = setup_of(cfg, pairs)
        >>> setup.method, [model.name for model in setup.priors]
        (Rejection(n_particles=5000), ['idm', 'ovm'])
    """
    abc = cfg.abc
    rollout = Rollout(
        pairs,
        paired=abc.layout == "paired",
        dtype=getattr(torch, cfg.dtype),
        device=device if device is not None else torch.device(cfg.device),
        weights=tuple(abc.weights),
        compile=cfg.compile,
        chunk_size=abc.chunk_size,
        early_rejection=abc.early_rejection,
    )
    priors = {spec.model: spec.bounds(torch.float64) for spec in cfg.models}
    selection = SelectionRule(
        top_n=abc.top_n,
        sensitivity_n=tuple(abc.sensitivity_n),
        mode=abc.selection,
        global_size=abc.global_size,
    )
    return CalibrationSetup(
        rollout, priors, method_of(cfg), selection, abc.seed, screen
    )


def method_of(cfg: TrainConfig) -> Method:
    """The sampler of section ``abc``."""
    abc = cfg.abc
    if abc.method == "smc":
        return SMC(abc.n_particles, SMCSettings(**abc.smc.model_dump()))
    if abc.method == "amortised":
        return _amortised(abc.amortised, abc.seed, abc.checkpoint_every, cfg.compile)
    return Rejection(abc.n_particles)


def _amortised(
    settings: AmortisedConfig, seed: int, checkpoint_every: float, compile: str
) -> Amortised:
    """The amortised sampler of section ``abc.amortised``."""
    refine = settings.refine
    return Amortised(
        samples_per_pair=settings.samples_per_pair,
        window_steps=settings.window_steps,
        noise=NoiseLevels(*settings.noise) if settings.noise is not None else None,
        training=TrainingSettings(
            simulations_per_epoch=settings.simulations_per_epoch,
            reuse=settings.reuse,
            max_epochs=settings.max_epochs,
            max_seconds=settings.max_seconds,
            validation_simulations=settings.validation_simulations,
            batch_size=settings.batch_size,
            learning_rate=settings.learning_rate,
            patience=settings.patience,
            checkpoint_every=checkpoint_every,
            seed=seed,
        ),
        network=estimator_settings(settings.network),
        refine=None
        if refine.rounds == 0
        else Refinement(
            rounds=refine.rounds,
            per_pair=refine.per_pair,
            population=refine.population,
            quantile=refine.quantile,
        ),
        estimator=Path(settings.estimator) if settings.estimator is not None else None,
        compile=compile,
    )


def estimator_settings(network: AmortisedNetworkConfig) -> EstimatorSettings:
    """The estimator's size of ``abc.amortised.network``; the encoder's first
    three convolutions (at most) halve the time axis."""
    encoder = EncoderSettings(
        width=network.encoder_width,
        depth=network.encoder_depth,
        strided=min(EncoderSettings.strided, network.encoder_depth),
        embedding=network.embedding,
    )
    return EstimatorSettings(
        encoder=encoder,
        head_width=network.head_width,
        transforms=network.transforms,
        flow_width=network.flow_width,
        bins=network.bins,
    )


__all__ = ["estimator_settings", "method_of", "setup_of"]
