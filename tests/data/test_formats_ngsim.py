"""NGSIM reader and writer: layouts, units, periods, ids, leaders, round trips."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from torchcf.data.formats import read_trajectories
from torchcf.data.formats.ngsim import (
    ARTERIAL_COLUMNS,
    FREEWAY_COLUMNS,
    read_ngsim,
    write_ngsim,
)
from torchcf.data.pairset import DataError, PairSet

FT = 0.3048
PEACHTREE = "ngsim-peachtree-fragment/peachtree_dotexport_first5000rows.csv"
EPOCH = 1_113_433_000_000  # an I-80-like Global_Time offset [ms]
#: Table column -> PairSet series prefix.
SERIES_OF = (("position", "x"), ("speed", "v"), ("acceleration", "a"))


def row(
    vehicle: int,
    frame: int,
    *,
    total: int = 100,
    offset: int = EPOCH,
    y: float = 0.0,
    length: float = 15.0,
    vel: float = 30.0,
    acc: float = 0.0,
    lane: int = 1,
    preceding: int = 0,
    headway: float = 0.0,
) -> dict[str, float]:
    """One record of the freeway layout (feet), unused columns 0."""
    record = dict.fromkeys(FREEWAY_COLUMNS, 0.0)
    record.update(
        Vehicle_ID=vehicle,
        Frame_ID=frame,
        Total_Frames=total,
        Global_Time=offset + 100 * frame,
        Local_Y=y,
        v_Length=length,
        v_Vel=vel,
        v_Acc=acc,
        Lane_ID=lane,
        Preceding=preceding,
        Space_Headway=headway,
    )
    return record


def write_txt(path: Path, records: list[dict[str, float]]) -> Path:
    """Write records as an original-layout text file (no header, spaces)."""
    # Runs of spaces and a leading one, as in the files' fixed-width columns.
    lines = [" " + "  ".join(_cell(r[c]) for c in FREEWAY_COLUMNS) for r in records]
    path.write_text("\n".join(lines) + "\n")
    return path


def _cell(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


def platoon(n_frames: int = 5) -> list[dict[str, float]]:
    """Vehicle 2 leads vehicle 1 in lane 3, 50 ft apart front to front."""
    records = []
    for k in range(1, n_frames + 1):
        records.append(row(2, k, y=100.0 + 3 * k, length=16.0, vel=30.0, lane=3))
        follower = row(1, k, y=50.0 + 3 * k, vel=30.5, acc=-1.5, lane=3)
        records.append(follower | {"Preceding": 2, "Space_Headway": 50.0})
    return records


def by_vehicle(table, vehicle: str, run: str | None = None) -> pd.DataFrame:
    frame = table.frame
    rows = frame[frame["vehicle"] == vehicle]
    return rows if run is None else rows[rows["run"] == run]


# ------------------------------------------------------------------ layouts
def test_feet_convert_to_si(tmp_path: Path) -> None:
    table = read_ngsim(write_txt(tmp_path / "trajectories-0400-0415.txt", platoon()))
    assert table.format == "ngsim" and table.road_frame is True
    follower = by_vehicle(table, "1")
    assert follower["time"].tolist() == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])
    assert follower["position"].iloc[0] == pytest.approx(53.0 * FT, rel=1e-15)
    assert (follower["speed"] == 30.5 * FT).all()
    assert (follower["acceleration"] == -1.5 * FT).all()
    assert (follower["length"] == 15.0 * FT).all()
    assert (follower["leader"] == "2").all() and (follower["lane"] == "3").all()
    # Gap: front-to-front 50 ft minus the leader's 16 ft.
    assert follower["gap"].to_numpy() == pytest.approx(34.0 * FT, rel=1e-14)
    leader = by_vehicle(table, "2")
    assert (leader["leader"] == "").all() and leader["gap"].isna().all()
    assert table.runs == [f"trajectories-0400-0415:{EPOCH}"]


def test_dispatch_by_format_name(tmp_path: Path) -> None:
    path = write_txt(tmp_path / "a.txt", platoon())
    assert read_trajectories(path, "ngsim").n_vehicles == 2


def test_sentinel_becomes_nan_and_is_noted(tmp_path: Path) -> None:
    records = platoon()
    records[3]["v_Vel"] = 9999.99  # vehicle 1, frame 2
    records[5]["Space_Headway"] = 9999.99  # vehicle 1, frame 3
    table = read_ngsim(write_txt(tmp_path / "s.txt", records))
    follower = by_vehicle(table, "1")
    speed, gap = follower["speed"].to_numpy(), follower["gap"].to_numpy()
    assert np.isnan(speed[1]) and np.isfinite(np.delete(speed, 1)).all()
    assert np.isnan(gap[2]) and np.isfinite(np.delete(gap, 2)).all()
    note = [n for n in table.notes if "9999.99" in n]
    assert len(note) == 1 and "v_Vel (1 rows)" in note[0]
    assert "Space_Headway (1 rows)" in note[0]


def test_unsorted_rows_come_out_sorted(tmp_path: Path) -> None:
    records = platoon(6)
    rng = np.random.default_rng(3)
    shuffled = [records[i] for i in rng.permutation(len(records))]
    table = read_ngsim(write_txt(tmp_path / "u.txt", shuffled))
    frame = table.frame
    assert frame["vehicle"].tolist() == ["1"] * 6 + ["2"] * 6
    assert np.all(np.diff(frame["time"].to_numpy()[:6]) > 0)
    assert np.all(np.diff(frame["position"].to_numpy()[6:]) > 0)


def test_reused_ids_in_two_periods_become_two_runs(tmp_path: Path) -> None:
    first = platoon(4)
    second = [
        row(2, 10 + k, total=50, offset=EPOCH + 11_700, y=float(k), length=20.0)
        for k in range(3)
    ]
    table = read_ngsim(write_txt(tmp_path / "p.txt", first + second))
    assert table.runs == [f"p:{EPOCH}", f"p:{EPOCH + 11_700}"]
    vehicle_2 = by_vehicle(table, "2").groupby("run").size()
    assert vehicle_2.to_dict() == {f"p:{EPOCH}": 4, f"p:{EPOCH + 11_700}": 3}
    assert table.n_vehicles == 3
    assert any("2 recording period(s)" in n for n in table.notes)
    assert any("reused across periods" in n and ": 2" in n for n in table.notes)


def test_ids_reused_within_one_period_split_by_total_frames(tmp_path: Path) -> None:
    # Id 7 is two vehicles in one period: frames 1-3 (Total_Frames 30) and
    # frames 8-9 (Total_Frames 40). Vehicle 5 follows whichever is present.
    records = [row(7, k, total=30, y=100.0 + k, length=14.0) for k in (1, 2, 3)]
    records += [row(7, k, total=40, y=200.0 + k, length=18.0) for k in (8, 9)]
    records += [
        row(5, k, y=50.0 + k, preceding=7, headway=60.0) for k in (1, 2, 3, 8, 9, 10)
    ]
    table = read_ngsim(write_txt(tmp_path / "w.txt", records))
    assert set(table.frame["vehicle"]) == {"5", "7#30", "7#40"}
    follower = by_vehicle(table, "5")
    assert follower["leader"].tolist() == ["7#30"] * 3 + ["7#40"] * 3
    gaps = follower["gap"].to_numpy()
    assert gaps[:3] == pytest.approx(46.0 * FT)
    assert gaps[3:5] == pytest.approx(42.0 * FT)
    assert np.isnan(gaps[5])  # frame 10: no row of 7#40, the nearest
    assert any(
        "split as ID#Total_Frames" in n and "id 7 (30, 40)" in n for n in table.notes
    )


def test_absent_leader_and_zero_headway_give_nan_gaps(tmp_path: Path) -> None:
    records = [row(1, k, y=10.0 + k, preceding=99, headway=40.0) for k in (1, 2)]
    records += [row(3, k, y=30.0 + k, preceding=1, headway=0.0) for k in (1, 2)]
    table = read_ngsim(write_txt(tmp_path / "a.txt", records))
    assert table.frame["gap"].isna().all()
    assert (by_vehicle(table, "1")["leader"] == "99").all()
    assert any(
        "1 leader(s) referenced but absent" in n and "ids 99" in n for n in table.notes
    )
    assert any(
        "2 row(s) name a leader but have no Space_Headway" in n for n in table.notes
    )


def test_csv_export_header_matched_case_insensitively(tmp_path: Path) -> None:
    frame = pd.DataFrame(platoon())
    frame = frame.rename(columns={"v_Length": "v_length", "v_Vel": "V_VEL"})
    frame["Location"] = "i-80"
    frame.to_csv(tmp_path / "export.csv", index=False)
    table = read_ngsim(tmp_path / "export.csv")
    assert table.runs == [f"export:{EPOCH}"]  # one location: not in the run
    assert (by_vehicle(table, "1")["speed"] == 30.5 * FT).all()
    assert (by_vehicle(table, "2")["length"] == 16.0 * FT).all()


def test_export_of_several_locations_and_duplicate_rows(tmp_path: Path) -> None:
    frame = pd.DataFrame(platoon(3))
    both = pd.concat([frame.assign(Location="us-101"), frame.assign(Location="i-80")])
    both = pd.concat([both, both.iloc[:1]])  # one row twice
    both.to_csv(tmp_path / "all.csv", index=False)
    table = read_ngsim(tmp_path / "all.csv")
    assert table.runs == [f"all:i-80:{EPOCH}", f"all:us-101:{EPOCH}"]
    assert len(table.frame) == 12
    assert any("1 row(s) repeat a vehicle and frame" in n for n in table.notes)


def test_arterial_layout_of_24_columns(tmp_path: Path) -> None:
    lines = []
    for record in platoon(3):
        record.update(dict.fromkeys(ARTERIAL_COLUMNS[14:20], 101))
        lines.append(" ".join(_cell(record[c]) for c in ARTERIAL_COLUMNS))
    (tmp_path / "trajectories-peachtree.txt").write_text("\n".join(lines))
    table = read_ngsim(tmp_path / "trajectories-peachtree.txt")
    assert by_vehicle(table, "1")["gap"].to_numpy() == pytest.approx(34.0 * FT)


def test_folder_reads_every_file_runs_apart(tmp_path: Path) -> None:
    write_txt(tmp_path / "one.txt", platoon(3))
    pd.DataFrame(platoon(4)).to_csv(tmp_path / "two.csv", index=False)
    (tmp_path / "readme.md").write_text("not data")
    table = read_ngsim(tmp_path)
    assert table.runs == [f"one:{EPOCH}", f"two:{EPOCH}"]
    assert len(table.frame) == 2 * 3 + 2 * 4


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("", "is empty"),
        ("1 2 3 4 5\n", "has 5 fields on line 1, expected 18"),
        ("Vehicle_ID,Frame_ID,Global_Time\n1,2,3\n", "lacks the column.*Local_Y"),
    ],
)
def test_malformed_files_raise(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(DataError, match=match) as info:
        read_ngsim(path)
    assert "bad.txt" in str(info.value)


# ------------------------------------------------------------------ variants
def export(tmp_path: Path, name: str, frame: pd.DataFrame, **options) -> Path:
    """``frame`` written as a CSV export (header row) under ``tmp_path/name``."""
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(path, index=False, **options)
    return path


#: Optional column -> what its absence leaves in the table of :func:`platoon`.
ABSENT = {
    "Global_Time": ("run", {"f"}),
    "Total_Frames": ("vehicle", {"1", "2"}),
    "v_Vel": ("speed", None),
    "v_Acc": ("acceleration", None),
    "v_Length": ("gap", None),  # and the length
    "Space_Headway": ("gap", None),
    "Lane_ID": ("lane", {""}),
    "Preceding": ("leader", {""}),
}


@pytest.mark.parametrize("column", list(ABSENT))
def test_optional_column_may_be_absent(tmp_path: Path, column: str) -> None:
    path = export(tmp_path, "f.csv", pd.DataFrame(platoon()).drop(columns=[column]))
    table = read_ngsim(path)
    assert table.n_vehicles == 2 and len(table.frame) == 10
    field, values = ABSENT[column]
    if values is None:
        assert table.frame[field].isna().all()
    else:
        assert set(table.frame[field]) == values
    assert sum(f"f.csv: no column {column}: " in n for n in table.notes) == 1
    # what is there is read as before
    follower = by_vehicle(table, "1")
    assert follower["position"].iloc[0] == pytest.approx(53.0 * FT, rel=1e-15)


def test_three_columns_are_enough(tmp_path: Path) -> None:
    frame = pd.DataFrame(platoon())[["Local_Y", "Frame_ID", "Vehicle_ID"]]
    table = read_ngsim(export(tmp_path, "min.csv", frame))
    assert table.runs == ["min"] and table.n_vehicles == 2
    assert table.frame[["speed", "acceleration", "length", "gap"]].isna().all().all()
    assert set(table.frame["leader"]) == {""}
    note = next(n for n in table.notes if "no column" in n)
    assert note.count("; no ") == 7 and "\n" not in note


def test_header_variants_read_alike(tmp_path: Path) -> None:
    """Column order, extra columns, separators, quotes, spellings, trailing
    separators: all give the table of the plain export."""
    plain = pd.DataFrame(platoon()).assign(Location="i-80")
    variants = {
        "reordered": (plain[plain.columns[::-1]], {}),
        "extra": (plain.assign(Comment="x", Speed_kmh=3.0), {}),
        "semicolon": (plain, {"sep": ";"}),
        "tabs": (plain, {"sep": "\t"}),
        "quoted": (plain, {"quoting": 1}),
        "spelled": (
            plain.rename(
                columns={
                    "Space_Headway": "Space_Hdwy",
                    "Preceding": "Prec_Veh",
                    "v_Length": "v_Len",
                    "Vehicle_ID": "Vehicle ID",
                    "Frame_ID": "FRAME-ID",
                }
            ),
            {},
        ),
        "unused twice": (
            plain.rename(columns={"Following": "v_Width"}),
            {},
        ),
    }
    reference = read_ngsim(export(tmp_path / "plain", "f.csv", plain)).frame
    for name, (frame, options) in variants.items():
        table = read_ngsim(export(tmp_path / name, "f.csv", frame, **options))
        pd.testing.assert_frame_equal(table.frame, reference, obj=name)
    text = (tmp_path / "plain" / "f.csv").read_text().splitlines()
    for name, lines in (
        ("every line", [line + "," for line in text]),
        # pandas takes the first column for an index when only the data lines
        # end in a comma: every value would move one column
        ("data lines", [text[0]] + [line + "," for line in text[1:]]),
        ("crlf", [line + "\r" for line in text]),
    ):
        path = tmp_path / name / "f.csv"
        path.parent.mkdir()
        path.write_text("\n".join(lines) + "\n")
        pd.testing.assert_frame_equal(read_ngsim(path).frame, reference, obj=name)


def test_text_layout_with_tabs_and_a_header_free_csv(tmp_path: Path) -> None:
    reference = read_ngsim(write_txt(tmp_path / "f.txt", platoon())).frame
    lines = (tmp_path / "f.txt").read_text().splitlines()
    for name, sep in (("tabs", "\t"), ("commas", ",")):
        path = tmp_path / name / "f.txt"
        path.parent.mkdir()
        path.write_text("\n".join(sep.join(line.split()) for line in lines))
        pd.testing.assert_frame_equal(read_ngsim(path).frame, reference, obj=name)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda ls: ls[:3] + [ls[3] + " 7"] + ls[4:], "Expected 18 fields in line 4"),
        (
            lambda ls: ls[:3] + [" ".join(ls[3].split()[:-1])] + ls[4:],
            "line 4 has fewer than 18 fields",
        ),
    ],
    ids=["a field too many", "a field too few"],
)
def test_ragged_text_lines_raise_not_shift(tmp_path: Path, edit, match) -> None:
    path = write_txt(tmp_path / "r.txt", platoon())
    path.write_text("\n".join(edit(path.read_text().splitlines())))
    with pytest.raises(DataError, match=match) as info:
        read_ngsim(path)
    assert "r.txt" in str(info.value) and "\n" not in str(info.value)


def test_unreadable_headers_raise_one_line(tmp_path: Path) -> None:
    frame = pd.DataFrame(platoon())
    cases = {
        "twice.csv": (
            frame.rename(columns={"Following": "Prec_Veh"}),
            "has the column\\(s\\) Preceding twice",
        ),
        "no_y.csv": (
            frame.drop(columns=["Local_Y"]),
            "lacks the column\\(s\\) Local_Y",
        ),
    }
    for name, (variant, match) in cases.items():
        with pytest.raises(DataError, match=match) as info:
            read_ngsim(export(tmp_path, name, variant))
        assert name in str(info.value) and "\n" not in str(info.value)
    binary = tmp_path / "b.csv"
    binary.write_bytes(b"\x00\x01garbage\n")
    with pytest.raises(DataError, match="b.csv' is not text"):
        read_ngsim(binary)


def test_folder_skips_files_that_are_not_trajectories(tmp_path: Path) -> None:
    write_txt(tmp_path / "trajectories-0400.txt", platoon(3))
    (tmp_path / "README.txt").write_text("NGSIM I-80\nfields: ...\n")
    table = read_ngsim(tmp_path)
    assert table.runs == [f"trajectories-0400:{EPOCH}"]
    assert any(
        n.startswith("skipped 1 file(s) that are not NGSIM") and "README.txt" in n
        for n in table.notes
    )
    (tmp_path / "trajectories-0400.txt").unlink()
    with pytest.raises(DataError, match="holds no NGSIM file"):
        read_ngsim(tmp_path)
    with pytest.raises(DataError, match="README.txt. lacks the column"):
        read_ngsim(tmp_path / "README.txt")  # named directly: read, and refused


def test_text_cell_names_column_and_line(tmp_path: Path) -> None:
    path = write_txt(tmp_path / "t.txt", platoon(3))
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace("30.5", "fast", 1)  # vehicle 1, frame 2
    path.write_text("\n".join(lines))
    with pytest.raises(DataError, match=r"t\.txt.*v_Vel.*'fast' on line 4"):
        read_ngsim(path)


def test_missing_source_raises(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no such file or folder"):
        read_ngsim(tmp_path / "nope.txt")
    with pytest.raises(DataError, match=r"no \*\.txt or \*\.csv"):
        read_ngsim(tmp_path)


# --------------------------------------------------------------- write / read
def small_pairs(dtype: torch.dtype = torch.float64) -> PairSet:
    """Two pairs, the second ragged (3 of 5 steps), irrational values."""
    steps = torch.arange(5, dtype=torch.float64)[:, None]  # (T, 1)
    x_lead = 100.0 + 13.1 * steps + torch.tensor([[0.0, 7.3]])  # (T, N)
    x_follow = x_lead - torch.tensor([[21.7, 33.3]]) - 0.1 * steps
    v_lead = torch.full((5, 2), 13.1) + torch.tensor([[1 / 3, 2 / 7]])
    v_follow = v_lead - 1.0 / 3.0
    a_lead = torch.full((5, 2), -0.123456789)
    a_follow = torch.full((5, 2), 0.987654321)
    mask = torch.ones(5, 2, dtype=torch.bool)
    mask[3:, 1] = False
    series = [
        s.to(dtype) for s in (x_lead, v_lead, a_lead, x_follow, v_follow, a_follow)
    ]
    return PairSet.from_arrays(series, dt=0.1, mask=mask, leader_length=4.5)


def assert_same_as_pairs(table, pairs: PairSet, rtol: float = 1e-9) -> None:
    """Every written vehicle reads back with the pairs' values, frame by frame."""
    frame = table.frame
    lengths = pairs.lengths.tolist()
    assert table.n_vehicles == 2 * pairs.n_pairs
    assert len(frame) == 2 * sum(lengths)
    groups = dict(tuple(frame.groupby("vehicle", sort=False)))
    for j, n in enumerate(lengths):
        for kind, vehicle in (("lead", 2 * j + 1), ("follow", 2 * j + 2)):
            rows = groups[str(vehicle)]
            assert rows["time"].to_numpy() == pytest.approx(0.1 * np.arange(1, n + 1))
            assert (rows["lane"] == str(j + 1)).all()
            for column, prefix in SERIES_OF:
                ref = getattr(pairs, f"{prefix}_{kind}")[:n, j].double().numpy()
                np.testing.assert_allclose(
                    rows[column].to_numpy(), ref, rtol=rtol, atol=1e-300
                )
        follower = groups[str(2 * j + 2)]
        assert (follower["leader"] == str(2 * j + 1)).all()
        spacing = (pairs.x_lead - pairs.x_follow)[:n, j].double().numpy()
        np.testing.assert_allclose(
            follower["gap"].to_numpy(), spacing - pairs.leader_length, rtol=1e-9
        )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_write_read_round_trip(tmp_path: Path, dtype: torch.dtype) -> None:
    pairs = small_pairs(dtype)
    path = tmp_path / "pairs.txt"
    write_ngsim(pairs, path)
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 18 and first[:4] == ["1", "1", "5", "1110000000100"]
    table = read_ngsim(path)
    assert table.runs == ["pairs:1110000000000"]
    assert_same_as_pairs(table, pairs)


