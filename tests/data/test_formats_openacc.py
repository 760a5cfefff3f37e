"""read_openacc on small files written here, and on the real samples when present."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from torchcf.data.formats import read_trajectories
from torchcf.data.formats.openacc import read_openacc
from torchcf.data.pairset import DataError

TIME = 1000.0 + 0.1 * np.arange(8)  # [s], the common clock does not start at 0
SPEED = {
    1: np.array([20.0, 20.5, 21.0, 21.0, 20.0, 19.0, 19.5, 20.0]),
    2: np.array([19.0, 19.5, 20.0, 20.5, 20.5, 20.0, 19.5, 19.0]),
    3: np.array([18.0, 18.0, 18.5, 19.0, 19.5, 20.0, 20.0, 19.5]),
}
IVS = {
    1: np.array([25.0, 25.2, 25.3, 25.3, 25.2, 25.0, 24.8, 24.9]),
    2: np.array([30.0, 29.8, 29.6, 29.5, 29.5, 29.6, 29.8, 30.1]),
}


def _metadata(names: list[str], pad: int = 0, acc: str = "1") -> list[str]:
    rows = [
        ["Date", "30", "9", "2020"],
        ["Vehicle_order", *names],
        ["Number_of_vehicles", str(len(names))],
        ["ACC", acc],
        ["Distance_setting", "shortest"],
    ]
    return [",".join(row + [""] * max(0, pad - len(row))) for row in rows]


def write_platoon(
    path: Path,
    columns: dict[str, object] | None = None,
    *,
    names: tuple[str, ...] = ("BMW", "Hyundai", "Ford"),
    pad: int = 0,
    trailing: bool = False,
    meta_rows: int = 5,
    acc: str = "1",
) -> Path:
    """A platoon CSV as JRC writes it: CRLF, 5 metadata rows, header, data.

    ``columns`` maps a header name to its cells (array or constant); ``pad``
    pads every metadata row with trailing commas to that many cells,
    ``trailing`` ends the header and data lines with a comma, ``meta_rows``
    keeps only the first metadata rows, ``acc`` is the ACC field.
    """
    if columns is None:
        columns = default_columns()
    header = list(columns)
    cells = {
        name: np.broadcast_to(np.asarray(values, dtype=object), TIME.shape)
        for name, values in columns.items()
    }
    end = "," if trailing else ""
    lines = [*_metadata(list(names), pad, acc)[:meta_rows], ",".join(header) + end]
    for i in range(TIME.size):
        lines.append(",".join(_cell(cells[name][i]) for name in header) + end)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("ascii"))
    return path


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "" if np.isnan(value) else repr(value)
    return str(value)


def default_columns() -> dict[str, object]:
    """Three vehicles, JRC's column order (per vehicle, then IVS, then Driver)."""
    columns: dict[str, object] = {"Time": TIME}
    for k in (1, 2, 3):
        columns[f"Speed{k}"] = SPEED[k]
        columns[f"Lat{k}"] = 0.7994
        columns[f"E{k}"] = 100.0 * k
    columns["IVS1"] = IVS[1]
    columns["IVS2"] = IVS[2]
    columns["Driver1"] = "Human"
    columns["Driver2"] = "ACC"
    columns["Driver3"] = "ACC"
    return columns


def _vehicle(table, k: int, run: str | None = None) -> pd.DataFrame:
    frame = table.frame
    rows = frame["vehicle"] == str(k)
    if run is not None:
        rows &= frame["run"] == run
    return frame[rows].sort_values("time").reset_index(drop=True)


def _odometer(time: np.ndarray, speed: np.ndarray) -> np.ndarray:
    steps = 0.5 * (speed[1:] + speed[:-1]) * np.diff(time)
    return np.concatenate(([0.0], np.cumsum(steps)))


