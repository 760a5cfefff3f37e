"""``--format gps``: GPS fixes put on one road path, against known answers.

Every track is made here: a road drawn in a local metric frame (a straight, a
bend, a loop), cars moved along it with known distances, their positions turned
into latitude and longitude with pyproj (the inverse of an azimuthal equidistant
projection centred elsewhere than the reader's), and written as GPS logs. The
reader must give back the distance along the road and the spacing.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.gps import GpsUnits, fuse_with_speed, parse_times, read_gps
from torchcf.data.pairset import DataError

pyproj = pytest.importorskip("pyproj")

ORIGIN = (47.09, 19.03)  # lat, lon: a test track in Hungary
DT = 0.1


def to_latlon(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local east/north [m] around ORIGIN -> latitude, longitude [deg]."""
    local = f"+proj=aeqd +lat_0={ORIGIN[0]} +lon_0={ORIGIN[1]} +datum=WGS84 +units=m"
    back = pyproj.Transformer.from_crs(local, "EPSG:4326", always_xy=True)
    lon, lat = back.transform(xy[:, 0], xy[:, 1])
    return np.asarray(lat), np.asarray(lon)


def straight(s: np.ndarray, heading_deg: float = 30.0) -> np.ndarray:
    h = math.radians(heading_deg)
    return np.column_stack([s * math.sin(h), s * math.cos(h)])


def bend(s: np.ndarray, radius: float = 150.0, start: float = 400.0) -> np.ndarray:
    """Due north for ``start`` m, a quarter circle to the east, then due east."""
    arc = radius * math.pi / 2
    x, y = np.zeros_like(s), s.copy()
    on_arc = (s > start) & (s <= start + arc)
    angle = (s[on_arc] - start) / radius
    x[on_arc] = radius * (1 - np.cos(angle))
    y[on_arc] = start + radius * np.sin(angle)
    after = s > start + arc
    x[after] = radius + (s[after] - start - arc)
    y[after] = start + radius
    return np.column_stack([x, y])


def loop(s: np.ndarray, radius: float = 100.0) -> np.ndarray:
    angle = s / radius
    return np.column_stack([radius * np.sin(angle), radius * (1 - np.cos(angle))])


def platoon_logs(
    road, folder: Path, seconds: float = 60.0, noise: float = 0.0, seed: int = 0
) -> tuple[Path, dict[str, np.ndarray]]:
    """Three cars on ``road``: A leads at 15 m/s, B and C follow at spacings
    that vary in time. One CSV per car (time, lat, lon, speed); returns the
    folder and each car's true distance along the road at the log times."""
    t = np.arange(0.0, seconds, DT)
    truth = {
        "A": 100.0 + 15.0 * t,
        "B": 100.0 + 15.0 * t - (25.0 + 5.0 * np.sin(0.2 * t)),
        "C": 100.0 + 15.0 * t - (55.0 + 8.0 * np.sin(0.13 * t + 1.0)),
    }
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for car, s in truth.items():
        xy = road(s) + noise * rng.standard_normal((len(s), 2))
        lat, lon = to_latlon(xy)
        speed = np.gradient(s, DT)
        pd.DataFrame({"time": t, "lat": lat, "lon": lon, "speed": speed}).to_csv(
            folder / f"{car}.csv", index=False, float_format="%.10f"
        )
    return folder, {car: s for car, s in truth.items()}


def spacing_error(table, truth, follower: str, leader: str) -> np.ndarray:
    """The reader's spacing minus the true one, at every step both have."""
    frame = table.frame.pivot_table(index="time", columns="vehicle", values="position")
    both = frame[[leader, follower]].dropna()
    t = both.index.to_numpy()
    true = np.interp(
        t, np.arange(len(truth[leader])) * DT, truth[leader] - truth[follower]
    )
    return (both[leader] - both[follower]).to_numpy() - true


