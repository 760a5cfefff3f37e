"""A training run (the library behind ``python -m torchcf.train CONFIG``).

    python -m torchcf.train configs/carII.json
    python -m torchcf.train configs/smoke.json --set abc.n_particles=50000
    python -m torchcf.train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

The ABC itself is :mod:`torchcf.abc`: for every model of the config, its prior
stream is run through its per-pair top-N buffer (:func:`torchcf.abc.run_rejection`)
and the hybrid is read from the buffers (:mod:`torchcf.abc.hybrid`). This module
holds what makes that a *run*: the output directory and the checkpoint (every
``abc.checkpoint_every`` seconds and after each model, so that ``--resume`` ends
identical to an uninterrupted run), progress bars and TensorBoard, the processes of
a ``torchrun`` group (rank 0 reads and writes, every rank holds the merged
buffers), and ``summary.json``.

The command line (:mod:`torchcf.train.__main__`) runs the study
(:func:`torchcf.pipeline.run_study`): training, then the test-split evaluation
(unless ``--no-eval``) and, with ``diagnose.run_after_training``, the diagnosis
loop.

The output directory (:class:`torchcf.rundir.RunDir`) receives ``config.json``
(resolved), ``checkpoint.pt``, TensorBoard event files under ``tb/``, and at the
end ``posterior.pt`` and ``summary.json``, written last: a directory without
``summary.json`` holds an unfinished run.

Exit codes (:mod:`torchcf.cli`): 0 done; 2 bad config, data, arguments or output
directory, a corrupted checkpoint, or an output that cannot be written (one line
on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import math
import platform
import sys
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from .. import __version__
from ..abc.distributed import SINGLE, Group
from ..abc.hybrid import Selection, hybrid_posterior, pairwise_table, select
from ..abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from ..abc.screen import PlausibilityScreen
from ..abc.smc import (
    SMCSettings,
    SMCState,
    evidence_shares,
    new_state,
    parameter_buffer,
    prior_mass,
    proposals_per_pair,
    run_smc,
    smc_budget,
)
from ..abc.topn import TopN
from ..cli import one_line
from ..config import ConfigError, TrainConfig, config_hash, load_split, resolved_json
from ..data import PairSet
from ..data.importer import record_extraction
from ..errors import TorchcfError
from ..evaluation.plots import hybrid_images, save_image
from ..files import RunFileError, ensure_directory, writing
from ..models import get_model
from ..posterior import Posterior
from ..posterior.tables import parameters_markdown, write_parameter_tables
from ..rundir import RunDir
from ..runtime import tune_malloc
from ..signals import StopRequest
from ..tblog import RunLogger, markdown_summary
from ..traffic.battery import Battery, battery_speed, check_plausibility, rejects

CHECKPOINT_FORMAT = "torchcf.checkpoint/1"
#: Particles per battery call on the hybrid after training. The battery holds
#: about 350 KiB per particle at its peak (the scenarios' recorded series): its
#: own default of 16 384 took 5.6 GiB once a model held that many hybrid
#: particles (10 000 pairs x 5), 2 048 take 0.7 GiB, and run faster (IDM, 8 192
#: particles: 13 s against 20 s on 1 thread). The result does not depend on it.
BATTERY_CHUNK = 1 << 11


class RunError(TorchcfError, RuntimeError):
    """A run that cannot start or continue as asked (one-line message)."""


@dataclass
class RunState:
    """Everything a checkpoint holds: per model, its progress and its buffer."""

    config_hash: str
    progress: dict[str, ModelProgress] = field(default_factory=dict)
    buffers: dict[str, TopN] = field(default_factory=dict)
    #: the refinement's state per model (``abc.method = "smc"`` only)
    smc: dict[str, SMCState] = field(default_factory=dict)
    #: buffer and refinement state dicts read from a checkpoint, until the
    #: buffers are built
    saved_buffers: dict[str, dict[str, Any]] = field(default_factory=dict)
    saved_smc: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_checkpoint(self) -> dict[str, Any]:
        checkpoint = {
            "format": CHECKPOINT_FORMAT,
            "config_hash": self.config_hash,
            "progress": {k: v.as_dict() for k, v in self.progress.items()},
            "buffers": {k: b.state_dict() for k, b in self.buffers.items()},
        }
        if self.smc:
            checkpoint["smc"] = {k: v.state_dict() for k, v in self.smc.items()}
        return checkpoint


# --------------------------------------------------------------------------------------
# Set-up


def run_device(cfg: TrainConfig, group: Group) -> torch.device:
    """The device this process simulates on; ConfigError if it is not there."""
    device = group.run_device(cfg.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"device: {cfg.device!r} asked for but CUDA is not available"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(
                f"device: {str(device)!r} asked for but only "
                f"{torch.cuda.device_count()} CUDA device(s) are visible"
            )
    return device


def open_run(cfg: TrainConfig, out: Path, resume: bool) -> RunState:
    """Check the output directory against ``--resume``, before any data is loaded.

    Probes that the directory can be created and written (leaving nothing
    behind: a bad config or data set found next must not leave an empty run
    directory); with ``resume`` loads the checkpoint and checks it was written
    with this very config.

    Raises:
        RunError: a run is there and ``resume`` is not asked, or ``resume`` is
            asked and no (matching, readable) checkpoint is there.
        RunFileError: the directory cannot be created or written.
    """
    run = RunDir(out)
    digest = config_hash(cfg)
    if resume:
        if not run.checkpoint.exists():
            raise RunError(f"--resume: no checkpoint.pt in {out}")
        try:
            raw = run.load_checkpoint()
        except RunFileError as error:
            raise RunError(
                f"--resume: {one_line(error)}; start again with another --out"
            ) from None
        if not isinstance(raw, dict) or raw.get("format") != CHECKPOINT_FORMAT:
            raise RunError(f"--resume: {run.checkpoint} is not a torchcf checkpoint")
        if raw.get("config_hash") != digest:
            raise RunError(
                f"--resume: {out} was run with a different config (hash "
                f"{raw.get('config_hash')}, this config {digest}); use another --out"
            )
        run.probe()
        return _checkpoint_state(raw, digest, run.checkpoint)
    if out.exists() and not out.is_dir():
        raise RunError(f"output directory {out} exists and is not a directory")
    if run.holds_run():
        raise RunError(
            f"{out} already holds a run; pass --resume to continue it, or --out "
            "for a new directory"
        )
    run.probe()
    return RunState(digest)


def _checkpoint_state(raw: dict[str, Any], digest: str, path: Path) -> RunState:
    """The RunState of a loaded checkpoint; RunError if its content is malformed."""
    state = RunState(digest)
    try:
        for name, progress in raw["progress"].items():
            state.progress[name] = ModelProgress(**progress)
            if not 0 <= state.progress[name].next:
                raise ValueError(f"{name}: negative progress")
        buffers = raw["buffers"]
        for name, buffer in buffers.items():
            if not all(
                isinstance(buffer.get(key), torch.Tensor)
                for key in ("score", "index", "theta")
            ):
                raise ValueError(f"{name}: buffer tensors missing")
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise RunError(
            f"--resume: {path} is corrupted ({type(error).__name__}: {error}); "
            "start again with another --out"
        ) from None
    state.saved_buffers = buffers
    state.saved_smc = raw.get("smc", {})
    return state


def check_budget(cfg: TrainConfig, pairs: PairSet) -> None:
    """Every training pair must be able to fill its buffer: ConfigError if not.

    In the paired layout a pair receives ``n_particles / n_pairs`` particles on
    average, in the full layout every particle; asking for more than that per pair
    (``top_n`` or an N of ``sensitivity_n``) can only leave buffers short.
    """
    abc = cfg.abc
    if abc.method == "smc":
        _check_smc_budget(cfg, pairs)
    paired = abc.layout == "paired"
    per_pair = abc.n_particles / pairs.n_pairs if paired else abc.n_particles
    for key, n in (("top_n", abc.top_n), ("sensitivity_n", max(abc.sensitivity_n))):
        if n <= per_pair:
            continue
        received = (
            f"abc.n_particles = {abc.n_particles} over {pairs.n_pairs} training "
            f"pairs, {per_pair:.3g} per pair on average in the paired layout"
            if paired
            else f"abc.n_particles = {abc.n_particles} in the full layout"
        )
        need = n * pairs.n_pairs if paired else n
        raise ConfigError(
            f"abc.{key}: {n} particles per pair asked for, more than a training "
            f"pair receives ({received}); set abc.n_particles >= {need} or lower "
            f"abc.{key}"
        )


def _check_smc_budget(cfg: TrainConfig, pairs: PairSet) -> None:
    """The refinement needs a population per pair from its prior round and at
    least one proposal per pair and round: ConfigError if the budget is short."""
    settings = smc_settings(cfg)
    budget = smc_budget(cfg.abc.n_particles, pairs.n_pairs, settings)
    need = max(
        settings.population * pairs.n_pairs / settings.prior_fraction,
        settings.rounds * pairs.n_pairs / (1 - settings.prior_fraction),
    )
    if budget.prior < settings.population * pairs.n_pairs or budget.per_pair < 1:
        raise ConfigError(
            f"abc.n_particles = {cfg.abc.n_particles} is too few for method 'smc' "
            f"on {pairs.n_pairs} training pairs: its prior round must give every "
            f"pair abc.smc.population = {settings.population} particles on "
            f"average and every later round a proposal per pair; set "
            f"abc.n_particles >= {math.ceil(need)} or lower abc.smc.population "
            "or abc.smc.rounds"
        )


def smc_settings(cfg: TrainConfig) -> SMCSettings:
    """The refinement's settings of a config."""
    return SMCSettings(**cfg.abc.smc.model_dump())


