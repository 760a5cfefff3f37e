"""Read the per-trajectory files of Punzo et al.'s car-following calibration package.

One file holds one leader-follower trajectory: six numeric columns, by position,

======  =====  ==============================================================
column  unit   meaning
======  =====  ==============================================================
t       s      time
x_lead  m      leader position (front bumper)
x_fol   m      follower position (front bumper)
v_lead  m/s    leader speed
v_fol   m/s    follower speed
L_lead  m      leader length: the spacing is ``x_lead - x_fol - L_lead``
======  =====  ==============================================================

That order and those units are issue 27's description of the package; no
public description of its files could be found to confirm them. The units
agree with the data such packages are built from, the Napoli car-following
database (Punzo and Simonelli 2005; GPS platoons, "speeds = metres/second,
distances = metres", 10 Hz), and ``L_lead`` beside front-bumper positions is
exactly torchcf's convention (:mod:`torchcf.data.trajectory`), so the columns
go into the long table as they are. Other units are converted with the
``csv`` format's tables (``length_unit``, ``speed_unit``; ``t`` may be a frame
number: ``time_unit="frame"`` with a ``frame_rate``).

Layout tolerated: the separator is found on the first data line (comma,
semicolon, tab or spaces; with semicolons a decimal comma is read too); a first
line that is not all numbers is a header and is skipped, since the columns are
taken by position, never by name; blank lines are skipped; a missing value is
written NaN, and an empty cell or a short row is an error.

A folder reads each ``*.txt``, ``*.csv`` and ``*.dat`` file in it (not
recursively), each file its own pair named by its stem, in its own run
(:func:`torchcf.data.formats.pairs.pairs_to_long`: vehicles ``"<stem>:leader"``
and ``"<stem>:follower"``). ``L_lead`` must stay within ``length_tolerance``
of its median in a file (a vehicle does not change length); the median is used.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pandas as pd

from torchcf.data.formats.generic import (
    first_line,
    require_text,
    source_files,
    unit_factors,
)
from torchcf.data.formats.pairs import (
    LENGTH_TOLERANCE,
    QUANTITY,
    pairs_to_long,
    parse_numbers,
)
from torchcf.data.pairset import DataError, positive_float
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["PUNZO_COLUMNS", "SUFFIXES", "read_punzo"]

#: The six columns in file order: the package's name -> the pair column.
PUNZO_COLUMNS: dict[str, str] = {
    "t": "time",
    "x_lead": "x_lead",
    "x_fol": "x_follow",
    "v_lead": "v_lead",
    "v_fol": "v_follow",
    "L_lead": "leader_length",
}
#: Suffixes of the files a folder is read for.
SUFFIXES: tuple[str, ...] = (".txt", ".csv", ".dat")
#: A cell that reads as a number (a decimal point or comma; NaN, inf).
_NUMBER = re.compile(
    r"^[+-]?(\d+([.,]\d*)?|[.,]\d+)([eE][+-]?\d+)?$|^[+-]?(nan|inf)$", re.IGNORECASE
)


def read_punzo(
    source: str | os.PathLike[str],
    *,
    length_unit: str = "m",
    speed_unit: str | None = None,
    time_unit: str = "s",
    frame_rate: float | None = None,
    length_tolerance: float = LENGTH_TOLERANCE,
) -> TrajectoryTable:
    """Read one Punzo trajectory file, or a folder of them, into a long table.

    Args:
        source: a six-column file, or a folder of them (:data:`SUFFIXES`).
        length_unit: unit of x_lead, x_fol and L_lead (a key of
            :data:`~torchcf.data.formats.generic.LENGTH_UNITS`).
        speed_unit: unit of v_lead and v_fol; None: the length unit per second.
        time_unit, frame_rate: unit of t, as for the ``csv`` format.
        length_tolerance: largest spread of L_lead within a file [m], > 0.

    Returns:
        The table, sorted, ``format="punzo"``, one run per file.

    Raises:
        DataError: a missing source, an empty folder or file, a file without
            six columns, with an empty cell or a text cell, two files of one
            stem, a leader length that changes within a file, or an unknown
            unit.
    """
    units = unit_factors(length_unit, speed_unit, None, time_unit, frame_rate)
    tolerance = positive_float(length_tolerance, "length_tolerance", "m")
    paths = source_files(source, SUFFIXES, "punzo")
    _check_unique_stems(paths)
    frames, notes = [], []
    for path in paths:
        pairs = _read_one(path, units)
        long, note = pairs_to_long(pairs, source=str(path), tolerance=tolerance)
        frames.append(long)
        notes.append(f"{path.name}: {note}")
    table = TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True),
        source=str(source),
        format="punzo",
        notes=notes,
    )
    return table.sorted()


def _read_one(path: Path, units: dict[str, float]) -> pd.DataFrame:
    """One file as pair columns (:data:`PUNZO_COLUMNS`) in SI, pair = stem."""
    require_text(path)
    data_line, skip = _layout(path)
    sep, decimal_comma = _separator(data_line)
    try:
        raw = pd.read_csv(
            path,
            sep=sep,
            header=None,
            skiprows=skip,
            skip_blank_lines=True,
            dtype=str,
            keep_default_na=False,  # "" is a missing cell, "NaN" a written one
            encoding="utf-8-sig",
        )
    except pd.errors.EmptyDataError:
        raise DataError(f"'{path}' has no data row") from None
    except (ValueError, UnicodeDecodeError) as err:  # includes parser errors
        raise DataError(f"cannot read '{path}' as punzo: {first_line(err)}") from None
    if raw.shape[1] != len(PUNZO_COLUMNS):
        raise DataError(
            f"'{path}' has {raw.shape[1]} columns; a punzo file has six: "
            f"{', '.join(PUNZO_COLUMNS)}"
        )
    _check_full(raw, path)
    out = pd.DataFrame({"pair": path.stem}, index=raw.index)
    for position, (name, column) in enumerate(PUNZO_COLUMNS.items()):
        cells = raw[position]
        if decimal_comma:
            cells = cells.str.replace(",", ".", regex=False)
        factor = units[QUANTITY[column]]
        out[column] = parse_numbers(cells, name, str(path)) * factor
    return out


def _layout(path: Path) -> tuple[str, int]:
    """The first data line of ``path`` and how many lines precede the data:
    up to and including a header (a first non-blank line that is not all
    numbers), or 0 without one.

    Raises:
        DataError: the file is empty, holds only a header, or is not text.
    """
    header_at = None
    first = True
    try:
        with path.open(encoding="utf-8-sig") as handle:
            for number, line in enumerate(handle):
                if not line.strip():
                    continue
                if first and not all(_NUMBER.match(f) for f in _fields(line)):
                    header_at = number
                    first = False
                    continue
                return line, 0 if header_at is None else header_at + 1
    except UnicodeDecodeError as err:
        raise DataError(f"cannot read '{path}' as text: {first_line(err)}") from None
    if header_at is not None:
        raise DataError(f"'{path}' has a header but no data row")
    raise DataError(f"'{path}' is empty")


def _check_full(raw: pd.DataFrame, path: Path) -> None:
    """A short row or an empty cell is a broken file, not a missing value
    (which MATLAB and numpy write as NaN)."""
    empty = (raw.apply(lambda cells: cells.str.strip()) == "").to_numpy()
    if empty.any():
        row, position = (int(i[0]) for i in empty.nonzero())
        raise DataError(
            f"'{path}': data row {row + 1} has no value for "
            f"{list(PUNZO_COLUMNS)[position]} ({int(empty.sum())} empty cell(s)); "
            "a punzo file is a full table of six numbers (NaN where none)"
        )


def _separator(line: str) -> tuple[str, bool]:
    """``(sep, decimal_comma)`` for pandas, from one line of the file."""
    if ";" in line:
        return ";", "," in line
    if "," in line:
        return ",", False
    if "\t" in line:
        return "\t", False
    return r"\s+", False


def _fields(line: str) -> list[str]:
    sep, _ = _separator(line)
    parts = re.split(sep, line.strip()) if sep == r"\s+" else line.split(sep)
    return [part.strip() for part in parts]


def _check_unique_stems(paths: list[Path]) -> None:
    stems: dict[str, Path] = {}
    for path in paths:
        if path.stem in stems:
            raise DataError(
                f"'{stems[path.stem]}' and '{path}' would be the same pair "
                f"'{path.stem}': rename one"
            )
        stems[path.stem] = path
