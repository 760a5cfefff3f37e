"""``torchcf predict RUN [DATA]``: predict pairs from a trained run.

    torchcf predict runs/carII                       # the run's own test pairs
    torchcf predict runs/ngsim couples/ --split test --out predictions/
    torchcf predict runs/carII data/ --history 20 --draws 500

Runs :func:`torchcf.predict.predict` (the population model, the hybrid's
median and bands, and the driver's own posterior after ``--history`` seconds)
and writes ``OUT/pairs.csv``, ``trajectories.csv``, ``predict.md`` and, last,
``predict.json`` (:mod:`torchcf.predict.files`).

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 a run that is not
trained, data that cannot be loaded or do not match the run (time step, leader
length), a bad option, an output that cannot be written (one line on stderr,
no traceback); 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from ..predict import PredictionSummary, PredictSettings, TrainedRun, predict
from ..predict.conditioning import CONDITIONINGS
from ..predict.files import REPORT, RESULT, write_prediction
from ..predict.population import OBJECTIVES
from ..predict.predict import MAX_DRAWS
from ..predict.trained import PredictError, pairs_to_predict
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    count,
    folder,
    natural,
    positive,
    run_main,
)


def build_parser() -> argparse.ArgumentParser:
    """``torchcf predict``'s parser."""
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf predict",
        description=(
            "Predict pairs (any lengths) from a trained run: the population "
            "model, the hybrid's median and bands, and each driver's own "
            "posterior after a history."
        ),
    )
    parser.add_argument("run_dir", type=Path, help="a trained run directory")
    parser.add_argument(
        "data",
        nargs="?",
        default=None,
        help="a named data set or a six-CSV folder (default: the run's test pairs)",
    )
    parser.add_argument(
        "--split",
        choices=("train", "test", "all"),
        default="test",
        help="which pairs of DATA (an extraction's Trajectory/ or Testing/)",
    )
    parser.add_argument(
        "--out", type=folder, default=None, help="output folder (default RUN/predict)"
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an earlier prediction"
    )
    parser.add_argument(
        "--draws",
        type=natural,
        default=200,
        help=f"posterior draws per pair (<= {MAX_DRAWS})",
    )
    parser.add_argument(
        "--history",
        type=positive,
        default=10.0,
        help="seconds of each pair that condition its driver's own posterior",
    )
    parser.add_argument(
        "--no-history", action="store_true", help="no conditioned prediction"
    )
    parser.add_argument(
        "--keep", type=count, default=100, help="particles of a driver's posterior"
    )
    parser.add_argument(
        "--refine",
        type=natural,
        default=0,
        help="rounds of a per-pair search after the rejection (0: none)",
    )
    parser.add_argument(
        "--conditioning",
        choices=CONDITIONINGS,
        default="auto",
        help="how a history conditions: the design best on the training pairs "
        "as if new, the hybrid's particles (rejection) or the population "
        "model shrunk toward the history",
    )
    parser.add_argument(
        "--objective",
        choices=OBJECTIVES,
        default="spacing",
        help="the population model's pooled objective",
    )
    parser.add_argument(
        "--seed", type=natural, default=0, help="seeds draws and searches"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf predict``.

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    args = build_parser().parse_args(argv)

    def body() -> int:
        settings = PredictSettings(
            draws=args.draws,
            history=None if args.no_history else args.history,
            keep=args.keep,
            refine=args.refine,
            conditioning=args.conditioning,
            objective=args.objective,
            seed=args.seed,
        )
        out = Path(args.out) if args.out else args.run_dir / "predict"
        if (out / RESULT).exists() and not args.overwrite:
            raise PredictError(f"{out} holds a prediction: pass --overwrite or --out")
        run = TrainedRun.load(args.run_dir)
        split = None if args.split == "all" else args.split
        pairs = pairs_to_predict(run, args.data, split if args.data else None)
        print(
            f"predicting {pairs.n_pairs} pairs ({args.data or 'the run test pairs'}) "
            f"from {args.run_dir}",
            flush=True,
        )
        began = time.perf_counter()

        def progress(stage: str) -> None:
            print(
                f"  [{time.perf_counter() - began:5.0f} s] {stage}",
                file=sys.stderr,
                flush=True,
            )

        found = predict(
            run,
            pairs,
            settings,
            data=str(args.data or "the run's test split"),
            progress=progress,
        )
        write_prediction(found, out)
        print_summary(found.summary)
        print(f"wrote {out / REPORT} (what each number answers) and {out / RESULT}")
        return 0

    return run_main(body)


def print_summary(summary: PredictionSummary) -> None:
    """The three predictions' mean spacing RMSE, and the bands' coverage."""
    population, bands, history = summary.population, summary.bands, summary.history
    rows = [
        (f"population model ({population.chosen})", population.spacing_rmse),
        (f"hybrid median ({bands.draws} draws)", bands.median),
    ]
    if history:
        rows += [
            (
                f"after {history.history:g} s: own ({history.design})",
                history.conditioned,
            ),
            (f"after {history.history:g} s: population", history.population),
        ]
    print(f"{'spacing RMSE per pair [m]':44} {'mean':>7} {'median':>7} {'pairs':>6}")
    for label, rmse in rows:
        print(f"{label:44} {_f(rmse.mean):>7} {_f(rmse.median):>7} {rmse.pairs:>6}")
    print(
        f"bands: 50 % covers {bands.coverage_50:.1%}, 90 % covers "
        f"{bands.coverage_90:.1%}; draws collided {bands.collisions:.1%}"
    )


def _f(value) -> str:
    return "-" if value is None else f"{value:.3f}"
