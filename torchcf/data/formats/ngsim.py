"""Read and write NGSIM vehicle trajectories (US-101, I-80, Lankershim, Peachtree).

Two layouts are read, told apart by the first line of the file:

* the per-site original text files ``trajectories-*.txt``: no header, fields
  separated by white space, 18 columns for the freeways (:data:`FREEWAY_COLUMNS`)
  or 24 for the arterials, which add the zone, intersection, section, direction
  and movement codes after ``Lane_ID`` (:data:`ARTERIAL_COLUMNS`);
* the data.transportation.gov CSV export, or any file with a header row: the
  export has 25 columns, but only the names matter, in any order and with any
  extra columns. Names are matched ignoring case, with spaces or hyphens read
  as "_" (the export writes ``v_length``, the text files ``v_Length``) and the
  spellings ``Space_Hdwy``, ``Time_Hdwy``, ``Prec_Veh``, ``Follow_Veh``,
  ``v_Len`` and ``v_Wid`` taken as the names below. The separator is "," or
  ";" when the header has one, else a tab, else runs of white space; cells
  may be quoted.

Only ``Vehicle_ID``, ``Frame_ID`` and ``Local_Y`` are required in a file with a
header. Every other column used may be absent; each absence is noted once per
file with what it costs: no ``Global_Time`` makes the file one recording
period (run = the file stem), no ``Total_Frames`` leaves ids reused within a
period unsplit, no ``v_Vel`` / ``v_Acc`` leaves speeds / accelerations NaN (the
extraction derives them), no ``v_Length`` or ``Space_Headway`` leaves lengths
or gaps NaN, no ``Lane_ID`` gives lane "", and no ``Preceding`` gives no leader
(so no pair). A file that truly cannot be read stops with one line naming it
and the problem: a required column missing, a used column twice, a line with
a field too many (or, in the text layouts, too few: white space has no empty
cell, so fields would shift), a text cell in a numeric column or an empty id
or clock cell (with its line), or no data row. A trailing separator on the
data lines (not the header) is tolerated; pandas would otherwise take the
first column for an index and shift every value by one column.

Units and meanings (NGSIM -> :class:`~torchcf.data.trajectory.TrajectoryTable`):

=============  ==========  ===============================================
NGSIM          unit        table column
=============  ==========  ===============================================
Frame_ID       0.1 s       time = Frame_ID * 0.1 s
Local_Y        ft          position (front bumper along the section) [m]
v_Vel          ft/s        speed [m/s]
v_Acc          ft/s^2      acceleration [m/s^2]
v_Length       ft          length [m]
Lane_ID        -           lane
Preceding      -           leader ("" when 0)
Space_Headway  ft          gap = Space_Headway - the leader's v_Length [m]
                           (front-to-front minus the leader's length, read
                           from the leader's row at the same frame)
=============  ==========  ===============================================

``Global_Time`` is not used as time: Peachtree's is no Unix epoch. It tells
recording periods apart instead: ``Global_Time - 100 * Frame_ID`` [ms] is
constant within one period, and the run of a row is ``"{file stem}:{offset}"``.
Vehicle ids are reused across periods (Peachtree: 70, 1311, 1322); within one
run, an id with several ``Total_Frames`` values is split into ``"{id}#{total}"``
vehicles, and a leader reference to such an id resolves to the one that has a
row at that frame. Where a CSV export holds several ``Location`` values, the run
is ``"{file stem}:{location}:{offset}"``.

``9999.99`` is NGSIM's "no value" (documented for ``Time_Headway``); in the
columns used it becomes NaN. Rows come in any order (the export is sorted by
``Global_Y``); the table returned is sorted. What the reader finds and handles
is reported in ``TrajectoryTable.notes``.

:func:`write_ngsim` writes a :class:`~torchcf.data.pairset.PairSet` back as an
original-layout (18-column) text file in feet.
"""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from torchcf.data.formats.generic import columns_text, source_files
from torchcf.data.pairset import DataError, PairSet
from torchcf.data.trajectory import TrajectoryTable

