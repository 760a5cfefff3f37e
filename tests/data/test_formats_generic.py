"""Generic long CSV reader: column maps, units, folders and errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.cli.test_bad_input import one_error_line
from tests.data.test_data_cli import extract_args, write_log
from tests.runs import exit_code
from torchcf.cli.data import main as data_main
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.generic import (
    ACCELERATION_UNITS,
    FRAME_UNIT,
    LENGTH_UNITS,
    SPEED_UNITS,
    TIME_UNITS,
    TableUnits,
    columns_text,
    parse_column_map,
    read_csv_table,
    time_factor,
    unit_factors,
)
from torchcf.data.pairset import DataError

MAP = "vehicle=ID,time=t,position=x,speed=v"


def write(path: Path, frame: pd.DataFrame, sep: str = ",") -> Path:
    frame.to_csv(path, index=False, sep=sep)
    return path


def two_cars() -> pd.DataFrame:
    """Car 7 ahead of car 8, two steps each, rows out of order, own names."""
    return pd.DataFrame(
        {
            "ID": ["8", "7", "8", "7"],
            "t": [1.0, 1.0, 0.0, 0.0],
            "x": [10.0, 40.0, 9.0, 38.0],
            "v": [36.0, 72.0, 36.0, 72.0],
            "ahead": ["7", "", "7", ""],
            "extra": ["a", "b", "c", "d"],
        }
    )


# ------------------------------------------------------------- column maps
def test_parse_column_map() -> None:
    assert parse_column_map(" vehicle = ID , time=t,position=x,speed=v,") == {
        "vehicle": "ID",
        "time": "t",
        "position": "x",
        "speed": "v",
    }


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("vehicle=ID,velocity=v,pos=x", "'velocity', 'pos'"),
        ("vehicle=ID,time", "'time' is not canonical=source"),
        ("vehicle=,time=t", "'vehicle=' is not canonical=source"),
        ("time=t,time=s", "names 'time' twice"),
    ],
)
def test_parse_column_map_rejects(text: str, match: str) -> None:
    with pytest.raises(DataError, match=match):
        parse_column_map(text)


# --------------------------------------------------------------- reading
def test_read_with_map_and_km_per_hour(tmp_path: Path) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    table = read_csv_table(
        path, columns=MAP + ",leader=ahead", units=TableUnits(speed_unit="km/h")
    )
    frame = table.frame
    assert table.format == "csv" and table.road_frame is None
    assert frame["run"].unique().tolist() == ["cars"]
    # Sorted by run, vehicle, time whatever the file's order.
    assert frame["vehicle"].tolist() == ["7", "7", "8", "8"]
    assert frame["time"].tolist() == [0.0, 1.0, 0.0, 1.0]
    assert frame["speed"].to_numpy() == pytest.approx([20.0, 20.0, 10.0, 10.0])
    assert frame["position"].tolist() == [38.0, 40.0, 9.0, 10.0]
    assert frame["leader"].tolist() == ["", "", "7", "7"]
    assert frame["acceleration"].isna().all() and (frame["lane"] == "").all()


def test_dict_map_and_dispatch(tmp_path: Path) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    mapping = {"vehicle": "ID", "time": "t", "speed": "v"}
    table = read_trajectories(path, "csv", columns=mapping, speed_unit="mph")
    assert table.frame["speed"].iloc[0] == pytest.approx(72.0 * 0.44704)
    with pytest.raises(DataError, match="unknown canonical column.*'velocity'"):
        read_csv_table(path, columns={"vehicle": "ID", "velocity": "v"})


def test_feet_default_speed_and_acceleration_units(tmp_path: Path) -> None:
    frame = pd.DataFrame(
        {
            "vehicle": [1, 1],
            "time": [0, 1],
            "position": [100.0, 130.0],
            "speed": [30.0, 30.0],
            "acceleration": [2.0, 2.0],
            "length": [15.0, 15.0],
            "gap": [50.0, 51.0],
        }
    )
    table = read_csv_table(
        write(tmp_path / "f.csv", frame), units=TableUnits(length_unit="ft")
    )
    out = table.frame
    assert out["position"].tolist() == [100.0 * 0.3048, 130.0 * 0.3048]
    assert (out["speed"] == 30.0 * 0.3048).all()  # ft/s by default
    assert (out["acceleration"] == 2.0 * 0.3048).all()  # ft/s^2 by default
    assert (out["length"] == 15.0 * 0.3048).all()
    assert out["gap"].tolist() == [50.0 * 0.3048, 51.0 * 0.3048]


def test_km_lengths_default_to_km_per_hour(tmp_path: Path) -> None:
    frame = pd.DataFrame(
        {"vehicle": [1], "time": [0.0], "position": [1.5], "speed": [90.0]}
    )
    table = read_csv_table(
        write(tmp_path / "k.csv", frame), units=TableUnits(length_unit="km")
    )
    assert table.frame["position"].iloc[0] == pytest.approx(1500.0)
    assert table.frame["speed"].iloc[0] == pytest.approx(25.0)


@pytest.mark.parametrize(("unit", "seconds"), [("s", 12.0), ("ms", 0.012), ("ds", 1.2)])
def test_time_units(tmp_path: Path, unit: str, seconds: float) -> None:
    frame = pd.DataFrame({"vehicle": ["a"], "time": [12]})
    table = read_csv_table(
        write(tmp_path / "t.csv", frame), units=TableUnits(time_unit=unit)
    )
    assert table.frame["time"].iloc[0] == pytest.approx(seconds)


# ------------------------------------------------------- frame-based time
def test_frame_numbers_at_25_hz(tmp_path: Path) -> None:
    frame = pd.DataFrame({"vehicle": ["a"] * 4, "frame": [0, 1, 25, 50]})
    path = write(tmp_path / "video.csv", frame)
    table = read_csv_table(
        path, columns="time=frame", units=TableUnits(time_unit="frame", frame_rate=25.0)
    )
    assert table.frame["time"].tolist() == pytest.approx([0.0, 0.04, 1.0, 2.0])
    assert time_factor(FRAME_UNIT, 30.0) == pytest.approx(1.0 / 30.0)
    assert unit_factors(time_unit="frame", frame_rate=10.0)["time"] == 0.1
    # ds is the frame unit at 10 Hz
    ds = read_csv_table(path, columns="time=frame", units=TableUnits(time_unit="ds"))
    assert ds.frame["time"].tolist() == pytest.approx([0.0, 0.1, 2.5, 5.0])


@pytest.mark.parametrize(
    ("unit", "rate", "match"),
    [
        ("frame", None, "time unit 'frame' needs a frame rate"),
        ("frame", 0.0, "frame rate must be finite and > 0"),
        ("frame", float("nan"), "frame rate must be finite and > 0"),
        ("s", 25.0, "frame rate is only used with time unit 'frame', not 's'"),
        ("fr", None, "unknown time unit 'fr'; known: s, ms, ds, frame"),
    ],
)
def test_frame_rate_goes_with_the_frame_unit(tmp_path, unit, rate, match) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    with pytest.raises(DataError, match=match):
        read_csv_table(
            path, columns=MAP, units=TableUnits(time_unit=unit, frame_rate=rate)
        )


def frame_log(path: Path) -> Path:
    """The command-line test's log with time as frame numbers at 10 Hz."""
    write_log(path)
    log = pd.read_csv(path)
    log["t"] = np.rint(log["t"] * 10.0).astype(int)
    log.to_csv(path, index=False)
    return path


