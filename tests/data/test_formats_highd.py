"""read_highd on small recordings written here, with known answers.

Every recording is made in road coordinates first (front bumper along the
direction of travel, speeds positive) and written in highD's image frame:
``x`` is the bounding box's low-x edge, ``width`` the vehicle's length, and
velocities are negative on the upper lanes (drivingDirection 1). Reading it
back must give the road coordinates again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from torchcf.data import formats
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.highd import read_highd
from torchcf.data.pairset import DataError

RATE = 25.0  # [Hz]
FRAMES = np.arange(1, 251)  # 10 s at 25 Hz, highD frames count from 1
CUT = 126  # the frame where a planted change happens (t = 5.04 s)
CAR, TRUCK = 4.5, 12.0  # lengths [m]

TRACK_HEADER = (
    "frame,id,x,y,width,height,xVelocity,yVelocity,xAcceleration,yAcceleration,"
    "frontSightDistance,backSightDistance,dhw,thw,ttc,precedingXVelocity,"
    "precedingId,followingId,leftPrecedingId,leftAlongsideId,leftFollowingId,"
    "rightPrecedingId,rightAlongsideId,rightFollowingId,laneId"
).split(",")
META_HEADER = (
    "id,width,height,initialFrame,finalFrame,numFrames,class,drivingDirection,"
    "traveledDistance,minXVelocity,maxXVelocity,meanXVelocity,minDHW,minTHW,"
    "minTTC,numLaneChanges"
).split(",")
RECORDING_HEADER = (
    "id,frameRate,locationId,speedLimit,month,weekDay,startTime,duration,"
    "totalDrivenDistance,totalDrivenTime,numVehicles,numCars,numTrucks,"
    "upperLaneMarkings,lowerLaneMarkings"
).split(",")


def motion(frames: np.ndarray, start: float, phase: float = 0.0):
    """Front bumper, speed, acceleration of v = 30 + 2 sin(0.5 t + phase) [m/s].

    Positions are the exact integral of the speed, so the jump filter passes.
    """
    t = frames / RATE
    speed = 30.0 + 2.0 * np.sin(0.5 * t + phase)
    front = start + 30.0 * t - 4.0 * (np.cos(0.5 * t + phase) - np.cos(phase))
    acceleration = 1.0 * np.cos(0.5 * t + phase)
    return front, speed, acceleration


@dataclass
class Vehicle:
    """One highD track in road coordinates (front bumper along the travel)."""

    id: int
    start: float  # front bumper at t = 0 [m]
    direction: int = 2
    length: float = CAR
    kind: str = "Car"
    frames: np.ndarray = field(default_factory=lambda: FRAMES)
    lane: object = 5  # a number, or (frames,) per frame
    preceding: object = 0  # an id, or (frames,) per frame
    phase: float = 0.0


def write_recording(
    folder: Path,
    vehicles: list[Vehicle],
    *,
    number: str = "01",
    rate: float = RATE,
    dhw: str = "front",
) -> Path:
    """The three highD files of one recording; returns the tracks file.

    ``dhw`` is written as "front" (front to front), "gap" (the leader's rear to
    the front), "centre" (centre to centre) or "noise" (unrelated numbers).
    """
    folder.mkdir(parents=True, exist_ok=True)
    rows = {}
    for v in vehicles:
        front, speed, acc = motion(v.frames * RATE / rate, v.start, v.phase)
        rows[v.id] = pd.DataFrame(
            {
                "frame": v.frames,
                "front": front,
                "speed": speed,
                "acc": acc,
                "lane": np.broadcast_to(v.lane, v.frames.shape),
                "preceding": np.broadcast_to(v.preceding, v.frames.shape),
            }
        )
    by_id = {v.id: v for v in vehicles}
    blocks = []
    for v in vehicles:
        r = rows[v.id]
        d = -1.0 if v.direction == 1 else 1.0
        # The box's low-x edge: the rear on the lower lanes, the front on the upper.
        x = r["front"] - v.length if v.direction == 2 else -r["front"]
        block = pd.DataFrame(0.0, index=r.index, columns=TRACK_HEADER)
        block["frame"] = r["frame"]
        block["id"] = v.id
        block["x"] = x
        block["y"] = 10.0 if v.direction == 1 else 25.0
        block["width"] = v.length
        block["height"] = 2.0
        block["xVelocity"] = d * r["speed"]
        block["xAcceleration"] = d * r["acc"]
        block["precedingId"] = r["preceding"]
        block["laneId"] = r["lane"]
        block["dhw"] = _dhw(r, rows, by_id, v, dhw)
        blocks.append(block)
    tracks = pd.concat(blocks, ignore_index=True)
    for column in ("frame", "id", "precedingId", "laneId"):
        tracks[column] = tracks[column].astype(int)
    path = folder / f"{number}_tracks.csv"
    tracks.to_csv(path, index=False)
    meta = pd.DataFrame(0, index=range(len(vehicles)), columns=META_HEADER)
    meta["id"] = [v.id for v in vehicles]
    meta["width"] = [v.length for v in vehicles]
    meta["height"] = 2.0
    meta["class"] = [v.kind for v in vehicles]
    meta["drivingDirection"] = [v.direction for v in vehicles]
    meta.to_csv(folder / f"{number}_tracksMeta.csv", index=False)
    recording = pd.DataFrame(
        [[int(number), rate, 2, -1.0, "09.2017", "Tue", "08:38", 10.0]
         + [0] * 5 + ["8.51;12.59;16.43", "21.00;24.96;28.80"]],
        columns=RECORDING_HEADER,
    )  # fmt: skip
    recording.to_csv(folder / f"{number}_recordingMeta.csv", index=False)
    return path


def _dhw(rows, all_rows, by_id, vehicle: Vehicle, kind: str) -> np.ndarray:
    """The dhw column of one vehicle, 0 where it has no leader."""
    out = np.zeros(len(rows))
    for i, (frame, leader) in enumerate(
        zip(rows["frame"], rows["preceding"], strict=True)
    ):
        if leader == 0:
            continue
        at = all_rows[leader]
        front_l = float(at.loc[at["frame"] == frame, "front"].iloc[0])
        spacing = front_l - rows["front"].iloc[i]
        length_l = by_id[leader].length
        out[i] = {
            "front": spacing,
            "gap": spacing - length_l,
            "centre": spacing - 0.5 * length_l + 0.5 * vehicle.length,
            "noise": 3.0 + 40.0 * (i % 7),
        }[kind]
    return np.round(out, 2)  # highD writes centimetres


def couple(direction: int = 2, **follower) -> list[Vehicle]:
    """Leader 1 and follower 2 (30 m further back, same motion) in lane 5."""
    lane = 2 if direction == 1 else 5
    return [
        Vehicle(1, 100.0, direction, lane=lane),
        Vehicle(2, 70.0, direction, lane=lane, preceding=1, **follower),
    ]


def options(**kwargs) -> ExtractOptions:
    kwargs.setdefault("window", 4.0)
    kwargs.setdefault("test_fraction", 0.0)
    return ExtractOptions(**kwargs)


# ------------------------------------------------------------------ reading
def test_lower_lanes_front_bumper_speed_and_time(tmp_path: Path) -> None:
    tracks = write_recording(tmp_path, couple(2))
    table = read_highd(tmp_path)
    rows = table.frame[table.frame["vehicle"] == "2"]
    raw = pd.read_csv(tracks)
    raw = raw[raw["id"] == 2]
    np.testing.assert_allclose(rows["time"], FRAMES / 25.0)
    np.testing.assert_allclose(rows["position"], raw["x"] + raw["width"])
    np.testing.assert_allclose(rows["speed"], raw["xVelocity"])
    np.testing.assert_allclose(rows["acceleration"], raw["xAcceleration"])
    assert set(rows["length"]) == {CAR} and set(rows["leader"]) == {"1"}
    assert set(rows["lane"]) == {"5"} and set(table.frame["run"]) == {"01"}
    assert table.format == "highd" and table.road_frame is True
    assert set(table.frame.loc[table.frame["vehicle"] == "1", "leader"]) == {""}


def test_upper_lanes_are_turned_along_the_travel(tmp_path: Path) -> None:
    tracks = write_recording(tmp_path, couple(1))
    raw = pd.read_csv(tracks)
    assert (raw["xVelocity"] < 0).all()  # as highD writes the upper lanes
    table = read_highd(tracks)
    for vehicle, rows in table.frame.groupby("vehicle"):
        own = raw[raw["id"] == int(vehicle)]
        assert (np.diff(rows["position"]) > 0).all()
        assert (rows["speed"] > 0).all()
        np.testing.assert_allclose(rows["position"], -own["x"])  # the low-x edge
        np.testing.assert_allclose(rows["speed"], -own["xVelocity"])
        np.testing.assert_allclose(rows["acceleration"], -own["xAcceleration"])
    lead = table.frame[table.frame["vehicle"] == "1"]["position"].to_numpy()
    follow = table.frame[table.frame["vehicle"] == "2"]["position"].to_numpy()
    np.testing.assert_allclose(lead - follow, 30.0, atol=1e-9)  # leader ahead


@pytest.mark.parametrize("rate", [25.0, 30.0])
def test_time_is_frame_over_the_recordings_frame_rate(
    tmp_path: Path, rate: float
) -> None:
    write_recording(tmp_path, couple(2), rate=rate)
    table = read_highd(tmp_path)
    np.testing.assert_allclose(
        table.frame.loc[table.frame["vehicle"] == "1", "time"], FRAMES / rate
    )


@pytest.mark.parametrize(
    ("written", "reading"),
    [
        ("front", "front to front"),
        ("gap", "the gap"),
        ("centre", "centre to centre"),
    ],
)
def test_dhw_becomes_the_bumper_gap_whatever_it_joins(
    tmp_path: Path, written: str, reading: str
) -> None:
    # A truck leads, so the three readings differ by metres.
    vehicles = [
        Vehicle(1, 100.0, length=TRUCK, kind="Truck"),
        Vehicle(2, 70.0, preceding=1),
    ]
    write_recording(tmp_path, vehicles, dhw=written)
    table = read_highd(tmp_path)
    follow = table.frame[table.frame["vehicle"] == "2"]
    np.testing.assert_allclose(follow["gap"], 30.0 - TRUCK, atol=0.011)
    assert any(reading in note for note in table.notes)
    assert table.frame.loc[table.frame["vehicle"] == "1", "gap"].isna().all()


def test_dhw_that_fits_no_reading_leaves_no_gap(tmp_path: Path) -> None:
    write_recording(tmp_path, couple(2), dhw="noise")
    table = read_highd(tmp_path)
    assert table.frame["gap"].isna().all()
    assert any("matches no reading" in note for note in table.notes)


@pytest.mark.parametrize("kind", ["tracks", "tracksMeta", "recordingMeta"])
def test_a_missing_file_is_named_in_one_line(tmp_path: Path, kind: str) -> None:
    write_recording(tmp_path, couple(2), number="07")
    (tmp_path / f"07_{kind}.csv").unlink()
    others = sorted(tmp_path.iterdir())
    for source in (tmp_path, others[0]):
        with pytest.raises(DataError, match=f"07_{kind}.csv") as info:
            read_highd(source)
        assert "\n" not in str(info.value)
        assert "recording 07" in str(info.value)


def test_folder_with_two_recordings_gives_two_runs(tmp_path: Path) -> None:
    write_recording(tmp_path, couple(2), number="01")
    write_recording(tmp_path, couple(1), number="02")
    (tmp_path / "02_highway.png").write_bytes(b"")  # other files are ignored
    table = read_highd(tmp_path)
    assert table.runs == ["01", "02"] and table.n_vehicles == 4
    assert table.road_frame is False  # two recordings: two roads
    assert sum(note.startswith("recording 0") for note in table.notes) >= 2
    only = read_highd(tmp_path, recordings="2")
    assert only.runs == ["02"] and only.road_frame is True
    assert read_highd(tmp_path, recordings=[1, "02"]).runs == ["01", "02"]
    assert read_highd(tmp_path / "02_tracksMeta.csv").runs == ["02"]
    with pytest.raises(DataError, match="recording.s. 03 not in"):
        read_highd(tmp_path, recordings="1-3")
    write_recording(tmp_path, couple(2), number="03")
    (tmp_path / "03_recordingMeta.csv").unlink()  # incomplete, but not asked for
    assert read_highd(tmp_path, recordings="1,2").runs == ["01", "02"]
    with pytest.raises(DataError, match="recording 03 .* lacks 03_recordingMeta"):
        read_highd(tmp_path)


def test_directions_option_keeps_one_carriageway(tmp_path: Path) -> None:
    upper = [
        Vehicle(3, 100.0, 1, lane=2),
        Vehicle(4, 70.0, 1, lane=2, preceding=3),
    ]
    write_recording(tmp_path, couple(2) + upper)
    both = read_highd(tmp_path)
    assert both.n_vehicles == 4 and both.road_frame is False  # two carriageways
    for value, kept in (("upper", {"3", "4"}), (2, {"1", "2"}), ("1,2", None)):
        table = read_highd(tmp_path, directions=value)
        if kept is not None:
            assert set(table.frame["vehicle"]) == kept and table.road_frame is True
    with pytest.raises(DataError, match="'left' is not 1, 2"):
        read_highd(tmp_path, directions="left")


def test_follower_classes_keep_other_classes_as_leaders(tmp_path: Path) -> None:
    vehicles = [
        Vehicle(1, 100.0, length=TRUCK, kind="Truck"),
        Vehicle(2, 70.0, preceding=1),
        Vehicle(3, 40.0, length=TRUCK, kind="Truck", preceding=2),
    ]
    write_recording(tmp_path, vehicles)
    table = read_highd(tmp_path, follower_classes="car")
    leaders = table.frame.groupby("vehicle")["leader"].agg(set)
    assert leaders.to_dict() == {"1": {""}, "2": {"1"}, "3": {""}}
    assert table.n_vehicles == 3  # the trucks stay, as leaders
    with pytest.raises(DataError, match="no vehicle of class bus"):
        read_highd(tmp_path, follower_classes=["Car", "Bus"])


def test_not_highd_and_exid_layout_are_refused(tmp_path: Path) -> None:
    write_recording(tmp_path / "d", couple(2))
    other = tmp_path / "d" / "notes.csv"
    other.write_text("a,b\n1,2\n")
    with pytest.raises(DataError, match="not a highD file"):
        read_highd(other)
    with pytest.raises(DataError, match="no such file or folder"):
        read_highd(tmp_path / "absent")
    with pytest.raises(DataError, match="holds no highD recording"):
        read_highd(tmp_path)  # the files are one folder down
    exid = tmp_path / "d" / "01_tracks.csv"
    exid.write_text("recordingId,trackId,frame,xCenter,yCenter\n0,0,0,1.0,2.0\n")
    with pytest.raises(DataError, match="exiD/inD/rounD layout"):
        read_highd(exid)


def test_bad_cells_and_meta_are_named(tmp_path: Path) -> None:
    tracks = write_recording(tmp_path, couple(2))
    text = tracks.read_text().splitlines()
    cells = text[3].split(",")
    cells[TRACK_HEADER.index("xVelocity")] = "fast"
    text[3] = ",".join(cells)
    tracks.write_text("\n".join(text) + "\n")
    with pytest.raises(DataError, match="xVelocity holds 'fast' on line 4"):
        read_highd(tmp_path)
    write_recording(tmp_path, couple(2))
    meta = pd.read_csv(tmp_path / "01_tracksMeta.csv")
    meta.loc[0, "drivingDirection"] = 3
    meta.to_csv(tmp_path / "01_tracksMeta.csv", index=False)
    with pytest.raises(DataError, match="drivingDirection 3, not 1 or 2"):
        read_highd(tmp_path)
    write_recording(tmp_path, couple(2))
    meta = pd.read_csv(tmp_path / "01_tracksMeta.csv").iloc[:1]
    meta.to_csv(tmp_path / "01_tracksMeta.csv", index=False)
    with pytest.raises(DataError, match="vehicle.s. 2 of .* not in '01_tracksMeta"):
        read_highd(tmp_path)


@pytest.mark.parametrize(
    ("value", "match"), [("1-x", "not a number or a range"), ("3-1", "range")]
)
def test_bad_recording_selection(tmp_path: Path, value: str, match: str) -> None:
    write_recording(tmp_path, couple(2))
    with pytest.raises(DataError, match=match):
        read_highd(tmp_path, recordings=value)


# ------------------------------------------------------------ through extract
def test_planted_lane_change_cuts_the_pair(tmp_path: Path) -> None:
    # Leader and follower both move from lane 5 to lane 6 at frame CUT: the
    # leader stays the same, only the lane changes.
    lane = np.where(FRAMES < CUT, 5, 6)
    vehicles = [
        Vehicle(1, 100.0, lane=lane),
        Vehicle(2, 70.0, lane=lane, preceding=1),
    ]
    write_recording(tmp_path, vehicles)
    result = extract_pairs(read_highd(tmp_path), options())
    index = result.index
    assert list(index["lane"]) == ["5", "6"] and set(index["leader"]) == {"1"}
    assert list(index["t_start"]) == pytest.approx([1 / RATE, CUT / RATE])
    assert list(index["steps"]) == [100, 100]
    assert any("2 lane change(s)" in note for note in result.notes)


def test_leader_switch_cuts_the_pair(tmp_path: Path) -> None:
    # Vehicle 3 cuts in between at frame CUT: precedingId goes from 1 to 3.
    cutter = FRAMES[FRAMES >= CUT]
    vehicles = [
        Vehicle(1, 100.0),
        Vehicle(2, 70.0, preceding=np.where(FRAMES < CUT, 1, 3)),
        Vehicle(3, 85.0, frames=cutter, phase=0.3),
    ]
    write_recording(tmp_path, vehicles)
    result = extract_pairs(read_highd(tmp_path), options())
    index = result.index
    assert list(index["leader"]) == ["1", "3"]
    assert list(index["t_start"]) == pytest.approx([1 / RATE, CUT / RATE])
    # Without the cut, the second window would start at frame 101 (t = 4.04 s).
    assert 101 / RATE not in list(index["t_start"])


def test_small_recording_end_to_end(tmp_path: Path) -> None:
    # Lower lanes: 1 leads 2 (a car behind a truck); upper lanes: 3 leads 4.
    # 250 frames hold two 4 s windows per couple.
    vehicles = [
        Vehicle(1, 100.0, length=TRUCK, kind="Truck"),
        Vehicle(2, 70.0, preceding=1),
        Vehicle(3, 300.0, 1, lane=2, phase=1.0),
        Vehicle(4, 275.0, 1, lane=2, preceding=3, phase=1.0),
    ]
    write_recording(tmp_path, vehicles)
    assert formats.FORMATS["highd"] is read_highd
    table = read_trajectories(tmp_path, "highd", directions="lower,upper")
    result = extract_pairs(table, options(leader_length=CAR))
    pairs, index = result.pairs, result.index
    assert pairs.n_pairs == 4 and pairs.n_steps == 100
    assert result.dt == pytest.approx(1 / RATE)
    assert list(index["follower"]) == ["2", "2", "4", "4"]
    assert list(index["leader_length"]) == [TRUCK, TRUCK, CAR, CAR]
    assert result.dropped.empty
    spacing = (pairs.x_lead - pairs.x_follow).numpy()  # (T, N), leader rebased to L
    gap = spacing - CAR
    np.testing.assert_allclose(gap[:, :2], 30.0 - TRUCK, atol=1e-9)
    np.testing.assert_allclose(gap[:, 2:], 25.0 - CAR, atol=1e-9)
    assert (pairs.v_follow.numpy() > 0).all() and (pairs.v_lead.numpy() > 0).all()
    t = (np.arange(100) + 1) / RATE
    _, speed, acc = motion(np.arange(1, 101), 0.0)
    np.testing.assert_allclose(pairs.v_follow[:, 0].numpy(), speed, atol=1e-9)
    np.testing.assert_allclose(pairs.a_follow[:, 0].numpy(), acc, atol=1e-9)
    assert list(index["t_start"]) == pytest.approx([t[0], t[0] + 4.0] * 2)


def test_the_command_line_reads_a_recording(tmp_path: Path) -> None:
    """``torchcf data extract DIR --format highd`` with its options;
    an option of another format is refused in one line."""
    from torchcf.cli.data import main

    vehicles = [
        Vehicle(1, 100.0, length=TRUCK, kind="Truck"),
        Vehicle(2, 70.0, preceding=1),
        Vehicle(3, 300.0, 1, lane=2, phase=1.0),
        Vehicle(4, 275.0, 1, lane=2, preceding=3, phase=1.0),
    ]
    write_recording(tmp_path / "raw", vehicles)
    out = tmp_path / "pairs"
    args = ["extract", str(tmp_path / "raw"), "--format", "highd", "--out", str(out)]
    lower = ["--directions", "lower", "--window", "4", "--test-fraction", "0"]
    assert main([*args, *lower]) == 0
    index = pd.read_csv(out / "index.csv")
    assert set(index["follower"].astype(str)) == {"2"}
    assert main([*args, "--overwrite", "--frame-rate", "25"]) == 2
