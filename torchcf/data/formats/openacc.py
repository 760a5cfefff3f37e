"""Read OpenACC (JRC) platoon files into a trajectory table.

OpenACC (Makridis et al., Transportation Research Part C 125, 2021, 103047) records
platoons of 2-11 cars on public roads and test tracks: the first car of the
platoon is driven by hand (or is a target car), each later car follows the one
ahead, most followers with their ACC on. One CSV file is one continuous
recording, sampled at 10 Hz (GNSS at 3-5 Hz or Ublox 9, cubic-spline
interpolated by JRC, not filtered). :func:`read_openacc` turns a file or a
folder of them (a whole campaign) into a
:class:`~torchcf.data.trajectory.TrajectoryTable`;
:func:`read_openacc_metadata` lists each run's vehicles with their names (car
makes), ACC flag and distance setting, one row per vehicle.

File layout (CRLF, comma-separated)::

    Date,DD,MM,YYYY                      <- metadata block, rows padded with
    Vehicle_order,veh1,veh2,...             trailing commas or not
    Number_of_vehicles,N
    ACC,0|1|2|<blank>
    Distance_setting,S|M|L|min|shortest|...
    Time,Speed1,Lat1,...,IVS1,...,Driver1,...   <- header
    ...                                         <- data, one row per time step

The metadata block is the leading rows whose first cell is one of those keys (a
file may lack ACC or Distance_setting; keys are matched ignoring case, spaces
for underscores); the next row is the header. Columns are found by name and
vehicle number K, never by position, because they differ between files. Those
used, in SI units:

=========  ====  ==========================================================
column     unit  meaning
=========  ====  ==========================================================
Time       s     common clock of all vehicles (not starting at 0)
SpeedK     m/s   speed of vehicle K (GNSS Doppler)
IVSK       m     bumper-to-bumper spacing from vehicle K's rear to the front
                 of the vehicle behind it (GNSS, bumper-corrected by JRC):
                 the gap of that follower
DriverK    -     "Human" or "ACC"; missing for some vehicles
=========  ====  ==========================================================

Lat/Lon, Alt, E/N/U (m, local ENU) and VE/VN/VU are not used for positions, see
below (E/N and Alt place the runs on a circular track's lap, "Lap frame"); other
columns (Eff_distanceK, Rel_SpeedK, anything unknown) are listed in the notes
and not read.

**Which vehicles.** The vehicle number K is the car's place in Vehicle_order,
and a file holds the vehicles its columns name, not 1..N: a vehicle is in the
file when it has a column of its own (SpeedK, EK, NK, UK, LatK, LonK, AltK,
VEK, VNK, VUK or DriverK). ZalaZONE's handling-course files number their cars
from 2 (the target car carries no column); ZalaZONE ``dynamic_part26`` has
vehicles 1, 2, 5, 6, 7 of 9. Number_of_vehicles and Vehicle_order are only
checked against the columns (a difference is noted); vehicle K's name is the
K-th entry of Vehicle_order.

**Which couples.** Take the vehicles of a file in the order of their numbers.
Vehicle m follows the vehicle k just before it in that order when the file has
IVSk; its gap is IVSk and its leader k. For consecutive numbers (m = k + 1)
this is JRC's definition. When the numbers skip (vehicles k+1..m-1 have no
column), IVSk is taken as the spacing to m, the nearest car behind k that the
file records: JRC computes IVS from the GNSS of both cars, so the car behind
k that IVSk measures to must be one with a recording. In the ZalaZONE files
every IVSk so linked equals the E/N chord distance of the two antennas less a
constant per couple (2.8-5.3 m, the antenna-to-bumper offsets) to 1e-12 m,
while IVS1 set against vehicle 3's antenna wanders by 3-74 m: the link is
the one JRC measured. An IVSk whose vehicle k is not in the file, or that has
no vehicle after k, links nothing and is noted. Without IVSk, vehicle m has no
recorded gap, so no leader: it heads a chain of its own.

**Positions** (one road frame per run, along the route). The couples cut the
vehicles into chains (runs of linked vehicles). A chain is anchored at its
first vehicle with a Speed column, whose position is its odometer:

    x_a(t_0) = 0
    x_a(t_i) = x_a(t_{i-1}) + (v_a(t_{i-1}) + v_a(t_i)) / 2 * (t_i - t_{i-1})

and every other vehicle of the chain is placed by the recorded spacings,
behind (x_m = x_k - length - IVS_k) or, for vehicles ahead of the anchor
without a speed, ahead (x_k = x_m + length + IVS_k). A chain without any Speed
column has no position: its vehicles are left out and noted. So x_k - x_m -
length equals IVS_k exactly and the gaps a car-following model sees are JRC's
own. Why not the ENU positions: they are 2-D antenna positions, not along the
lane (a curve would need a route to project on), and the antenna-to-bumper
offsets are published nowhere but inside IVS. In the four Italian sample files
the ENU distance between two antennas minus IVS is a constant per file
(3.7-6.7 m): IVS is the GNSS chord distance with JRC's bumper correction, so it
carries every GNSS jump too (Vicolungo part3: IVS4 falls from 118 m to 48 m
within 0.5 s at t0 + 5 s while the Doppler speeds say the gap grows), and such
stretches are for a quality filter to drop.

Consequences worth knowing: the anchor's odometry drifts (a speed bias of 1 %
is 3 m per 10 s at 30 m/s), but that drift moves the whole chain alike and
changes no spacing. A follower's position is not the integral of its own
Doppler speed: IVS(t) - IVS(t0) and the integral of v_leader - v_follower part
by up to 1.5-18 m over 40 s in the samples (relative speed biases of about
0.1 m/s), so a position derived from it differs from the recorded speed by that
much. OpenACC gives no vehicle length, so ``vehicle_length`` is used for every
car; since a follower is placed exactly ``length + IVS`` behind its leader's
front, the length cancels in every spacing x_k - x_m - length and only shifts
the followers' absolute positions.

**Lap frame** (``lap_frame=True``, for runs round one circular track such as
ZalaZONE's dynamic platform; :func:`torchcf.data.formats.track.place_on_lap`).
One circle is fitted to the E/N paths of every chain's anchor over all runs; a run whose
anchor strays more than :data:`~torchcf.data.formats.track.OFF_TRACK` from it
(an access road) or does not go round is left out and noted. Each chain is then
shifted as a whole so that its anchor's odometer follows the anchor's lap
coordinate (the median difference over the run is removed): the arc length
from the track's lowest point (the plane fitted to the anchors' Alt) in the
run's direction of travel. On a tilted
plane both directions then feel one grade profile of period ``2 pi R``; the
spacings stay the recorded IVS. The odometer and the arc length part slowly
(the speed's bias, the antenna's own radius): the largest difference per run is
in the notes.

**Table rows.** Vehicle id "K" (the column number), leader "k" or "", speed =
SpeedK (NaN without the column), gap = the linking IVS, lane "" (the platoon
tests stay in one lane, so the leader is always the vehicle ahead in the
file's order), acceleration NaN (OpenACC has none; derive it with
:func:`torchcf.data.derive.fill_derivatives`). The mode is the control mode
with the run's distance setting: DriverK where the file has it, else the ACC
field (0: every car "Human"; 1: every car after vehicle 1 "ACC"; 2 or blank:
""); an "ACC" mode carries the Distance_setting as ``"ACC:<setting>"`` (e.g.
"ACC:S"), because a gap setting is part of how the ACC controls, and it is the
one per-row field that the pair index keeps. The car makes stay in the notes
and in :func:`read_openacc_metadata` (vehicle ids stay the column numbers, so
the group split of earlier extractions is unchanged).

**Folders.** A folder is read recursively: every ``*.csv`` whose first cell is
"Date" is one run, named by its path relative to the folder without the suffix
(``short_setting/dynamic_part1``), so runs of different subfolders stay apart;
other CSV files (the vehicle specifications) are skipped and listed in the
notes. A file that is a platoon file but cannot be read stops the whole read
with its name: a campaign is not silently shortened.

Missing values: where the anchor's speed is NaN its position is NaN; the
odometer steps over the hole with one trapezoid between its finite neighbours
(speed linear across it), so one hole does not shift or poison everything
after it (and x_a = 0 at the first sample with a speed). A vehicle's position
is NaN where the vehicle it is placed from has a NaN position or the IVS is
NaN. Rows without a time are dropped. Each case is counted in the notes.
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

from torchcf.data.formats.track import Anchor, place_on_lap
from torchcf.data.pairset import DataError, positive_float
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["METADATA_COLUMNS", "METADATA_KEYS", "read_openacc", "read_openacc_metadata"]

#: First cells of the metadata rows above the header, normalised (see _key).
METADATA_KEYS: tuple[str, ...] = (
    "date",
    "vehicle_order",
    "number_of_vehicles",
    "acc",
    "distance_setting",
)
#: Columns of :func:`read_openacc_metadata`.
METADATA_COLUMNS: tuple[str, ...] = (
    "run",
    "vehicle",
    "name",
    "date",
    "acc",
    "distance_setting",
    "leader",
    "has_speed",
    "names_match_count",
    "file",
)
#: Column prefixes that make a vehicle part of the file (its own columns).
_OWN = ("speed", "e", "n", "u", "lat", "lon", "alt", "ve", "vn", "vu", "driver")
#: Per-couple columns JRC documents but this reader does not use.
_COUPLE_UNUSED = ("eff_distance", "rel_speed")
#: Cell texts that mean "no value" (lower case, stripped).
_MISSING = ("", "nan", "na", "n/a", "null")
_SUFFIXED = re.compile(r"([a-z_]+?)_?(\d+)")


class _Metadata(NamedTuple):
    names: list[str]  # Vehicle_order, one per vehicle as far as given
    n_vehicles: int  # Number_of_vehicles as written
    date: str  # "D-M-YYYY", "" when absent
    acc: str  # the ACC field, "" blank
    distance: str  # the Distance_setting field, "" blank
    n_rows: int  # rows of the block; the header is the next row


class _Header(NamedTuple):
    """Where the used columns are: vehicle number -> column index."""

    time: int
    speed: dict[int, int]
    ivs: dict[int, int]
    driver: dict[int, int]
    east: dict[int, int]
    north: dict[int, int]
    altitude: dict[int, int]
    vehicles: list[int]  # numbers with a column of their own, ascending
    unread: list[str]  # names of columns that are neither used nor known-unused


class _Plan(NamedTuple):
    """How one file's vehicles are linked and placed (from its header only)."""

    leader: dict[int, int]  # follower -> leader, linked by IVS<leader>
    chains: list[list[int]]  # linked vehicles, front to back
    anchor: dict[int, int]  # chain head -> the chain's first vehicle with speed
    unused_ivs: list[int]  # IVSk that link no couple


