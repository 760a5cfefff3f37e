"""Training the amortised estimator on torchcf's own simulations.

The loss of an example (model ``m``, parameters with unit-cube coordinate
``u``, series ``x``) is ``-log q(m | x) - log q_m(logit u | x)``
(:meth:`AmortisedEstimator.latent_log_prob`), averaged over a batch; Adam
minimises it.

Data: every epoch reads a simulated set of ``simulations_per_epoch`` examples
(:class:`~torchcf.amortised.simulations.TrainingSimulator`); a set serves
``reuse`` epochs in a row, then the next one is drawn. ``reuse = 1`` (the
default) is *fresh simulations every epoch*: the estimator never sees an
example twice, so it cannot overfit them, and a fresh set costs less than the
gradient steps on it (the rollouts are batched); ``reuse = max_epochs`` is the
fixed simulated set of the usual neural posterior estimation, whose training
loss falls below its validation loss within a few epochs of the sizes tried
(overfitting), a budget better spent on new examples. A validation set
(its own seed) is drawn once; after every epoch its loss decides early
stopping (``patience`` epochs without a lower one) and the weights of the
lowest are the result.

The budget: ``max_epochs``, hence ``simulations_per_epoch x ceil(max_epochs /
reuse)`` simulations plus the validation set, and optionally ``max_seconds``
of training (which ends the epoch early and makes the result depend on the
machine's speed).

Checkpoints (:mod:`torchcf.amortised.training_state`) are written every
``checkpoint_every`` seconds between batches, at the end of every epoch when
due, when a stop is requested and at the end; a run resumed from one ends
identical to an uninterrupted run (deterministic on the CPU for a seed).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor
from tqdm import tqdm

from ..abc.streams import block_seed
from ..system.console import bar_interval
from .estimator import AmortisedEstimator
from .simulations import NoiseLevels, SimulatedSet, TrainingSimulator
from .training_state import (
    CheckpointError,
    EpochRecord,
    TrainingProgress,
    copy_state,
    load_checkpoint,
    save_checkpoint,
)


@dataclass(frozen=True)
class TrainingSettings:
    """The training's budget and optimiser.

    Attributes:
        simulations_per_epoch: examples drawn for a simulated set.
        reuse: epochs each simulated set serves (1: fresh every epoch).
        max_epochs: epochs at most.
        max_seconds: training time at most [s]; None: no limit.
        validation_simulations: examples drawn for the validation set.
        batch_size: examples per gradient step.
        learning_rate: Adam's.
        patience: epochs without a lower validation loss before stopping.
        checkpoint_every: seconds between checkpoints.
        seed: every set, every epoch's order (and, through
            :func:`~torchcf.amortised.estimator.new_estimator`, the initial
            weights) is a function of it.

    Examples:
        >>> settings = TrainingSettings(simulations_per_epoch=1_000, max_epochs=5,
        ...                             validation_simulations=200)
        >>> settings.simulation_budget  # 5 sets of 1 000, and the validation set
        5200
    """

    simulations_per_epoch: int = 20_000
    reuse: int = 1
    max_epochs: int = 40
    max_seconds: float | None = None
    validation_simulations: int = 4_000
    batch_size: int = 256
    learning_rate: float = 1e-3
    patience: int = 5
    checkpoint_every: float = 300.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in (
            "simulations_per_epoch",
            "reuse",
            "max_epochs",
            "validation_simulations",
            "batch_size",
            "patience",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be > 0, got {self.learning_rate}")

    @property
    def simulation_budget(self) -> int:
        """Simulations at most: the sets' and the validation set's."""
        sets = math.ceil(self.max_epochs / self.reuse)
        return sets * self.simulations_per_epoch + self.validation_simulations


class Stopper(Protocol):
    """Asks the training to stop at its next batch
    (:class:`torchcf.system.signals.StopRequest`)."""

    @property
    def requested(self) -> bool: ...

    def stop(self, checkpointed: bool = True) -> None: ...


class TrainingResult(NamedTuple):
    """How a training ended (the estimator holds the best weights).

    Attributes:
        progress: epochs, simulations, seconds and the history.
        best_loss: the lowest validation loss.
        validation_accuracy: the model head's accuracy at that epoch.

    Examples:
        >>> TrainingResult._fields  # train_estimator's example makes one
        ('progress', 'best_loss', 'validation_accuracy')
    """

    progress: TrainingProgress
    best_loss: float
    validation_accuracy: float


@dataclass(frozen=True)
class Session:
    """Where a training keeps its state, and how it reports.

    Attributes:
        checkpoint: the checkpoint's path; None: none written.
        resume: continue from ``checkpoint`` (which must exist).
        stop: a stop request checked between batches; None: none.
        progress_bar: show a tqdm bar on stderr.

    Examples:
        >>> from pathlib import Path
        >>> Session(checkpoint=Path("amortised.pt"), resume=True)
        Session(checkpoint=PosixPath('amortised.pt'), resume=True, stop=None,
                progress_bar=True)
    """

    checkpoint: Path | None = None
    resume: bool = False
    stop: Stopper | None = None
    progress_bar: bool = True


def train_estimator(
    estimator: AmortisedEstimator,
    simulator: TrainingSimulator,
    settings: TrainingSettings = TrainingSettings(),
    session: Session = Session(),
) -> TrainingResult:
    """Train ``estimator`` on ``simulator``'s examples (module docstring).

    Args:
        estimator: the networks, trained in place; at the end they hold the
            weights of the lowest validation loss.
        simulator: draws the simulated sets.
        settings: budget and optimiser.
        session: checkpoint, resume, stop request, progress bar.

    Raises:
        CheckpointError: ``session.resume`` from another training's checkpoint.
        RunFileError: the checkpoint cannot be read or written.
        Stopped: a stop was requested (a checkpoint was written first).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> from torchcf.amortised import (EncoderSettings, EstimatorSettings,
        ...     ParameterSpace, SimulationSettings, new_estimator)
        >>> idm = get_model("idm")
        >>> pairs = synthetic_pairs(idm, [1.5, 2.0, 33.0, 1.2, 2.0, 4.0], 4, n_steps=50)
        >>> space = ParameterSpace([idm, get_model("ovm")])
        >>> simulator = TrainingSimulator(space, pairs, SimulationSettings(40))
        >>> encoder = EncoderSettings(width=8, depth=2, strided=1, embedding=8)
        >>> tiny = EstimatorSettings(encoder, head_width=8, transforms=1, flow_width=8)
        >>> settings = TrainingSettings(simulations_per_epoch=32, max_epochs=2,
        ...                             validation_simulations=16, batch_size=16)
        >>> result = train_estimator(new_estimator(space, tiny), simulator, settings,
        ...                          Session(progress_bar=False))
        >>> result.progress.epoch, result.progress.finished, result.progress.simulations
        (2, 'epochs', 80)
    """
    if simulator.space.names != estimator.space.names:
        raise ValueError(
            f"the simulator's models {simulator.space.names} are not the "
            f"estimator's {estimator.space.names}"
        )
    trainer = _Trainer(estimator, simulator, settings, session)
    return trainer.run()


class _Trainer:
    """One training session: the state, the loop and the checkpoints."""

    def __init__(
        self,
        estimator: AmortisedEstimator,
        simulator: TrainingSimulator,
        settings: TrainingSettings,
        session: Session,
    ) -> None:
        self.estimator = estimator
        self.simulator = simulator
        self.settings = settings
        self.session = session
        self.optimiser = torch.optim.Adam(
            estimator.parameters(), lr=settings.learning_rate
        )
        self.progress = TrainingProgress()
        self.best: dict[str, Tensor] | None = None
        self.fingerprint = _fingerprint(estimator, simulator, settings)
        if session.resume:
            if session.checkpoint is None:
                raise ValueError("resume needs a checkpoint path")
            self._load(session.checkpoint)
        self._last_save = time.perf_counter()

    def run(self) -> TrainingResult:
        settings, progress = self.settings, self.progress
        if progress.finished:  # resumed after it ended: its weights alone
            return self._result()
        validation = self.simulator.draw("validation", settings.validation_simulations)
        if progress.epoch == 0 and progress.batch == 0 and not progress.history:
            progress.simulations += validation.n_drawn
            progress.invalid += validation.n_invalid
        bar = self._bar()
        started, spent = time.perf_counter(), progress.seconds
        data: SimulatedSet | None = None
        with bar:
            while not progress.finished:
                if progress.epoch >= settings.max_epochs:
                    progress.finished = "epochs"
                    break
                data = self._epoch_set(data)
                out_of_time = self._run_batches(data, bar, started, spent)
                progress.seconds = spent + time.perf_counter() - started
                self._end_epoch(validation, bar)
                if out_of_time:
                    progress.finished = "seconds"
                elif progress.epoch >= settings.max_epochs and not progress.finished:
                    progress.finished = "epochs"
                self._checkpoint(force=bool(progress.finished))
        return self._result()

    def _result(self) -> TrainingResult:
        """The best weights into the estimator, and how the training ended."""
        progress = self.progress
        if self.best is not None:
            self.estimator.load_state_dict(self.best)
        return TrainingResult(progress, progress.best_loss, progress.best_accuracy)

    # ------------------------------------------------------------------ epochs
    def _epoch_set(self, previous: SimulatedSet | None) -> SimulatedSet:
        """The epoch's simulated set: the previous one while it serves, else
        the next one drawn (counted once, when first drawn)."""
        settings, progress = self.settings, self.progress
        index = progress.epoch // settings.reuse
        if previous is not None and (progress.epoch % settings.reuse):
            return previous
        data = self.simulator.draw(f"set-{index}", settings.simulations_per_epoch)
        first_use = progress.epoch % settings.reuse == 0 and progress.batch == 0
        if first_use:
            progress.simulations += data.n_drawn
            progress.invalid += data.n_invalid
        return data

    def _run_batches(
        self, data: SimulatedSet, bar: tqdm, started: float, spent: float
    ) -> bool:
        """The epoch's batches from ``progress.batch`` on; True when the time
        budget ran out."""
        settings, progress = self.settings, self.progress
        order = _epoch_order(settings.seed, progress.epoch, len(data))
        batches = order.split(settings.batch_size)
        self.estimator.train()
        for number in range(progress.batch, len(batches)):
            rows = batches[number]
            loss = self._step(data, rows)
            progress.loss_sum += loss * rows.numel()
            progress.loss_count += rows.numel()
            progress.batch = number + 1
            bar.update(1)
            progress.seconds = spent + time.perf_counter() - started
            stop = self.session.stop
            if stop is not None and stop.requested:
                self._checkpoint(force=True)
                stop.stop()
            self._checkpoint(force=False)
            limit = settings.max_seconds
            if limit is not None and progress.seconds >= limit:
                return True
        return False

    def _step(self, data: SimulatedSet, rows: Tensor) -> float:
        """One gradient step on the examples ``rows``; their mean loss."""
        features = data.features[rows]
        lengths = torch.full((rows.numel(),), features.shape[-1], dtype=torch.int64)
        embedding = self.estimator.embed(features, lengths)
        loss = -self.estimator.latent_log_prob(
            embedding, data.model[rows], data.unit[rows]
        ).mean()
        self.optimiser.zero_grad(set_to_none=True)
        loss.backward()
        # a rare example far out in a flow's tail must not throw the weights off
        torch.nn.utils.clip_grad_norm_(self.estimator.parameters(), 5.0)
        self.optimiser.step()
        return float(loss.detach())

    def _end_epoch(self, validation: SimulatedSet, bar: tqdm) -> None:
        """Validation loss and accuracy, the best weights, early stopping."""
        progress, settings = self.progress, self.settings
        loss, accuracy = validation_scores(
            self.estimator, validation, settings.batch_size
        )
        train_loss = progress.loss_sum / max(progress.loss_count, 1)
        progress.history.append(
            EpochRecord(progress.epoch, train_loss, loss, accuracy, progress.seconds)
        )
        if loss < progress.best_loss:
            progress.best_loss, progress.since_best = loss, 0
            self.best = copy_state(self.estimator.state_dict())
        else:
            progress.since_best += 1
        progress.epoch += 1
        progress.batch, progress.loss_sum, progress.loss_count = 0, 0.0, 0
        if progress.since_best >= settings.patience:
            progress.finished = "patience"
        bar.set_postfix_str(
            f"loss {train_loss:.3f}, validation {loss:.3f}, "
            f"model accuracy {accuracy:.1%}",
            refresh=False,
        )

    # ------------------------------------------------------------- checkpoint
    def _checkpoint(self, force: bool) -> None:
        path = self.session.checkpoint
        if path is None:
            return
        now = time.perf_counter()
        if not force and now - self._last_save < self.settings.checkpoint_every:
            return
        save_checkpoint(
            path,
            {
                "fingerprint": self.fingerprint,
                "estimator": self.estimator.state_dict(),
                "optimiser": self.optimiser.state_dict(),
                "best": self.best,
                "progress": self.progress.as_dict(),
            },
        )
        self._last_save = now

    def _load(self, path: Path) -> None:
        raw = load_checkpoint(path, self.fingerprint)
        self.estimator.load_state_dict(raw["estimator"])
        self.optimiser.load_state_dict(raw["optimiser"])
        self.best = raw["best"]
        self.progress = TrainingProgress.from_dict(raw["progress"])
        limit = self.settings.max_seconds
        if self.progress.finished == "seconds" and (
            limit is None or self.progress.seconds < limit
        ):
            self.progress.finished = ""  # resumed with more time: go on

    def _bar(self) -> tqdm:
        settings, progress = self.settings, self.progress
        per_epoch = math.ceil(settings.simulations_per_epoch / settings.batch_size)
        return tqdm(
            total=settings.max_epochs * per_epoch,
            initial=progress.epoch * per_epoch + progress.batch,
            desc="amortised",
            unit="batch",
            dynamic_ncols=True,
            file=sys.stderr,
            mininterval=bar_interval(),
            disable=not self.session.progress_bar,
        )


def validation_scores(
    estimator: AmortisedEstimator, data: SimulatedSet, batch_size: int
) -> tuple[float, float]:
    """The mean loss of ``data``'s examples and the share whose most probable
    model is the true one, in batches of ``batch_size``.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.amortised import ParameterSpace, new_estimator
        >>> estimator = new_estimator(ParameterSpace([get_model("idm")]))
        >>> data = SimulatedSet(torch.zeros(4, 5, 30), torch.zeros(4, dtype=torch.long),
        ...     torch.full((4, 6), 0.5, dtype=torch.float64), torch.tensor([4]),
        ...     torch.tensor([0]))
        >>> loss, accuracy = validation_scores(estimator, data, batch_size=2)
        >>> accuracy  # one model: always the true one
        1.0
    """
    estimator.eval()
    total, correct = 0.0, 0
    with torch.no_grad():
        for rows in torch.arange(len(data)).split(batch_size):
            features = data.features[rows]
            lengths = torch.full((rows.numel(),), features.shape[-1], dtype=torch.int64)
            embedding = estimator.embed(features, lengths)
            log_prob = estimator.latent_log_prob(
                embedding, data.model[rows], data.unit[rows]
            )
            total += float(-log_prob.sum())
            guess = estimator.model_logits(embedding).argmax(1)
            correct += int((guess == data.model[rows]).sum())
    estimator.train()
    n = max(len(data), 1)
    return total / n, correct / n


def _epoch_order(seed: int, epoch: int, n: int) -> Tensor:
    """(n,) the order of an epoch's examples, a function of (seed, epoch)."""
    generator = torch.Generator().manual_seed(
        block_seed(seed, "amortised/order", epoch)
    )
    return torch.randperm(n, generator=generator)


