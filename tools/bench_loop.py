"""Benchmark: the diagnosis loop's wall time at its defaults on a 50-pair run.

The issue's target: ``python -m torchcf.diagnose RUN`` at its defaults, on a run
of 50 training pairs trained with 2e5 particles per model (the eight models), in
<= 3 minutes on 2 cores when nothing is chosen and <= 6 minutes when an effect
is re-calibrated. Two runs:

- **measured**: 50 training and 20 test pairs of the ZalaZONE OpenACC campaign
  (ACC platoons, ``$TORCHCF_RAW/openacc-zalazone-dynamic``, extracted with the
  defaults of ``python -m torchcf.data extract``, drawn at random with a fixed
  seed from its training and test pairs);
- **synthetic delay**: 50 training and 20 test pairs from IDM with a 0.8 s
  perception delay the pool does not have (``torchcf.synthetic``), where the
  loop chooses ``delay`` and re-calibrates.

Each run is trained once (``python -m torchcf.train``, not timed), then the loop
is timed as a whole process, ``--repeats`` times (its ledger and
re-calibration removed between repeats: every repeat starts from nothing).

    TORCHCF_RAW=../shared/data/raw python tools/bench_loop.py

Writes ``reports/bench/loop.{json,md}``.
"""

from __future__ import annotations

import argparse
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
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.data import load_pairs  # noqa: E402
from torchcf.data.writer import write_six_csv  # noqa: E402
from torchcf.synthetic import synthetic_pairs  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
MODELS = ["ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc"]
IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]


def subset(source: Path, out: Path, n_train: int, n_test: int, seed: int) -> None:
    """``n_train`` / ``n_test`` pairs drawn from an extraction's splits."""
    generator = torch.Generator().manual_seed(seed)
    for split, folder, n in (
        ("train", "Trajectory", n_train),
        ("test", "Testing", n_test),
    ):
        pairs = load_pairs(source, split=split)
        keep = torch.randperm(pairs.n_pairs, generator=generator)[:n].sort().values
        write_six_csv(pairs.subset(keep), out / folder)
    shutil.copy(source / "meta.json", out / "meta.json")


def measured_data(raw: Path, work: Path) -> Path:
    source = work / "zalazone"
    subprocess.run(
        [sys.executable, "-m", "torchcf.data", "extract",
         str(raw / "openacc-zalazone-dynamic"), "--format", "openacc",
         "--out", str(source)],
        check=True, capture_output=True,
    )  # fmt: skip
    out = work / "measured"
    subset(source, out, 50, 20, seed=0)
    return out


def synthetic_data(work: Path) -> Path:
    out = work / "synthetic"
    train = synthetic_pairs("idm+delay", IDM + [0.8], 50, 400, seed=1, noise=0.05)
    test = synthetic_pairs("idm+delay", IDM + [0.8], 20, 400, seed=2, noise=0.05)
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


def time_loop(run: Path, threads: int, repeats: int) -> tuple[list[float], dict]:
    times = []
    for _ in range(repeats):
        for stale in ("loop", "loop.json", "loop.md"):
            target = run / stale
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
        began = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "torchcf.diagnose", str(run),
             "--threads", str(threads)],
            check=True, capture_output=True,
        )  # fmt: skip
        times.append(time.perf_counter() - began)
    return times, json.loads((run / "loop.json").read_text())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--particles", type=float, default=2e5)
    parser.add_argument("--out", default=str(REPORTS / "bench" / "loop"))
    args = parser.parse_args(argv)
    raw = Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        cases = {"synthetic delay": synthetic_data(work)}
        if (raw / "openacc-zalazone-dynamic").is_dir():
            cases = {"measured (ZalaZONE)": measured_data(raw, work), **cases}
        for name, data in cases.items():
            run = work / f"run-{len(rows)}"
            cfg = config(
                data, int(args.particles), args.threads, work / f"{len(rows)}.json"
            )
            env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
            subprocess.run(
                [sys.executable, "-m", "torchcf.train", str(cfg), "--out", str(run)],
                check=True, capture_output=True, env=env,
            )  # fmt: skip
            times, result = time_loop(run, args.threads, args.repeats)
            rows.append(
                {
                    "case": name,
                    "n_train": 50,
                    "seconds": times,
                    "median": statistics.median(times),
                    "chosen": result["chosen"],
                    "recalibrated": bool(result["chosen"]),
                    "steps": len(result["steps"]),
                    "target": 360 if result["chosen"] else 180,
                }
            )
            print(
                f"{name}: {statistics.median(times):.0f} s, chosen {result['chosen']}"
            )
    payload = {"meta": bench_meta(sys.argv, args.threads), "cases": rows}
    write_report(Path(args.out), payload, markdown(payload))
    return 0


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The diagnosis loop's wall time",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"{meta['cpu']}, git {meta['git']}. A run of 50 training and 20 test pairs "
        "trained with 2e5 particles per model (eight models), then "
        "`python -m torchcf.diagnose RUN` at its defaults, timed as a whole "
        "process (start-up included) from an empty loop folder.",
        "",
        "| case | chosen | steps | loop [s] (median) | runs [s] | target [s] |",
        "|---|---|---|---|---|---|",
    ]
    for row in payload["cases"]:
        lines.append(
            f"| {row['case']} | {', '.join(row['chosen']) or 'none'} | "
            f"{row['steps']} | {row['median']:.0f} | "
            f"{', '.join(f'{t:.0f}' for t in row['seconds'])} | <= {row['target']} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
