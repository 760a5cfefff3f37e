"""``torchcf evaluate RUN_DIR``: the
test-split evaluation of a trained run.

    torchcf evaluate runs/carII
    torchcf evaluate runs/carII --report elsewhere/ --pair 3

Runs :func:`torchcf.evaluation.evaluate.evaluate_run` (which writes
``RUN_DIR/metrics.json`` and the report) and prints each learned set's average
position error, minimum distance, 0.15-WS and WS.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 a run that is not trained, a
corrupted file, data that cannot be loaded or an output that cannot be written
(one line on stderr, no traceback); 130 interrupted.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from ..evaluation.evaluate import evaluate_run
from ..runs.directory import RunDir
from ..runs.metrics import Evaluation
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    folder,
    natural,
    run_main,
)


def build_parser() -> argparse.ArgumentParser:
    """``torchcf evaluate``'s parser."""
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf evaluate",
        description="Evaluate a trained run on its test pairs (SPEC section 6).",
    )
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--report", type=folder, default=None, help="report folder")
    parser.add_argument(
        "--pair", type=natural, default=None, help="test pair of Fig. 4"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf evaluate``.

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    args = build_parser().parse_args(argv)

    def body() -> int:
        result = evaluate_run(
            args.run_dir, report_dir=args.report, figure_pair=args.pair
        )
        print_metrics(result)
        print(f"wrote {RunDir(args.run_dir).metrics_json}")
        return 0

    return run_main(body)


def print_metrics(result: Evaluation) -> None:
    """One row per learned set: e_p, minimum distance, 0.15-WS, WS."""
    print(f"{'':8} {'e_p':>8} {'min':>8} {'0.15-WS':>8} {'WS':>8}")
    for entry, s in result.sets.items():
        m = s.metrics
        print(f"{entry:8} {m.e_p:8.3f} {m.min:8.3f} {m.beta_ws:8.3f} {m.ws:8.3f}")
