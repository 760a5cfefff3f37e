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

import numpy as np

__all__ = [
    "OFF_TRACK",
    "Circle",
    "Tilt",
    "fit_circle",
    "fit_tilt",
    "lap_position",
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