def estimator_fingerprint(estimator: AmortisedEstimator) -> dict[str, Any]:
    """What a trained estimator must match to be reused by another run: the
    models and their boxes, the networks' sizes (a checkpoint's
    fingerprint's first entries; plain data, as every entry).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.amortised import ParameterSpace, new_estimator
        >>> estimator = new_estimator(ParameterSpace([get_model("idm")]))
        >>> fingerprint = estimator_fingerprint(estimator)
        >>> sorted(fingerprint), fingerprint["models"]
        (['estimator', 'high', 'low', 'models'], ['idm'])
    """
    space = estimator.space
    return {
        "models": list(space.names),
        "low": space.low.nan_to_num(0.0).tolist(),
        "high": space.high.nan_to_num(0.0).tolist(),
        "estimator": asdict(estimator.settings),
    }


def fingerprint_noise(fingerprint: Mapping[str, Any]) -> NoiseLevels:
    """The measurement noise a checkpoint's estimator was trained with: its
    fingerprint's ``noise``, ``{"position": .., "speed": .., "acceleration":
    ..}`` (:class:`~torchcf.amortised.NoiseLevels`' fields).

    Raises:
        CheckpointError: no such entry (a checkpoint of an older format, read
            without :func:`~torchcf.amortised.load_trained`'s check).

    Examples:
        >>> noise = {"position": 0.01, "speed": 0.05, "acceleration": 0.5}
        >>> fingerprint_noise({"models": ["idm"], "noise": noise})
        NoiseLevels(position=0.01, speed=0.05, acceleration=0.5)
    """
    noise = fingerprint.get("noise")
    names = [f.name for f in fields(NoiseLevels)]
    if not isinstance(noise, Mapping) or sorted(noise) != sorted(names):
        raise CheckpointError(
            f"the fingerprint's noise is {noise!r}, not NoiseLevels' fields: "
            "a checkpoint of an older torchcf; train the estimator again"
        )
    return NoiseLevels(**{name: float(noise[name]) for name in names})


def _fingerprint(
    estimator: AmortisedEstimator,
    simulator: TrainingSimulator,
    settings: TrainingSettings,
) -> dict[str, Any]:
    """What a checkpoint must match to be resumed: the models and boxes, the
    networks' sizes, the simulation's and the training's settings (all but
    the time budget and the checkpoints' pace, which a resumed run may
    change)."""
    training = asdict(settings)
    for free in ("max_seconds", "checkpoint_every"):
        training.pop(free)
    sim = simulator.settings
    return {
        **estimator_fingerprint(estimator),
        "window_steps": sim.window_steps,
        "noise": asdict(sim.noise),
        "chunk_size": sim.chunk_size,
        "simulator_seed": simulator.seed,
        "pairs": [simulator.pairs.name, simulator.pairs.n_pairs],
        "training": training,
    }


__all__ = [
    "Session",
    "Stopper",
    "TrainingResult",
    "TrainingSettings",
    "estimator_fingerprint",
    "fingerprint_noise",
    "train_estimator",
    "validation_scores",
]
