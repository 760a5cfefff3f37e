"""The amortised sampler's samples (:class:`~torchcf.calibration.Amortised`).

Before the models' streams, one estimator (:mod:`torchcf.amortised`) is
trained on simulations of the calibration's models over their prior boxes,
behind the training pairs' leaders, and ``samples_per_pair`` samples of
(model, parameters) are drawn for every training pair. Each model's stream is
then its samples (:func:`torchcf.amortised.run_amortised`), scored and kept in
its per-pair buffer as rejection's particles are.

The training writes its own checkpoint where the caller says (a run's
``amortised.pt``); resumed, it continues (or reads back the finished weights)
and the samples, a function of the weights, the seed and each pair, come out
identical. With ``Amortised.estimator`` nothing is trained: a finished
estimator of the same models, boxes and network is read (and copied to the
checkpoint's place, so that a run keeps its estimator either way).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from torch import Tensor

from ..amortised import (
    AmortisedEstimator,
    CheckpointError,
    NoiseLevels,
    PairPosteriors,
    ParameterSpace,
    Session,
    SimulationSettings,
    TrainingProgress,
    TrainingSimulator,
    estimator_fingerprint,
    fingerprint_noise,
    infer,
    load_trained,
    new_estimator,
    train_estimator,
)
from ..data import PairSet
from ..models import CFModel
from ..runs.summary import AmortisedResult
from ..sim.compiled import compiler_available
from ..system.files import RunFileError, atomic_torch_save, read_torch
from ..system.signals import StopRequest
from .budget import CalibrationError
from .methods import Amortised

#: Samples (training pairs x ``samples_per_pair``) from which ``compile =
#: "auto"`` compiles the flows' sampling: below it compiling the flows on an
#: empty compile cache costs more than it saves (``tools/bench_amortised.py``;
#: ``reports/performance.md``, "Amortised calibration").
COMPILE_MIN_SAMPLES = 10_000_000

#: A run directory holds its estimator's training checkpoint under this name.
ESTIMATOR_FILE = "amortised.pt"


class EstimatorError(CalibrationError):
    """A finished estimator to reuse that cannot be read or does not fit
    (one-line message: ``estimator: ...``)."""


class AmortisedSamples(NamedTuple):
    """The training pairs' samples and the estimator's record.

    Attributes:
        samples: every training pair's samples of (model, parameters).
        record: how the estimator was trained (a run summary's ``amortised``).
    """

    samples: PairPosteriors
    record: AmortisedResult


def parameter_space(priors: Mapping[CFModel, Tensor]) -> ParameterSpace:
    """The models and their prior boxes ``(K, 2)``, the estimator's space."""
    return ParameterSpace(list(priors), list(priors.values()))


def amortised_samples(
    method: Amortised,
    priors: Mapping[CFModel, Tensor],
    pairs: PairSet,
    seed: int,
    checkpoint: Path | None = None,
    resume: bool = False,
    stop: StopRequest | None = None,
) -> AmortisedSamples:
    """Train (or resume, or read back) the estimator and draw the training
    pairs' samples.

    Args:
        method: the sampler's settings.
        priors: the models and their prior boxes ``(K, 2)``.
        pairs: the training pairs.
        seed: the training's sets, the initial weights and the samples.
        checkpoint: where the training's checkpoint is kept; None: nowhere.
        resume: continue the checkpoint where there is one.
        stop: a stop request checked between the training's batches.
    """
    space = parameter_space(priors)
    if method.estimator is not None:
        return reused_samples(method, space, pairs, seed, checkpoint, resume)
    noise = method.noise if method.noise is not None else NoiseLevels.of_pairs(pairs)
    simulator = TrainingSimulator(
        space,
        pairs,
        SimulationSettings(window_steps=method.window_steps, noise=noise),
        seed=seed,
    )
    estimator = new_estimator(space, method.network, seed=seed)
    session = Session(
        checkpoint=checkpoint,
        resume=resume and checkpoint is not None and checkpoint.exists(),
        stop=stop,
    )
    training = replace(method.training, seed=seed)
    result = train_estimator(estimator, simulator, training, session)
    record = _record(method, result.progress, noise)
    return AmortisedSamples(_samples(method, estimator, pairs, seed), record)


def reused_samples(
    method: Amortised,
    space: ParameterSpace,
    pairs: PairSet,
    seed: int,
    copy: Path | None,
    resume: bool,
) -> AmortisedSamples:
    """The training pairs' samples of the finished estimator
    ``method.estimator`` (no training), copied to ``copy`` first (a resumed
    run reads its copy).

    Raises:
        EstimatorError: the estimator cannot be read or is not of these
            models, boxes and network (:func:`reused_checkpoint`).
    """
    source = reused_source(method, copy, resume)
    raw = reused_checkpoint(method, space, source)
    if copy is not None and source != copy:
        atomic_torch_save(raw, copy)
    progress = TrainingProgress.from_dict(raw["progress"])
    noise = fingerprint_noise(raw["fingerprint"])
    record = _record(method, progress, noise, reused=str(method.estimator))
    estimator = estimator_of(method, space, raw)
    return AmortisedSamples(_samples(method, estimator, pairs, seed), record)


def reused_source(method: Amortised, copy: Path | None, resume: bool) -> Path:
    """Where a calibration reusing ``method.estimator`` reads it: its own copy
    when resumed and the copy is there, else the estimator's path."""
    if resume and copy is not None and copy.exists():
        return copy
    return Path(method.estimator)


def reused_checkpoint(
    method: Amortised, space: ParameterSpace, source: Path | None = None
) -> dict:
    """The finished training checkpoint of ``method.estimator`` (or of
    ``source``; a directory stands for its ``amortised.pt``), checked against
    the space's models, prior boxes and the network.

    Raises:
        EstimatorError: missing, unreadable, not a finished training's, or
            another estimator's (the first differing entry named).
    """
    path = Path(source if source is not None else method.estimator)
    if path.is_dir():
        path = path / ESTIMATOR_FILE
    fingerprint = estimator_fingerprint(new_estimator(space, method.network))
    try:
        return load_trained(path, fingerprint)
    except (RunFileError, CheckpointError) as error:
        raise EstimatorError(f"estimator: {error}") from None


def trained_estimator(
    method: Amortised, priors: Mapping[CFModel, Tensor], checkpoint: Path
) -> AmortisedEstimator:
    """The estimator kept in a finished training's ``checkpoint`` (its best
    weights), in eval mode.

    Raises:
        RunFileError: the checkpoint is missing, unreadable or corrupted.
    """
    return estimator_of(method, parameter_space(priors), read_torch(checkpoint))


def estimator_of(
    method: Amortised, space: ParameterSpace, raw: dict
) -> AmortisedEstimator:
    """The estimator of a training checkpoint's kept weights, in eval mode."""
    estimator = new_estimator(space, method.network)
    best = raw.get("best")
    estimator.load_state_dict(best if best is not None else raw["estimator"])
    return estimator.eval()


def _samples(
    method: Amortised, estimator: AmortisedEstimator, pairs: PairSet, seed: int
) -> PairPosteriors:
    """The training pairs' ``samples_per_pair`` samples each."""
    return infer(
        estimator,
        pairs,
        method.samples_per_pair,
        seed=seed,
        compile=sampling_compiled(method, pairs.n_pairs),
    )


def sampling_compiled(method: Amortised, n_pairs: int) -> bool:
    """Whether the samples are drawn with the flows compiled
    (:func:`torchcf.amortised.infer`): ``method.compile``, "auto" from
    :data:`COMPILE_MIN_SAMPLES` samples on where a C++ compiler is there."""
    if method.compile != "auto":
        return method.compile == "on"
    samples = n_pairs * method.samples_per_pair
    return samples >= COMPILE_MIN_SAMPLES and compiler_available()


def _record(
    method: Amortised,
    progress: TrainingProgress,
    noise: NoiseLevels,
    reused: str | None = None,
) -> AmortisedResult:
    """A run summary's ``amortised`` of a training's progress."""
    return AmortisedResult(
        samples_per_pair=method.samples_per_pair,
        noise=(noise.position, noise.speed, noise.acceleration),
        epochs=len(progress.history),
        finished=progress.finished,
        simulations=progress.simulations,
        invalid=progress.invalid,
        seconds=round(progress.seconds, 3),
        validation_loss=progress.best_loss,
        validation_accuracy=progress.best_accuracy,
        reused=reused,
    )


__all__ = [
    "EstimatorError",
    "COMPILE_MIN_SAMPLES",
    "ESTIMATOR_FILE",
    "AmortisedSamples",
    "amortised_samples",
    "estimator_of",
    "parameter_space",
    "reused_checkpoint",
    "reused_samples",
    "reused_source",
    "sampling_compiled",
    "trained_estimator",
]
