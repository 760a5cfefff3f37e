"""A closed circular track's lap coordinate, from planar positions and altitude.

Platoon tests on a circular platform (OpenACC's ZalaZONE dynamic platform: a
circle of radius about 143 m, tilted about 1 %) record every car's local East /
North position [m] and its altitude [m] beside its speed. A reader integrates
each run's speed from 0, so the runs of a campaign do not share a road frame
and no road effect can be offered. On a circle the shared frame is the lap
coordinate: the arc length from a reference point of the track, in the direction
of travel, and the road frame's period is the lap length ``C = 2 pi R``.

**Direction of travel.** A grade felt along the path flips its sign with the
direction: driving clockwise at angle ``phi`` is climbing where driving
anticlockwise is descending. Measured from the *lowest point* of the track in
each run's own direction, both directions see one profile whenever the track's
elevation is symmetric about that point, which holds exactly for a circle on a
plane of any tilt (``z(phi) = z0 - h cos(phi - phi_low)``, even about
``phi_low``): at arc length ``s`` from the lowest point the grade is
``(h / R) sin(s / R)`` either way. So the reference point is the lowest point of
the plane fitted to the altitudes (:func:`fit_tilt`); without altitudes it is
the point due East of the centre, which is exact only for runs that all go one
way.

Shapes: S samples; angles in radians, anticlockwise from East (``atan2(N, E)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pandas as pd

from torchcf.data.pairset import DataError

__all__ = [
    "OFF_TRACK",
    "Anchor",
    "Circle",
    "Tilt",
    "fit_circle",
    "fit_tilt",
    "lap_position",
    "place_on_lap",
    "travel_direction",
]

#: A sample farther than this from the fitted circle [m] is off the track
#: (lanes and GNSS scatter stay within a few metres; ZalaZONE's access roads
#: lie hundreds of metres away).
OFF_TRACK = 10.0


@dataclass(frozen=True)
class Circle:
    """A circle in the local plane.

    Attributes:
        east, north: centre [m].
        radius: [m].
    """

    east: float
    north: float
    radius: float

    @property
    def lap(self) -> float:
        """Lap length ``2 pi R`` [m]."""
        return 2.0 * math.pi * self.radius

    def angle(self, east: np.ndarray, north: np.ndarray) -> np.ndarray:
        """(S,) polar angle of the points about the centre [rad], in (-pi, pi]."""
        return np.arctan2(north - self.north, east - self.east)

    def distance(self, east: np.ndarray, north: np.ndarray) -> np.ndarray:
        """(S,) distance of the points from the circle [m] (>= 0)."""
        return np.abs(np.hypot(east - self.east, north - self.north) - self.radius)


def fit_circle(paths: list[tuple[np.ndarray, np.ndarray]]) -> Circle:
    """The circle most of the paths' points lie on.

    Every path (one vehicle's (S,) east and north [m], finite) proposes the
    circle fitted to its own points; the proposal with the most points of all
    paths within :data:`OFF_TRACK` wins and is refitted on those points (twice,
    so it settles), so that runs partly or wholly off the track (access
    roads) neither pull the circle nor choose it. A single fit to all points
    would: on ZalaZONE, three runs of nineteen that drive to the platform drew
    a circle of radius 251 m through nobody's path.

    Each fit is Kasa's algebraic least squares: ``E^2 + N^2 = 2 a E + 2 b N +
    c`` is linear in ``(a, b, c)``; the centre is ``(a, b)`` and ``R^2 = c +
    a^2 + b^2``.

    Raises:
        ValueError: no path whose points fit a circle (fewer than 3 points, or
            on a line).
    """
    proposals = []
    for east, north in paths:
        try:
            proposals.append(_kasa(east, north))
        except ValueError:
            continue
    if not proposals:
        raise ValueError("no path of 3 points or more that are not on a line")
    east = np.concatenate([e for e, _ in paths])
    north = np.concatenate([n for _, n in paths])
    circle = max(
        proposals, key=lambda c: int((c.distance(east, north) <= OFF_TRACK).sum())
    )
    for _ in range(2):
        near = circle.distance(east, north) <= OFF_TRACK
        circle = _kasa(east[near], north[near])
    return circle


def _kasa(east: np.ndarray, north: np.ndarray) -> Circle:
    if east.size < 3:
        raise ValueError(f"a circle needs 3 points or more, got {east.size}")
    design = np.column_stack([2.0 * east, 2.0 * north, np.ones_like(east)])
    coef, _, rank, _ = np.linalg.lstsq(design, east**2 + north**2, rcond=None)
    a, b, c = (float(v) for v in coef)
    if rank < 3 or c + a * a + b * b <= 0:
        raise ValueError("the points lie on a line, not on a circle")
    return Circle(a, b, math.sqrt(c + a * a + b * b))


@dataclass(frozen=True)
class Tilt:
    """The plane a circular track lies on, from altitudes round it.

    Attributes:
        lowest: polar angle of the track's lowest point [rad].
        grade: the plane's slope [1] (0.01 = 1 %): the steepest grade along the
            circle, reached a quarter lap from the lowest point.
        rms: root-mean-square altitude residual about the plane [m] (GNSS
            altitude noise, and how far the track is from a plane).
        samples: altitudes used.
    """

    lowest: float
    grade: float
    rms: float
    samples: int


def fit_tilt(angle: np.ndarray, altitude: np.ndarray, radius: float) -> Tilt:
    """The plane through altitudes measured round a circle of ``radius`` [m]:
    ``z = z0 + b cos(phi) + c sin(phi)`` by least squares, so ``z = z0 - h
    cos(phi - phi_low)`` with ``h = sqrt(b^2 + c^2)``, ``phi_low = atan2(-c,
    -b)`` and slope ``h / R``.

    Args:
        angle: (S,) polar angles [rad]; altitude: (S,) [m], both finite, S >= 3.

    Raises:
        ValueError: fewer than 3 samples or all at one angle.
    """
    if angle.size < 3:
        raise ValueError(f"a tilt needs 3 altitudes or more, got {angle.size}")
    design = np.column_stack([np.ones_like(angle), np.cos(angle), np.sin(angle)])
    coef, _, rank, _ = np.linalg.lstsq(design, altitude, rcond=None)
    if rank < 3:
        raise ValueError("the altitudes were measured at one point of the circle")
    _, b, c = (float(v) for v in coef)
    residual = altitude - design @ coef
    return Tilt(
        lowest=math.atan2(-c, -b),
        grade=math.hypot(b, c) / radius,
        rms=float(np.sqrt(np.mean(residual**2))),
        samples=int(angle.size),
    )


def travel_direction(angle: np.ndarray) -> int:
    """+1 when the (S,) polar angles [rad] of one vehicle's path increase on
    the whole (anticlockwise), -1 when they decrease (clockwise), 0 when the
    vehicle does not turn: the sign of the unwrapped net turn."""
    total = float(np.sum(np.diff(np.unwrap(angle))))
    return 1 if total > 0 else -1 if total < 0 else 0


def lap_position(
    angle: float, direction: int, reference: float, radius: float
) -> float:
    """The lap coordinate [m] of a point at polar ``angle`` [rad]: the arc
    length from the ``reference`` angle to it in the ``direction`` of travel
    (+1 anticlockwise, -1 clockwise), in ``[0, 2 pi radius)``."""
    turn = (direction * (angle - reference)) % (2.0 * math.pi)
    return float(turn * radius)


# ------------------------------------------------------- runs on the lap
class Anchor(NamedTuple):
    """A chain's anchor (the car its positions are placed from) with its
    planar path, as a platoon reader hands it to :func:`place_on_lap`."""

    vehicle: int  # the anchor's number
    chain: list[int]  # the vehicles placed from it
    east: np.ndarray  # (T,) E [m], NaN where missing
    north: np.ndarray  # (T,) N [m]
    altitude: np.ndarray  # (T,) Alt [m]; all NaN without the column


def place_on_lap(
    runs: list[str],
    frames: list[pd.DataFrame],
    anchors: list[list[Anchor]],
    source: str,
) -> tuple[list[pd.DataFrame], float, list[str]]:
    """The runs on one circular track's lap coordinate (module docstring, "Lap
    frame"): the frames of the runs kept, shifted; the lap length [m]; notes.

    Raises:
        DataError: no anchor with E/N positions, no run on the track, or runs
            both ways round it without altitudes to find its lowest point.
    """
    paths = [
        (a.east[ok], a.north[ok])
        for run_anchors in anchors
        for a in run_anchors
        if (ok := np.isfinite(a.east) & np.isfinite(a.north)).any()
    ]
    if not paths:
        raise DataError(
            f"lap_frame: no anchor vehicle of '{source}' has E/N positions "
            "(EK, NK columns), so no track can be fitted"
        )
    try:
        circle = fit_circle(paths)
    except ValueError as err:
        raise DataError(f"lap_frame: no circular track in '{source}': {err}") from None
    notes: list[str] = []
    kept: list[int] = []
    direction: dict[tuple[int, int], int] = {}
    for i, (run, run_anchors) in enumerate(zip(runs, anchors, strict=True)):
        why = _off_track(circle, run_anchors)
        if why is None:
            for a in run_anchors:
                ok = np.isfinite(a.east) & np.isfinite(a.north)
                direction[i, a.vehicle] = travel_direction(
                    circle.angle(a.east[ok], a.north[ok])
                )
            if 0 in (direction[i, a.vehicle] for a in run_anchors):
                why = "does not go round the track"
        if why is None:
            kept.append(i)
        else:
            notes.append(f"lap frame: run {run} left out: {why}")
    if not kept:
        raise DataError(
            f"lap_frame: no run of '{source}' stays on the circle of radius "
            f"{circle.radius:.1f} m (within {OFF_TRACK:g} m): {'; '.join(notes)}"
        )
    ways = [direction[i, a.vehicle] for i in kept for a in anchors[i]]
    reference, tilt_note = _lowest_point(
        circle, [anchors[i] for i in kept], set(ways), source
    )
    out, drift = [], {}
    for i in kept:
        frame = frames[i].copy()
        for a in anchors[i]:
            shift, parted = _lap_shift(
                circle, a, frame, direction[i, a.vehicle], reference
            )
            drift[runs[i]] = max(drift.get(runs[i], 0.0), parted)
            chain = frame["vehicle"].isin([str(k) for k in a.chain])
            frame.loc[chain, "position"] += shift
        out.append(frame)
    worst = max(drift, key=drift.get)
    notes += [
        f"lap frame: {len(kept)} of {len(runs)} runs on a circle of radius "
        f"{circle.radius:.1f} m about E {circle.east:.1f} m, N {circle.north:.1f} "
        f"m (lap {circle.lap:.1f} m); {ways.count(-1)} chain(s) clockwise, "
        f"{ways.count(1)} anticlockwise; position = the arc length from the "
        f"reference point in the direction of travel (each chain's odometer "
        f"shifted by its median difference to it, so every gap stays the "
        f"recorded IVS)",
        tilt_note,
        f"lap frame: the odometer and the arc length round the circle part by "
        f"up to {drift[worst]:.1f} m over a run (run {worst}): the speed "
        f"integrated against the path's angle",
    ]
    return out, round(circle.lap, 2), notes


def _off_track(circle: Circle, anchors: list[Anchor]) -> str | None:
    """Why a run's anchors do not stay on the circle, or None."""
    for a in anchors:
        ok = np.isfinite(a.east) & np.isfinite(a.north)
        if not ok.any():
            return f"vehicle {a.vehicle} has no E/N position"
        distance = circle.distance(a.east[ok], a.north[ok])
        if distance.max() > OFF_TRACK:
            return (
                f"vehicle {a.vehicle} drives up to {distance.max():.0f} m off the "
                f"circle ({(distance > OFF_TRACK).mean():.0%} of its samples over "
                f"{OFF_TRACK:g} m)"
            )
    return None


def _lowest_point(
    circle: Circle, anchors: list[list[Anchor]], ways: set[int], source: str
) -> tuple[float, str]:
    """The reference angle [rad] of the lap coordinate and its note: the
    track's lowest point from the anchors' altitudes, or East of the centre
    without altitudes when all runs go one way."""
    angle, altitude = [], []
    for a in (a for run_anchors in anchors for a in run_anchors):
        ok = np.isfinite(a.east) & np.isfinite(a.north) & np.isfinite(a.altitude)
        angle.append(circle.angle(a.east[ok], a.north[ok]))
        altitude.append(a.altitude[ok])
    angle_all, altitude_all = np.concatenate(angle), np.concatenate(altitude)
    try:
        tilt = fit_tilt(angle_all, altitude_all, circle.radius)
    except ValueError as err:
        if len(ways) > 1:
            raise DataError(
                f"lap_frame: the runs of '{source}' go both ways round the track "
                f"and their altitudes (AltK) cannot place its lowest point "
                f"({err}), so the two directions cannot share a grade profile"
            ) from None
        return 0.0, (
            f"lap frame: no altitudes ({err}); reference point due East of the "
            "centre (every run goes the same way)"
        )
    return tilt.lowest, (
        f"lap frame: the altitudes ({tilt.samples} samples) lie on a plane of "
        f"slope {100 * tilt.grade:.2f} % (rms {tilt.rms:.2f} m about it); "
        f"reference point its lowest point, at {math.degrees(tilt.lowest):.0f} "
        f"deg from East: the grade at lap coordinate s is about "
        f"{100 * tilt.grade:.2f} % x sin(s / {circle.radius:.1f} m) either way round"
    )


def _lap_shift(
    circle: Circle,
    anchor: Anchor,
    frame: pd.DataFrame,
    direction: int,
    reference: float,
) -> tuple[float, float]:
    """The shift [m] that puts an anchor's odometer on the lap coordinate, and
    the largest difference [m] left between the shifted odometer and the arc
    length round the circle.

    The arc length is the lap coordinate at the anchor's first sample with a
    position and an E/N, continued by the unwrapped angle; the shift is the
    median of arc length minus odometer over the run, so a slow drift between
    the two (the speed's bias, the antenna's own radius) is split about the
    middle of the run instead of growing from its start."""
    odometer = frame.loc[frame["vehicle"] == str(anchor.vehicle), "position"].to_numpy()
    ok = np.isfinite(odometer) & np.isfinite(anchor.east) & np.isfinite(anchor.north)
    if not ok.any():
        raise DataError(
            f"lap_frame: run {frame['run'].iloc[0]}: vehicle {anchor.vehicle} has "
            "no sample with both a speed-based position and an E/N position"
        )
    angle = circle.angle(anchor.east[ok], anchor.north[ok])
    start = lap_position(float(angle[0]), direction, reference, circle.radius)
    arc = start + direction * circle.radius * (np.unwrap(angle) - angle[0])
    shift = float(np.median(arc - odometer[ok]))
    return shift, float(np.abs(odometer[ok] + shift - arc).max())
