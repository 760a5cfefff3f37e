"""Benchmark: per-model throughput against the per-particle NumPy peer baseline.

For each of the eight models, in one run on one machine:

* **torchcf**: ``--particles`` prior draws, each simulated on one training pair of
  CAR MODEL II (paired layout, 576 steps, float32) by :func:`torchcf.simulate`,
  fused with ``torch.compile`` (MPC around its eager QP solver); one warm-up
  call (compilation), then the median of ``--repeats`` timed calls.
* **peer baseline**: the first ``--baseline-particles`` of the same particles, one
  at a time, by ``tools/peer_numpy.py`` (a Python loop over time steps on NumPy
  arrays, the style of the paper's released implementation; one process, one
  core), timed in total. Its scores are checked against torchcf's (float64) on
  the same particles, so both sides do the same work.

Both are reported in simulated particle-steps per second; the speed-up is their
ratio, and per core it divides by torchcf's threads (the baseline is one core; run
``--threads 1`` for a core-to-core comparison). The baseline's rate is per step
and does not depend on the particle count, so a few dozen particles measure it.

    python tools/bench_models.py                                  # 1e6, 2 threads
    python tools/bench_models.py --particles 2e5 --models idm hl --repeats 1
    python tools/bench_models.py --device cuda --particles 1e7   # on a GPU

Writes ``reports/bench/models.json`` and ``reports/bench/models.md`` (``--out``),
with the exact command, torch version, threads, machine and git revision. Needs
the data: ``$TORCHCF_DATA`` or ``--data-root``.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, setup, write_report  # noqa: E402
from peer_numpy import quiet_stdout, simulate_one  # noqa: E402

import torchcf  # noqa: E402
from torchcf import MODELS, Execution, get_model, simulate  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402
from torchcf.system.process import tune_malloc  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_torchcf(name, theta, pairs, index, device, compile_mode, repeats):
    """Median seconds of ``repeats`` calls after one warm-up call, plus the
    warm-up's excess (compilation) and the invalid fraction."""
    device = torch.device(device)
    theta, index = theta.to(device), index.to(device)
    run = Execution(compile=compile_mode)

    def call():
        _sync(device)
        start = time.perf_counter()
        out = simulate(get_model(name), theta, pairs, index, execution=run)
        _sync(device)
        return time.perf_counter() - start, out

    first, _ = call()
    times, outs = zip(*(call() for _ in range(repeats)), strict=True)
    median = statistics.median(times)
    invalid = float((~outs[-1].valid).float().mean())
    return median, list(times), max(first - median, 0.0), invalid


def time_baseline(name, theta, pairs, index, weights=(0.5, 0.3, 0.2)):
    """Seconds the peer baseline takes for these particles, and its scores."""
    series = {k: v.numpy() for k, v in pairs.series().items()}  # (T, N) float64
    params = theta.double().numpy()
    pair_of = index.tolist()
    scores = np.empty(len(pair_of))
    with quiet_stdout():
        start = time.perf_counter()
        for j, pair in enumerate(pair_of):
            scores[j] = simulate_one(
                name,
                params[j],
                series["x_lead"][:, pair],
                series["v_lead"][:, pair],
                series["x_follow"][:, pair],
                series["v_follow"][:, pair],
                series["a_follow"][:, pair],
                pairs.dt,
                pairs.leader_length,
                weights,
            )
        seconds = time.perf_counter() - start
    return seconds, scores