def _buffers(cfg: TrainConfig, pairs: PairSet, state: RunState, run: RunDir) -> None:
    """Every model's buffer (from the checkpoint where it has one), progress and,
    for SMC, refinement state (whose buffers carry one more column, ``log r``)."""
    smc = cfg.abc.method == "smc"
    for spec in cfg.models:
        n_params = len(get_model(spec.name).param_names)
        buffer = TopN(pairs.n_pairs, cfg.abc.buffer_size, n_params + smc)
        refinement = new_state(pairs.n_pairs, smc_settings(cfg), n_params)
        try:
            if spec.name in state.saved_buffers:
                buffer.load_state_dict(state.saved_buffers[spec.name])
            if smc and spec.name in state.saved_smc:
                refinement.load_state_dict(state.saved_smc[spec.name])
        except (KeyError, ValueError, TypeError) as error:
            raise RunError(
                f"--resume: {run.checkpoint} does not match this run ({error})"
            ) from None
        state.buffers[spec.name] = buffer
        if smc:
            state.smc[spec.name] = refinement
        state.progress.setdefault(spec.name, ModelProgress())


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
    )


# --------------------------------------------------------------------------------------
# One model's stream, with checkpoints and progress


class _Checkpointer:
    """Saves the run state on rank 0, every ``every`` seconds when asked, and at
    once when a stop was requested (Ctrl-C or SIGTERM: :mod:`torchcf.signals`),
    after which it stops the run."""

    def __init__(
        self,
        run: RunDir,
        state: RunState,
        every: float,
        group: Group,
        stop: StopRequest | None = None,
    ):
        self.run, self.state, self.every, self.group = run, state, every, group
        self.stop = stop
        self.last = time.perf_counter()

    def due(self) -> bool:
        if self.stop is not None and self.stop.requested:
            return True
        return time.perf_counter() - self.last >= self.every

    def save(self) -> None:
        """Every rank holds the merged buffers: rank 0 saves them; then a
        requested stop raises :class:`~torchcf.signals.Stopped`."""
        self.group.on_main(self.run.save_checkpoint, self.state.as_checkpoint())
        self.last = time.perf_counter()
        if self.stop is not None:
            self.stop.stop(checkpointed=True)


