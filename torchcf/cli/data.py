"""``torchcf data extract``: raw trajectories to a six-CSV pair folder.

    torchcf data extract openacc/ --format openacc --out pairs/openacc
    torchcf data extract trajectories-0400-0415.txt --format ngsim \\
        --out pairs/i80
    torchcf data extract log.csv --format csv \\
        --columns vehicle=id,time=t,position=x,speed=v,leader=lead \\
        --speed-unit km/h --out pairs/mine
    torchcf data extract ultra-av/ --format pairs --out pairs/ultra
    torchcf data extract couples.csv --format pairs \\
        --columns pair=id,time=frame,x_lead=xl,x_follow=xf,gap=s \\
        --time-unit frame --frame-rate 25 --out pairs/video
    torchcf data extract punzo/ --format punzo --out pairs/punzo
    torchcf data extract log.csv --format csv --window whole \\
        --test-fraction 0 --out pairs/whole

The folder it writes (:mod:`torchcf.data.writer`) is a ``data.path`` for
``torchcf train``; a config's ``data.raw`` section runs the same
extraction when the run starts. With ``--test-fraction 0`` the folder has no
test split (no ``Testing/``): a run trains on it and skips the evaluation.
Exit codes: 0 done, 2 bad input (one line on stderr), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from pydantic import ValidationError

from torchcf.config.messages import ConfigError, describe
from torchcf.config.raw import RawSource
from torchcf.data.extract import AUTO, MIN_WHOLE_LENGTH, WHOLE
from torchcf.data.formats import FORMATS, reader_options
from torchcf.data.formats.generic import (
    FRAME_UNIT,
    LENGTH_UNITS,
    SPEED_UNITS,
    TIME_UNITS,
    parse_column_map,
)
from torchcf.data.formats.gps import GPS_COLUMNS
from torchcf.data.formats.pairs import LENGTH_TOLERANCE, PAIR_COLUMNS
from torchcf.data.importer import extract_source
from torchcf.data.trajectory import COLUMNS
from torchcf.data.writer import write_extraction
from torchcf.system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    folder,
    natural,
    nonnegative,
    positive,
    run_main,
    share,
)

#: RawSource fields set by the reader options of the command line, and their
#: defaults there (those of the readers).
_READER_ARGS: dict[str, object] = {
    "columns": None,
    "length_unit": "m",
    "speed_unit": None,
    "acceleration_unit": None,
    "time_unit": "s",
    "frame_rate": None,
    "road_frame": None,
    "length_tolerance": LENGTH_TOLERANCE,
    "recordings": None,
    "directions": None,
    "follower_classes": None,
    "lap_frame": False,
    "time_format": "auto",
    "leader_rule": None,
    "platoon": None,
    "path_file": None,
}


def _optional_float(text: str) -> float | None:
    """A number, or "none" / "off" to switch a filter off."""
    if text.lower() in ("none", "off"):
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number or 'none': {text!r}") from None


#: The longest window a pair may span [s]: a day of driving (a longer one is a
#: mistyped unit, and its step count would not fit in memory).
LONGEST_WINDOW = 86_400.0


def _window(text: str) -> float | str:
    """A window length [s], "auto" or "whole"."""
    if text.strip().lower() in (AUTO, WHOLE):
        return text.strip().lower()
    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not a number of seconds, 'auto' or 'whole': {text[:40]!r}"
        ) from None
    if not 0.0 < seconds <= LONGEST_WINDOW:
        raise argparse.ArgumentTypeError(
            f"a window of 0-{LONGEST_WINDOW:g} s, 'auto' or 'whole', got {text[:40]!r}"
        )
    return seconds


def _parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="torchcf data",
        description="Raw trajectory data to torchcf's pair layout.",
        formatter_class=DefaultsHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser(
        "extract",
        help="cut leader-follower pairs from raw trajectories",
        formatter_class=DefaultsHelpFormatter,
        description=(
            "Read raw trajectories, cut leader-follower pairs of one length (or "
            "keep whole couples, --window whole), drop what fails the quality "
            "filters, split by source group and write the six-CSV layout with "
            "meta.json, index.csv, dropped.csv and extract.json."
        ),
    )
    p.add_argument("source", help="raw file or folder")
    p.add_argument(
        "--format", required=True, choices=sorted(FORMATS), help="the raw format"
    )
    p.add_argument(
        "--out", type=folder, required=True, help="folder to write (must not exist)"
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace an earlier extraction"
    )
    _add_reader_options(p)
    _add_highd_options(p)
    _add_gps_options(p)
    p.add_argument(
        "--vehicle-length",
        type=positive,
        default=5.0,
        help="openacc: vehicle length [m]",
    )
    p.add_argument(
        "--lap-frame",
        action="store_true",
        default=_READER_ARGS["lap_frame"],
        help=(
            "openacc: the runs go round one circular track; put every run on its "
            "lap coordinate (E/N, Alt) so road effects can be offered"
        ),
    )
    cut = p.add_argument_group("windows and split")
    cut.add_argument(
        "--window",
        type=_window,
        default=40.0,
        help="pair length [s]; 'auto': the median length of the couples' "
        "spans, rounded down to 0.5 s, at most 40 s; 'whole': every couple one "
        "pair of its own length, cut only where a step fails a filter into "
        f"clean stretches of at least {MIN_WHOLE_LENGTH:g} s",
    )
    cut.add_argument(
        "--stride",
        type=positive,
        default=None,
        help="[s] between windows (None: window; not with --window whole)",
    )
    cut.add_argument(
        "--leader-length",
        type=positive,
        default=None,
        help="[m] leader length of the pair set (None: the median)",
    )
    cut.add_argument(
        "--default-length", type=positive, default=5.0, help="[m] where none is known"
    )
    cut.add_argument(
        "--split-by",
        default="follower",
        choices=("follower", "couple", "run"),
        help="the group kept whole in one split",
    )
    cut.add_argument(
        "--test-fraction",
        type=share,
        default=0.3,
        help="share of pairs for test, whole groups; 0: no test split (no "
        "Testing/: training runs, the evaluation is skipped)",
    )
    cut.add_argument("--seed", type=natural, default=0, help="seed of the split")
    quality = p.add_argument_group("quality filters ('none' switches one off)")
    quality.add_argument("--jump", type=_optional_float, default=1.0, help="[m]")
    quality.add_argument(
        "--speed-mismatch",
        type=_optional_float,
        default=3.0,
        help="[m/s] a step's speed against the recorded speeds",
    )
    quality.add_argument(
        "--max-acceleration", type=_optional_float, default=8.0, help="[m/s^2]"
    )
    quality.add_argument("--gap-drift", type=_optional_float, default=2.0, help="[m]")
    quality.add_argument(
        "--gap-drift-rate", type=nonnegative, default=0.2, help="[m/s]"
    )
    quality.add_argument(
        "--standstill-speed", type=_optional_float, default=0.5, help="[m/s]"
    )
    return parser


def _add_reader_options(p: argparse.ArgumentParser) -> None:
    """The options of the csv, pairs and punzo readers (units, columns)."""
    group = p.add_argument_group("csv, pairs and punzo formats")
    group.add_argument(
        "--columns",
        help=(
            "column map canonical=SOURCE,...; csv: "
            f"{', '.join(COLUMNS)} (default: those names), e.g. "
            "vehicle=ID,time=t,position=x; pairs: "
            f"{', '.join(PAIR_COLUMNS)} (default: ULTra-AV's Trajectory_ID, "
            "Time_Index, Pos_LV, Speed_LV, Acc_LV, Pos_FAV, Speed_FAV, Acc_FAV, "
            "Spatial_Gap or Space_Gap; an item replaces one default)"
        ),
    )
    group.add_argument(
        "--length-unit",
        default=_READER_ARGS["length_unit"],
        help=f"unit of positions, gaps, lengths ({', '.join(LENGTH_UNITS)})",
    )
    group.add_argument(
        "--speed-unit",
        default=_READER_ARGS["speed_unit"],
        help=f"unit of speeds ({', '.join(SPEED_UNITS)}; None: length unit / s)",
    )
    group.add_argument(
        "--acceleration-unit",
        default=_READER_ARGS["acceleration_unit"],
        help="unit of accelerations (m/s^2, ft/s^2; None: length unit / s^2)",
    )
    group.add_argument(
        "--time-unit",
        default=_READER_ARGS["time_unit"],
        help=(
            f"unit of time stamps ({', '.join((*TIME_UNITS, FRAME_UNIT))}); "
            "frame: frame numbers, time = frame / --frame-rate"
        ),
    )
    group.add_argument(
        "--frame-rate",
        type=positive,
        default=_READER_ARGS["frame_rate"],
        help="frames per second [Hz] of --time-unit frame (required with it)",
    )
    group.add_argument(
        "--road-frame",
        choices=("yes", "no"),
        default=_READER_ARGS["road_frame"],
        help="csv, pairs: whether all positions lie on one road (None: unknown)",
    )
    group.add_argument(
        "--length-tolerance",
        type=nonnegative,
        default=_READER_ARGS["length_tolerance"],
        help=(
            "pairs, punzo: largest spread [m] of a pair's leader length, "
            "x_lead - x_follow - gap or the length column"
        ),
    )


def _add_highd_options(p: argparse.ArgumentParser) -> None:
    """The options of the highD reader (which recordings, directions, classes)."""
    group = p.add_argument_group("highd format")
    group.add_argument(
        "--recordings", help='recording numbers, e.g. "1,2,5-7" (None: all)'
    )
    group.add_argument(
        "--directions",
        help='driving directions: "upper" (1), "lower" (2) or "upper,lower" '
        "(None: both)",
    )
    group.add_argument(
        "--follower-classes",
        help='vehicle classes that may follow, e.g. "Car" (None: all; others '
        "stay as leaders)",
    )


def _add_gps_options(p: argparse.ArgumentParser) -> None:
    """The options of the GPS reader (time format, leaders, path)."""
    group = p.add_argument_group(
        "gps format (columns: " + ", ".join(GPS_COLUMNS) + "; --time-unit, "
        "--speed-unit as above)"
    )
    group.add_argument(
        "--time-format",
        choices=("auto", "seconds", "gps-week", "timestamp"),
        default=_READER_ARGS["time_format"],
        help="numbers, GPS week seconds (rollovers undone) or date stamps",
    )
    group.add_argument(
        "--leader-rule",
        choices=("column", "platoon", "nearest"),
        default=_READER_ARGS["leader_rule"],
        help="each vehicle's leader: a leader column, --platoon's order, or the "
        "nearest vehicle ahead on the path (None: column, else platoon, else nearest)",
    )
    group.add_argument(
        "--platoon", default=None, help='the vehicles in driving order, "A,B,C"'
    )
    group.add_argument(
        "--path-file",
        default=None,
        help="a CSV of the road's lat, lon in driving order (None: the platoon's path)",
    )


def _reader_fields(args: argparse.Namespace) -> dict:
    """The reader options as RawSource fields: all that ``args.format`` takes,
    and any other one set on the command line (RawSource refuses those)."""
    takes = reader_options(args.format)
    fields = {}
    for name, default in _READER_ARGS.items():
        value = getattr(args, name)
        if name not in takes and value == default:
            continue
        if name == "columns" and value is not None:
            known = {"pairs": PAIR_COLUMNS, "gps": GPS_COLUMNS}.get(
                args.format, COLUMNS
            )
            value = parse_column_map(value, known)
        elif name == "road_frame" and value is not None:
            value = value == "yes"
        fields[name] = value
    return fields


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
        "speed_mismatch": args.speed_mismatch,
        "max_acceleration": args.max_acceleration,
        "gap_drift": args.gap_drift,
        "gap_drift_rate": args.gap_drift_rate,
        "standstill_speed": args.standstill_speed,
        "split_by": args.split_by,
        "test_fraction": args.test_fraction,
        "seed": args.seed,
    }
    fields.update(_reader_fields(args))
    try:
        return RawSource(**fields)
    except ValidationError as error:
        raise ConfigError(describe(error, RawSource)) from None


def _listed(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items()) or "none"


def _report(extraction, out, seconds: float) -> None:
    summary = extraction.summary
    print(_whole_line(summary) if extraction.whole else _windows_line(summary))
    for note in extraction.attention:  # units that look wrong, a chosen window
        print(f"note: {note}")
    others = len(extraction.notes) - len(extraction.attention)
    more = f"{others} more note{'s' if others != 1 else ''} in extract.json"
    print(f"wrote {out} in {seconds:.1f} s ({more})")


def _windows_line(summary: dict) -> str:
    return (
        f"{summary['pairs']} pairs ({summary['train_pairs']} train, "
        f"{summary['test_pairs']} test) of {summary['window_steps']} steps at "
        f"dt = {summary['dt']:g} s from {summary['vehicles']} vehicles in "
        f"{summary['runs']} run(s); {summary['candidate_windows']} candidate windows, "
        f"dropped: {_listed(summary['windows_dropped'])}; "
        f"{summary['spans_short']} couple spans shorter than a window of "
        f"{summary['window_steps'] * summary['dt']:g} s "
        f"({summary['seconds_in_short_spans']:.0f} s of data in them)"
    )


def _whole_line(summary: dict) -> str:
    seconds = summary["pair_seconds"]
    shortest = summary["min_pair_steps"] * summary["dt"]
    return (
        f"{summary['pairs']} pairs ({summary['train_pairs']} train, "
        f"{summary['test_pairs']} test), {summary['pairs_are']} of "
        f"{seconds['min']:.1f}-{seconds['max']:.1f} s (median "
        f"{seconds['median']:.1f} s) at dt = {summary['dt']:g} s from "
        f"{summary['vehicles']} vehicles in {summary['runs']} run(s); couples cut "
        f"at: {_listed(summary['defects'])}; stretches dropped: "
        f"{_listed(summary['stretches_dropped'])}; {summary['spans_short']} couple "
        f"spans and {summary['stretches_short']} stretches shorter than "
        f"{shortest:g} s ({summary['seconds_in_short_spans']:.0f} s and "
        f"{summary['seconds_in_short_stretches']:.0f} s of data in them)"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf data``. Returns the exit code."""
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
            "command": "torchcf data "
            + " ".join(sys.argv[1:] if argv is None else argv),
            "raw": raw.model_dump(),
        }
        out = write_extraction(
            extraction, args.out, record=record, overwrite=args.overwrite
        )
        _report(extraction, out, time.perf_counter() - began)
        return 0

    return run_main(body)
