"""What the plausibility filter costs in fit, and whether the hybrid still wins.

For each of the paper's data sets (``configs/<set>.json``: the 8 models, the
paper's split; needs ``TORCHCF_DATA``) the study is trained and evaluated
twice at ``--n-particles`` per model: as configured, and with
``plausibility.filter`` on (particles that collide in the battery rejected
before they enter the buffers; :mod:`torchcf.abc.screen`). It reports the test
split's WS, 0.15-WS (SPEC's, and over the particles valid on some test pair
where SPEC's is infinite) and minimum distance, the hybrid's shares, the
particles rejected per model, the training time, the share of the hybrid's
particles that collide in the battery, and whether the hybrid's WS beats every
single model's (the paper's central claim).

    python tools/plausibility_cost.py                    # 200 000 per model
    python tools/plausibility_cost.py --sets carII --n-particles 50000

Writes ``reports/plausibility/plausibility.{md,json}``.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.config import (
    load_config,  # noqa: E402
    load_split,  # noqa: E402
)
from torchcf.posterior import Posterior  # noqa: E402
from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.study.pipeline import train_and_evaluate  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402
from torchcf.traffic import HybridSampler  # noqa: E402
from torchcf.traffic.battery import plausibility_by_model  # noqa: E402
from torchcf.traffic.configured import plausibility_battery  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SETS = {"carI": "CAR MODEL I", "carII": "CAR MODEL II", "ngsim": "NGSIM I-80"}


def run_set(
    name: str, n_particles: int, filtered: bool, threads: int, keep: Path | None
) -> dict:
    """Train and evaluate one data set; the numbers the report needs. With
    ``keep`` the run stays in ``keep/<set>-<filter on|off>``."""
    overrides = [f"abc.n_particles={n_particles}", f"threads={threads}"]
    if filtered:
        overrides.append("plausibility.filter=true")
    path = ROOT / "configs" / f"{name}.json"
    cfg = load_config(path, overrides)
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        if keep is not None:
            out = keep / f"{name}-{'on' if filtered else 'off'}"
        began = time.perf_counter()
        summary = train_and_evaluate(cfg, out).summary
        seconds = time.perf_counter() - began
        evaluation = RunDir(out).read_metrics()
        posterior = Posterior.load(out / "posterior.pt")
    sampler = HybridSampler.from_posterior(posterior, dt=0.1)
    battery = plausibility_battery(cfg.plausibility, load_split(cfg.data)[0])
    particles = {model: sampler.particles(model.name) for model in sampler.models}
    collided = {
        name: row.collided
        for name, row in plausibility_by_model(particles, battery).items()
    }
    return {
        "seconds": seconds,
        "shares": summary.shares,
        "implausible": {m: row.implausible for m, row in summary.per_model.items()},
        "metrics": {
            key: {
                k: getattr(evaluation.sets[key].metrics, k)
                for k in (
                    "ws",
                    "beta_ws",
                    "min",
                    "ws_valid",
                    "beta_ws_valid",
                    "particles_never_valid",
                )
            }
            for key in [*summary.models, "hybrid"]
            if key in evaluation.sets
        },  # fmt: skip
        "hybrid_collided": collided,
        "battery_speed": battery.speed,
    }


def hybrid_beats_every_model(metrics: dict, key: str) -> tuple[bool, str]:
    """Whether the hybrid's ``key`` is below every single model's, and the
    best single model."""
    hybrid = metrics["hybrid"][key]
    singles = {
        m: v[key] for m, v in metrics.items() if m != "hybrid" and v[key] is not None
    }
    best = min(singles, key=singles.get)
    return hybrid is not None and hybrid < singles[best], best


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# What plausibility costs in fit",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"git {meta['git']}. Each data set's config (`configs/<set>.json`: 8 "
        f"models, the paper's split) at {payload['n_particles']:,} particles per "
        "model, trained and evaluated twice: as configured, and with "
        "`plausibility.filter` on (particles that collide in the battery, "
        "`torchcf.traffic.check_plausibility`, at the training pairs' "
        "95th-percentile leader speed, rejected before they enter the buffers). "
        "Test split. WS* and 0.15-WS*: over the particles valid on some test "
        "pair, where SPEC's WS is infinite.",
        "",
        "| data set | filter | WS | WS* | 0.15-WS | min distance | hybrid particles "
        "colliding in the battery | particles rejected | training + evaluation [s] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, runs in payload["sets"].items():
        for label, run in (("off", runs["off"]), ("on", runs["on"])):
            h = run["metrics"]["hybrid"]
            shares = run["shares"]
            collided = sum(
                shares.get(m, 0.0) * c for m, c in run["hybrid_collided"].items()
            )
            lines.append(
                f"| {SETS[name]} | {label} | {_f(h['ws'])} | {_f(h['ws_valid'])} | "
                f"{_f(h['beta_ws'])} | {_f(h['min'])} | {collided:.1%} | "
                f"{sum(run['implausible'].values()):,} | {run['seconds']:.0f} |"
            )
    lines += [
        "",
        "Shares of the hybrid (filter off -> on):",
        "",
        "| data set | " + " | ".join(payload["models"]) + " |",
        "|---|" + "---|" * len(payload["models"]),
    ]
    for name, runs in payload["sets"].items():
        off, on = runs["off"]["shares"], runs["on"]["shares"]
        cells = [
            f"{off.get(m, 0):.1%} -> {on.get(m, 0):.1%}" for m in payload["models"]
        ]
        lines.append(f"| {SETS[name]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "The paper's central claim: does the hybrid's WS beat every single "
        "model's? (WS* where SPEC's WS is infinite.)",
        "",
        "| data set | filter | hybrid WS | best single model (WS) | hybrid best? |",
        "|---|---|---|---|---|",
    ]
    for name, runs in payload["sets"].items():
        for label in ("off", "on"):
            metrics = runs[label]["metrics"]
            never = metrics["hybrid"]["particles_never_valid"]
            key = "ws" if never == 0 else "ws_valid"
            wins, best = hybrid_beats_every_model(metrics, key)
            lines.append(
                f"| {SETS[name]} | {label} | {_f(metrics['hybrid'][key])} | "
                f"{best} ({_f(metrics[best][key])}) | {'yes' if wins else '**no**'} |"
            )
    return "\n".join(lines) + "\n"


def _f(value) -> str:
    return "-" if value is None else f"{float(value):.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS)
    parser.add_argument("--n-particles", type=count, default=200_000)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--out", type=Path, default=ROOT / "reports/plausibility")
    parser.add_argument(
        "--keep", type=Path, default=None, help="keep the runs in this folder"
    )
    args = parser.parse_args(argv)
    if args.n_particles < 1000:
        print("error: --n-particles must be >= 1000", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    sets = {}
    for name in args.sets:
        sets[name] = {
            label: run_set(
                name, args.n_particles, label == "on", args.threads, args.keep
            )
            for label in ("off", "on")
        }
        print(
            f"{SETS[name]}: WS {_f(sets[name]['off']['metrics']['hybrid']['ws'])} -> "
            f"{_f(sets[name]['on']['metrics']['hybrid']['ws'])}",
            file=sys.stderr,
            flush=True,
        )
    models = list(next(iter(sets.values()))["off"]["shares"])
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "n_particles": args.n_particles,
        "models": models,
        "sets": sets,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_report(args.out / "plausibility", payload, markdown(payload))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
