"""Benchmark: vehicle-steps per second of a ring road driven by a HybridSampler.

One ring of ``--vehicles`` vehicles (25 m apart, 10 m/s at the start) driven by
each learned hybrid given (default: the NGSIM and CAR MODEL II runs of
``runs/paper/``), and, as a reference without mixing, by the IDM particles of the
first hybrid alone. Each is timed eager and fused by ``torch.compile`` (the whole
ring step: the sampler's grouped commands, the realisation, the spacing update;
MPC's solver stays eager inside it), float32, after warm-up steps (the
compilation, reported apart), as the median of ``--repeats`` runs of ``--steps``
steps.

    python tools/bench_traffic.py                          # 1e5 vehicles, 2 threads
    python tools/bench_traffic.py --device cuda            # on a GPU
    python tools/bench_traffic.py --posteriors runs/ngsim/posterior.pt

Writes ``reports/bench/traffic.json`` and ``reports/bench/traffic.md`` (torch
version, threads, CPU model, load average, git SHA). A missing posterior file is
a one-line error (exit 2).
"""

from __future__ import annotations

import os
import shlex
import statistics
import sys
import time
from pathlib import Path

import torch

from torchcf import HybridSampler
from torchcf.system.process import tune_malloc
from torchcf.traffic.scenarios import ring_initial_state, ring_road

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_POSTERIORS = [
    ROOT / "runs/paper/ngsim/posterior.pt",
    ROOT / "runs/paper/carII/posterior.pt",
]
SPACING = 25.0  # [m] initial spacing
SPEED = 10.0  # [m/s] initial speed


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def setup(sampler: HybridSampler, n_vehicles: int, device: torch.device, seed: int):
    """The sampler on ``device`` with one ring of ``n_vehicles`` drawn vehicles."""
    sampler = sampler.to(device)
    generator = torch.Generator(device=device).manual_seed(seed)
    sampler.sample((1, n_vehicles), generator)
    length = n_vehicles * SPACING
    return sampler, length, ring_initial_state(sampler, length, v_init=SPEED)