# ------------------------------------------------------------------ public API
def read_openacc(
    source: str | os.PathLike[str],
    *,
    vehicle_length: float = 5.0,
    lap_frame: bool = False,
) -> TrajectoryTable:
    """Read an OpenACC platoon file, or every platoon file below a folder.

    Args:
        source: a platoon CSV file, or a folder searched recursively for them
            (a whole campaign, e.g. ZalaZONE's ``<setting>/dynamic_part*.csv``).
        vehicle_length: length [m] given to every vehicle, > 0 (OpenACC has
            none; it changes no spacing, see the module docstring).
        lap_frame: the runs were driven round one circular track (ZalaZONE's
            dynamic platform): put every run on the track's lap coordinate
            (module docstring, "Lap frame"), so that all pairs share one road
            frame with a period, the lap length; runs that leave the circle
            are left out and noted.

    Returns:
        A table with ``format="openacc"``, one run per file (named by its path
        below the folder), and ``road_frame`` True for one file (its positions
        are distances along one route) and False for several (each file is
        another recording, its positions start at 0), or True with
        ``road_period`` the lap length under ``lap_frame``; vehicles as the columns
        name them, each follower led by the vehicle before it when the IVS
        links them (module docstring). The notes give per run the vehicles by
        name, the couples, the ACC flag and distance setting, and every
        missing value, unused column or skipped file.

    Raises:
        DataError: no such path, a folder without platoon files, a file whose
            metadata block is not OpenACC's ("not an OpenACC file: ..."), no
            Time or no Speed column, a duplicated column, a cell that is not a
            number, or times that do not increase; always naming the file.
    """
    path = Path(source)
    length = positive_float(vehicle_length, "vehicle_length", "m")
    runs, skipped = _platoon_files(path)
    frames: list[pd.DataFrame] = []
    notes: list[str] = []
    anchors: list[list[Anchor]] = []
    for run, file in runs:
        frame, run_notes, run_anchors = _read_file(file, run, length, lap_frame)
        frames.append(frame)
        notes.extend(run_notes)
        anchors.append(run_anchors)
    period = None
    if lap_frame:
        frames, period, lap_notes = place_on_lap(
            [run for run, _ in runs], frames, anchors, str(path)
        )
        notes.extend(lap_notes)
    notes.append(
        f"positions: each chain of linked vehicles anchored at its first vehicle "
        f"with a Speed column, by integrating that speed over Time (trapezoids, 0 "
        f"at the run's first sample); the others at {length:g} m + IVS behind or "
        f"ahead, so every gap is the recorded IVS; length {length:g} m for every "
        f"vehicle (OpenACC gives none)"
    )
    notes.append(
        "acceleration: none in OpenACC (NaN; derive it with "
        "torchcf.data.derive.fill_derivatives); lane: '' (one-lane platoon tests)"
    )
    if skipped:
        notes.append(_skipped_note(skipped))
    return TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True),
        source=str(path),
        format="openacc",
        road_frame=True if lap_frame else len(runs) == 1,
        road_period=period,
        notes=notes,
    )