def test_write_needs_frames_of_a_tenth_of_a_second(tmp_path: Path) -> None:
    pairs = small_pairs()
    slow = PairSet.from_arrays(pairs.series(), dt=0.5, mask=pairs.mask)
    with pytest.raises(DataError, match="NGSIM frames are 0.1 s.*dt = 0.5"):
        write_ngsim(slow, tmp_path / "x.txt")


# ---------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def peachtree():
    root = os.environ.get("TORCHCF_RAW")
    if not root or not (Path(root) / PEACHTREE).is_file():
        pytest.skip("TORCHCF_RAW is not set or lacks the NGSIM Peachtree sample")
    return read_ngsim(Path(root) / PEACHTREE)


def test_peachtree_periods_and_reused_ids(peachtree) -> None:
    frame = peachtree.frame
    stem = "peachtree_dotexport_first5000rows"
    assert frame.groupby("run").size().to_dict() == {
        f"{stem}:1163018600": 4017,
        f"{stem}:1163030300": 983,
    }
    assert peachtree.n_vehicles == 165
    assert frame["vehicle"].nunique() == 162
    for vehicle in ("70", "1311", "1322"):
        assert by_vehicle(peachtree, vehicle)["run"].nunique() == 2
    assert by_vehicle(peachtree, "70").groupby("run").size().tolist() == [381, 19]
    assert not frame["vehicle"].str.contains("#").any()  # no split within a run
    assert set(frame["lane"]) == {"1", "2", "11"}


