"""Read any long CSV of trajectories, given a column mapping and units.

One row per vehicle and time step, one column per quantity, any column names:
``columns`` says which source column holds each canonical column of
:mod:`torchcf.data.trajectory` (a dict, or the text ``"vehicle=ID,time=t"``);
a canonical column not mapped is read from the source column of the same name
when there is one. Only ``vehicle`` and ``time`` are required.

Units are given per quantity and converted to SI with the factors of
:data:`LENGTH_UNITS`, :data:`SPEED_UNITS`, :data:`ACCELERATION_UNITS` and
:data:`TIME_UNITS`:

============  =====================================  ==========================
quantity      columns                                units
============  =====================================  ==========================
length        position, length, gap                  m, ft, km
speed         speed                                  m/s, ft/s, km/h, mph
acceleration  acceleration                           m/s^2, ft/s^2
time          time                                   s, ms, ds (0.1 s: frame
                                                     numbers at 10 Hz), frame
                                                     (with a frame rate)
============  =====================================  ==========================

The speed unit defaults to the length unit per second (km: km/h), the
acceleration unit to the length unit per second squared (km: m/s^2). Time in
``frame`` units is a frame number: ``time = frame / frame_rate`` [s], so a
25 Hz video's frame 50 is t = 2 s; the rate is required with that unit and
refused with the others (a rate given with seconds is a slip, not a wish).

A folder source reads every ``*.csv`` in it (not recursively). ``run`` is the
file stem when not mapped; when mapped, it is the column's value, prefixed by
the file stem (``stem:value``) in a folder, so files stay apart.

The column maps, unit factors, file lists and header checks here serve the
other CSV readers too (:mod:`.pairs`, :mod:`.punzo`, :mod:`.ngsim`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from torchcf.data.pairset import DataError
from torchcf.data.trajectory import COLUMNS, TEXT, TrajectoryTable

__all__ = [
    "ACCELERATION_UNITS",
    "FRAME_UNIT",
    "LENGTH_UNITS",
    "SI_UNITS",
    "SPEED_UNITS",
    "TIME_UNITS",
    "TableUnits",
    "check_canonical",
    "column_map",
    "columns_text",
    "first_line",
    "parse_column_map",
    "read_csv_table",
    "read_header",
    "read_selected",
    "resolve_columns",
    "source_files",
    "time_factor",
    "unit_factors",
]

#: Length unit -> metres; applies to position, length and gap.
LENGTH_UNITS: dict[str, float] = {"m": 1.0, "ft": 0.3048, "km": 1000.0}
#: Speed unit -> m/s (1 mph = 1609.344 m / 3600 s, exactly).
SPEED_UNITS: dict[str, float] = {
    "m/s": 1.0,
    "ft/s": 0.3048,
    "km/h": 1.0 / 3.6,
    "mph": 0.44704,
}
#: Acceleration unit -> m/s^2.
ACCELERATION_UNITS: dict[str, float] = {"m/s^2": 1.0, "ft/s^2": 0.3048}
#: Time unit -> s; "ds" (deciseconds) reads 10 Hz frame numbers as time.
TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "ds": 0.1}
#: The time unit of frame numbers: its factor is 1 / frame rate, given apart.
FRAME_UNIT = "frame"

#: Default speed and acceleration units for each length unit.
_DEFAULT_SPEED: dict[str, str] = {"m": "m/s", "ft": "ft/s", "km": "km/h"}
_DEFAULT_ACCELERATION: dict[str, str] = {"m": "m/s^2", "ft": "ft/s^2", "km": "m/s^2"}
#: The quantity, hence the unit, of each numeric canonical column.
_QUANTITY: dict[str, str] = {
    "time": "time",
    "position": "length",
    "speed": "speed",
    "acceleration": "acceleration",
    "length": "length",
    "gap": "length",
}

#: How many source columns a "not in FILE; it has: ..." message lists.
_SHOWN_COLUMNS = 12
#: Characters of one column name shown in a message.
_SHOWN_NAME = 40
#: Bytes read at the start of a file to tell text from binary.
_SNIFF_BYTES = 1 << 16


def parse_column_map(text: str, known: Iterable[str] = COLUMNS) -> dict[str, str]:
    """Parse ``"vehicle=ID,time=t,speed=v"`` into ``{canonical: source column}``.

    Items are separated by commas; spaces around names are dropped.

    Args:
        text: the mapping, one ``canonical=source`` item per column.
        known: the canonical names a reader knows (default: the long table's
            :data:`COLUMNS`; the ``pairs`` reader has its own).

    Returns:
        The mapping, in the order given.

    Raises:
        DataError: an item without ``=`` or with an empty side, a canonical name
            given twice, or a canonical name not in ``known``.
    """
    mapping: dict[str, str] = {}
    for item in str(text).split(","):
        if not item.strip():
            continue
        canonical, sep, column = (part.strip() for part in item.partition("="))
        if not sep or not canonical or not column:
            raise DataError(
                f"column map item {item.strip()!r} is not canonical=source "
                f"(e.g. 'vehicle=ID,time=t')"
            )
        if canonical in mapping:
            raise DataError(f"column map names {canonical!r} twice")
        mapping[canonical] = column
    check_canonical(mapping, known)
    return mapping


@dataclass(frozen=True)
class TableUnits:
    """The units of a table's columns (the module docstring's table). The
    fields are named as the options of ``data.raw`` and ``torchcf data
    extract`` (:func:`torchcf.data.formats.reader_options`).

    Attributes:
        length_unit: unit of position, length and gap, a key of
            :data:`LENGTH_UNITS`.
        speed_unit: a key of :data:`SPEED_UNITS`; None: from ``length_unit``.
        acceleration_unit: a key of :data:`ACCELERATION_UNITS`; None: from
            ``length_unit``.
        time_unit: a key of :data:`TIME_UNITS`, or :data:`FRAME_UNIT`.
        frame_rate: frames per second [Hz] of ``time_unit="frame"``; None
            with every other unit.
    """

    length_unit: str = "m"
    speed_unit: str | None = None
    acceleration_unit: str | None = None
    time_unit: str = "s"
    frame_rate: float | None = None

    def factors(self) -> dict[str, float]:
        """The factor to SI of each quantity (:func:`unit_factors`).

        Raises:
            DataError: an unknown unit, or a frame unit without its rate.
        """
        return unit_factors(
            self.length_unit,
            self.speed_unit,
            self.acceleration_unit,
            self.time_unit,
            self.frame_rate,
        )


#: Metres and seconds, speed in m/s and acceleration in m/s^2: SI, the readers'
#: default.
SI_UNITS = TableUnits()


def read_csv_table(
    source: str | os.PathLike[str],
    *,
    columns: dict[str, str] | str | None = None,
    units: TableUnits = SI_UNITS,
    sep: str = ",",
    road_frame: bool | None = None,
) -> TrajectoryTable:
    """Read a long CSV (or a folder of them) into a trajectory table in SI units.

    Args:
        source: a CSV file, or a folder whose ``*.csv`` files are all read.
        columns: ``{canonical: source column}`` or its text form (see
            :func:`parse_column_map`); None reads the canonical names.
        units: the units of the columns (:class:`TableUnits`; default SI).
        sep: field separator, passed to :func:`pandas.read_csv`.
        road_frame: whether the positions of one run lie on one road (None:
            unknown); stored on the table.

    Returns:
        The table, sorted by run, vehicle and time, ``format="csv"``.

    Raises:
        DataError: a missing source or an empty folder, an unknown unit or
            canonical name, a frame unit without a rate (or a rate without
            it), a mapped column not in a file (named with the columns it
            has), no column for ``vehicle`` or ``time``, a file that does not
            parse, or a text cell in a numeric column.
    """
    given = column_map(columns, COLUMNS)
    to_si = units.factors()
    factors = {column: to_si[q] for column, q in _QUANTITY.items()}
    paths = source_files(source, (".csv",), "csv")
    in_folder = Path(source).is_dir()
    frames = [
        _read_one(path, given, factors, sep, prefix_run=in_folder) for path in paths
    ]
    frame = pd.concat(frames, ignore_index=True)
    table = TrajectoryTable.from_frame(
        frame, source=str(source), format="csv", road_frame=road_frame
    )
    return table.sorted()


def source_files(
    source: str | os.PathLike[str], suffixes: Iterable[str], format: str
) -> list[Path]:
    """The file ``source``, or the files of folder ``source`` with a suffix.

    Args:
        source: a file or a folder (not searched recursively).
        suffixes: lower-case suffixes with the dot, e.g. ``(".csv",)``; matched
            case-insensitively, for folders only.
        format: format name, for messages.

    Returns:
        The files, sorted by name.

    Raises:
        DataError: ``source`` does not exist, or the folder holds no such file.
    """
    path = Path(source)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise DataError(f"no such file or folder: '{path}'")
    wanted = tuple(s.lower() for s in suffixes)
    files = sorted(
        p
        for p in path.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in wanted
    )
    if not files:
        raise DataError(
            f"folder '{path}' holds no {' or '.join('*' + s for s in wanted)} "
            f"file to read as {format}"
        )
    return files


def columns_text(columns: Iterable[object]) -> str:
    """The first column names of a file, for "it has: ..." messages (each cut
    to :data:`_SHOWN_NAME` characters: a binary file's 'header' can be a
    whole file long)."""
    names = [_short(str(c)) for c in columns]
    shown = ", ".join(names[:_SHOWN_COLUMNS])
    more = len(names) - _SHOWN_COLUMNS
    return f"{shown}, ... ({more} more)" if more > 0 else shown


def column_map(
    columns: dict[str, str] | str | None, known: Iterable[str]
) -> dict[str, str]:
    """The items a user mapped, ``{canonical: source}``, checked against ``known``.

    Args:
        columns: a dict, its text form (:func:`parse_column_map`) or None.
        known: the reader's canonical names.

    Raises:
        DataError: an unknown canonical name, or text that does not parse.
    """
    if columns is None:
        return {}
    if isinstance(columns, str):
        return parse_column_map(columns, known)
    given = {str(k).strip(): str(v).strip() for k, v in columns.items()}
    check_canonical(given, known)
    return given


def check_canonical(mapping: dict[str, str], known: Iterable[str] = COLUMNS) -> None:
    """Raise a DataError naming the keys of ``mapping`` not in ``known``."""
    names = tuple(known)
    unknown = [c for c in mapping if c not in names]
    if unknown:
        raise DataError(
            f"unknown canonical column(s) {', '.join(map(repr, unknown))} in the "
            f"column map; known: {', '.join(names)}"
        )


def time_factor(time_unit: str, frame_rate: float | None = None) -> float:
    """Seconds per unit of ``time_unit``; for frames, ``1 / frame_rate``.

    Raises:
        DataError: an unknown unit, ``"frame"`` without a positive finite rate,
            or a rate given with another unit.
    """
    if time_unit == FRAME_UNIT:
        if frame_rate is None:
            raise DataError(
                "time unit 'frame' needs a frame rate (--frame-rate HZ, or "
                "frame_rate in a config): time = frame / rate"
            )
        rate = float(frame_rate)
        if not (math.isfinite(rate) and rate > 0):
            raise DataError(f"frame rate must be finite and > 0 [Hz], got {rate:g}")
        return 1.0 / rate
    if frame_rate is not None:
        raise DataError(
            f"a frame rate is only used with time unit 'frame', not {time_unit!r}"
        )
    known = (*TIME_UNITS, FRAME_UNIT)
    if time_unit not in TIME_UNITS:
        raise DataError(f"unknown time unit {time_unit!r}; known: {', '.join(known)}")
    return TIME_UNITS[time_unit]


def unit_factors(
    length_unit: str = "m",
    speed_unit: str | None = None,
    acceleration_unit: str | None = None,
    time_unit: str = "s",
    frame_rate: float | None = None,
) -> dict[str, float]:
    """The factor to SI of each quantity: ``length``, ``speed``,
    ``acceleration`` and ``time`` (the module docstring's table).

    Raises:
        DataError: an unknown unit, or a frame unit without its rate.
    """
    length = _unit(length_unit, LENGTH_UNITS, "length")
    speed = _unit(speed_unit or _DEFAULT_SPEED[length_unit], SPEED_UNITS, "speed")
    acceleration = _unit(
        acceleration_unit or _DEFAULT_ACCELERATION[length_unit],
        ACCELERATION_UNITS,
        "acceleration",
    )
    return {
        "length": length,
        "speed": speed,
        "acceleration": acceleration,
        "time": time_factor(time_unit, frame_rate),
    }


def resolve_columns(
    path: Path,
    header: list[str],
    given: dict[str, str],
    defaults: dict[str, tuple[str, ...]],
    required: Iterable[str],
) -> dict[str, str]:
    """Which source column of ``path`` holds each canonical column.

    A mapped column must be in the file; an unmapped canonical column takes
    the first of its default names that the file has, or is left out.

    Args:
        path: the file, for messages.
        header: its column names.
        given: the user's ``{canonical: source}`` items.
        defaults: ``{canonical: candidate source names}``, in the canonical
            order; also the list of canonical columns.
        required: canonical columns the file must provide.

    Returns:
        ``{canonical: source}`` for every column found, in the canonical order.

    Raises:
        DataError: a mapped column not in the file, or a required column
            without a source (both name the file's columns).
    """
    chosen: dict[str, str] = {}
    for canonical, names in defaults.items():
        if canonical in given:
            column = given[canonical]
            if column not in header:
                raise DataError(
                    f"column '{column}' (mapped to {canonical}) not in '{path}'; "
                    f"it has: {columns_text(header)}"
                )
            chosen[canonical] = column
            continue
        found = next((name for name in names if name in header), None)
        if found is not None:
            chosen[canonical] = found
    for canonical in required:
        if canonical not in chosen:
            raise DataError(
                f"no column for '{canonical}' in '{path}': map one with "
                f"{canonical}=COLUMN; it has: {columns_text(header)}"
            )
    return chosen


def read_selected(
    path: Path, chosen: dict[str, str], text: Iterable[str], sep: str
) -> pd.DataFrame:
    """The chosen columns of a CSV under their canonical names, as written.

    Args:
        path: the CSV file.
        chosen: ``{canonical: source}`` (from :func:`resolve_columns`).
        text: canonical columns read as text (ids: "007" is not 7); the
            others are parsed later, where a text cell can be named by row.
        sep: field separator.

    Raises:
        DataError: the file does not parse.
    """
    text_sources = {chosen[c] for c in text if c in chosen}
    try:
        raw = pd.read_csv(
            path,
            sep=sep,
            usecols=sorted(set(chosen.values())),
            dtype={c: str for c in text_sources},
            encoding="utf-8-sig",
        )
    except (ValueError, UnicodeDecodeError) as err:  # includes parser errors
        raise DataError(f"cannot read '{path}' as CSV: {first_line(err)}") from None
    return pd.DataFrame({c: raw[s] for c, s in chosen.items()})


def _short(text: str) -> str:
    return text if len(text) <= _SHOWN_NAME else text[: _SHOWN_NAME - 3] + "..."


#: The longest header line of a long-format table [bytes] (a real one names a
#: few dozen columns).
LONGEST_HEADER = 64 * 1024


def require_text(path: Path) -> None:
    """Refuse a binary file before a CSV parser reads it whole as one 'header'.

    Raises:
        DataError: NUL bytes in the file's first 64 KiB (text has none).
    """
    try:
        with path.open("rb") as fh:
            start = fh.read(_SNIFF_BYTES)
    except OSError as err:
        raise DataError(f"cannot read '{path}': {err.strerror}") from None
    if b"\x00" in start:
        raise DataError(f"'{path}' is not text (NUL bytes)")


def require_header_line(path: Path) -> None:
    """Refuse a table whose first line (its header) is longer than
    :data:`LONGEST_HEADER` bytes: a one-line file of megabytes is no table with a
    header, and a parser would spend minutes naming its 'columns'.

    Raises:
        DataError: no line break within the first :data:`LONGEST_HEADER` bytes.
    """
    try:
        with path.open("rb") as fh:
            start = fh.read(LONGEST_HEADER + 1)
    except OSError as err:
        raise DataError(f"cannot read '{path}': {err.strerror}") from None
    if len(start) > LONGEST_HEADER and b"\n" not in start:
        raise DataError(
            f"'{path}' has no line break in its first {LONGEST_HEADER // 1024} KiB: "
            "not a table with a header line"
        )


def read_header(path: Path, sep: str) -> list[str]:
    """The column names of a CSV file.

    Raises:
        DataError: the file is binary, empty, has a header line too long to be
            one, or does not parse.
    """
    require_text(path)
    require_header_line(path)
    try:
        return [
            str(c)
            for c in pd.read_csv(path, sep=sep, nrows=0, encoding="utf-8-sig").columns
        ]
    except pd.errors.EmptyDataError:
        raise DataError(f"'{path}' is empty") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read '{path}' as CSV: {first_line(err)}") from None


def first_line(err: Exception) -> str:
    """An exception's message cut to its first line (at most 200 characters:
    a parser may quote the offending input), for one-line errors."""
    text = str(err).strip()
    return text.splitlines()[0][:200] if text else type(err).__name__


def _unit(value: str, units: dict[str, float], quantity: str) -> float:
    if value not in units:
        raise DataError(f"unknown {quantity} unit {value!r}; known: {', '.join(units)}")
    return units[value]


def _read_one(
    path: Path,
    given: dict[str, str],
    factors: dict[str, float],
    sep: str,
    *,
    prefix_run: bool,
) -> pd.DataFrame:
    """One file as canonical columns in SI (validated by ``from_frame``)."""
    header = read_header(path, sep)
    same_name = {c: (c,) for c in COLUMNS}
    chosen = resolve_columns(path, header, given, same_name, ("vehicle", "time"))
    frame = read_selected(path, chosen, TEXT, sep)
    table = TrajectoryTable.from_frame(frame, source=str(path), format="csv")
    out = table.frame.copy()
    for column, factor in factors.items():
        if factor != 1.0:
            out[column] = out[column] * factor
    if "run" not in chosen:
        out["run"] = path.stem
    elif prefix_run:
        out["run"] = path.stem + ":" + out["run"]
    return out