def plausibility_battery(cfg: TrainConfig, pairs: PairSet) -> Battery:
    """The config's battery at the training pairs' dt, leader length and
    (unless ``plausibility.speed`` is set) 95th-percentile leader speed."""
    settings = cfg.plausibility
    speed = settings.speed or battery_speed(pairs.v_lead, pairs.mask)
    return Battery(
        speed=speed,
        decelerations=tuple(settings.decelerations),
        collision_spacing=settings.collision_spacing,
        dt=pairs.dt,
        leader_length=pairs.leader_length,
    )


def hybrid_plausibility(
    cfg: TrainConfig, pairs: PairSet, posterior: Posterior
) -> dict[str, Any]:
    """The battery's shares per model over the hybrid's particles, on the
    CPU in float64 (:meth:`torchcf.traffic.Plausibility.summary`), in chunks
    of :data:`BATTERY_CHUNK` particles."""
    battery = plausibility_battery(cfg, pairs)
    return {
        name: check_plausibility(
            name, posterior.hybrid[name].theta, battery, chunk=BATTERY_CHUNK
        ).summary()
        for name in posterior.models
        if name in posterior.hybrid and len(posterior.hybrid[name])
    }


def plausibility_screen(cfg: TrainConfig, pairs: PairSet) -> PlausibilityScreen | None:
    """The calibration's plausibility filter (``plausibility.filter``) on the
    battery of :func:`plausibility_battery`; None when the filter is off."""
    if not cfg.plausibility.filter:
        return None
    battery = plausibility_battery(cfg, pairs)
    return PlausibilityScreen(rejects(battery, cfg.plausibility.reject_string_unstable))