@pytest.mark.parametrize(("road", "tolerance"), [(straight, 0.01), (bend, 0.15)])
def test_spacing_along_a_straight_and_a_bend(tmp_path, road, tolerance):
    folder, truth = platoon_logs(road, tmp_path / "logs")
    table = read_gps(folder, platoon="A,B,C")
    assert table.format == "gps" and table.road_frame
    for follower, leader in (("B", "A"), ("C", "B")):
        error = spacing_error(table, truth, follower, leader)
        assert np.abs(error).max() < tolerance, (follower, np.abs(error).max())
    leaders = table.frame.groupby("vehicle")["leader"].first().to_dict()
    assert leaders == {"A": "", "B": "A", "C": "B"}
    # positions increase in the direction of travel at the cars' speed
    a = table.frame[table.frame["vehicle"] == "A"]
    assert np.polyfit(a["time"], a["position"], 1)[0] == pytest.approx(15.0, rel=1e-3)


def test_a_loop_driven_twice_counts_its_distance_on(tmp_path):
    """2.3 laps of a 628 m circle: positions never jump back a lap."""
    folder, truth = platoon_logs(loop, tmp_path / "logs", seconds=96.0)
    table = read_gps(folder, platoon="A,B,C")
    for car in "ABC":
        rows = table.frame[table.frame["vehicle"] == car]
        assert np.all(np.diff(rows["position"].to_numpy()) > 0)
        driven = rows["position"].iloc[-1] - rows["position"].iloc[0]
        assert driven == pytest.approx(truth[car][-1] - truth[car][0], rel=2e-3)
    assert np.abs(spacing_error(table, truth, "B", "A")).max() < 0.15


def test_receiver_noise_is_tamed_by_the_recorded_speed(tmp_path):
    """0.5 m of white noise on every fix (each axis): fused with the recorded
    speeds, the spacing's error falls well under that of two noisy positions
    (0.5 sqrt(2) m), without bias; without speeds, it stays that of the fixes."""
    folder, truth = platoon_logs(bend, tmp_path / "logs", noise=0.5)
    table = read_gps(folder, platoon="A,B,C")
    error = spacing_error(table, truth, "B", "A")
    assert np.sqrt(np.mean(error**2)) < 0.25
    assert abs(np.mean(error)) < 0.1  # no bias
    for car in "ABC":
        log = pd.read_csv(folder / f"{car}.csv").drop(columns="speed")
        log.to_csv(folder / f"{car}.csv", index=False, float_format="%.10f")
    raw = spacing_error(read_gps(folder, platoon="A,B,C"), truth, "B", "A")
    assert 0.5 < np.sqrt(np.mean(raw**2)) < 0.9


def test_the_fusion_follows_a_speed_and_restarts_after_a_gap():
    t = np.r_[np.arange(0.0, 5.0, 0.1), np.arange(10.0, 12.0, 0.1)]
    speed = np.full(t.size, 10.0)
    exact = 10.0 * t
    assert fuse_with_speed(exact, speed, t, 0.1) == pytest.approx(exact)
    shifted = exact + np.where(t >= 10.0, 3.0, 0.0)  # a jump across the dropout
    fused = fuse_with_speed(shifted, speed, t, 0.1)
    assert fused[t >= 10.0] == pytest.approx(shifted[t >= 10.0])  # restarted


def test_a_dropout_leaves_its_steps_out_and_a_jump_is_dropped(tmp_path):
    folder, truth = platoon_logs(straight, tmp_path / "logs")
    log = pd.read_csv(folder / "B.csv")
    log = log[(log["time"] < 20.0) | (log["time"] >= 23.0)].copy()
    jump = log.index[log["time"].sub(30.0).abs().argmin()]
    log.loc[jump, "lat"] += 0.003  # 330 m north: off the road and a jump
    log.to_csv(folder / "B.csv", index=False, float_format="%.10f")
    table = read_gps(folder, platoon="A,B,C")
    b = table.frame[table.frame["vehicle"] == "B"]
    times = np.round(b["time"].to_numpy() / DT).astype(int)
    assert not set(range(201, 230)) & set(times)  # the dropout's steps
    assert set(range(100, 200)) <= set(times)
    assert any("dropped 1 fix (off path)" in note for note in table.notes)
    assert np.abs(spacing_error(table, truth, "B", "A")).max() < 0.01


