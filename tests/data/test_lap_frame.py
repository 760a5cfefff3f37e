"""A circular track's lap coordinate (``read_openacc(..., lap_frame=True)``).

Platoon files written here drive round a known tilted circle, both ways, with
one run on an access road; the lap frame must find the circle, leave that run
out, and put every car on one coordinate along which both directions feel the
same grade. Then the real ZalaZONE campaign when ``$TORCHCF_RAW`` holds it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from torchcf.cli.data import main as data_main
from torchcf.data.formats.openacc import read_openacc
from torchcf.data.formats.track import (
    Circle,
    fit_circle,
    fit_tilt,
    lap_position,
    travel_direction,
)
from torchcf.data.pairset import DataError

CENTRE = (40.0, -25.0)  # [m] E, N
RADIUS = 120.0  # [m]
SLOPE = 0.012  # the plane's grade [1]
LOWEST = math.radians(-50.0)  # polar angle of the track's lowest point
LENGTH = 5.0  # [m] the reader's vehicle length
DT = 0.1  # [s]
STEPS = 600
SPEED = 15.0  # [m/s] every car
IVS = 20.0  # [m] every gap


def altitude(angle: np.ndarray) -> np.ndarray:
    """[m] of the tilted plane round the circle (lowest at LOWEST)."""
    return 200.0 - SLOPE * RADIUS * np.cos(angle - LOWEST)


def write_run(path: Path, start: float, direction: int, *, off: bool = False) -> Path:
    """Three cars round the circle from polar angle ``start`` [rad], ``direction``
    +1 anticlockwise / -1 clockwise, 20 m apart; ``off`` drives the whole run
    on a straight road 500 m away instead."""
    time = 100.0 + DT * np.arange(STEPS)
    columns: dict[str, np.ndarray] = {"Time": time}
    for k in (1, 2, 3):
        behind = (k - 1) * (IVS + LENGTH)  # arc metres behind car 1
        arc = SPEED * (time - time[0]) - behind
        angle = start + direction * arc / RADIUS
        if off:
            east, north = 600.0 + arc, np.full(STEPS, 500.0)
        else:
            east = CENTRE[0] + RADIUS * np.cos(angle)
            north = CENTRE[1] + RADIUS * np.sin(angle)
        columns[f"Speed{k}"] = np.full(STEPS, SPEED)
        columns[f"E{k}"], columns[f"N{k}"] = east, north
        columns[f"Alt{k}"] = altitude(angle)
    for k in (1, 2):
        columns[f"IVS{k}"] = np.full(STEPS, IVS)
    lines = [
        "Date,8,10,2019",
        "Vehicle_order,TARGET,CAR_A,CAR_B,",
        "Number_of_vehicles,3",
        "ACC,1",
        "Distance_setting,S",
        ",".join(columns),
        *(",".join(f"{columns[c][i]:.6f}" for c in columns) for i in range(STEPS)),
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\r\n".join(lines) + "\r\n", encoding="ascii")
    return path


@pytest.fixture
def campaign(tmp_path) -> Path:
    root = tmp_path / "campaign"
    write_run(root / "cw" / "run1.csv", start=0.3, direction=-1)
    write_run(root / "cw" / "run2.csv", start=2.0, direction=-1)
    write_run(root / "ccw" / "run3.csv", start=-2.5, direction=1)
    write_run(root / "access" / "run4.csv", start=0.0, direction=1, off=True)
    return root


# ------------------------------------------------------------------- geometry
def test_fit_circle_follows_the_majority_not_a_road_off_the_track():
    rng = np.random.default_rng(0)
    angle = rng.uniform(-math.pi, math.pi, 400)
    on = (
        CENTRE[0] + RADIUS * np.cos(angle) + rng.normal(0, 0.5, 400),
        CENTRE[1] + RADIUS * np.sin(angle) + rng.normal(0, 0.5, 400),
    )
    road = (np.linspace(-600.0, 600.0, 300), np.full(300, 700.0))
    circle = fit_circle([on, road])
    assert circle.east == pytest.approx(CENTRE[0], abs=0.2)
    assert circle.north == pytest.approx(CENTRE[1], abs=0.2)
    assert circle.radius == pytest.approx(RADIUS, abs=0.2)
    assert circle.lap == pytest.approx(2 * math.pi * circle.radius)
    with pytest.raises(ValueError, match="not on a line"):
        fit_circle([(np.arange(5.0), 2 * np.arange(5.0))])


def test_fit_tilt_finds_the_lowest_point_and_the_slope():
    angle = np.linspace(-3.0, 2.0, 300)  # part of the circle suffices
    tilt = fit_tilt(angle, altitude(angle), RADIUS)
    assert tilt.lowest == pytest.approx(LOWEST, abs=1e-9)
    assert tilt.grade == pytest.approx(SLOPE, rel=1e-9)
    assert tilt.rms < 1e-9 and tilt.samples == 300


def test_direction_and_lap_position():
    assert travel_direction(np.array([3.0, 3.1, -3.1, -3.0])) == 1  # over +-pi
    assert travel_direction(np.array([0.2, 0.1, 0.0])) == -1
    assert travel_direction(np.zeros(4)) == 0
    # a quarter lap from the reference, each way round
    assert lap_position(math.pi / 2, 1, 0.0, 100.0) == pytest.approx(50 * math.pi)
    assert lap_position(math.pi / 2, -1, 0.0, 100.0) == pytest.approx(150 * math.pi)
    assert Circle(0.0, 0.0, 2.0).distance(np.array([3.0]), np.array([0.0]))[0] == 1.0


# ------------------------------------------------------------------ lap frame
def test_every_run_on_the_circle_shares_one_grade_profile(campaign):
    """Both ways round, the grade a car feels (the altitude's change per metre
    driven) is the same function of its lap position: ``SLOPE sin(s / R)``,
    s measured from the lowest point in the direction of travel."""
    table = read_openacc(campaign, lap_frame=True)
    assert table.road_frame is True
    assert table.road_period == pytest.approx(2 * math.pi * RADIUS, abs=0.05)
    frame = table.frame
    assert set(frame["run"]) == {"cw/run1", "cw/run2", "ccw/run3"}
    assert any("access/run4 left out" in n for n in table.notes)
    assert any("slope 1.20 %" in n for n in table.notes)
    for _, car in frame.groupby(["run", "vehicle"]):
        s = car["position"].to_numpy()
        # the grade felt: d altitude / d distance driven, from the file's Alt
        lap = np.mod(s, table.road_period)
        felt = SLOPE * np.sin(lap / RADIUS)
        true = _grade_driven(campaign, car)
        np.testing.assert_allclose(felt[1:-1], true[1:-1], atol=2e-4)


def _grade_driven(root: Path, car) -> np.ndarray:
    """(T,) d altitude / d distance [1] of one car, from its file's E/N/Alt."""
    run, k = car["run"].iloc[0], car["vehicle"].iloc[0]
    text = (root / f"{run}.csv").read_text().splitlines()
    names = text[5].split(",")
    rows = np.array([[float(c) for c in line.split(",")] for line in text[6:]])
    col = {n: rows[:, i] for i, n in enumerate(names)}
    path = np.hypot(np.diff(col[f"E{k}"]), np.diff(col[f"N{k}"]))
    slope = np.diff(col[f"Alt{k}"]) / path
    # central estimate at each sample (the mean of the steps either side)
    return np.concatenate(([slope[0]], 0.5 * (slope[1:] + slope[:-1]), [slope[-1]]))


