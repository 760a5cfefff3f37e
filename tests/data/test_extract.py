"""Pair extraction from a long trajectory table: couples, windows, filters, split.

Every table is made here with a known answer: a leader whose speed is a sine
around 15 m/s and a follower that repeats it 1 s later, 20 m further back, so
positions, speeds, accelerations and the recorded gap agree exactly.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from torchcf.data import load_pairs
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.pairset import DataError
from torchcf.data.quality import QualityThresholds
from torchcf.data.trajectory import TrajectoryTable

DT = 0.1
LENGTH = 5.0


def leader_motion(t: np.ndarray, phase: float = 0.0):
    """x, v, a of a leader with v = 15 + 3 sin(0.2 t + phase) [m, m/s, m/s^2]."""
    v = 15.0 + 3.0 * np.sin(0.2 * t + phase)
    x = 15.0 * t - 15.0 * np.cos(0.2 * t + phase) + 15.0 * np.cos(phase)
    a = 0.6 * np.cos(0.2 * t + phase)
    return x, v, a


def couple_rows(
    t: np.ndarray,
    *,
    run: str = "r",
    leader: str = "L",
    follower: str = "F",
    lane: str = "1",
    phase: float = 0.0,
    offset: float = 0.0,
) -> list[pd.DataFrame]:
    """Rows of a leader and its follower (1 s behind in time, 20 m further back)."""
    xl, vl, al = leader_motion(t, phase)
    xl = xl + offset
    xf, vf, af = leader_motion(t - 1.0, phase)
    xf = xf + offset - 20.0
    gap = xl - LENGTH - xf
    lead = pd.DataFrame(
        {
            "run": run,
            "vehicle": leader,
            "time": t,
            "position": xl,
            "speed": vl,
            "acceleration": al,
            "leader": "",
            "lane": lane,
            "length": LENGTH,
        }
    )
    follow = pd.DataFrame(
        {
            "run": run,
            "vehicle": follower,
            "time": t,
            "position": xf,
            "speed": vf,
            "acceleration": af,
            "leader": leader,
            "lane": lane,
            "length": LENGTH,
            "gap": gap,
        }
    )
    return [lead, follow]


def table_of(frames: list[pd.DataFrame], **kwargs) -> TrajectoryTable:
    return TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True), source="test", format="test", **kwargs
    )


def options(**kwargs) -> ExtractOptions:
    kwargs.setdefault("window", 10.0)
    kwargs.setdefault("test_fraction", 0.0)
    return ExtractOptions(**kwargs)


T = np.round(np.arange(0.0, 30.0, DT), 10)  # 300 steps: three 10 s windows


def test_clean_couple_gives_its_windows_exactly() -> None:
    result = extract_pairs(table_of(couple_rows(T)), options())
    pairs = result.pairs
    assert pairs.n_pairs == 3 and pairs.n_steps == 100
    assert result.dt == pytest.approx(DT)
    xl, vl, al = leader_motion(T)
    xf, vf, _ = leader_motion(T - 1.0)
    for j, start in enumerate((0, 100, 200)):
        part = slice(start, start + 100)
        np.testing.assert_allclose(pairs.x_lead[:, j].numpy(), xl[part], atol=1e-9)
        np.testing.assert_allclose(pairs.v_lead[:, j].numpy(), vl[part], atol=1e-12)
        np.testing.assert_allclose(pairs.a_lead[:, j].numpy(), al[part], atol=1e-12)
        np.testing.assert_allclose(
            pairs.x_follow[:, j].numpy(), xf[part] - 20.0, atol=1e-9
        )
        np.testing.assert_allclose(pairs.v_follow[:, j].numpy(), vf[part], atol=1e-12)
    assert list(result.index["t_start"]) == pytest.approx([0.0, 10.0, 20.0])
    assert set(result.index["follower"]) == {"F"} and set(result.index["leader"]) == {
        "L"
    }
    assert result.dropped.empty


def test_stride_overlaps_windows() -> None:
    result = extract_pairs(table_of(couple_rows(T)), options(stride=5.0))
    assert list(result.index["t_start"]) == pytest.approx([0.0, 5.0, 10.0, 15.0, 20.0])


def test_leader_switch_and_lane_change_end_a_couple() -> None:
    frames = couple_rows(T)
    follow = frames[1]
    # From 12 s on the follower follows another vehicle "M" (a cut-in) ...
    switch = follow["time"] >= 12.0
    follow.loc[switch, "leader"] = "M"
    xm, vm, am = leader_motion(T, 0.0)
    cutter = pd.DataFrame(
        {
            "run": "r",
            "vehicle": "M",
            "time": T,
            "position": xm - 8.0,
            "speed": vm,
            "acceleration": am,
            "leader": "",
            "lane": "1",
            "length": LENGTH,
        }
    )
    # ... and at 25 s it changes lane.
    follow.loc[follow["time"] >= 25.0, "lane"] = "2"
    result = extract_pairs(table_of([*frames, cutter]), options())
    # F-L lasts 12 s: one window [0, 10); F-M lasts 12..25 s: one window [12, 22).
    assert result.pairs.n_pairs == 2
    rows = result.index.sort_values("t_start")
    assert list(rows["leader"]) == ["L", "M"]
    assert list(rows["t_start"]) == pytest.approx([0.0, 12.0])
    # the follower in lane 2 after 25 s has its leader (lane 1) elsewhere: no couple
    assert result.summary["rows_outside_couples"] == {"the leader in another lane": 50}
    # F in lane 2 for 5 s: no span; nothing else is short
    assert result.summary["spans_short"] == 0


def test_planted_nan_and_gnss_jump_drop_their_windows() -> None:
    frames = couple_rows(T)
    follow = frames[1]
    follow.loc[follow.index[15], "speed"] = np.nan  # window 0
    follow.loc[follow.index[150:], "position"] += 3.0  # a 3 m jump in window 1
    follow.loc[follow.index[150:], "gap"] -= 3.0
    result = extract_pairs(table_of(frames), options())
    assert result.pairs.n_pairs == 1
    assert list(result.index["t_start"]) == pytest.approx([20.0])
    reasons = dict(
        zip(result.dropped["t_start"].round(6), result.dropped["reason"], strict=True)
    )
    assert reasons == {0.0: "missing", 10.0: "jump"}
    assert result.summary["windows_dropped"] == {"missing": 1, "jump": 1}
    jump = result.dropped.loc[result.dropped["reason"] == "jump", "value"].item()
    assert jump == pytest.approx(3.0, abs=0.01)


def test_time_gap_is_a_missing_step() -> None:
    frames = couple_rows(T)
    frames[1] = frames[1].drop(frames[1].index[120:125])  # 0.5 s hole in window 1
    result = extract_pairs(table_of(frames), options())
    assert list(result.index["t_start"]) == pytest.approx([0.0, 20.0])
    assert result.dropped["reason"].tolist() == ["missing"]
    assert result.dropped["value"].item() == 5  # steps


def test_gap_consistency_acceleration_and_standstill() -> None:
    frames = couple_rows(T)
    follow = frames[1]
    # window 0: the recorded gap drifts by 5 m (a shifted spacing log), more
    # than the 2 m + 0.2 m/s x 9.9 s allowed
    follow.loc[follow.index[50:100], "gap"] += 5.0
    # window 1: a 12 m/s^2 spike on the follower
    follow.loc[follow.index[150], "acceleration"] = 12.0
    result = extract_pairs(table_of(frames), options())
    assert dict(
        zip(result.dropped["t_start"].round(6), result.dropped["reason"], strict=True)
    ) == {
        0.0: "gap_consistency",
        10.0: "acceleration",
    }
    off = QualityThresholds(gap_drift=None, max_acceleration=None)
    assert extract_pairs(table_of(frames), options(quality=off)).pairs.n_pairs == 3

    # a standing leader and a follower stopped behind it
    still = couple_rows(T)
    for frame in still:
        frame["speed"] = 0.0
        frame["acceleration"] = 0.0
    still[0]["position"] = 100.0
    still[1]["position"] = 80.0
    still[1]["gap"] = 15.0
    with pytest.raises(DataError, match="leader_standstill 3"):
        extract_pairs(table_of(still), options())


def test_no_window_left_names_the_filters() -> None:
    frames = couple_rows(T)
    frames[1]["acceleration"] = 9.0
    with pytest.raises(DataError, match=r"no window .* passed .* acceleration 3"):
        extract_pairs(table_of(frames), options())
    with pytest.raises(DataError, match=r"lasts one window \(60 s\).*longest 30"):
        extract_pairs(table_of(couple_rows(T)), options(window=60.0))


def test_short_couples_get_a_window_proposed_and_auto_picks_it() -> None:
    """Couples of 6, 8 and 12 s (a data set of short trajectories): the
    default window's error names the spans and proposes the median, 8 s;
    ``window="auto"`` takes it, so two of the three couples give a pair."""
    frames = []
    for k, seconds in enumerate((6.0, 8.0, 12.0)):
        t = np.round(np.arange(0.0, seconds, DT), 10)
        frames += couple_rows(t, run=f"r{k}")
    table = table_of(frames)
    with pytest.raises(DataError) as error:
        extract_pairs(table, options(window=40.0))
    message = str(error.value)
    assert "3 couple spans, median 8.0 s, the longest 12.0 s" in message
    assert "the data support --window 8 (--window auto: the median" in message
    chosen = extract_pairs(table, options(window="auto"))
    assert chosen.summary["window_steps"] == 80
    assert chosen.pairs.n_pairs == 2
    assert any(n.startswith("window 8 s from the data (auto:") for n in chosen.notes)


def test_overlapping_vehicles_are_a_non_positive_gap() -> None:
    frames = couple_rows(T)
    # the follower 40 m further ahead from 20 s on: it overlaps its leader
    late = frames[1]["time"] >= 20.0 - 1e-9
    frames[1].loc[late, "position"] += 40.0
    frames[1].loc[late, "gap"] -= 40.0
    result = extract_pairs(table_of(frames), options())
    assert result.dropped["reason"].tolist() == ["non_positive_gap"]
    assert result.dropped["t_start"].item() == pytest.approx(20.0)


def test_leader_lengths_are_kept_in_the_spacing() -> None:
    a = couple_rows(T, run="a")
    b = couple_rows(T, run="b")
    b[0]["length"] = 12.0  # a truck leads in run b; the gap is to its rear
    b[1]["gap"] = b[1]["gap"] - 7.0
    result = extract_pairs(table_of([*a, *b]), options(leader_length=5.0))
    pairs = result.pairs
    spacing = (pairs.x_lead - pairs.x_follow - pairs.leader_length).numpy()  # (W, 6)
    assert list(result.index["run"]) == ["a"] * 3 + ["b"] * 3
    np.testing.assert_allclose(spacing[:, 3:], spacing[:, :3] - 7.0, atol=1e-9)
    np.testing.assert_allclose(pairs.x_follow[:, 3:], pairs.x_follow[:, :3])
    assert list(result.index["leader_length"]) == [5.0] * 3 + [12.0] * 3


def test_split_keeps_followers_apart_and_is_seeded() -> None:
    frames = []
    for k in range(6):
        frames += couple_rows(
            T, run="r", leader=f"L{k}", follower=f"F{k}", lane=str(k), phase=k
        )
    table = table_of(frames)
    result = extract_pairs(table, options(test_fraction=0.3, seed=3))
    index = result.index
    sides = index.groupby("follower")["split"].nunique()
    assert (sides == 1).all()
    assert result.summary["test_pairs"] == 6  # two followers x three windows
    assert result.train.n_pairs + result.test.n_pairs == result.pairs.n_pairs
    again = extract_pairs(table, options(test_fraction=0.3, seed=3))
    assert again.index["split"].tolist() == index["split"].tolist()
    other = extract_pairs(table, options(test_fraction=0.3, seed=4))
    assert other.index["split"].tolist() != index["split"].tolist()
    with pytest.raises(DataError, match="one run only"):
        extract_pairs(table, options(test_fraction=0.3, split_by="run"))


def test_result_does_not_depend_on_row_order() -> None:
    frames = couple_rows(T) + couple_rows(T, run="s", phase=1.0)
    table = table_of(frames)
    shuffled = table_of(
        [pd.concat(frames).sample(frac=1.0, random_state=0).reset_index(drop=True)]
    )
    a, b = extract_pairs(table, options()), extract_pairs(shuffled, options())
    assert a.pairs.x_follow.equal(b.pairs.x_follow)
    pd.testing.assert_frame_equal(a.index, b.index)


def test_units_that_cannot_be_right() -> None:
    frames = couple_rows(T)
    for frame in frames:
        frame["speed"] *= 3.6 * 2.0  # km/h, and fast: 30 m/s -> 216 "m/s"
    with pytest.raises(DataError, match="units cannot be right"):
        extract_pairs(table_of(frames), options())
    frames = couple_rows(T)
    for frame in frames:
        frame["position"] /= 0.3048  # positions in feet, speeds in m/s
    frames[1]["gap"] /= 0.3048
    with pytest.raises(DataError, match="position in ft, speed in m/s"):
        extract_pairs(table_of(frames), options())


@pytest.mark.parametrize(
    ("factor", "needle"),
    [(1e-3, "time in s read as ms? (--time-unit s)"),
     (1e3, "time in ms read as s? (--time-unit ms)")],
)  # fmt: skip
def test_a_time_step_no_recording_has_names_the_time_column(factor, needle) -> None:
    """Times in seconds read as milliseconds (or the reverse): the error names
    the time column's unit, not the positions and speeds."""
    frames = couple_rows(T)
    for frame in frames:
        frame["time"] *= factor
    with pytest.raises(DataError) as error:
        extract_pairs(table_of(frames), options(window=10.0 * factor))
    assert "time column's unit cannot be right" in str(error.value)
    assert needle in str(error.value)


