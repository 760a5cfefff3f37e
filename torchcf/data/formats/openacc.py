"""Read OpenACC (JRC) platoon files into a trajectory table.

OpenACC (Makridis et al., Transportation Research Part C 125, 2021, 103047) records
platoons of 2-5 cars on public roads and test tracks: vehicle 1 is driven by hand,
vehicle K+1 follows vehicle K, most followers with their ACC on. One CSV file is
one continuous recording, sampled at 10 Hz (GNSS at 3-5 Hz or Ublox 9, cubic-spline
interpolated by JRC, not filtered). :func:`read_openacc` turns a file or a
folder of them into a :class:`~torchcf.data.trajectory.TrajectoryTable`.

File layout (CRLF, comma-separated)::

    Date,DD,MM,YYYY                      <- metadata block, rows padded with
    Vehicle_order,veh1,veh2,...             trailing commas or not
    Number_of_vehicles,N
    ACC,0|1|2|<blank>
    Distance_setting,min|shortest|...
    Time,Speed1,Lat1,...,IVS1,...,Driver1,...   <- header
    ...                                         <- data, one row per time step

The metadata block is the leading rows whose first cell is one of those keys (a
file may lack ACC or Distance_setting); the next row is the header. Columns are
found by name and vehicle index K, never by position, because they differ between
files. Those used, in SI units:

=========  ====  ==========================================================
column     unit  meaning
=========  ====  ==========================================================
Time       s     common clock of all vehicles (not starting at 0)
SpeedK     m/s   speed of vehicle K (GNSS Doppler)
IVSK       m     bumper-to-bumper spacing from vehicle K's rear to vehicle
                 K+1's front (GNSS, bumper-corrected by JRC): the gap of
                 follower K+1
DriverK    -     "Human" or "ACC"; missing for some vehicles
=========  ====  ==========================================================

Lat/Lon (rad), Alt, E/N/U (m, local ENU) and VE/VN/VU are not used, see below.

Table rows: vehicle id "K", leader of vehicle K+1 "K" (vehicle 1 has none), speed
= SpeedK, gap of K+1 = IVSK, mode = DriverK ("" where the column is missing),
lane "" (the platoon tests stay in one lane, so the leader is always the vehicle
ahead in the file's order), acceleration NaN (OpenACC has none; derive it with
:func:`torchcf.data.derive.fill_derivatives`). A folder is read recursively: every
``*.csv`` whose first cell is "Date" is one run, named by its path relative to the
folder without the suffix; other CSV files (the vehicle specifications) are
skipped and listed in the notes.

Positions (one road frame per run, along the route):

    x_1(t_0) = 0
    x_1(t_i) = x_1(t_{i-1}) + (v_1(t_{i-1}) + v_1(t_i)) / 2 * (t_i - t_{i-1})
    x_{K+1}(t) = x_K(t) - length - IVS_K(t)

Only the platoon leader's position comes from odometry; every follower is placed
behind its leader by the recorded spacing, so x_K - x_{K+1} - length equals IVS_K
exactly and the gaps a car-following model sees are JRC's own. Why not the ENU
positions: they are 2-D antenna positions, not along the lane (a curve would need
a route to project on), and the antenna-to-bumper offsets are published nowhere
but inside IVS. In the four sample files the ENU distance between two antennas
minus IVS is a constant per file (3.7-6.7 m): IVS is the GNSS chord distance with
JRC's bumper correction, so it carries every GNSS jump too (Vicolungo part3:
IVS4 falls from 118 m to 48 m within 0.5 s at t0 + 5 s while the Doppler speeds
say the gap grows), and such stretches are for a quality filter to drop.

Consequences worth knowing: the leader's odometry drifts (a speed bias of 1 %
is 3 m per 10 s at 30 m/s), but that drift moves the whole platoon alike and
changes no spacing. A follower's position is not the integral of its own
Doppler speed: IVS(t) - IVS(t0) and the integral of v_leader - v_follower part
by up to 1.5-18 m over 40 s in the samples (relative speed biases of about
0.1 m/s), so a position derived from it differs from the recorded speed by that
much. OpenACC gives no vehicle length, so ``vehicle_length`` is used for every
car; since a follower is placed exactly ``length + IVS`` behind its leader's
front, the length cancels in every spacing x_K - x_{K+1} - length and only
shifts the followers' absolute positions.

Missing columns: a file names the vehicles it has (ZalaZONE files skip some).
Without IVSK, vehicle K+1 has no recorded gap to vehicle K: it gets no leader
and its own odometer (a chain of its own, starting at 0); a vehicle with neither
SpeedK nor IVS(K-1) is not in the file. Both are noted.

Missing values: where Speed1 is NaN the leader's position is NaN; the odometer
steps over the hole with one trapezoid between its finite neighbours (speed
linear across it), so one hole does not shift or poison everything after it
(and x_1 = 0 at the first sample with a speed).
A follower's position is NaN where its leader's position or the IVS is NaN.
Rows without a time are dropped. Each case is counted in the notes.
"""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from torchcf.data.pairset import DataError, positive_float
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["METADATA_KEYS", "read_openacc"]