def test_cli_frame_time(tmp_path, capsys) -> None:
    log = frame_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    more = ["--time-unit", "frame", "--frame-rate", "10"]
    assert data_main([*extract_args(log, out), *more]) == 0
    assert "12 pairs (9 train, 3 test) of 200 steps at dt = 0.1 s" in (
        capsys.readouterr().out
    )
    record = json.loads((out / "extract.json").read_text())
    assert record["raw"]["time_unit"] == "frame"
    assert record["raw"]["frame_rate"] == 10.0


@pytest.mark.parametrize(
    ("more", "needles"),
    [
        (["--time-unit", "frame"], ["time_unit", "needs a frame rate"]),
        (["--frame-rate", "10"], ["frame rate is only used with time unit"]),
        (["--time-unit", "frame", "--frame-rate", "-5"], ["--frame-rate", "> 0"]),
    ],
)
def test_cli_frame_errors_are_one_line(tmp_path, capsys, more, needles) -> None:
    log = frame_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    assert exit_code(data_main, [*extract_args(log, out), *more]) == 2
    one_error_line(capsys.readouterr().err, *needles)
    assert not out.exists()


def test_unit_tables_are_consistent() -> None:
    assert LENGTH_UNITS["ft"] == SPEED_UNITS["ft/s"] == ACCELERATION_UNITS["ft/s^2"]
    assert SPEED_UNITS["km/h"] * 3.6 == pytest.approx(1.0)
    assert TIME_UNITS["ds"] == 0.1


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"length_unit": "yd"}, "unknown length unit 'yd'; known: m, ft, km"),
        ({"speed_unit": "kph"}, "unknown speed unit 'kph'"),
        ({"acceleration_unit": "g"}, "unknown acceleration unit 'g'"),
        ({"time_unit": "min"}, "unknown time unit 'min'"),
    ],
)
def test_unknown_units_raise(tmp_path: Path, options: dict, match: str) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    with pytest.raises(DataError, match=match):
        read_csv_table(path, columns=MAP, units=TableUnits(**options))


