"""A training run (the library behind ``python -m torchcf.train CONFIG``).

    python -m torchcf.train configs/carII.json
    python -m torchcf.train configs/smoke.json --set abc.n_particles=50000
    python -m torchcf.train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

The ABC itself is :mod:`torchcf.abc`: for every model of the config, its prior
stream is run through its per-pair top-N buffer (:func:`torchcf.abc.run_rejection`)
and the hybrid is read from the buffers (:mod:`torchcf.abc.hybrid`). With
``abc.method = "amortised"`` an estimator is trained first and its samples for
the training pairs are the streams (:mod:`torchcf.train.amortised`), refined
per pair with ``abc.amortised.refine`` (:mod:`torchcf.train.refinement`). This module
is the run's orchestration: :func:`train` streams each model (with a progress
bar, TensorBoard scalars and checkpoints), then selects the hybrid and writes the
outputs, across the processes of a ``torchrun`` group (rank 0 reads and writes,
every rank holds the merged buffers). Its parts, by concern:

- :mod:`torchcf.train.checkpoint`: the checkpoint's format, resuming from it
  (``abc.checkpoint_every`` seconds and after each model, so that ``--resume``
  ends identical to an uninterrupted run), the checkpointer;
- :mod:`torchcf.train.engine`: the config translated for the engine (device,
  budgets, SMC settings, buffers, the rollout);
- :mod:`torchcf.train.summary`: the results and ``summary.json``
  (:class:`~torchcf.train.summary.RunSummary`).

The command line (:mod:`torchcf.train.__main__`) runs the study
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
from contextlib import nullcontext
from functools import partial
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..abc.configured import rollout_of, smc_settings
from ..abc.distributed import SINGLE, Group
from ..abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from ..abc.rounds import RoundHooks
from ..abc.smc import refine_population, run_smc
from ..amortised import PairPosteriors, run_amortised
from ..config import ModelSpec, TrainConfig, load_split, resolved_json
from ..data import PairSet
from ..data.importer import record_extraction
from ..evaluation.plots import hybrid_images, save_image
from ..posterior import Posterior
from ..posterior.tables import parameters_markdown, write_parameter_tables
from ..runs.directory import RunDir
from ..runs.tensorboard import RunLogger, markdown_summary
from ..system.console import bar_interval
from ..system.files import ensure_directory, writing
from ..system.process import tune_malloc
from ..system.signals import StopRequest
from ..traffic.configured import hybrid_plausibility, plausibility_screen
from .amortised import amortised_samples, reused_checkpoint, reused_source
from .checkpoint import (
    Checkpointer,
    RunError,
    RunState,
    open_run,
    resume_note,
)
from .engine import (
    build_buffers,
    check_budget,
    refine_settings,
    run_device,
    weighted_buffers,
)
from .refinement import refine_budget, refinement_result, scores_before
from .summary import RunSummary, read_results

# --------------------------------------------------------------------------------------
# One model's stream, with checkpoints and progress


def _stream_model(
    cfg: TrainConfig,
    spec: ModelSpec,
    rollout: Rollout,
    state: RunState,
    checkpointer: Checkpointer,
    logger: RunLogger,
    group: Group,
    samples: PairPosteriors | None = None,
    refining: bool = False,
) -> None:
    """Run one model's particles through its buffer (rejection, SMC or the
    amortised samples), with a progress bar, TensorBoard scalars and
    checkpoints between rounds.

    ``spec`` is the model's config entry (its model object and prior box); its
    buffer, progress and refinement state in ``state`` are keyed by its name;
    ``samples``: the training pairs' amortised samples (``abc.method =
    "amortised"`` only). With ``abc.amortised.refine`` a model is streamed
    twice: its samples (the model left unfinished, since the shares before
    the refinement need every model's), then, ``refining``, its refinement
    (:mod:`torchcf.train.refinement`).
    """
    name = spec.name
    buffer, progress = state.buffers[name], state.progress[name]
    if progress.done:
        return
    n_total = cfg.abc.n_particles
    own = refine = None
    if samples is not None:  # the model's samples are its stream
        own = samples.of_model([s.name for s in cfg.models].index(name))
        n_total = own[0].shape[0]
        if refine_settings(cfg) is not None:
            refine = refine_budget(cfg, n_total, rollout.pairs.n_pairs)
            n_total = refine.total
    bar = _progress_bar(name, n_total, progress.next, enabled=group.is_main)
    screen = plausibility_screen(cfg.plausibility, rollout.pairs)

    def after_round(progress: ModelProgress, due: bool) -> None:
        bar.update(progress.next - bar.n)
        invalid_rate = progress.invalid / (progress.next * rollout.cells_per_particle)
        postfix = f"invalid {invalid_rate:.1%}"
        if screen is not None:
            postfix += f", implausible {progress.implausible}"
        if rollout.early_rejection:
            cells = progress.next * rollout.cells_per_particle
            postfix += f", rejected early {progress.stopped / cells:.0%}"
        bar.set_postfix_str(postfix, refresh=False)
        logger.progress(
            name,
            particles=progress.next,
            threshold=float(buffer.threshold().mean()),
            particles_per_s=progress.next / max(progress.seconds, 1e-9),
            invalid_rate=invalid_rate,
        )
        if due:
            checkpointer.save()

    stream = prior_stream(spec.model, spec.bounds(torch.float64), cfg.abc.seed, rollout)
    hooks = RoundHooks(group, screen, checkpointer.due, after_round)
    with bar:
        if refine is not None and refining:
            refine_population(
                stream,
                buffer,
                rollout,
                refine,
                refine_settings(cfg),
                progress,
                state.smc[name],
                hooks=hooks,
            )
        elif own is not None:
            if progress.next < own[0].shape[0]:
                run_amortised(
                    spec.model,
                    own,
                    buffer,
                    rollout,
                    progress,
                    hooks=hooks,
                    weight_column=refine is not None,
                )
            if refine is not None:  # refined once every model's samples are in
                checkpointer.save()
                return
        elif cfg.abc.method == "smc":
            run_smc(
                stream,
                buffer,
                rollout,
                n_total,
                smc_settings(cfg),
                progress,
                state.smc[name],
                hooks=hooks,
            )
        else:
            run_rejection(stream, buffer, rollout, n_total, progress, hooks=hooks)
    progress.done = True
    checkpointer.save()


def _refine_models(
    cfg: TrainConfig,
    rollout: Rollout,
    state: RunState,
    checkpointer: Checkpointer,
    logger: RunLogger,
    group: Group,
    samples: PairPosteriors,
) -> None:
    """Every model's refinement, after the record of the shares and scores
    before it (kept in the checkpoint, so that a resumed run reports the
    same)."""
    if state.refinement_before is None:
        state.refinement_before = scores_before(cfg, state.buffers)
        checkpointer.save()
    for spec in cfg.models:
        _stream_model(
            cfg, spec, rollout, state, checkpointer, logger, group, samples, True
        )


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
        :class:`~torchcf.train.summary.RunSummary` (``summary.shares``;
        ``summary.to_json()`` is the file's content).

    Raises:
        ConfigError, DataError, RunError: bad config, data, output directory or
            checkpoint.
        RunFileError: an output could not be written (a full disk: the previous
            checkpoint is kept intact).
    """
    began = time.perf_counter()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    tune_malloc()
    device = run_device(cfg, group)
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
    state = group.on_main(open_run, cfg, run.path, resume)  # before the data
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
    check_budget(cfg, train_pairs)
    if cfg.abc.method == "amortised" and cfg.abc.amortised.estimator is not None:
        # a bad estimator found before any output
        group.on_main(reused_checkpoint, cfg, reused_source(cfg, run, resume))
    _prepare(cfg, run, group)
    smc = weighted_buffers(cfg)
    build_buffers(
        [spec.model for spec in cfg.models],
        train_pairs.n_pairs,
        cfg.abc.buffer_size,
        smc,
        state,
        run.checkpoint,
    )
    rollout = rollout_of(cfg, train_pairs, device)
    stop = StopRequest()
    checkpointer = Checkpointer(run, state, cfg.abc.checkpoint_every, group, stop)

    with RunLogger(run.tb_dir, enabled=group.is_main) as logger:
        with stop:  # a signal stops the stream at its next checkpoint
            amortised = None
            if cfg.abc.method == "amortised":
                # the run's checkpoint first: a run stopped while its estimator
                # trains is a run to resume
                checkpointer.save()
                amortised = group.on_main(
                    amortised_samples, cfg, train_pairs, run, resume, stop
                )
            samples = amortised.samples if amortised is not None else None
            for spec in cfg.models:
                _stream_model(
                    cfg, spec, rollout, state, checkpointer, logger, group, samples
                )
            if samples is not None and refine_settings(cfg) is not None:
                _refine_models(
                    cfg, rollout, state, checkpointer, logger, group, samples
                )
        # Every rank holds the same buffers now; the selection is cheap and
        # deterministic, so each computes it and only rank 0 writes.
        wall = time.perf_counter() - began
        posterior, summary = read_results(
            cfg, train_pairs, test_pairs, state, wall, group.world_size
        )
        if amortised is not None:
            record = amortised.record
            if state.refinement_before is not None:
                record = record.with_refinement(
                    refinement_result(
                        cfg, state.refinement_before, state.buffers, train_pairs.n_pairs
                    )
                )
            summary = summary.with_amortised(record)
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
        _log_results(cfg, logger, posterior, summary, images)
    if group.is_main:
        _write_outputs(run, posterior, summary, images)
    return summary


def _prepare(cfg: TrainConfig, run: RunDir, group: Group) -> None:
    """The run directory made (rank 0) with the resolved ``config.json`` and,
    for a raw source, the extraction's record."""
    group.on_main(run.prepare)
    group.on_main(run.write_config, resolved_json(cfg))
    if cfg.data.raw is not None:  # where the pairs came from, what was dropped
        group.on_main(record_extraction, cfg.data.raw, run.data_dir)


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
    run.write_summary(summary.to_json())  # last: its presence says it finished


def _finished_summary(run: RunDir, resume: bool) -> RunSummary | None:
    """The summary of a run resumed after it finished (its checkpoint matched the
    config: :func:`open_run`), else None. Training it again would redo the
    selection and the battery, and log every result to TensorBoard twice.

    Raises:
        RunError: its ``summary.json`` is not a run summary.
    """
    if not (resume and run.is_trained()):
        return None
    try:
        return RunSummary.from_json(run.read_summary())
    except ValueError as error:
        raise RunError(f"--resume: {run.summary_json}: {error}") from None


def _log_results(
    cfg: TrainConfig,
    logger: RunLogger,
    posterior: Posterior,
    summary: RunSummary,
    images: dict[str, np.ndarray] | None,
) -> None:
    """The accepted parameters, the shares and the summary in TensorBoard;
    ``images``: the hybrid's figures, rendered once for here and the report."""
    names = list(posterior.models)
    for name in names:
        particles = posterior.hybrid[name]
        logger.posterior(name, particles.param_names, particles.theta)
    sensitivity = dict(summary.sensitivity)
    if images is not None:  # rendered on rank 0, whose logger writes
        logger.hybrid(posterior.shares, images, sensitivity)
    logger.text("summary", markdown_summary(summary.to_json()))
    logger.text("parameters", parameters_markdown(posterior))
    logger.hparams(
        {
            "dataset": summary.dataset,
            "layout": cfg.abc.layout,
            "n_particles": cfg.abc.n_particles,
            "top_n": cfg.abc.top_n,
            "seed": cfg.abc.seed,
            "dtype": cfg.dtype,
            "models": ",".join(names),
        },
        {f"share/{name}": share for name, share in posterior.shares.items()},
    )


__all__ = ["train"]