__all__ = [
    "ARTERIAL_COLUMNS",
    "FEET",
    "FRAME_S",
    "FREEWAY_COLUMNS",
    "SENTINEL",
    "read_ngsim",
    "write_ngsim",
]

#: Feet to metres.
FEET = 0.3048
#: Duration of one NGSIM frame [s] (10 Hz).
FRAME_S = 0.1
#: NGSIM's "no value" (e.g. ``Time_Headway`` behind a standing leader).
SENTINEL = 9999.99
#: Columns of the freeway text files (US-101, I-80), in file order.
FREEWAY_COLUMNS: tuple[str, ...] = (
    "Vehicle_ID",
    "Frame_ID",
    "Total_Frames",
    "Global_Time",
    "Local_X",
    "Local_Y",
    "Global_X",
    "Global_Y",
    "v_Length",
    "v_Width",
    "v_Class",
    "v_Vel",
    "v_Acc",
    "Lane_ID",
    "Preceding",
    "Following",
    "Space_Headway",
    "Time_Headway",
)
#: Columns of the arterial text files (Lankershim, Peachtree), in file order.
ARTERIAL_COLUMNS: tuple[str, ...] = (
    *FREEWAY_COLUMNS[:14],
    "O_Zone",
    "D_Zone",
    "Int_ID",
    "Section_ID",
    "Direction",
    "Movement",
    *FREEWAY_COLUMNS[14:],
)

#: Columns without which a file cannot be read (lower case).
_REQUIRED = ("vehicle_id", "frame_id", "local_y")
#: Columns read when present, each with what its absence means (for the notes).
_OPTIONAL: dict[str, str] = {
    "global_time": "one recording period per file (run = the file stem)",
    "total_frames": "an id reused within a period is not split",
    "v_length": "length NaN and gap NaN (the gap needs the leader's length)",
    "v_vel": "speed NaN (derived from positions by the extraction)",
    "v_acc": "acceleration NaN (derived by the extraction)",
    "lane_id": "lane ''",
    "preceding": "no leader known, so no pair can be cut from this file",
    "space_headway": "gap NaN",
}
_USED = (*_REQUIRED, *_OPTIONAL)
#: Ids and the clock: whole numbers, no empty cell.
_IDS = ("vehicle_id", "frame_id", "total_frames", "global_time")
#: Used columns in feet (or ft/s, ft/s^2), where 9999.99 may stand for "none".
_FEET_COLUMNS = ("local_y", "v_length", "v_vel", "v_acc", "space_headway")
#: Columns a note lists when they hold a sentinel though they are not used.
_UNUSED_WITH_SENTINEL = ("time_headway",)
#: Other spellings of header names (normalised) -> the name used here.
_ALIASES: dict[str, str] = {
    "space_hdwy": "space_headway",
    "time_hdwy": "time_headway",
    "prec_veh": "preceding",
    "follow_veh": "following",
    "v_len": "v_length",
    "v_wid": "v_width",
}
#: Separators of files with a header, tried in this order on the first line.
_SEPARATORS = (",", ";", "\t")
#: Rows parsed at a time: bounds the memory of the full 1.5 GB export.
_CHUNK_ROWS = 1_000_000
#: The offset of :func:`write_ngsim`'s clock [ms], an I-80-like epoch.
_WRITE_EPOCH_MS = 1_110_000_000_000
#: Display names of the lower-cased columns, for notes and messages.
_NAMES: dict[str, str] = {c.lower(): c for c in (*ARTERIAL_COLUMNS, "Location")}
#: How many ids a note lists before "...".
_SHOWN_IDS = 10


