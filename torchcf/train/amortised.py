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

With ``abc.amortised.estimator`` the run trains nothing: it reads a finished
estimator of an earlier run (same models, boxes and network), copies it into
its own directory and draws its pairs' samples from it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

from ..amortised import (
    AmortisedEstimator,
    CheckpointError,
    EncoderSettings,
    EstimatorSettings,
    NoiseLevels,
    PairPosteriors,
    ParameterSpace,
    Session,
    SimulationSettings,
    TrainingProgress,
    TrainingSettings,
    TrainingSimulator,
    estimator_fingerprint,
    infer,
    load_trained,
    new_estimator,
    train_estimator,
)
from ..config import AmortisedNetworkConfig, ConfigError, TrainConfig
from ..data import PairSet
from ..runs.directory import RunDir
from ..sim.compiled import compiler_available
from ..system.files import RunFileError, atomic_torch_save, read_torch
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
    if settings.estimator is not None:
        return reused_samples(cfg, pairs, run, resume)
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
    noises = (noise.position, noise.speed, noise.acceleration)
    record = _record(cfg, result.progress, noises)
    return AmortisedSamples(_samples(cfg, estimator, pairs), record)


#: Samples (training pairs x ``samples_per_pair``) from which ``compile =
#: "auto"`` compiles the flows' sampling: below it compiling the flows on an
#: empty compile cache costs more than it saves (``tools/bench_amortised.py``;
#: ``reports/performance.md``, "Amortised calibration").
COMPILE_MIN_SAMPLES = 10_000_000


def sampling_compiled(cfg: TrainConfig, n_pairs: int) -> bool:
    """Whether the run's samples are drawn with the flows compiled
    (:func:`torchcf.amortised.infer`): the config's ``compile``, "auto" from
    :data:`COMPILE_MIN_SAMPLES` samples on where a C++ compiler is there."""
    if cfg.compile != "auto":
        return cfg.compile == "on"
    samples = n_pairs * cfg.abc.amortised.samples_per_pair
    return samples >= COMPILE_MIN_SAMPLES and compiler_available()


def parameter_space(cfg: TrainConfig) -> ParameterSpace:
    """The config's models and their prior boxes, the estimator's space."""
    return ParameterSpace(
        [spec.model for spec in cfg.models],
        [spec.bounds() for spec in cfg.models],
    )


def reused_samples(
    cfg: TrainConfig, pairs: PairSet, run: RunDir, resume: bool
) -> AmortisedSamples:
    """The training pairs' samples of the trained estimator of
    ``abc.amortised.estimator`` (no training), which is copied into the run
    directory first, so that the run keeps its estimator as a run that
    trained one does (a resumed run reads its copy).

    Raises:
        ConfigError: the estimator cannot be read or is not this config's
            (:func:`reused_checkpoint`).
    """
    settings = cfg.abc.amortised
    copy = run.amortised_checkpoint
    source = reused_source(cfg, run, resume)
    raw = reused_checkpoint(cfg, source)
    if source != copy:
        atomic_torch_save(raw, copy)
    progress = TrainingProgress.from_dict(raw["progress"])
    noises = _noise_of(raw["fingerprint"]["noise"])
    record = _record(cfg, progress, noises, reused=str(settings.estimator))
    samples = _samples(cfg, _estimator_of(cfg, raw), pairs)
    return AmortisedSamples(samples, record)


def _samples(
    cfg: TrainConfig, estimator: AmortisedEstimator, pairs: PairSet
) -> PairPosteriors:
    """The training pairs' ``abc.amortised.samples_per_pair`` samples each."""
    return infer(
        estimator,
        pairs,
        cfg.abc.amortised.samples_per_pair,
        seed=cfg.abc.seed,
        compile=sampling_compiled(cfg, pairs.n_pairs),
    )


def _record(
    cfg: TrainConfig,
    progress: TrainingProgress,
    noise: tuple[float, float, float],
    reused: str | None = None,
) -> AmortisedResult:
    """``summary.json``'s ``amortised`` of a training's progress."""
    return AmortisedResult(
        samples_per_pair=cfg.abc.amortised.samples_per_pair,
        noise=noise,
        epochs=len(progress.history),
        finished=progress.finished,
        simulations=progress.simulations,
        invalid=progress.invalid,
        seconds=round(progress.seconds, 3),
        validation_loss=progress.best_loss,
        validation_accuracy=progress.best_accuracy,
        reused=reused,
    )


def reused_source(cfg: TrainConfig, run: RunDir, resume: bool) -> Path:
    """Where a run reusing ``abc.amortised.estimator`` reads it: its own copy
    when resumed and the copy is there, else the configured path."""
    copy = run.amortised_checkpoint
    if resume and copy.exists():
        return copy
    return Path(cfg.abc.amortised.estimator)


def reused_checkpoint(cfg: TrainConfig, source: Path | None = None) -> dict:
    """The finished training checkpoint of ``abc.amortised.estimator`` (or of
    ``source``; a run directory stands for its ``amortised.pt``), checked
    against the config's models, prior boxes and network.

    Raises:
        ConfigError: missing, unreadable, not a finished training's, or
            another estimator's (the first differing entry named).
    """
    path = Path(source if source is not None else cfg.abc.amortised.estimator)
    if path.is_dir():
        path = RunDir(path).amortised_checkpoint
    fingerprint = estimator_fingerprint(_new_estimator(cfg))
    try:
        return load_trained(path, fingerprint)
    except (RunFileError, CheckpointError) as error:
        raise ConfigError(f"abc.amortised.estimator: {error}") from None


def trained_estimator(cfg: TrainConfig, run: RunDir) -> AmortisedEstimator:
    """The estimator a finished amortised run trained or reused (its kept
    weights, read from :attr:`RunDir.amortised_checkpoint
    <torchcf.runs.directory.RunDir.amortised_checkpoint>`), in eval mode.

    Raises:
        RunFileError: the checkpoint is missing, unreadable or corrupted.
    """
    return _estimator_of(cfg, read_torch(run.amortised_checkpoint))


def _new_estimator(cfg: TrainConfig) -> AmortisedEstimator:
    """A fresh estimator of the config's models, boxes and network."""
    return new_estimator(
        parameter_space(cfg),
        estimator_settings(cfg.abc.amortised.network),
        seed=cfg.abc.seed,
    )


def _estimator_of(cfg: TrainConfig, raw: dict) -> AmortisedEstimator:
    """The estimator of a training checkpoint's kept weights, in eval mode."""
    estimator = _new_estimator(cfg)
    best = raw.get("best")
    estimator.load_state_dict(best if best is not None else raw["estimator"])
    return estimator.eval()


def _noise_of(text: str) -> tuple[float, float, float]:
    """The noise levels of a checkpoint's fingerprint (``repr`` of
    :class:`~torchcf.amortised.NoiseLevels`): position, speed, acceleration."""
    values = dict(re.findall(r"(\w+)=([^,)]+)", text))
    return tuple(float(values[k]) for k in ("position", "speed", "acceleration"))


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
    "COMPILE_MIN_SAMPLES",
    "AmortisedSamples",
    "amortised_samples",
    "estimator_settings",
    "parameter_space",
    "reused_checkpoint",
    "reused_samples",
    "reused_source",
    "sampling_compiled",
    "trained_estimator",
]