def test_peachtree_is_sorted_in_si(peachtree) -> None:
    frame = peachtree.frame
    keys = list(zip(frame["run"], frame["vehicle"], frame["time"], strict=True))
    assert keys == sorted(keys)
    assert frame["time"].min() == pytest.approx(4.5)  # Frame_ID 45
    assert frame["position"].max() == pytest.approx(63.945 * FT)
    assert frame["speed"].max() == pytest.approx(51.3 * FT)
    assert frame[["position", "speed", "acceleration", "length"]].notna().all().all()


def test_peachtree_leaders_and_gaps(peachtree) -> None:
    frame = peachtree.frame
    follower = frame[(frame["vehicle"] == "70") & (frame["leader"] == "69")]
    leader = frame[frame["vehicle"] == "69"]
    common = follower.merge(leader, on=["run", "time"], suffixes=("", "_lead"))
    assert len(common) == 341
    # Space_Headway agrees with the positions to the file's 0.001-0.005 ft.
    spacing = common["position_lead"] - common["position"] - common["length_lead"]
    np.testing.assert_allclose(common["gap"], spacing, atol=0.006 * FT)
    assert np.isfinite(common["gap"]).all() and (common["gap"] > 0).all()
    notes = "\n".join(peachtree.notes)
    assert "2 recording period(s)" in notes
    assert "reused across periods, one vehicle per run: 70, 1311, 1322" in notes
    assert "54 leader(s) referenced but absent" in notes
    assert "Time_Headway holds 9999.99 in 2057 rows" in notes


@pytest.mark.slow  # the whole I-80 sample
def test_ngsim_i80_pairs_round_trip(tmp_path: Path) -> None:
    if not os.environ.get("TORCHCF_DATA"):
        pytest.skip("TORCHCF_DATA is not set: no NGSIM I-80 pairs")
    from torchcf.data import load_pairs

    pairs = load_pairs("ngsim-i80", None, download=False)
    assert (pairs.n_pairs, pairs.n_steps) == (150, 350)
    path = tmp_path / "i80.txt"
    write_ngsim(pairs, path)
    assert_same_as_pairs(read_ngsim(path), pairs)
