"""Read GPS logs: each vehicle's latitude/longitude fixes put on one road path.

Many field tests log every car by GNSS alone: time, latitude, longitude, perhaps
speed and heading, one file per car or one long table, the platoon's order known.
There is no road position and no gap; this reader makes them, so that positions,
gaps and speeds agree:

1. **Fixes.** The columns of :data:`GPS_COLUMNS` by name, or mapped with
   ``columns`` (``"vehicle=ID,time=t,lat=Lat,lon=Lon"``); ``vehicle`` defaults
   to the file stem (a folder of one file per car), ``run`` to the file stem
   where ``vehicle`` is a column. Time: seconds (``time_unit``), GPS week
   seconds (a drop of over half a week is the week's rollover: +604 800 s) or
   time stamps (text, read as dates; without a zone, UTC). A row without a
   finite fix in range is dropped as ``no fix``. ``heading`` is read and not
   used: the road's direction is the path vehicle's travel.
2. **Local frame.** pyproj projects each run's fixes into an azimuthal
   equidistant frame on the WGS 84 ellipsoid, centred on the run's mean fix
   (metres east, north: on a test track or a few km of road, distances are
   exact to well under a millimetre per kilometre).
3. **Reference path.** A path file (``lat``, ``lon`` columns, in driving order)
   or the platoon's own path: the track of its first vehicle (``platoon``'s
   first; else the vehicle with the most fixes), led in by the road another
   car drove before it first passed within :data:`JOIN` m of that track's first
   fix (the cars behind start before it) and led out by the road one drove
   after its last (the longest of each), resampled every :data:`PATH_STEP` m
   along its length, smoothed over :data:`PATH_SMOOTH` m (the receiver's noise
   off the road) and extended straight by :data:`PATH_EXTENSION` m at both
   ends.
4. **Road positions.** Each fix is projected onto the path. A vehicle's first
   fix is looked for within :data:`FIRST_REACH` m of where the path vehicle is
   at that time, each later one near the vehicle's previous position (so a
   loop driven twice counts its distance on instead of jumping back a lap).
   ``position`` is the distance along the path [m], increasing in the
   direction of travel. A fix over :data:`MAX_OFFSET` m from the path is
   dropped as ``off path``; one whose distance from the last kept fix implies
   over :data:`~torchcf.data.extract.MAX_SPEED` as ``jump``.
5. **One clock.** Receivers do not stamp on one grid: every vehicle's positions
   and speeds are interpolated onto its run's grid (the median step between
   fixes, from a whole multiple of it), between fixes at most
   :data:`BRIDGE` steps apart, so a dropout leaves its steps out (the
   extraction then drops the windows that cover them as ``missing``). Where
   the log records speeds, the positions are fused with them
   (:func:`fuse_with_speed`): a receiver's position differenced over one step
   is too noisy for the extraction's jump filter, its speed is not.
6. **Leaders.** ``leader_rule="column"`` reads a leader column; ``"platoon"`` takes
   ``platoon``'s order (each vehicle follows the one before it); ``"nearest"``
   the nearest vehicle ahead along the path at each step, within
   :data:`NEAREST_REACH` m. The default: the column where there is one, else the
   platoon where given, else the nearest.

Spacing: the positions are the antennas'. With the antenna at the same place in
every car, ``x_lead - x_follow`` is the front-to-front spacing the pairs need;
``length`` is left unknown (the extraction's ``default_length``), ``gap`` is
not measured.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from torchcf.data.extract import MAX_SPEED
from torchcf.data.formats.generic import (
    SPEED_UNITS,
    TIME_UNITS,
    column_map,
    read_header,
    read_selected,
    resolve_columns,
    source_files,
)
from torchcf.data.pairset import DataError
from torchcf.data.trajectory import TrajectoryTable

__all__ = [
    "GPS_COLUMNS",
    "LEADER_RULES",
    "GpsUnits",
    "LocalFrame",
    "ReferencePath",
    "fuse_with_speed",
    "read_gps",
]

#: The canonical columns of a GPS log; ``vehicle``, ``time``, ``lat`` and ``lon``
#: are required (``vehicle``: or the file stem).
GPS_COLUMNS = ("run", "vehicle", "time", "lat", "lon", "speed", "heading", "leader")
#: How each vehicle's leader is found.
LEADER_RULES = ("column", "platoon", "nearest")
#: Time formats: numbers in ``time_unit``, GPS week seconds, date stamps.
TIME_FORMATS = ("auto", "seconds", "gps-week", "timestamp")
#: Seconds in a GPS week (the week-seconds counter's rollover).
GPS_WEEK = 604_800.0
#: Spacing of the reference path's points [m] and the length it is smoothed
#: over [m] (a moving average of the resampled track).
PATH_STEP = 1.0
PATH_SMOOTH = 15.0
#: How far the path is extended straight beyond the path vehicle's first and
#: last fix [m].
PATH_EXTENSION = 500.0
#: How far from the path vehicle a vehicle's first fix is looked for [m].
FIRST_REACH = 1000.0
#: Margin [m] of the search window around a vehicle's expected next position.
SEARCH_MARGIN = 30.0
#: Largest distance of a kept fix from the path [m] (a lane or two, GNSS error).
MAX_OFFSET = 15.0
#: Steps a gap between fixes may span and still be interpolated over.
BRIDGE = 1.5
#: How near another vehicle must pass the path vehicle's first (last) fix
#: for its track before (after) it to lead the path in (out) [m].
JOIN = 5.0
#: Time constant [s] of the fusion of positions with recorded speeds: a car's
#: speed changes little within it, a receiver's position error wanders slower.
FUSION_TAU = 2.0
#: Passes of the path within this of a fix's closest one are candidates [m].
TIE = 1.0
#: How far ahead a leader is looked for [m] (``leader_rule="nearest"``).
NEAREST_REACH = 250.0


@dataclass(frozen=True)
class ReferencePath:
    """A polyline in a run's local frame and the distance along it.

    Attributes:
        xy: ``(M, 2)`` points [m], east and north, in driving order.
        s: ``(M,)`` distance along the path at each point [m], from 0 at the
            start of the extension behind the path vehicle's first fix.
    """

    xy: np.ndarray
    s: np.ndarray

    @classmethod
    def from_track(cls, xy: np.ndarray) -> ReferencePath:
        """The path of a track: resampled, smoothed, extended (module doc)."""
        dense = _resample(xy, PATH_STEP)
        width = max(1, int(round(PATH_SMOOTH / PATH_STEP)))
        smooth = _moving_average(dense, width)
        return cls.through(_extend(smooth, PATH_EXTENSION, PATH_STEP))

    @classmethod
    def through(cls, xy: np.ndarray) -> ReferencePath:
        """The path through ``xy`` as it is."""
        step = np.hypot(*np.diff(xy, axis=0).T)
        return cls(xy, np.concatenate([[0.0], np.cumsum(step)]))

    def locate(
        self, point: np.ndarray, low: float, high: float, near: float
    ) -> tuple[float, float]:
        """Where ``point`` projects onto the segments within ``[low, high]``
        along the path: the distance along it, and the point's distance from
        the path [m] (``inf`` when no segment lies in the window). Where the
        path passes the point more than once (a loop driven twice), the pass
        nearest ``near`` along the path, among those within :data:`TIE` m of
        the closest."""
        first = max(int(np.searchsorted(self.s, low)) - 1, 0)
        last = min(int(np.searchsorted(self.s, high)) + 1, len(self.s) - 1)
        if last <= first:
            return float("nan"), float("inf")
        a, b = self.xy[first:last], self.xy[first + 1 : last + 1]  # (W, 2) each
        ab = b - a
        length2 = np.maximum((ab**2).sum(1), 1e-12)
        u = np.clip(((point - a) * ab).sum(1) / length2, 0.0, 1.0)  # (W,)
        distance = np.hypot(*(point - (a + u[:, None] * ab)).T)
        along = self.s[first:last] + u * np.diff(self.s)[first:last]
        # each pass of the path by the point is a local minimum of the distance
        padded = np.concatenate([[np.inf], distance, [np.inf]])
        passes = (distance <= padded[:-2]) & (distance <= padded[2:])
        passes &= distance <= distance.min() + TIE
        k = int(np.flatnonzero(passes)[np.argmin(np.abs(along[passes] - near))])
        return float(along[k]), float(distance[k])


@dataclass(frozen=True)
class GpsUnits:
    """How a GPS log's times and speeds read. The fields are named as the
    options of ``data.raw`` and ``torchcf data extract``
    (:func:`torchcf.data.formats.reader_options`).

    Attributes:
        time_unit: unit of numeric times (a key of ``TIME_UNITS``).
        time_format: ``"seconds"``, ``"gps-week"``, ``"timestamp"`` or
            ``"auto"`` (numbers: seconds, week rollovers undone; text: stamps).
        speed_unit: unit of a speed column (a key of ``SPEED_UNITS``; None:
            m/s).
    """

    time_unit: str = "s"
    time_format: str = "auto"
    speed_unit: str | None = None


def read_gps(
    source: str | os.PathLike[str],
    *,
    columns: dict[str, str] | str | None = None,
    units: GpsUnits = GpsUnits(),
    leader_rule: str | None = None,
    platoon: str | None = None,
    path_file: str | os.PathLike[str] | None = None,
    sep: str = ",",
) -> TrajectoryTable:
    """Read GPS logs (a CSV, or a folder of them) into a trajectory table.

    Args:
        source: a CSV file, or a folder whose ``*.csv`` files are all read
            (one per vehicle, or long tables).
        columns: ``{canonical: source}`` over :data:`GPS_COLUMNS`, or its text
            form; None reads the canonical names.
        units: how the times and speeds read (:class:`GpsUnits`: seconds,
            their format found, m/s).
        leader_rule: one of :data:`LEADER_RULES`; None: the module
            docstring's default.
        platoon: the vehicles in driving order, ``"A,B,C"`` (A leads).
        path_file: a CSV of the reference path's ``lat``, ``lon`` in driving
            order (None: the platoon's path).
        sep: field separator.

    Returns:
        The table on one road frame per run, sorted, ``format="gps"``, with
        what was dropped and why in its notes.

    Raises:
        DataError: a missing source or column, fixes out of range, unknown
            units, rules or vehicles, a platoon without its vehicles, or no
            fix left.
    """
    given = column_map(columns, GPS_COLUMNS)
    time_unit, time_format = units.time_unit, units.time_format
    speed_unit = units.speed_unit or "m/s"
    _known(time_unit, TIME_UNITS, "time unit")
    _known(time_format, TIME_FORMATS, "time format")
    _known(speed_unit, SPEED_UNITS, "speed unit")
    order = [v.strip() for v in platoon.split(",") if v.strip()] if platoon else []
    paths = source_files(source, (".csv",), "gps")
    fixes = pd.concat([_read_one(p, given, sep) for p in paths], ignore_index=True)
    rule = _leader_rule(leader_rule, fixes, order)
    factor = TIME_UNITS[time_unit]
    fixes["time"] = fixes.groupby(["run", "vehicle"], sort=False)["time"].transform(
        lambda t: pd.Series(parse_times(t, time_format, factor), index=t.index)
    )  # per vehicle, in its file's order: a week's rollover is the vehicle's own
    fixes["speed"] = fixes["speed"] * SPEED_UNITS[speed_unit]
    dropped: dict[str, int] = {}
    fixes = _drop(fixes, ~_valid_fix(fixes), "no fix", dropped)
    if fixes.empty:
        raise DataError(
            f"no GPS fix in '{source}' with a finite latitude and longitude"
        )
    frames = []
    for run, part in fixes.groupby("run", sort=True):
        frames.append(_run_table(str(run), part, order, rule, path_file, sep, dropped))
    frame = pd.concat(frames, ignore_index=True)
    notes = [
        f"GPS: dropped {n} fix{'es' if n > 1 else ''} ({why})"
        for why, n in dropped.items()
        if n
    ]
    table = TrajectoryTable.from_frame(
        frame, source=str(source), format="gps", road_frame=True, notes=notes
    )
    return table.sorted()


def parse_times(values: pd.Series, time_format: str, factor: float) -> np.ndarray:
    """Times [s] of ``values``: numbers times ``factor`` (GPS week seconds with
    rollovers undone), or date stamps as seconds since 1970 (UTC).

    Raises:
        DataError: text that is neither a number nor a date.
    """
    numbers = pd.to_numeric(values, errors="coerce")
    as_text = time_format == "timestamp" or (
        time_format == "auto" and numbers.isna().all() and values.notna().any()
    )
    if as_text:
        stamps = pd.to_datetime(values, errors="coerce", utc=True)
        bad = stamps.isna() & values.notna()
        if bad.any():
            raise DataError(f"time {str(values[bad].iloc[0])[:40]!r} is not a date")
        return (stamps - pd.Timestamp(0, tz="UTC")).dt.total_seconds().to_numpy()
    bad = numbers.isna() & values.notna()
    if bad.any():
        raise DataError(f"time {str(values[bad].iloc[0])[:40]!r} is not a number")
    seconds = numbers.to_numpy(dtype=float) * factor
    if time_format in ("auto", "gps-week"):
        seconds = _undo_week_rollover(seconds)
    return seconds


def _undo_week_rollover(seconds: np.ndarray) -> np.ndarray:
    """GPS week seconds restart at 0 each week: a drop of more than half a week
    between consecutive rows is a rollover (rows of one file, in order)."""
    if len(seconds) < 2:
        return seconds
    drops = np.diff(seconds) < -GPS_WEEK / 2
    return seconds + GPS_WEEK * np.concatenate([[0], np.cumsum(drops)])


class LocalFrame:
    """An azimuthal equidistant frame on the WGS 84 ellipsoid centred on a
    point (pyproj): ``frame(lat, lon)`` gives ``(n, 2)`` metres east, north."""

    def __init__(self, lat0: float, lon0: float) -> None:
        from pyproj import Transformer

        self._to_local = Transformer.from_crs(
            "EPSG:4326",
            f"+proj=aeqd +lat_0={lat0!r} +lon_0={lon0!r} +datum=WGS84 +units=m",
            always_xy=True,
        )

    @classmethod
    def centred_on(cls, lat: np.ndarray, lon: np.ndarray) -> LocalFrame:
        """The frame centred on the mean of the fixes."""
        return cls(float(np.mean(lat)), float(np.mean(lon)))

    def __call__(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        east, north = self._to_local.transform(np.asarray(lon), np.asarray(lat))
        return np.column_stack([east, north])


def _read_one(path: Path, given: dict[str, str], sep: str) -> pd.DataFrame:
    """One file's fixes under the canonical names; ``vehicle`` (or ``run``)
    from the file stem where the file has none."""
    header = read_header(path, sep)
    names = {c: (c,) for c in GPS_COLUMNS}
    chosen = resolve_columns(path, header, given, names, ("time", "lat", "lon"))
    frame = read_selected(path, chosen, ("run", "vehicle", "leader"), sep)
    for column in ("lat", "lon", "speed", "heading"):
        if column in frame:
            frame[column] = pd.to_numeric(frame[column], errors="coerce")
        else:
            frame[column] = np.nan
    if "vehicle" not in frame:
        frame["vehicle"] = path.stem
    if "run" not in frame:
        frame["run"] = path.stem if "vehicle" in chosen else path.parent.name
    frame["leader"] = frame["leader"].fillna("") if "leader" in frame else ""
    return frame[list(GPS_COLUMNS)].astype({"run": str, "vehicle": str, "leader": str})


def _leader_rule(rule: str | None, fixes: pd.DataFrame, order: list[str]) -> str:
    """The leader rule asked for, or the default (module docstring)."""
    if rule is None:
        has_column = bool((fixes["leader"] != "").any())
        rule = "column" if has_column else "platoon" if order else "nearest"
    _known(rule, LEADER_RULES, "leader rule")
    if rule == "platoon":
        if len(order) < 2:
            raise DataError("leader 'platoon' needs the platoon's order, e.g. 'A,B,C'")
        missing = sorted(set(order) - set(fixes["vehicle"]))
        if missing:
            raise DataError(
                f"platoon vehicle(s) {', '.join(missing)} not in the logs; they "
                f"hold: {', '.join(sorted(set(fixes['vehicle']))[:12])}"
            )
    return rule


def _valid_fix(fixes: pd.DataFrame) -> pd.Series:
    lat, lon, time = fixes["lat"], fixes["lon"], fixes["time"]
    return (
        np.isfinite(lat) & np.isfinite(lon) & np.isfinite(time)
        & (lat.abs() <= 90.0) & (lon.abs() <= 180.0)
    )  # fmt: skip


def _drop(frame: pd.DataFrame, bad, why: str, dropped: dict[str, int]) -> pd.DataFrame:
    bad = np.asarray(bad, dtype=bool)
    dropped[why] = dropped.get(why, 0) + int(bad.sum())
    return frame.loc[~bad]


def _run_table(
    run: str,
    fixes: pd.DataFrame,
    order: list[str],
    rule: str,
    path_file: str | os.PathLike[str] | None,
    sep: str,
    dropped: dict[str, int],
) -> pd.DataFrame:
    """One run's rows of the trajectory table (module docstring, steps 2-6)."""
    fixes = fixes.sort_values(["vehicle", "time"], kind="stable")
    lat, lon = fixes["lat"].to_numpy(), fixes["lon"].to_numpy()
    frame = LocalFrame.centred_on(lat, lon)
    xy = frame(lat, lon)
    fixes = fixes.assign(x=xy[:, 0], y=xy[:, 1])
    tracks = {str(v): part for v, part in fixes.groupby("vehicle", sort=True)}
    guide = _path_vehicle(tracks, order)
    if path_file is not None:
        path = ReferencePath.through(_path_points(path_file, frame, sep))
        start = None
    else:
        track, behind = _platoon_track(tracks, guide)
        path = ReferencePath.from_track(track)
        start = PATH_EXTENSION + behind
    guide_s = _positions(path, tracks[guide], start, dropped)
    dt = _grid_step(tracks.values())
    rows = []
    for vehicle, track in tracks.items():
        s = guide_s if vehicle == guide else _positions(path, track, guide_s, dropped)
        rows.append(_on_grid(run, vehicle, track, s, dt))
    table = pd.concat(rows, ignore_index=True)
    table["leader"] = _leaders(table, rule, order)
    return table


def _path_vehicle(tracks: dict[str, pd.DataFrame], order: list[str]) -> str:
    """The vehicle whose track is the path: the platoon's first, else the one
    with the most fixes."""
    if order and order[0] in tracks:
        return order[0]
    return max(tracks, key=lambda v: (len(tracks[v]), v))


def _platoon_track(
    tracks: dict[str, pd.DataFrame], guide: str
) -> tuple[np.ndarray, float]:
    """The path vehicle's track, led in by the road the others drove before
    they reached its first fix and led out by the road they drove after its
    last (the longest of each), so that the whole platoon lies on the path;
    and the length [m] of the lead-in."""
    xy = tracks[guide][["x", "y"]].to_numpy()
    lead_in, lead_out = xy[:0], xy[:0]
    for vehicle, track in tracks.items():
        if vehicle == guide:
            continue
        other = track[["x", "y"]].to_numpy()
        at_start = np.flatnonzero(np.hypot(*(other - xy[0]).T) <= JOIN)
        at_end = np.flatnonzero(np.hypot(*(other - xy[-1]).T) <= JOIN)
        if at_start.size and _length(other[: at_start[0]]) > _length(lead_in):
            lead_in = other[: at_start[0]]
        if at_end.size and _length(other[at_end[-1] + 1 :]) > _length(lead_out):
            lead_out = other[at_end[-1] + 1 :]
    track = np.concatenate([lead_in, xy, lead_out])
    joined = _length(np.concatenate([lead_in, xy[:1]])) if len(lead_in) else 0.0
    return track, joined


def _length(xy: np.ndarray) -> float:
    """The length of a polyline [m]."""
    return float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0


def _path_points(path_file, frame: LocalFrame, sep: str) -> np.ndarray:
    """A path file's points (``lat``, ``lon`` columns) in the run's frame."""
    file = Path(path_file)
    header = read_header(file, sep)
    names = {"lat": ("lat",), "lon": ("lon",)}
    chosen = resolve_columns(file, header, {}, names, ("lat", "lon"))
    points = read_selected(file, chosen, (), sep).apply(pd.to_numeric, errors="coerce")
    points = points.dropna()
    if len(points) < 2:
        raise DataError(f"path file '{file}' holds fewer than 2 points")
    return frame(points["lat"].to_numpy(), points["lon"].to_numpy())


def _positions(
    path: ReferencePath,
    track: pd.DataFrame,
    guide: tuple[np.ndarray, np.ndarray] | float | None,
    dropped: dict[str, int],
) -> tuple[np.ndarray, np.ndarray]:
    """``(times, positions)`` of a track's kept fixes along ``path``
    (module docstring, step 4). ``guide``, for the first fix: the path
    vehicle's ``(times, positions)``, or where along the path the path vehicle
    starts, or None (a path file: anywhere along it)."""
    times = track["time"].to_numpy()
    xy = track[["x", "y"]].to_numpy()
    kept_t, kept_s = [], []
    off = jumps = 0
    previous: tuple[float, float] | None = None  # (time, position)
    for t, point in zip(times, xy, strict=True):
        if previous is None:
            if guide is None:
                near, low, high = 0.0, -np.inf, np.inf
            else:
                near = guide if np.isscalar(guide) else float(np.interp(t, *guide))
                low, high = near - FIRST_REACH, near + FIRST_REACH
        else:
            near = previous[1]
            reach = MAX_SPEED * max(t - previous[0], 0.0) + SEARCH_MARGIN
            low, high = near - SEARCH_MARGIN, near + reach
        along, distance = path.locate(point, low, high, near)
        if not distance <= MAX_OFFSET:
            off += 1
            continue
        if previous is not None and t > previous[0]:
            if abs(along - previous[1]) / (t - previous[0]) > MAX_SPEED:
                jumps += 1
                continue
        kept_t.append(t)
        kept_s.append(along)
        previous = (t, along)
    dropped["off path"] = dropped.get("off path", 0) + off
    dropped["jump"] = dropped.get("jump", 0) + jumps
    return np.asarray(kept_t, dtype=float), np.asarray(kept_s, dtype=float)


def _grid_step(tracks: Iterable[pd.DataFrame]) -> float:
    """The median step between consecutive fixes of every vehicle [s]."""
    steps = np.concatenate([np.diff(t["time"].to_numpy()) for t in tracks])
    steps = steps[steps > 0]
    if steps.size == 0:
        raise DataError(
            "GPS logs with fewer than 2 fixes per vehicle have no time step"
        )
    return float(np.median(steps))


def _on_grid(
    run: str,
    vehicle: str,
    track: pd.DataFrame,
    kept: tuple[np.ndarray, np.ndarray],
    dt: float,
) -> pd.DataFrame:
    """A vehicle's positions (and recorded speeds) on its run's time grid,
    interpolated between kept fixes at most :data:`BRIDGE` steps apart."""
    times, s = kept
    columns = ("run", "vehicle", "time", "position", "speed", "leader")
    if times.size < 2:
        return pd.DataFrame({c: [] for c in columns})
    grid = np.arange(np.ceil(times[0] / dt), np.floor(times[-1] / dt) + 1) * dt
    eps = 1e-6 * dt  # a grid step on a fix's stamp, within rounding
    before = np.clip(np.searchsorted(times, grid + eps, side="right") - 1, 0, None)
    after = np.minimum(before + 1, times.size - 1)
    on_fix = np.abs(times[before] - grid) <= eps
    bridged = on_fix | (times[after] - times[before] <= BRIDGE * dt + eps)
    grid = grid[bridged]
    position = np.interp(grid, times, s)
    fix_times, recorded = track["time"].to_numpy(), track["speed"].to_numpy()
    speed = (
        np.interp(grid, fix_times, recorded)
        if np.isfinite(recorded).all()
        else np.full(grid.size, np.nan)
    )
    if np.isfinite(speed).all():
        position = fuse_with_speed(position, speed, grid, dt)
    last_fix = np.clip(np.searchsorted(fix_times, grid, side="right") - 1, 0, None)
    leader = track["leader"].to_numpy()[last_fix]  # the latest fix's, a column's
    return pd.DataFrame(
        {"run": run, "vehicle": vehicle, "time": grid, "position": position,
         "speed": speed, "leader": leader}
    )  # fmt: skip


def fuse_with_speed(
    position: np.ndarray, speed: np.ndarray, time: np.ndarray, dt: float
) -> np.ndarray:
    """Positions along the road [m] fused with the recorded speeds [m/s] by a
    complementary filter of time constant :data:`FUSION_TAU`:

        p(k) = alpha (p(k-1) + (v(k-1) + v(k)) dt / 2) + (1 - alpha) s(k),
        alpha = tau / (tau + dt),

    restarted at every gap in ``time``. Over one step a position follows the
    speed (a receiver's speed is far less noisy than its position differenced
    over 0.1 s); over many it follows the fixes, so it does not drift. White
    position noise falls by about ``sqrt(dt / (2 tau))`` (0.16 at 10 Hz); a
    speed bias ``b`` shifts it by ``b tau``."""
    alpha = FUSION_TAU / (FUSION_TAU + dt)
    fused = position.copy()
    for k in range(1, position.size):
        if time[k] - time[k - 1] > BRIDGE * dt:  # a dropout: start again
            continue
        step = 0.5 * (speed[k - 1] + speed[k]) * (time[k] - time[k - 1])
        fused[k] = alpha * (fused[k - 1] + step) + (1.0 - alpha) * position[k]
    return fused


def _leaders(frame: pd.DataFrame, rule: str, order: list[str]) -> pd.Series:
    """Each row's leader under ``rule`` (module docstring, step 6)."""
    if rule == "platoon":
        ahead = {order[i]: order[i - 1] for i in range(1, len(order))}
        return frame["vehicle"].map(ahead).fillna("")
    if rule == "column":
        return frame["leader"]
    leaders = pd.Series("", index=frame.index)
    for _, at in frame.groupby("time", sort=False):
        if len(at) < 2:
            continue
        order_at = at.sort_values("position")
        positions = order_at["position"].to_numpy()
        names = order_at["vehicle"].to_numpy()
        gaps = np.diff(positions)
        close = gaps <= NEAREST_REACH
        index = order_at.index.to_numpy()
        leaders.loc[index[:-1][close]] = names[1:][close]
    return leaders


def _known(value: str, known: Iterable[str], what: str) -> None:
    if value not in known:
        raise DataError(f"unknown {what} {value!r}; known: {', '.join(known)}")


# ------------------------------------------------------------------ geometry
def _resample(xy: np.ndarray, step: float) -> np.ndarray:
    """``(M, 2)`` points every ``step`` m along the polyline ``xy`` (repeated
    points, a car standing still, dropped)."""
    moved = np.concatenate([[True], np.hypot(*np.diff(xy, axis=0).T) > 1e-6])
    xy = xy[moved]
    if len(xy) < 2:
        raise DataError("the path vehicle does not move: no path to put fixes on")
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    at = np.arange(0.0, along[-1], step)
    return np.column_stack(
        [np.interp(at, along, xy[:, 0]), np.interp(at, along, xy[:, 1])]
    )


def _moving_average(xy: np.ndarray, width: int) -> np.ndarray:
    """``xy`` averaged over ``width`` points, the ends over what there is."""
    if width < 2 or len(xy) < width:
        return xy
    kernel = np.ones(width)
    counts = np.convolve(np.ones(len(xy)), kernel, mode="same")
    return np.column_stack(
        [np.convolve(xy[:, k], kernel, mode="same") / counts for k in range(2)]
    )


def _extend(xy: np.ndarray, length: float, step: float) -> np.ndarray:
    """``xy`` extended straight by ``length`` m at both ends, along its end
    directions (taken over the last ``PATH_SMOOTH`` m)."""
    reach = min(max(int(PATH_SMOOTH / step), 1), len(xy) - 1)
    offsets = np.arange(1, int(length / step) + 1)[:, None] * step  # (E, 1)

    def unit(v: np.ndarray) -> np.ndarray:
        return v / max(float(np.hypot(*v)), 1e-12)

    back = unit(xy[0] - xy[reach])
    ahead = unit(xy[-1] - xy[-1 - reach])
    before = xy[0] + offsets[::-1] * back
    after = xy[-1] + offsets * ahead
    return np.concatenate([before, xy, after])
