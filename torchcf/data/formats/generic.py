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
                                                     numbers at 10 Hz)
============  =====================================  ==========================

The speed unit defaults to the length unit per second (km: km/h), the
acceleration unit to the length unit per second squared (km: m/s^2).

A folder source reads every ``*.csv`` in it (not recursively). ``run`` is the
file stem when not mapped; when mapped, it is the column's value, prefixed by
the file stem (``stem:value``) in a folder, so files stay apart.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from torchcf.data.pairset import DataError
from torchcf.data.trajectory import COLUMNS, TEXT, TrajectoryTable

__all__ = [
    "ACCELERATION_UNITS",
    "LENGTH_UNITS",
    "SPEED_UNITS",
    "TIME_UNITS",
    "parse_column_map",
    "read_csv_table",
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

#: Default speed and acceleration units for each length unit.
_DEFAULT_SPEED: dict[str, str] = {"m": "m/s", "ft": "ft/s", "km": "km/h"}
_DEFAULT_ACCELERATION: dict[str, str] = {"m": "m/s^2", "ft": "ft/s^2", "km": "m/s^2"}

#: How many source columns a "not in FILE; it has: ..." message lists.
_SHOWN_COLUMNS = 12


def parse_column_map(text: str) -> dict[str, str]:
    """Parse ``"vehicle=ID,time=t,speed=v"`` into ``{canonical: source column}``.

    Items are separated by commas; spaces around names are dropped.

    Args:
        text: the mapping, one ``canonical=source`` item per column.

    Returns:
        The mapping, in the order given.

    Raises:
        DataError: an item without ``=`` or with an empty side, a canonical name
            given twice, or a canonical name not in :data:`COLUMNS`.
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
    _check_canonical(mapping)
    return mapping


def read_csv_table(
    source: str | os.PathLike[str],
    *,
    columns: dict[str, str] | str | None = None,
    length_unit: str = "m",
    speed_unit: str | None = None,
    acceleration_unit: str | None = None,
    time_unit: str = "s",
    sep: str = ",",
    road_frame: bool | None = None,
) -> TrajectoryTable:
    """Read a long CSV (or a folder of them) into a trajectory table in SI units.

    Args:
        source: a CSV file, or a folder whose ``*.csv`` files are all read.
        columns: ``{canonical: source column}`` or its text form (see
            :func:`parse_column_map`); None reads the canonical names.
        length_unit: unit of position, length and gap, a key of
            :data:`LENGTH_UNITS`.
        speed_unit: a key of :data:`SPEED_UNITS`; None: from ``length_unit``.
        acceleration_unit: a key of :data:`ACCELERATION_UNITS`; None: from
            ``length_unit``.
        time_unit: a key of :data:`TIME_UNITS`.
        sep: field separator, passed to :func:`pandas.read_csv`.
        road_frame: whether the positions of one run lie on one road (None:
            unknown); stored on the table.

    Returns:
        The table, sorted by run, vehicle and time, ``format="csv"``.

    Raises:
        DataError: a missing source or an empty folder, an unknown unit or
            canonical name, a mapped column not in a file (named with the
            columns it has), no column for ``vehicle`` or ``time``, a file that
            does not parse, or a text cell in a numeric column.
    """
    mapping = _mapping(columns)
    factors = _factors(length_unit, speed_unit, acceleration_unit, time_unit)
    paths = source_files(source, (".csv",), "csv")
    in_folder = Path(source).is_dir()
    frames = [
        _read_one(path, mapping, factors, sep, prefix_run=in_folder) for path in paths
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
    """The first column names of a file, for "it has: ..." messages."""
    names = [str(c) for c in columns]
    shown = ", ".join(names[:_SHOWN_COLUMNS])
    more = len(names) - _SHOWN_COLUMNS
    return f"{shown}, ... ({more} more)" if more > 0 else shown


def _mapping(columns: dict[str, str] | str | None) -> dict[str, str]:
    """The full ``{canonical: source}`` map: given items over same-name defaults."""
    if columns is None:
        given: dict[str, str] = {}
    elif isinstance(columns, str):
        given = parse_column_map(columns)
    else:
        given = {str(k).strip(): str(v).strip() for k, v in columns.items()}
        _check_canonical(given)
    return given


def _check_canonical(mapping: dict[str, str]) -> None:
    unknown = [c for c in mapping if c not in COLUMNS]
    if unknown:
        raise DataError(
            f"unknown canonical column(s) {', '.join(map(repr, unknown))} in the "
            f"column map; known: {', '.join(COLUMNS)}"
        )


def _unit(value: str, units: dict[str, float], quantity: str) -> float:
    if value not in units:
        raise DataError(f"unknown {quantity} unit {value!r}; known: {', '.join(units)}")
    return units[value]


def _factors(
    length_unit: str,
    speed_unit: str | None,
    acceleration_unit: str | None,
    time_unit: str,
) -> dict[str, float]:
    """Factor to SI of every numeric canonical column."""
    length = _unit(length_unit, LENGTH_UNITS, "length")
    speed = _unit(speed_unit or _DEFAULT_SPEED[length_unit], SPEED_UNITS, "speed")
    acceleration = _unit(
        acceleration_unit or _DEFAULT_ACCELERATION[length_unit],
        ACCELERATION_UNITS,
        "acceleration",
    )
    return {
        "time": _unit(time_unit, TIME_UNITS, "time"),
        "position": length,
        "speed": speed,
        "acceleration": acceleration,
        "length": length,
        "gap": length,
    }


def _read_one(
    path: Path,
    mapping: dict[str, str],
    factors: dict[str, float],
    sep: str,
    *,
    prefix_run: bool,
) -> pd.DataFrame:
    """One file as canonical columns in SI (validated by ``from_frame``)."""
    header = _header(path, sep)
    chosen: dict[str, str] = {}
    for canonical in COLUMNS:
        if canonical in mapping:
            column = mapping[canonical]
            if column not in header:
                raise DataError(
                    f"column '{column}' (mapped to {canonical}) not in '{path}'; "
                    f"it has: {columns_text(header)}"
                )
            chosen[canonical] = column
        elif canonical in header:
            chosen[canonical] = canonical
    for required in ("vehicle", "time"):
        if required not in chosen:
            raise DataError(
                f"no column for '{required}' in '{path}': map one with "
                f"{required}=COLUMN; it has: {columns_text(header)}"
            )
    # Ids stay text as written ("007" is not 7); numbers are parsed by from_frame,
    # which names the row of a text cell.
    text_sources = {chosen[c] for c in chosen if c in TEXT}
    try:
        raw = pd.read_csv(
            path,
            sep=sep,
            usecols=sorted(set(chosen.values())),
            dtype={c: str for c in text_sources},
            encoding="utf-8-sig",
        )
    except (ValueError, UnicodeDecodeError) as err:  # includes parser errors
        raise DataError(f"cannot read '{path}' as CSV: {_first_line(err)}") from None
    frame = pd.DataFrame({c: raw[s] for c, s in chosen.items()})
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


def _header(path: Path, sep: str) -> list[str]:
    try:
        return [
            str(c)
            for c in pd.read_csv(path, sep=sep, nrows=0, encoding="utf-8-sig").columns
        ]
    except pd.errors.EmptyDataError:
        raise DataError(f"'{path}' is empty") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read '{path}' as CSV: {_first_line(err)}") from None


def _first_line(err: Exception) -> str:
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
