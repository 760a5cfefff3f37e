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

The first five judge single steps or links (the move from one step to the
next), and a window's number is their worst over the window. Whole couples
(``window="whole"`` in :mod:`torchcf.data.extract`) use them step by step
(:func:`step_failures`): a couple is cut where a step or a link fails, and
``gap_consistency`` and ``leader_standstill``, which judge a stretch as a
whole, then judge each stretch that is left.

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

__all__ = [
    "FILTERS",
    "LINK_FILTERS",
    "STEP_FILTERS",
    "QualityThresholds",
    "StepFailures",
    "Windows",
    "first_failure",
    "step_failures",
    "worst",
]


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


# The step-wise measures: one number per step (W, K) or per link, the move
# from one step to the next (W - 1, K). A window's check reduces them over the
# window; a whole couple is cut where they fail (:func:`step_failures`).
def _missing_steps(w: Windows) -> np.ndarray:
    """(W, K) True where a step has no row or a NaN in a series."""
    values = np.stack(
        [w.x_lead, w.v_lead, w.a_lead, w.x_follow, w.v_follow, w.a_follow]
    )
    return ~w.present | ~np.isfinite(values).all(axis=0)


def _gaps(w: Windows) -> np.ndarray:
    """(W, K) bumper-to-bumper gap ``x_l - L_l - x_f`` [m]."""
    return w.x_lead - w.leader_length - w.x_follow


def _link_disagreement(w: Windows) -> np.ndarray:
    """(W - 1, K) |x(k+1) - x(k) - (v(k) + v(k+1)) dt / 2| [m], the larger of
    the two vehicles'."""
    return np.maximum(
        _step_disagreement(w.x_lead, w.v_lead, w.dt),
        _step_disagreement(w.x_follow, w.v_follow, w.dt),
    )


def _step_disagreement(x: np.ndarray, v: np.ndarray, dt: float) -> np.ndarray:
    """(W - 1, K) |x(k+1) - x(k) - (v(k) + v(k+1)) dt / 2| [m]."""
    return np.abs(np.diff(x, axis=0) - 0.5 * (v[1:] + v[:-1]) * dt)


def _largest_link_disagreement(w: Windows) -> np.ndarray:
    """(K,) the window's largest link disagreement [m] (0 for one step)."""
    if w.x_lead.shape[0] < 2:
        return np.zeros(w.x_lead.shape[1])
    return _link_disagreement(w).max(axis=0)


def _abs_acceleration(w: Windows) -> np.ndarray:
    """(W, K) the larger |a| of the two vehicles [m/s^2]."""
    return np.maximum(np.abs(w.a_lead), np.abs(w.a_follow))


def _missing(w: Windows, q: QualityThresholds):
    """(fails (K,), number of missing steps (K,))."""
    if not q.missing:
        return None
    count = _missing_steps(w).sum(axis=0)
    return count > 0, count.astype(float)


def _non_positive_gap(w: Windows, q: QualityThresholds):
    if not q.non_positive_gap:
        return None
    smallest = np.min(_gaps(w), axis=0)
    return smallest <= 0.0, smallest


def _jump(w: Windows, q: QualityThresholds):
    if q.jump is None:
        return None
    worst = _largest_link_disagreement(w)
    return worst > q.jump, worst


def _speed_mismatch(w: Windows, q: QualityThresholds):
    if q.speed_mismatch is None:
        return None
    worst = _largest_link_disagreement(w) / w.dt
    return worst > q.speed_mismatch, worst


def _acceleration(w: Windows, q: QualityThresholds):
    if q.max_acceleration is None:
        return None
    worst = _abs_acceleration(w).max(axis=0)
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


#: The filters that judge one step, or one link (the move from a step to the
#: next), rather than a whole window: where one fails, a whole couple is cut
#: (:func:`step_failures`); the others judge each stretch that is left.
STEP_FILTERS = ("missing", "non_positive_gap", "acceleration")
LINK_FILTERS = ("jump", "speed_mismatch")


class StepFailures(NamedTuple):
    """The first step-wise filter each step and each link of W steps fails.

    ``steps``: (W, K) object array of filter names ("" where a step passes),
    ``step_values``: (W, K) that filter's number at the step; ``links`` and
    ``link_values``: the same, (W - 1, K), for the move from step k to k + 1.
    Numbers are in the filter's unit (:data:`FILTERS`); a missing step counts 1.
    """

    steps: np.ndarray
    step_values: np.ndarray
    links: np.ndarray
    link_values: np.ndarray


def _step_checks(
    w: Windows, q: QualityThresholds
) -> dict[str, tuple[np.ndarray, np.ndarray] | None]:
    """Each step-wise filter's ``(fails, number)`` per step or link, None when off.

    NaN compares False, so a NaN step fails ``missing`` alone.
    """
    missing, gaps = _missing_steps(w), _gaps(w)
    link, accel = _link_disagreement(w), _abs_acceleration(w)
    checks: dict[str, tuple[np.ndarray, np.ndarray] | None] = dict.fromkeys(
        (*STEP_FILTERS, *LINK_FILTERS)
    )
    if q.missing:
        checks["missing"] = missing, missing.astype(float)
    if q.non_positive_gap:
        checks["non_positive_gap"] = gaps <= 0.0, gaps
    if q.jump is not None:
        checks["jump"] = link > q.jump, link
    if q.speed_mismatch is not None:
        checks["speed_mismatch"] = link / w.dt > q.speed_mismatch, link / w.dt
    if q.max_acceleration is not None:
        checks["acceleration"] = accel > q.max_acceleration, accel
    return checks


def step_failures(windows: Windows, thresholds: QualityThresholds) -> StepFailures:
    """Where the step-wise filters (:data:`STEP_FILTERS`, :data:`LINK_FILTERS`)
    fail, step by step and link by link, each naming the first it fails in the
    order of :data:`FILTERS` (the window checks reduce these same numbers)."""
    n_steps, k = windows.x_lead.shape
    steps = np.full((n_steps, k), "", dtype=object)
    links = np.full((max(n_steps - 1, 0), k), "", dtype=object)
    step_values, link_values = (
        np.full(steps.shape, np.nan),
        np.full(links.shape, np.nan),
    )
    checks = _step_checks(windows, thresholds)
    for name in FILTERS:  # the order of the window checks
        if checks.get(name) is None:
            continue
        fails, number = checks[name]
        names, values = (
            (steps, step_values) if name in STEP_FILTERS else (links, link_values)
        )
        new = fails & (names == "")
        names[new] = name
        values[new] = number[new]
    return StepFailures(steps, step_values, links, link_values)


def worst(name: str, numbers: np.ndarray) -> float:
    """A step-wise filter's number over several steps or links, as its window
    check reduces it (:data:`FILTERS`' units): the count of missing steps, the
    smallest gap, else the largest number."""
    if name == "missing":
        return float(numbers.size)
    if name == "non_positive_gap":
        return float(numbers.min())
    return float(numbers.max())
