"""Whole couples: each couple kept as one pair of its own length, cut at defects.

``window="whole"`` (:mod:`torchcf.data.extract`) keeps every couple's span whole
instead of cutting it into windows of one length:

1. **Short couples.** A span shorter than :data:`MIN_WHOLE_LENGTH` is dropped as
   ``short`` (unit "s (span length)"), as a span shorter than a window is.
2. **Defects.** The step-wise quality filters judge every step and every link,
   the move from one step to the next (:func:`torchcf.data.quality.
   step_failures`). A failing step (a missing row, a NaN, an overlap, an
   acceleration no car makes) is left out; a failing link (a jump, a speed
   mismatch) separates the steps on its two sides, so a tracking jump costs no
   step. A step between two failing links is left out with them: a noisy
   stretch gives no one-step pieces. Each run of steps or links that fail one
   filter is one defect in ``dropped.csv``, with the filter's worst number over
   it (:func:`torchcf.data.quality.worst`).
3. **Clean stretches.** What is left of a span is cut into its longest clean
   stretches. One shorter than :data:`MIN_WHOLE_LENGTH` is dropped as ``short``
   (unit "s (stretch length)"); the others must pass the filters that judge a
   stretch as a whole (``gap_consistency``: a drift allowed to grow with the
   stretch's duration, and ``leader_standstill``) or are dropped for the first
   they fail, like a window.

Each stretch left is a pair; the pairs are ragged, stored with their lengths
(:class:`~torchcf.data.pairset.PairSet`'s prefix mask, empty cells in the CSV).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np

from torchcf.data.quality import (
    FILTERS,
    QualityThresholds,
    Windows,
    first_failure,
    step_failures,
    worst,
)

__all__ = [
    "MIN_WHOLE_LENGTH",
    "CoupleSpan",
    "Defect",
    "SpanCut",
    "WholeCandidates",
    "cut_span",
    "whole_candidates",
]

#: The shortest whole couple or clean stretch kept as a pair [s]: a follower
#: needs some seconds to show its response to the leader (a speed change and
#: the follower's answer to it); shorter pieces are mostly start-up from the
#: observed state, where every model fits.
MIN_WHOLE_LENGTH = 10.0

#: The units of a couple's span and of a clean stretch dropped as ``short``.
SPAN_UNIT, STRETCH_UNIT = "s (span length)", "s (stretch length)"
#: The columns of a dropped record that say where it was.
_WHERE = ("run", "follower", "leader", "lane")


class CoupleSpan(NamedTuple):
    """One couple's span on its dense time grid.

    Attributes:
        describe: the couple: run, follower, leader, lane, mode,
            follower_length (:mod:`torchcf.data.extract`).
        t0: the time of the span's first step [s].
        series: the span's (W, 1) arrays; ``present`` False on steps without
            a row (their values NaN).
    """

    describe: dict
    t0: float
    series: Windows


class Defect(NamedTuple):
    """A run of steps, or of links, of one span that fail one filter.

    ``start``, ``stop``: the steps it touches, ``[start, stop)`` local to the
    span (a link from step k to k + 1 touches both); ``value``: the filter's
    worst number over it, in its unit (:data:`~torchcf.data.quality.FILTERS`).
    """

    start: int
    stop: int
    reason: str
    value: float


class SpanCut(NamedTuple):
    """A span cut at its defects: clean stretches ``[start, stop)`` of local
    steps, in time order, and the defects."""

    stretches: list[tuple[int, int]]
    defects: list[Defect]


class WholeCandidates(NamedTuple):
    """The clean stretches of every span that pass the filters, and the rest.

    Attributes:
        windows: (T, K) ragged arrays of the K stretches kept, T the longest;
            after a stretch's end ``present`` is False and the values NaN.
        lengths: (K,) steps of each stretch.
        meta: K dicts: the couple (``describe``) with ``t_start``, ``t_end``.
        dropped: one dict per short span, defect, short stretch or stretch
            that failed a filter (:data:`torchcf.data.extract.DROPPED_COLUMNS`).
        counts: the summary's counts (:func:`whole_candidates`).
    """

    windows: Windows
    lengths: np.ndarray
    meta: list[dict]
    dropped: list[dict]
    counts: dict


def cut_span(series: Windows, quality: QualityThresholds) -> SpanCut:
    """Cut one (W, 1) span at the steps and links that fail a step-wise filter."""
    failures = step_failures(series, quality)
    steps, links = failures.steps[:, 0], failures.links[:, 0]
    defects = [
        *(
            Defect(a, b, name, worst(name, failures.step_values[a:b, 0]))
            for a, b, name in _runs(steps)
        ),
        *(
            # links a .. b - 1 join steps a .. b
            Defect(a, b + 1, name, worst(name, failures.link_values[a:b, 0]))
            for a, b, name in _runs(links)
        ),
    ]
    defects.sort(key=lambda d: (d.start, d.stop))
    return SpanCut(_clean_stretches(steps == "", links == ""), defects)


def _runs(names: np.ndarray) -> Iterable[tuple[int, int, str]]:
    """``(start, stop, name)`` of each run of equal, non-empty names in (W,)."""
    if names.size == 0:
        return
    change = np.r_[True, names[1:] != names[:-1]]
    starts = np.flatnonzero(change)
    stops = np.r_[starts[1:], names.size]
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        if names[a]:
            yield a, b, str(names[a])


def _clean_stretches(
    good_step: np.ndarray, good_link: np.ndarray
) -> list[tuple[int, int]]:
    """``[start, stop)`` of the maximal runs of good steps joined by good links.

    Args:
        good_step: (W,) True where a step passes.
        good_link: (W - 1,) True where the move from step k to k + 1 passes.
    """
    bad_link = ~good_link
    between_bad_links = np.zeros_like(good_step)
    between_bad_links[1:-1] = bad_link[:-1] & bad_link[1:]
    good = good_step & ~between_bad_links
    joined = np.r_[False, good[:-1] & good[1:] & good_link]  # k continues k - 1
    starts = np.flatnonzero(good & ~joined)
    stops = np.flatnonzero(good & ~np.r_[joined[1:], False]) + 1
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def whole_candidates(
    spans: Iterable[CoupleSpan], min_steps: int, quality: QualityThresholds
) -> WholeCandidates:
    """The clean stretches of at least ``min_steps`` steps of every span that
    pass the filters (module docstring, steps 1-3).

    Returns:
        The stretches kept and the records; ``counts`` holds ``stretches``
        (the clean stretches long enough to be judged), ``defects`` (filter ->
        the defects it cut couples at), ``stretches_dropped`` (filter -> the
        stretches it dropped), ``spans_short`` and ``seconds_in_short_spans``
        (couples shorter than the minimum), ``stretches_short`` and
        ``seconds_in_short_stretches`` (pieces left between defects).
    """
    kept: list[Windows] = []
    meta: list[dict] = []
    dropped: list[dict] = []
    defects: Counter[str] = Counter()
    failed: Counter[str] = Counter()
    short_spans: list[float] = []
    short_stretches: list[float] = []
    judged = 0
    for span in spans:
        dt = span.series.dt
        length = span.series.x_lead.shape[0]
        if length < min_steps:
            short_spans.append(length * dt)
            dropped.append(_row(span, 0, length, "short", length * dt, SPAN_UNIT))
            continue
        cut = cut_span(span.series, quality)
        for defect in cut.defects:
            defects[defect.reason] += 1
            dropped.append(_row(span, *defect))
        for start, stop in cut.stretches:
            if stop - start < min_steps:
                short_stretches.append((stop - start) * dt)
                dropped.append(
                    _row(span, start, stop, "short", short_stretches[-1], STRETCH_UNIT)
                )
                continue
            judged += 1
            stretch = _part(span.series, start, stop)
            reason, value = first_failure(stretch, quality)
            if reason[0]:
                failed[reason[0]] += 1
                dropped.append(_row(span, start, stop, reason[0], value[0]))
                continue
            kept.append(stretch)
            meta.append({**span.describe, **_times(span, start, stop)})
    windows, lengths = _stack_ragged(kept)
    counts = {
        "stretches": judged,
        "defects": _in_filter_order(defects),
        "stretches_dropped": _in_filter_order(failed),
        "spans_short": len(short_spans),
        "seconds_in_short_spans": round(float(sum(short_spans)), 6),
        "stretches_short": len(short_stretches),
        "seconds_in_short_stretches": round(float(sum(short_stretches)), 6),
    }
    return WholeCandidates(windows, lengths, meta, dropped, counts)


def _times(span: CoupleSpan, start: int, stop: int) -> dict[str, float]:
    """``t_start``, ``t_end`` [s] of the span's steps ``[start, stop)``."""
    dt = span.series.dt
    return {"t_start": span.t0 + start * dt, "t_end": span.t0 + (stop - 1) * dt}


