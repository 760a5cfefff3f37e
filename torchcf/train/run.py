"""A training run: a calibration (:func:`torchcf.calibration.calibrate`) with
a run directory around it.

    torchcf train configs/carII.json
    torchcf train configs/smoke.json --set abc.n_particles=50000
    torchcf train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf train configs/carII.json

:func:`train` translates the config once (:func:`torchcf.calibration.of_config.
setup_of`: the rollout, the prior boxes, the sampler, the selection), checks
the budget before any output, and runs the calibration with a
:class:`RunTracker`: a progress bar per model, TensorBoard scalars, and
checkpoints (``abc.checkpoint_every`` seconds and after each model, so that
``--resume`` ends identical to an uninterrupted run), across the processes of a
``torchrun`` group (rank 0 reads and writes, every rank holds the merged
buffers). Then it writes the outputs. Its parts, by concern:

- :mod:`torchcf.train.checkpoint`: the checkpoint's format, resuming from it,
  the checkpointer, the device;
- :mod:`torchcf.train.summary`: ``summary.json``'s record
  (:class:`~torchcf.runs.summary.RunSummary`) of a calibration.

The command line (:mod:`torchcf.cli.train`) runs the study
(:func:`torchcf.study.pipeline.run_study`): training, then the test-split evaluation
(unless ``--no-eval``) and, with ``diagnose.run_after_training``, the diagnosis
loop.

The output directory (:class:`torchcf.runs.directory.RunDir`) receives ``config.json``
(resolved), ``checkpoint.pt``, TensorBoard event files under ``tb/``, and at the
end ``posterior.pt`` and ``summary.json``, written last: a directory without
``summary.json`` holds an unfinished run.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 bad config, data, arguments
or output directory, a corrupted checkpoint, or an output that cannot be
written (one line on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..abc.distributed import SINGLE, Group
from ..abc.rejection import ModelProgress, Rollout
from ..calibration import (
    Amortised,
    CalibrationError,
    CalibrationSetup,
    Tracker,
)
from ..calibration.estimator_samples import (
    EstimatorError,
    parameter_space,
    reused_checkpoint,
    reused_source,
)
from ..calibration.of_config import setup_of
from ..calibration.state import StateError
from ..config import ConfigError, TrainConfig, config_hash, load_split, resolved_json
from ..data import PairSet
from ..data.importer import record_extraction
from ..evaluation.plots import hybrid_images, save_image
from ..posterior import Posterior
from ..posterior.tables import parameters_markdown, write_parameter_tables
from ..runs.directory import RunDir
from ..runs.summary import RunSummary
from ..runs.tensorboard import RunLogger, markdown_summary
from ..system.console import bar_interval, one_line
from ..system.files import RunFileError, ensure_directory, writing
from ..system.process import tune_malloc
from ..system.signals import StopRequest
from ..traffic.configured import hybrid_plausibility, plausibility_screen
from .checkpoint import (
    Checkpointer,
    RunError,
    RunState,
    open_run,
    resume_note,
    run_device,
)
from .summary import dataset_label, run_summary

# --------------------------------------------------------------------------------------
# The calibration's tracker: progress bars, TensorBoard, checkpoints


class RunTracker(Tracker):
    """A training run's :class:`~torchcf.calibration.Tracker`: the state is the
    checkpoint's (:class:`~torchcf.train.checkpoint.RunState`), every model a
    progress bar (rank 0) and TensorBoard scalars, a checkpoint every
    ``abc.checkpoint_every`` seconds and after each model."""

    def __init__(
        self,
        run: RunDir,
        state: RunState,
        checkpointer: Checkpointer,
        logger: RunLogger,
        group: Group,
        screened: bool,
        resume: bool,
    ) -> None:
        super().__init__(
            state.calibration,
            estimator_checkpoint=run.amortised_checkpoint,
            resume=resume,
            stop=checkpointer.stop,
        )
        self.checkpointer, self.logger, self.group = checkpointer, logger, group
        self.screened = screened
        self.bar: tqdm | None = None

    @contextmanager
    def model(self, name: str, total: int, done: int) -> Iterator[None]:
        with _progress_bar(name, total, done, self.group.is_main) as bar:
            self.bar = bar
            yield
        self.bar = None

    def round(self, name: str, progress: ModelProgress, rollout: Rollout) -> None:
        bar = self.bar
        cells_per_particle = rollout.cells_per_particle
        invalid_rate = progress.invalid / (progress.next * cells_per_particle)
        if bar is not None:
            bar.update(progress.next - bar.n)
            postfix = f"invalid {invalid_rate:.1%}"
            if self.screened:
                postfix += f", implausible {progress.implausible}"
            if rollout.early_rejection:
                cells = progress.next * cells_per_particle
                postfix += f", rejected early {progress.stopped / cells:.0%}"
            bar.set_postfix_str(postfix, refresh=False)
        self.logger.progress(
            name,
            particles=progress.next,
            threshold=float(self.state.buffers[name].threshold().mean()),
            particles_per_s=progress.next / max(progress.seconds, 1e-9),
            invalid_rate=invalid_rate,
        )

    def due(self) -> bool:
        return self.checkpointer.due()

    def save(self) -> None:
        self.checkpointer.save()


def _progress_bar(name: str, total: int, initial: int, enabled: bool) -> tqdm:
    """A model's progress bar on stderr, in particles."""
    return tqdm(
        total=total,
        initial=initial,
        desc=f"{name:>5}",
        unit="particle",
        unit_scale=True,
        dynamic_ncols=True,
        file=sys.stderr,
        # In a log file (no terminal) a line every 30 s instead of a live bar.
        mininterval=bar_interval(),
        disable=not enabled,
    )