def test_the_lap_frame_keeps_every_recorded_gap(campaign):
    plain, lap = read_openacc(campaign), read_openacc(campaign, lap_frame=True)
    for table in (plain, lap):
        frame = table.frame.set_index(["run", "vehicle", "time"])
        follower = frame.xs("2", level="vehicle")
        leader = frame.xs("1", level="vehicle")
        np.testing.assert_allclose(
            leader["position"] - follower["position"] - LENGTH, IVS, atol=1e-9
        )
    assert plain.road_frame is False and plain.road_period is None


def test_both_ways_without_altitudes_is_refused(campaign):
    for path in campaign.rglob("*.csv"):
        lines = path.read_text().splitlines()
        names = lines[5].split(",")
        keep = [i for i, n in enumerate(names) if not n.startswith("Alt")]
        lines = lines[:5] + [",".join(r.split(",")[i] for i in keep) for r in lines[5:]]
        path.write_text("\r\n".join(lines) + "\r\n")
    with pytest.raises(DataError, match="both ways round the track"):
        read_openacc(campaign, lap_frame=True)


def test_no_run_on_a_circle_is_refused(tmp_path):
    write_run(tmp_path / "a.csv", start=0.0, direction=1, off=True)
    with pytest.raises(DataError, match="lap_frame: no"):
        read_openacc(tmp_path, lap_frame=True)


def test_extract_writes_the_period_and_the_loop_reads_it(campaign, tmp_path, capsys):
    """``data extract --lap-frame`` records the lap in meta.json; the pairs read
    back carry it, and a bare grade becomes a profile round the lap."""
    from torchcf.data import load_pairs
    from torchcf.diagnose.arms.arena import resolve_effect

    out = tmp_path / "pairs"
    argv = ["extract", str(campaign), "--format", "openacc", "--lap-frame"]
    assert data_main([*argv, "--window", "20", "--out", str(out)]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["road_frame"] is True
    assert meta["road_period"] == pytest.approx(2 * math.pi * RADIUS, abs=0.05)
    pairs = load_pairs(out, "train")
    assert pairs.road_period == meta["road_period"]
    token = resolve_effect("grade", pairs).token
    assert token == f"grade(period={meta['road_period']:g})"
    assert data_main([*argv[:3], "csv", "--lap-frame", "--out", str(tmp_path)]) == 2
    assert "lap_frame: only used with format='openacc'" in capsys.readouterr().err


# ------------------------------------------------------------------ real data
def test_zalazone_lap_frame(zalazone):
    """The dynamic platform: a circle of radius ~143.4 m (SOURCE.md: about
    143.6 m, 902 m a lap) tilted about 1 %; the three runs that drive to it on
    the access roads are left out."""
    table = read_openacc(zalazone, lap_frame=True)
    assert table.road_period == pytest.approx(901.0, abs=3.0)
    assert table.frame["run"].nunique() == 16
    left = [n for n in table.notes if "left out" in n]
    assert len(left) == 3 and any("dynamic_part26" in n for n in left)
    (tilt,) = [n for n in table.notes if "lie on a plane of slope" in n]
    slope = float(tilt.split("slope ")[1].split(" %")[0])
    assert 0.8 <= slope <= 1.3


def test_a_config_names_the_lap_frame_for_openacc_only():
    from torchcf.config.raw import RawSource

    raw = RawSource(source="x", format="openacc", lap_frame=True)
    assert raw.reader_options()["lap_frame"] is True
    with pytest.raises(ValueError, match="lap_frame: only used with format='openacc'"):
        RawSource(source="x", format="csv", lap_frame=True)