def read_ngsim(source: str | os.PathLike[str]) -> TrajectoryTable:
    """Read NGSIM trajectories (a file, or a folder of them) into SI units.

    Args:
        source: an NGSIM text file or CSV export, or a folder whose ``*.txt``
            and ``*.csv`` files are all read (not recursively; a file whose
            first line is neither numbers nor a header naming Vehicle_ID, such
            as a read-me, is skipped and noted); runs of different files stay
            apart by the file stem.

    Returns:
        The table, sorted by run, vehicle and time; ``format="ngsim"``,
        ``road_frame=True`` (``Local_Y`` is the distance along the section of
        the location), and ``notes`` on periods, reused ids, sentinels,
        duplicate rows and absent leaders.

    Raises:
        DataError: a missing source or an empty folder, an empty or unparsable
            file, a header without Vehicle_ID, Frame_ID or Local_Y or with a
            used column twice, a text file with neither 18 nor 24 columns, a
            line with too many fields (too few in a text layout), a non-numeric
            cell or an empty id, frame or clock cell (with its file, column and
            line). Every message is one line that names the file.
    """
    paths = source_files(source, (".txt", ".csv"), "ngsim")
    notes: list[str] = []
    if Path(source).is_dir():
        # A folder may hold a read-me or data dictionary beside the data.
        skipped = [p for p in paths if not _looks_like_ngsim(p)]
        if len(skipped) == len(paths):
            raise DataError(
                f"folder '{source}' holds no NGSIM file (a header naming "
                f"Vehicle_ID, or a first line of numbers): {_listed(skipped)}"
            )
        if skipped:
            notes.append(
                f"skipped {len(skipped)} file(s) that are not NGSIM trajectories "
                f"(no Vehicle_ID header, no numbers on line 1): "
                f"{_listed([p.name for p in skipped])}"
            )
        paths = [p for p in paths if p not in skipped]
    stems = [p.stem for p in paths]
    frames: list[pd.DataFrame] = []
    for path in paths:
        # Two files of one stem (x.txt, x.csv) would share runs: use the name.
        label = path.stem if stems.count(path.stem) == 1 else path.name
        frame, file_notes = _read_file(path, label)
        frames.append(frame)
        notes.extend(file_notes)
    table = TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True),
        source=str(source),
        format="ngsim",
        road_frame=True,
        notes=notes,
    )
    return table.sorted()


def write_ngsim(pairs: PairSet, path: str | os.PathLike[str]) -> None:
    """Write a PairSet as an NGSIM original-layout (18-column) text file, in feet.

    Pair j becomes leader ``Vehicle_ID`` 2j+1 and follower 2j+2 in ``Lane_ID``
    j+1, at ``Frame_ID`` 1 .. T_j (masked steps are omitted). The follower's
    ``Preceding`` is the leader (``Space_Headway`` = x_lead - x_follow, front to
    front), the leader's is 0; both get ``v_Length`` = ``leader_length``, so
    :func:`read_ngsim` gives the follower a gap of x_lead - x_follow -
    leader_length. ``Global_Time`` = 1.11e12 + 100 * Frame_ID [ms] (one run),
    ``Total_Frames`` = T_j, the leader's ``Following`` = the follower; the other
    columns are 0. Numbers are written with 17 significant digits, so reading
    them back gives the pairs' values to within float64 rounding.

    Args:
        pairs: the pairs, in SI units, ``dt`` = 0.1 s.
        path: the file to write (overwritten).

    Raises:
        DataError: ``pairs.dt`` is not 0.1 s (NGSIM frames are 0.1 s).
    """
    if abs(pairs.dt - FRAME_S) > 1e-9:
        raise DataError(
            f"NGSIM frames are {FRAME_S} s but the pair set "
            f"'{pairs.name}' has dt = {pairs.dt} s; cannot write '{path}'"
        )
    series = {f: t.detach().cpu().double().numpy() for f, t in pairs.series().items()}
    mask = pairs.mask.detach().cpu().numpy()
    length_ft = pairs.leader_length / FEET
    blocks = []
    for j in range(pairs.n_pairs):
        n_frames = int(mask[:, j].sum())  # mask is a prefix
        rows = slice(0, n_frames)
        leader, follower = 2 * j + 1, 2 * j + 2
        spacing = series["x_lead"][rows, j] - series["x_follow"][rows, j]
        for vehicle, kind, preceding, following, headway in (
            (leader, "lead", 0, follower, np.zeros(n_frames)),
            (follower, "follow", leader, 0, spacing / FEET),
        ):
            block = np.zeros((n_frames, len(FREEWAY_COLUMNS)))
            frame_id = np.arange(1, n_frames + 1)
            block[:, 0] = vehicle
            block[:, 1] = frame_id
            block[:, 2] = n_frames
            block[:, 3] = _WRITE_EPOCH_MS + 100 * frame_id
            block[:, 5] = series[f"x_{kind}"][rows, j] / FEET
            block[:, 8] = length_ft
            block[:, 11] = series[f"v_{kind}"][rows, j] / FEET
            block[:, 12] = series[f"a_{kind}"][rows, j] / FEET
            block[:, 13] = j + 1
            block[:, 14] = preceding
            block[:, 15] = following
            block[:, 16] = headway
            blocks.append(block)
    table = np.concatenate(blocks) if blocks else np.zeros((0, len(FREEWAY_COLUMNS)))
    # Ids and the clock are integers (Global_Time > 2**31); the rest round-trips.
    fmt = ["%d"] * 4 + ["%.17g"] * 9 + ["%d"] * 3 + ["%.17g"] * 2
    np.savetxt(Path(path), table, fmt=fmt, delimiter=" ")