def _row(
    span: CoupleSpan,
    start: int,
    stop: int,
    reason: str,
    value: float,
    unit: str | None = None,
) -> dict:
    """A ``dropped.csv`` row for the span's steps ``[start, stop)``; ``unit``
    None: the filter's (:data:`~torchcf.data.quality.FILTERS`)."""
    return {
        **{k: span.describe[k] for k in _WHERE},
        **_times(span, start, stop),
        "reason": reason,
        "value": float(value),
        "unit": FILTERS[reason][1] if unit is None else unit,
    }


def _in_filter_order(counts: Counter[str]) -> dict[str, int]:
    return {name: counts[name] for name in FILTERS if counts[name]}


def _part(series: Windows, start: int, stop: int) -> Windows:
    """Steps ``[start, stop)`` of a (W, K) Windows."""
    return Windows(
        **{
            k: v[start:stop] if isinstance(v, np.ndarray) else v
            for k, v in series._asdict().items()
        }
    )


def _stack_ragged(parts: list[Windows]) -> tuple[Windows, np.ndarray]:
    """(T, K) arrays of K (W_i, 1) stretches, NaN and absent after each end;
    (K,) their lengths."""
    lengths = np.array([p.x_lead.shape[0] for p in parts], dtype=np.int64)
    n_steps = int(lengths.max()) if parts else 0
    present = np.arange(n_steps)[:, None] < lengths[None, :]  # (T, K)
    columns = {}
    for name in Windows._fields:
        if name in ("present", "dt"):
            continue
        column = np.full((n_steps, len(parts)), np.nan)
        for j, part in enumerate(parts):
            column[: lengths[j], j] = getattr(part, name)[:, 0]
        columns[name] = column
    dt = parts[0].dt if parts else 1.0
    return Windows(present=present, dt=dt, **columns), lengths