# --------------------------------------------------------------------------------------
# Entry points


def train(
    cfg: TrainConfig,
    out: str | Path | RunDir,
    *,
    resume: bool = False,
    pairs: tuple[PairSet, PairSet | None] | None = None,
    group: Group = SINGLE,
) -> RunSummary:
    """Run (or resume) the ABC rejection and hybrid selection of ``cfg`` into ``out``.

    Training only: the evaluation and the diagnosis loop are run after it by
    :mod:`torchcf.study.pipeline`.

    Args:
        cfg: the run's configuration.
        out: output directory.
        resume: continue the run in ``out`` (same config) instead of refusing it.
        pairs: optional ``(train, test)`` pair sets to use instead of loading
            ``cfg.data`` (which then only labels the run; the config hash that
            guards ``resume`` does not cover these pairs). In a distributed run
            every process must pass the same pairs. Training needs no test
            pairs: test None (data without a test split) counts none.
        group: the processes sharing the run (:func:`torchcf.abc.distributed.
            init_from_env`); default a single process. Every process of the group
            calls ``train`` with the same arguments; rank 0 writes the outputs.

    Returns:
        The summary (also written to ``out/summary.json``), on every rank: a
        :class:`~torchcf.runs.summary.RunSummary` (``summary.shares``;
        ``summary.to_json()`` is the file's content).

    Raises:
        ConfigError, DataError, RunError: bad config, data, output directory or
            checkpoint.
        RunFileError: an output could not be written (a full disk: the previous
            checkpoint is kept intact).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=3, n_steps=60)
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm", "ovm"],
        ...                   abc={"n_particles": 600, "sensitivity_n": [5]},
        ...                   plausibility={"report": False})
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     summary = train(cfg, Path(folder) / "run", pairs=(pairs, None))
        ...     finished = (Path(folder) / "run" / "summary.json").is_file()
        >>> finished, summary.n_train, sorted(summary.shares)
        (True, 3, ['idm', 'ovm'])
    """
    began = time.perf_counter()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    tune_malloc()
    device = run_device(cfg.device, group)
    run = RunDir(out)
    with run.locked() if group.is_main else nullcontext():
        return _train_held(cfg, run, resume, pairs, group, device, began)


def _train_held(
    cfg: TrainConfig,
    run: RunDir,
    resume: bool,
    pairs: tuple[PairSet, PairSet | None] | None,
    group: Group,
    device: torch.device,
    began: float,
) -> RunSummary:
    """:func:`train` with the run directory held by rank 0 (no second process
    trains into it meanwhile)."""
    # Rank 0 reads the checkpoint and the data and sends them to the others:
    # only rank 0 needs the output directory and the data files.
    state = group.on_main(open_run, config_hash(cfg), run.path, resume)
    finished = group.on_main(_finished_summary, run, resume)
    if finished is not None:  # resumed after it ended: nothing left to do
        return finished
    if resume and group.is_main:
        models = [spec.name for spec in cfg.models]
        # an amortised run's models have their samples' count, not n_particles
        counted = None if cfg.abc.method == "amortised" else cfg.abc.n_particles
        print(resume_note(state, models, counted), file=sys.stderr)
    if pairs is None:  # training needs no test pairs
        pairs = group.on_main(partial(load_split, require_test=False), cfg.data)
    train_pairs, test_pairs = pairs
    # the posterior is labelled by its pairs' name: the run's data set
    train_pairs = replace(train_pairs, name=dataset_label(cfg.data))
    screen = plausibility_screen(cfg.plausibility, train_pairs)
    setup = setup_of(cfg, train_pairs, device, screen)
    check_setup(setup, run, resume, group)
    group.on_main(run.prepare)
    group.on_main(run.write_config, resolved_json(cfg))
    if cfg.data.raw is not None:  # where the pairs came from, what was dropped
        group.on_main(record_extraction, cfg.data.raw, run.data_dir)
    stop = StopRequest()
    checkpointer = Checkpointer(run, state, cfg.abc.checkpoint_every, group, stop)

    with RunLogger(run.tb_dir, enabled=group.is_main) as logger:
        tracker = RunTracker(
            run, state, checkpointer, logger, group, screen is not None, resume
        )
        with stop:  # a signal stops the stream at its next checkpoint
            try:
                calibration = setup.run(group=group, tracker=tracker)
            except StateError as error:
                raise RunError(
                    f"--resume: {run.checkpoint} does not match this run ({error})"
                ) from None
        # Every rank holds the same buffers now; the selection is cheap and
        # deterministic, so each computes it and only rank 0 writes.
        wall = time.perf_counter() - began
        summary = run_summary(
            cfg, calibration, train_pairs, test_pairs, wall, group.world_size
        )
        posterior = calibration.posterior
        if cfg.plausibility.report and group.is_main:
            report = hybrid_plausibility(
                cfg.plausibility, train_pairs, posterior, progress=True
            )
            summary = summary.with_plausibility(report)
            logger.plausibility(report)
        images = None
        if group.is_main:
            pairwise = summary.pairwise.to_json()
            images = hybrid_images(
                posterior.shares, pairwise["models"], pairwise["table"]
            )
        _log_results(logger, posterior, summary, images, hparams(cfg))
    if group.is_main:
        _write_outputs(run, posterior, summary, images)
    return summary


