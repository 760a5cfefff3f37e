"""Benchmark: the diagnosis loop's wall time at its defaults, and how it grows
with the number of pairs.

The targets: on 2 quiet cores ``python -m torchcf diagnose RUN`` at its
defaults, on a run of 50 measured training pairs where an effect is chosen and
re-calibrated, in <= 5 minutes, on 500 pairs in <= 20 minutes, its cost
linear in pairs (the whole ZalaZONE campaign: 451 pairs, 314 of them
training). The runs (eight models trained with 2e5 particles each by
``python -m torchcf train``, not timed):

- **measured, log 0.8 s ahead**: 50 training and 20 test pairs of the ZalaZONE
  OpenACC campaign (ACC platoons, ``$TORCHCF_RAW/openacc-zalazone-dynamic``,
  extracted with the defaults of ``python -m torchcf data extract``, drawn at
  random with a fixed seed from its training and test pairs) with the leader's
  log planted 0.8 s ahead of the follower's (``tools/loop_cases.py``'s
  ``planted``): the followers seem to answer 0.8 s late, and the loop chooses an
  effect and re-calibrates;
- **measured, as measured**: the same pairs as recorded;
- **synthetic delay**: 50 training and 20 test pairs from IDM with a 0.8 s
  perception delay the pool does not have (``torchcf.sim.synthetic``);
- **campaign, N pairs** (``--campaign``): the same plant on 150 pairs drawn from
  the campaign (105 / 45) and on the whole campaign (its own split), the cost's
  growth in pairs.

Each loop is timed as a whole process, ``--repeats`` times (its ledger and
re-calibration removed between repeats: every repeat starts from nothing).
With ``--work DIR`` the data and trained runs are kept in ``DIR`` and a case's
run is trained only where ``DIR`` has none finished (``summary.json``); with
``--train-only`` nothing is timed. Together they let a long training (the
whole campaign's) run beside other work, and the loop be timed later on quiet
cores.

    TORCHCF_RAW=../shared/data/raw python tools/bench_loop.py [--campaign]

Writes ``reports/bench/loop.{json,md}``.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402
from loop_cases import planted  # noqa: E402

from torchcf.data import load_pairs  # noqa: E402
from torchcf.data.writer import write_six_csv  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.sim.synthetic import synthetic_pairs  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
MODELS = ["ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc"]
IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]


def subset(
    source: Path, out: Path, n_train: int | None, n_test: int | None, shift: float
) -> None:
    """``n_train`` / ``n_test`` pairs drawn from an extraction's splits (None:
    all of them), the leader's log advanced by ``shift`` seconds."""
    generator = torch.Generator().manual_seed(0)
    for split, folder, n in (
        ("train", "Trajectory", n_train),
        ("test", "Testing", n_test),
    ):
        pairs = load_pairs(source, split=split)
        if n is not None:
            keep = torch.randperm(pairs.n_pairs, generator=generator)[:n]
            pairs = pairs.subset(keep.sort().values)
        write_six_csv(planted(pairs, "shift", shift), out / folder)
    shutil.copy(source / "meta.json", out / "meta.json")


def extracted(raw: Path, work: Path) -> Path:
    """The ZalaZONE campaign extracted at the defaults (once)."""
    source = work / "zalazone"
    if not source.exists():
        subprocess.run(
            [sys.executable, "-m", "torchcf", "data", "extract",
             str(raw / "openacc-zalazone-dynamic"), "--format", "openacc",
             "--out", str(source)],
            check=True, capture_output=True,
        )  # fmt: skip
    return source


def measured_data(
    raw: Path, work: Path, name: str, n_train: int | None, n_test: int | None,
    shift: float,
) -> Path:  # fmt: skip
    out = work / name
    subset(extracted(raw, work), out, n_train, n_test, shift)
    return out


def synthetic_data(work: Path) -> Path:
    out = work / "synthetic"
    train = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 50, 400, seed=1, noise=0.05
    )
    test = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 20, 400, seed=2, noise=0.05
    )
    write_six_csv(train, out / "Trajectory")
    write_six_csv(test, out / "Testing")
    (out / "meta.json").write_text(json.dumps({"dt": 0.1, "units": "m"}))
    return out


def config(data: Path, n_particles: int, threads: int, path: Path) -> Path:
    path.write_text(
        json.dumps(
            {
                "data": {"path": str(data), "split": "dataset"},
                "models": MODELS,
                "abc": {"n_particles": n_particles, "seed": 0},
                "dtype": "float32",
                "threads": threads,
            }
        )
    )
    return path


def train(data: Path, run: Path, n_particles: int, threads: int) -> None:
    """Train the case's run (eight models, ``n_particles`` each) into ``run``."""
    if run.exists():
        shutil.rmtree(run)  # an unfinished training: start it again
    cfg = config(data, n_particles, threads, run.parent / f"{run.name}.json")
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    subprocess.run(
        [sys.executable, "-m", "torchcf", "train", str(cfg), "--out", str(run)],
        check=True, capture_output=True, env=env,
    )  # fmt: skip