def test_positions_follow_the_chain_and_gaps_are_the_ivs(tmp_path) -> None:
    table = read_openacc(write_platoon(tmp_path / "part14_1.csv"))
    assert table.format == "openacc" and table.road_frame is True
    assert table.runs == ["part14_1"] and table.n_vehicles == 3
    x = {k: _vehicle(table, k)["position"].to_numpy() for k in (1, 2, 3)}
    np.testing.assert_allclose(x[1], _odometer(TIME, SPEED[1]), rtol=0, atol=1e-12)
    assert x[1][0] == 0.0
    for k in (1, 2):
        np.testing.assert_array_equal(x[k + 1], x[k] - 5.0 - IVS[k])
        np.testing.assert_allclose(x[k] - x[k + 1] - 5.0, IVS[k], atol=1e-12)
        follower = _vehicle(table, k + 1)
        np.testing.assert_array_equal(follower["gap"], IVS[k])
        assert set(follower["leader"]) == {str(k)}
    first = _vehicle(table, 1)
    assert set(first["leader"]) == {""} and first["gap"].isna().all()
    for k in (1, 2, 3):
        rows = _vehicle(table, k)
        np.testing.assert_array_equal(rows["time"], TIME)
        np.testing.assert_array_equal(rows["speed"], SPEED[k])
        assert rows["acceleration"].isna().all()
        assert set(rows["lane"]) == {""} and set(rows["length"]) == {5.0}
    assert list(_vehicle(table, 1)["mode"].unique()) == ["Human"]
    # an ACC mode carries the run's distance setting
    assert list(_vehicle(table, 3)["mode"].unique()) == ["ACC:shortest"]
    assert table.notes[0].startswith(
        "run part14_1: vehicles 1=BMW, 2=Hyundai, 3=Ford; 8 rows every 0.1 s"
    )


def test_length_changes_no_spacing(tmp_path) -> None:
    path = write_platoon(tmp_path / "a.csv")
    short, long = read_openacc(path), read_openacc(path, vehicle_length=4.2)
    for k in (1, 2):
        x_lead = _vehicle(long, k)["position"].to_numpy()
        x_follow = _vehicle(long, k + 1)["position"].to_numpy()
        np.testing.assert_allclose(x_lead - x_follow - 4.2, IVS[k], atol=1e-12)
    np.testing.assert_array_equal(
        _vehicle(short, 1)["position"], _vehicle(long, 1)["position"]
    )
    assert set(long.frame["length"]) == {4.2}


def test_trailing_commas_and_column_order_do_not_matter(tmp_path) -> None:
    plain = read_openacc(write_platoon(tmp_path / "a" / "f.csv"))
    padded = read_openacc(write_platoon(tmp_path / "b" / "f.csv", pad=26))
    ended = read_openacc(write_platoon(tmp_path / "d" / "f.csv", trailing=True))
    short = read_openacc(write_platoon(tmp_path / "e" / "f.csv", meta_rows=4))
    reordered = dict(reversed(list(default_columns().items())))
    shuffled = read_openacc(write_platoon(tmp_path / "c" / "f.csv", reordered))
    for other in (padded, ended):
        pd.testing.assert_frame_equal(plain.frame, other.frame)
    # without Distance_setting the ACC mode has no setting; all else alike
    pd.testing.assert_frame_equal(
        plain.frame.drop(columns="mode"), short.frame.drop(columns="mode")
    )
    assert set(_vehicle(short, 3)["mode"]) == {"ACC"}
    assert short.notes[0].endswith("ACC 1, distance setting blank")
    pd.testing.assert_frame_equal(plain.sorted().frame, shuffled.sorted().frame)
    assert "\r\n" in (tmp_path / "a" / "f.csv").read_bytes().decode()


def test_missing_driver_column_takes_the_acc_field(tmp_path) -> None:
    columns = default_columns()
    del columns["Driver1"], columns["Driver3"]
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    assert set(_vehicle(table, 1)["mode"]) == {""}  # the first car: unknown
    assert set(_vehicle(table, 2)["mode"]) == {"ACC:shortest"}  # Driver2
    assert set(_vehicle(table, 3)["mode"]) == {"ACC:shortest"}  # ACC 1
    assert (
        "run f: no Driver column for vehicle(s) 1, 3: mode from the ACC field "
        "('', 'ACC:shortest')" in table.notes
    )
    # ACC 0: all by hand; ACC 2 (mixed): unknown; Driver columns still win
    manual = read_openacc(write_platoon(tmp_path / "m.csv", columns, acc="0"))
    assert set(manual.frame["mode"]) == {"Human", "ACC:shortest"}
    assert set(_vehicle(manual, 3)["mode"]) == {"Human"}
    mixed = read_openacc(write_platoon(tmp_path / "x.csv", columns, acc="2"))
    assert set(_vehicle(mixed, 3)["mode"]) == {""}


def test_missing_follower_speed_is_nan(tmp_path) -> None:
    columns = default_columns()
    del columns["Speed3"]
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    assert _vehicle(table, 3)["speed"].isna().all()
    assert np.isfinite(_vehicle(table, 3)["position"]).all()
    assert "run f: no Speed column for vehicle(s) 3: speed NaN" in table.notes