def read_openacc_metadata(source: str | os.PathLike[str]) -> pd.DataFrame:
    """Each run's vehicles with their metadata, from the files' first rows only.

    Meant to be joined with an extraction's ``index.csv`` on ``(run, follower)``
    = ``(run, vehicle)`` (same run names and vehicle ids as
    :func:`read_openacc`), e.g. for shares per distance setting or car make.

    Args:
        source: a platoon CSV file, or a folder searched recursively for them.

    Returns:
        One row per vehicle in a file (:data:`METADATA_COLUMNS`): ``name`` the
        vehicle's Vehicle_order entry ("" beyond the list), ``date``
        ("D-M-YYYY"), ``acc`` and ``distance_setting`` as written, ``leader``
        the vehicle it follows ("" none), ``has_speed`` whether it has a Speed
        column, ``names_match_count`` whether Vehicle_order names exactly
        Number_of_vehicles cars (when not, the names may not be these cars:
        ZalaZONE ``short_setting/dynamic_part1`` lists 11 names for 6 cars),
        and ``file`` the path read.

    Raises:
        DataError: as :func:`read_openacc`, for the metadata block and header.
    """
    runs, _ = _platoon_files(Path(source))
    rows = []
    for run, file in runs:
        meta, header = _read_head(file)
        plan = _plan(header)
        for k in header.vehicles:
            rows.append(
                {
                    "run": run,
                    "vehicle": str(k),
                    "name": _name(meta, k),
                    "date": meta.date,
                    "acc": meta.acc,
                    "distance_setting": meta.distance,
                    "leader": str(plan.leader[k]) if k in plan.leader else "",
                    "has_speed": k in header.speed,
                    "names_match_count": len(meta.names) == meta.n_vehicles,
                    "file": str(file),
                }
            )
    return pd.DataFrame(rows, columns=list(METADATA_COLUMNS))


