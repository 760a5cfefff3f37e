"""Punzo et al.'s six-column trajectory files (``--format punzo``).

Each file is written here with a known answer: the motions of
``tests/data/test_extract.py`` (leader speed a sine around 15 m/s, the follower
repeating it 1 s later, 20 m further back), front-bumper positions and a 4.6 m
leader, so the spacing ``x_lead - x_fol - L_lead`` is known at every step.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.cli.test_bad_input import one_error_line
from tests.data.test_extract import leader_motion
from tests.runs import exit_code
from torchcf.cli.data import main as data_main
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.punzo import read_punzo
from torchcf.data.pairset import DataError

DT = 0.1
L_LEAD = 4.6
HEADER = "t,x_lead,x_fol,v_lead,v_fol,L_lead"


def columns(n: int = 400, phase: float = 0.0) -> np.ndarray:
    """(n, 6) rows t, x_lead, x_fol, v_lead, v_fol, L_lead, t = 0, 0.1, ... [s]."""
    t = np.round(DT * np.arange(n), 10)
    x_lead, v_lead, _ = leader_motion(t, phase)
    x_fol, v_fol, _ = leader_motion(t - 1.0, phase)
    return np.column_stack([t, x_lead, x_fol - 20.0, v_lead, v_fol, np.full(n, L_LEAD)])


def write(path: Path, data: np.ndarray, *, sep: str = " ", header: str = "") -> Path:
    lines = [header] if header else []
    lines += [sep.join(f"{value:.10g}" for value in row) for row in data]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_headerless_file_is_one_pair(tmp_path) -> None:
    data = columns()
    table = read_punzo(write(tmp_path / "A01.txt", data))
    assert table.format == "punzo" and table.runs == ["A01"]
    frame = table.frame
    lead = frame[frame["vehicle"] == "A01:leader"]
    follow = frame[frame["vehicle"] == "A01:follower"]
    np.testing.assert_allclose(lead["time"], data[:, 0], atol=1e-12)
    np.testing.assert_allclose(lead["position"], data[:, 1], atol=1e-8)
    np.testing.assert_allclose(follow["position"], data[:, 2], atol=1e-8)
    np.testing.assert_allclose(lead["speed"], data[:, 3], atol=1e-8)
    np.testing.assert_allclose(follow["speed"], data[:, 4], atol=1e-8)
    assert (lead["length"] == L_LEAD).all() and follow["length"].isna().all()
    assert set(follow["leader"]) == {"A01:leader"} and follow["gap"].isna().all()
    assert frame["acceleration"].isna().all()  # derived at extraction
    assert table.notes == (
        "A01.txt: leader lengths from the leader_length column: median 4.60 m, "
        "4.60..4.60 m over 1 pair(s)",
    )


@pytest.mark.parametrize(
    ("sep", "header"),
    [(",", HEADER), ("\t", HEADER.replace(",", "\t")), (" ", "t x_lead x_fol")],
)
def test_a_header_is_skipped_and_columns_go_by_position(tmp_path, sep, header):
    data = columns(50)
    plain = read_punzo(write(tmp_path / "plain.txt", data)).frame
    headed = read_punzo(write(tmp_path / "p.csv", data, sep=sep, header=header))
    np.testing.assert_array_equal(
        headed.frame["position"].to_numpy(), plain["position"].to_numpy()
    )
    np.testing.assert_array_equal(headed.frame["time"], plain["time"])


def test_semicolons_with_decimal_commas_and_blank_lines(tmp_path) -> None:
    data = columns(30)
    text = "\n" + HEADER.replace(",", ";") + "\n\n"
    text += "\n".join(
        ";".join(f"{v:.10g}".replace(".", ",") for v in row) for row in data
    )
    path = tmp_path / "it.txt"
    path.write_text(text + "\n")
    table = read_punzo(path)
    lead = table.frame[table.frame["vehicle"] == "it:leader"]
    np.testing.assert_allclose(lead["position"], data[:, 1], atol=1e-8)
    np.testing.assert_allclose(lead["time"], data[:, 0], atol=1e-12)


def test_folder_each_file_its_own_pair(tmp_path) -> None:
    folder = tmp_path / "package"
    folder.mkdir()
    write(folder / "exp1_veh2.txt", columns(phase=0.0))
    write(folder / "exp1_veh3.csv", columns(phase=1.0), sep=",", header=HEADER)
    write(folder / "exp2_veh2.dat", columns(phase=2.0), sep="\t")
    (folder / "README.md").write_text("not a trajectory")
    table = read_trajectories(folder, "punzo")
    assert table.runs == ["exp1_veh2", "exp1_veh3", "exp2_veh2"]
    assert table.n_vehicles == 6 and len(table.notes) == 3
    extraction = extract_pairs(table, ExtractOptions(window=20.0, test_fraction=0.0))
    assert extraction.pairs.n_pairs == 6
    assert extraction.pairs.leader_length == pytest.approx(L_LEAD)
    index = extraction.index
    assert sorted(set(index["run"])) == table.runs
    assert set(index["leader"]) == {f"{run}:leader" for run in table.runs}
    # the spacing is the package's x_lead - x_fol - L_lead
    pairs = extraction.pairs
    spacing = (pairs.x_lead - pairs.x_follow - pairs.leader_length).numpy()
    t = index["t_start"].to_numpy()[None, :] + DT * np.arange(200)[:, None]
    phase = index["run"].map({"exp1_veh2": 0.0, "exp1_veh3": 1.0, "exp2_veh2": 2.0})
    phase = phase.to_numpy()[None, :]
    x_lead, _, _ = leader_motion(t, phase)
    x_fol, _, _ = leader_motion(t - 1.0, phase)
    np.testing.assert_allclose(spacing, x_lead - x_fol + 20.0 - L_LEAD, atol=1e-7)


def test_frame_numbers_and_units(tmp_path) -> None:
    data = columns(100)
    frames = data.copy()
    frames[:, 0] = np.arange(100)  # frame numbers of a 25 Hz video
    frames[:, 1:3] /= 0.3048
    frames[:, 5] /= 0.3048
    frames[:, 3:5] *= 3.6
    path = write(tmp_path / "f.txt", frames)
    table = read_punzo(
        path, time_unit="frame", frame_rate=25.0, length_unit="ft", speed_unit="km/h"
    )
    lead = table.frame[table.frame["vehicle"] == "f:leader"]
    np.testing.assert_allclose(lead["time"], np.arange(100) / 25.0, atol=1e-12)
    np.testing.assert_allclose(lead["position"], data[:, 1], atol=1e-7)
    np.testing.assert_allclose(lead["speed"], data[:, 3], atol=1e-7)
    np.testing.assert_allclose(lead["length"], L_LEAD, atol=1e-9)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("", "is empty"),
        ("\n\n", "is empty"),
        (HEADER + "\n", "has a header but no data row"),
        ("0 1 2 3 4\n0.1 1 2 3 4\n", "has 5 columns; a punzo file has six"),
        ("0 1 2 3 4 5\n0.1 1 oops 3 4 5\n", "'x_fol' holds 'oops' at data row 2"),
        ("0 1 2 3 4 5\n0.1 1 2 3 4\n", "data row 2 has no value for L_lead"),
        ("0,1,2,3,4,5\n0.1,1,,3,4,5\n", "data row 2 has no value for x_fol"),
        ("0 1 2 3 4 5\n0.1 1 2 3 4 5 6\n", "cannot read"),
    ],
)
def test_bad_files(tmp_path, content, match) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(DataError, match=match) as info:
        read_punzo(path)
    assert "bad.txt" in str(info.value)


def test_a_written_nan_is_a_missing_value(tmp_path) -> None:
    path = tmp_path / "gps.txt"
    path.write_text("0 10 0 5 5 4.6\n0.1 10.5 NaN 5 5 4.6\n0.2 11 1 5 5 NaN\n")
    frame = read_punzo(path).frame
    follow = frame[frame["vehicle"] == "gps:follower"]
    lead = frame[frame["vehicle"] == "gps:leader"]
    assert np.isnan(follow["position"].to_numpy()[1])
    assert (lead["length"] == 4.6).all()  # the pair's median fills the gap


def test_leader_length_changing_within_a_file(tmp_path) -> None:
    data = columns(100)
    data[50:, 5] = 6.0
    with pytest.raises(DataError) as info:
        read_punzo(write(tmp_path / "grow.txt", data))
    assert "leader_length, the leader length, ranges over 4.60..6.00 m" in str(
        info.value
    )
    table = read_punzo(write(tmp_path / "grow.txt", data), length_tolerance=2.0)
    assert table.n_vehicles == 2


def test_two_files_of_one_stem_and_empty_folder(tmp_path) -> None:
    write(tmp_path / "a.txt", columns(10))
    write(tmp_path / "a.csv", columns(10), sep=",")
    with pytest.raises(DataError, match="would be the same pair 'a'"):
        read_punzo(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match=r"holds no \*\.txt or \*\.csv or \*\.dat"):
        read_punzo(empty)


# --------------------------------------------------------------- command line
def test_cli_reads_a_folder(tmp_path, capsys) -> None:
    folder = tmp_path / "package"
    folder.mkdir()
    for k in range(3):
        write(folder / f"traj{k}.txt", columns(phase=float(k)))
    out = tmp_path / "out"
    args = ["extract", str(folder), "--format", "punzo", "--window", "20"]
    assert data_main([*args, "--out", str(out)]) == 0
    assert "6 pairs (4 train, 2 test) of 200 steps" in capsys.readouterr().out
    assert (out / "index.csv").is_file()


@pytest.mark.parametrize(
    ("more", "needles"),
    [
        ([], ["has 5 columns", "six"]),
        (["--columns", "time=t"], ["columns: only used with format='csv'"]),
        (["--time-unit", "frame"], ["needs a frame rate"]),
        (["--time-unit", "frame", "--frame-rate", "0"], ["--frame-rate", "> 0"]),
        (["--time-unit", "hours"], ["unknown time unit 'hours'", "frame"]),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys, more, needles):
    path = tmp_path / "five.txt"
    path.write_text("0 1 2 3 4\n0.1 1 2 3 4\n")
    args = ["extract", str(path), "--format", "punzo", "--out", str(tmp_path / "o")]
    assert exit_code(data_main, [*args, *more]) == 2
    one_error_line(capsys.readouterr().err, *needles)
    assert not (tmp_path / "o").exists()