def test_missing_ivs_starts_a_chain_of_its_own(tmp_path) -> None:
    columns = default_columns()
    del columns["IVS2"]
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    third = _vehicle(table, 3)
    assert (third["leader"] == "").all() and third["gap"].isna().all()
    np.testing.assert_allclose(third["position"], _odometer(TIME, SPEED[3]))
    assert _vehicle(table, 2)["leader"].eq("1").all()
    assert any("no IVS2: vehicle 3 has no recorded gap" in n for n in table.notes)


def test_vehicle_without_speed_or_link_is_left_out(tmp_path) -> None:
    columns = default_columns()
    del columns["IVS2"], columns["Speed3"]  # Lat3, E3, Driver3 remain
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    assert table.n_vehicles == 2
    assert (
        "run f: vehicle(s) 3 left out: no Speed column in their chain, so no "
        "position" in table.notes
    )


def test_vehicle_named_by_no_column_is_absent(tmp_path) -> None:
    columns = {k: v for k, v in default_columns().items() if not k.endswith("3")}
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    assert table.n_vehicles == 2 and set(table.frame["vehicle"]) == {"1", "2"}
    # IVS2 measures to a car the file does not record: it links nothing
    assert "run f: IVS2 not used: no vehicle after 2 in the file" in table.notes
    assert any("columns name vehicle(s) 1, 2; none for 3" in n for n in table.notes)


def test_leader_without_speed_is_placed_ahead_of_the_anchor(tmp_path) -> None:
    columns = default_columns()
    del columns["Speed1"]  # vehicle 1 keeps Lat1, E1, Driver1
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    x = {k: _vehicle(table, k)["position"].to_numpy() for k in (1, 2, 3)}
    np.testing.assert_allclose(x[2], _odometer(TIME, SPEED[2]), atol=1e-12)
    np.testing.assert_allclose(x[1] - x[2] - 5.0, IVS[1], atol=1e-12)
    np.testing.assert_allclose(x[2] - x[3] - 5.0, IVS[2], atol=1e-12)
    assert _vehicle(table, 1)["speed"].isna().all()
    assert _vehicle(table, 2)["leader"].eq("1").all()


def test_missing_time_or_every_speed_names_the_file(tmp_path) -> None:
    columns = default_columns()
    del columns["Time"]
    path = write_platoon(tmp_path / "broken.csv", columns)
    with pytest.raises(DataError, match="broken.csv' lacks the column 'Time'"):
        read_openacc(path)
    columns = {k: v for k, v in default_columns().items() if "Speed" not in k}
    path = write_platoon(tmp_path / "slow.csv", columns)
    with pytest.raises(DataError, match="slow.csv' has no Speed column"):
        read_openacc(path)


def test_nan_speed_leaves_holes_not_a_poisoned_tail(tmp_path) -> None:
    columns = default_columns()
    speed = SPEED[1].copy()
    speed[[2, 3]] = np.nan
    ivs = IVS[2].copy()
    ivs[6] = np.nan
    columns["Speed1"], columns["IVS2"] = speed, ivs
    table = read_openacc(write_platoon(tmp_path / "f.csv", columns))
    x1 = _vehicle(table, 1)["position"].to_numpy()
    assert np.flatnonzero(np.isnan(x1)).tolist() == [2, 3]
    finite = np.isfinite(speed)
    # the hole is bridged by one trapezoid between its finite neighbours
    np.testing.assert_allclose(x1[finite], _odometer(TIME[finite], speed[finite]))
    x3 = _vehicle(table, 3)["position"].to_numpy()
    assert np.flatnonzero(np.isnan(x3)).tolist() == [2, 3, 6]
    assert "run f: Speed1 NaN at 2 row(s)" in table.notes
    assert "run f: position of vehicle 3 NaN at 3 row(s)" in table.notes