def test_missing_mapped_column_names_it(tmp_path: Path) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    with pytest.raises(DataError) as info:
        read_csv_table(path, columns="vehicle=ID,time=t,speed=vel")
    message = str(info.value)
    assert "column 'vel' (mapped to speed) not in" in message
    assert "cars.csv" in message and "it has: ID, t, x, v, ahead, extra" in message


def test_long_headers_are_listed_in_part(tmp_path: Path) -> None:
    frame = pd.DataFrame({f"c{i}": [0] for i in range(20)})
    path = write(tmp_path / "wide.csv", frame)
    with pytest.raises(DataError, match=r"it has: c0, .*, c11, \.\.\. \(8 more\)"):
        read_csv_table(path, columns="vehicle=c0,time=zz")


def test_required_columns_must_resolve(tmp_path: Path) -> None:
    path = write(tmp_path / "cars.csv", two_cars())
    with pytest.raises(DataError, match="no column for 'vehicle'.*vehicle=COLUMN"):
        read_csv_table(path)


def test_text_in_numeric_column_names_file_and_row(tmp_path: Path) -> None:
    frame = two_cars()
    frame["x"] = frame["x"].astype(object)
    frame.loc[2, "x"] = "n/a?"
    path = write(tmp_path / "cars.csv", frame)
    with pytest.raises(DataError, match=r"cars\.csv.*'position' holds 'n/a\?'.*row 3"):
        read_csv_table(path, columns=MAP)


def test_ids_stay_text_and_separator(tmp_path: Path) -> None:
    frame = pd.DataFrame(
        {"vehicle": ["007", "007"], "time": [0.0, 0.1], "lane": ["01", "01"]}
    )
    table = read_csv_table(write(tmp_path / "s.csv", frame, sep=";"), sep=";")
    assert table.frame["vehicle"].tolist() == ["007", "007"]
    assert table.frame["lane"].tolist() == ["01", "01"]


def test_folder_reads_every_csv_run_per_file(tmp_path: Path) -> None:
    write(tmp_path / "b.csv", two_cars())
    write(tmp_path / "a.csv", two_cars().iloc[:2])
    (tmp_path / "notes.txt").write_text("not read")
    table = read_csv_table(tmp_path, columns=MAP)
    assert table.runs == ["a", "b"]
    assert len(table.frame) == 6 and table.n_vehicles == 4


def test_mapped_run_is_kept_in_a_file_prefixed_in_a_folder(tmp_path: Path) -> None:
    frame = two_cars().assign(trip=["r1", "r2", "r1", "r2"])
    path = write(tmp_path / "cars.csv", frame)
    assert read_csv_table(path, columns=MAP + ",run=trip").runs == ["r1", "r2"]
    folder_runs = read_csv_table(tmp_path, columns=MAP + ",run=trip").runs
    assert folder_runs == ["cars:r1", "cars:r2"]


def test_missing_source_and_empty_folder(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no such file or folder"):
        read_csv_table(tmp_path / "none.csv")
    with pytest.raises(DataError, match=r"holds no \*\.csv file"):
        read_csv_table(tmp_path)
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DataError, match=r"empty\.csv' is empty"):
        read_csv_table(tmp_path / "empty.csv")


def test_empty_vehicle_cell_raises(tmp_path: Path) -> None:
    frame = pd.DataFrame({"vehicle": ["1", None], "time": [0.0, 0.1]})
    path = write(tmp_path / "e.csv", frame)
    with pytest.raises(DataError, match=r"e\.csv.*'vehicle' has 1 empty"):
        read_csv_table(path)


@pytest.mark.parametrize("fmt", ["csv", "pairs", "punzo", "highd", "ngsim"])
def test_a_binary_file_is_refused_in_one_short_line(tmp_path, capsys, fmt) -> None:
    """A file of NUL bytes is 'not text', whatever the format; the message
    never quotes the file (a CSV parser reads it whole as one header name)."""
    path = tmp_path / "01_tracks.csv"
    path.write_bytes(b"\x00" * 300_000)
    if fmt == "highd":  # a recording is three files; the tracks are read first
        for meta in ("01_tracksMeta.csv", "01_recordingMeta.csv"):
            (tmp_path / meta).write_bytes(b"\x00" * 1000)
    out = tmp_path / "out"
    argv = ["extract", str(path), "--format", fmt, "--out", str(out)]
    if fmt == "csv":
        argv += ["--columns", MAP]
    assert data_main(argv) == 2
    line = one_error_line(capsys.readouterr().err, "not text (NUL bytes)")
    assert len(line) < 300
    assert not out.exists()


def test_column_names_are_cut_in_messages() -> None:
    text = columns_text(["a" * 5000, "speed"])
    assert len(text) < 60 and text.endswith("..., speed")
