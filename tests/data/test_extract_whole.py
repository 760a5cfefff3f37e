"""Whole couples (``window="whole"``): each couple one pair of its own length,
cut only at its defects, written and read back ragged.

The couples are those of :mod:`tests.data.test_extract` (a leader on a sine
around 15 m/s, its follower repeating it 1 s later 20 m back), of different
durations, so every pair's length and values are known.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from tests.data.test_extract import DT, couple_rows, leader_motion, table_of
from torchcf.data import load_pairs
from torchcf.data.extract import MIN_WHOLE_LENGTH, ExtractOptions, extract_pairs
from torchcf.data.pairset import DataError
from torchcf.data.quality import (
    FILTERS,
    QualityThresholds,
    Windows,
    first_failure,
    step_failures,
)
from torchcf.data.writer import write_extraction


def seconds(duration: float) -> np.ndarray:
    return np.round(np.arange(0.0, duration, DT), 10)


def whole(**kwargs) -> ExtractOptions:
    kwargs.setdefault("test_fraction", 0.0)
    return ExtractOptions(window="whole", **kwargs)


#: run -> duration [s]: three couples long enough, one under the minimum.
DURATIONS = {"a": 30.0, "b": 45.0, "c": 12.3, "d": 6.0}


def ragged_table():
    frames = []
    for k, (run, duration) in enumerate(DURATIONS.items()):
        frames += couple_rows(seconds(duration), run=run, phase=0.5 * k)
    return table_of(frames)


def test_whole_couples_keep_their_lengths_and_values() -> None:
    result = extract_pairs(ragged_table(), whole())
    pairs, index = result.pairs, result.index
    assert list(index["run"]) == ["a", "b", "c"]
    assert pairs.lengths.tolist() == [300, 450, 123] == list(index["steps"])
    assert pairs.n_steps == 450  # the longest; the others are masked after
    assert list(index["t_start"]) == pytest.approx([0.0, 0.0, 0.0])
    assert list(index["t_end"]) == pytest.approx([29.9, 44.9, 12.2])
    for j, (run, duration) in enumerate(list(DURATIONS.items())[:3]):
        t = seconds(duration)
        steps = len(t)
        xf, vf, _ = leader_motion(t - 1.0, 0.5 * j)
        np.testing.assert_allclose(
            pairs.x_follow[:steps, j].numpy(), xf - 20.0, atol=1e-9
        )
        np.testing.assert_allclose(pairs.v_follow[:steps, j].numpy(), vf, atol=1e-12)
        assert pairs.mask[:, j].sum() == steps, run
    summary = result.summary
    assert summary["pairs_are"] == "whole couples"
    assert summary["pair_seconds"] == pytest.approx(
        {"min": 12.3, "median": 30.0, "max": 45.0}
    )
    assert any("whole couples of 12.3-45.0 s" in n for n in result.notes)


def test_a_couple_under_the_minimum_is_dropped_and_counted() -> None:
    result = extract_pairs(ragged_table(), whole())
    assert MIN_WHOLE_LENGTH == 10.0
    assert "d" not in set(result.index["run"])
    assert result.summary["spans_short"] == 1
    assert result.summary["seconds_in_short_spans"] == pytest.approx(6.0)
    (row,) = result.dropped.itertuples()
    assert (row.run, row.reason, row.unit) == ("d", "short", "s (span length)")
    assert row.value == pytest.approx(6.0)


def test_defects_cut_a_couple_into_its_clean_stretches() -> None:
    """A 3 m jump at 20 s splits a 45 s couple without losing a step; a NaN
    speed at 35 s removes that step, and the 9.9 s left after it is short."""
    frames = couple_rows(seconds(45.0))
    follow = frames[1]
    follow.loc[follow.index[200:], "position"] += 3.0
    follow.loc[follow.index[200:], "gap"] -= 3.0
    follow.loc[follow.index[350], "speed"] = np.nan
    result = extract_pairs(table_of(frames), whole())
    assert result.pairs.lengths.tolist() == [200, 150]
    assert list(result.index["t_start"]) == pytest.approx([0.0, 20.0])
    assert list(result.index["t_end"]) == pytest.approx([19.9, 34.9])
    # the second stretch starts on the step after the jump, shifted 3 m
    xf, _, _ = leader_motion(seconds(45.0) - 1.0)
    assert result.pairs.x_follow[0, 1].item() == pytest.approx(xf[200] - 17.0)
    summary = result.summary
    assert summary["defects"] == {"missing": 1, "jump": 1}
    assert summary["stretches_short"] == 1
    assert summary["seconds_in_short_stretches"] == pytest.approx(9.9)
    dropped = result.dropped.set_index("reason")
    assert dropped.loc["jump", "value"] == pytest.approx(3.0, abs=0.01)
    assert dropped.loc["jump", "t_start"] == pytest.approx(19.9)  # the link
    assert dropped.loc["missing", "t_start"] == pytest.approx(35.0)
    assert dropped.loc["short", "unit"] == "s (stretch length)"


def test_stretch_wide_filters_judge_each_stretch() -> None:
    frames = couple_rows(seconds(30.0)) + couple_rows(seconds(30.0), run="s")
    frames[1].loc[frames[1].index[150:], "gap"] += 8.0  # a shifted spacing log
    result = extract_pairs(table_of(frames), whole())
    assert list(result.index["run"]) == ["s"]
    assert result.summary["stretches_dropped"] == {"gap_consistency": 1}
    (row,) = result.dropped.itertuples()
    assert (row.run, row.reason, row.t_start, row.t_end) == pytest.approx(
        ("r", "gap_consistency", 0.0, 29.9)
    )
    off = whole(quality=QualityThresholds(gap_drift=None))
    assert extract_pairs(table_of(frames), off).pairs.n_pairs == 2


def test_written_ragged_folder_reads_back_with_its_lengths(tmp_path) -> None:
    result = extract_pairs(ragged_table(), whole(test_fraction=0.4, split_by="run"))
    out = write_extraction(result, tmp_path / "pairs", record={"command": "test"})
    meta = json.loads((out / "meta.json").read_text())
    assert meta["pairs"]["kind"] == "whole couples"
    assert meta["pairs"]["seconds"] == pytest.approx(
        {"min": 12.3, "median": 30.0, "max": 45.0}
    )
    index = pd.read_csv(out / "index.csv", keep_default_na=False)
    full = load_pairs(out)
    assert full.lengths.tolist() == index["steps"].tolist() == [300, 450, 123]
    valid = full.mask.numpy()
    np.testing.assert_array_equal(
        full.x_follow.numpy()[valid], result.pairs.x_follow.numpy()[valid]
    )
    for split in ("train", "test"):
        side = load_pairs(out, split)
        steps = index.loc[index["split"] == split, "steps"].tolist()
        assert side.lengths.tolist() == steps and steps


def test_no_test_split_writes_no_testing_folder(tmp_path) -> None:
    result = extract_pairs(ragged_table(), whole())
    assert result.test is None and result.summary["test_pairs"] == 0
    out = write_extraction(result, tmp_path / "pairs")
    assert (out / "Trajectory").is_dir() and not (out / "Testing").exists()
    assert load_pairs(out, "train").lengths.tolist() == [300, 450, 123]


def test_whole_mode_errors() -> None:
    short = table_of(couple_rows(seconds(6.0)) + couple_rows(seconds(8.0), run="s"))
    with pytest.raises(DataError, match=r"lasts 10 s.*2 couple spans, median 7.0"):
        extract_pairs(short, whole())
    with pytest.raises(DataError, match="stride is not used with window 'whole'"):
        whole(stride=5.0)
    with pytest.raises(DataError, match="> 0, 'auto' or 'whole'"):
        ExtractOptions(window="wholes")


def test_windows_are_unchanged_by_the_whole_mode() -> None:
    result = extract_pairs(ragged_table(), ExtractOptions(window=10.0, test_fraction=0))
    assert result.summary["pairs_are"] == "windows"
    assert result.summary["window_steps"] == 100
    assert result.pairs.mask.all() and not result.whole
    assert (result.index["steps"] == 100).all()


def test_step_failures_agree_with_the_window_checks() -> None:
    """The first step-wise filter a window fails is the earliest filter that
    fails at one of its steps or links (the window checks reduce the same
    numbers), on random windows with planted defects."""
    rng = np.random.default_rng(0)
    width, k, dt = 30, 400, 0.1
    v_lead = 15.0 + rng.normal(0.0, 0.3, (width, k))
    v_follow = 15.0 + rng.normal(0.0, 0.3, (width, k))
    x_lead = 30.0 + np.cumsum(v_lead * dt, axis=0)
    x_follow = np.cumsum(v_follow * dt, axis=0)
    a_lead, a_follow = rng.normal(0.0, 3.0, (2, width, k))
    for size in (2.0, 0.4):  # a jump; a speed mismatch (0.4 m in 0.1 s)
        planted = np.where(rng.random((width, k)) < 0.01, size, 0.0)
        x_follow += planted.cumsum(axis=0)
    present = rng.random((width, k)) > 0.003
    x_lead[~present] = np.nan
    x_follow[rng.random((width, k)) < 0.003] = 40.0  # past the leader
    w = Windows(
        present=present,
        x_lead=x_lead,
        v_lead=v_lead,
        a_lead=a_lead,
        x_follow=x_follow,
        v_follow=v_follow,
        a_follow=a_follow,
        gap=np.full((width, k), np.nan),
        leader_length=np.full((width, k), 5.0),
        dt=dt,
    )
    q = QualityThresholds(gap_drift=None, standstill_speed=None, jump=0.5)
    reason, _ = first_failure(w, q)
    failed = step_failures(w, q)
    order = {name: i for i, name in enumerate(FILTERS)}
    for column in range(k):
        names = {*failed.steps[:, column], *failed.links[:, column]} - {""}
        earliest = min(names, key=order.get) if names else ""
        assert earliest == reason[column], column
    planted = {"missing", "non_positive_gap", "jump", "speed_mismatch"}
    assert planted | {"acceleration"} <= set(reason)