# ------------------------------------------------------------------ discovery
def _platoon_files(path: Path) -> tuple[list[tuple[str, Path]], list[str]]:
    """``[(run name, file)]`` to read and the CSV files skipped (folder only).

    Raises:
        DataError: no such path, or a folder without platoon files.
    """
    if path.is_file():
        return [(path.stem, path)], []
    if not path.is_dir():
        raise DataError(f"no such file or folder: '{path}'")
    runs, skipped = [], []
    # Sorted on the relative path, so runs come in the same order on any OS.
    for file in sorted(path.rglob("*.csv"), key=lambda f: f.relative_to(path)):
        name = file.relative_to(path)
        if file.is_file() and _first_cell(file) == "Date":
            runs.append((name.with_suffix("").as_posix(), file))
        else:
            skipped.append(name.as_posix())
    if not runs:
        raise DataError(
            f"no OpenACC platoon file (a .csv whose first cell is 'Date') "
            f"under '{path}'"
        )
    return runs, skipped


def _first_cell(path: Path) -> str:
    """The first cell of a file's first line, "" when it cannot be read as text."""
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            line = fh.readline()
    except (OSError, UnicodeDecodeError):
        return ""
    return line.split(",", 1)[0].strip()


def _skipped_note(skipped: list[str]) -> str:
    return (
        f"skipped {len(skipped)} csv file(s) that are not platoon files "
        f"(first cell not 'Date'): {', '.join(skipped)}"
    )


