"""ABC rejection with hybrid model selection: ``python -m torchcf.train CONFIG``.

    python -m torchcf.train configs/carII.json
    python -m torchcf.train configs/smoke.json --set abc.n_particles=50000
    python -m torchcf.train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

For every model of the config, ``abc.n_particles`` particles are drawn from its
uniform prior (:mod:`torchcf.streams`), simulated on the training pairs
(:func:`torchcf.simulate`, paired or full layout) and offered to per-pair top-N
buffers (:mod:`torchcf.topn`); the hybrid, its shares, the pairwise table and the
sensitivity over N are then read from the buffers (:mod:`torchcf.hybrid`).

Under ``torchrun`` the particle stream of each model is shared by the processes
and the buffers merged after every round of chunks (:mod:`torchcf.distributed`);
the result is identical to a single-process run, and rank 0 writes every output.
On CUDA (``"device": "cuda"``) chunks are larger by default (:data:`CUDA_CHUNK_CELLS`).

The output directory receives ``config.json`` (resolved), ``checkpoint.pt``
(rewritten atomically every ``abc.checkpoint_every`` seconds and after each model),
TensorBoard event files under ``tb/``, and at the end ``posterior.pt``
(:mod:`torchcf.posterior`) and ``summary.json``, written last: a directory without
``summary.json`` holds an unfinished run.

Exit codes: 0 done; 2 bad config, data, arguments or output directory, a corrupted
checkpoint, or an output that cannot be written (one line on stderr, no
traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from . import __version__
from .abc.distributed import SINGLE, Group, GroupError, init_from_env
from .abc.hybrid import Selection, pairwise_table, select
from .abc.streams import ParticleStream
from .abc.topn import TopN
from .config import ConfigError, TrainConfig, config_hash, load_config, resolved_json
from .data import DataError, PairSet, load_split
from .diagnose.loop import DiagnoseError, diagnose_run
from .evaluate import EvaluationError, evaluate_run
from .models import get_model
from .models.base import CFModel
from .posterior import (
    ModelParticles,
    Posterior,
    PosteriorError,
    WriteError,
    atomic_torch_save,
    atomic_write_text,
)
from .runtime import tune_malloc
from .sim import COMPILE_CHUNK_MULTIPLE, _resolve_compile, simulate
from .tblog import RunLogger, markdown_summary

CHECKPOINT_FORMAT = "torchcf.checkpoint/1"
#: Default simulated cells per chunk on CUDA (at least): a GPU runs one kernel per
#: operation and step whatever the chunk, so larger chunks amortise the launches.
#: The result does not depend on it (chunk-size invariance).
CUDA_CHUNK_CELLS = 2**21


class RunError(RuntimeError):
    """A run that cannot start or continue as asked (one-line message)."""


#: Errors of the user's making or of the machine (config, data, output directory,
#: a corrupted file, a full disk, a process group that cannot be joined): the
#: command-line entry points print them as one line and exit with code 2.
USER_ERRORS = (
    ConfigError,
    DataError,
    RunError,
    EvaluationError,
    DiagnoseError,
    WriteError,
    PosteriorError,
    GroupError,
)


@dataclass
class ModelProgress:
    """One model's state in a run (saved in the checkpoint)."""

    next: int = 0  # particles 0 .. next-1 are in the buffer
    invalid: int = 0  # invalid rollouts among them (cells, in the full layout)
    seconds: float = 0.0  # simulation and selection time spent on them
    done: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {
            "next": self.next,
            "invalid": self.invalid,
            "seconds": self.seconds,
            "done": self.done,
        }


@dataclass
class RunState:
    """Everything a checkpoint holds."""

    config_hash: str
    progress: dict[str, ModelProgress] = field(default_factory=dict)
    buffers: dict[str, TopN] = field(default_factory=dict)
    #: buffer state dicts read from a checkpoint, until the buffers are built
    saved_buffers: dict[str, dict[str, Any]] = field(default_factory=dict)

    def save(self, path: Path) -> None:
        atomic_torch_save(
            {
                "format": CHECKPOINT_FORMAT,
                "config_hash": self.config_hash,
                "progress": {k: v.as_dict() for k, v in self.progress.items()},
                "buffers": {k: b.state_dict() for k, b in self.buffers.items()},
            },
            path,
        )