def _stream_model(
    cfg: TrainConfig,
    name: str,
    rollout: Rollout,
    state: RunState,
    checkpointer: _Checkpointer,
    logger: RunLogger,
    group: Group,
) -> None:
    """Run one model's particles through its buffer (rejection or SMC), with a
    progress bar, TensorBoard scalars and checkpoints between rounds."""
    spec = next(s for s in cfg.models if s.name == name)
    buffer, progress = state.buffers[name], state.progress[name]
    if progress.done:
        return
    n_total = cfg.abc.n_particles
    bar = tqdm(
        total=n_total,
        initial=progress.next,
        desc=f"{name:>5}",
        unit="particle",
        unit_scale=True,
        dynamic_ncols=True,
        file=sys.stderr,
        # In a log file (no terminal) a line every 30 s instead of a live bar.
        mininterval=0.1 if sys.stderr.isatty() else 30.0,
        disable=not group.is_main,
    )

    screen = plausibility_screen(cfg, rollout.pairs)

    def after_round(progress: ModelProgress, due: bool) -> None:
        bar.update(progress.next - bar.n)
        invalid_rate = progress.invalid / (progress.next * rollout.cells_per_particle)
        postfix = f"invalid {invalid_rate:.1%}"
        if screen is not None:
            postfix += f", implausible {progress.implausible}"
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

    bounds = spec.bounds(torch.float64)
    with bar:
        if cfg.abc.method == "smc":
            run_smc(
                name,
                bounds,
                cfg.abc.seed,
                buffer,
                rollout,
                n_total,
                smc_settings(cfg),
                progress,
                state.smc[name],
                group=group,
                checkpoint_due=checkpointer.due,
                after_round=after_round,
                screen=screen,
            )
        else:
            run_rejection(
                prior_stream(name, bounds, cfg.abc.seed, rollout),
                buffer,
                rollout,
                n_total,
                progress,
                group=group,
                checkpoint_due=checkpointer.due,
                after_round=after_round,
                screen=screen,
            )
    progress.done = True
    checkpointer.save()