# ---------------------------------------------------------------- one file
def _read_file(
    path: Path, run: str, length: float, lap: bool
) -> tuple[pd.DataFrame, list[str], list[Anchor]]:
    """One platoon file as table rows (vehicle after vehicle), its notes and
    (with ``lap``) its chains' anchors with their E/N/Alt paths."""
    rows = _csv_rows(path)
    meta = _metadata(rows, path)
    if meta.n_rows >= len(rows):
        raise DataError(f"'{path}' has no header row after its metadata block")
    header_cells = rows[meta.n_rows]
    header = _header(header_cells, path)
    plan = _plan(header)
    data, file_rows = _data_rows(rows, meta.n_rows, len(header_cells), path)

    def column(j: int) -> list[str]:
        return [row[j] if j < len(row) else "" for row in data]

    def numbers(j: int) -> np.ndarray:
        return _numbers(column(j), header_cells[j], path, file_rows)

    time = numbers(header.time)
    speed = {k: numbers(j) for k, j in header.speed.items()}
    ivs = {k: numbers(j) for k, j in header.ivs.items()}
    driver = {k: np.array(column(j), dtype=object) for k, j in header.driver.items()}
    place = (
        {
            name: {
                k: numbers(j) for k, j in columns.items() if k in plan.anchor.values()
            }
            for name, columns in (
                ("east", header.east),
                ("north", header.north),
                ("altitude", header.altitude),
            )
        }
        if lap
        else {"east": {}, "north": {}, "altitude": {}}
    )

    notes: list[str] = []
    keep = np.isfinite(time)
    if not keep.all():
        notes.append(f"run {run}: dropped {int((~keep).sum())} row(s) without a Time")
        if not keep.any():
            raise DataError(f"'{path}' has no data row with a Time")
        time, file_rows = time[keep], file_rows[keep]
        speed = {k: v[keep] for k, v in speed.items()}
        ivs = {k: v[keep] for k, v in ivs.items()}
        driver = {k: v[keep] for k, v in driver.items()}
        place = {n: {k: v[keep] for k, v in c.items()} for n, c in place.items()}
    _check_increasing(time, file_rows, path)

    position = _positions(plan, time, speed, ivs, length)
    mode = {k: _mode(k, driver.get(k), meta, time.size) for k in position}
    frames = [
        pd.DataFrame(
            {
                "run": run,
                "vehicle": str(k),
                "time": time,
                "position": position[k],
                "speed": speed.get(k, np.full(time.size, np.nan)),
                "acceleration": np.nan,
                "leader": str(plan.leader[k]) if k in plan.leader else "",
                "lane": "",
                "length": length,
                "gap": ivs[plan.leader[k]] if k in plan.leader else np.nan,
                "mode": mode[k],
            }
        )
        for k in header.vehicles
        if k in position
    ]
    notes = [
        _describe(run, meta, header, time),
        *notes,
        *_plan_notes(run, meta, header, plan),
        *_quality_notes(run, header, time, speed, ivs, position, mode),
    ]
    missing = np.full(time.size, np.nan)
    anchors = (
        [
            Anchor(
                vehicle=k,
                chain=next(chain for chain in plan.chains if chain[0] == head),
                east=place["east"].get(k, missing),
                north=place["north"].get(k, missing),
                altitude=place["altitude"].get(k, missing),
            )
            for head, k in plan.anchor.items()
        ]
        if lap
        else []
    )
    return pd.concat(frames, ignore_index=True), notes, anchors