def time_case(sampler, length, initial, steps, repeats, warmup, use_compile, device):
    """Warm-up seconds, the timed runs' seconds, and the collided fraction."""
    start = time.perf_counter()
    out = ring_road(
        sampler,
        length,
        warmup,
        initial=initial,
        record_every=None,
        compile=use_compile,
    )
    synchronize(device)
    warmup_s = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = ring_road(
            sampler,
            length,
            steps,
            initial=out.final,
            record_every=None,
            compile=use_compile,
        )
        synchronize(device)
        runs.append(time.perf_counter() - start)
    return warmup_s, runs, float(out.collided.float().mean())


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--posteriors", nargs="+", type=Path, default=DEFAULT_POSTERIORS
    )
    parser.add_argument("--vehicles", type=count, default=1e5)
    parser.add_argument("--steps", type=count, default=100)
    parser.add_argument("--warmup", type=natural, default=10)
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument(
        "--threads", type=count, nargs="+", default=[2], help="one or more counts"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--out", type=Path, default=ROOT / "reports/bench/traffic")
    args = parser.parse_args(argv)

    missing = [str(p) for p in args.posteriors if not Path(p).is_file()]
    if missing:
        print(f"error: no posterior file {', '.join(missing)}", file=sys.stderr)
        return 2
    try:
        device = torch.device(args.device)
    except RuntimeError as error:
        print(f"error: --device: {error}", file=sys.stderr)
        return 2
    if device.type == "cuda" and not torch.cuda.is_available():
        print("error: --device cuda but CUDA is not available", file=sys.stderr)
        return 2
    if (
        args.vehicles < 2
        or min(args.steps, args.repeats, args.warmup) < 1
        or min(args.threads) < 1
    ):
        print(
            "error: need --vehicles >= 2 and --steps, --repeats, --warmup, "
            "--threads >= 1",
            file=sys.stderr,
        )
        return 2
    tune_malloc()
    n_vehicles = int(args.vehicles)
    load_before = os.getloadavg()

    cases = []
    for path in args.posteriors:
        label = Path(path).parent.name or Path(path).stem
        try:
            cases.append((f"{label} hybrid", HybridSampler.from_file(path)))
        except ValueError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
    first = cases[0][1]
    if "idm" in first.model_names and first.particles("idm").shape[0]:
        idm = first.models[first.model_names.index("idm")]
        idm_only = HybridSampler(
            [idm], [first.particles("idm")], dt=first.dt, dtype=first.dtype
        )
        cases.append((f"{cases[0][0].split()[0]} IDM only", idm_only))

    rows = []
    for label, sampler in cases:
        sampler, length, initial = setup(sampler, n_vehicles, device, seed=0)
        groups = {name: share for name, share in sampler.shares.items() if share > 0}
        modes = (False,) if args.no_compile else (False, True)
        for threads, use_compile in ((t, c) for t in args.threads for c in modes):
            torch.set_num_threads(threads)
            warmup_s, runs, collided = time_case(
                sampler,
                length,
                initial,
                args.steps,
                args.repeats,
                args.warmup,
                use_compile,
                device,
            )
            median = statistics.median(runs)
            row = {
                "case": label,
                "models": groups,
                "mode": "compiled" if use_compile else "eager",
                "threads": threads,
                "vehicles": n_vehicles,
                "steps": args.steps,
                "median_s": median,
                "runs_s": runs,
                "vehicle_steps_per_s": n_vehicles * args.steps / median,
                "ms_per_step": 1e3 * median / args.steps,
                "warmup_s": warmup_s,
                "warmup_steps": args.warmup,
                "collided_fraction": collided,
            }
            rows.append(row)
            print(
                f"{label:22s} {row['mode']:8s} {threads} thr "
                f"{row['vehicle_steps_per_s']:.3g} "
                f"vehicle-steps/s ({row['ms_per_step']:.1f} ms/step), warm-up "
                f"{warmup_s:.1f} s",
                flush=True,
            )

    arguments = argv if argv is not None else sys.argv[1:]
    meta = {
        **bench_meta(
            ["tools/bench_traffic.py", *(shlex.quote(a) for a in arguments)],
            args.threads,
            str(device),
        ),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "dtype": str(first.dtype).replace("torch.", ""),
        "ring": f"1 x {n_vehicles} vehicles, {SPACING:g} m apart, {SPEED:g} m/s",
        "dt": first.dt,
        "repeats": args.repeats,
    }
    lines = [
        "# Ring-road throughput of the HybridSampler",
        "",
        f"`{meta['command']}`; median of {args.repeats} runs of {args.steps} steps "
        f"after {args.warmup} warm-up steps.",
        "",
        *(f"- {key}: {value}" for key, value in meta.items() if key != "command"),
        "",
        "| case | models (share) | mode | threads | vehicle-steps/s | ms/step "
        "| warm-up [s] | collided |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        models = ", ".join(f"{k} {v:.2f}" for k, v in r["models"].items())
        lines.append(
            f"| {r['case']} | {models} | {r['mode']} | {r['threads']} | "
            f"{r['vehicle_steps_per_s']:.3g} | {r['ms_per_step']:.1f} | "
            f"{r['warmup_s']:.1f} | {r['collided_fraction']:.3f} |"
        )
    lines += [
        "",
        "Warm-up: the first steps, which for `compiled` include torch.compile's "
        "one-off compilation (inductor caches kernels on disk: a later process "
        "compiles faster). `collided`: fraction of vehicles whose spacing reached "
        "0 by the end (the learned models are simulated as they are, far from the "
        "data they were fitted on; see `reports/traffic/`). The machine's load "
        "average is recorded because other work may share its cores: compare runs "
        "on the same, quiet machine only.",
        "",
    ]
    write_report(args.out, {"meta": meta, "rows": rows}, "\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