def test_lengths_no_car_has_are_flagged_with_the_likely_unit() -> None:
    """A file in feet read as metres, positions, speeds and lengths alike: they
    agree with each other, but 5 m cars are 16.4 "m" long (feet?)."""
    frames = couple_rows(T)
    for frame in frames:
        for column in ("position", "speed", "acceleration", "length"):
            frame[column] /= 0.3048
    frames[1]["gap"] /= 0.3048
    result = extract_pairs(table_of(frames), options())
    (flag,) = [n for n in result.notes if n.startswith("vehicle lengths of")]
    assert "16.4 m (median of 2 vehicles)" in flag and "--length-unit ft" in flag
    clean = extract_pairs(table_of(couple_rows(T)), options())
    assert not [n for n in clean.notes if n.startswith("vehicle lengths")]


def test_off_grid_time_and_duplicate_rows() -> None:
    frames = couple_rows(T)
    frames[1].loc[frames[1].index[7], "time"] += 0.03
    with pytest.raises(DataError, match="not on a grid of dt = 0.1 s"):
        extract_pairs(table_of(frames), options())
    frames = couple_rows(T)
    frames[1] = pd.concat([frames[1], frames[1].iloc[[4]]])
    with pytest.raises(DataError, match="'F' has two rows at (t = |time )0.4"):
        extract_pairs(table_of(frames), options())


