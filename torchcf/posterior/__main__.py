"""``python -m torchcf.posterior RUN``: the calibrated parameters of a run.

    python -m torchcf.posterior runs/carII            # Markdown tables, to stdout
    python -m torchcf.posterior runs/carII --csv      # RUN/report/parameters.{csv,md}
    python -m torchcf.posterior runs/carII --csv out.csv
    python -m torchcf.posterior runs/carII --csv -    # the CSV to stdout

Reads ``RUN/posterior.pt`` (a finished training; :mod:`torchcf.posterior.tables`
says what the tables hold). Training writes the same files into ``RUN/report``;
this exports them from a run trained before they existed, or elsewhere.

Exit codes (:mod:`torchcf.cli`): 0 done; 2 no finished run there, or an output
that cannot be written (one line on stderr).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ..cli import DefaultsHelpFormatter, run_main
from ..files import atomic_write_text, ensure_directory
from ..rundir import RunDir
from .tables import parameters_csv, parameters_markdown, write_parameter_tables

#: ``--csv`` without a path: the run's report folder.
DEFAULT = "report"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.posterior",
        description="The calibrated parameters of a trained run: a Markdown table "
        "per model (median and 5-95%% range), or one CSV row per accepted particle.",
        formatter_class=DefaultsHelpFormatter,
    )
    parser.add_argument("run_dir", type=Path, help="a trained run directory")
    parser.add_argument(
        "--csv",
        nargs="?",
        const=DEFAULT,
        default=None,
        metavar="PATH",
        help="write the CSV (no PATH: RUN/report/parameters.csv with "
        "parameters.md beside it; '-': to stdout)",
    )
    args = parser.parse_args(argv)

    def body() -> int:
        run = RunDir(args.run_dir)
        posterior = run.load_posterior()
        if args.csv is None:
            print(parameters_markdown(posterior))
            return 0
        if args.csv == "-":
            sys.stdout.write(parameters_csv(posterior))
            return 0
        if args.csv == DEFAULT:
            folder = ensure_directory(run.report_dir, "report directory")
            for path in write_parameter_tables(posterior, folder):
                print(f"wrote {path}")
            return 0
        target = Path(args.csv)
        ensure_directory(target.parent, "output directory")
        atomic_write_text(target, parameters_csv(posterior))
        print(f"wrote {target}")
        return 0

    return run_main(body)


if __name__ == "__main__":
    raise SystemExit(main())
