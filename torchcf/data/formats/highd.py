"""Read highD drone trajectories (levelXdata): ``XX_tracks.csv`` and its meta files.

A highD recording ``XX`` (01-60) is three CSV files side by side:

* ``XX_recordingMeta.csv``: one row; ``frameRate`` [Hz] (25) and ``locationId``
  are used;
* ``XX_tracksMeta.csv``: one row per vehicle; ``id``, ``class`` ("Car" or
  "Truck") and ``drivingDirection`` are used: 1 for the upper lanes of the
  image, driven towards -x; 2 for the lower lanes, driven towards +x;
* ``XX_tracks.csv``: one row per vehicle and frame, 25 columns, in metres and
  seconds: ``frame, id, x, y, width, height, xVelocity, yVelocity,
  xAcceleration, yAcceleration, frontSightDistance, backSightDistance, dhw,
  thw, ttc, precedingXVelocity, precedingId, followingId, leftPrecedingId,
  leftAlongsideId, leftFollowingId, rightPrecedingId, rightAlongsideId,
  rightFollowingId, laneId``.

``(x, y)`` is the corner of the vehicle's bounding box with the smallest x (and
y); ``width`` is the box's extent along x, i.e. the vehicle's length, and
``height`` its extent across the road. Velocities and accelerations are signed
along x, so they are negative on the upper lanes. The reader turns the image
frame into a road frame per driving direction, with ``d`` = +1 on the lower
lanes (2) and -1 on the upper lanes (1):

=============  =================================================================
highD          :class:`~torchcf.data.trajectory.TrajectoryTable` column
=============  =================================================================
frame          time = frame / frameRate [s]
x, width       position: the front bumper along the direction of travel [m],
               ``x + width`` on the lower lanes, ``-x`` on the upper lanes (their
               front is the box's low-x edge, and -x grows as they drive on)
xVelocity      speed = d * xVelocity [m/s] (positive when driving forward)
xAcceleration  acceleration = d * xAcceleration [m/s^2]
width          length [m]
laneId         lane (highD numbers the lanes of both directions apart)
precedingId    leader ("" where 0: no vehicle ahead in the lane)
dhw            gap: the leader's rear to this vehicle's front [m] (below)
=============  =================================================================

``dhw`` is the "distance headway"; highD does not say between which points of
the two vehicles. The reader tells from the data, per recording: where a
vehicle has a leader, it compares ``dhw`` with the spacing implied by the
positions read as front to front, as the bumper-to-bumper gap and as centre to
centre (:data:`DHW_READINGS`) and keeps the reading whose median difference is
under :data:`DHW_TOLERANCE`; the gap is then ``dhw`` less what that reading
counts beyond the gap. When none fits, the gap is NaN (the gap-consistency
filter skips such windows) and a note says so.

Each recording is a run named by its number as written (``"01"``); vehicle ids
are unique within it. A leader change (``precedingId`` changes) and a lane
change (``laneId`` changes) end a leader-follower couple in
:mod:`torchcf.data.extract`, which cuts on both. The control mode is unknown
(""). The vehicle class is not a table column: ``follower_classes`` keeps
couples whose follower is of the classes named, and the notes count the classes.

The exiD, inD and rounD files of the same family have another layout
(``trackId``, ``xCenter``, lanelets) and no road coordinate without their
map: they are refused with a message saying so.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from torchcf.data.formats.generic import columns_text, require_text
from torchcf.data.pairset import DataError
from torchcf.data.trajectory import TrajectoryTable

__all__ = [
    "DHW_READINGS",
    "DHW_TOLERANCE",
    "DIRECTIONS",
    "KINDS",
    "read_highd",
]

#: The three files of a recording, by kind: ``f"{XX}_{kind}.csv"``.
KINDS: tuple[str, ...] = ("tracks", "tracksMeta", "recordingMeta")
#: drivingDirection -> (name, sign of x along the direction of travel).
DIRECTIONS: dict[int, tuple[str, int]] = {1: ("upper", -1), 2: ("lower", +1)}
#: Ways to read ``dhw``: name -> (a, b) with ``dhw = gap + a L_leader + b L_follower``
#: (L: the vehicles' lengths [m]).
DHW_READINGS: dict[str, tuple[float, float]] = {
    "front to front": (1.0, 0.0),
    "the leader's rear to the front (the gap)": (0.0, 0.0),
    "centre to centre": (0.5, 0.5),
}
#: Largest median |dhw - reading| [m] for a reading to be taken; highD rounds
#: to centimetres, so a right reading is off by about 0.01 m and a wrong one by
#: half a car length or more.
DHW_TOLERANCE = 0.5

_FILE = re.compile(r"^(\d+)_(tracks|tracksMeta|recordingMeta)\.csv$")
_TRACK_COLUMNS = (
    "frame",
    "id",
    "x",
    "width",
    "xVelocity",
    "xAcceleration",
    "dhw",
    "precedingId",
    "laneId",
)
_META_COLUMNS = ("id", "class", "drivingDirection")
#: The id column of the exiD / inD / rounD files, which highD calls ``id``.
_OTHER_LAYOUT = "trackId"


@dataclass(frozen=True)
class _Recording:
    """The three files of one recording."""

    number: str  # as written in the file names, e.g. "01"
    tracks: Path
    tracks_meta: Path
    recording_meta: Path


def read_highd(
    source: str | os.PathLike[str],
    *,
    recordings: str | int | Iterable[int | str] | None = None,
    directions: str | int | Iterable[int | str] | None = None,
    follower_classes: str | Iterable[str] | None = None,
) -> TrajectoryTable:
    """Read highD recordings into a trajectory table in road coordinates.

    Args:
        source: a folder holding one or more recordings (``XX_tracks.csv``,
            ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv``; not searched
            recursively), or any one of the three files of a recording (the
            other two are read beside it).
        recordings: the recording numbers to read, e.g. ``[1, 2]`` or the text
            ``"1,2,5-7"``; None reads all.
        directions: drivingDirection(s) to keep: 1 or "upper", 2 or "lower", a
            list or the text ``"upper,lower"``; None keeps both.
        follower_classes: vehicle classes (e.g. "Car", "Truck", or the text
            ``"Car,Truck"``; any case) that may be followers; vehicles of other
            classes stay in the table as leaders only. None keeps all.

    Returns:
        The table, sorted by run, vehicle and time; ``format="highd"``, one run
        per recording, ``road_frame`` True for one recording and one driving
        direction (False otherwise: other roads, or the two carriageways), and
        notes on conventions, classes, directions, lane changes and ``dhw``.

    Raises:
        DataError: no such path; a file or folder that is not highD (the
            exiD/inD/rounD layout included); a recording that lacks one of its
            three files (named); a recording asked for that is not there; a
            missing column, a non-numeric cell, a frame rate that is not
            positive, a vehicle missing from the tracks meta file or with a
            drivingDirection other than 1 or 2; an unknown direction; a class
            no vehicle has; no row left after the selection.
    """
    wanted = _parse_numbers(recordings)
    keep_directions = _parse_directions(directions)
    classes = _parse_classes(follower_classes)
    folder, numbers = _recording_numbers(Path(source))
    found = [_complete(folder, n) for n in _select(numbers, wanted, source)]

    frames: list[pd.DataFrame] = []
    notes: list[str] = [_CONVENTIONS]
    seen_classes: set[str] = set()
    for recording in found:
        frame, recording_notes, present = _read_recording(
            recording, keep_directions, classes
        )
        frames.append(frame)
        notes.extend(recording_notes)
        seen_classes |= present
    absent = (classes or set()) - {c.lower() for c in seen_classes}
    if absent:
        raise DataError(
            f"no vehicle of class {', '.join(sorted(absent))} in '{source}' "
            f"(classes there: {', '.join(sorted(seen_classes)) or 'none'})"
        )
    frame = pd.concat(frames, ignore_index=True)
    if frame.empty:
        raise DataError(
            f"no highD row left in '{source}' after choosing driving direction(s) "
            f"{', '.join(DIRECTIONS[d][0] for d in sorted(keep_directions))}"
        )
    one_road = len(found) == 1 and frame["direction"].nunique() == 1
    table = TrajectoryTable.from_frame(
        frame.drop(columns=["direction"]),
        source=str(source),
        format="highd",
        road_frame=one_road,
        notes=notes,
    )
    return table.sorted()


_CONVENTIONS = (
    "highD to road coordinates: position = front bumper along the direction of "
    "travel (x + width on the lower lanes, drivingDirection 2; -x on the upper "
    "lanes, 1); speed and acceleration = xVelocity and xAcceleration times +1 "
    "(lower) or -1 (upper); length = width (the box along x); time = frame / "
    "frameRate; leader = precedingId (0: none); one run per recording"
)


# ------------------------------------------------------------------ the files
def _recording_numbers(path: Path) -> tuple[Path, list[str]]:
    """The folder of the recordings and their numbers as written: those of a
    folder, or the one a file belongs to.

    Raises:
        DataError: no such path, or no highD file.
    """
    if path.is_file():
        match = _FILE.match(path.name)
        if match is None:
            raise DataError(
                f"'{path}' is not a highD file (expected XX_tracks.csv, "
                "XX_tracksMeta.csv or XX_recordingMeta.csv)"
            )
        return path.parent, [match.group(1)]
    if not path.is_dir():
        raise DataError(f"no such file or folder: '{path}'")
    numbers = sorted(
        {m.group(1) for p in path.iterdir() if (m := _FILE.match(p.name))},
        key=lambda n: (int(n), n),
    )
    if not numbers:
        raise DataError(
            f"folder '{path}' holds no highD recording (XX_tracks.csv, "
            "XX_tracksMeta.csv, XX_recordingMeta.csv; not searched recursively)"
        )
    return path, numbers


def _complete(folder: Path, number: str) -> _Recording:
    """Recording ``number`` of ``folder`` with its three files.

    Raises:
        DataError: one of the three files is missing (it is named).
    """
    files = {kind: folder / f"{number}_{kind}.csv" for kind in KINDS}
    missing = [p.name for p in files.values() if not p.is_file()]
    if missing:
        raise DataError(
            f"highD recording {number} in '{folder}' lacks {' and '.join(missing)}"
        )
    return _Recording(
        number, files["tracks"], files["tracksMeta"], files["recordingMeta"]
    )


def _select(
    numbers: list[str], wanted: set[int] | None, source: str | os.PathLike[str]
) -> list[str]:
    """The recording numbers asked for, in the order found (a recording left
    out need not be complete).

    Raises:
        DataError: a number asked for is not among those found.
    """
    if wanted is None:
        return numbers
    absent = sorted(wanted - {int(n) for n in numbers})
    if absent:
        raise DataError(
            f"highD recording(s) {', '.join(f'{n:02d}' for n in absent)} not in "
            f"'{source}' (it has {', '.join(numbers)})"
        )
    return [n for n in numbers if int(n) in wanted]


def _read_csv(
    path: Path, columns: tuple[str, ...], optional: tuple[str, ...] = ()
) -> pd.DataFrame:
    """The named columns of a highD CSV, and those of ``optional`` it has.

    Cells are parsed by pandas; a numeric column that holds text comes back as
    text, and :func:`_numbers` names the line of the bad cell.

    Raises:
        DataError: an unreadable file, the exiD/inD/rounD layout, or a missing
            column (named with the columns the file has).
    """
    require_text(path)
    try:
        header = list(pd.read_csv(path, nrows=0, encoding="utf-8-sig").columns)
    except pd.errors.EmptyDataError:
        raise DataError(f"'{path}' is empty") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read '{path}' as CSV: {_first_line(err)}") from None
    names = {str(c).strip(): c for c in header}  # as written, by stripped name
    header = list(names)
    if _OTHER_LAYOUT in header:
        raise DataError(
            f"'{path}' has the exiD/inD/rounD layout (trackId, xCenter, ...), not "
            "highD's: those need their lanelet map for a road coordinate and are "
            "not read"
        )
    missing = [c for c in columns if c not in header]
    if missing:
        raise DataError(
            f"highD file '{path}' lacks the column(s) {', '.join(missing)}; it "
            f"has: {columns_text(header)}"
        )
    wanted = [*columns, *(c for c in optional if c in names)]
    try:
        # Only the used columns: a tracks file has 25 and ~10^5-10^6 rows.
        raw = pd.read_csv(
            path,
            encoding="utf-8-sig",
            usecols=[names[c] for c in wanted],
            skipinitialspace=True,
        )
    except (ValueError, UnicodeDecodeError) as err:
        raise DataError(f"cannot read '{path}' as CSV: {_first_line(err)}") from None
    return raw.rename(columns={names[c]: c for c in wanted})[wanted]


def _numbers(raw: pd.DataFrame, column: str, path: Path) -> np.ndarray:
    """A column as float64 (empty cells NaN).

    Raises:
        DataError: a cell that is not a number, with its line in the file.
    """
    text = raw[column]
    if pd.api.types.is_numeric_dtype(text):
        return text.to_numpy(np.float64, copy=True)
    values = pd.to_numeric(text, errors="coerce").to_numpy(np.float64, copy=True)
    bad = text.notna().to_numpy() & np.isnan(values)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"highD file '{path}': column {column} holds "
            f"{str(text.iloc[row])[:40]!r} on line {row + 2}, not a number"
        )
    return values


def _ids(raw: pd.DataFrame, column: str, path: Path, *, empty: int | None = None):
    """An id or frame column as int64; ``empty`` fills blank cells, else raises."""
    values = _numbers(raw, column, path)
    blank = ~np.isfinite(values)
    if blank.any():
        if empty is None:
            row = int(np.flatnonzero(blank)[0])
            raise DataError(
                f"highD file '{path}': column {column} is empty on line {row + 2}"
            )
        values[blank] = empty
    return np.rint(values).astype(np.int64)


# -------------------------------------------------------------- one recording
def _read_recording(
    recording: _Recording, keep: set[int], classes: set[str] | None
) -> tuple[pd.DataFrame, list[str], set[str]]:
    """One recording as table rows (plus a ``direction`` column), its notes and
    the vehicle classes it holds."""
    rate, location = _frame_rate(recording.recording_meta)
    meta = _vehicle_meta(recording.tracks_meta)
    raw = _read_csv(recording.tracks, _TRACK_COLUMNS)
    path = recording.tracks
    vehicle = _ids(raw, "id", path)
    unknown = np.setdiff1d(vehicle, meta.index.to_numpy())
    if unknown.size:
        raise DataError(
            f"vehicle(s) {', '.join(map(str, unknown[:10]))} of '{path}' are not "
            f"in '{recording.tracks_meta.name}'"
        )
    direction = meta["drivingDirection"].reindex(vehicle).to_numpy()  # (rows,)
    sign = np.where(direction == 1, DIRECTIONS[1][1], DIRECTIONS[2][1])  # (rows,)
    x = _numbers(raw, "x", path)
    length = _numbers(raw, "width", path)
    preceding = _ids(raw, "precedingId", path, empty=0)
    frame_number = _ids(raw, "frame", path)
    _check_unique(vehicle, frame_number, path)
    frame = pd.DataFrame(
        {
            "run": recording.number,
            "vehicle": vehicle.astype(str),
            "frame": frame_number,
            "time": frame_number / rate,
            # The front is the box's high-x edge when driving to +x, else its low.
            "position": np.where(sign > 0, x + length, -x),
            "speed": sign * _numbers(raw, "xVelocity", path),
            "acceleration": sign * _numbers(raw, "xAcceleration", path),
            "leader": np.where(preceding > 0, preceding.astype(str), ""),
            "lane": _lane_text(_numbers(raw, "laneId", path)),
            "length": length,
            "dhw": _numbers(raw, "dhw", path),
            "direction": direction,
        }
    )
    notes = [_describe(recording, rate, location, meta, frame)]
    frame = frame[np.isin(direction, sorted(keep))].reset_index(drop=True)
    frame["gap"], dhw_note = _gaps(frame, recording.number)
    notes.append(dhw_note)
    if classes is not None:
        frame["leader"] = _only_classes(frame, meta, classes)
    notes.extend(_quality_notes(frame, recording.number))
    present = set(meta["class"])
    return frame.drop(columns=["frame", "dhw"]), notes, present


def _frame_rate(path: Path) -> tuple[float, str]:
    """``frameRate`` [Hz] and ``locationId`` ("?" when absent) of a recording.

    Raises:
        DataError: no row, or a frame rate that is not a positive number.
    """
    raw = _read_csv(path, ("frameRate",), optional=("locationId",))
    if raw.empty:
        raise DataError(f"highD file '{path}' has no row")
    rate = float(_numbers(raw, "frameRate", path)[0])
    if not (np.isfinite(rate) and rate > 0):
        raise DataError(f"highD file '{path}': frameRate {rate} is not > 0")
    location = str(raw["locationId"].iloc[0]) if "locationId" in raw else "?"
    return rate, location


def _vehicle_meta(path: Path) -> pd.DataFrame:
    """``class`` and ``drivingDirection`` by vehicle id (the index).

    Raises:
        DataError: a drivingDirection other than 1 or 2, or an id given twice.
    """
    raw = _read_csv(path, _META_COLUMNS)
    meta = pd.DataFrame(
        {
            "class": raw["class"].fillna("").astype(str).str.strip().to_numpy(),
            "drivingDirection": _ids(raw, "drivingDirection", path),
        },
        index=_ids(raw, "id", path),
    )
    if meta.index.has_duplicates:
        twice = meta.index[meta.index.duplicated()][0]
        raise DataError(f"highD file '{path}' lists vehicle {twice} twice")
    odd = ~meta["drivingDirection"].isin(list(DIRECTIONS))
    if odd.any():
        raise DataError(
            f"highD file '{path}': vehicle {meta.index[odd.to_numpy()][0]} has "
            f"drivingDirection {meta['drivingDirection'][odd].iloc[0]}, not 1 or 2"
        )
    return meta


def _gaps(frame: pd.DataFrame, run: str) -> tuple[np.ndarray, str]:
    """(rows,) bumper-to-bumper gaps from ``dhw`` read as the positions say, and
    a note on the reading taken (module docstring)."""
    leaders = frame[["vehicle", "frame", "position", "length"]].rename(
        columns={
            "vehicle": "leader",
            "position": "position_l",
            "length": "length_l",
        }
    )
    joined = frame[["leader", "frame", "position", "length", "dhw"]].merge(
        leaders, on=["leader", "frame"], how="left", validate="many_to_one"
    )
    gap_from_positions = (
        joined["position_l"] - joined["length_l"] - joined["position"]
    ).to_numpy()
    dhw = joined["dhw"].to_numpy()
    usable = np.isfinite(gap_from_positions) & (dhw > 0)
    if not usable.any():
        return np.full(len(frame), np.nan), (
            f"recording {run}: no vehicle has a leader with a dhw: gap NaN"
        )
    length_l = joined["length_l"].to_numpy()
    length_f = joined["length"].to_numpy()
    beyond_gap = {  # (rows,) what each reading adds to the gap [m]
        name: a * length_l + b * length_f for name, (a, b) in DHW_READINGS.items()
    }
    misfit = {
        name: float(np.median(np.abs(dhw - gap_from_positions - extra)[usable]))
        for name, extra in beyond_gap.items()
    }
    best = min(misfit, key=misfit.__getitem__)
    if misfit[best] > DHW_TOLERANCE:
        return np.full(len(frame), np.nan), (
            f"recording {run}: dhw matches no reading of the positions (median "
            f"misfit {misfit[best]:.2f} m as {best}): gap NaN"
        )
    has_dhw = (frame["leader"].to_numpy() != "") & (dhw > 0)
    # The leader's length comes from its row; a leader without one leaves NaN.
    gap = np.where(has_dhw, dhw - beyond_gap[best], np.nan)
    a, b = DHW_READINGS[best]
    return gap, (
        f"recording {run}: dhw read as {best} (median misfit {misfit[best]:.3f} m "
        f"over {int(usable.sum())} rows): gap = dhw - {a:g} L_leader - "
        f"{b:g} L_follower"
    )


def _only_classes(
    frame: pd.DataFrame, meta: pd.DataFrame, classes: set[str]
) -> np.ndarray:
    """The leader column with "" on rows of followers of other classes: they
    remain as leaders, and form no couple of their own."""
    follower_class = meta["class"].str.lower().reindex(frame["vehicle"].astype(int))
    keep = follower_class.isin(classes).to_numpy()
    return np.where(keep, frame["leader"].to_numpy(), "")


def _describe(
    recording: _Recording,
    rate: float,
    location: str,
    meta: pd.DataFrame,
    frame: pd.DataFrame,
) -> str:
    """The recording in one line: site, rate, vehicles by class and direction."""
    in_tracks = meta.loc[np.unique(frame["vehicle"].astype(int))]
    classes = in_tracks["class"].value_counts()
    directions = in_tracks["drivingDirection"].value_counts()
    ordered = frame.sort_values(["vehicle", "frame"], kind="stable")
    same_vehicle = (
        ordered["vehicle"].to_numpy()[1:] == ordered["vehicle"].to_numpy()[:-1]
    )
    new_lane = ordered["lane"].to_numpy()[1:] != ordered["lane"].to_numpy()[:-1]
    lane_changes = int((same_vehicle & new_lane).sum())
    return (
        f"recording {recording.number} ({recording.tracks.name}, location "
        f"{location}, {rate:g} Hz): {len(in_tracks)} vehicles ("
        + ", ".join(f"{n} {c}" for c, n in classes.items())
        + "), "
        + ", ".join(
            f"{directions.get(d, 0)} {DIRECTIONS[d][0]} ({d})" for d in DIRECTIONS
        )
        + f"; {len(frame)} rows; {lane_changes} lane change(s)"
    )


def _quality_notes(frame: pd.DataFrame, run: str) -> list[str]:
    """Notes on rows driven backwards and leaders absent from the tracks."""
    notes = []
    backwards = int((frame["speed"].to_numpy() < 0).sum())
    if backwards:
        notes.append(
            f"recording {run}: {backwards} row(s) with speed < 0 in the direction "
            "of travel (xVelocity against drivingDirection)"
        )
    present = pd.MultiIndex.from_frame(frame[["vehicle", "frame"]])
    referenced = pd.MultiIndex.from_frame(
        frame[["leader", "frame"]].rename(columns={"leader": "vehicle"})
    )
    absent = (frame["leader"].to_numpy() != "") & ~referenced.isin(present)
    if absent.any():
        notes.append(
            f"recording {run}: {int(absent.sum())} row(s) name a leader that has "
            "no row at that frame (in another driving direction, or not kept)"
        )
    return notes


def _check_unique(vehicle: np.ndarray, frame: np.ndarray, path: Path) -> None:
    """Raises DataError when a vehicle has two rows at one frame."""
    twice = pd.DataFrame({"id": vehicle, "frame": frame}).duplicated().to_numpy()
    if twice.any():
        row = int(np.flatnonzero(twice)[0])
        raise DataError(
            f"highD file '{path}': vehicle {vehicle[row]} has two rows at frame "
            f"{frame[row]} (line {row + 2})"
        )


def _lane_text(lane: np.ndarray) -> np.ndarray:
    """Lane ids as text ("" where blank)."""
    text = np.full(lane.shape, "", dtype=object)
    known = np.isfinite(lane)
    text[known] = np.rint(lane[known]).astype(np.int64).astype(str)
    return text


# ------------------------------------------------------------------- options
def _parse_numbers(value: str | int | Iterable[int | str] | None) -> set[int] | None:
    """Recording numbers from ``3``, ``[1, "02"]`` or ``"1,2,5-7"``.

    Raises:
        DataError: an item that is not a number or a range ``a-b`` with a <= b.
    """
    if value is None:
        return None
    items = (
        str(value).split(",")
        if isinstance(value, (str, int))
        else [str(v) for v in value]
    )
    numbers: set[int] = set()
    for item in (i.strip() for i in items):
        if not item:
            continue
        first, dash, last = item.partition("-")
        if first.isdigit() and (not dash or last.strip().isdigit()):
            stop = int(last) if dash else int(first)
            if stop >= int(first):
                numbers.update(range(int(first), stop + 1))
                continue
        raise DataError(
            f"highD recordings: {item!r} is not a number or a range like 5-7"
        )
    if not numbers:
        raise DataError("highD recordings: none given")
    return numbers


def _parse_directions(value: str | int | Iterable[int | str] | None) -> set[int]:
    """drivingDirection codes from 1, 2, "upper", "lower" or a list of them.

    Raises:
        DataError: an unknown direction.
    """
    if value is None:
        return set(DIRECTIONS)
    items = (
        str(value).split(",")
        if isinstance(value, (str, int))
        else [str(v) for v in value]
    )
    by_name = {
        **{str(code): code for code in DIRECTIONS},
        **{name: code for code, (name, _) in DIRECTIONS.items()},
    }
    codes = set()
    for item in (i.strip().lower() for i in items if i.strip()):
        if item not in by_name:
            raise DataError(f"highD direction {item!r} is not 1, 2, 'upper' or 'lower'")
        codes.add(by_name[item])
    if not codes:
        raise DataError("highD directions: none given")
    return codes


def _parse_classes(value: str | Iterable[str] | None) -> set[str] | None:
    """Lower-case class names from "Car", "car,truck" or a list."""
    if value is None:
        return None
    items = str(value).split(",") if isinstance(value, str) else list(value)
    classes = {str(i).strip().lower() for i in items if str(i).strip()}
    if not classes:
        raise DataError("highD follower classes: none given")
    return classes


def _first_line(err: Exception) -> str:
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
