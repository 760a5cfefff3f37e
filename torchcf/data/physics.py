"""Units checked by physics: figures that only make sense in another unit.

Readers convert each column with the unit the user gives; columns that agree
with each other can still all be wrong (a file in feet read as metres keeps
positions and speeds consistent). What cars do is the second check, in SI:

==============  ==========================================  =====================
quantity        what cars do                                else
==============  ==========================================  =====================
time step       0.005-5 s (a 200 Hz radar to a 0.2 Hz log)  refused, the likely
                                                            time unit named
speed           99 % under :data:`MAX_SPEED` (252 km/h)     refused (km/h? ft/s?)
position rate   the median |dx/dt| within a factor 2 of     refused, the factor's
                the median recorded speed                   likely unit named
vehicle length  median of the known ones 2-12 m (cars       flagged in the notes
                3.5-5.5 m, buses and trucks to 18 m)        (feet?)
acceleration    99 % of the recorded ones under             flagged in the notes
                :data:`MAX_ACCELERATION` (1.2 g)            (ft/s^2?)
==============  ==========================================  =====================

A refusal is a :class:`~torchcf.data.pairset.DataError` naming the column and
the unit it most likely is; a flag is a note of the extraction, printed by
``torchcf data extract``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from torchcf.data.pairset import DataError

__all__ = ["MAX_SPEED", "check_time_step", "check_units"]

#: Fastest plausible road-vehicle speed [m/s] (252 km/h): anything faster is a
#: unit error (km/h or ft/s read as m/s).
MAX_SPEED = 70.0
#: Largest plausible |acceleration| of a road vehicle [m/s^2] (1.2 g: beyond
#: any emergency stop on dry asphalt).
MAX_ACCELERATION = 12.0
#: Sampling steps [s] of vehicle recordings: a 200 Hz radar to a 0.2 Hz log.
TIME_STEPS = (0.005, 5.0)
#: Median vehicle length [m] a data set of road vehicles has (cars 3.5-5.5 m;
#: a set of buses and trucks stays under 12 m in the median).
LENGTHS = (2.0, 12.0)

#: A time unit read for another: the factor the true step is of the read one,
#: and what to say.
_TIME_SLIPS = {
    1e3: "time in s read as ms? (--time-unit s)",
    1e-3: "time in ms read as s? (--time-unit ms)",
    10.0: "time in s read as ds? (--time-unit s)",
    0.1: "time in ds (frame numbers at 10 Hz) read as s? (--time-unit ds)",
}
#: Position rate over recorded speed -> the likely slip.
_RATE_SLIPS = {
    1 / 0.3048: "position in ft, speed in m/s? (--length-unit ft --speed-unit m/s)",
    0.3048: "position in m, speed in ft/s? (--speed-unit ft/s)",
    3.6: "speed in m/s read as km/h? (--speed-unit m/s)",
    1 / 3.6: "speed in km/h read as m/s? (--speed-unit km/h)",
    1 / 2.23694: "speed in mph read as m/s? (--speed-unit mph)",
}


def check_time_step(dt: float, source: str) -> None:
    """Refuse a median time step no vehicle recording has.

    Raises:
        DataError: ``dt`` outside :data:`TIME_STEPS`, naming the time column's
            likely unit.
    """
    low, high = TIME_STEPS
    if low <= dt <= high:
        return
    plausible = {
        f: why for f, why in _TIME_SLIPS.items() if low <= dt * f <= high
    }  # fmt: skip
    guess = (
        plausible[min(plausible, key=lambda f: abs(np.log(dt * f / 0.1)))]
        if plausible
        else "check the time column and its unit"
    )
    raise DataError(
        f"time steps of {dt:.3g} s (median) in '{source}': vehicle recordings "
        f"sample every {low:g}-{high:g} s, so the time column's unit cannot be "
        f"right ({guess})"
    )


def check_units(frame: pd.DataFrame, dt: float, source: str) -> list[str]:
    """Refuse speeds no road vehicle reaches and positions out of step with the
    speeds; flag vehicle lengths no road vehicle has.

    Args:
        frame: the trajectory rows with their integer ``step`` on the grid.
        dt: the grid's step [s].
        source: for messages.

    Returns:
        the flags (notes), one line each.

    Raises:
        DataError: the 99th percentile speed over :data:`MAX_SPEED`, or the
            median position rate |dx/dt| off the median speed by a factor
            outside [0.5, 2] (naming the unit slip it looks like).
    """
    speed = frame["speed"].to_numpy()
    finite = speed[np.isfinite(speed)]
    if finite.size and np.quantile(np.abs(finite), 0.99) > MAX_SPEED:
        top = float(np.quantile(np.abs(finite), 0.99))
        raise DataError(
            f"speeds up to {top:.1f} m/s (99th percentile) in '{source}': no road "
            f"vehicle is that fast (> {MAX_SPEED:g} m/s); the units cannot be right "
            "(the speed column in km/h or ft/s read as m/s?)"
        )
    by_vehicle = frame.groupby(["run", "vehicle"], sort=False)
    rate = (by_vehicle["position"].diff() / (by_vehicle["step"].diff() * dt)).to_numpy()
    moving = np.isfinite(rate) & (speed > 1.0)
    if moving.sum() >= 10:
        ratio = float(np.median(np.abs(rate[moving]))) / float(np.median(speed[moving]))
        if not 0.5 <= ratio <= 2.0:
            raise DataError(
                f"positions in '{source}' move {ratio:.2f} times as fast as the "
                "recorded speeds: the units of the position and speed columns "
                f"disagree ({_likely_rate_slip(ratio)})"
            )
    return [*_length_flags(frame, source), *_acceleration_flags(frame, source)]


def _acceleration_flags(frame: pd.DataFrame, source: str) -> list[str]:
    """A flag where 1 % of the accelerations (recorded, or derived from the
    speeds) exceed :data:`MAX_ACCELERATION`."""
    recorded = frame["acceleration"].to_numpy()
    recorded = np.abs(recorded[np.isfinite(recorded)])
    if recorded.size < 10:
        return []
    top = float(np.quantile(recorded, 0.99))
    if top <= MAX_ACCELERATION:
        return []
    guess = (
        f"the acceleration column in ft/s^2? ({top * 0.3048:.1f} m/s^2; "
        "--acceleration-unit ft/s^2)"
        if top * 0.3048 <= MAX_ACCELERATION
        else "noisy positions or a unit slip"
    )
    return [
        f"accelerations up to {top:.1f} m/s^2 (99th percentile) in '{source}': "
        f"road vehicles stay under {MAX_ACCELERATION:g} m/s^2; {guess}"
    ]


def _length_flags(frame: pd.DataFrame, source: str) -> list[str]:
    """A flag where the median known vehicle length is outside :data:`LENGTHS`."""
    lengths = frame.groupby(["run", "vehicle"], sort=False)["length"].median()
    lengths = lengths[np.isfinite(lengths)]
    if lengths.empty:
        return []
    median = float(lengths.median())
    low, high = LENGTHS
    if low <= median <= high:
        return []
    guess = (
        f"positions and lengths in ft? ({median * 0.3048:.1f} m; --length-unit ft)"
        if low <= median * 0.3048 <= high
        else "check the length and position columns"
    )
    return [
        f"vehicle lengths of {median:.1f} m (median of {len(lengths)} vehicles) in "
        f"'{source}': road vehicles are {low:g}-{high:g} m in the median; {guess}"
    ]


def _likely_rate_slip(ratio: float) -> str:
    best = min(_RATE_SLIPS, key=lambda f: abs(np.log(ratio / f)))
    if abs(np.log(ratio / best)) < 0.1:
        return _RATE_SLIPS[best]
    if ratio > 100 or ratio < 0.01:
        return "the time column's unit? positions move a power of ten off"
    return "check both"