# ---------------------------------------------------------------------- reading
def _read_file(path: Path, label: str) -> tuple[pd.DataFrame, list[str]]:
    """One file as canonical table columns (SI) and its notes."""
    raw, first_line = _read_raw(path)
    name = path.name
    notes: list[str] = []

    absent = [c for c in _OPTIONAL if c not in raw.columns]
    if absent:
        notes.append(
            f"{name}: no column "
            + "; no ".join(f"{_NAMES[c]}: {_OPTIONAL[c]}" for c in absent)
        )
    ids = {c: _integers(raw[c], c, path, first_line) for c in _IDS if c in raw.columns}
    run = _run_labels(raw, ids, label)
    runs, counts = np.unique(run, return_counts=True)
    by = "Global_Time - 100*Frame_ID" if "global_time" in ids else "no Global_Time"
    notes.append(
        f"{name}: {len(runs)} recording period(s) ({by}): "
        + ", ".join(f"{r} ({c} rows)" for r, c in zip(runs, counts, strict=True))
    )

    values = {
        c: raw[c].to_numpy(dtype=np.float64, copy=True)
        if c in raw.columns
        else np.full(len(raw), np.nan)
        for c in _FEET_COLUMNS
    }
    found = {c: int(_is_sentinel(v).sum()) for c, v in values.items()}
    for v in values.values():
        v[_is_sentinel(v)] = np.nan
    if any(found.values()):
        notes.append(
            f"{name}: {SENTINEL} ('no value') replaced by NaN in "
            + ", ".join(f"{_NAMES[c]} ({n} rows)" for c, n in found.items() if n)
        )
    for column in _UNUSED_WITH_SENTINEL:
        if column in raw.columns:
            n = int(_is_sentinel(pd.to_numeric(raw[column], errors="coerce")).sum())
            if n:
                notes.append(
                    f"{name}: {_NAMES.get(column, column)} holds {SENTINEL} in "
                    f"{n} rows (column not used)"
                )

    vehicle, split_note = _vehicle_labels(
        run, ids["vehicle_id"], ids.get("total_frames"), name
    )
    notes.extend(split_note)
    notes.extend(_reused_note(run, ids["vehicle_id"], name))

    frame = pd.DataFrame(
        {
            "run": run,
            "vehicle": vehicle,
            "frame_id": ids["frame_id"],
            "time": ids["frame_id"] * FRAME_S,
            "position": values["local_y"] * FEET,
            "speed": values["v_vel"] * FEET,
            "acceleration": values["v_acc"] * FEET,
            "lane": _lanes(raw),
            "length": values["v_length"] * FEET,
            "headway": values["space_headway"] * FEET,
            "preceding": _ids_or_zero(raw["preceding"])
            if "preceding" in raw.columns
            else np.zeros(len(raw), dtype=np.int64),
        }
    )
    duplicated = frame.duplicated(["run", "vehicle", "frame_id"])
    if duplicated.any():
        notes.append(
            f"{name}: {int(duplicated.sum())} row(s) repeat a vehicle and frame "
            "already read; the first is kept"
        )
        frame = frame[~duplicated.to_numpy()].reset_index(drop=True)

    frame["leader"] = _leader_labels(frame)
    gap, leader_notes = _gaps(frame, name)
    frame["gap"] = gap
    notes.extend(leader_notes)
    return frame.drop(columns=["frame_id", "headway", "preceding"]), notes