def _csv_rows(path: Path) -> list[list[str]]:
    """The file's rows as stripped cells (any line ending, BOM dropped)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise DataError(f"'{path}' is not UTF-8 text ({err})") from None
    except OSError as err:
        raise DataError(f"cannot read '{path}': {err.strerror or err}") from None
    return [
        [cell.strip() for cell in row]
        for row in csv.reader(io.StringIO(text, newline=""))
    ]


def _read_head(path: Path) -> tuple[_Metadata, _Header]:
    """The metadata block and header of a file, reading no data row."""
    rows: list[list[str]] = []
    try:
        with path.open(encoding="utf-8-sig", newline="") as fh:
            for row in csv.reader(fh):
                rows.append([cell.strip() for cell in row])
                if _key(rows[-1][0] if rows[-1] else "") not in METADATA_KEYS:
                    break  # the header: the first row that is no metadata key
    except UnicodeDecodeError as err:
        raise DataError(f"'{path}' is not UTF-8 text ({err})") from None
    meta = _metadata(rows, path)
    if meta.n_rows >= len(rows):
        raise DataError(f"'{path}' has no header row after its metadata block")
    return meta, _header(rows[meta.n_rows], path)


def _key(cell: str) -> str:
    """A metadata key or column name, normalised: lower case, spaces as '_'."""
    return re.sub(r"\s+", "_", cell.strip().lower())


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
        key = _key(row[0]) if row else ""
        if key not in METADATA_KEYS:
            break
        # Trailing commas pad the rows: empty cells are no values.
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
        date="-".join(fields.get("date", [])),
        acc=" ".join(fields.get("acc", [])),
        distance=" ".join(fields.get("distance_setting", [])),
        n_rows=n_rows,
    )


def _header(cells: list[str], path: Path) -> _Header:
    """Find Time and each vehicle's columns by name and number.

    Raises:
        DataError: no Time column, no Speed column, or a used column twice.
    """
    time: int | None = None
    used: dict[str, dict[int, int]] = {
        "speed": {},
        "ivs": {},
        "driver": {},
        "e": {},
        "n": {},
        "alt": {},
    }
    own: set[int] = set()
    unread: list[str] = []
    for j, name in enumerate(cells):
        key = _key(name)
        if not key:
            continue  # trailing commas pad the header too
        if key == "time":
            if time is not None:
                raise DataError(f"'{path}' has the column '{name}' twice")
            time = j
            continue
        match = _SUFFIXED.fullmatch(key)
        prefix, k = (match.group(1), int(match.group(2))) if match else ("", -1)
        if prefix in used:
            if k in used[prefix]:
                raise DataError(f"'{path}' has the column '{name}' twice")
            used[prefix][k] = j
        elif prefix not in _OWN and prefix not in _COUPLE_UNUSED:
            unread.append(name)
        if prefix in _OWN:
            own.add(k)
    if time is None:
        raise DataError(f"'{path}' lacks the column 'Time'")
    if not used["speed"]:
        raise DataError(
            f"'{path}' has no Speed column (SpeedK): no vehicle can be placed"
        )
    return _Header(
        time=time,
        speed=used["speed"],
        ivs=used["ivs"],
        driver=used["driver"],
        east=used["e"],
        north=used["n"],
        altitude=used["alt"],
        vehicles=sorted(own),
        unread=unread,
    )


def _plan(header: _Header) -> _Plan:
    """Couples and chains of a file (module docstring, "Which couples").

    Consecutive vehicles of the file (k, m), in the order of their numbers,
    are a couple when IVSk exists; the couples cut the vehicles into chains.
    """
    leader: dict[int, int] = {}
    chains: list[list[int]] = []
    previous: int | None = None
    for k in header.vehicles:
        if previous is not None and previous in header.ivs:
            leader[k] = previous
            chains[-1].append(k)
        else:
            chains.append([k])
        previous = k
    anchor = {}
    for chain in chains:
        with_speed = [k for k in chain if k in header.speed]
        if with_speed:
            anchor[chain[0]] = with_speed[0]
    unused = sorted(set(header.ivs) - set(leader.values()))
    return _Plan(leader=leader, chains=chains, anchor=anchor, unused_ivs=unused)


def _data_rows(
    rows: list[list[str]], header_row: int, width: int, path: Path
) -> tuple[list[list[str]], np.ndarray]:
    """Non-blank rows below the header and their 1-based line numbers.

    Raises:
        DataError: no data row, or a row with more filled cells than the header.
    """
    # Blank lines are formatting; line numbers count them all the same.
    numbered = [
        (i + 1, row)
        for i, row in enumerate(rows[header_row + 1 :], start=header_row + 1)
        if any(row)
    ]
    if not numbered:
        raise DataError(f"'{path}' has no data row")
    for line, row in numbered:
        if any(row[width:]):
            raise DataError(
                f"'{path}' row {line} has {len(row)} cells but the header has {width}"
            )
    return [row for _, row in numbered], np.array([line for line, _ in numbered])


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


def _check_increasing(time: np.ndarray, file_rows: np.ndarray, path: Path) -> None:
    """Raise a DataError at the first time step that is not positive."""
    steps = np.diff(time)
    if (steps <= 0).any():
        bad = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise DataError(
            f"'{path}': Time does not increase at row {file_rows[bad]} "
            f"({time[bad - 1]} then {time[bad]})"
        )


# ----------------------------------------------------------------- positions
def _positions(
    plan: _Plan,
    time: np.ndarray,
    speed: dict[int, np.ndarray],
    ivs: dict[int, np.ndarray],
    length: float,
) -> dict[int, np.ndarray]:
    """(T,) front-bumper position [m] of every vehicle of an anchored chain.

    Vehicles of a chain without a Speed column are absent from the result.
    """
    position: dict[int, np.ndarray] = {}
    for chain in plan.chains:
        if chain[0] not in plan.anchor:
            continue
        a = chain.index(plan.anchor[chain[0]])
        position[chain[a]] = _odometer(time, speed[chain[a]])
        # Behind the anchor: each follower length + IVS behind its leader.
        for leader, follower in zip(chain[a:], chain[a + 1 :], strict=False):
            position[follower] = position[leader] - length - ivs[leader]
        # Ahead of it (no speed there): each leader length + IVS ahead.
        for leader, follower in zip(
            reversed(chain[:a]), reversed(chain[1 : a + 1]), strict=True
        ):
            position[leader] = position[follower] + length + ivs[leader]
    return position


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


def _mode(k: int, driver: np.ndarray | None, meta: _Metadata, n: int) -> np.ndarray:
    """(T,) control mode of vehicle ``k``: DriverK, else from the ACC field.

    An "ACC" mode carries the run's distance setting ("ACC:S").
    """
    if driver is not None:
        mode = driver.copy()
    elif meta.acc == "0":
        mode = np.full(n, "Human", dtype=object)
    elif meta.acc == "1" and k > 1:
        # ACC 1: "the whole experiment conducted with ACC" (JRC's notes) holds
        # for the followers; the first car of Vehicle_order leads, and how
        # (by hand, a target car) the file does not say: it stays "".
        mode = np.full(n, "ACC", dtype=object)
    else:
        mode = np.full(n, "", dtype=object)
    if meta.distance:
        acc = np.array([str(m).upper() == "ACC" for m in mode], dtype=bool)
        mode[acc] = f"ACC:{meta.distance}"
    return mode


# --------------------------------------------------------------------- notes
def _name(meta: _Metadata, k: int) -> str:
    return meta.names[k - 1] if 1 <= k <= len(meta.names) else ""


def _describe(run: str, meta: _Metadata, header: _Header, time: np.ndarray) -> str:
    """The run's vehicles by name, its span and its metadata, in one line."""
    names = [f"{k}={_name(meta, k) or '?'}" for k in header.vehicles]
    step = float(np.median(np.diff(time))) if time.size > 1 else float("nan")
    return (
        f"run {run}: vehicles {', '.join(names)}; {time.size} rows every "
        f"{step:.3g} s, t = {time[0]:.1f}-{time[-1]:.1f} s; ACC "
        f"{meta.acc or 'blank'}, distance setting {meta.distance or 'blank'}"
    )


