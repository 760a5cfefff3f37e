"""The long trajectory table: raw measurements before they become pairs.

Every reader of a raw format (:mod:`torchcf.data.formats`) turns its source into one
:class:`TrajectoryTable`, and pair extraction (:mod:`torchcf.data.extract`) turns a
table into a :class:`~torchcf.data.pairset.PairSet`. The table is the only contract
between the two: one row per vehicle and time step, in SI units.

Columns of ``TrajectoryTable.frame`` (a pandas DataFrame):

============  =======  =========  ==================================================
column        dtype    unit       meaning
============  =======  =========  ==================================================
run           str      -          recording the row belongs to (a file, a period);
                                  vehicle ids are unique within a run
vehicle       str      -          vehicle id within the run
time          float64  s          time stamp on the run's clock
position      float64  m          front-bumper position along the lane / road;
                                  increases in the direction of travel
speed         float64  m/s        NaN where the source has none (then derived)
acceleration  float64  m/s^2      NaN where the source has none (then derived)
leader        str      -          id of the vehicle ahead in the same lane and run;
                                  "" when there is none
lane          str      -          lane id; "" when the source does not say
length        float64  m          vehicle length; NaN when the source does not say
gap           float64  m          recorded bumper-to-bumper gap to the leader (the
                                  leader's rear to this vehicle's front); NaN when
                                  the source records none
mode          str      -          control mode, e.g. "ACC" or "Human"; "" unknown
============  =======  =========  ==================================================

Missing measurements are NaN (numeric columns) or "" (text columns), never a
sentinel such as NGSIM's 9999.99: readers translate those. Rows may come in any
order; :meth:`TrajectoryTable.sorted` orders them by run, vehicle and time.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pandas as pd

from torchcf.data.pairset import DataError

__all__ = ["COLUMNS", "NUMERIC", "TEXT", "TrajectoryTable"]

#: Text columns and numeric columns of the table, in the canonical order.
TEXT: tuple[str, ...] = ("run", "vehicle", "leader", "lane", "mode")
NUMERIC: tuple[str, ...] = (
    "time",
    "position",
    "speed",
    "acceleration",
    "length",
    "gap",
)
COLUMNS: tuple[str, ...] = (
    "run",
    "vehicle",
    "time",
    "position",
    "speed",
    "acceleration",
    "leader",
    "lane",
    "length",
    "gap",
    "mode",
)
#: Columns every row must have a value in.
REQUIRED: tuple[str, ...] = ("run", "vehicle", "time")


@dataclass(frozen=True, eq=False)
class TrajectoryTable:
    """Raw trajectories of many vehicles, one row per vehicle and time step, SI.

    Attributes:
        frame: the rows, with exactly the columns of :data:`COLUMNS` (see the
            module docstring for their units); built by :meth:`from_frame`.
        source: where the rows came from (a file or folder), for messages and
            the pair index.
        format: the reader that produced the table ("ngsim", "openacc", "csv").
        road_frame: True when all positions of the table (every run) lie on
            one road frame, so pairs cut from it share road effects such as a
            grade profile; False when they do not (e.g. platoon files recorded
            on different roads); None when the source does not say.
        road_period: the lap length [m] when that road is a closed track
            (positions are odometers round it), else None.
        notes: what the reader found and handled (one line each, for humans).
    """

    frame: pd.DataFrame
    source: str = ""
    format: str = ""
    road_frame: bool | None = None
    notes: tuple[str, ...] = ()
    road_period: float | None = None

    @classmethod
    def from_frame(
        cls,
        frame: pd.DataFrame,
        *,
        source: str = "",
        format: str = "",
        road_frame: bool | None = None,
        notes: tuple[str, ...] | list[str] = (),
        road_period: float | None = None,
    ) -> TrajectoryTable:
        """Build a table from a DataFrame holding some of :data:`COLUMNS`.

        Missing optional columns are added (NaN or ""); extra columns are
        dropped; text columns become ``str`` and numeric ones ``float64``.

        Raises:
            DataError: a required column is missing or has empty cells, a
                numeric column holds text, or the table has no row.
        """
        missing = [c for c in ("vehicle", "time") if c not in frame.columns]
        if missing:
            raise DataError(
                f"trajectory table from '{source}' lacks the column(s) "
                f"{', '.join(missing)}"
            )
        if len(frame) == 0:
            raise DataError(f"trajectory table from '{source}' has no row")
        out = pd.DataFrame(index=pd.RangeIndex(len(frame)))
        for column in COLUMNS:
            if column in TEXT:
                values = (
                    frame[column].to_numpy()
                    if column in frame.columns
                    else np.full(len(frame), "" if column != "run" else source)
                )
                out[column] = [_text(v) for v in values]
            else:
                out[column] = (
                    _numeric(frame[column], column, source)
                    if column in frame.columns
                    else np.full(len(frame), np.nan)
                )
        for column in REQUIRED:
            empty = (
                (out[column] == "").to_numpy()
                if column in TEXT
                else ~np.isfinite(out[column].to_numpy())
            )
            if empty.any():
                row = int(np.flatnonzero(empty)[0])
                raise DataError(
                    f"trajectory table from '{source}': column '{column}' has "
                    f"{int(empty.sum())} empty or non-finite cell(s), first at "
                    f"data row {row + 1}"
                )
        return cls(
            frame=out,
            source=str(source),
            format=str(format),
            road_frame=road_frame,
            notes=tuple(notes),
            road_period=road_period,
        )

    def sorted(self) -> TrajectoryTable:
        """The same rows ordered by run, vehicle and time (stable)."""
        frame = self.frame.sort_values(
            ["run", "vehicle", "time"], kind="stable"
        ).reset_index(drop=True)
        return dataclasses.replace(self, frame=frame)

    def with_notes(self, *notes: str) -> TrajectoryTable:
        return dataclasses.replace(self, notes=(*self.notes, *notes))

    @property
    def n_vehicles(self) -> int:
        """Distinct (run, vehicle) couples."""
        return int(self.frame.groupby(["run", "vehicle"], sort=False).ngroups)

    @property
    def runs(self) -> list[str]:
        return sorted(set(self.frame["run"]))


def _text(value) -> str:
    """A cell as an id string: NaN and None are "", 12.0 becomes "12"."""
    if value is None:
        return ""
    if isinstance(value, float):
        if not np.isfinite(value):
            return ""
        if value.is_integer():
            return str(int(value))
    if isinstance(value, (np.floating,)):
        return _text(float(value))
    if isinstance(value, (np.integer,)):
        return str(int(value))
    return str(value).strip()


def _numeric(series: pd.Series, column: str, source: str) -> np.ndarray:
    values = pd.to_numeric(series, errors="coerce").to_numpy(
        dtype=np.float64, copy=True
    )
    text = series.notna().to_numpy() & ~np.isfinite(values)
    bad = text & ~np.isin(series.astype(str).str.lower(), ("inf", "-inf", "nan"))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        shown = str(series.iloc[row])[:40]
        raise DataError(
            f"trajectory table from '{source}': column '{column}' holds "
            f"{shown!r} at data row {row + 1}, not a number"
        )
    values[~np.isfinite(values)] = np.nan
    return values