def _read_raw(path: Path) -> tuple[pd.DataFrame, int]:
    """The used columns of one file, lower-cased, and the line of its first row.

    Columns absent from a file with a header are absent from the frame too;
    the text layouts have them all.

    Raises:
        DataError: no required column, a used column twice, a text file with
            neither 18 nor 24 fields, a line with a field too many (or, in a
            text layout, too few), or a cell that is not a number.
    """
    first = _first_line(path)
    has_header = not _is_number(re.split(r"[,;\s]", first, maxsplit=1)[0])
    sep = _separator(first, has_header)
    fields = _header_fields(first, sep)
    if has_header:
        names = _header_names(fields, path)
        wanted = [c for c in names if c in (*_USED, "location", *_UNUSED_WITH_SENTINEL)]
    else:
        layouts = {len(FREEWAY_COLUMNS): FREEWAY_COLUMNS, 24: ARTERIAL_COLUMNS}
        if len(fields) not in layouts:
            raise DataError(
                f"NGSIM file '{path}' has {len(fields)} fields on line 1, expected "
                f"{len(FREEWAY_COLUMNS)} (freeway) or 24 (arterial) without header"
            )
        names = [c.lower() for c in layouts[len(fields)]]
        wanted = [c for c in names if c in (*_USED, *_UNUSED_WITH_SENTINEL)]
    first_line = 2 if has_header else 1  # messages count the header line
    raw = _parse(path, sep, has_header, names, wanted, first_line)
    if len(raw) == 0:
        raise DataError(f"NGSIM file '{path}' has no data row")
    for column in _USED:
        if column in raw.columns:
            raw[column] = _numbers(raw[column], column, path, first_line)
    return raw, first_line


def _looks_like_ngsim(path: Path) -> bool:
    """Whether line 1 is numbers or a header that names Vehicle_ID (folders)."""
    try:
        first = _first_line(path)
    except DataError:
        return False
    token = re.split(r"[,;\s]", first, maxsplit=1)[0]
    if _is_number(token):
        return True
    fields = _header_fields(first, _separator(first, has_header=True))
    return "vehicle_id" in (_column_key(f) for f in fields)


def _separator(first: str, has_header: bool) -> str:
    """The field separator: "," or ";" when the first line has one, a tab in a
    file with a header (a spreadsheet export may leave cells empty), else runs
    of white space (the text layouts pad their columns with spaces or tabs)."""
    for sep in _SEPARATORS:
        if sep in first and (sep != "\t" or has_header):
            return sep
    return r"\s+"


def _first_line(path: Path) -> str:
    """The first non-blank line, stripped.

    Raises:
        DataError: the file cannot be read, is not UTF-8 text, or is empty.
    """
    try:
        with path.open(encoding="utf-8-sig") as fh:
            for line in fh:
                if "\x00" in line:
                    raise DataError(f"NGSIM file '{path}' is not text (NUL bytes)")
                if line.strip():
                    return line.strip()
    except UnicodeDecodeError as err:
        raise DataError(f"NGSIM file '{path}' is not UTF-8 text ({err})") from None
    except OSError as err:
        raise DataError(f"cannot read NGSIM file '{path}': {err.strerror}") from None
    raise DataError(f"NGSIM file '{path}' is empty")