def check_scores(name, theta, pairs, index, baseline: np.ndarray) -> dict:
    """The baseline's scores against torchcf's float64 scores, same particles."""
    ours = simulate(get_model(name), theta.double(), pairs, index, dtype=torch.float64)
    ours = ours.score.numpy()
    both = np.isfinite(ours) & np.isfinite(baseline)
    rel = np.abs(ours[both] - baseline[both]) / np.maximum(np.abs(ours[both]), 1e-12)
    return {
        "particles_compared": int(both.sum()),
        "validity_disagrees": int((np.isfinite(ours) != np.isfinite(baseline)).sum()),
        "max_relative_score_difference": float(rel.max()) if rel.size else 0.0,
    }


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=count, default=1e6)
    parser.add_argument("--baseline-particles", type=count, default=40)
    parser.add_argument("--models", nargs="+", default=list(MODELS))
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--compile",
        choices=("on", "off"),
        default="on",
        help="fuse the time loop with torch.compile where the model allows",
    )
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=REPORTS / "models")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    tune_malloc()
    pairs = torchcf.load_pairs(
        "car-model-2",
        split="train",
        data_root=args.data_root,
        cleaning=torchcf.data.Cleaning(drop_duplicates=False),
    )
    n_particles, steps = int(args.particles), pairs.n_steps
    rows = []
    for name in args.models:
        theta, index = setup(name, n_particles, pairs.n_pairs)
        model = MODELS[name]
        fused = args.compile == "on" and (model.compilable or model.corrects)
        seconds, runs, compile_s, invalid = time_torchcf(
            name, theta, pairs, index, args.device, fused, args.repeats
        )
        n_base = min(args.baseline_particles, n_particles)
        base_s, base_scores = time_baseline(name, theta[:n_base], pairs, index[:n_base])
        check = check_scores(name, theta[:n_base], pairs, index[:n_base], base_scores)
        rate = n_particles * steps / seconds
        base_rate = n_base * steps / base_s
        row = {
            "model": name,
            "particles": n_particles,
            "steps": steps,
            "fused": fused,
            "seconds": seconds,
            "runs_s": runs,
            "compile_s": compile_s,
            "particle_steps_per_s": rate,
            "invalid_fraction": invalid,
            "baseline_particles": n_base,
            "baseline_seconds": base_s,
            "baseline_particle_steps_per_s": base_rate,
            "baseline_seconds_per_particle": base_s / n_base,
            "speedup": rate / base_rate,
            "speedup_per_core": rate / base_rate / args.threads,
            **check,
        }
        rows.append(row)
        print(
            f"{name:6s} torchcf {rate:.3g} particle-steps/s ({seconds:.2f} s), "
            f"baseline {base_rate:.3g} /s: {row['speedup']:.0f}x "
            f"(scores agree to {check['max_relative_score_difference']:.1e})",
            flush=True,
        )

    meta = bench_meta(
        ["tools/bench_models.py", *sys.argv[1:]], args.threads, args.device
    )
    meta |= {
        "dataset": f"car-model-2 train ({pairs.n_pairs} pairs, {steps} steps)",
        "dtype": "float32 (baseline: float64 NumPy)",
        "layout": "paired",
        "repeats": args.repeats,
    }
    write_report(
        args.out, {"meta": meta, "rows": rows}, markdown(meta, rows, args.threads)
    )
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


def markdown(meta: dict, rows: list[dict], threads: int) -> str:
    lines = [
        "# Per-model throughput and speed-up over the per-particle NumPy baseline",
        "",
        f"`{meta['command']}`",
        "",
        *(f"- {key}: {value}" for key, value in meta.items() if key != "command"),
        "",
        f"torchcf: batched, {threads} thread(s) on {meta['device']}, median of "
        f"{meta['repeats']} timed runs after a warm-up (fused: `torch.compile`, "
        "compilation excluded). Baseline: `tools/peer_numpy.py`, one particle at a "
        "time, a Python loop over the steps on NumPy arrays, one core; its scores "
        "are checked against torchcf's (float64) on the same particles.",
        "",
        "| model | torchcf particle-steps/s | time [s] | fused | baseline "
        "particle-steps/s | baseline s/particle | speed-up | per core | "
        "scores agree to | invalid |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        agree = r["max_relative_score_difference"]
        agree_text = (
            f"{agree:.0e}"
            if r["validity_disagrees"] == 0
            else (f"{agree:.0e}, {r['validity_disagrees']} validity")
        )
        lines.append(
            f"| {r['model']} | {r['particle_steps_per_s']:.3g} | {r['seconds']:.2f} | "
            f"{'yes' if r['fused'] else 'no'} | "
            f"{r['baseline_particle_steps_per_s']:.3g} | "
            f"{r['baseline_seconds_per_particle']:.3g} | {r['speedup']:,.0f}x | "
            f"{r['speedup_per_core']:,.0f}x | {agree_text} | "
            f"{r['invalid_fraction']:.3f} |"
        )
    one_m = [r for r in rows if not math.isnan(r["baseline_seconds_per_particle"])]
    if one_m:
        hours = sum(r["baseline_seconds_per_particle"] for r in one_m) * 1e6 / 3600
        ours = sum(r["seconds"] / r["particles"] for r in one_m) * 1e6
        lines += [
            "",
            f"At the paper's budget (1e6 particles per model, the {len(one_m)} "
            f"models above): the baseline needs about {hours:,.1f} core-hours, "
            f"torchcf about {ours:,.0f} s on {threads} thread(s) (simulation only).",
        ]
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(run_main(main))