#: First cells of the metadata rows above the header, lower case.
METADATA_KEYS: tuple[str, ...] = (
    "date",
    "vehicle_order",
    "number_of_vehicles",
    "acc",
    "distance_setting",
)
#: Per-vehicle columns whose index K must not exceed the number of vehicles.
_PER_VEHICLE = ("speed", "ivs", "driver")
#: Cell texts that mean "no value" (lower case, stripped).
_MISSING = ("", "nan", "na", "n/a", "null")
_SUFFIXED = re.compile(r"([A-Za-z_]+?)(\d+)")


class _Metadata(NamedTuple):
    names: list[str]  # Vehicle_order, one per vehicle as far as given
    n_vehicles: int
    acc: str  # the ACC field, "" blank
    distance: str  # the Distance_setting field, "" blank
    n_rows: int  # rows of the block; the header is the next row


def read_openacc(
    source: str | os.PathLike[str], *, vehicle_length: float = 5.0
) -> TrajectoryTable:
    """Read an OpenACC platoon file, or every platoon file below a folder.

    Args:
        source: a platoon CSV file, or a folder searched recursively for them.
        vehicle_length: length [m] given to every vehicle, > 0 (OpenACC has
            none; it changes no spacing, see the module docstring).

    Returns:
        A table with ``format="openacc"``, one run per file, and ``road_frame``
        True for one file (its positions are distances along one route) and
        False for several (each file is another road, its positions start at 0);
        vehicles "1".."N", vehicle K+1 led by vehicle K, positions from the
        leader's odometry and the recorded spacings. The notes give the vehicle
        names per run and every missing value or skipped file.

    Raises:
        DataError: no such path, a folder without platoon files, a file whose
            metadata block is not OpenACC's ("not an OpenACC file: ..."), a
            missing Time or Speed1 column, a cell
            that is not a number, or times that do not increase.
    """
    path = Path(source)
    length = positive_float(vehicle_length, "vehicle_length", "m")
    skipped: list[str] = []
    if path.is_dir():
        runs = []
        for file in sorted(path.rglob("*.csv")):
            name = file.relative_to(path)
            if _first_cell(file) == "Date":
                runs.append((name.with_suffix("").as_posix(), file))
            else:
                skipped.append(name.as_posix())
        if not runs:
            raise DataError(
                f"no OpenACC platoon file (a .csv whose first cell is 'Date') "
                f"under '{path}'"
            )
    elif path.is_file():
        runs = [(path.stem, path)]
    else:
        raise DataError(f"no such file or folder: '{path}'")

    frames: list[pd.DataFrame] = []
    notes: list[str] = []
    for run, file in runs:
        frame, run_notes = _read_file(file, run, length)
        frames.append(frame)
        notes.extend(run_notes)
    notes.append(
        f"positions: vehicle 1 by integrating Speed1 over Time (trapezoids, 0 at "
        f"each run's first sample); vehicle K+1 at x_K - {length:g} m - IVSK, so "
        f"every gap is the recorded IVS; length {length:g} m for every vehicle "
        f"(OpenACC gives none)"
    )
    notes.append(
        "acceleration: none in OpenACC (NaN; derive it with "
        "torchcf.data.derive.fill_derivatives); lane: '' (one-lane platoon tests)"
    )
    if skipped:
        notes.append(
            f"skipped {len(skipped)} csv file(s) that are not platoon files "
            f"(first cell not 'Date'): {', '.join(skipped)}"
        )
    return TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True),
        source=str(path),
        format="openacc",
        road_frame=len(runs) == 1,
        notes=notes,
    )


