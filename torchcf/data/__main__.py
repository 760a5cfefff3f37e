"""``python -m torchcf.data extract``: raw trajectories to a six-CSV pair folder.

    python -m torchcf.data extract openacc/ --format openacc --out pairs/openacc
    python -m torchcf.data extract trajectories-0400-0415.txt --format ngsim \\
        --out pairs/i80
    python -m torchcf.data extract log.csv --format csv \\
        --columns vehicle=id,time=t,position=x,speed=v,leader=lead \\
        --speed-unit km/h --out pairs/mine

The folder it writes (:mod:`torchcf.data.writer`) is a ``data.path`` for
``python -m torchcf.train``; a config's ``data.raw`` section runs the same
extraction when the run starts. Exit codes: 0 done, 2 bad input (one line on
stderr), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from pydantic import ValidationError

from torchcf.cli import DefaultsHelpFormatter, run_main
from torchcf.config.messages import ConfigError, describe
from torchcf.config.raw import RawSource
from torchcf.data.formats import FORMATS
from torchcf.data.formats.generic import parse_column_map
from torchcf.data.importer import extract_source
from torchcf.data.writer import write_extraction


def _optional_float(text: str) -> float | None:
    """A number, or "none" / "off" to switch a filter off."""
    if text.lower() in ("none", "off"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or 'none': {text!r}") from None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.data",
        description="Raw trajectory data to torchcf's pair layout.",
        formatter_class=DefaultsHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser(
        "extract",
        help="cut leader-follower pairs from raw trajectories",
        formatter_class=DefaultsHelpFormatter,
        description=(
            "Read raw trajectories, cut leader-follower pairs of one length, drop "
            "windows that fail the quality filters, split by source group and "
            "write the six-CSV layout with meta.json, index.csv, dropped.csv and "
            "extract.json."
        ),
    )
    p.add_argument("source", help="raw file or folder")
    p.add_argument(
        "--format", required=True, choices=sorted(FORMATS), help="the raw format"
    )
    p.add_argument("--out", required=True, help="folder to write (must not exist)")
    p.add_argument(
        "--overwrite", action="store_true", help="replace an earlier extraction"
    )
    csv = p.add_argument_group("csv format")
    csv.add_argument("--columns", help="mapping, e.g. vehicle=ID,time=t,position=x")
    csv.add_argument("--length-unit", default="m", help="unit of positions (m, ft)")
    csv.add_argument(
        "--speed-unit", default=None, help="unit of speeds (None: length unit / s)"
    )
    csv.add_argument(
        "--acceleration-unit",
        default=None,
        help="unit of accelerations (None: length unit / s^2)",
    )
    csv.add_argument(
        "--road-frame",
        choices=("yes", "no"),
        default=None,
        help="whether all positions lie on one road (None: unknown)",
    )
    csv.add_argument("--time-unit", default="s", help="unit of time stamps (s, ms)")
    p.add_argument(
        "--vehicle-length", type=float, default=5.0, help="openacc: vehicle length [m]"
    )
    cut = p.add_argument_group("windows and split")
    cut.add_argument("--window", type=float, default=40.0, help="pair length [s]")
    cut.add_argument(
        "--stride", type=float, default=None, help="[s] between windows (None: window)"
    )
    cut.add_argument(
        "--leader-length",
        type=float,
        default=None,
        help="[m] leader length of the pair set (None: the median)",
    )
    cut.add_argument(
        "--default-length", type=float, default=5.0, help="[m] where none is known"
    )
    cut.add_argument(
        "--split-by",
        default="follower",
        choices=("follower", "couple", "run"),
        help="the group kept whole in one split",
    )
    cut.add_argument(
        "--test-fraction", type=float, default=0.3, help="share of groups for test"
    )
    cut.add_argument("--seed", type=int, default=0, help="seed of the split")
    quality = p.add_argument_group("quality filters ('none' switches one off)")
    quality.add_argument("--jump", type=_optional_float, default=1.0, help="[m]")
    quality.add_argument(
        "--max-acceleration", type=_optional_float, default=8.0, help="[m/s^2]"
    )
    quality.add_argument("--gap-drift", type=_optional_float, default=2.0, help="[m]")
    quality.add_argument("--gap-drift-rate", type=float, default=0.2, help="[m/s]")
    quality.add_argument(
        "--standstill-speed", type=_optional_float, default=0.5, help="[m/s]"
    )
    return parser


def _raw_source(args: argparse.Namespace) -> RawSource:
    fields = {
        "source": args.source,
        "format": args.format,
        "vehicle_length": args.vehicle_length,
        "window": args.window,
        "stride": args.stride,
        "leader_length": args.leader_length,
        "default_length": args.default_length,
        "jump": args.jump,
        "max_acceleration": args.max_acceleration,
        "gap_drift": args.gap_drift,
        "gap_drift_rate": args.gap_drift_rate,
        "standstill_speed": args.standstill_speed,
        "split_by": args.split_by,
        "test_fraction": args.test_fraction,
        "seed": args.seed,
    }
    if args.format == "csv":
        fields.update(
            columns=parse_column_map(args.columns) if args.columns else None,
            length_unit=args.length_unit,
            speed_unit=args.speed_unit,
            acceleration_unit=args.acceleration_unit,
            time_unit=args.time_unit,
            road_frame=None if args.road_frame is None else args.road_frame == "yes",
        )
    try:
        return RawSource(**fields)
    except ValidationError as error:
        raise ConfigError(describe(error, RawSource)) from None


def _report(extraction, out, seconds: float) -> None:
    summary = extraction.summary
    dropped = summary["windows_dropped"]
    print(
        f"{summary['pairs']} pairs ({summary['train_pairs']} train, "
        f"{summary['test_pairs']} test) of {summary['window_steps']} steps at "
        f"dt = {summary['dt']:g} s from {summary['vehicles']} vehicles in "
        f"{summary['runs']} run(s); {summary['candidate_windows']} candidate windows, "
        f"dropped: {', '.join(f'{k} {v}' for k, v in dropped.items()) or 'none'}; "
        f"{summary['spans_short']} couple spans shorter than a window "
        f"({summary['seconds_in_short_spans']:.0f} s)"
    )
    print(f"wrote {out} in {seconds:.1f} s")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torchcf.data``. Returns the exit code."""
    args = _parser().parse_args(argv)

    def body() -> int:
        began = time.perf_counter()
        raw = _raw_source(args)
        extraction = extract_source(
            raw.source,
            raw.format,
            reader_options=raw.reader_options(),
            options=raw.extract_options(),
        )
        record = {
            "command": "python -m torchcf.data "
            + " ".join(sys.argv[1:] if argv is None else argv),
            "raw": raw.model_dump(),
        }
        out = write_extraction(
            extraction, args.out, record=record, overwrite=args.overwrite
        )
        _report(extraction, out, time.perf_counter() - began)
        return 0

    return run_main(body)


if __name__ == "__main__":
    raise SystemExit(main())