# --------------------------------------------------------------------------------------
# Set-up


def _device(cfg: TrainConfig, group: Group) -> torch.device:
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


def _chunk_size(
    cfg: TrainConfig,
    model: CFModel,
    pairs: PairSet,
    compiled: bool,
    device: torch.device,
) -> int:
    """Particles per simulate call: the config's, else the model's cell budget."""
    cells = 1 if cfg.abc.layout == "paired" else pairs.n_pairs
    budget = model.chunk_cells
    if device.type == "cuda":
        budget = max(budget, CUDA_CHUNK_CELLS)
    chunk = cfg.abc.chunk_size or max(1, budget // cells)
    chunk = min(chunk, cfg.abc.n_particles)
    if compiled:  # compiled blocks want whole vector lanes (see torchcf.sim)
        chunk = -(-chunk // COMPILE_CHUNK_MULTIPLE) * COMPILE_CHUNK_MULTIPLE
    return chunk


def _compile_mode(
    cfg: TrainConfig, model: CFModel, device: torch.device, pairs
) -> bool:
    if cfg.compile == "on":
        return model.compilable
    if cfg.compile == "off":
        return False
    cells = cfg.abc.n_particles * pairs.n_steps
    if cfg.abc.layout == "full":
        cells *= pairs.n_pairs
    return _resolve_compile(model, "auto", device, cells)


def _open_run(cfg: TrainConfig, out: Path, resume: bool) -> RunState:
    """Check the output directory against ``--resume`` and load the checkpoint."""
    digest = config_hash(cfg)
    checkpoint = out / "checkpoint.pt"
    if resume:
        if not checkpoint.exists():
            raise RunError(f"--resume: no checkpoint.pt in {out}")
        try:
            raw = torch.load(checkpoint, map_location="cpu", weights_only=True)
        except Exception as error:  # noqa: BLE001 - any unreadable file
            reason = " ".join(str(error).split()) or type(error).__name__
            raise RunError(
                f"--resume: {checkpoint} is unreadable or corrupted ({reason}); "
                "start again with another --out"
            ) from None
        if not isinstance(raw, dict) or raw.get("format") != CHECKPOINT_FORMAT:
            raise RunError(f"--resume: {checkpoint} is not a torchcf checkpoint")
        if raw.get("config_hash") != digest:
            raise RunError(
                f"--resume: {out} was run with a different config (hash "
                f"{raw.get('config_hash')}, this config {digest}); use another --out"
            )
        return _checkpoint_state(raw, digest, checkpoint)
    if checkpoint.exists() or (out / "summary.json").exists():
        raise RunError(
            f"{out} already holds a run; pass --resume to continue it, or --out "
            "for a new directory"
        )
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
    return state


def _check_budget(cfg: TrainConfig, pairs: PairSet) -> None:
    """Every training pair must be able to fill its buffer: ConfigError if not.

    In the paired layout a pair receives ``n_particles / n_pairs`` particles on
    average, in the full layout every particle; asking for more than that per pair
    (``top_n`` or an N of ``sensitivity_n``) can only leave buffers short.
    """
    abc = cfg.abc
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


def _prepare_output(cfg: TrainConfig, out: Path) -> None:
    """Create the output directory and write ``config.json``; RunError or
    WriteError (one line) if it cannot be written."""
    if out.exists() and not out.is_dir():
        raise RunError(f"output directory {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise RunError(
            f"cannot create the output directory {out}: {error.strerror or error}"
        ) from None
    atomic_write_text(
        out / "config.json", json.dumps(resolved_json(cfg), indent=2) + "\n"
    )


# --------------------------------------------------------------------------------------
# The ABC rejection of one model


def _run_model(
    cfg: TrainConfig,
    index: int,
    pairs: PairSet,
    state: RunState,
    checkpoint: Path,
    logger: RunLogger,
    device: torch.device,
    dtype: torch.dtype,
    last_save: list[float],
    group: Group,
) -> None:
    """Stream one model's particles through its buffer, in rounds of one chunk
    per process (a round is one chunk in a single process)."""
    spec = cfg.models[index]
    name = spec.name
    model = get_model(name)
    buffer = state.buffers[name]
    progress = state.progress[name]
    if progress.done:
        return
    n_total = cfg.abc.n_particles
    paired = cfg.abc.layout == "paired"
    stream = ParticleStream(
        name,
        spec.bounds(torch.float64),
        cfg.abc.seed,
        pairs.n_pairs if paired else None,
    )
    compiled = _compile_mode(cfg, model, device, pairs)
    chunk = _chunk_size(cfg, model, pairs, compiled, device)
    cells_per_particle = 1 if paired else pairs.n_pairs
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
    round_size = chunk * group.world_size
    with bar:
        for first in range(progress.next, n_total, round_size):
            began = time.perf_counter()
            start, stop = group.shard(first, n_total, chunk)
            invalid = 0
            if start < stop:
                # Always a whole chunk: a compiled block then sees one shape per
                # model, and a process simulates the chunks a single one would.
                theta, pair = stream.draw(start, start + chunk)
                real = stop - start
                out = simulate(
                    model,
                    theta.to(dtype),
                    pairs,
                    pair,
                    dtype=dtype,
                    device=device,
                    weights=cfg.abc.weights,
                    chunk_size=chunk,
                    compile=compiled,
                )
                particle = torch.arange(start, stop)
                score = out.score[:real]
                if paired:
                    buffer.push(pair[:real], score, particle, theta[:real])
                else:
                    buffer.push_full(score, particle, theta[:real])
                invalid = int((~out.valid[:real]).sum())
            due = time.perf_counter() - last_save[0] >= cfg.abc.checkpoint_every
            invalid, due = group.end_round(buffer, invalid, due)
            progress.invalid += invalid
            done_before = progress.next
            progress.next = min(first + round_size, n_total)
            progress.seconds += time.perf_counter() - began
            bar.update(progress.next - done_before)
            rate = progress.next / max(progress.seconds, 1e-9)
            invalid_rate = progress.invalid / (progress.next * cells_per_particle)
            bar.set_postfix_str(f"invalid {invalid_rate:.1%}", refresh=False)
            logger.progress(
                name,
                particles=progress.next,
                threshold=float(buffer.threshold().mean()),
                particles_per_s=rate,
                invalid_rate=invalid_rate,
            )
            if due:  # every rank holds the merged buffers: rank 0 saves them
                group.on_main(state.save, checkpoint)
                last_save[0] = time.perf_counter()
    progress.done = True
    group.on_main(state.save, checkpoint)
    last_save[0] = time.perf_counter()


# --------------------------------------------------------------------------------------
# Results


def _hybrid_posterior(
    cfg: TrainConfig, pairs: PairSet, state: RunState, selection: Selection
) -> Posterior:
    names = [spec.name for spec in cfg.models]
    pair_ids = torch.as_tensor(pairs.pair_ids, dtype=torch.int64)
    n = cfg.abc.top_n
    hybrid = {}
    buffers = {}
    for m, name in enumerate(names):
        buffer = state.buffers[name]
        score, index, theta = buffer.first(n)
        member = selection.member[m]  # (n_pairs, n)
        rows, ranks = member.nonzero(as_tuple=True)
        param_names = tuple(get_model(name).param_names)
        hybrid[name] = ModelParticles(
            param_names,
            theta[rows, ranks].clone(),
            score[rows, ranks].clone(),
            pair_ids[rows],
            index[rows, ranks].clone(),
        )
        buffers[name] = {"param_names": list(param_names), **buffer.state_dict()}
    return Posterior(
        dataset=_dataset_label(cfg),
        selection=cfg.abc.selection,
        top_n=n,
        models=tuple(names),
        shares=selection.shares(),
        train_pair_ids=pair_ids,
        hybrid=hybrid,
        buffers=buffers,
    )


def _dataset_label(cfg: TrainConfig) -> str:
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


def _fmt(value: Any) -> str:
    """A metric for the console: 3 decimals, or as stored ("inf")."""
    return f"{value:.3f}" if isinstance(value, int | float) else str(value)


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
    evaluate: bool = True,
    group: Group = SINGLE,
) -> dict[str, Any]:
    """Run (or resume) the ABC rejection and hybrid selection of ``cfg`` into ``out``.

    Args:
        cfg: the run's configuration.
        out: output directory.
        resume: continue the run in ``out`` (same config) instead of refusing it.
        pairs: optional ``(train, test)`` pair sets to use instead of loading
            ``cfg.data`` (which then only labels the run; the config hash that
            guards ``resume`` does not cover these pairs). In a distributed run
            every process must pass the same pairs.
        evaluate: then evaluate the result on the test pairs
            (:func:`torchcf.evaluate.evaluate_run`: ``metrics.json``, ``report/``)
            and, with ``diagnose.run_after_training``, close the loop
            (:func:`torchcf.diagnose.diagnose_run`: ``loop.json``, ``loop.md``).
        group: the processes sharing the run (:func:`torchcf.distributed.
            init_from_env`); default a single process. Every process of the group
            calls ``train`` with the same arguments; rank 0 writes the outputs.

    Returns:
        The summary (also written to ``out/summary.json``), on every rank.

    Raises:
        ConfigError, DataError, RunError: bad config, data, output directory or
            checkpoint.
        WriteError: an output could not be written (a full disk: the previous
            checkpoint is kept intact).
    """
    began = time.perf_counter()
    out = Path(out)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    tune_malloc()
    device = _device(cfg, group)
    dtype = getattr(torch, cfg.dtype)
    # Rank 0 reads the checkpoint and the data and sends them to the others:
    # only rank 0 needs the output directory and the data files.
    state = group.on_main(_open_run, cfg, out, resume)  # before the data: fail fast
    if pairs is None:
        pairs = group.on_main(load_split, cfg.data)
    train_pairs, test_pairs = pairs
    _check_budget(cfg, train_pairs)
    group.on_main(_prepare_output, cfg, out)
    checkpoint = out / "checkpoint.pt"

    for spec in cfg.models:
        n_params = len(get_model(spec.name).param_names)
        buffer = TopN(train_pairs.n_pairs, cfg.abc.buffer_size, n_params)
        if spec.name in state.saved_buffers:
            try:
                buffer.load_state_dict(state.saved_buffers[spec.name])
            except (KeyError, ValueError) as error:
                raise RunError(
                    f"--resume: {checkpoint} does not match this run ({error})"
                ) from None
        state.buffers[spec.name] = buffer
        state.progress.setdefault(spec.name, ModelProgress())

    with RunLogger(out / "tb", enabled=group.is_main) as logger:
        last_save = [time.perf_counter()]
        for index in range(len(cfg.models)):
            _run_model(
                cfg,
                index,
                train_pairs,
                state,
                checkpoint,
                logger,
                device,
                dtype,
                last_save,
                group,
            )
        # Every rank holds the same buffers now; the selection is cheap and
        # deterministic, so each computes it and only rank 0 writes.
        names = [spec.name for spec in cfg.models]
        buffers = [state.buffers[name] for name in names]
        kwargs = {"mode": cfg.abc.selection, "global_size": cfg.abc.global_size}
        selection = select(buffers, names, cfg.abc.top_n, **kwargs)
        table = pairwise_table(buffers, names, cfg.abc.top_n, **kwargs)
        sensitivity = {
            n: select(buffers, names, n, **kwargs).shares()
            for n in sorted(set(cfg.abc.sensitivity_n))
        }
        posterior = _hybrid_posterior(cfg, train_pairs, state, selection)
        summary = _summary(
            cfg,
            train_pairs,
            test_pairs,
            state,
            posterior,
            table,
            sensitivity,
            time.perf_counter() - began,
            group.world_size,
        )
        for name in names:
            particles = posterior.hybrid[name]
            logger.posterior(name, particles.param_names, particles.theta)
        logger.hybrid(posterior.shares, names, table, sensitivity)
        logger.text("summary", markdown_summary(summary))
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
    if not group.is_main:
        # The evaluation and the diagnosis loop are rank 0's alone (single-process
        # work on small sets); the other ranks are done.
        return summary
    posterior.save(out / "posterior.pt")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    if evaluate:
        evaluate_run(out, pairs=(train_pairs, test_pairs))
        if cfg.diagnose.run_after_training:
            diagnose_run(out, pairs=(train_pairs, test_pairs))
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torchcf.train``, alone or under ``torchrun``.

    Returns:
        0 done; 2 an error of the user's making or a failed write (one line on
        stderr); 130 interrupted.
    """
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.train",
        description="ABC rejection and hybrid model selection on car-following data.",
        epilog=(
            "Distributed: torchrun --standalone --nproc-per-node K -m torchcf.train "
            "CONFIG (README, 'Distributed runs')."
        ),
    )
    parser.add_argument("config", help="JSON config (see configs/ and --schema)")
    parser.add_argument("--out", default=None, help="output directory")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="override a config field, e.g. --set abc.n_particles=200000",
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in the output directory"
    )
    parser.add_argument(
        "--no-eval",
        action="store_true",
        help="skip the test-split evaluation (python -m torchcf.evaluate DIR later)",
    )
    args = parser.parse_args(argv)
    group = SINGLE
    try:
        cfg = load_config(args.config, args.overrides)
        out = Path(args.out) if args.out is not None else Path(cfg.output)
        group = init_from_env(cfg.device)
        summary = train(
            cfg, out, resume=args.resume, evaluate=not args.no_eval, group=group
        )
    except USER_ERRORS as error:
        _report(error, group)
        return 2
    except OSError as error:
        # The machine's, not a bug: a file system or device failing underneath.
        _report(error, group)
        return 2
    except KeyboardInterrupt:
        if group.is_main:
            print("interrupted: continue with --resume", file=sys.stderr)
        return 130
    finally:
        group.close()
    if not group.is_main:
        return 0
    width = max(len(name) for name in summary["shares"])
    print(f"hybrid shares ({summary['dataset']}, N = {summary['top_n']}):")
    for name, share in summary["shares"].items():
        seconds = summary["per_model"][name]["seconds"]
        print(f"  {name:<{width}}  {share:6.1%}   ({seconds:.1f} s)")
    metrics_path = out / "metrics.json"
    if not args.no_eval and metrics_path.exists():
        metrics = json.loads(metrics_path.read_text())
        hybrid = {k: _fmt(v) for k, v in metrics["hybrid"].items()}
        print(
            f"test split ({metrics['n_test']} pairs), hybrid: WS {hybrid['ws']}, "
            f"0.15-WS {hybrid['beta_ws']}, minimum distance {hybrid['min']}"
        )
    print(f"wrote {out}")
    return 0


def _report(error: BaseException, group: Group) -> None:
    """``error: <one line>`` on stderr; an error rank 0 already reports is left to
    it, and another rank's own error names the rank."""
    if getattr(error, "from_main", False):
        return
    message = " ".join(str(error).split()) or type(error).__name__
    rank = int(os.environ.get("RANK", "0")) if group is SINGLE else group.rank
    where = f"rank {rank}: " if rank else ""
    print(f"error: {where}{message}", file=sys.stderr)


if __name__ == "__main__":
    raise SystemExit(main())