def _header_fields(line: str, sep: str) -> list[str]:
    """The cells of the first line, unquoted and stripped."""
    if sep == r"\s+":
        cells = line.split()
    else:
        cells = next(csv.reader([line], delimiter=sep))
    return [c.strip().strip('"').strip("'").strip() for c in cells]


def _column_key(field: str) -> str:
    """A header cell as a name of this reader: lower case, spaces and hyphens
    as "_", aliases (:data:`_ALIASES`) mapped."""
    key = re.sub(r"[\s\-]+", "_", field.strip().lower())
    return _ALIASES.get(key, key)


def _header_names(fields: list[str], path: Path) -> list[str]:
    """Header cells as the reader's lower-case names (spaces and aliases mapped).

    Raises:
        DataError: a required column is missing, or a used one appears twice.
    """
    names = [_column_key(field) for field in fields]
    missing = [_NAMES[c] for c in _REQUIRED if c not in names]
    if missing:
        raise DataError(
            f"NGSIM file '{path}' lacks the column(s) {', '.join(missing)}; "
            f"it has: {columns_text(fields)}"
        )
    twice = sorted({c for c in names if c in _USED and names.count(c) > 1})
    if twice:
        raise DataError(
            f"NGSIM file '{path}' has the column(s) "
            f"{', '.join(_NAMES[c] for c in twice)} twice (aliases counted)"
        )
    # Unused names may repeat, and a header ending in a separator has an empty
    # one: pandas wants them unique.
    return [
        n if n and (n in _USED or names.count(n) == 1) else f"_unread_{j}"
        for j, n in enumerate(names)
    ]


def _parse(
    path: Path,
    sep: str,
    has_header: bool,
    names: list[str],
    wanted: list[str],
    first_line: int,
) -> pd.DataFrame:
    """The ``wanted`` columns of every data row, read in chunks.

    Every column is parsed, not only the wanted ones: with ``usecols`` pandas
    silently drops a line's extra fields, and a field inserted mid-line would
    shift the values after it. ``index_col=False`` keeps a trailing separator
    on the data lines (but not the header) from turning the first column into
    the index, which would shift every column by one.
    """
    try:
        chunks = pd.read_csv(
            path,
            sep=sep,
            header=0 if has_header else None,
            names=names,
            index_col=False,
            encoding="utf-8-sig",
            skipinitialspace=True,
            chunksize=_CHUNK_ROWS,
        )
        # White space has no empty cell: a NaN in the last field is a short line.
        last = names[-1] if sep == r"\s+" else None
        keep = list(dict.fromkeys([*wanted, last] if last else wanted))
        parts = [chunk[keep] for chunk in chunks]
    except (ValueError, UnicodeDecodeError) as err:  # includes parser errors
        text = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise DataError(f"cannot read NGSIM file '{path}': {text}") from None
    if not parts:
        return pd.DataFrame(columns=wanted)
    raw = pd.concat(parts, ignore_index=True)
    if last is not None:
        short = raw[last].isna().to_numpy()
        if short.any():
            row = int(np.flatnonzero(short)[0])
            raise DataError(
                f"NGSIM file '{path}': line {row + first_line} has fewer than "
                f"{len(names)} fields"
            )
    return raw[wanted]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _numbers(series: pd.Series, column: str, path: Path, first_line: int) -> pd.Series:
    """``series`` as float64; a text cell raises with its line in the file."""
    values = pd.to_numeric(series, errors="coerce")
    bad = series.notna().to_numpy() & values.isna().to_numpy()
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"NGSIM file '{path}': column {_NAMES[column]} holds "
            f"{str(series.iloc[row])[:40]!r} on line {row + first_line}, not a number"
        )
    return values.astype(np.float64)


