"""Predictive coverage and bootstrap intervals of evaluated runs, side by side.

Reads each run's ``metrics.json`` (written by ``python -m torchcf.evaluate RUN``,
:mod:`torchcf.evaluation.uncertainty` lists its keys) and writes one table per
run: for every learned set, the fraction of the test split's observed spacings and
speeds inside its central 50 % and 90 % predictive bands, with their bootstrap
interval over test pairs, and the headline metrics with theirs; then the hybrid
minus each model on the same resamples.

    python tools/coverage_report.py runs/paper/carII runs/paper/carI runs/paper/ngsim

Writes ``reports/uncertainty/coverage.{md,json}`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "uncertainty"
SETS = ("hybrid", "ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")
COVERAGE = (
    "coverage_spacing_50",
    "coverage_spacing_90",
    "coverage_speed_50",
    "coverage_speed_90",
)
METRICS = ("min", "beta_ws", "ws")
LABELS = {"min": "minimum distance", "beta_ws": "0.15-WS", "ws": "WS"}


def _interval(entry: dict, key: str, digits: int = 2) -> str:
    # metrics.json writes infinities as the string "inf"
    value, low, high = (
        None if v is None else float(v)
        for v in (entry[key], entry.get(f"{key}_low"), entry.get(f"{key}_high"))
    )
    if low is None or high is None:
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def run_table(name: str, metrics: dict) -> list[str]:
    """Markdown lines of one run: coverage, headline metrics, differences."""
    boot = metrics.get("bootstrap", {})
    lines = [
        f"## {name} ({metrics.get('dataset', '?')}, {metrics.get('n_test', '?')} "
        "test pairs)",
        "",
        f"Intervals: {boot.get('level', 0.95):.0%} percentile bootstrap over test "
        f"pairs ({boot.get('resamples', '?')} resamples; WS and 0.15-WS "
        f"{boot.get('resamples_transport', '?')}).",
        "",
        "| set | spacing 50 % | spacing 90 % | speed 50 % | speed 90 % |",
        "|---|---|---|---|---|",
    ]
    for s in SETS:
        if s in metrics and COVERAGE[0] in metrics[s]:
            cells = [_interval(metrics[s], key) for key in COVERAGE]
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| set | " + " | ".join(LABELS[k] for k in METRICS) + " |",
        "|---|---|---|---|",
    ]
    for s in SETS:
        if s in metrics and "min" in metrics[s]:
            cells = [_interval(metrics[s], key, 3) for key in METRICS]
            lines.append(f"| {s} | " + " | ".join(cells) + " |")
    minus = metrics.get("hybrid_minus", {})
    if minus:
        lines += [
            "",
            "Hybrid minus each model on the same resamples (negative: the hybrid "
            "is closer; **bold**: the interval excludes 0):",
            "",
            "| model | " + " | ".join(LABELS[k] for k in METRICS) + " |",
            "|---|---|---|---|",
        ]
        for model, row in minus.items():
            cells = []
            for key in METRICS:
                d = row[key]
                value, low, high = (float(d[k]) for k in ("value", "low", "high"))
                text = f"{value:+.3f} [{low:+.3f}, {high:+.3f}]"
                cells.append(f"**{text}**" if d["excludes_zero"] else text)
            lines.append(f"| {model} | " + " | ".join(cells) + " |")
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=REPORTS)
    args = parser.parse_args(argv)
    revision = subprocess.run(
        ["git", "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
        check=False,
    ).stdout.strip()
    payload, lines = (
        {},
        [
            "# Predictive coverage and intervals of the paper's data sets",
            "",
            f"`python tools/coverage_report.py {' '.join(map(str, args.runs))}` "
            f"(git {revision}); each run evaluated by "
            "`python -m torchcf.evaluate RUN`.",
            "",
            "How to read: a set's central q band at each step runs between the "
            "(1 - q)/2 and (1 + q)/2 quantiles of its particles' simulated spacing "
            "(or speed) on the test pair's leader; a calibrated set holds a fraction q "
            "of the observed points inside (0.50 and 0.90). Below q the set is "
            "overconfident (its particles agree more than the data do), above it the "
            "bands are wider than needed. `report/calibration.png` of each run draws "
            "the whole curve (q = 0.1 ... 0.9).",
            "",
            "The WS intervals lie mostly above their point value: a resample "
            "repeats some test pairs and drops others, and the particles' equal "
            "marginals must then travel to fewer distinct pairs, so the WS of a "
            "resample is biased upward (the minimum distance, a mean over pairs, "
            "is not). Read the WS intervals as spread, and compare sets by the "
            "differences on the same resamples, where the bias largely cancels.",
            "",
        ],
    )
    for run in args.runs:
        metrics = json.loads((run / "metrics.json").read_text())
        payload[str(run)] = {
            s: {k: metrics[s].get(k) for k in metrics[s] if k.startswith("coverage")}
            for s in SETS
            if s in metrics
        }
        payload[str(run)]["hybrid_minus"] = metrics.get("hybrid_minus", {})
        lines += run_table(run.name, metrics)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "coverage.json").write_text(json.dumps(payload, indent=1) + "\n")
    (args.out / "coverage.md").write_text("\n".join(lines))
    print(f"wrote {args.out / 'coverage.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