def test_receivers_on_different_clocks_meet_on_one_grid(tmp_path):
    """B's receiver stamps 40 ms late: its positions are interpolated onto the
    run's grid, and the spacing at each step is the true one."""
    folder, truth = platoon_logs(straight, tmp_path / "logs")
    log = pd.read_csv(folder / "B.csv")
    log["time"] += 0.04
    late = log["time"].to_numpy()
    b_at = 100.0 + 15.0 * late - (25.0 + 5.0 * np.sin(0.2 * late))  # B's truth
    log["lat"], log["lon"] = to_latlon(straight(b_at))
    log["speed"] = 15.0 - np.cos(0.2 * late)  # and its speed then
    log.to_csv(folder / "B.csv", index=False, float_format="%.10f")
    table = read_gps(folder, platoon="A,B,C")
    frame = table.frame.pivot_table(index="time", columns="vehicle", values="position")
    both = frame[["A", "B"]].dropna()
    assert len(both) > 500
    t = both.index.to_numpy()
    stamps = np.arange(len(truth["B"])) * DT
    true = np.interp(t, stamps, truth["A"]) - np.interp(t, stamps, truth["B"])
    # linear interpolation of B's motion between fixes: under 1 mm here
    assert np.abs((both["A"] - both["B"]).to_numpy() - true).max() < 0.01


def test_the_nearest_car_ahead_leads_without_a_platoon(tmp_path):
    folder, _ = platoon_logs(bend, tmp_path / "logs")
    table = read_gps(folder)
    leaders = table.frame.groupby("vehicle")["leader"].agg(lambda s: set(s))
    assert leaders.to_dict() == {"A": {""}, "B": {"A"}, "C": {"B"}}


def test_one_long_table_with_its_own_names_and_a_leader_column(tmp_path):
    folder, truth = platoon_logs(straight, tmp_path / "logs")
    rows = []
    for car, ahead in (("A", ""), ("B", "A"), ("C", "B")):
        log = pd.read_csv(folder / f"{car}.csv")
        rows.append(log.assign(car=car, front=ahead))
    long = pd.concat(rows).rename(columns={"time": "T", "lat": "Lat", "lon": "Lng"})
    path = tmp_path / "fleet.csv"
    long.to_csv(path, index=False, float_format="%.10f")
    table = read_trajectories(
        path, "gps", columns="vehicle=car,time=T,lat=Lat,lon=Lng,leader=front"
    )
    assert set(table.frame["run"]) == {"fleet"}
    assert np.abs(spacing_error(table, truth, "C", "B")).max() < 0.01
    assert set(table.frame.loc[table.frame["vehicle"] == "C", "leader"]) == {"B"}


def test_gps_week_seconds_and_time_stamps():
    week = pd.Series([604_799.8, 604_799.9, 0.0, 0.1])
    assert parse_times(week, "auto", 1.0) == pytest.approx(
        [604_799.8, 604_799.9, 604_800.0, 604_800.1]
    )
    stamps = pd.Series(["2026-05-01T10:00:00.0Z", "2026-05-01T10:00:00.1Z"])
    seconds = parse_times(stamps, "auto", 1.0)
    assert seconds[1] - seconds[0] == pytest.approx(0.1)
    with pytest.raises(DataError, match="is not a date"):
        parse_times(pd.Series(["2026-05-01", "soon"]), "timestamp", 1.0)


def test_a_week_rollover_is_undone_per_vehicle(tmp_path):
    """Two cars logged in GPS week seconds across the week's end, one file
    each: each car's clock rolls over once, whatever the other's does."""
    folder, truth = platoon_logs(straight, tmp_path / "logs", seconds=20.0)
    for car in "ABC":
        log = pd.read_csv(folder / f"{car}.csv")
        log["time"] = (log["time"] + 604_790.0) % 604_800.0
        log.to_csv(folder / f"{car}.csv", index=False, float_format="%.10f")
    table = read_gps(folder, platoon="A,B,C")
    for car in "ABC":
        times = table.frame.loc[table.frame["vehicle"] == car, "time"].to_numpy()
        assert times.min() == pytest.approx(604_790.0, abs=0.1)
        assert np.all(np.diff(times) > 0) and times.max() < 604_811.0
    assert np.abs(spacing_error_shifted(table, truth, 604_790.0)).max() < 0.01


