"""Benchmark: peak memory of the streaming trainer against the particle count.

The trainer streams each model's particles through fixed-size chunks and keeps
only per-pair top-N buffers, so its memory should not grow with the number of
particles. This runs :func:`torchcf.train.train` on IDM alone (CAR MODEL II
training split, paired layout, no evaluation) once per ``--sizes`` entry, each in
a fresh child process, and records the child's peak resident set size
(``resource.getrusage(RUSAGE_SELF).ru_maxrss`` at its end: everything the process
touched, the Python interpreter, torch and the data included). The target: the
largest size's peak at most ``--target`` (1.1) times the smallest's.

    python tools/bench_memory.py                          # 1e5 vs 1e7 particles
    python tools/bench_memory.py --sizes 1e4 1e6 --compile off   # a quick check

Both sizes run the same code path with the same chunk (``--compile`` and
``--chunk-size`` apply to both; the default chunk, 1e5 particles, is the one the
1e5 run takes by itself, as a chunk never exceeds the particle count), so the
ratio measures what the particle count adds; the chunk sets the level (``--chunk-
size 0`` takes the model's default, 2^18 for IDM, where the runs allow it).
Writes ``reports/bench/memory.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.system.console import OneLineParser, count, natural, positive, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"


def child(n_particles: int, args: argparse.Namespace) -> dict:
    """One training run in this (fresh) process; returns its peak RSS and time."""
    from torchcf.config import validate_config
    from torchcf.train import train

    raw = {
        "data": {"name": "car-model-2"},
        "models": ["idm"],
        "abc": {
            "n_particles": n_particles,
            "sensitivity_n": [5, 10, 15],
            "chunk_size": args.chunk_size or None,
        },
        "compile": args.compile,
        "threads": args.threads,
        "device": args.device,
    }
    if args.data_root:
        raw["data"]["root"] = args.data_root
    cfg = validate_config(raw)
    with tempfile.TemporaryDirectory(prefix="torchcf-memory-") as out:
        start = time.perf_counter()
        summary = train(cfg, Path(out) / "run")
        seconds = time.perf_counter() - start
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    result = {
        "particles": n_particles,
        "peak_rss_mib": peak_kib / 1024,
        "seconds": seconds,
        "particles_per_s": summary.per_model["idm"].particles_per_s,
    }
    if args.device.startswith("cuda"):
        import torch

        result["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return result


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=count, nargs="+", default=[1e5, 1e7])
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--compile", choices=("on", "off"), default="on")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--chunk-size",
        type=natural,
        default=100_000,
        help="particles per chunk in every run (0: the model's default)",
    )
    parser.add_argument("--target", type=positive, default=1.1)
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=REPORTS / "memory")
    parser.add_argument("--child", type=count, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        print(json.dumps(child(int(args.child), args)))
        return 0

    forwarded = [
        "--threads",
        str(args.threads),
        "--compile",
        args.compile,
        "--device",
        args.device,
        "--chunk-size",
        str(args.chunk_size),
        *(["--data-root", args.data_root] if args.data_root else []),
    ]
    rows = []
    for size in sorted(args.sizes):
        command = [sys.executable, __file__, "--child", str(size), *forwarded]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            print(done.stderr[-3000:], file=sys.stderr)
            return 1
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(row)
        peak, seconds = row["peak_rss_mib"], row["seconds"]
        print(f"{size:.0e} particles: peak RSS {peak:.0f} MiB, {seconds:.1f} s")
    ratio = rows[-1]["peak_rss_mib"] / rows[0]["peak_rss_mib"]
    meta = bench_meta(
        ["tools/bench_memory.py", *sys.argv[1:]], args.threads, args.device
    )
    meta |= {
        "model": "idm",
        "dataset": "car-model-2 train",
        "compile": args.compile,
        "chunk_size": args.chunk_size or "model default",
    }
    result = {"meta": meta, "rows": rows, "ratio": ratio, "target": args.target}
    verdict = "met" if ratio <= args.target else "NOT met"
    lines = [
        "# Peak memory of the streaming trainer against the particle count",
        "",
        f"`{meta['command']}`",
        "",
        *(f"- {key}: {value}" for key, value in meta.items() if key != "command"),
        "",
        "IDM alone through `torchcf.train.train` (paired layout, per-pair top-15 "
        "buffers, no evaluation), each size in a fresh process with the same "
        "chunk; peak resident set size of that process.",
        "",
        "| particles | peak RSS [MiB] | seconds | particles/s |",
        "|---|---|---|---|",
        *(
            f"| {r['particles']:.0e} | {r['peak_rss_mib']:.0f} | {r['seconds']:.1f} | "
            f"{r['particles_per_s']:.3g} |"
            for r in rows
        ),
        "",
        f"Ratio {rows[-1]['particles']:.0e} / {rows[0]['particles']:.0e}: "
        f"**{ratio:.3f}** (target <= {args.target}: {verdict}).",
        "",
    ]
    write_report(args.out, result, "\n".join(lines))
    print(f"ratio {ratio:.3f} (target <= {args.target}: {verdict})")
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0 if ratio <= args.target else 1


if __name__ == "__main__":
    raise SystemExit(run_main(main))
