"""Benchmark: every pair calibrated, at scale (thousands of pairs, eight models).

Synthetic pairs (:func:`scale_pairs`: 40 s at dt 0.1, i.e. 400 steps; followers
driven by four pool models, IDM, HL, LLCTG and MPC, and by Gipps, a model outside
the pool, in blocks of 10 pairs with per-pair parameters) are calibrated with the
eight models by :func:`torchcf.train.train`: the whole training path, checkpoints
(every 60 s), progress, the hybrid, ``posterior.pt``, the parameter tables and
``summary.json`` (no evaluation). Each size runs in a fresh child process, which
records its wall time and its peak resident set size
(``resource.getrusage(RUSAGE_SELF).ru_maxrss`` at its end: the whole process,
the interpreter, torch, the pairs and every temporary included).

The same per-pair budget at every size (``--per-pair``, proposals per pair and
model; ``abc.n_particles = per_pair x pairs``), so the per-pair quality of a
large run is compared with the smallest run's (``--pairs``' first, 150 by
default). Pair ``i`` is the same pair whatever the size (blocks are seeded by
their position), so the comparison is made on the pairs both runs hold and over
all of them. Quality: the hybrid's per-pair N-th best score (the worst particle it
keeps on a pair), mean over pairs, and each model's own (its buffer's N-th best).

    python tools/bench_scale.py --pairs 150 1000 3000 10000 --threads 1
    python tools/bench_scale.py --pairs 150 1000 3000 --method rejection \
        --layout full --name scale_full     # every particle on every pair
    python tools/bench_scale.py --render   # scale.md again from scale.json

In the full layout ``--per-pair`` is the particles per model (each simulated on
every pair). On a shared machine take one thread: with two, another process on
one of the two cores stalls every eager operation's thread barrier (a model ran
25x slower).

Writes ``reports/bench/<name>.{json,md}`` (default ``scale``), with the exact
command, the machine and the git revision, and a linear fit of time and peak
memory against the pairs (over the runs of at least 1 000 pairs).
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.data import PairSet  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.sim.synthetic import Gipps, synthetic_pairs  # noqa: E402
from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"
MODELS = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")
#: The followers' models and their central parameters (SI); each pair of a block
#: draws its own within +-10 % of these (inside the prior box).
GENERATORS = (
    ("idm", (1.2, 2.0, 30.0, 1.3, 2.0, 4.0)),
    ("hl", (1.0, 0.3, 1.0, 1.0, -1.0, 5.0)),
    ("llctg", (1.0, 0.6, 0.8, 5.0)),
    ("mpc", (1.0, 1.0, 1.0, 5.0, -4.0, 4.0)),
    ("gipps", (1.5, 2.5, 3.0, 30.0, 0.8, 7.0)),
)
BLOCK = 10
N_STEPS = 400  # 40 s at dt 0.1
DT = 0.1


# ----------------------------------------------------------------- the pairs
def _block(b: int, seed: int) -> PairSet:
    """Block ``b`` (pairs ``10 b .. 10 b + 9``): one generating model, per-pair
    parameters, leaders and noise seeded by the block's position alone."""
    name, centre = GENERATORS[b % len(GENERATORS)]
    model = Gipps() if name == "gipps" else get_model(name)
    bounds = model.prior_bounds(torch.float64)
    g = torch.Generator().manual_seed(seed * 1_000_003 + b)
    centre_t = torch.tensor(centre, dtype=torch.float64)
    jitter = 1.0 + 0.1 * (2.0 * torch.rand(BLOCK, len(centre), generator=g) - 1.0)
    theta = torch.minimum(torch.maximum(centre_t * jitter, bounds[:, 0]), bounds[:, 1])
    for attempt in (theta, centre_t):  # the centre if a jittered follower crashes
        try:
            return synthetic_pairs(
                model,
                attempt,
                BLOCK,
                N_STEPS,
                DT,
                seed=seed * 1_000_003 + b,
                noise=0.05,
            )
        except ValueError:
            continue
    raise RuntimeError(f"block {b}: {name} crashes at its central parameters")