def test_missing_derivatives_are_derived() -> None:
    frames = couple_rows(T)
    for frame in frames:
        frame["acceleration"] = np.nan
    result = extract_pairs(table_of(frames), options())
    _, _, al = leader_motion(T)
    # Savitzky-Golay over 1 s of a 0.2 rad/s sine: exact to a few 1e-4 m/s^2
    np.testing.assert_allclose(
        result.pairs.a_lead[:, 1].numpy(), al[100:200], atol=2e-3
    )
    assert any("acceleration" in note for note in result.notes)


def test_written_folder_loads_as_pairs(tmp_path) -> None:
    from torchcf.data.writer import write_extraction

    frames = []
    for k in range(4):
        frames += couple_rows(T, leader=f"L{k}", follower=f"F{k}", lane=str(k), phase=k)
    result = extract_pairs(table_of(frames), options(test_fraction=0.25))
    out = write_extraction(result, tmp_path / "pairs", record={"command": "test"})
    meta = json.loads((out / "meta.json").read_text())
    assert meta == {"dt": 0.1, "units": "m", "leader_length": 5.0, "road_frame": None}
    full = load_pairs(out)
    assert full.x_lead.equal(result.pairs.x_lead)
    train, test = load_pairs(out, "train"), load_pairs(out, "test")
    assert train.n_pairs == result.train.n_pairs and test.n_pairs == 3
    index = pd.read_csv(out / "index.csv", keep_default_na=False)
    assert index["split"].value_counts().to_dict() == {"train": 9, "test": 3}
    record = json.loads((out / "extract.json").read_text())
    assert record["command"] == "test" and record["summary"]["pairs"] == 12
    with pytest.raises(DataError, match="--overwrite"):
        write_extraction(result, out)
    write_extraction(result, out, overwrite=True)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    with pytest.raises(DataError, match="not an extraction"):
        write_extraction(result, tmp_path / "other")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_accelerations_no_car_reaches_are_flagged() -> None:
    """Accelerations of 5 m/s^2 written in ft/s^2 (16.4) and read as m/s^2."""
    frames = couple_rows(T)
    for frame in frames:
        frame["acceleration"] = 5.0 / 0.3048
    no_filter = QualityThresholds(max_acceleration=None)
    result = extract_pairs(table_of(frames), options(quality=no_filter))
    (flag,) = [n for n in result.notes if n.startswith("accelerations up to")]
    assert "16.4 m/s^2" in flag and "--acceleration-unit ft/s^2" in flag


def test_the_command_line_shows_what_needs_attention(tmp_path, capsys) -> None:
    """A file in feet read as metres: the flag is printed, the other notes are
    counted and left to extract.json."""
    from torchcf.cli.data import main as data_main

    frames = couple_rows(T)
    for frame in frames:
        for column in ("position", "speed", "acceleration", "length"):
            frame[column] = frame[column] / 0.3048
    frames[1]["gap"] /= 0.3048
    path = tmp_path / "feet.csv"
    pd.concat(frames).to_csv(path, index=False)
    argv = ["extract", str(path), "--format", "csv", "--window", "10",
            "--test-fraction", "0", "--out", str(tmp_path / "out")]  # fmt: skip
    assert data_main(argv) == 0
    printed = capsys.readouterr().out
    assert "note: vehicle lengths of 16.4 m" in printed
    assert "more note" in printed and "in extract.json" in printed