def check_setup(
    setup: CalibrationSetup, run: RunDir, resume: bool, group: Group
) -> None:
    """The budget, and a reused estimator, checked before any output: a
    ConfigError naming the config's setting (the study checks before it reads
    the test pairs, training again, cheaply, as it must when called alone)."""
    try:
        setup.check(prefix="abc.")
        method = setup.method
        if isinstance(method, Amortised) and method.estimator is not None:
            source = reused_source(method, run.amortised_checkpoint, resume)
            space = parameter_space(setup.priors)
            group.on_main(reused_checkpoint, method, space, source)
    except EstimatorError as error:  # its setting is abc.amortised.estimator
        raise ConfigError(f"abc.amortised.{error}") from None
    except CalibrationError as error:  # the budget's names carry the prefix
        raise ConfigError(str(error)) from None


def hparams(cfg: TrainConfig) -> dict[str, str | int | float]:
    """The run's settings TensorBoard's hparams table shows."""
    return {
        "dataset": dataset_label(cfg.data),
        "layout": cfg.abc.layout,
        "n_particles": cfg.abc.n_particles,
        "top_n": cfg.abc.top_n,
        "seed": cfg.abc.seed,
        "dtype": cfg.dtype,
    }


def _write_outputs(
    run: RunDir,
    posterior: Posterior,
    summary: RunSummary,
    images: dict[str, np.ndarray],
) -> None:
    """``posterior.pt``, the report (parameter tables, figures) and, last,
    ``summary.json``, whose presence says the run finished."""
    run.save_posterior(posterior)
    report = ensure_directory(run.report_dir, "report directory")
    write_parameter_tables(posterior, report)
    for name, image in images.items():
        path = report / f"{name}.png"
        with writing(path):
            save_image(image, path)
    run.write_summary(summary)  # last: its presence says it finished


def _finished_summary(run: RunDir, resume: bool) -> RunSummary | None:
    """The summary of a run resumed after it finished (its checkpoint matched the
    config: :func:`open_run`), else None. Training it again would redo the
    selection and the battery, and log every result to TensorBoard twice.

    Raises:
        RunError: its ``summary.json`` is not a training's run summary.
    """
    if not (resume and run.is_trained()):
        return None
    try:
        summary = run.read_summary()
    except RunFileError as error:
        raise RunError(f"--resume: {one_line(error)}") from None
    if not isinstance(summary, RunSummary):
        raise RunError(f"--resume: {run.summary_json} is a re-calibration's summary")
    return summary


def _log_results(
    logger: RunLogger,
    posterior: Posterior,
    summary: RunSummary,
    images: dict[str, np.ndarray] | None,
    settings: dict[str, str | int | float],
) -> None:
    """The accepted parameters, the shares and the summary in TensorBoard;
    ``images``: the hybrid's figures, rendered once for here and the report;
    ``settings``: the hparams table's (:func:`hparams`)."""
    names = list(posterior.models)
    for name in names:
        particles = posterior.hybrid[name]
        logger.posterior(name, particles.param_names, particles.theta)
    sensitivity = dict(summary.sensitivity)
    if images is not None:  # rendered on rank 0, whose logger writes
        logger.hybrid(posterior.shares, images, sensitivity)
    logger.text("summary", markdown_summary(summary))
    logger.text("parameters", parameters_markdown(posterior))
    logger.hparams(
        settings | {"models": ",".join(names)},
        {f"share/{name}": share for name, share in posterior.shares.items()},
    )


__all__ = ["RunTracker", "check_setup", "hparams", "train"]