def _first_cell(path: Path) -> str:
    """The first cell of a file's first line, "" when it cannot be read as text."""
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            line = fh.readline()
    except (OSError, UnicodeDecodeError):
        return ""
    return line.split(",", 1)[0].strip()


def _read_file(path: Path, run: str, length: float) -> tuple[pd.DataFrame, list[str]]:
    """One platoon file as table rows (vehicle after vehicle) and its notes."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise DataError(f"'{path}' is not UTF-8 text ({err})") from None
    rows = [
        [cell.strip() for cell in row]
        for row in csv.reader(io.StringIO(text, newline=""))
    ]
    meta = _metadata(rows, path)
    header_row = meta.n_rows  # 0-based index of the header line
    if header_row >= len(rows):
        raise DataError(f"'{path}' has no header row after its metadata block")
    columns = _columns(rows[header_row], meta.n_vehicles, path)
    # Blank lines are formatting; file_rows keeps the 1-based line numbers.
    data = [
        (i + 1, row)
        for i, row in enumerate(rows[header_row + 1 :], start=header_row + 1)
        if any(row)
    ]
    if not data:
        raise DataError(f"'{path}' has no data row")
    width = len(rows[header_row])
    for line, row in data:
        if any(row[width:]):
            raise DataError(
                f"'{path}' row {line} has {len(row)} cells but the header has {width}"
            )
    file_rows = np.array([line for line, _ in data])

    def cells(column: str) -> list[str]:
        j = columns[column.lower()]
        return [row[j] if j < len(row) else "" for _, row in data]

    n = meta.n_vehicles
    time = _numbers(cells("Time"), "Time", path, file_rows)
    speed = [
        _numbers(cells(f"Speed{k}"), f"Speed{k}", path, file_rows)
        if f"speed{k}" in columns
        else np.full(time.size, np.nan)
        for k in range(1, n + 1)
    ]
    # A missing IVSK breaks the chain: vehicle K+1 has no recorded gap to K.
    ivs = [
        _numbers(cells(f"IVS{k}"), f"IVS{k}", path, file_rows)
        if f"ivs{k}" in columns
        else np.full(time.size, np.nan)
        for k in range(1, n)
    ]
    mode = [
        np.array(cells(f"Driver{k}"), dtype=object)
        if f"driver{k}" in columns
        else np.full(time.size, "", dtype=object)
        for k in range(1, n + 1)
    ]
    notes: list[str] = []
    keep = np.isfinite(time)
    if not keep.all():
        notes.append(f"run {run}: dropped {int((~keep).sum())} row(s) without a Time")
        if not keep.any():
            raise DataError(f"'{path}' has no data row with a Time")
        time, file_rows = time[keep], file_rows[keep]
        speed = [values[keep] for values in speed]
        ivs = [values[keep] for values in ivs]
        mode = [values[keep] for values in mode]
    steps = np.diff(time)
    if (steps <= 0).any():
        bad = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DataError(
            f"'{path}': Time does not increase at row {file_rows[bad]} "
            f"({time[bad - 1]} then {time[bad]})"
        )

    linked = [True] + [f"ivs{k}" in columns for k in range(1, n)]  # K led by K-1
    position = [_odometer(time, speed[0])]
    for k in range(1, n):
        position.append(
            position[k - 1] - length - ivs[k - 1]
            if linked[k]
            else _odometer(time, speed[k])  # a chain of its own, from 0
        )

    frames = []
    for k in range(n):
        if not linked[k] and f"speed{k + 1}" not in columns:
            continue  # named by no column: not in this file
        frames.append(
            pd.DataFrame(
                {
                    "run": run,
                    "vehicle": str(k + 1),
                    "time": time,
                    "position": position[k],
                    "speed": speed[k],
                    "acceleration": np.nan,
                    "leader": str(k) if linked[k] and k else "",
                    "lane": "",
                    "length": length,
                    "gap": ivs[k - 1] if linked[k] and k else np.nan,
                    "mode": mode[k],
                }
            )
        )
    notes = [
        _describe(run, meta, time),
        *notes,
        *_quality_notes(run, meta, columns, time, speed, ivs, position, mode),
    ]
    return pd.concat(frames, ignore_index=True), notes


def _metadata(rows: list[list[str]], path: Path) -> _Metadata:
    """Parse the block of key rows above the header.

    Raises:
        DataError: "not an OpenACC file" when the first cell is not "Date", or
            Vehicle_order or a positive Number_of_vehicles is missing.
    """
    first = rows[0][0] if rows and rows[0] else ""
    if first != "Date":
        raise DataError(
            f"not an OpenACC file: '{path}' (first cell {first[:40]!r}, "
            f"expected 'Date')"
        )
    fields: dict[str, list[str]] = {}
    n_rows = 0
    for row in rows:
        key = row[0].lower() if row else ""
        if key not in METADATA_KEYS:
            break
        fields[key] = [cell for cell in row[1:] if cell]
        n_rows += 1
    count = fields.get("number_of_vehicles", [])
    if "vehicle_order" not in fields or not count or not count[0].isdigit():
        raise DataError(
            f"not an OpenACC file: '{path}' (its metadata block lacks "
            f"Vehicle_order or a Number_of_vehicles)"
        )
    n_vehicles = int(count[0])
    if n_vehicles < 1:
        raise DataError(f"not an OpenACC file: '{path}' (Number_of_vehicles is 0)")
    return _Metadata(
        names=fields["vehicle_order"],
        n_vehicles=n_vehicles,
        acc=" ".join(fields.get("acc", [])),
        distance=" ".join(fields.get("distance_setting", [])),
        n_rows=n_rows,
    )


def _columns(header: list[str], n_vehicles: int, path: Path) -> dict[str, int]:
    """Lower-case column name -> index, checked against the vehicle count.

    Raises:
        DataError: a duplicated name, a missing Time or Speed1, or
            a per-vehicle column of a vehicle beyond Number_of_vehicles.
    """
    columns: dict[str, int] = {}
    for j, name in enumerate(header):
        if not name:
            continue  # trailing commas pad the header too
        key = name.lower()
        if key in columns:
            raise DataError(f"'{path}' has the column '{name}' twice")
        columns[key] = j
        match = _SUFFIXED.fullmatch(key)
        if match and match.group(1) in _PER_VEHICLE:
            k = int(match.group(2))
            # IVSK belongs to the couple (K, K+1), so K < N.
            last = n_vehicles - 1 if match.group(1) == "ivs" else n_vehicles
            if not 1 <= k <= last:
                raise DataError(
                    f"'{path}' has the column '{name}' but Number_of_vehicles is "
                    f"{n_vehicles}"
                )
    required = ["Time", "Speed1"]
    for name in required:
        if name.lower() not in columns:
            raise DataError(f"'{path}' lacks the column '{name}'")
    return columns


def _numbers(
    texts: list[str], column: str, path: Path, file_rows: np.ndarray
) -> np.ndarray:
    """Cells as float64, missing and infinite ones NaN.

    Raises:
        DataError: a cell holds text that is not a number, named by its row.
    """
    series = pd.Series(texts, dtype=object)
    values = pd.to_numeric(series, errors="coerce").to_numpy(np.float64, copy=True)
    missing = series.str.lower().isin(_MISSING).to_numpy()
    bad = np.isnan(values) & ~missing
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"'{path}': column '{column}' holds {texts[i][:40]!r} at row "
            f"{file_rows[i]}, not a number"
        )
    values[~np.isfinite(values)] = np.nan
    return values


def _odometer(time: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Cumulative trapezoid integral of ``speed`` [m/s] over ``time`` [s], from 0.

    NaN where the speed is NaN; a hole is bridged by one trapezoid between its
    finite neighbours, so the positions after it stay on the same frame.
    """
    out = np.full(time.shape, np.nan)
    finite = np.flatnonzero(np.isfinite(speed))
    if finite.size == 0:
        return out
    t, v = time[finite], speed[finite]
    steps = 0.5 * (v[1:] + v[:-1]) * np.diff(t)
    out[finite] = np.concatenate(([0.0], np.cumsum(steps)))
    return out