def _integers(
    series: pd.Series, column: str, path: Path, first_line: int
) -> np.ndarray:
    """An id or clock column as int64; an empty cell raises with its line."""
    values = series.to_numpy(dtype=np.float64)
    empty = ~np.isfinite(values)
    if empty.any():
        row = int(np.flatnonzero(empty)[0])
        raise DataError(
            f"NGSIM file '{path}': column {_NAMES[column]} is empty on line "
            f"{row + first_line}"
        )
    # Rounding, not truncation: a re-written export may hold 1163368300.0000002.
    return np.rint(values).astype(np.int64)


def _ids_or_zero(series: pd.Series) -> np.ndarray:
    """An id column where empty means 0 (none), as int64."""
    values = series.to_numpy(dtype=np.float64)
    return np.rint(np.where(np.isfinite(values), values, 0.0)).astype(np.int64)


def _is_sentinel(values) -> np.ndarray:
    # The export was re-written by pandas in places: 9999.990000000002 counts too.
    return np.abs(np.asarray(values, dtype=np.float64) - SENTINEL) < 1e-6


def _id_text(value: float) -> str:
    return str(int(round(value))) if np.isfinite(value) else ""


def _run_labels(
    raw: pd.DataFrame, ids: dict[str, np.ndarray], label: str
) -> np.ndarray:
    """(rows,) run of each row: ``label[:location]:offset`` (module docstring).

    Without Global_Time the whole file (or location) is one run, ``label``.
    """
    run = pd.Series(label, index=raw.index, dtype=object)
    if "location" in raw.columns and raw["location"].nunique() > 1:
        run = run + ":" + raw["location"].astype(str).str.strip()
    if "global_time" in ids:
        offset = ids["global_time"] - 100 * ids["frame_id"]  # (rows,) [ms]
        run = run + ":" + pd.Series(offset, index=raw.index).astype(str)
    return run.to_numpy(dtype=object)


def _lanes(raw: pd.DataFrame) -> list[str]:
    """(rows,) lane ids as text, "" where the cell or the column is missing."""
    if "lane_id" not in raw.columns:
        return [""] * len(raw)
    return [_id_text(v) for v in raw["lane_id"].to_numpy(dtype=np.float64)]


def _vehicle_labels(
    run: np.ndarray,
    vehicle_id: np.ndarray,
    total_frames: np.ndarray | None,
    name: str,
) -> tuple[np.ndarray, list[str]]:
    """Vehicle labels: the id, or ``id#total`` where one run reuses the id.

    Without Total_Frames (``None``) ids are not split.
    """
    if total_frames is None:
        return vehicle_id.astype(str).astype(object), []
    keys = pd.DataFrame({"run": run, "id": vehicle_id, "total": total_frames})
    n_totals = keys.groupby(["run", "id"])["total"].transform("nunique").to_numpy()
    labels = vehicle_id.astype(str).astype(object)
    split = n_totals > 1
    if not split.any():
        return labels, []
    labels[split] = [
        f"{i}#{t}" for i, t in zip(vehicle_id[split], total_frames[split], strict=True)
    ]
    reused = keys[split].groupby(["run", "id"])["total"].unique()
    listed = "; ".join(
        f"{r} id {i} ({', '.join(map(str, sorted(t)))})" for (r, i), t in reused.items()
    )
    return labels, [
        f"{name}: {len(reused)} Vehicle_ID(s) with several Total_Frames within one "
        f"period, split as ID#Total_Frames: {listed}"
    ]


def _reused_note(run: np.ndarray, vehicle_id: np.ndarray, name: str) -> list[str]:
    """A note on ids that denote a vehicle in more than one period."""
    per_id = pd.DataFrame({"run": run, "id": vehicle_id}).groupby("id")["run"]
    n_runs = per_id.nunique()
    reused = sorted(int(i) for i in n_runs[n_runs > 1].index)
    if not reused:
        return []
    return [
        f"{name}: {len(reused)} Vehicle_ID(s) reused across periods, one vehicle "
        f"per run: {_listed(reused)}"
    ]


