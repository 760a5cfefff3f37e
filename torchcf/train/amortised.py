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

from ..amortised import (
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
from ..config import TrainConfig
from ..data import PairSet
from ..runs.directory import RunDir
from ..system.signals import StopRequest


def amortised_samples(
    cfg: TrainConfig,
    pairs: PairSet,
    run: RunDir,
    resume: bool,
    stop: StopRequest | None = None,
) -> PairPosteriors:
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
        Every training pair's samples (:class:`~torchcf.amortised.PairPosteriors`).
    """
    settings = cfg.abc.amortised
    space = ParameterSpace(
        [spec.model for spec in cfg.models],
        [spec.bounds() for spec in cfg.models],
    )
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
    estimator = new_estimator(space, seed=cfg.abc.seed)
    checkpoint = run.amortised_checkpoint
    session = Session(
        checkpoint=checkpoint,
        resume=resume and checkpoint.exists(),
        stop=stop,
    )
    train_estimator(estimator, simulator, training, session)
    return infer(estimator, pairs, settings.samples_per_pair, seed=cfg.abc.seed)


__all__ = ["amortised_samples"]