def spacing_error_shifted(table, truth, shift: float) -> np.ndarray:
    frame = table.frame.pivot_table(index="time", columns="vehicle", values="position")
    both = frame[["A", "B"]].dropna()
    t = both.index.to_numpy() - shift
    stamps = np.arange(len(truth["A"])) * DT
    true = np.interp(t, stamps, truth["A"] - truth["B"])
    return (both["A"] - both["B"]).to_numpy() - true


def test_pairs_cut_from_gps_logs_carry_the_spacing(tmp_path):
    """End to end: logs -> table -> pairs, whose spacing is the true one."""
    folder, truth = platoon_logs(bend, tmp_path / "logs", seconds=90.0)
    table = read_gps(folder, platoon="A,B,C")
    extraction = extract_pairs(table, ExtractOptions(window=40.0))
    pairs = extraction.pairs
    assert pairs.n_pairs == 4  # two couples x two 40-s windows
    spacing = (pairs.x_lead - pairs.x_follow).double()
    assert float(spacing.min()) > 15.0 and float(spacing.max()) < 70.0


@pytest.mark.parametrize(
    ("options", "needle"),
    [
        ({"platoon": "A,X"}, "platoon vehicle(s) X not in the logs"),
        ({"leader_rule": "platoon"}, "needs the platoon's order"),
        ({"leader_rule": "ahead"}, "unknown leader rule 'ahead'"),
        ({"units": GpsUnits(time_format="julian")}, "unknown time format"),
        ({"columns": "lat=Latitude"}, "column 'Latitude' (mapped to lat) not in"),
    ],
)
def test_bad_options_are_one_line(tmp_path, options, needle):
    folder, _ = platoon_logs(straight, tmp_path / "logs", seconds=5.0)
    with pytest.raises(DataError) as error:
        read_gps(folder, **options)
    assert needle in str(error.value) and "\n" not in str(error.value)


def test_fixes_without_a_position_are_dropped_with_their_reason(tmp_path):
    folder, _ = platoon_logs(straight, tmp_path / "logs", seconds=10.0)
    log = pd.read_csv(folder / "C.csv")
    log.loc[5:9, "lat"] = np.nan
    log.loc[10, "lon"] = 400.0
    log.to_csv(folder / "C.csv", index=False)
    table = read_gps(folder, platoon="A,B,C")
    assert any("dropped 6 fixes (no fix)" in note for note in table.notes)


def test_the_command_line_extracts_pairs_from_gps_logs(tmp_path, capsys):
    from torchcf.cli.data import main as data_main

    folder, _ = platoon_logs(bend, tmp_path / "logs", seconds=90.0)
    out = tmp_path / "pairs"
    argv = ["extract", str(folder), "--format", "gps", "--platoon", "A,B,C",
            "--out", str(out), "--window", "40", "--test-fraction", "0.5"]  # fmt: skip
    assert data_main(argv) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "couple spans shorter than a window of 40 s (" in printed  # the window
    record = json.loads((out / "extract.json").read_text())
    assert record["summary"]["pairs"] == 4
    # a window from the data: the couples last the whole 90 s, auto caps at 40 s
    auto = [
        *argv[: argv.index("--window")],
        "--window",
        "auto",
        *argv[argv.index("--window") + 2 :],
    ]
    assert data_main([*auto, "--overwrite"]) == 0
    assert (
        json.loads((out / "extract.json").read_text())["summary"]["window_steps"] == 400
    )
    # an option of another format is refused in one line
    argv[argv.index("--platoon")] = "--recordings"
    assert data_main([*argv, "--overwrite"]) == 2
    assert "recordings: only used with format='highd'" in capsys.readouterr().err