def test_folder_reads_every_platoon_file_and_skips_the_rest(tmp_path) -> None:
    write_platoon(tmp_path / "Ispra" / "part1.csv")
    two = {k: v for k, v in default_columns().items() if not k.endswith("3")}
    del two["IVS2"]
    write_platoon(tmp_path / "Casale" / "deep" / "part4.csv", two, names=("A", "B"))
    (tmp_path / "Ispra" / "Veh_specifications.csv").write_text(
        "Vehicles,Max power (kW)\r\nBMW,100\r\n"
    )
    (tmp_path / "Ispra" / "notes.txt").write_text("Date,not a csv\r\n")
    table = read_trajectories(tmp_path, "openacc")
    assert table.runs == ["Casale/deep/part4", "Ispra/part1"]
    assert table.n_vehicles == 5
    assert "run Casale/deep/part4: vehicles 1=A, 2=B; 8 rows" in "\n".join(table.notes)
    assert table.notes[-1] == (
        "skipped 1 csv file(s) that are not platoon files (first cell not 'Date'): "
        "Ispra/Veh_specifications.csv"
    )


def test_not_an_openacc_file(tmp_path) -> None:
    spec = tmp_path / "Veh_specifications.csv"
    spec.write_text("Vehicles,Max power (kW)\r\nBMW,100\r\n")
    with pytest.raises(DataError, match="not an OpenACC file: '.*Veh_spec"):
        read_openacc(spec)
    odd = tmp_path / "odd.csv"
    odd.write_text("Date,1,2,2020\r\nTime,Speed1\r\n1.0,2.0\r\n")
    with pytest.raises(DataError, match="not an OpenACC file: .*Number_of_vehicles"):
        read_openacc(odd)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="no OpenACC platoon file"):
        read_openacc(empty)
    with pytest.raises(DataError, match="no such file or folder"):
        read_openacc(tmp_path / "nowhere")


def test_header_and_cell_errors(tmp_path) -> None:
    columns = default_columns()
    columns["speed2"] = 1.0  # names are matched ignoring case
    with pytest.raises(DataError, match="a.csv' has the column 'speed2' twice"):
        read_openacc(write_platoon(tmp_path / "a.csv", columns))
    columns = default_columns()
    speed = SPEED[2].astype(object)
    speed[4] = "fast"
    columns["Speed2"] = speed
    with pytest.raises(
        DataError, match=r"b.csv': column 'Speed2' holds 'fast' at row 11"
    ):
        read_openacc(write_platoon(tmp_path / "b.csv", columns))
    columns = default_columns()
    columns["Time"] = TIME[::-1]
    with pytest.raises(DataError, match="Time does not increase at row 8"):
        read_openacc(write_platoon(tmp_path / "c.csv", columns))
    with pytest.raises(DataError, match="vehicle_length"):
        read_openacc(write_platoon(tmp_path / "d.csv"), vehicle_length=0.0)


# -- the real samples ---------------------------------------------------------

ROWS = {
    "Vicolungo": 1455,
    "Casale": 1151,
    "Ispra_JRC_low_speed": 1016,
    "Cherasco": 1448,
}


@pytest.fixture(scope="module")
def real_table():
    """The four OpenACC sample files under ``$TORCHCF_RAW/openacc``."""
    root = os.environ.get("TORCHCF_RAW")
    if not root or not (Path(root) / "openacc").is_dir():
        pytest.skip("TORCHCF_RAW is not set or holds no openacc/: no real samples")
    return read_openacc(Path(root) / "openacc")


def test_real_samples(real_table) -> None:
    frame = real_table.frame
    assert len(real_table.runs) == 4 and real_table.n_vehicles == 12
    followers = frame.loc[frame["leader"] != "", ["run", "vehicle"]]
    assert len(followers.drop_duplicates()) == 8
    sizes = frame.groupby(["run", "vehicle"]).size()
    for (run, _), size in sizes.items():
        assert size == ROWS[run.split("/")[0]], run
    speed = frame["speed"].to_numpy()
    assert np.isfinite(speed).all() and speed.min() >= 0.0 and speed.max() <= 45.0
    assert np.isfinite(frame["position"]).all()
    skipped = real_table.notes[-1]
    assert skipped.startswith("skipped 4 csv file(s)") and "Veh_spec" in skipped


def test_real_spacing_is_the_ivs(real_table) -> None:
    frame = real_table.frame
    couples = 0
    for run in real_table.runs:
        for k in range(1, 6):
            lead = _vehicle(real_table, k, run)
            follow = _vehicle(real_table, k + 1, run)
            if follow.empty:
                break
            spacing = lead["position"] - follow["position"] - 5.0
            np.testing.assert_allclose(spacing, follow["gap"], rtol=0, atol=1e-9)
            couples += 1
    assert couples == 8
    assert set(frame["mode"]) == {"", "ACC:min", "ACC:shortest", "Human"}
