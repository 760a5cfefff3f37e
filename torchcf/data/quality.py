"""Quality filters for candidate windows cut from raw trajectories.

A candidate window is W consecutive time steps of one leader-follower couple (see
:mod:`torchcf.data.extract`). Each filter looks at the (W, K) arrays of K windows at
once and says which fail, with a number that shows by how much; a window is dropped
for the first filter it fails, in the order of :data:`FILTERS`:

==================  ==========================================================
filter              a window fails when
==================  ==========================================================
missing             a step has no row for the follower or the leader, or a
                    NaN in position, speed or acceleration (NaN or time gap)
non_positive_gap    the bumper-to-bumper gap ``x_l - L_l - x_f`` is <= 0 at
                    some step (the vehicles overlap: a position error)
jump                a position step disagrees with the speeds:
                    ``|x(k+1) - x(k) - (v(k) + v(k+1)) dt / 2| > jump`` [m] for
                    either vehicle (a GNSS or tracking jump)
speed_mismatch      a position step's speed departs from the recorded one:
                    ``|(x(k+1) - x(k)) / dt - (v(k) + v(k+1)) / 2| >
                    speed_mismatch`` [m/s] for either vehicle (positions built
                    from a noisy range sensor; the jump filter's measure per
                    second, so it does not loosen as the rate rises)
acceleration        ``|a| > max_acceleration`` [m/s^2] for either vehicle
gap_consistency     the recorded gap drifts from the speeds' integral:
                    ``max_k |g(k) - g(0) - sum (v_l - v_f) dt|`` [m] exceeds
                    ``gap_drift + gap_drift_rate * duration`` (trapezoid sum;
                    only where the source records a gap)
leader_standstill   the leader's speed stays under ``standstill_speed`` [m/s]
                    throughout (nothing to follow: every model fits it)
==================  ==========================================================

Every threshold can be switched off with ``None``. The defaults are for 10 Hz
data of passenger cars: 1 m per step is about three times the position noise of
tracked video or GNSS and far below a tracking jump; a step's speed may depart
from the recorded speed by 3 m/s (at 10 Hz, 0.3 m: the noise of a position
differenced over one step, where a range sensor's glitch reaches 9 m/s on the
ZalaZONE runs); 8 m/s^2 (0.8 g) is beyond the
emergency braking of most passenger cars on dry asphalt, so larger values are
measurement noise. The gap may drift by 2 m (a GNSS multipath error) plus 0.2 m/s
times the window's duration (a bias of 0.2 m/s, 0.7 km/h, between two vehicles'
speed logs): 10 m over 40 s. On the OpenACC samples the drift of clean windows
is 0.1-0.7 % of the distance driven (0.2-9 m over 40 s); a spacing log with a
jump or a shifted clock drifts by far more (18 m and 103 m there).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = ["FILTERS", "QualityThresholds", "Windows", "first_failure"]


@dataclass(frozen=True)
class QualityThresholds:
    """Thresholds of the quality filters; None switches a filter off.

    Attributes:
        jump: largest disagreement of a position step with the speeds [m].
        speed_mismatch: largest disagreement of a step's speed, position
            difference over dt, with the recorded speeds [m/s].
        max_acceleration: largest plausible |acceleration| [m/s^2].
        gap_drift: drift of the recorded gap from the integral of the speed
            difference allowed at any duration [m].
        gap_drift_rate: drift allowed per second of the window [m/s].
        standstill_speed: a leader slower than this throughout a window [m/s]
            stands still.
        non_positive_gap: drop windows whose gap is <= 0 at some step.
        missing: drop windows with a missing step or a NaN.
    """

    jump: float | None = 1.0
    speed_mismatch: float | None = 3.0
    max_acceleration: float | None = 8.0
    gap_drift: float | None = 2.0
    gap_drift_rate: float = 0.2
    standstill_speed: float | None = 0.5
    non_positive_gap: bool = True
    missing: bool = True


class Windows(NamedTuple):
    """K candidate windows of W steps each; every array is (W, K), SI units.

    ``present`` is False where a vehicle has no row at that step; values there
    are NaN. ``gap`` is the recorded bumper-to-bumper gap (NaN where the source
    records none) and ``leader_length`` the leader's length at each step [m].
    """

    present: np.ndarray
    x_lead: np.ndarray
    v_lead: np.ndarray
    a_lead: np.ndarray
    x_follow: np.ndarray
    v_follow: np.ndarray
    a_follow: np.ndarray
    gap: np.ndarray
    leader_length: np.ndarray
    dt: float


Check = Callable[[Windows, QualityThresholds], "tuple[np.ndarray, np.ndarray] | None"]


def _missing(w: Windows, q: QualityThresholds):
    """(fails (K,), number of missing steps (K,))."""
    if not q.missing:
        return None
    values = np.stack(
        [w.x_lead, w.v_lead, w.a_lead, w.x_follow, w.v_follow, w.a_follow]
    )
    bad = ~w.present | ~np.isfinite(values).all(axis=0)  # (W, K)
    count = bad.sum(axis=0)
    return count > 0, count.astype(float)


def _non_positive_gap(w: Windows, q: QualityThresholds):
    if not q.non_positive_gap:
        return None
    smallest = np.min(w.x_lead - w.leader_length - w.x_follow, axis=0)
    return smallest <= 0.0, smallest


def _jump(w: Windows, q: QualityThresholds):
    if q.jump is None:
        return None
    worst = np.maximum(
        _step_disagreement(w.x_lead, w.v_lead, w.dt),
        _step_disagreement(w.x_follow, w.v_follow, w.dt),
    )
    return worst > q.jump, worst


def _step_disagreement(x: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
    """(K,) max_k |x(k+1) - x(k) - (v(k) + v(k+1)) dt / 2| [m]."""
    if x.shape[0] < 2:
        return np.zeros(x.shape[1])
    step = np.diff(x, axis=0) - 0.5 * (v[1:] + v[:-1]) * dt
    return np.abs(step).max(axis=0)


def _speed_mismatch(w: Windows, q: QualityThresholds):
    if q.speed_mismatch is None:
        return None
    worst = (
        np.maximum(
            _step_disagreement(w.x_lead, w.v_lead, w.dt),
            _step_disagreement(w.x_follow, w.v_follow, w.dt),
        )
        / w.dt
    )
    return worst > q.speed_mismatch, worst


def _acceleration(w: Windows, q: QualityThresholds):
    if q.max_acceleration is None:
        return None
    worst = np.maximum(np.abs(w.a_lead).max(axis=0), np.abs(w.a_follow).max(axis=0))
    return worst > q.max_acceleration, worst


def _gap_consistency(w: Windows, q: QualityThresholds):
    if q.gap_drift is None:
        return None
    drift = gap_drift(w.gap, w.v_lead, w.v_follow, w.dt)
    duration = (w.gap.shape[0] - 1) * w.dt
    allowed = q.gap_drift + q.gap_drift_rate * duration
    return np.nan_to_num(drift, nan=0.0) > allowed, drift


def gap_drift(
    gap: np.ndarray, v_lead: np.ndarray, v_follow: np.ndarray, dt: float
) -> np.ndarray:
    """(K,) max_k |g(k) - g(0) - integral_0^k (v_l - v_f) dt| [m]; NaN without a gap.

    The integral is the cumulative trapezoid sum of the (W, K) speed difference,
    so a gap that moves exactly as the speeds say drifts by 0.
    """
    closing = v_lead - v_follow  # (W, K)
    integral = np.concatenate(
        [
            np.zeros((1, closing.shape[1])),
            np.cumsum(0.5 * (closing[1:] + closing[:-1]) * dt, axis=0),
        ]
    )
    drift = np.abs(gap - gap[:1] - integral)  # (W, K), NaN where no gap
    recorded = np.isfinite(gap).all(axis=0)
    largest = np.where(np.isfinite(drift), drift, 0.0).max(axis=0)
    return np.where(recorded, largest, np.nan)


def _leader_standstill(w: Windows, q: QualityThresholds):
    if q.standstill_speed is None:
        return None
    fastest = np.abs(w.v_lead).max(axis=0)
    return fastest < q.standstill_speed, fastest


#: The filters in the order they are applied, with the unit of their number.
FILTERS: dict[str, tuple[Check, str]] = {
    "missing": (_missing, "steps"),
    "non_positive_gap": (_non_positive_gap, "m (smallest gap)"),
    "jump": (_jump, "m (largest step disagreement)"),
    "speed_mismatch": (_speed_mismatch, "m/s (largest step-speed disagreement)"),
    "acceleration": (_acceleration, "m/s^2 (largest |a|)"),
    "gap_consistency": (_gap_consistency, "m (largest drift)"),
    "leader_standstill": (_leader_standstill, "m/s (leader's top speed)"),
}


def first_failure(
    windows: Windows, thresholds: QualityThresholds
) -> tuple[np.ndarray, np.ndarray]:
    """The first filter each window fails, and its number.

    Returns:
        ``(reason, value)``: (K,) object array of filter names ("" for a window
        that passes every filter) and (K,) float of the failing filter's number
        (NaN for passing windows).
    """
    k = windows.x_lead.shape[1]
    reason = np.full(k, "", dtype=object)
    value = np.full(k, np.nan)
    for name, (check, _) in FILTERS.items():
        result = check(windows, thresholds)
        if result is None:
            continue
        fails, number = result
        new = fails & (reason == "")
        reason[new] = name
        value[new] = number[new]
    return reason, value