def _plan_notes(run: str, meta: _Metadata, header: _Header, plan: _Plan) -> list[str]:
    """The couples, and every way the header departs from 1..N, linked."""
    notes = []
    couples = [f"{plan.leader[k]}>{k}" for k in header.vehicles if k in plan.leader]
    notes.append(f"run {run}: couples (leader>follower) {', '.join(couples) or 'none'}")
    if header.vehicles != list(range(1, meta.n_vehicles + 1)):
        absent = sorted(set(range(1, meta.n_vehicles + 1)) - set(header.vehicles))
        beyond = [k for k in header.vehicles if not 1 <= k <= meta.n_vehicles]
        notes.append(
            f"run {run}: Number_of_vehicles is {meta.n_vehicles} but the columns "
            f"name vehicle(s) {_listed(header.vehicles)}"
            + (f"; none for {_listed(absent)}" if absent else "")
            + (f"; beyond the count: {_listed(beyond)}" if beyond else "")
        )
    if len(meta.names) != meta.n_vehicles:
        notes.append(
            f"run {run}: Vehicle_order names {len(meta.names)} vehicle(s) but "
            f"Number_of_vehicles is {meta.n_vehicles}: vehicle K is named by the "
            f"K-th entry, which may not be that car"
        )
    for k, m in zip(header.vehicles, header.vehicles[1:], strict=False):
        if m not in plan.leader:
            notes.append(
                f"run {run}: no IVS{k}: vehicle {m} has no recorded gap to vehicle "
                f"{k}, so no leader; its chain is placed by its own odometer "
                f"(another frame)"
            )
        elif m != k + 1:
            skipped = _listed(list(range(k + 1, m)))
            notes.append(
                f"run {run}: IVS{k} taken as the spacing from vehicle {k} to "
                f"vehicle {m}, the next vehicle in the file ({skipped} absent)"
            )
    for k in plan.unused_ivs:
        why = (
            f"vehicle {k} is not in the file"
            if k not in header.vehicles
            else f"no vehicle after {k} in the file"
        )
        notes.append(f"run {run}: IVS{k} not used: {why}")
    unplaced = [
        k for chain in plan.chains if chain[0] not in plan.anchor for k in chain
    ]
    if unplaced:
        notes.append(
            f"run {run}: vehicle(s) {_listed(unplaced)} left out: no Speed column "
            f"in their chain, so no position"
        )
    if header.unread:
        notes.append(f"run {run}: columns not read: {', '.join(header.unread)}")
    return notes


