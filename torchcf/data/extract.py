"""From a long trajectory table to leader-follower pairs: couples, windows, filters.

:func:`extract_pairs` turns a :class:`~torchcf.data.trajectory.TrajectoryTable` into
a :class:`~torchcf.data.pairset.PairSet` of equal-length windows, or of whole
couples of their own lengths (``window="whole"``), with a record of where every
pair came from and of what was dropped and why:

1. **Derivatives.** Speeds and accelerations the source lacks are derived from
   positions and speeds (:func:`torchcf.data.derive.fill_derivatives`).
2. **Time grid.** ``dt`` is the median time step of all vehicles; every time stamp
   must lie on the grid ``t0 + k dt`` of its run (within 5 % of dt), and one
   vehicle may not have two rows at one step.
3. **Units**, checked against what cars do (:mod:`torchcf.data.physics`): a time
   step no recording has, speeds over :data:`MAX_SPEED` or positions that move
   at a multiple of the recorded speeds stop the extraction with an error that
   names the column and its likely unit; vehicle lengths no car has are flagged
   in the notes (``feet?``).
4. **Couples.** A follower row belongs to its couple's *span* while its leader
   stays the same, the follower stays in its lane and control mode, and the
   leader has a row at the same step in the same lane. A leader change, lane
   change or mode change ends a span, and so does a gap in the follower's record
   longer than one window. Steps missing inside a span (shorter gaps) stay in it
   and make the windows that cover them fail the ``missing`` filter.
5. **Windows.** Each span is cut into windows of ``window`` seconds, one every
   ``stride`` seconds from its start; the tail after the last whole window is not
   used. A span shorter than one window is dropped as ``short``.
6. **Filters.** Each window passes the quality filters of
   :mod:`torchcf.data.quality` or is dropped for the first it fails.

   With ``window="whole"``, steps 5 and 6 are those of :mod:`torchcf.data.whole`
   instead: each span is one pair, cut where a step or a link fails a filter
   into its clean stretches of at least :data:`MIN_WHOLE_LENGTH` (a gap in the
   follower's record longer than that ends a span), and the pairs are ragged
   (``PairSet.mask``; ``index.csv``'s ``steps`` is each pair's length).
7. **Pairs.** The PairSet has one leader length ``L`` (the median leader length of
   the kept windows, or ``leader_length=``). Where a pair's own leader length
   ``L_i`` differs, its leader position is written as the leader's rear bumper
   plus ``L`` (``x_l - L_i + L``), so every spacing ``x_l - x_f - L`` is the
   measured one; the index keeps ``L_i``.
8. **Split.** Training and test pairs are split by source group (the follower
   vehicle by default, or the couple, or the run), so no group lands on both
   sides (:func:`torchcf.data.splits.group_split`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import pandas as pd
import torch

from torchcf.data.derive import fill_derivatives
from torchcf.data.pairset import DataError, PairSet
from torchcf.data.physics import MAX_SPEED, check_time_step, check_units
from torchcf.data.quality import FILTERS, QualityThresholds, Windows, first_failure
from torchcf.data.splits import group_split
from torchcf.data.trajectory import TrajectoryTable
from torchcf.data.whole import MIN_WHOLE_LENGTH, CoupleSpan, whole_candidates

__all__ = [
    "MAX_SPEED",
    "MIN_WHOLE_LENGTH",
    "WHOLE",
    "ExtractOptions",
    "Extraction",
    "extract_pairs",
]


SplitBy = Literal["follower", "couple", "run"]
#: ``window="auto"``: the window is chosen from the data (:func:`auto_window`).
AUTO = "auto"
#: ``window="whole"``: every couple is one pair of its own length, cut only at
#: its defects (:mod:`torchcf.data.whole`).
WHOLE = "whole"
#: What the summary's ``pairs_are`` says of whole couples (else "windows").
WHOLE_COUPLES = "whole couples"
#: The default window [s] and the cap of an automatic one: long enough to hold
#: several speed changes (the paper's pairs last 35-58 s).
DEFAULT_WINDOW = 40.0
#: An automatic window is a whole multiple of this [s].
AUTO_STEP = 0.5
AUTO_RULE = (
    "the median length of the couples' spans, rounded down to 0.5 s, at most "
    "40 s: at least half the couples then give a pair"
)


@dataclass(frozen=True)
class ExtractOptions:
    """How to cut pairs from a trajectory table.

    Attributes:
        window: length of a pair [s]. The default suits the paper's 35-58 s
            pairs: long enough to hold several speed changes. "auto": chosen
            from the data (:func:`auto_window`); "whole": every couple is one
            pair of its own length, at least :data:`MIN_WHOLE_LENGTH`, cut
            only at its defects (:mod:`torchcf.data.whole`).
        stride: start-to-start distance of windows of one span [s]; None = the
            window (windows do not overlap). Not used with "whole".
        leader_length: the PairSet's leader length [m]; None = the median
            leader length of the kept windows.
        default_length: length of vehicles whose source gives none [m].
        quality: thresholds of the quality filters.
        speed_window, acceleration_window: Savitzky-Golay windows [s] for
            speeds and accelerations the source lacks.
        split_by: the source group no two sides may share: "follower" (the
            following vehicle of a run), "couple" (leader and follower) or "run".
        test_fraction: share of the pairs to put in the test split, in [0, 1).
        seed: seed of the split's random order of groups.
        name: name of the pair set (defaults to the table's source).

    Examples:
        >>> from torchcf.data.extract import ExtractOptions
        >>> options = ExtractOptions(window=10.0, test_fraction=0.0)  # 10 s pairs
        >>> options.stride, options.split_by
        (None, 'follower')
        >>> ExtractOptions(window="whole", stride=5.0)
        Traceback (most recent call last):
            ...
        torchcf.data.pairset.DataError: stride is not used with window 'whole': ...
    """

    window: float | Literal["auto", "whole"] = DEFAULT_WINDOW
    stride: float | None = None
    leader_length: float | None = None
    default_length: float = 5.0
    quality: QualityThresholds = field(default_factory=QualityThresholds)
    speed_window: float = 1.0
    acceleration_window: float = 1.0
    split_by: SplitBy = "follower"
    test_fraction: float = 0.3
    seed: int = 0
    name: str = ""

    def __post_init__(self) -> None:
        if self.window not in (AUTO, WHOLE):
            _positive_number("window", self.window)
        if self.window == WHOLE and self.stride is not None:
            raise DataError(
                "stride is not used with window 'whole': each couple is one pair, "
                "not cut into windows"
            )
        for label, value in (
            ("default_length", self.default_length),
            ("speed_window", self.speed_window),
            ("acceleration_window", self.acceleration_window),
        ):
            if not (np.isfinite(value) and value > 0):
                raise DataError(f"{label} must be > 0, got {value}")
        if self.stride is not None and not (
            np.isfinite(self.stride) and self.stride > 0
        ):
            raise DataError(f"stride must be > 0 [s], got {self.stride}")
        if self.leader_length is not None and not self.leader_length > 0:
            raise DataError(f"leader_length must be > 0 [m], got {self.leader_length}")
        if self.split_by not in ("follower", "couple", "run"):
            raise DataError(
                f"split_by must be 'follower', 'couple' or 'run', got {self.split_by!r}"
            )
        if not 0.0 <= self.test_fraction < 1.0:
            raise DataError(
                f"test_fraction must be in [0, 1), got {self.test_fraction}"
            )


def _positive_number(label: str, value: object) -> None:
    if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
        raise DataError(f"{label} must be > 0, 'auto' or 'whole', got {value!r}")


@dataclass(frozen=True, eq=False)
class Extraction:
    """The pairs cut from a table, and the record of how.

    Attributes:
        pairs: (W, N) full set; ``pair_ids`` 0 .. N-1 = the row of ``index``.
        train, test: the split (subsets of ``pairs``, same ids); ``test`` is None
            when ``test_fraction`` is 0.
        index: one row per pair: where it came from (see :data:`INDEX_COLUMNS`).
        dropped: one row per dropped window or short span, with the reason.
        dt: sampling interval [s].
        road_frame: whether all pairs share one road frame.
        road_period: the lap length [m] of that road when it is a closed track,
            else None.
        summary: counts for humans and for ``extract.json``.
        notes: what was found and handled, one line each (the table's notes
            first).
        attention: the notes a user must see (among ``notes``): units that
            look wrong (:mod:`torchcf.data.physics`), a window chosen from the
            data.
        whole: the pairs are whole couples of their own lengths (ragged:
            ``pairs.mask``), not windows of one length.

    Examples:
        What an extraction holds (:func:`extract_pairs`' example makes one):

        >>> import dataclasses
        >>> [f.name for f in dataclasses.fields(Extraction)][:4]
        ['pairs', 'train', 'test', 'index']
    """

    pairs: PairSet
    train: PairSet
    test: PairSet | None
    index: pd.DataFrame
    dropped: pd.DataFrame
    dt: float
    road_frame: bool | None
    summary: dict
    notes: tuple[str, ...]
    road_period: float | None = None
    attention: tuple[str, ...] = ()
    whole: bool = False


INDEX_COLUMNS = (
    "pair",
    "split",
    "run",
    "follower",
    "leader",
    "lane",
    "mode",
    "t_start",
    "t_end",
    "steps",
    "leader_length",
    "follower_length",
    "min_gap",
    "mean_speed",
    "source",
)
DROPPED_COLUMNS = (
    "run",
    "follower",
    "leader",
    "lane",
    "t_start",
    "t_end",
    "reason",
    "value",
    "unit",
)


class _Cut(NamedTuple):
    """Steps 4-6 of either kind: the (T, K) candidates and their (K,) lengths
    in steps (all T for windows), the kept candidates' columns, where each
    came from, what was dropped, the kind's summary entries, and the closing
    note's two halves (what the pairs are; what was dropped)."""

    windows: Windows
    lengths: np.ndarray
    kept: np.ndarray
    meta: list[dict]
    dropped: list[dict]
    summary: dict
    note: tuple[str, str]


def extract_pairs(
    table: TrajectoryTable, options: ExtractOptions | None = None
) -> Extraction:
    """Cut leader-follower pairs out of ``table`` (module docstring, steps 1-8).

    Raises:
        DataError: time stamps off a common grid, implausible units, no couple
            lasting one window (or :data:`MIN_WHOLE_LENGTH` for whole couples),
            no window or stretch passing the filters (the message counts what
            each filter removed), or a split that cannot keep groups apart.

    Examples:
        >>> import numpy as np
        >>> import pandas as pd
        >>> from torchcf.data.extract import ExtractOptions, extract_pairs
        >>> from torchcf.data.trajectory import TrajectoryTable
        >>> t = np.round(np.arange(0.0, 30.0, 0.1), 10)  # 30 s at 0.1 s
        >>> car = {"time": t, "speed": 15.0, "acceleration": 0.0, "length": 5.0}
        >>> leader = pd.DataFrame({"vehicle": "L", "position": 30.0 + 15.0 * t, **car})
        >>> follower = pd.DataFrame({"vehicle": "F", "position": 15.0 * t, **car})
        >>> follower["leader"] = "L"  # 30 m behind it, both at 15 m/s
        >>> rows = pd.concat([leader, follower])
        >>> table = TrajectoryTable.from_frame(rows, source="demo")
        >>> options = ExtractOptions(window=10.0, test_fraction=0.0)  # 10 s pairs
        >>> found = extract_pairs(table, options)
        >>> found.pairs.n_pairs, found.pairs.n_steps  # three 10 s windows
        (3, 100)
        >>> spacing = found.pairs.x_lead - found.pairs.x_follow  # [m]
        >>> round(float(spacing.min()), 3), round(float(spacing.max()), 3)
        (30.0, 30.0)
    """
    options = options or ExtractOptions()
    table = fill_derivatives(
        table.sorted(),
        speed_window=options.speed_window,
        acceleration_window=options.acceleration_window,
    )
    source = table.source or "the table"
    frame, dt, flags = _on_grid(table.frame, options, source)
    couples = _couple_rows(frame)
    chosen: tuple[str, ...] = ()
    if options.window == AUTO:
        spans, _ = _spans(couples, int(round(DEFAULT_WINDOW / dt)))
        options = dataclasses.replace(options, window=auto_window(spans, dt))
        chosen = (f"window {options.window:g} s from the data (auto: {AUTO_RULE})",)
    if options.window == WHOLE:
        cut, spans, unmatched = _cut_whole(couples, dt, options, source)
    else:
        cut, spans, unmatched = _cut_windows(couples, dt, options, source)
    windows, kept = cut.windows, cut.kept

    leader_length = options.leader_length or float(
        np.median(windows.leader_length[0, kept])
    )
    pairs = dataclasses.replace(
        _pair_set(
            windows, cut.lengths, kept, leader_length, options.name or table.source
        ),
        road_frame=table.road_frame,
        road_period=table.road_period,
    )
    index = _index(cut.meta, windows, cut.lengths, kept, table.source)
    index, train_ids, test_ids = group_split(
        index, options.split_by, options.test_fraction, options.seed
    )
    summary = {
        "dt": dt,
        "pairs_are": WHOLE_COUPLES if options.window == WHOLE else "windows",
        **cut.summary,
        "rows": int(len(frame)),
        "runs": int(frame["run"].nunique()),
        "vehicles": int(frame.groupby(["run", "vehicle"]).ngroups),
        "spans": len(spans),
        "pairs": int(pairs.n_pairs),
        "train_pairs": len(train_ids),
        "test_pairs": len(test_ids),
        "leader_length": leader_length,
        "rows_outside_couples": unmatched,
    }
    return Extraction(
        pairs=pairs,
        train=dataclasses.replace(pairs.subset(train_ids), split="train"),
        test=(
            dataclasses.replace(pairs.subset(test_ids), split="test")
            if test_ids
            else None
        ),
        index=index,
        dropped=pd.DataFrame(cut.dropped, columns=list(DROPPED_COLUMNS)),
        dt=dt,
        road_frame=table.road_frame,
        road_period=table.road_period,
        summary=summary,
        notes=(
            *table.notes,
            *flags,
            *chosen,
            *_notes(index, unmatched, cut.note),
        ),
        attention=(*flags, *chosen),
        whole=options.window == WHOLE,
    )


def _cut_windows(
    couples: pd.DataFrame, dt: float, options: ExtractOptions, source: str
) -> tuple[_Cut, list[_Span], dict[str, int]]:
    """Steps 4-6 for windows of ``options.window`` seconds: the cut, the spans
    and the follower rows outside any couple.

    Raises:
        DataError: the window is under two steps, no couple lasts one window,
            or no window passes the filters.
    """
    width = int(round(options.window / dt))
    if width < 2:
        raise DataError(f"window {options.window} s is under two steps of {dt} s")
    stride = width if options.stride is None else max(1, round(options.stride / dt))

    spans, unmatched = _spans(couples, width)
    windows, meta, dropped = _candidate_windows(couples, spans, width, stride, dt)
    if not meta:
        lengths = np.array([s.stop - s.start for s in spans]) * dt
        proposal = (
            f"; the data support --window {auto_window(spans, dt):g} "
            f"(--window auto: {AUTO_RULE})"
            if lengths.size and lengths.max() >= 2 * dt
            else ""
        )
        raise DataError(
            f"no leader-follower couple in '{source}' lasts one window "
            f"({options.window:g} s): {_span_lengths(spans, dt)}{proposal}"
        )
    kept, counts = _filter(windows, meta, dropped, options.quality, source)
    summary = {
        "window_steps": width,
        "stride_steps": stride,
        "candidate_windows": len(meta),
        **counts,
    }
    note = (
        f"{len(kept)} pairs of {options.window:g} s",
        f"{len(meta) - len(kept)} of {len(meta)} candidate windows dropped",
    )
    lengths = np.full(len(meta), width)
    return _Cut(windows, lengths, kept, meta, dropped, summary, note), spans, unmatched


def _span_lengths(spans: list[_Span], dt: float) -> str:
    """How many spans, and their median and longest length, for a message."""
    lengths = np.array([s.stop - s.start for s in spans]) * dt
    return (
        f"{lengths.size} couple spans, median "
        f"{np.median(lengths) if lengths.size else 0.0:.1f} s, the longest "
        f"{float(lengths.max()) if lengths.size else 0.0:.1f} s"
    )


def _cut_whole(
    couples: pd.DataFrame, dt: float, options: ExtractOptions, source: str
) -> tuple[_Cut, list[_Span], dict[str, int]]:
    """Steps 4-6 for whole couples (:mod:`torchcf.data.whole`): the cut, the
    spans and the follower rows outside any couple.

    Raises:
        DataError: no couple lasts :data:`MIN_WHOLE_LENGTH`, or no clean
            stretch of it is left (the message counts the defects and drops).
    """
    min_steps = max(2, int(round(MIN_WHOLE_LENGTH / dt)))
    # A hole in the follower's record up to the minimum's length stays inside
    # its span, as missing steps the couple is cut at; a longer one ends it.
    spans, unmatched = _spans(couples, min_steps)
    found = whole_candidates(
        _couple_spans(couples, spans, dt), min_steps, options.quality
    )
    counts = found.counts
    if not found.meta:
        if counts["spans_short"] == len(spans):
            raise DataError(
                f"no leader-follower couple in '{source}' lasts "
                f"{MIN_WHOLE_LENGTH:g} s, the shortest whole couple kept: "
                f"{_span_lengths(spans, dt)} (--window auto cuts shorter pairs)"
            )
        raise DataError(
            f"no clean stretch of {MIN_WHOLE_LENGTH:g} s is left in '{source}': "
            f"{len(spans)} couple spans, cut at "
            + _listed(counts["defects"])
            + f", {counts['stretches_short']} pieces shorter than "
            f"{MIN_WHOLE_LENGTH:g} s, stretches dropped by "
            + _listed(counts["stretches_dropped"])
        )
    seconds = found.lengths * dt
    summary = {
        "min_pair_steps": min_steps,
        # rounded: steps x dt carries float noise (63.900000000000006)
        "pair_seconds": {
            "min": round(float(seconds.min()), 6),
            "median": round(float(np.median(seconds)), 6),
            "max": round(float(seconds.max()), 6),
        },
        "seconds_in_pairs": round(float(seconds.sum()), 6),
        **counts,
    }
    note = (
        f"{len(found.meta)} pairs, whole couples of {seconds.min():.1f}-"
        f"{seconds.max():.1f} s (median {np.median(seconds):.1f} s, at least "
        f"{MIN_WHOLE_LENGTH:g} s)",
        f"{counts['spans_short']} of {len(spans)} couple spans shorter than "
        f"{MIN_WHOLE_LENGTH:g} s; couples cut at " + _listed(counts["defects"]),
    )
    kept = np.arange(len(found.meta))
    cut = _Cut(
        found.windows, found.lengths, kept, found.meta, found.dropped, summary, note
    )
    return cut, spans, unmatched


def _listed(counts: dict[str, int]) -> str:
    """``name n, name n`` or ``none``."""
    return ", ".join(f"{k} {v}" for k, v in counts.items()) or "none"


def auto_window(spans: list[_Span], dt: float) -> float:
    """The window ``--window auto`` picks (:data:`AUTO_RULE`): the median
    length of the couples' spans, rounded down to a multiple of
    :data:`AUTO_STEP` (at least two steps), at most :data:`DEFAULT_WINDOW`.

    Raises:
        DataError: no couple at all.
    """
    if not spans:
        raise DataError("no leader-follower couple to choose a window from")
    median = float(np.median([s.stop - s.start for s in spans])) * dt
    window = min(DEFAULT_WINDOW, np.floor(median / AUTO_STEP) * AUTO_STEP)
    return float(max(window, 2 * dt))


def _on_grid(
    frame: pd.DataFrame, options: ExtractOptions, source: str
) -> tuple[pd.DataFrame, float, list[str]]:
    """Steps 2-3: the rows with their integer ``step`` and lengths filled, dt,
    and what the unit checks flag (:mod:`torchcf.data.physics`)."""
    frame = frame.copy()
    dt = infer_dt(frame, source)
    check_time_step(dt, source)
    frame["step"] = grid_steps(frame, dt, source)
    flags = check_units(frame, dt, source)
    frame["length"] = frame["length"].fillna(options.default_length)
    return frame, dt, flags


def _filter(
    windows: Windows,
    meta: list[dict],
    dropped: list[dict],
    quality: QualityThresholds,
    source: str,
) -> tuple[np.ndarray, dict]:
    """Step 6: the kept windows' columns; failing windows appended to ``dropped``.

    Raises:
        DataError: no window passes (the message counts each filter's drops).
    """
    reason, value = first_failure(windows, quality)
    for k in np.flatnonzero(reason != ""):
        dropped.append(
            {
                **meta[k],
                "reason": reason[k],
                "value": value[k],
                "unit": FILTERS[reason[k]][1],
            }
        )
    counts = _counts(reason, dropped)
    kept = np.flatnonzero(reason == "")
    if kept.size == 0:
        raise DataError(
            f"no window of '{source}' passed the quality filters: "
            f"{len(meta)} candidate windows, dropped by "
            + ", ".join(f"{r} {n}" for r, n in counts["windows_dropped"].items())
        )
    return kept, counts


def _notes(
    index: pd.DataFrame, unmatched: dict[str, int], note: tuple[str, str]
) -> list[str]:
    notes = []
    if unmatched:
        notes.append(
            "follower rows outside any couple: "
            + ", ".join(f"{n} with {why}" for why, n in unmatched.items())
        )
    what, dropped = note
    notes.append(
        f"{what} from {index['run'].nunique()} run(s), "
        f"{index['follower'].nunique()} follower id(s); {dropped}"
    )
    return notes


# ------------------------------------------------------------------ time grid
def infer_dt(frame: pd.DataFrame, source: str) -> float:
    """The median positive time step over all vehicles [s]."""
    steps = frame.groupby(["run", "vehicle"], sort=False)["time"].diff().to_numpy()
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if steps.size == 0:
        raise DataError(f"no vehicle in '{source}' has two time stamps")
    dt = float(np.median(steps))
    # Round away float noise of the kind 0.09999999999: a clean decimal step.
    return float(f"{dt:.6g}")


def grid_steps(frame: pd.DataFrame, dt: float, source: str) -> np.ndarray:
    """(rows,) integer step of every row on its run's grid ``t0 + k dt``."""
    t0 = frame.groupby("run", sort=False)["time"].transform("min").to_numpy()
    exact = (frame["time"].to_numpy() - t0) / dt
    steps = np.rint(exact).astype(np.int64)
    off = np.abs(exact - steps) > 0.05
    if off.any():
        row = int(np.flatnonzero(off)[0])
        raise DataError(
            f"time stamps of '{source}' are not on a grid of dt = {dt:g} s: "
            f"run {frame['run'].iat[row]!r}, vehicle {frame['vehicle'].iat[row]!r}, "
            f"t = {frame['time'].iat[row]:.6g} s ({int(off.sum())} rows); resample "
            "the data to one sampling interval first"
        )
    keys = pd.DataFrame(
        {"run": frame["run"], "vehicle": frame["vehicle"], "step": steps}
    )
    twice = keys.duplicated()
    if twice.any():
        row = int(np.flatnonzero(twice.to_numpy())[0])
        raise DataError(
            f"vehicle {frame['vehicle'].iat[row]!r} of run {frame['run'].iat[row]!r} "
            f"has two rows at t = {frame['time'].iat[row]:.6g} s in '{source}' "
            f"({int(twice.sum())} such rows): vehicle ids must be unique per run"
        )
    return steps


# --------------------------------------------------------------------- couples
_LEADER = ("position", "speed", "acceleration", "lane", "length")


def _couple_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """Follower rows that name a leader, joined with the leader's row at that step.

    Columns: run, vehicle, leader, lane, mode, step, time, follower's position,
    speed, acceleration, length, gap; the leader's with suffix ``_l`` (NaN when
    the leader has no row at that step) and ``present_l``.
    """
    followers = frame[frame["leader"] != ""]
    leaders = frame[["run", "vehicle", "step", *_LEADER]].rename(
        columns={c: f"{c}_l" for c in ("vehicle", *_LEADER)}
    )
    leaders["present_l"] = True
    joined = followers.merge(
        leaders,
        how="left",
        left_on=["run", "leader", "step"],
        right_on=["run", "vehicle_l", "step"],
    )
    joined["present_l"] = joined["present_l"].fillna(False).astype(bool)
    return joined.sort_values(["run", "vehicle", "step"], kind="stable").reset_index(
        drop=True
    )


@dataclass(frozen=True)
class _Span:
    rows: slice  # rows of the couple frame
    start: int  # first step
    stop: int  # last step + 1


def _spans(couples: pd.DataFrame, width: int) -> tuple[list[_Span], dict[str, int]]:
    """Maximal runs of rows of one couple, in one lane and mode (step 4)."""
    lane_ok = (
        (couples["lane"] == "")
        | (couples["lane_l"].fillna("") == "")
        | (couples["lane"] == couples["lane_l"].fillna(""))
    )
    usable = (couples["present_l"] & lane_ok).to_numpy()
    unmatched = {
        "the leader not recorded at that time": int((~couples["present_l"]).sum()),
        "the leader in another lane": int((couples["present_l"] & ~lane_ok).sum()),
    }
    keys = couples[["run", "vehicle", "leader", "lane", "mode"]]
    same = (keys == keys.shift()).all(axis=1).to_numpy()
    step = couples["step"].to_numpy()
    close = np.r_[False, np.diff(step) <= width]
    previous_usable = np.r_[False, usable[:-1]]
    start = ~(same & close & previous_usable) & usable
    # A span runs from its start row to the row before the next start or the
    # next unusable row: one pass over the boundaries, linear in the rows.
    firsts = np.flatnonzero(start)
    boundaries = np.flatnonzero(start | ~usable)
    ends = np.append(boundaries, len(usable))[
        np.searchsorted(boundaries, firsts, side="right")
    ]
    spans = [
        _Span(slice(first, end), step[first], step[end - 1] + 1)
        for first, end in zip(firsts.tolist(), ends.tolist(), strict=True)
    ]
    return spans, {k: v for k, v in unmatched.items() if v}


#: The couple frame's column of each :class:`Windows` series.
_SERIES = {
    "x_lead": "position_l",
    "v_lead": "speed_l",
    "a_lead": "acceleration_l",
    "x_follow": "position",
    "v_follow": "speed",
    "a_follow": "acceleration",
    "gap": "gap",
    "leader_length": "length_l",
}


class _Columns(NamedTuple):
    """The couple frame as arrays: each series (rows,), step and time."""

    series: dict[str, np.ndarray]
    steps: np.ndarray
    time: np.ndarray


def _columns(couples: pd.DataFrame) -> _Columns:
    return _Columns(
        {k: couples[c].to_numpy(dtype=float) for k, c in _SERIES.items()},
        couples["step"].to_numpy(),
        couples["time"].to_numpy(),
    )


def _describe(
    couples: pd.DataFrame, columns: _Columns, span: _Span, dt: float
) -> tuple[dict, float]:
    """The couple of ``span`` (run, follower, leader, lane, mode,
    follower_length) and the time of its first step [s]."""
    first = span.rows.start
    row = couples.iloc[first]
    t0 = float(columns.time[first]) - (columns.steps[first] - span.start) * dt
    describe = {
        "run": row["run"],
        "follower": row["vehicle"],
        "leader": row["leader"],
        "lane": row["lane"],
        "mode": row["mode"],
        "follower_length": float(row["length"]),
    }
    return describe, t0


def _dense(columns: _Columns, span: _Span, dt: float) -> Windows:
    """The span's (W, 1) series on its dense grid of W = stop - start steps;
    steps without a row are absent (``present`` False, values NaN)."""
    length = span.stop - span.start
    local = columns.steps[span.rows] - span.start
    dense = {k: np.full((length, 1), np.nan) for k in _SERIES}
    for k in _SERIES:
        dense[k][local, 0] = columns.series[k][span.rows]
    present = np.zeros((length, 1), dtype=bool)
    present[local] = True
    return Windows(present=present, dt=dt, **dense)


def _couple_spans(
    couples: pd.DataFrame, spans: list[_Span], dt: float
) -> Iterator[CoupleSpan]:
    """Every span as a :class:`~torchcf.data.whole.CoupleSpan`, one at a time."""
    columns = _columns(couples)
    for span in spans:
        describe, t0 = _describe(couples, columns, span, dt)
        yield CoupleSpan(describe, t0, _dense(columns, span, dt))


def _candidate_windows(
    couples: pd.DataFrame, spans: list[_Span], width: int, stride: int, dt: float
) -> tuple[Windows, list[dict], list[dict]]:
    """Dense (W, K) arrays of every candidate window, their metadata, short spans."""
    columns = _columns(couples)
    blocks: dict[str, list[np.ndarray]] = {k: [] for k in (*_SERIES, "present")}
    meta: list[dict] = []
    short: list[dict] = []
    for span in spans:
        describe, t0 = _describe(couples, columns, span, dt)
        length = span.stop - span.start
        if length < width:
            short.append(
                {
                    **_where(describe),
                    "t_start": t0,
                    "t_end": t0 + (length - 1) * dt,
                    "reason": "short",
                    "value": length * dt,
                    "unit": "s (span length)",
                }
            )
            continue
        dense = _dense(columns, span, dt)
        for first in range(0, length - width + 1, stride):
            part = slice(first, first + width)
            for k in (*_SERIES, "present"):
                blocks[k].append(getattr(dense, k)[part, 0])
            meta.append(
                {
                    **describe,
                    "t_start": t0 + first * dt,
                    "t_end": t0 + (first + width - 1) * dt,
                }
            )
    stacked = {
        k: (np.stack(v, axis=1) if v else np.zeros((width, 0)))
        for k, v in blocks.items()
    }
    windows = Windows(
        present=stacked["present"].astype(bool),
        dt=dt,
        **{k: stacked[k] for k in _SERIES},
    )
    return windows, meta, short


def _where(describe: dict) -> dict:
    return {k: describe[k] for k in ("run", "follower", "leader", "lane")}


def _counts(reason: np.ndarray, dropped: list[dict]) -> dict:
    windows = {
        name: int((reason == name).sum()) for name in FILTERS if (reason == name).any()
    }
    short = [d for d in dropped if d["reason"] == "short"]
    return {
        "windows_dropped": windows,
        "spans_short": len(short),
        "seconds_in_short_spans": float(sum(d["value"] for d in short)),
    }


# ----------------------------------------------------------------------- pairs
def _index(
    meta: list[dict],
    w: Windows,
    lengths: np.ndarray,
    kept: np.ndarray,
    source: str,
) -> pd.DataFrame:
    """One row per kept candidate (:data:`INDEX_COLUMNS`), over its own
    ``lengths[k]`` steps; ``split`` filled later."""
    rows = []
    for pair, k in enumerate(kept):
        steps = slice(0, int(lengths[k]))
        gap = w.x_lead[steps, k] - w.leader_length[steps, k] - w.x_follow[steps, k]
        rows.append(
            {
                "pair": pair,
                "split": "",
                **{
                    c: meta[k][c] for c in ("run", "follower", "leader", "lane", "mode")
                },
                "t_start": meta[k]["t_start"],
                "t_end": meta[k]["t_end"],
                "steps": int(lengths[k]),
                "leader_length": float(w.leader_length[0, k]),
                "follower_length": meta[k]["follower_length"],
                "min_gap": float(gap.min()),
                "mean_speed": float(w.v_follow[steps, k].mean()),
                "source": source,
            }
        )
    return pd.DataFrame(rows, columns=list(INDEX_COLUMNS))


def _pair_set(
    w: Windows,
    lengths: np.ndarray,
    kept: np.ndarray,
    leader_length: float,
    name: str,
) -> PairSet:
    """(T, N) PairSet of the kept candidates, each valid for its ``lengths``
    steps (the mask; all T for windows); leader positions re-based to the
    common leader length."""
    shift = leader_length - w.leader_length[:, kept]  # (T, N), NaN after an end
    series = [
        w.x_lead[:, kept] + shift,
        w.v_lead[:, kept],
        w.a_lead[:, kept],
        w.x_follow[:, kept],
        w.v_follow[:, kept],
        w.a_follow[:, kept],
    ]
    mask = np.arange(w.x_lead.shape[0])[:, None] < lengths[kept][None, :]  # (T, N)
    return PairSet.from_arrays(
        [torch.from_numpy(np.ascontiguousarray(s)) for s in series],
        dt=w.dt,
        mask=torch.from_numpy(mask),
        leader_length=leader_length,
        name=name,
    )
