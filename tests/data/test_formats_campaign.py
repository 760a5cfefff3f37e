"""OpenACC campaigns: vehicles as the columns name them, and whole folders.

Small ZalaZONE-style files written here, one per variant of the issue (numbering
from 2, a vehicle missing in the middle, extra columns, trailing commas in the
header block, a nested campaign folder), each with its known vehicles, couples
and spacings; then the real ZalaZONE dynamic-platform campaign under
``$TORCHCF_RAW/openacc-zalazone-dynamic`` when it is there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from torchcf.cli.data import main as data_main
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.openacc import read_openacc, read_openacc_metadata

N_STEPS = 12
TIME = 950.1 + 0.1 * np.arange(N_STEPS)  # [s], ZalaZONE's clock
LENGTH = 5.0  # [m], the reader's default vehicle length
FLEET = (
    "SMART_TARGET",
    "MAZDA_3",
    "TOYOTA_RAV4",
    "AUDI_E_TRON",
    "BMW_I3",
    "MERCEDES_GLE450",
    "JAGUAR_I_PACE",
    "TESLA_MODELX",
    "TESLA_MODELS",
    "AUDI_A4",
)


def speed(k: int) -> np.ndarray:
    """(T,) Speed{k} [m/s]: distinct per vehicle."""
    return 12.0 + 0.25 * k + 0.05 * np.arange(N_STEPS)


def spacing(k: int) -> np.ndarray:
    """(T,) IVS{k} [m]: distinct per vehicle and in time."""
    return 8.0 + k + 0.1 * np.sin(np.arange(N_STEPS) + k)


def odometer(values: np.ndarray) -> np.ndarray:
    steps = 0.5 * (values[1:] + values[:-1]) * np.diff(TIME)
    return np.concatenate(([0.0], np.cumsum(steps)))


def write_run(
    path: Path,
    vehicles: list[int],
    ivs: list[int],
    *,
    n_vehicles: int | None = None,
    distance: str = "S",
    extra: dict[str, object] | None = None,
    pad: bool = False,
) -> Path:
    """A ZalaZONE platoon file: CRLF, 5 metadata rows, header, data at 10 Hz.

    Per vehicle ``Speed, E, N, Lon, Lat, Alt`` (JRC's ZalaZONE order), then the
    ``IVS`` columns, then ``extra`` columns (name -> cells). Vehicle_order is
    :data:`FLEET` up to ``n_vehicles`` and ends in a comma, as ZalaZONE's does;
    ``pad`` also pads the other metadata rows and ends the header and data
    lines with commas.
    """
    n_vehicles = n_vehicles or max(vehicles)
    columns: dict[str, object] = {"Time": TIME}
    for k in vehicles:
        columns[f"Speed{k}"] = speed(k)
        for name in ("E", "N", "Lon", "Lat", "Alt"):
            columns[f"{name}{k}"] = 100.0 * k
    for k in ivs:
        columns[f"IVS{k}"] = spacing(k)
    columns.update(extra or {})
    tail = ",,,," if pad else ""
    meta = [
        "Date,8,10,2019" + tail,
        "Vehicle_order," + ",".join(FLEET[:n_vehicles]) + ",",
        f"Number_of_vehicles,{n_vehicles}" + tail,
        "ACC,1" + tail,
        f"Distance_setting,{distance}" + tail,
    ]
    cells = {
        name: np.broadcast_to(np.asarray(values, dtype=object), TIME.shape)
        for name, values in columns.items()
    }
    end = "," if pad else ""
    lines = [*meta, ",".join(columns) + end]
    for i in range(N_STEPS):
        lines.append(",".join(str(cells[name][i]) for name in columns) + end)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("ascii"))
    return path


def couples(table, run: str | None = None) -> set[tuple[str, str]]:
    """(leader, follower) couples of a table (one run, or all)."""
    frame = table.frame
    if run is not None:
        frame = frame[frame["run"] == run]
    linked = frame.loc[frame["leader"] != "", ["leader", "vehicle"]]
    return set(linked.drop_duplicates().itertuples(index=False, name=None))


def vehicle(table, k: int, run: str | None = None) -> pd.DataFrame:
    frame = table.frame
    rows = frame["vehicle"] == str(k)
    if run is not None:
        rows &= frame["run"] == run
    return frame[rows].sort_values("time").reset_index(drop=True)


def assert_chain(table, chain: list[int], run: str | None = None) -> None:
    """The chain's head on its own odometer; each follower IVS + length behind."""
    head = vehicle(table, chain[0], run)
    np.testing.assert_allclose(head["position"], odometer(speed(chain[0])))
    assert set(head["leader"]) == {""} and head["gap"].isna().all()
    for leader, follower in zip(chain, chain[1:], strict=False):
        lead, follow = vehicle(table, leader, run), vehicle(table, follower, run)
        np.testing.assert_array_equal(follow["gap"], spacing(leader))
        np.testing.assert_allclose(
            lead["position"] - follow["position"] - LENGTH, spacing(leader), atol=1e-9
        )
        np.testing.assert_array_equal(follow["speed"], speed(follower))


# ------------------------------------------------------------------ variants
def test_handling_course_numbered_from_two(tmp_path) -> None:
    """The issue's file: ``Time, Speed2, E2, ..., IVS2 ... IVS9`` (no vehicle 1)."""
    path = write_run(
        tmp_path / "handling_part1.csv", list(range(2, 11)), list(range(2, 10))
    )
    table = read_openacc(path)
    assert sorted(table.frame["vehicle"].unique(), key=int) == [
        str(k) for k in range(2, 11)
    ]
    assert couples(table) == {(str(k), str(k + 1)) for k in range(2, 10)}
    assert_chain(table, list(range(2, 11)))
    # every car here follows the (unrecorded) target car: ACC at setting S
    assert set(table.frame["mode"]) == {"ACC:S"}
    notes = "\n".join(table.notes)
    assert "vehicles 2=MAZDA_3, 3=TOYOTA_RAV4," in notes
    assert "the columns name vehicle(s) 2, 3, 4, 5, 6, 7, 8, 9, 10; none for 1" in notes


def test_vehicles_missing_in_the_middle(tmp_path) -> None:
    """ZalaZONE dynamic_part26's pattern: vehicles 1, 2, 5, 6, 7 of 9; IVS1, 5, 6."""
    table = read_openacc(
        write_run(tmp_path / "p26.csv", [1, 2, 5, 6, 7], [1, 5, 6], n_vehicles=9)
    )
    assert set(table.frame["vehicle"]) == {"1", "2", "5", "6", "7"}
    assert couples(table) == {("1", "2"), ("5", "6"), ("6", "7")}
    assert_chain(table, [1, 2])
    assert_chain(table, [5, 6, 7])  # no IVS2 (nor IVS4): a chain of its own
    assert (
        "run p26: no IVS2: vehicle 5 has no recorded gap to vehicle 2, so no "
        "leader; its chain is placed by its own odometer (another frame)"
    ) in table.notes


def test_ivs_links_to_the_next_vehicle_in_the_file(tmp_path) -> None:
    """Vehicle 3 absent: IVS2 is the spacing from 2 to 4; IVS3 links nothing."""
    table = read_openacc(
        write_run(tmp_path / "gap.csv", [1, 2, 4], [1, 2, 3], n_vehicles=4)
    )
    assert couples(table) == {("1", "2"), ("2", "4")}
    assert_chain(table, [1, 2, 4])
    notes = table.notes
    assert (
        "run gap: IVS2 taken as the spacing from vehicle 2 to vehicle 4, the next "
        "vehicle in the file (3 absent)"
    ) in notes
    assert "run gap: IVS3 not used: vehicle 3 is not in the file" in notes
    assert "run gap: couples (leader>follower) 1>2, 2>4" in notes


def test_extra_columns_change_nothing(tmp_path) -> None:
    plain = read_openacc(write_run(tmp_path / "a" / "f.csv", [1, 2, 3], [1, 2]))
    extra = {
        "Eff_distance1": 3.0,  # per-couple columns JRC documents
        "Rel_Speed2": 0.1,
        "U3": 1.0,  # per-vehicle, not used
        "VE1": 2.0,
        "Comment": "lap",  # unknown
        "Yaw2": 0.5,
    }
    table = read_openacc(
        write_run(tmp_path / "b" / "f.csv", [1, 2, 3], [1, 2], extra=extra)
    )
    pd.testing.assert_frame_equal(plain.frame, table.frame)
    assert "run f: columns not read: Comment, Yaw2" in table.notes


def test_trailing_commas_in_the_header_block(tmp_path) -> None:
    plain = read_openacc(write_run(tmp_path / "a" / "f.csv", [2, 3, 4], [2, 3]))
    padded_path = write_run(tmp_path / "b" / "f.csv", [2, 3, 4], [2, 3], pad=True)
    assert padded_path.read_text().splitlines()[5].endswith("IVS3,")
    padded = read_openacc(padded_path)
    pd.testing.assert_frame_equal(plain.frame, padded.frame)
    assert padded.notes[0].startswith("run f: vehicles 2=MAZDA_3, 3=TOYOTA_RAV4")
    assert couples(padded) == {("2", "3"), ("3", "4")}


def test_a_nested_campaign_folder_in_one_read(tmp_path) -> None:
    root = tmp_path / "campaign"
    write_run(
        root / "long_setting" / "dynamic_part2.csv", [1, 2, 3], [1, 2], distance="L"
    )
    write_run(root / "medium_setting" / "dynamic_part8.csv", [1, 2], [1], distance="M")
    # the same file name under another setting: a run of its own
    write_run(root / "short_setting" / "dynamic_part2.csv", [1, 2, 5], [1, 2])
    write_run(
        root / "handling" / "day2" / "handling_part1.csv",
        [2, 3, 4],
        [2, 3],
        distance="M",
    )
    (root / "Veh_specifications.csv").write_text("Vehicles,Max power (kW)\r\n")
    (root / "SOURCE.md").write_text("# not data\n")
    table = read_trajectories(root, "openacc")
    runs = [
        "handling/day2/handling_part1",
        "long_setting/dynamic_part2",
        "medium_setting/dynamic_part8",
        "short_setting/dynamic_part2",
    ]
    assert table.runs == runs and table.road_frame is False
    assert table.n_vehicles == 3 + 2 + 3 + 3
    expected = {
        runs[0]: {("2", "3"), ("3", "4")},
        runs[1]: {("1", "2"), ("2", "3")},
        runs[2]: {("1", "2")},
        runs[3]: {("1", "2"), ("2", "5")},
    }
    for run, pairs in expected.items():
        assert couples(table, run) == pairs, run
    assert_chain(table, [2, 3, 4], runs[0])
    assert_chain(table, [1, 2, 5], runs[3])
    # the distance setting travels with every follower's rows
    modes = table.frame[table.frame["leader"] != ""].groupby("run")["mode"].unique()
    assert {run: list(m) for run, m in modes.items()} == {
        runs[0]: ["ACC:M"],
        runs[1]: ["ACC:L"],
        runs[2]: ["ACC:M"],
        runs[3]: ["ACC:S"],
    }
    assert table.notes[-1] == (
        "skipped 1 csv file(s) that are not platoon files (first cell not "
        "'Date'): Veh_specifications.csv"
    )


def test_metadata_joins_runs_and_vehicles_to_makes(tmp_path) -> None:
    root = tmp_path / "campaign"
    write_run(root / "long_setting" / "p2.csv", [1, 2, 3], [1, 2], distance="L")
    write_run(root / "short_setting" / "p26.csv", [1, 2, 5], [1], n_vehicles=9)
    meta = read_openacc_metadata(root)
    assert meta[["run", "vehicle", "name", "distance_setting", "leader"]].to_dict(
        "records"
    ) == [
        {"run": "long_setting/p2", "vehicle": "1", "name": "SMART_TARGET",
         "distance_setting": "L", "leader": ""},
        {"run": "long_setting/p2", "vehicle": "2", "name": "MAZDA_3",
         "distance_setting": "L", "leader": "1"},
        {"run": "long_setting/p2", "vehicle": "3", "name": "TOYOTA_RAV4",
         "distance_setting": "L", "leader": "2"},
        {"run": "short_setting/p26", "vehicle": "1", "name": "SMART_TARGET",
         "distance_setting": "S", "leader": ""},
        {"run": "short_setting/p26", "vehicle": "2", "name": "MAZDA_3",
         "distance_setting": "S", "leader": "1"},
        {"run": "short_setting/p26", "vehicle": "5", "name": "BMW_I3",
         "distance_setting": "S", "leader": ""},
    ]  # fmt: skip
    assert set(meta["date"]) == {"8-10-2019"} and meta["names_match_count"].all()
    # the same ids as the table's: a join on (run, vehicle) is exact
    table = read_openacc(root)
    keys = table.frame[["run", "vehicle"]].drop_duplicates()
    assert len(keys.merge(meta, on=["run", "vehicle"])) == len(meta) == len(keys)


def test_extract_command_reads_a_campaign_folder(tmp_path, capsys) -> None:
    root = tmp_path / "campaign"
    write_run(
        root / "long_setting" / "dynamic_part2.csv", [1, 2, 3], [1, 2], distance="L"
    )
    write_run(root / "short_setting" / "dynamic_part2.csv", [2, 3, 4], [2, 3])
    out = tmp_path / "pairs"
    code = data_main(
        ["extract", str(root), "--format", "openacc", "--out", str(out),
         "--window", "0.8", "--test-fraction", "0"]
    )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "from 6 vehicles in 2 run(s)" in printed
    index = pd.read_csv(out / "index.csv", dtype=str, keep_default_na=False)
    # 12 steps = one whole window of 8 per couple, 2 couples per run
    got = set(
        zip(
            index["run"], index["leader"], index["follower"], index["mode"], strict=True
        )
    )
    assert got == {
        ("long_setting/dynamic_part2", "1", "2", "ACC:L"),
        ("long_setting/dynamic_part2", "2", "3", "ACC:L"),
        ("short_setting/dynamic_part2", "2", "3", "ACC:S"),
        ("short_setting/dynamic_part2", "3", "4", "ACC:S"),
    }


# ----------------------------------------------------------------- real data
#: SOURCE.md's files with their row counts, and the vehicles their columns name.
ZALAZONE = {
    "long_setting/dynamic_part16": (1200, 7),
    "long_setting/dynamic_part18": (2499, 10),
    "long_setting/dynamic_part19": (1448, 11),
    "long_setting/dynamic_part2": (5148, 6),
    "long_setting/dynamic_part25": (1399, 9),
    "medium_setting/dynamic_part8": (4448, 5),
    "mixed/dynamic_part5": (2650, 10),
    "mixed/dynamic_part6": (1199, 9),
    "mixed/dynamic_part7": (990, 6),
    "short_setting/dynamic_part1": (5497, 6),  # Vehicle_order names 11
    "short_setting/dynamic_part10": (7578, 4),
    "short_setting/dynamic_part12": (1299, 11),
    "short_setting/dynamic_part14": (999, 10),
    "short_setting/dynamic_part20": (1497, 10),
    "short_setting/dynamic_part21": (1249, 10),
    "short_setting/dynamic_part22": (329, 9),
    "short_setting/dynamic_part23": (729, 8),
    "short_setting/dynamic_part26": (699, 5),  # vehicles 1, 2, 5, 6, 7 of 9
    "short_setting/dynamic_part4": (2249, 11),
}


@pytest.fixture(scope="module")
def zalazone_table(zalazone):
    return read_openacc(zalazone)


def test_zalazone_campaign_reads_every_file(zalazone_table) -> None:
    frame = zalazone_table.frame
    assert zalazone_table.runs == sorted(ZALAZONE)
    sizes = frame.groupby("run")["vehicle"].nunique().to_dict()
    assert sizes == {run: n for run, (_, n) in ZALAZONE.items()}
    rows = frame.groupby(["run", "vehicle"]).size()
    for (run, _), size in rows.items():
        assert size == ZALAZONE[run][0], run
    assert zalazone_table.n_vehicles == 157
    # every file is one chain, but part26, whose vehicle 5 has no IVS to 2
    links = frame.loc[frame["leader"] != "", ["run", "vehicle"]].drop_duplicates()
    assert len(links) == 157 - 19 - 1
    assert couples(zalazone_table, "short_setting/dynamic_part26") == {
        ("1", "2"), ("5", "6"), ("6", "7"),
    }  # fmt: skip
    settings = frame[frame["leader"] != ""].groupby("run")["mode"].unique()
    for run, modes in settings.items():
        expected = {"long": "L", "medium": "M"}.get(run.split("_")[0], "S")
        assert list(modes) == [f"ACC:{expected}"], run


def test_zalazone_ivs_is_the_antenna_chord_of_each_couple(zalazone) -> None:
    """Each couple the reader links has chord(E, N) - IVS constant (to 1e-12 m
    in these files): the IVS measures between those two cars; IVS1 against
    vehicle 3, a wrong link, wanders by 3-74 m."""
    table = read_openacc(zalazone / "short_setting")  # part26's gap included
    checked = 0
    for path in sorted((zalazone / "short_setting").glob("*.csv")):
        raw = pd.read_csv(path, skiprows=5)
        for leader, follower in couples(table, f"{path.stem}"):
            a, b = int(leader), int(follower)
            chord = np.hypot(raw[f"E{a}"] - raw[f"E{b}"], raw[f"N{a}"] - raw[f"N{b}"])
            offset = (chord - raw[f"IVS{a}"]).dropna()
            assert 2.0 < offset.median() < 6.0, (path.stem, a, b)
            assert offset.max() - offset.min() < 0.01, (path.stem, a, b)
            checked += 1
    assert checked == 10 + 3 + 10 + 9 + 9 + 9 + 8 + 7 + 3 + 5


def test_zalazone_metadata(zalazone) -> None:
    meta = read_openacc_metadata(zalazone)
    assert len(meta) == 157 and meta["run"].nunique() == 19
    assert set(meta["date"]) == {"8-10-2019"} and set(meta["acc"]) == {"1"}
    shares = meta.drop_duplicates("run")["distance_setting"].value_counts()
    assert shares.to_dict() == {"S": 13, "L": 5, "M": 1}
    mismatched = meta.loc[~meta["names_match_count"], "run"].unique().tolist()
    assert mismatched == ["short_setting/dynamic_part1"]
    part26 = meta[meta["run"] == "short_setting/dynamic_part26"]
    assert part26["name"].tolist() == [
        "SMART_TARGET", "BMW_I3", "TESLA_MODELX", "TESLA_MODEL3", "TESLA_MODELS",
    ]  # fmt: skip


def test_zalazone_extracts_end_to_end(zalazone_table) -> None:
    result = extract_pairs(zalazone_table, ExtractOptions())
    summary = result.summary
    assert summary["runs"] == 19 and summary["vehicles"] == 157
    assert summary["spans"] == 137
    # 19 windows whose IVS-placed followers step up to 6.8 m/s off their
    # Doppler speed (470 pairs without the speed-mismatch filter)
    assert summary["candidate_windows"] == 591 and summary["pairs"] == 451
    assert summary["windows_dropped"] == {
        "missing": 113, "jump": 8, "speed_mismatch": 19,
    }  # fmt: skip
    assert summary["spans_short"] == 8
    assert result.index["mode"].value_counts().to_dict() == {
        "ACC:S": 254, "ACC:L": 156, "ACC:M": 41,
    }  # fmt: skip
