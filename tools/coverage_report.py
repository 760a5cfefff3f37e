"""Predictive coverage and bootstrap intervals of evaluated runs, side by side.

Reads each run's ``metrics.json`` (written by ``torchcf evaluate RUN``,
:mod:`torchcf.evaluation.uncertainty` lists its keys) and writes one table per
run: for every learned set, the fraction of the test split's observed spacings and
speeds inside its central 50 % and 90 % predictive bands, with their bootstrap
interval over test pairs, and the headline metrics with theirs; then the hybrid
minus each model on the same resamples.

    python tools/coverage_report.py runs/paper/carII runs/paper/carI runs/paper/ngsim

Writes ``reports/uncertainty/coverage.{md,json}`` (``--out`` to change).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from torchcf.evaluation.report import (
    coverage_table,
    differences_table,
    intervals_table,
)
from torchcf.runs.directory import RunDir
from torchcf.runs.metrics import Evaluation
from torchcf.system.console import OneLineParser, run_main
from torchcf.system.files import json_safe

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "uncertainty"
SETS = ("hybrid", "ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")


def set_rows(evaluation: Evaluation) -> dict[str, dict]:
    """The evaluation's sets in :data:`SETS` order, each as its ``metrics.json``
    entry (the rows of :mod:`torchcf.evaluation.report`'s tables)."""
    return {s: evaluation.sets[s].to_json() for s in SETS if s in evaluation.sets}


def run_table(name: str, evaluation: Evaluation) -> list[str]:
    """Markdown lines of one run: the tables its own ``report/table.md`` has
    (:mod:`torchcf.evaluation.report`), coverage first."""
    rows = set_rows(evaluation)
    order = list(rows)
    return [
        f"## {name} ({evaluation.dataset}, {evaluation.n_test} test pairs)",
        "",
        coverage_table(rows, order, evaluation.coverage_levels),
        intervals_table(rows, order, evaluation.bootstrap),
        differences_table(evaluation.hybrid_minus),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
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
            "`torchcf evaluate RUN`.",
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
        evaluation = RunDir(run).read_metrics()
        payload[str(run)] = {
            s: {k: v for k, v in row.items() if k.startswith("coverage")}
            for s, row in set_rows(evaluation).items()
        }
        payload[str(run)]["hybrid_minus"] = {
            model: {key: d.to_json() for key, d in row.items()}
            for model, row in evaluation.hybrid_minus.items()
        }
        lines += run_table(run.name, evaluation)
    args.out.mkdir(parents=True, exist_ok=True)
    text = json.dumps(json_safe(payload), indent=1)
    (args.out / "coverage.json").write_text(text + "\n")
    (args.out / "coverage.md").write_text("\n".join(lines))
    print(f"wrote {args.out / 'coverage.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