def _describe(run: str, meta: _Metadata, time: np.ndarray) -> str:
    """The run's vehicles by name, its span and its metadata, in one line."""
    names = [
        f"{k}={meta.names[k - 1] if k <= len(meta.names) else '?'}"
        for k in range(1, meta.n_vehicles + 1)
    ]
    step = float(np.median(np.diff(time))) if time.size > 1 else float("nan")
    return (
        f"run {run}: vehicles {', '.join(names)}; {time.size} rows every "
        f"{step:.3g} s, t = {time[0]:.1f}-{time[-1]:.1f} s; ACC "
        f"{meta.acc or 'blank'}, distance setting {meta.distance or 'blank'}"
    )


def _quality_notes(
    run: str,
    meta: _Metadata,
    columns: dict[str, int],
    time: np.ndarray,
    speed: list[np.ndarray],
    ivs: list[np.ndarray],
    position: list[np.ndarray],
    mode: list[np.ndarray],
) -> list[str]:
    """Notes on what is missing or odd in one run (nothing when all is clean)."""
    notes = []
    n = meta.n_vehicles
    if len(meta.names) != n:
        notes.append(
            f"run {run}: Vehicle_order names {len(meta.names)} vehicle(s) but "
            f"Number_of_vehicles is {n}"
        )
    no_speed = [
        str(k)
        for k in range(2, n + 1)
        if f"speed{k}" not in columns and f"ivs{k - 1}" in columns
    ]
    if no_speed:
        notes.append(
            f"run {run}: no Speed column for vehicle(s) {', '.join(no_speed)}: "
            f"speed NaN"
        )
    unlinked = [k for k in range(1, n) if f"ivs{k}" not in columns]
    for k in unlinked:
        if f"speed{k + 1}" in columns:
            notes.append(
                f"run {run}: no IVS{k}: vehicle {k + 1} has no recorded gap to "
                f"vehicle {k}, so no leader; its position is its own odometer "
                f"(another frame)"
            )
        else:
            notes.append(
                f"run {run}: no Speed{k + 1} or IVS{k}: vehicle {k + 1} is not "
                f"in the file"
            )
    no_driver = [str(k) for k in range(1, n + 1) if f"driver{k}" not in columns]
    if no_driver:
        notes.append(
            f"run {run}: no Driver column for vehicle(s) {', '.join(no_driver)}: "
            f"mode ''"
        )
    if time.size > 1:
        steps = np.diff(time)
        gaps = steps > 1.5 * np.median(steps)
        if gaps.any():
            notes.append(
                f"run {run}: {int(gaps.sum())} time gap(s), longest "
                f"{steps.max():.2f} s, bridged by the odometer's trapezoid"
            )
    counted = [
        *(
            (f"Speed{k}", speed[k - 1])
            for k in range(1, n + 1)
            if f"speed{k}" in columns
        ),
        *((f"IVS{k}", ivs[k - 1]) for k in range(1, n) if f"ivs{k}" in columns),
        *(
            (f"position of vehicle {k}", position[k - 1])
            for k in range(1, n + 1)
            if f"speed{k}" in columns or f"ivs{k - 1}" in columns
        ),
    ]
    for label, values in counted:
        holes = int(np.isnan(values).sum())
        if holes:
            notes.append(f"run {run}: {label} NaN at {holes} row(s)")
    for k, values in enumerate(ivs, start=1):
        low = values <= 0  # a missing column is NaN: never low
        if low.any():
            notes.append(
                f"run {run}: IVS{k} <= 0 at {int(low.sum())} row(s) (min "
                f"{np.nanmin(values):.2f} m)"
            )
    for k, values in enumerate(mode, start=1):
        present = values[values != ""]
        switches = int((present[1:] != present[:-1]).sum())
        if switches:
            notes.append(
                f"run {run}: Driver{k} changes {switches} time(s) "
                f"({', '.join(sorted(set(present)))})"
            )
    return notes
