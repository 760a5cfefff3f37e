"""The amortised method in a training run (``abc.method = "amortised"``).

Before the models' streams, the run trains one estimator
(:mod:`torchcf.amortised`) on simulations of the config's models, over their
configured prior boxes, behind the training pairs' leaders, and draws
``abc.amortised.samples_per_pair`` samples of (model, parameters) for every
training pair. Each model's stream is then its samples
(:func:`torchcf.amortised.run_amortised`), scored and kept in its per-pair
buffer as rejection's particles are, so that ``posterior.pt``, the shares and
the parameter tables come out as for rejection.

The estimator's training writes its own checkpoint, ``amortised.pt`` in the
run directory (:attr:`RunDir.amortised_checkpoint
<torchcf.runs.directory.RunDir.amortised_checkpoint>`), which also holds the
trained weights after the run; ``--resume`` continues it (or reads it back,
finished) and the samples, a function of the weights, the seed and each
pair, are drawn again identical.
"""

from __future__ import annotations

from typing import NamedTuple

from ..amortised import (
    AmortisedEstimator,
    EncoderSettings,
    EstimatorSettings,
    NoiseLevels,
    PairPosteriors,
    ParameterSpace,
    Session,
    SimulationSettings,
    TrainingSettings,
    TrainingSimulator,
    infer,
    new_estimator,
    train_estimator,
)
from ..config import AmortisedNetworkConfig, TrainConfig
from ..data import PairSet
from ..runs.directory import RunDir
from ..system.files import read_torch
from ..system.signals import StopRequest
from .summary import AmortisedResult


class AmortisedSamples(NamedTuple):
    """The training pairs' samples and the estimator's record.

    Attributes:
        samples: every training pair's samples of (model, parameters).
        record: how the estimator was trained (``summary.json``'s
            ``amortised``).
    """

    samples: PairPosteriors
    record: AmortisedResult


def amortised_samples(
    cfg: TrainConfig,
    pairs: PairSet,
    run: RunDir,
    resume: bool,
    stop: StopRequest | None = None,
) -> AmortisedSamples:
    """Train (or resume, or read back) the run's estimator and draw the
    training pairs' samples.

    Args:
        cfg: the run's config (``abc.amortised``, ``abc.seed``, the models
            and their boxes).
        pairs: the training pairs.
        run: the run directory (the estimator's checkpoint).
        resume: continue the estimator's checkpoint where there is one.
        stop: a stop request checked between the training's batches.

    Returns:
        Every training pair's samples
        (:class:`~torchcf.amortised.PairPosteriors`) and the training's record.
    """
    settings = cfg.abc.amortised
    space = parameter_space(cfg)
    noise = (
        NoiseLevels(*settings.noise)
        if settings.noise is not None
        else NoiseLevels.of_pairs(pairs)
    )
    simulator = TrainingSimulator(
        space,
        pairs,
        SimulationSettings(window_steps=settings.window_steps, noise=noise),
        seed=cfg.abc.seed,
    )
    training = TrainingSettings(
        simulations_per_epoch=settings.simulations_per_epoch,
        reuse=settings.reuse,
        max_epochs=settings.max_epochs,
        max_seconds=settings.max_seconds,
        validation_simulations=settings.validation_simulations,
        batch_size=settings.batch_size,
        learning_rate=settings.learning_rate,
        patience=settings.patience,
        checkpoint_every=cfg.abc.checkpoint_every,
        seed=cfg.abc.seed,
    )
    estimator = new_estimator(
        space, estimator_settings(settings.network), seed=cfg.abc.seed
    )
    checkpoint = run.amortised_checkpoint
    session = Session(
        checkpoint=checkpoint,
        resume=resume and checkpoint.exists(),
        stop=stop,
    )
    result = train_estimator(estimator, simulator, training, session)
    samples = infer(estimator, pairs, settings.samples_per_pair, seed=cfg.abc.seed)
    progress = result.progress
    record = AmortisedResult(
        samples_per_pair=settings.samples_per_pair,
        noise=(noise.position, noise.speed, noise.acceleration),
        epochs=len(progress.history),
        finished=progress.finished,
        simulations=progress.simulations,
        invalid=progress.invalid,
        seconds=round(progress.seconds, 3),
        validation_loss=result.best_loss,
        validation_accuracy=result.validation_accuracy,
    )
    return AmortisedSamples(samples, record)


def parameter_space(cfg: TrainConfig) -> ParameterSpace:
    """The config's models and their prior boxes, the estimator's space."""
    return ParameterSpace(
        [spec.model for spec in cfg.models],
        [spec.bounds() for spec in cfg.models],
    )


def trained_estimator(cfg: TrainConfig, run: RunDir) -> AmortisedEstimator:
    """The estimator a finished amortised run trained (its kept weights, read
    from :attr:`RunDir.amortised_checkpoint
    <torchcf.runs.directory.RunDir.amortised_checkpoint>`), in eval mode.

    Raises:
        RunFileError: the checkpoint is missing, unreadable or corrupted.
    """
    raw = read_torch(run.amortised_checkpoint)
    estimator = new_estimator(
        parameter_space(cfg),
        estimator_settings(cfg.abc.amortised.network),
        seed=cfg.abc.seed,
    )
    best = raw.get("best")
    estimator.load_state_dict(best if best is not None else raw["estimator"])
    return estimator.eval()


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


__all__ = [
    "AmortisedSamples",
    "amortised_samples",
    "estimator_settings",
    "parameter_space",
    "trained_estimator",
]
