"""``torchcf posterior RUN``: the calibrated parameters of a run, and its shares
per group of pairs.

    torchcf posterior runs/carII            # Markdown tables, to stdout
    torchcf posterior runs/carII --csv      # RUN/report/parameters.{csv,md}
    torchcf posterior runs/carII --csv out.csv
    torchcf posterior runs/carII --csv -    # the CSV to stdout

    torchcf posterior runs/zz --by mode        # shares per index.csv mode
    torchcf posterior runs/zz --by mode --csv  # report/shares_by_mode.*
    torchcf posterior runs/zz --groups makes.csv --cluster run,follower

Reads ``RUN/posterior.pt`` (a finished training; :mod:`torchcf.posterior.tables`
says what the tables hold). Training writes the parameter tables into
``RUN/report``; this exports them from a run trained before they existed, or
elsewhere.

``--by COLUMN`` groups the training pairs by a column of the data folder's
``index.csv`` (found from the run's ``config.json``:
:func:`~torchcf.posterior.tables.locate_index`), ``--groups FILE.csv`` by a
mapping file (a ``group`` column and key columns of the index, e.g. ``pair`` or
``run,follower``), and prints each model's share of the hybrid's slots per
group, with a bootstrap interval over pairs (``--cluster``: over clusters of
pairs).

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 no finished run there, a column or
mapping that cannot group the pairs, or an output that cannot be written (one
line on stderr).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ..posterior.learned_set import Posterior
from ..posterior.tables import (
    LEVEL,
    N_BOOTSTRAP,
    NO_GROUP,
    Bootstrap,
    GroupedShares,
    GroupError,
    grouped_shares,
    groups_by_column,
    groups_from_file,
    locate_index,
    parameters_csv,
    parameters_markdown,
    read_index,
    shares_csv,
    shares_markdown,
    training_pairs,
    write_grouped_shares,
    write_parameter_tables,
)
from ..runs.directory import RunDir
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    natural,
    open_fraction,
    run_main,
)
from ..system.files import atomic_write_text, ensure_directory

#: ``--csv`` without a path: the run's report folder.
DEFAULT = "report"


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(
        prog="torchcf posterior",
        description="The calibrated parameters of a trained run: a Markdown table "
        "per model (median and 5-95% range), or one CSV row per accepted particle; "
        "with --by or --groups, the hybrid's shares per group of training pairs.",
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
        "parameters.md beside it; with --by or --groups: shares_by_<group>.{csv,md}, "
        "shares_by_<group>-clusters-<columns>.{csv,md} with --cluster; '-': to stdout)",
    )
    grouping = parser.add_mutually_exclusive_group()
    grouping.add_argument(
        "--by",
        metavar="COLUMN",
        help="shares per value of this column of the data's index.csv (e.g. mode, "
        "run, follower)",
    )
    grouping.add_argument(
        "--groups",
        type=Path,
        metavar="FILE",
        help="shares per group of a mapping CSV: a 'group' column and key "
        "columns of index.csv (pair, or e.g. run,follower)",
    )
    parser.add_argument(
        "--cluster",
        metavar="COLUMNS",
        help="bootstrap whole clusters of pairs: index.csv columns, comma-separated "
        "(e.g. run,follower); default: single pairs",
    )
    parser.add_argument(
        "--bootstrap",
        type=natural,
        default=N_BOOTSTRAP,
        metavar="B",
        help="bootstrap resamples per group (0: no interval)",
    )
    parser.add_argument(
        "--level", type=open_fraction, default=LEVEL, help="coverage of the interval"
    )
    parser.add_argument(
        "--seed", type=natural, default=0, help="seed of the bootstrap (default: 0)"
    )
    parser.add_argument(
        "--data",
        type=Path,
        metavar="DIR",
        help="the folder holding the pairs' index.csv (default: the run's data, "
        "from its config.json)",
    )
    args = parser.parse_args(argv)
    grouped = args.by is not None or args.groups is not None
    if not grouped and (args.cluster or args.data):
        parser.error("--cluster and --data go with --by or --groups")

    def body() -> int:
        run = RunDir(args.run_dir)
        posterior = run.load_posterior()
        if grouped:
            result = _grouped(run, posterior, args)
            text, csv_text = shares_markdown(result), shares_csv(result)
        else:
            text, csv_text = parameters_markdown(posterior), parameters_csv(posterior)
        if args.csv is None:
            print(text)
            return 0
        if args.csv == "-":
            sys.stdout.write(csv_text)
            return 0
        if args.csv == DEFAULT:
            folder = ensure_directory(run.report_dir, "report directory")
            paths = (
                write_grouped_shares(result, folder)
                if grouped
                else write_parameter_tables(posterior, folder)
            )
            for path in paths:
                print(f"wrote {path}")
            return 0
        target = Path(args.csv)
        ensure_directory(target.parent, "output directory")
        atomic_write_text(target, csv_text)
        print(f"wrote {target}")
        return 0

    return run_main(body)


def _grouped(
    run: RunDir, posterior: Posterior, args: argparse.Namespace
) -> GroupedShares:
    """The shares per group that ``--by`` / ``--groups`` ask for."""
    data = run.read_config().data
    try:
        where = locate_index(data, run.path, args.data)
    except GroupError:
        # A mapping file keyed by pair needs no index (a registered data set).
        if args.by is not None or args.data is not None or data.name is None:
            raise
        where = None
    if where is None:
        table, source = training_pairs(posterior), "the run's pair ids"
    else:
        source = str(where.path)
        table = training_pairs(
            posterior,
            read_index(where.path),
            by_position=where.by_position,
            train_columns=where.train_columns,
            source=source,
        )
    if args.by is not None:
        groups, by = groups_by_column(table, args.by, source), args.by
    else:
        groups, by = groups_from_file(table, args.groups, source), args.groups.stem
        ungrouped = groups.count(NO_GROUP)
        if ungrouped:
            print(
                f"note: {ungrouped} of {len(groups)} training pairs are in no row "
                f"of {args.groups} (their group: {NO_GROUP})",
                file=sys.stderr,
            )
        source = f"{args.groups} joined to {source}"
    clusters, unit = None, "pair"
    if args.cluster is not None:
        columns = [c.strip() for c in args.cluster.split(",") if c.strip()]
        if not columns:
            raise GroupError(f"--cluster {args.cluster!r} names no column")
        keys = [groups_by_column(table, c, source) for c in columns]
        clusters = ["\x1f".join(k) for k in zip(*keys, strict=True)]
        unit = ",".join(columns)
    return grouped_shares(
        posterior,
        groups,
        by=by,
        source=source,
        clusters=clusters,
        unit=unit,
        bootstrap=Bootstrap(args.bootstrap, args.level, args.seed),
    )


__all__ = ["main"]