# --------------------------------------------------------------------------------------
# Results


def _dataset_label(cfg: TrainConfig) -> str:
    """The data set's name, folder, or raw source ("SOURCE (FORMAT)")."""
    if cfg.data.raw is not None:
        return f"{cfg.data.raw.source} ({cfg.data.raw.format})"
    return cfg.data.name if cfg.data.name is not None else str(cfg.data.path)


def _summary(
    cfg: TrainConfig,
    train: PairSet,
    test: PairSet,
    state: RunState,
    posterior: Posterior,
    table: torch.Tensor,
    sensitivity: dict[int, dict[str, float]],
    wall: float,
    processes: int = 1,
) -> dict[str, Any]:
    names = list(posterior.models)
    cells = 1 if cfg.abc.layout == "paired" else train.n_pairs
    per_model = {}
    for name in names:
        buffer, progress = state.buffers[name], state.progress[name]
        nth = buffer.first(cfg.abc.top_n)[0][:, -1]  # N-th best score per pair
        finite = nth[torch.isfinite(nth)]
        per_model[name] = {
            "particles": progress.next,
            "invalid": progress.invalid,
            "invalid_rate": progress.invalid / max(progress.next * cells, 1),
            "implausible": progress.implausible,
            "seconds": round(progress.seconds, 3),
            "particles_per_s": progress.next / max(progress.seconds, 1e-9),
            "best_score": _finite_or_none(float(buffer.score[:, 0].min())),
            "threshold": _finite_or_none(float(finite.mean()))
            if finite.numel()
            else None,
            "threshold_max": _finite_or_none(float(nth.max())),
            "thresholds": [_finite_or_none(float(v)) for v in nth],
            "pairs_short_of_n": int((~torch.isfinite(nth)).sum()),
        }
    return {
        "dataset": _dataset_label(cfg),
        "layout": cfg.abc.layout,
        "selection": cfg.abc.selection,
        "top_n": cfg.abc.top_n,
        "n_particles": cfg.abc.n_particles,
        "n_train": train.n_pairs,
        "n_test": test.n_pairs,
        "train_pair_ids": [int(i) for i in train.pair_ids],
        "test_pair_ids": [int(i) for i in test.pair_ids],
        "models": names,
        "shares": posterior.shares,
        "hybrid_size": sum(len(p) for p in posterior.hybrid.values()),
        "pairwise": {
            "models": names,
            "table": [[round(float(v), 6) for v in row] for row in table],
            "meaning": "table[i][j]: share of models[i] in the hybrid of {i, j} alone",
        },
        "sensitivity": {str(k): v for k, v in sensitivity.items()},
        "per_model": per_model,
        "seconds_total": round(sum(p.seconds for p in state.progress.values()), 3),
        "seconds_wall_this_process": round(wall, 3),
        "processes": processes,
        "config_hash": config_hash(cfg),
        "versions": {
            "torchcf": __version__,
            "torch": torch.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
    }


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


# --------------------------------------------------------------------------------------
# Entry points


def train(
    cfg: TrainConfig,
    out: str | Path,
    *,
    resume: bool = False,
    pairs: tuple[PairSet, PairSet] | None = None,
    group: Group = SINGLE,
) -> dict[str, Any]:
    """Run (or resume) the ABC rejection and hybrid selection of ``cfg`` into ``out``.

    Training only: the evaluation and the diagnosis loop are run after it by
    :mod:`torchcf.pipeline`.

    Args:
        cfg: the run's configuration.
        out: output directory.
        resume: continue the run in ``out`` (same config) instead of refusing it.
        pairs: optional ``(train, test)`` pair sets to use instead of loading
            ``cfg.data`` (which then only labels the run; the config hash that
            guards ``resume`` does not cover these pairs). In a distributed run
            every process must pass the same pairs.
        group: the processes sharing the run (:func:`torchcf.abc.distributed.
            init_from_env`); default a single process. Every process of the group
            calls ``train`` with the same arguments; rank 0 writes the outputs.

    Returns:
        The summary (also written to ``out/summary.json``), on every rank.

    Raises:
        ConfigError, DataError, RunError: bad config, data, output directory or
            checkpoint.
        RunFileError: an output could not be written (a full disk: the previous
            checkpoint is kept intact).
    """
    began = time.perf_counter()
    out = Path(out)
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
    pairs: tuple[PairSet, PairSet] | None,
    group: Group,
    device: torch.device,
    began: float,
) -> dict[str, Any]:
    """:func:`train` with the run directory held by rank 0 (no second process
    trains into it meanwhile)."""
    out = run.path
    # Rank 0 reads the checkpoint and the data and sends them to the others:
    # only rank 0 needs the output directory and the data files.
    state = group.on_main(open_run, cfg, out, resume)  # before the data: fail fast
    finished = group.on_main(_finished_summary, run, resume)
    if finished is not None:  # resumed after it ended: nothing left to do
        return finished
    if pairs is None:
        pairs = group.on_main(load_split, cfg.data)
    train_pairs, test_pairs = pairs
    check_budget(cfg, train_pairs)
    group.on_main(run.prepare)
    group.on_main(run.write_config, resolved_json(cfg))
    if cfg.data.raw is not None:  # where the pairs came from, what was dropped
        group.on_main(record_extraction, cfg.data.raw, run.data_dir)
    _buffers(cfg, train_pairs, state, run)
    rollout = rollout_of(cfg, train_pairs, device)
    stop = StopRequest()
    checkpointer = _Checkpointer(run, state, cfg.abc.checkpoint_every, group, stop)

    with RunLogger(run.tb_dir, enabled=group.is_main) as logger:
        with stop:  # a signal stops the stream at its next checkpoint
            for spec in cfg.models:
                _stream_model(
                    cfg, spec.name, rollout, state, checkpointer, logger, group
                )
        # Every rank holds the same buffers now; the selection is cheap and
        # deterministic, so each computes it and only rank 0 writes.
        posterior, summary = _results(
            cfg, train_pairs, test_pairs, state, time.perf_counter() - began, group
        )
        if cfg.plausibility.report and group.is_main:
            summary["plausibility"] = hybrid_plausibility(cfg, train_pairs, posterior)
            logger.plausibility(summary["plausibility"])
        images = None
        if group.is_main:
            pairwise = summary["pairwise"]
            images = hybrid_images(
                posterior.shares, pairwise["models"], pairwise["table"]
            )
        _log_results(cfg, logger, posterior, summary, images)
    if group.is_main:
        run.save_posterior(posterior)
        report = ensure_directory(run.report_dir, "report directory")
        write_parameter_tables(posterior, report)
        for name, image in images.items():
            path = report / f"{name}.png"
            with writing(path):
                save_image(image, path)
        run.write_summary(summary)  # last: its presence says the run finished
    return summary


