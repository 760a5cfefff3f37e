"""Pair-wide tables (``--format pairs``): ULTra-AV names, leader lengths, errors.

Every table is written here in ULTra-AV's layout with a known answer: the
motions of ``tests/data/test_extract.py`` (leader speed a sine around 15 m/s, the
follower repeating it 1 s later, 20 m further back), written as vehicle-centre
positions of a 4.8 m leader and a 4.2 m follower, so the bumper-to-bumper gap is
``Pos_LV - Pos_FAV - 4.5`` and the leader length torchcf derives is 4.5 m.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.cli.test_bad_input import one_error_line
from tests.data.test_extract import leader_motion
from tests.runs import exit_code
from torchcf.cli.data import main as data_main
from torchcf.config import load_split, validate_config
from torchcf.config.raw import RawSource
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories, reader_options
from torchcf.data.formats.generic import TableUnits
from torchcf.data.formats.pairs import PAIR_COLUMNS, ULTRA_AV, read_pairs
from torchcf.data.pairset import DataError

DT = 0.1
L_LEAD, L_FOLLOW = 4.8, 4.2
HALF_SUM = (L_LEAD + L_FOLLOW) / 2  # what x_lead - x_follow - gap is for centres


def trajectory(pair: int, n: int = 400, phase: float = 0.0) -> pd.DataFrame:
    """One ULTra-AV trajectory of n steps at 10 Hz, t = 0.1, 0.2, ... [s]."""
    t = np.round(DT * np.arange(1, n + 1), 10)
    x_lead, v_lead, a_lead = leader_motion(t, phase)  # front bumpers
    x_follow, v_follow, a_follow = leader_motion(t - 1.0, phase)
    x_follow = x_follow - 20.0
    pos_lv, pos_fav = x_lead - L_LEAD / 2, x_follow - L_FOLLOW / 2  # centres
    return pd.DataFrame(
        {
            "Trajectory_ID": pair,
            "Time_Index": t,
            "ID_LV": -1,
            "Type_LV": 0,
            "Pos_LV": pos_lv,
            "Speed_LV": v_lead,
            "Acc_LV": a_lead,
            "ID_FAV": 7,
            "Pos_FAV": pos_fav,
            "Speed_FAV": v_follow,
            "Acc_FAV": a_follow,
            "Spatial_Gap": x_lead - L_LEAD - x_follow,
            "Spatial_Headway": pos_lv - pos_fav,
            "Speed_Diff": v_lead - v_follow,
        }
    )


def ultra_av(path: Path, n_pairs: int = 3, **changes) -> Path:
    """A file of ``n_pairs`` trajectories; ``changes`` rename or replace columns."""
    frame = pd.concat(
        [trajectory(k, phase=0.7 * k) for k in range(n_pairs)], ignore_index=True
    )
    for name, value in changes.items():
        if isinstance(value, str):
            frame = frame.rename(columns={name: value})
        else:
            frame[name] = value(frame) if callable(value) else value
    frame.to_csv(path, index=False)
    return path


def vehicle(table, run: str, role: str) -> pd.DataFrame:
    frame = table.frame
    return frame[(frame["run"] == run) & (frame["vehicle"] == f"{run}:{role}")]


# ------------------------------------------------------------- the default map
def test_ultra_av_names_become_a_leader_and_a_follower(tmp_path) -> None:
    table = read_pairs(ultra_av(tmp_path / "u.csv"))
    assert table.format == "pairs" and table.road_frame is None
    assert table.runs == ["0", "1", "2"] and table.n_vehicles == 6
    raw = trajectory(1, phase=0.7)
    lead, follow = vehicle(table, "1", "leader"), vehicle(table, "1", "follower")
    np.testing.assert_allclose(lead["time"], raw["Time_Index"], atol=1e-12)
    np.testing.assert_allclose(lead["position"], raw["Pos_LV"], atol=1e-9)
    np.testing.assert_allclose(lead["speed"], raw["Speed_LV"], atol=1e-12)
    np.testing.assert_allclose(lead["acceleration"], raw["Acc_LV"], atol=1e-12)
    np.testing.assert_allclose(follow["position"], raw["Pos_FAV"], atol=1e-9)
    np.testing.assert_allclose(follow["speed"], raw["Speed_FAV"], atol=1e-12)
    np.testing.assert_allclose(follow["gap"], raw["Spatial_Gap"], atol=1e-9)
    assert set(follow["leader"]) == {"1:leader"} and set(lead["leader"]) == {""}
    assert lead["gap"].isna().all() and follow["length"].isna().all()
    # centres: x_lead - x_follow - gap is (l_lead + l_follow) / 2, one per pair
    np.testing.assert_allclose(lead["length"], HALF_SUM, atol=1e-9)
    assert "x_lead - x_follow - gap: median 4.50 m" in table.notes[0]


def test_extracted_spacing_is_the_recorded_gap(tmp_path) -> None:
    table = read_trajectories(ultra_av(tmp_path / "u.csv"), "pairs")
    options = ExtractOptions(window=20.0, test_fraction=0.0)
    extraction = extract_pairs(table, options)
    pairs = extraction.pairs
    assert pairs.n_pairs == 6 and extraction.dt == pytest.approx(DT)
    assert pairs.leader_length == pytest.approx(HALF_SUM)
    spacing = pairs.x_lead - pairs.x_follow - pairs.leader_length  # (T, N)
    # the follower is 20 m and 1 s behind: gap = x_l(t) - 4.8 - x_l(t - 1) + 20
    t = extraction.index["t_start"].to_numpy()[None, :] + DT * np.arange(200)[:, None]
    x_now, _, _ = leader_motion(t, 0.0)
    x_before, _, _ = leader_motion(t - 1.0, 0.0)
    first = (extraction.index["run"] == "0").to_numpy()
    expected = x_now - L_LEAD - x_before + 20.0
    np.testing.assert_allclose(
        spacing.numpy()[:, first], expected[:, first], rtol=0, atol=1e-9
    )
    assert set(extraction.index["follower"]) == {f"{k}:follower" for k in range(3)}


def test_space_gap_is_read_too(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", Spatial_Gap="Space_Gap")
    table = read_pairs(path)
    assert table.frame["gap"].notna().sum() == 3 * 400
    np.testing.assert_allclose(vehicle(table, "0", "leader")["length"], HALF_SUM)


def test_a_user_item_replaces_one_default(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", Pos_LV="xl", Time_Index="frame_time")
    table = read_pairs(path, columns="x_lead=xl,time=frame_time")
    reference = read_pairs(ultra_av(tmp_path / "ref.csv"))
    pd.testing.assert_frame_equal(table.frame, reference.frame)
    with pytest.raises(DataError, match="no column for 'x_lead'.*x_lead=COLUMN"):
        read_pairs(path, columns="time=frame_time")


def test_canonical_names_need_no_map(tmp_path) -> None:
    names = {v[0]: k for k, v in ULTRA_AV.items() if len(v) > 1}
    path = ultra_av(tmp_path / "u.csv", **names)
    assert read_pairs(path).n_vehicles == 6


def test_mapped_run_groups_trajectories(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", ID_FAV=lambda f: f["Trajectory_ID"] % 2)
    table = read_pairs(path, columns="run=ID_FAV")
    assert table.runs == ["0", "1"]
    assert sorted(set(table.frame["vehicle"][table.frame["run"] == "0"])) == [
        "0:follower",
        "0:leader",
        "2:follower",
        "2:leader",
    ]
    options = ExtractOptions(window=20.0, split_by="run", test_fraction=0.3)
    extraction = extract_pairs(table, options)
    assert extraction.index.groupby("run")["split"].nunique().max() == 1


def test_folder_prefixes_runs_by_file(tmp_path) -> None:
    folder = tmp_path / "collection"
    folder.mkdir()
    ultra_av(folder / "waymo.csv", n_pairs=2)
    ultra_av(folder / "cats.csv", n_pairs=1)
    (folder / "README.md").write_text("not read")
    table = read_pairs(folder)
    assert table.runs == ["cats:0", "waymo:0", "waymo:1"]
    assert set(table.frame["vehicle"]) >= {"0:leader", "1:follower"}
    assert [note.split(":")[0] for note in table.notes] == ["cats.csv", "waymo.csv"]


# ------------------------------------------------------------- leader length
def test_front_bumper_positions_with_a_length_column(tmp_path) -> None:
    path = ultra_av(
        tmp_path / "u.csv",
        Pos_LV=lambda f: f["Pos_LV"] + L_LEAD / 2,  # back to front bumpers
        Pos_FAV=lambda f: f["Pos_FAV"] + L_FOLLOW / 2,
        L=L_LEAD,
    )
    table = read_pairs(path, columns="leader_length=L")
    np.testing.assert_allclose(vehicle(table, "2", "leader")["length"], L_LEAD)
    assert "the leader_length column" in table.notes[0]


def test_length_column_disagreeing_with_gap_and_positions(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", L=L_LEAD)  # centres: 4.5 m, not 4.8 m
    with pytest.raises(DataError) as info:
        read_pairs(path, columns="leader_length=L", length_tolerance=0.2)
    message = str(info.value)
    assert "pair '0'" in message and "u.csv" in message
    assert "leader_length is 4.80 m but x_lead - x_follow - gap is 4.50 m" in message
    assert "leave leader_length unmapped" in message and "\n" not in message
    # within the default tolerance of 0.5 m the column is used
    table = read_pairs(path, columns="leader_length=L")
    np.testing.assert_allclose(vehicle(table, "0", "leader")["length"], L_LEAD)


def test_length_column_must_be_constant_per_pair(tmp_path) -> None:
    path = ultra_av(
        tmp_path / "u.csv", L=lambda f: 4.0 + 2.0 * (f["Time_Index"] > 20.0)
    )
    with pytest.raises(DataError) as info:
        read_pairs(path, columns="leader_length=L")
    assert "pair '0'" in str(info.value)
    assert "leader_length, the leader length, ranges over 4.00..6.00 m" in str(
        info.value
    )
    assert "does not change within a trajectory" in str(info.value)


def test_a_gap_jump_is_a_length_inconsistency(tmp_path) -> None:
    def jump(frame: pd.DataFrame) -> pd.Series:
        gap = frame["Spatial_Gap"].copy()
        gap[(frame["Trajectory_ID"] == 1) & (frame["Time_Index"] > 30.0)] += 2.0
        return gap

    path = ultra_av(tmp_path / "u.csv", Spatial_Gap=jump)
    with pytest.raises(DataError) as info:
        read_pairs(path)
    message = str(info.value)
    assert message.startswith("pair '1' of ")
    assert "x_lead - x_follow - gap, the leader length, ranges over 2.50..4.50 m" in (
        message
    )
    assert "--length-tolerance" in message
    table = read_pairs(path, length_tolerance=2.5)  # a looser tolerance reads it
    assert table.n_vehicles == 6


def test_a_headway_mapped_as_gap_is_refused(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv")
    with pytest.raises(DataError, match="not a bumper-to-bumper gap.*headway"):
        read_pairs(path, columns="gap=Spatial_Headway")


def test_without_gap_or_length_the_default_length_applies(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", n_pairs=2)
    frame = pd.read_csv(path).drop(columns=["Spatial_Gap"])
    frame.to_csv(path, index=False)
    table = read_pairs(path)
    assert table.frame["length"].isna().all() and table.frame["gap"].isna().all()
    assert "default length" in table.notes[0]
    options = ExtractOptions(window=20.0, test_fraction=0.0, default_length=4.5)
    pairs = extract_pairs(table, options).pairs
    assert pairs.leader_length == 4.5


# ------------------------------------------------------------ units and time
def test_feet_and_frame_numbers(tmp_path) -> None:
    foot = 0.3048
    path = ultra_av(
        tmp_path / "u.csv",
        n_pairs=1,
        Time_Index=lambda f: np.rint(f["Time_Index"] * 10.0),  # frames at 10 Hz
        Pos_LV=lambda f: f["Pos_LV"] / foot,
        Pos_FAV=lambda f: f["Pos_FAV"] / foot,
        Spatial_Gap=lambda f: f["Spatial_Gap"] / foot,
        Speed_LV=lambda f: f["Speed_LV"] / foot,
        Speed_FAV=lambda f: f["Speed_FAV"] / foot,
        Acc_LV=lambda f: f["Acc_LV"] / foot,
        Acc_FAV=lambda f: f["Acc_FAV"] / foot,
    )
    table = read_pairs(
        path, units=TableUnits(length_unit="ft", time_unit="frame", frame_rate=10.0)
    )
    reference = read_pairs(ultra_av(tmp_path / "ref.csv", n_pairs=1))
    for column in ("time", "position", "speed", "acceleration", "gap", "length"):
        np.testing.assert_allclose(
            table.frame[column], reference.frame[column], rtol=1e-12, atol=1e-9
        )
    with pytest.raises(DataError, match="time unit 'frame' needs a frame rate"):
        read_pairs(path, units=TableUnits(time_unit="frame"))


# ------------------------------------------------------------------ errors
def test_bad_inputs(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv", n_pairs=1)
    with pytest.raises(DataError, match=r"unknown canonical column\(s\) 'vehicle'"):
        read_pairs(path, columns="vehicle=ID_FAV")
    with pytest.raises(DataError, match="column 'nope' \\(mapped to gap\\) not in"):
        read_pairs(path, columns={"gap": "nope"})
    with pytest.raises(DataError, match="length_tolerance must be finite and > 0"):
        read_pairs(path, length_tolerance=0.0)
    frame = pd.read_csv(path)
    frame["Pos_FAV"] = frame["Pos_FAV"].astype(object)
    frame.loc[4, "Pos_FAV"] = "lost"
    frame.to_csv(tmp_path / "text.csv", index=False)
    with pytest.raises(DataError, match="'x_follow' holds 'lost' at data row 5"):
        read_pairs(tmp_path / "text.csv")
    frame = pd.read_csv(path).astype({"Trajectory_ID": object})
    frame.loc[2, "Trajectory_ID"] = None
    frame.to_csv(tmp_path / "noid.csv", index=False)
    with pytest.raises(DataError, match="1 row\\(s\\) without a pair id.*row 3"):
        read_pairs(tmp_path / "noid.csv")


def test_reader_options_and_config(tmp_path) -> None:
    assert set(reader_options("pairs")) >= {"columns", "frame_rate", "time_unit"}
    raw = RawSource(
        source=str(tmp_path),
        format="pairs",
        columns={"pair": "ID"},
        time_unit="frame",
        frame_rate=25.0,
        length_tolerance=1.0,
    )
    options = raw.reader_options()
    assert options["columns"] == {"pair": "ID"} and options["frame_rate"] == 25.0
    assert options["length_tolerance"] == 1.0 and "vehicle_length" not in options
    assert set(PAIR_COLUMNS) == set(ULTRA_AV)


def test_config_raw_section_reads_pairs(tmp_path) -> None:
    path = ultra_av(tmp_path / "u.csv")
    raw = {"source": str(path), "format": "pairs", "window": 20, "split_by": "couple"}
    cfg = validate_config({"data": {"raw": raw}, "models": ["idm"]})
    train, test = load_split(cfg.data)
    assert train.n_pairs == 4 and test is not None and test.n_pairs == 2
    assert train.leader_length == pytest.approx(HALF_SUM)


# --------------------------------------------------------------- command line
def test_cli_extracts_pairs(tmp_path, capsys) -> None:
    path = ultra_av(tmp_path / "u.csv")
    out = tmp_path / "out"
    args = ["extract", str(path), "--format", "pairs", "--window", "20"]
    assert data_main([*args, "--split-by", "couple", "--out", str(out)]) == 0
    assert "6 pairs (4 train, 2 test) of 200 steps" in capsys.readouterr().out
    index = pd.read_csv(out / "index.csv", keep_default_na=False)
    assert index["leader_length"].to_numpy() == pytest.approx(HALF_SUM)


@pytest.mark.parametrize(
    ("more", "needles"),
    [
        (["--columns", "leader_length=ID_FAV"], ["leader_length is 7.00 m"]),
        (["--columns", "x_lead=Spatial_Headway,gap=nope"], ["'nope'", "gap"]),
        (["--columns", "vehicle=ID_FAV"], ["unknown canonical", "'vehicle'"]),
        (["--time-unit", "frame"], ["time unit 'frame' needs a frame rate"]),
        (["--frame-rate", "25"], ["frame rate is only used with time unit 'frame'"]),
        (["--vehicle-length", "4"], ["vehicle_length", "format='openacc'"]),
        (["--length-tolerance", "-1"], ["--length-tolerance", ">= 0"]),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys, more, needles):
    path = ultra_av(tmp_path / "u.csv", n_pairs=2)
    args = ["extract", str(path), "--format", "pairs", "--out", str(tmp_path / "o")]
    assert exit_code(data_main, [*args, *more]) == 2
    one_error_line(capsys.readouterr().err, *needles)
    assert not (tmp_path / "o").exists()