def _quality_notes(
    run: str,
    header: _Header,
    time: np.ndarray,
    speed: dict[int, np.ndarray],
    ivs: dict[int, np.ndarray],
    position: dict[int, np.ndarray],
    mode: dict[int, np.ndarray],
) -> list[str]:
    """Notes on what is missing or odd in one run (nothing when all is clean)."""
    notes = []
    no_speed = [k for k in position if k not in header.speed]
    if no_speed:
        notes.append(
            f"run {run}: no Speed column for vehicle(s) {_listed(no_speed)}: speed NaN"
        )
    no_driver = [k for k in position if k not in header.driver]
    if no_driver:
        modes = sorted({str(m) for k in no_driver for m in set(mode[k])})
        notes.append(
            f"run {run}: no Driver column for vehicle(s) {_listed(no_driver)}: "
            f"mode from the ACC field ({', '.join(repr(m) for m in modes)})"
        )
    if time.size > 1:
        steps = np.diff(time)
        gaps = steps > 1.5 * np.median(steps)
        if gaps.any():
            notes.append(
                f"run {run}: {int(gaps.sum())} time gap(s), longest "
                f"{steps.max():.2f} s, bridged by the odometer's trapezoid"
            )
    counted: list[tuple[str, np.ndarray]] = [
        *((f"Speed{k}", v) for k, v in speed.items()),
        *((f"IVS{k}", v) for k, v in ivs.items()),
        *((f"position of vehicle {k}", v) for k, v in position.items()),
    ]
    for label, values in counted:
        holes = int(np.isnan(values).sum())
        if holes:
            notes.append(f"run {run}: {label} NaN at {holes} row(s)")
    for k, values in ivs.items():
        low = values <= 0  # NaN is never low
        if low.any():
            notes.append(
                f"run {run}: IVS{k} <= 0 at {int(low.sum())} row(s) (min "
                f"{np.nanmin(values):.2f} m)"
            )
    for k, values in mode.items():
        present = values[values != ""]
        switches = int((present[1:] != present[:-1]).sum())
        if switches:
            notes.append(
                f"run {run}: Driver{k} changes {switches} time(s) "
                f"({', '.join(sorted(set(present)))})"
            )
    return notes


def _listed(numbers: list[int]) -> str:
    return ", ".join(str(k) for k in numbers)