def _finished_summary(run: RunDir, resume: bool) -> dict[str, Any] | None:
    """The summary of a run resumed after it finished (its checkpoint matched the
    config: :func:`open_run`), else None. Training it again would redo the
    selection and the battery, and log every result to TensorBoard twice."""
    return run.read_summary() if resume and run.is_trained() else None


def _results(
    cfg: TrainConfig,
    train_pairs: PairSet,
    test_pairs: PairSet,
    state: RunState,
    wall: float,
    group: Group,
) -> tuple[Posterior, dict[str, Any]]:
    """The hybrid (posterior) and the summary, read from the buffers."""
    names = [spec.name for spec in cfg.models]
    buffers = [state.buffers[name] for name in names]
    if cfg.abc.method == "smc":  # the hybrid reads the parameters alone
        buffers = [parameter_buffer(b) for b in buffers]
    kwargs = {"mode": cfg.abc.selection, "global_size": cfg.abc.global_size}
    selection = select(buffers, names, cfg.abc.top_n, **kwargs)
    table = pairwise_table(buffers, names, cfg.abc.top_n, **kwargs)
    sensitivity = {
        n: select(buffers, names, n, **kwargs).shares()
        for n in sorted(set(cfg.abc.sensitivity_n))
    }
    posterior = hybrid_posterior(
        buffers,
        names,
        selection,
        cfg.abc.top_n,
        torch.as_tensor(train_pairs.pair_ids, dtype=torch.int64),
        dataset=_dataset_label(cfg),
        mode=cfg.abc.selection,
    )
    summary = _summary(
        cfg,
        train_pairs,
        test_pairs,
        state,
        posterior,
        table,
        sensitivity,
        wall,
        group.world_size,
    )
    summary["method"] = cfg.abc.method
    if cfg.abc.method == "smc":
        summary["smc"] = _smc_summary(cfg, train_pairs, state, selection)
    return posterior, summary


