"""Benchmark: a whole training run, timed from outside.

Runs ``python -m torchcf train CONFIG --out DIR`` in a child process (under
``torchrun`` with ``--nproc K``), measures its wall time and peak resident memory
(the largest process), and writes the per-model times, rates, invalid counts and
the shares found to ``reports/bench/train_<config>.{json,md}``. It runs twice:
first with an empty ``torch.compile`` (inductor) cache, as on a fresh machine, then
again with the cache that run filled, as for every later run.

    python tools/bench_train.py configs/carII.json   # the paper's CAR MODEL II run
    python tools/bench_train.py configs/smoke.json --threads 2
    python tools/bench_train.py configs/carII.json --nproc 2 --threads 1  # torchrun
    python tools/bench_train.py configs/carII.json --set device=cuda --no-cold
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"


def _run(args, stem: str, env: dict[str, str]) -> dict | None:
    """One training run in a child process: wall time, peak RSS, its summary."""
    run_dir = Path(tempfile.mkdtemp(prefix=f"torchcf-{stem}-"))
    launcher = ["-m", "torchcf", "train"]
    if args.nproc > 1:
        launcher = [
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            str(args.nproc),
            *launcher,
        ]
    command = [
        sys.executable,
        *launcher,
        str(args.config),
        "--out",
        str(run_dir / "run"),
        "--set",
        f"threads={args.threads}",
        *(item for o in args.overrides for item in ("--set", o)),
    ]
    start = time.perf_counter()
    pid = subprocess.Popen(command, env={**os.environ, **env}).pid
    _, status, usage = os.wait4(pid, 0)
    wall = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        if code != 2:  # 2: the command said why, on one line
            print(f"training failed: exit code {code}", file=sys.stderr)
        return None
    summary = RunDir(run_dir / "run").read_summary()
    shutil.rmtree(run_dir, ignore_errors=True)
    return {
        "wall_seconds": wall,
        "peak_rss_mib": usage.ru_maxrss / 1024,
        "summary": summary,
    }


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--threads", type=count, default=2, help="per process")
    parser.add_argument(
        "--nproc", type=count, default=1, help="processes (torchrun) on this machine"
    )
    parser.add_argument(
        "--no-cold",
        action="store_true",
        help="skip the empty-cache run: one run with the machine's inductor cache",
    )
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--out", type=Path, default=None, help="report path stem")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        parser.error(f"no config file {args.config}")
    stem = args.config.stem
    suffix = f"_x{args.nproc}" if args.nproc > 1 else ""
    report = args.out or REPORTS / f"train_{stem}{suffix}"

    cache = Path(tempfile.mkdtemp(prefix="torchcf-inductor-"))
    env = {} if args.no_cold else {"TORCHINDUCTOR_CACHE_DIR": str(cache)}
    if args.nproc > 1:
        env["OMP_NUM_THREADS"] = str(args.threads)
    runs = {}
    for label in ("warm",) if args.no_cold else ("cold", "warm"):
        run = _run(args, stem, env)
        if run is None:
            return 2
        runs[label] = run
    shutil.rmtree(cache, ignore_errors=True)
    if "cold" not in runs:
        runs["cold"] = runs["warm"]
    summary = runs["warm"]["summary"]
    if runs["cold"]["summary"].shares != summary.shares:
        print("the two runs found different shares", file=sys.stderr)
        return 1

    device = next(
        (o.split("=", 1)[1] for o in args.overrides if o.startswith("device=")), "cpu"
    )
    meta = bench_meta(["tools/bench_train.py", *sys.argv[1:]], args.threads, device)
    meta["processes"] = args.nproc
    wall = runs["warm"]["wall_seconds"]
    cold_wall = runs["cold"]["wall_seconds"]
    peak_mib = max(run["peak_rss_mib"] for run in runs.values())
    result = {
        "meta": meta,
        "cold_cache": {k: v for k, v in runs["cold"].items() if k != "summary"},
        "warm_cache": {k: v for k, v in runs["warm"].items() if k != "summary"},
        "cold_cache_per_model_seconds": {
            name: m.seconds for name, m in runs["cold"]["summary"].per_model.items()
        },
        "summary": summary.to_json(),
    }
    lines = [
        f"# Training run: `{args.config}`",
        "",
        f"`{meta['command']}`",
        "",
        *(f"- {key}: {value}" for key, value in meta.items() if key != "command"),
        "",
        f"{summary.dataset}: {summary.n_train} training pairs, "
        f"{summary.n_particles:,} particles per model, layout {summary.layout}, "
        f"N = {summary.top_n}.",
        "",
        (
            f"**Wall time {wall:.0f} s ({wall / 60:.1f} min)** with the machine's "
            "compile cache"
            if args.no_cold
            else f"**Wall time {cold_wall:.0f} s ({cold_wall / 60:.1f} min) on a "
            f"fresh machine** (empty compile cache) and **{wall:.0f} s "
            f"({wall / 60:.1f} min) once the cache holds the compiled kernels**"
        )
        + f", {args.nproc} process(es) x {args.threads} thread(s), for the whole "
        "run (start-up, data loading, compilation, simulation, selection, outputs, "
        f"test-split evaluation); peak resident memory {peak_mib:.0f} MiB (largest "
        "process)." + ("" if args.no_cold else " Both runs found the same shares."),
        "",
        "Per model:" if args.no_cold else "Per model (seconds: cold / warm cache):",
        "",
        "| model | share | seconds | particles/s (warm) | invalid rollouts | "
        "stopped early | best score | threshold (mean N-th best) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    cold_seconds = result["cold_cache_per_model_seconds"]
    for name in summary.models:
        m = summary.per_model[name]
        best = "n/a" if m.best_score is None else f"{m.best_score:.3f}"
        thr = "n/a" if m.threshold is None else f"{m.threshold:.3f}"
        lines.append(
            f"| {name} | {summary.shares[name]:.1%} | "
            f"{cold_seconds[name]:.1f} / {m.seconds:.1f} | "
            f"{m.particles_per_s:.3g} | {m.invalid:,} | "
            f"{m.stopped:,} | {best} | {thr} |"
        )
    early = any(m.stopped for m in summary.per_model.values())
    lines += [
        "",
        (
            "Early rejection (`abc.early_rejection`): every model's rollouts "
            + (
                "run compiled (`compile` on: one graph per model for every batch size)"
                if any("compile=on" in o.replace(" ", "") for o in args.overrides)
                else 'run eager (`compile: "auto"` stays eager with it)'
            )
            + " and stop once their score is sure to exceed their pair's "
            "buffer threshold; invalid rollouts are counted among those run to "
            "the end."
            if early
            else "Seconds per model include `torch.compile` of its time loop "
            'where it runs compiled (`compile`: "auto" compiles from 2e8 '
            "particle-steps on the CPU, from 1e11 on CUDA; MPC compiles around "
            "its QP solver, which runs eager)."
        ),
        "",
    ]
    write_report(report, result, "\n".join(lines))
    print(f"wrote {report.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
