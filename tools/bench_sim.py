"""Benchmark: simulated particle-steps per second per model (paired layout).

The paper's setting: particles drawn from each model's prior, each simulated on one
training pair of CAR MODEL II (576 steps at 0.1 s), float32, on ``--threads`` CPU
threads. For every model it times the fused path (``torch.compile``, compilation
excluded and reported apart) and the eager fallback, with warm-up runs first and
the median of ``--repeats`` timed runs.

    python tools/bench_sim.py                      # 1e6 particles, 2 threads
    python tools/bench_sim.py --particles 2e5 --models idm hl

Writes ``reports/bench_sim.json`` and ``reports/bench_sim.md`` (torch version,
threads, CPU model, git SHA). Needs the data: ``$TORCHCF_DATA`` or ``--data-root``.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

import torchcf
from torchcf import MODELS, Execution, get_model, simulate
from torchcf.system.console import OneLineParser, count, run_main
from torchcf.system.process import tune_malloc

REPORTS = Path(__file__).resolve().parents[1] / "reports"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_sha() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=REPORTS.parent,
            check=True,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=REPORTS.parent,
            check=True,
        ).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def device_name(device: str) -> str:
    """The accelerator's name for a CUDA device, else the CPU model."""
    if torch.device(device).type == "cuda" and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    return cpu_model()


def bench_meta(argv: list[str], threads: int, device: str = "cpu") -> dict:
    """What a benchmark report records about its run: the exact command, versions,
    threads, machine and git revision (compare runs on the same machine only)."""
    import numpy

    return {
        "command": " ".join(["python", *argv]),
        "torch": torch.__version__,
        "torchcf": torchcf.__version__,
        "numpy": numpy.__version__,
        "python": sys.version.split()[0],
        "threads": threads,
        "device": device,
        "machine": device_name(device),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "git": git_sha(),
    }


def provenance(meta: dict) -> str:
    """A report's first words: the command, torch, threads, CPU and git revision
    of :func:`bench_meta` (the caller goes on with its own punctuation)."""
    return (
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"{meta['cpu']}, git {meta['git']}"
    )


def write_report(out: Path, payload: dict, markdown: str) -> None:
    """Write a benchmark's ``out.json`` (``payload``) and ``out.md`` (``markdown``)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(payload, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)


def setup(model_name: str, n_particles: int, n_pairs: int, seed: int = 0):
    """Prior draws and their training pairs, as the ABC run would make them."""
    model = MODELS[model_name]
    generator = torch.Generator().manual_seed(seed)
    bounds = model.prior_bounds(torch.float32)
    unit = torch.rand(n_particles, model.n_params, generator=generator)
    theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * unit
    pair_index = torch.randint(0, n_pairs, (n_particles,), generator=generator)
    return theta, pair_index


def time_run(model_name, theta, pairs, pair_index, compile_mode, repeats):
    """Median wall time of ``repeats`` timed runs, and the invalid fraction."""
    times = []
    run = Execution(compile=compile_mode)
    for _ in range(repeats):
        start = time.perf_counter()
        out = simulate(get_model(model_name), theta, pairs, pair_index, execution=run)
        times.append(time.perf_counter() - start)
    return statistics.median(times), times, float((~out.valid).float().mean())


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=count, default=1e6)
    parser.add_argument(
        "--eager-particles",
        type=count,
        default=2e5,
        help="particles for the (slow) eager runs",
    )
    # MPC is benchmarked by tools/bench_qp.py (its solver is not compiled).
    default_models = [name for name, model in MODELS.items() if model.compilable]
    parser.add_argument("--models", nargs="+", default=default_models)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=REPORTS / "bench_sim")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    tune_malloc()
    pairs = torchcf.load_pairs(
        "car-model-2",
        split="train",
        data_root=args.data_root,
        cleaning=torchcf.data.Cleaning(drop_duplicates=False),
    )
    n_particles, n_eager = int(args.particles), int(args.eager_particles)
    rows = []
    for name in args.models:
        theta, index = setup(name, n_particles, pairs.n_pairs)
        # Warm-up: the first full-size call compiles; its excess over the median
        # of the timed runs is the compilation cost.
        start = time.perf_counter()
        simulate(
            get_model(name), theta, pairs, index, execution=Execution(compile=True)
        )
        first_s = time.perf_counter() - start
        fused_s, fused_all, invalid = time_run(
            name, theta, pairs, index, True, args.repeats
        )
        compile_s = max(first_s - fused_s, 0.0)
        eager = Execution(compile=False)
        simulate(
            get_model(name), theta[:n_eager], pairs, index[:n_eager], execution=eager
        )
        eager_s, eager_all, _ = time_run(
            name, theta[:n_eager], pairs, index[:n_eager], False, args.repeats
        )
        steps = pairs.n_steps
        row = {
            "model": name,
            "particles": n_particles,
            "steps": steps,
            "fused_s": fused_s,
            "fused_runs_s": fused_all,
            "fused_steps_per_s": n_particles * steps / fused_s,
            "eager_particles": n_eager,
            "eager_s": eager_s,
            "eager_runs_s": eager_all,
            "eager_steps_per_s": n_eager * steps / eager_s,
            "compile_warmup_s": compile_s,
            "invalid_fraction": invalid,
        }
        rows.append(row)
        print(
            f"{name:6s} fused {row['fused_steps_per_s']:.3g} /s "
            f"({fused_s:.2f} s for {n_particles:.0e}), eager "
            f"{row['eager_steps_per_s']:.3g} /s, compile {compile_s:.1f} s",
            flush=True,
        )

    idm = next((r for r in rows if r["model"] == "idm"), None)
    meta = {
        "torch": torch.__version__,
        "torchcf": torchcf.__version__,
        "python": sys.version.split()[0],
        "threads": torch.get_num_threads(),
        "cpu": cpu_model(),
        "git": git_sha(),
        "dataset": f"car-model-2 train ({pairs.n_pairs} pairs, {pairs.n_steps} steps)",
        "dtype": "float32",
        "layout": "paired",
        "repeats": args.repeats,
    }
    lines = [
        "# Rollout throughput (paired layout)",
        "",
        f"`python tools/bench_sim.py --particles {args.particles:.0e} "
        f"--threads {args.threads}`; medians of {args.repeats} timed runs after "
        "warm-up.",
        "",
        *(f"- {key}: {value}" for key, value in meta.items()),
        "",
        "| model | fused particle-steps/s | fused time [s] | vs IDM | eager "
        "particle-steps/s | fused / eager | compile [s] | invalid |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ratio = (
            r["fused_steps_per_s"] / idm["fused_steps_per_s"] if idm else float("nan")
        )
        lines.append(
            f"| {r['model']} | {r['fused_steps_per_s']:.3g} | {r['fused_s']:.2f} | "
            f"{ratio:.2f} | {r['eager_steps_per_s']:.3g} | "
            f"{r['fused_steps_per_s'] / r['eager_steps_per_s']:.1f}x | "
            f"{r['compile_warmup_s']:.1f} | {r['invalid_fraction']:.3f} |"
        )
    lines += [
        "",
        f"Particles: {n_particles:.0e} per model (fused), "
        f"{n_eager:.0e} (eager; throughput is linear in the particle count).",
        "Compile: the first call's time minus the median (torch.compile's one-off "
        "cost in this process; inductor caches kernels on disk, so a later process "
        "compiles faster).",
        "",
    ]
    write_report(args.out, {"meta": meta, "rows": rows}, "\n".join(lines))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