def clear_loop(run: Path) -> None:
    """Remove a run's loop folder and reports: the next loop starts from nothing."""
    for stale in ("loop", "loop.json", "loop.md"):
        target = run / stale
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()


def time_loop(run: Path, threads: int, repeats: int) -> tuple[list[float], dict]:
    times = []
    for _ in range(repeats):
        clear_loop(run)
        began = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "torchcf", "diagnose", str(run),
             "--threads", str(threads)],
            check=True, capture_output=True,
        )  # fmt: skip
        times.append(time.perf_counter() - began)
    return times, json.loads((run / "loop.json").read_text())


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--repeats", type=count, default=1)
    parser.add_argument("--particles", type=count, default=2e5)
    parser.add_argument("--out", default=str(REPORTS / "bench" / "loop"))
    parser.add_argument(
        "--campaign", action="store_true",
        help="also the 150-pair draw and the whole campaign (the growth in pairs)",
    )  # fmt: skip
    parser.add_argument(
        "--only", nargs="+", default=None, help="only the cases whose name holds one"
    )
    parser.add_argument(
        "--keep", default=None, help="a folder to copy each case's loop.md/json to"
    )
    parser.add_argument(
        "--work", default=None,
        help="a folder to keep the data and trained runs in (a finished run is reused)",
    )  # fmt: skip
    parser.add_argument(
        "--train-only", action="store_true", help="train the runs, time nothing"
    )
    args = parser.parse_args(argv)
    raw = Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        work = Path(args.work or folder)
        work.mkdir(parents=True, exist_ok=True)
        cases = {}
        if (raw / "openacc-zalazone-dynamic").is_dir():
            cases["measured, log 0.8 s ahead"] = lambda: measured_data(
                raw, work, "shifted", 50, 20, SHIFT
            )
            cases["measured, as measured"] = lambda: measured_data(
                raw, work, "measured", 50, 20, 0.0
            )
        cases["synthetic delay"] = lambda: synthetic_data(work)
        if args.campaign and (raw / "openacc-zalazone-dynamic").is_dir():
            cases["campaign, 150 pairs, log 0.8 s ahead"] = lambda: measured_data(
                raw, work, "campaign-150", 105, 45, SHIFT
            )
            cases["campaign, all pairs, log 0.8 s ahead"] = lambda: measured_data(
                raw, work, "campaign", None, None, SHIFT
            )
        for name, make in cases.items():
            if args.only and not any(key in name for key in args.only):
                continue
            key = name.replace(" ", "_").replace(",", "")
            run = work / f"run-{key}"
            if not (run / "summary.json").exists():
                train(make(), run, int(args.particles), args.threads)
            if args.train_only:
                continue
            data = Path(json.loads((run / "config.json").read_text())["data"]["path"])
            n_train = load_pairs(data, split="train").n_pairs
            times, result = time_loop(run, args.threads, args.repeats)
            if args.keep:
                kept = Path(args.keep) / key
                kept.mkdir(parents=True, exist_ok=True)
                for written in ("loop.json", "loop.md"):
                    shutil.copy(run / written, kept / written)
            rows.append(
                {
                    "case": name,
                    "n_train": n_train,
                    "seconds": times,
                    "median": statistics.median(times),
                    "per_pair": statistics.median(times) / n_train,
                    "chosen": result["chosen"],
                    "recalibrated": bool(result["chosen"]),
                    "steps": len(result["steps"]),
                    "target": target(n_train),
                }
            )
            print(
                f"{name}: {statistics.median(times):.0f} s, chosen {result['chosen']}",
                flush=True,
            )
            payload = {"meta": bench_meta(sys.argv, args.threads), "cases": rows}
            write_report(Path(args.out), payload, markdown(payload))
    return 0


#: The leader's log planted ahead of the follower's in the measured cases [s].
SHIFT = 0.8


def target(n_train: int) -> int:
    """The wall-time target [s]: 5 minutes at 50 training pairs, 20 at 500
    pairs (350 training pairs at the campaign's 70 / 30 split), linear between
    and beyond."""
    return int(300 + (1200 - 300) * max(0, n_train - 50) / (350 - 50))


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The diagnosis loop's wall time",
        "",
        provenance(meta) + ". A run trained with 2e5 particles "
        "per model (eight models), then `python -m torchcf diagnose RUN` at its "
        "defaults, timed as a whole process (start-up included) from an empty "
        "loop folder.",
        "",
        "| case | training pairs | chosen | steps | loop [s] (median) | per pair [s] "
        "| runs [s] | target [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in payload["cases"]:
        lines.append(
            f"| {row['case']} | {row['n_train']} | "
            f"{', '.join(row['chosen']) or 'none'} | "
            f"{row['steps']} | {row['median']:.0f} | {row['per_pair']:.2f} | "
            f"{', '.join(f'{t:.0f}' for t in row['seconds'])} | <= {row['target']} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(run_main(main))