def _leader_labels(frame: pd.DataFrame) -> np.ndarray:
    """The leader's vehicle label for each row ("" when Preceding is 0).

    A split id resolves to the vehicle having a row at that frame; if none has,
    to the one whose frames lie nearest.
    """
    labels = np.where(
        frame["preceding"].to_numpy() > 0,
        frame["preceding"].astype(str).to_numpy(),
        "",
    ).astype(object)
    split = frame[frame["vehicle"].str.contains("#", regex=False)]
    if split.empty:
        return labels
    split_id = split["vehicle"].str.split("#").str[0].astype(np.int64)
    candidates = split.assign(id=split_id.to_numpy())
    spans = candidates.groupby(["run", "id", "vehicle"])["frame_id"].agg(["min", "max"])
    present = set(
        zip(
            candidates["run"],
            candidates["vehicle"],
            candidates["frame_id"],
            strict=True,
        )
    )
    refer = frame.set_index(["run", "preceding"]).index.isin(spans.droplevel(2).index)
    for row in np.flatnonzero(refer):
        run, preceding = frame.at[row, "run"], int(frame.at[row, "preceding"])
        at = int(frame.at[row, "frame_id"])
        options = spans.loc[(run, preceding)]
        have = [v for v in options.index if (run, v, at) in present]
        if have:
            labels[row] = have[0]
        else:
            distance = np.maximum(options["min"] - at, at - options["max"])
            labels[row] = distance.idxmin()
    return labels


def _gaps(frame: pd.DataFrame, name: str) -> tuple[np.ndarray, list[str]]:
    """Gap = Space_Headway - the leader's length at the same frame, and notes."""
    lengths = frame[["run", "vehicle", "frame_id", "length"]].rename(
        columns={"vehicle": "leader", "length": "leader_length"}
    )
    merged = frame[["run", "leader", "frame_id"]].merge(
        lengths, on=["run", "leader", "frame_id"], how="left", validate="many_to_one"
    )
    headway = frame["headway"].to_numpy()
    has_leader = frame["leader"].to_numpy() != ""
    leader_length = merged["leader_length"].to_numpy()
    # An absent leader row (or length) leaves NaN, which the subtraction keeps.
    gap = np.where(has_leader & (headway > 0), headway - leader_length, np.nan)

    vehicles = pd.MultiIndex.from_frame(frame[["run", "vehicle"]])
    leaders = pd.MultiIndex.from_frame(frame[["run", "leader"]])
    absent_rows = has_leader & ~leaders.isin(vehicles)
    notes = []
    if absent_rows.any():
        absent = frame.loc[absent_rows, ["run", "leader"]].drop_duplicates()
        by_run = absent.groupby("run")["leader"]
        notes.append(
            f"{name}: {len(absent)} leader(s) referenced but absent from the file "
            f"(gap NaN on their followers' {int(absent_rows.sum())} rows): "
            + "; ".join(
                f"{run} ids {_listed(sorted(ids, key=_id_key))}" for run, ids in by_run
            )
        )
    zero = has_leader & ~(headway > 0)
    if zero.any():
        notes.append(
            f"{name}: {int(zero.sum())} row(s) name a leader but have no "
            "Space_Headway (0 or none): gap NaN"
        )
    elsewhere = has_leader & (headway > 0) & np.isnan(leader_length) & ~absent_rows
    if elsewhere.any():
        notes.append(
            f"{name}: {int(elsewhere.sum())} row(s) whose leader is in the file but "
            "has no row (or no length) at that frame: gap NaN"
        )
    return gap, notes


def _id_key(label: str) -> tuple[int, str]:
    """Sort ids by number ("70" before "112"), then by the rest ("#628")."""
    number, _, rest = label.partition("#")
    return (int(number) if number.isdigit() else -1, rest)


def _listed(items: list) -> str:
    shown = ", ".join(str(i) for i in items[:_SHOWN_IDS])
    return shown + (
        f", ... ({len(items) - _SHOWN_IDS} more)" if len(items) > _SHOWN_IDS else ""
    )
