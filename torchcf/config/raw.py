"""The ``data.raw`` section: train on a raw trajectory file, extracted on the fly.

    "data": {"raw": {"source": "openacc/", "format": "openacc", "window": 40}}

The same settings as ``torchcf data extract`` (the command line builds a
:class:`RawSource` too), so a study run from a config and a folder extracted by
hand hold the same pairs. Reading and extraction live in :mod:`torchcf.data`:
:func:`torchcf.data.importer.extract_source`.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, model_validator

from torchcf.data.extract import MIN_WHOLE_LENGTH, ExtractOptions
from torchcf.data.formats import FORMATS
from torchcf.data.formats import reader_options as format_options
from torchcf.data.formats.generic import (
    ACCELERATION_UNITS,
    FRAME_UNIT,
    LENGTH_UNITS,
    SPEED_UNITS,
    TIME_UNITS,
    time_factor,
)
from torchcf.data.pairset import DataError
from torchcf.data.quality import QualityThresholds

__all__ = ["RawSource"]

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
_OptionalPositive = float | None
Format = Literal["ngsim", "openacc", "csv", "pairs", "punzo", "highd", "gps"]


class RawSource(BaseModel):
    """A raw trajectory source and how to cut pairs from it
    (:mod:`torchcf.data.extract`, :mod:`torchcf.data.quality`)."""

    model_config = _STRICT

    source: str = Field(min_length=1, description="Raw file or folder.")
    format: Format = Field(description=f"Reader: one of {', '.join(FORMATS)}.")
    columns: dict[str, str] | None = Field(
        None,
        description=(
            "csv, pairs and gps only: source column of each table column, e.g. "
            '{"vehicle": "ID", "time": "t", "position": "x"} (csv), '
            '{"pair": "ID", "x_lead": "xl"} (pairs) or {"lat": "Latitude"} (gps); '
            "None = the reader's default names."
        ),
    )
    length_unit: str = Field(
        "m", description=f"csv, pairs, punzo: one of {', '.join(LENGTH_UNITS)}."
    )
    speed_unit: str | None = Field(
        None,
        description=(
            f"csv, pairs, punzo: one of {', '.join(SPEED_UNITS)}; None = length/s."
        ),
    )
    acceleration_unit: str | None = Field(
        None,
        description=(
            f"csv, pairs: one of {', '.join(ACCELERATION_UNITS)}; None = length/s^2."
        ),
    )
    time_unit: str = Field(
        "s",
        description=(
            f"csv, pairs, punzo: one of {', '.join((*TIME_UNITS, FRAME_UNIT))} "
            "(frame: frame numbers, with frame_rate)."
        ),
    )
    frame_rate: float | None = Field(
        None,
        gt=0,
        description="time_unit 'frame' only: frames per second [Hz]; t = frame / rate.",
    )
    length_tolerance: float = Field(
        0.5,
        gt=0,
        description=(
            "pairs and punzo only: largest spread of a pair's leader length [m] "
            "(positions, gap and length must agree)."
        ),
    )
    recordings: str | None = Field(
        None,
        description=(
            'highd only: recording numbers to read, e.g. "1,2,5-7"; None = all.'
        ),
    )
    directions: str | None = Field(
        None,
        description=(
            'highd only: driving directions to keep, "upper" (1), "lower" (2) or '
            '"upper,lower"; None = both.'
        ),
    )
    follower_classes: str | None = Field(
        None,
        description=(
            'highd only: vehicle classes that may follow, e.g. "Car" or '
            '"Car,Truck"; other vehicles stay as leaders. None = all.'
        ),
    )
    time_format: Literal["auto", "seconds", "gps-week", "timestamp"] = Field(
        "auto",
        description=(
            "gps only: numbers in time_unit ('seconds'), GPS week seconds "
            "('gps-week': rollovers undone), date stamps ('timestamp'), or 'auto' "
            "(numbers with rollovers undone, text as dates)."
        ),
    )
    leader_rule: Literal["column", "platoon", "nearest"] | None = Field(
        None,
        description=(
            "gps only: each vehicle's leader from a leader column, the platoon's "
            "order, or the nearest vehicle ahead on the path; None = the column "
            "if there is one, else the platoon if given, else the nearest."
        ),
    )
    platoon: str | None = Field(
        None,
        description='gps only: the vehicles in driving order, e.g. "A,B,C" (A leads).',
    )
    path_file: str | None = Field(
        None,
        description=(
            "gps only: a CSV of the road's lat, lon in driving order; None = the "
            "platoon's own smoothed path."
        ),
    )
    road_frame: bool | None = Field(
        None,
        description=(
            "csv, pairs: whether all positions lie on one road (the loop's road "
            "effects need it); None = unknown, the loop decides."
        ),
    )
    vehicle_length: float = Field(
        5.0, gt=0, description="openacc only: vehicle length [m] (the files give none)."
    )
    lap_frame: bool = Field(
        False,
        description=(
            "openacc only: the runs go round one circular track; put them on its "
            "lap coordinate (from E/N and Alt), one road frame with the lap as "
            "period, so road effects such as a grade can be offered; runs that "
            "leave the circle are left out."
        ),
    )
    window: PositiveFloat | Literal["auto", "whole"] = Field(
        40.0,
        description=(
            "Pair length [s]; 'auto': the median length of the couples' spans, "
            "rounded down to 0.5 s, at most 40 s; 'whole': every couple one pair "
            "of its own length, cut only where a step fails a filter into clean "
            f"stretches of at least {MIN_WHOLE_LENGTH:g} s."
        ),
    )
    stride: float | None = Field(
        None,
        gt=0,
        description=(
            "Start-to-start distance of windows [s]; None = window. Not with "
            "window 'whole'."
        ),
    )
    leader_length: float | None = Field(
        None, gt=0, description="Leader length of the pair set [m]; None = median."
    )
    default_length: float = Field(
        5.0, gt=0, description="Length of vehicles the source gives none for [m]."
    )
    jump: _OptionalPositive = Field(
        1.0,
        gt=0,
        description="Jump filter: largest position-step disagreement [m]; null = off.",
    )
    speed_mismatch: _OptionalPositive = Field(
        3.0,
        gt=0,
        description=(
            "Speed-mismatch filter: largest disagreement of a step's speed (position "
            "difference over dt) with the recorded speeds [m/s]; null = off."
        ),
    )
    max_acceleration: _OptionalPositive = Field(
        8.0, gt=0, description="Acceleration filter: largest |a| [m/s^2]; null = off."
    )
    gap_drift: _OptionalPositive = Field(
        2.0, gt=0, description="Gap-consistency filter: largest drift [m]; null = off."
    )
    gap_drift_rate: float = Field(
        0.2, ge=0, description="Gap-consistency filter: drift allowed per second [m/s]."
    )
    standstill_speed: _OptionalPositive = Field(
        0.5, gt=0, description="Leader-standstill filter: speed [m/s]; null = off."
    )
    split_by: Literal["follower", "couple", "run"] = Field(
        "follower", description="Source group kept on one side of the split."
    )
    test_fraction: float = Field(
        0.3,
        ge=0,
        lt=1,
        description=(
            "Share of test pairs; 0: no test split (the run trains and skips the "
            "evaluation)."
        ),
    )
    seed: int = Field(0, description="Seed of the split's order of groups.")

    @model_validator(mode="after")
    def _reader_options_of_the_format(self) -> RawSource:
        # Each reader says which options it takes (its keyword-only
        # parameters); one set for another format is a mistake, not a no-op.
        takes = format_options(self.format)
        defaults = type(self).model_fields
        used = [
            k
            for k in _reader_fields()
            if k not in takes and getattr(self, k) != defaults[k].default
        ]
        if used:
            raise ValueError(
                "; ".join(
                    f"{k}: only used with format="
                    + " or ".join(repr(f) for f in FORMATS if k in format_options(f))
                    for k in used
                )
            )
        for name, units in (
            ("length_unit", LENGTH_UNITS),
            ("speed_unit", SPEED_UNITS),
            ("acceleration_unit", ACCELERATION_UNITS),
        ):
            value = getattr(self, name)
            if value is not None and value not in units:
                raise ValueError(
                    f"{name} must be one of {', '.join(units)}, got {value!r}"
                )
        try:
            time_factor(self.time_unit, self.frame_rate)
        except DataError as error:
            raise ValueError(f"time_unit: {error}") from None
        if self.window == "whole" and self.stride is not None:
            raise ValueError(
                "stride: not used with window 'whole' (each couple is one pair, "
                "not cut into windows)"
            )
        return self

    def reader_options(self) -> dict[str, Any]:
        """Keyword arguments of the format's reader: those of its options
        this section has."""
        fields = type(self).model_fields
        return {k: getattr(self, k) for k in format_options(self.format) if k in fields}

    def extract_options(self) -> ExtractOptions:
        """The extraction settings (:class:`torchcf.data.extract.ExtractOptions`)."""
        return ExtractOptions(
            window=self.window,
            stride=self.stride,
            leader_length=self.leader_length,
            default_length=self.default_length,
            quality=QualityThresholds(
                jump=self.jump,
                speed_mismatch=self.speed_mismatch,
                max_acceleration=self.max_acceleration,
                gap_drift=self.gap_drift,
                gap_drift_rate=self.gap_drift_rate,
                standstill_speed=self.standstill_speed,
            ),
            split_by=self.split_by,
            test_fraction=self.test_fraction,
            seed=self.seed,
        )


def _reader_fields() -> list[str]:
    """The fields of :class:`RawSource` that some format's reader takes."""
    taken = {k for f in FORMATS for k in format_options(f)}
    return [k for k in RawSource.model_fields if k in taken]