def scale_pairs(n_pairs: int, seed: int = 0) -> PairSet:
    """``n_pairs`` synthetic pairs (a multiple of 10 is not needed: the last block
    is cut); pair ``i`` is the same whatever ``n_pairs``."""
    blocks = [_block(b, seed) for b in range(-(-n_pairs // BLOCK))]
    series = {
        key: torch.cat([getattr(p, key) for p in blocks], dim=1)[:, :n_pairs]
        for key in ("x_lead", "v_lead", "a_lead", "x_follow", "v_follow", "a_follow")
    }
    return PairSet.from_arrays(series, dt=DT, name="synthetic-scale")


# ------------------------------------------------------------ one size (child)
def hybrid_nth(posterior, n_pairs: int) -> torch.Tensor:
    """(N,) per training pair, the worst score the hybrid keeps (its N-th best)."""
    worst = torch.full((n_pairs,), -math.inf, dtype=torch.float64)
    position = {int(p): i for i, p in enumerate(posterior.train_pair_ids.tolist())}
    for particles in posterior.hybrid.values():
        rows = torch.tensor([position[int(p)] for p in particles.pair_ids.tolist()])
        if rows.numel():
            worst.scatter_reduce_(0, rows, particles.score, "amax")
    return worst


def child(args: argparse.Namespace) -> int:
    """One calibration of ``args.n`` pairs in this fresh process; writes its
    measurements as JSON to ``args.result``."""
    from torchcf.config import validate_config
    from torchcf.posterior import Posterior
    from torchcf.train import train

    torch.set_num_threads(args.threads)
    began = time.perf_counter()
    pairs = scale_pairs(args.n)
    made = time.perf_counter() - began
    test = pairs.subset(torch.arange(min(10, args.n)))
    abc = {
        "method": args.method,
        "layout": args.layout,
        "n_particles": args.per_pair * (args.n if args.layout == "paired" else 1),
        "seed": 0,
    }
    if args.chunk_size:
        abc["chunk_size"] = args.chunk_size
    raw = {
        "data": {"path": "synthetic-scale (tools/bench_scale.py)"},
        "models": list(args.models),
        "abc": abc,
        "compile": args.compile,
        "threads": args.threads,
    }
    cfg = validate_config(raw)
    with tempfile.TemporaryDirectory(prefix="torchcf-scale-") as folder:
        out = Path(folder) / "run"
        start = time.perf_counter()
        summary = train(cfg, out, pairs=(pairs, test))
        seconds = time.perf_counter() - start
        posterior = Posterior.load(out / "posterior.pt")
        sizes = {p.name: p.stat().st_size for p in out.iterdir() if p.is_file()}
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    nth = hybrid_nth(posterior, args.n)
    per_model = summary.per_model
    simulated = sum(per_model[m].particles for m in args.models)
    result = {
        "pairs": args.n,
        "seconds": seconds,
        "seconds_pairs": made,
        "peak_rss_mib": peak_kib / 1024,
        "sims_per_pair": simulated / len(args.models) / args.n
        if args.layout == "paired"
        else simulated / len(args.models),
        "per_model_seconds": {m: per_model[m].seconds for m in args.models},
        "hybrid_nth": nth.tolist(),
        "model_nth": {
            m: [math.inf if v is None else v for v in per_model[m].thresholds]
            for m in args.models
        },
        "shares": summary.shares,
        "files_bytes": sizes,
        "smc_budget": None if summary.smc is None else summary.smc.budget.to_json(),
    }
    Path(args.result).write_text(json.dumps(result))
    return 0


# ------------------------------------------------------------ the benchmark
def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return sum(finite) / len(finite) if finite else math.inf


def compare(run: dict, small: dict) -> dict:
    """Per-pair quality of ``run`` against the small run: mean over the pairs both
    hold and over all of ``run``'s, hybrid and per model (ratio > 1: worse)."""
    common = small["pairs"]
    ratio = {
        "hybrid_common": _mean(run["hybrid_nth"][:common]) / _mean(small["hybrid_nth"]),
        "hybrid_all": _mean(run["hybrid_nth"]) / _mean(small["hybrid_nth"]),
    }
    models = {
        m: _mean(run["model_nth"][m]) / _mean(small["model_nth"][m])
        for m in run["model_nth"]
    }
    ratio["worst_model"] = max(models.items(), key=lambda kv: kv[1])
    ratio["models"] = models
    return ratio


def run_size(n: int, args: argparse.Namespace) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as handle:
        command = [
            sys.executable,
            __file__,
            "--child",
            "--n",
            str(n),
            "--result",
            handle.name,
            "--per-pair",
            str(args.per_pair),
            "--threads",
            str(args.threads),
            "--compile",
            args.compile,
            "--method",
            args.method,
            "--layout",
            args.layout,
            "--chunk-size",
            str(args.chunk_size or 0),
            "--models",
            *args.models,
        ]
        began = time.perf_counter()
        done = subprocess.run(command, check=False)
        wall = time.perf_counter() - began
        if done.returncode != 0:
            raise SystemExit(f"the {n}-pair run failed (exit {done.returncode})")
        result = json.loads(Path(handle.name).read_text())
    result["process_seconds"] = wall
    return result


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=count, nargs="+", default=[150, 1000, 10000])
    parser.add_argument(
        "--per-pair",
        type=count,
        default=500,
        help="proposals per pair and model (full layout: particles per model)",
    )
    parser.add_argument("--method", default="smc", choices=("smc", "rejection"))
    parser.add_argument("--layout", default="paired", choices=("paired", "full"))
    parser.add_argument("--models", nargs="+", default=list(MODELS))
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--compile", default="auto", choices=("auto", "on", "off"))
    parser.add_argument("--chunk-size", type=natural, default=0)
    parser.add_argument("--name", default="scale")
    parser.add_argument(
        "--render",
        action="store_true",
        help="rewrite <name>.md from <name>.json (no run)",
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--n", type=count, help=argparse.SUPPRESS)
    parser.add_argument("--result", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return child(args)
    if args.render:
        payload = json.loads((REPORTS / f"{args.name}.json").read_text())
        payload["extrapolation"] = extrapolate(payload["runs"])
        write_report(REPORTS / args.name, payload, markdown(payload))
        return 0
    runs = []
    for n in args.pairs:
        run = run_size(n, args)
        runs.append(run)
        print(
            f"{n:>6d} pairs: {run['seconds']:7.1f} s, {run['peak_rss_mib']:7.0f} MiB, "
            f"quality {_mean(run['hybrid_nth']):.4f}",
            file=sys.stderr,
        )
    small = runs[0]
    rows = []
    for run in runs:
        ratio = compare(run, small)
        rows.append(
            {
                "pairs": run["pairs"],
                "seconds": run["seconds"],
                "process_seconds": run["process_seconds"],
                "seconds_pairs": run["seconds_pairs"],
                "seconds_per_1000_pairs": 1000 * run["seconds"] / run["pairs"],
                "sims_per_pair": run["sims_per_pair"],
                "peak_rss_mib": run["peak_rss_mib"],
                "quality": _mean(run["hybrid_nth"]),
                "quality_ratio": ratio,
                "per_model_seconds": run["per_model_seconds"],
                "shares": run["shares"],
                "files_bytes": run["files_bytes"],
                "smc_budget": run["smc_budget"],
            }
        )
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "settings": {
            "per_pair": args.per_pair,
            "method": args.method,
            "layout": args.layout,
            "models": args.models,
            "compile": args.compile,
            "chunk_size": args.chunk_size or None,
            "steps": N_STEPS,
            "dt": DT,
            "generators": [g[0] for g in GENERATORS],
        },
        "runs": rows,
        "extrapolation": extrapolate(rows),
    }
    write_report(REPORTS / args.name, payload, markdown(payload))
    return 0


def extrapolate(rows: list[dict]) -> dict:
    """A least-squares line of wall time and peak RSS against the pairs (the runs
    of at least 1 000 pairs where there are two, else all), at 10 000 pairs."""
    fit = [r for r in rows if r["pairs"] >= 1000]
    fit = fit if len(fit) >= 2 else rows
    if len(fit) < 2:
        return {}
    out = {"from_pairs": [r["pairs"] for r in fit]}
    for key in ("seconds", "peak_rss_mib"):
        slope, intercept = statistics.linear_regression(
            [r["pairs"] for r in fit], [r[key] for r in fit]
        )
        out[key] = {
            "slope": slope,
            "intercept": intercept,
            "at_10000": intercept + slope * 1e4,
        }
    return out


def markdown(payload: dict) -> str:
    meta, settings = payload["meta"], payload["settings"]
    lines = [
        "# Every pair calibrated, at scale",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"{meta['cpu']} ({meta['cpu_count']} cores, shared: timings are noisy), "
        f"git {meta['git']}, compile {settings['compile']}.",
        "",
        f"Synthetic pairs, {settings['steps']} steps at dt {settings['dt']} s, "
        f"followers by {', '.join(settings['generators'])} (gipps outside the "
        f"pool); {len(settings['models'])} models, method {settings['method']}, "
        f"layout {settings['layout']}, {settings['per_pair']} proposals per pair and "
        "model. Seconds: `train` (every model, hybrid, outputs; no evaluation); RSS: "
        "the child process's peak. Quality: the hybrid's per-pair N-th best score, "
        "mean over pairs, and its ratio to the smallest run's (on the pairs both "
        "hold / on all pairs; the worst model's own ratio).",
        "",
        "| pairs | seconds | s / 1000 pairs | sims / pair / model | peak RSS (MiB) "
        "| quality | vs small: common | all | worst model |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in payload["runs"]:
        q = r["quality_ratio"]
        worst, value = q["worst_model"]
        cells = (
            f"{r['pairs']:,}",
            f"{r['seconds']:.1f}",
            f"{r['seconds_per_1000_pairs']:.1f}",
            f"{r['sims_per_pair']:.0f}",
            f"{r['peak_rss_mib']:.0f}",
            f"{r['quality']:.4f}",
            f"{q['hybrid_common']:.3f}",
            f"{q['hybrid_all']:.3f}",
            f"{worst} {value:.3f}",
        )
        lines.append("| " + " | ".join(cells) + " |")
    ext = payload["extrapolation"]
    if ext:
        s, m = ext["seconds"], ext["peak_rss_mib"]
        ran = 10_000 in ext["from_pairs"]
        at = "the fit" if ran else "**an extrapolation** (10 000 pairs not run)"
        lines += [
            "",
            f"Linear fit over {', '.join(f'{p:,}' for p in ext['from_pairs'])} pairs: "
            f"{s['slope'] * 1000:.1f} s per 1 000 pairs + {s['intercept']:.0f} s "
            f"(compilation, the fixed part of the battery and the outputs), peak RSS "
            f"{m['slope'] * 1000:.0f} MiB per 1 000 pairs + {m['intercept']:.0f} MiB; "
            f"at 10 000 pairs {at}: {s['at_10000'] / 60:.1f} min, "
            f"{m['at_10000']:.0f} MiB.",
        ]
    lines += [
        "",
        "Where the time and the memory go: pair generation (not in `seconds`), the "
        "models' streams (the sum of `per_model` seconds), everything after them "
        "(the hybrid, the plausibility battery on its particles, the posterior, the "
        "tables and figures, `summary.json`), and the run's files:",
        "",
        "| pairs | generation s | models s | after s | checkpoint.pt MiB "
        "| posterior.pt MiB |",
        "|---|---|---|---|---|---|",
    ]
    for r in payload["runs"]:
        models_s = sum(r["per_model_seconds"].values())
        files = r["files_bytes"]
        lines.append(
            f"| {r['pairs']:,} | {r['seconds_pairs']:.1f} | {models_s:.1f} | "
            f"{r['seconds'] - models_s:.1f} | {files['checkpoint.pt'] / 2**20:.1f} | "
            f"{files['posterior.pt'] / 2**20:.1f} |"
        )
    lines += ["", "Seconds per model (slowest first):", ""]
    for r in payload["runs"]:
        slow = sorted(r["per_model_seconds"].items(), key=lambda kv: -kv[1])
        lines.append(
            f"- {r['pairs']:,} pairs: " + ", ".join(f"{m} {v:.1f}" for m, v in slow)
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(run_main(main))