def _smc_summary(
    cfg: TrainConfig, pairs: PairSet, state: RunState, selection: Selection
) -> dict[str, Any]:
    """The refinement's settings, budget and the shares with the prior's Occam
    factor (:func:`torchcf.abc.smc.evidence_shares`)."""
    names = [spec.name for spec in cfg.models]
    settings = smc_settings(cfg)
    budget = smc_budget(cfg.abc.n_particles, pairs.n_pairs, settings)
    n = cfg.abc.top_n
    scores = torch.stack([state.buffers[m].first(n)[0] for m in names])  # (M, N, n)
    member = torch.where(selection.member, scores, -math.inf)
    tau = member.amax(dim=(0, 2))  # (N,) the hybrid's worst member per pair
    masses = []
    for spec in cfg.models:
        proposals = proposals_per_pair(
            spec.name, spec.bounds(torch.float64), cfg.abc.seed, budget
        )
        masses.append(prior_mass(state.buffers[spec.name], proposals, tau))
    return {
        "settings": settings.__dict__,
        "budget": {
            "prior_draws": budget.prior,
            "proposals_per_pair_and_round": budget.per_pair,
            "rounds": budget.rounds,
            "proposals": budget.total,
            "unspent": cfg.abc.n_particles - budget.total,
        },
        "evidence_shares": evidence_shares(names, masses),
        "meaning": (
            "shares: each model's share of the per-pair top-N slots, as in "
            "rejection but from a search refined where it fits, so without the "
            "prior's Occam factor; evidence_shares: importance-sampling estimate of "
            "each model's prior mass within the hybrid's per-pair threshold, "
            "normalised per pair and averaged over pairs: what rejection's shares "
            "estimate, with the Occam factor"
        ),
    }


def _log_results(
    cfg: TrainConfig,
    logger: RunLogger,
    posterior: Posterior,
    summary: dict[str, Any],
    images: dict[str, np.ndarray] | None,
) -> None:
    """The accepted parameters, the shares and the summary in TensorBoard;
    ``images``: the hybrid's figures, rendered once for here and the report."""
    names = list(posterior.models)
    for name in names:
        particles = posterior.hybrid[name]
        logger.posterior(name, particles.param_names, particles.theta)
    table = torch.tensor(summary["pairwise"]["table"], dtype=torch.float64)
    sensitivity = {int(k): v for k, v in summary["sensitivity"].items()}
    logger.hybrid(posterior.shares, names, table, sensitivity, images)
    logger.text("summary", markdown_summary(summary))
    logger.text("parameters", parameters_markdown(posterior))
    logger.hparams(
        {
            "dataset": summary["dataset"],
            "layout": cfg.abc.layout,
            "n_particles": cfg.abc.n_particles,
            "top_n": cfg.abc.top_n,
            "seed": cfg.abc.seed,
            "dtype": cfg.dtype,
            "models": ",".join(names),
        },
        {f"share/{name}": share for name, share in posterior.shares.items()},
    )
