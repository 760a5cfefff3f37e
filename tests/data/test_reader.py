"""read_six_csv on synthetic folders: values, units, ragged files and every error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcf.data import DataError, read_six_csv
from torchcf.data.pairset import SERIES


def test_reads_values_exactly(write_six, make_arrays) -> None:
    folder = write_six("my set")
    pairs = read_six_csv(folder, dt=0.1)
    for f, expected in make_arrays().items():
        assert torch.equal(getattr(pairs, f), torch.from_numpy(expected))
    assert pairs.dtype == torch.float64 and bool(pairs.mask.all())
    assert pairs.pair_ids == (0, 1, 2) and pairs.name == "my set"
    assert read_six_csv(folder, dt=0.1, name="x", leader_length=4.0).name == "x"


def test_feet_are_converted_to_metres(write_six, make_arrays) -> None:
    metres = read_six_csv(write_six(), dt=0.1)
    feet = read_six_csv(write_six(), dt=0.1, units="ft")
    for f in SERIES:
        assert torch.equal(getattr(feet, f), getattr(metres, f) * 0.3048)


def test_bad_units(write_six) -> None:
    with pytest.raises(DataError, match=r"units must be one of 'm', 'ft', got 'km'"):
        read_six_csv(write_six(), dt=0.1, units="km")


@pytest.mark.parametrize("dt", [0.0, -1.0, float("inf"), None])
def test_bad_dt(write_six, dt) -> None:
    with pytest.raises(DataError, match="dt"):
        read_six_csv(write_six(), dt=dt)


def test_text_in_a_number(write_six) -> None:
    folder = write_six(text={"a_lead": "0,0,0\n0,0,0\n0,abc,0\n0,0,0\n0,0,0\n"})
    with pytest.raises(
        DataError,
        match=r"not a number: 'abc' at row 3, column 2 of 'Leading Acc.csv'",
    ):
        read_six_csv(folder, dt=0.1)


@pytest.mark.parametrize(
    ("cell", "match"),
    [
        ("nan", r"NaN \('nan'\)"),
        ("NaN", r"NaN \('NaN'\)"),
        ("inf", r"infinite value \('inf'\)"),
        ("-Infinity", r"infinite value \('-Infinity'\)"),
        ("1e400", r"infinite value \('1e400'\)"),
        ("NA", r"not a number: 'NA'"),
    ],
)
def test_nan_and_inf_cells(write_six, cell: str, match: str) -> None:
    rows = ["1,2,3"] * 5
    rows[3] = f"1,2,{cell}"
    folder = write_six(text={"v_follow": "\n".join(rows) + "\n"})
    with pytest.raises(
        DataError, match=match + r" at row 4, column 3 of 'Following Speed.csv'"
    ):
        read_six_csv(folder, dt=0.1)


def test_shape_mismatch_names_both_files(write_six, make_arrays) -> None:
    folder = write_six(arrays={"v_lead": make_arrays(n_steps=5, n_pairs=2)["v_lead"]})
    with pytest.raises(
        DataError,
        match=r"'Leading Speed.csv' has 5 rows x 2 columns but "
        r"'Leading Position.csv' has 5 rows x 3 columns",
    ):
        read_six_csv(folder, dt=0.1)


def test_missing_file(write_six) -> None:
    folder = write_six(skip=("x_follow",))
    with pytest.raises(DataError, match="missing file 'Following Position.csv' in"):
        read_six_csv(folder, dt=0.1)


def test_missing_folder(tmp_path) -> None:
    with pytest.raises(DataError, match="not a folder"):
        read_six_csv(tmp_path / "nope", dt=0.1)


@pytest.mark.parametrize("content", ["", "\n\n", " ,\n"])
def test_empty_file(write_six, content: str) -> None:
    folder = write_six(text={"a_follow": content})
    with pytest.raises(DataError, match="'Following Acc.csv' is empty"):
        read_six_csv(folder, dt=0.1)


def test_non_positive_spacing_in_metres(write_six, make_arrays) -> None:
    arrays = make_arrays()
    arrays["x_follow"][3, 2] = arrays["x_lead"][3, 2] + 1.0
    with pytest.raises(
        DataError,
        match=r"spacing x_lead - x_follow = -0.3048 m at row 4, column 3 "
        r"\(pair id 2\) in '.*set'",
    ):
        read_six_csv(write_six(arrays=arrays), dt=0.1, units="ft")


def test_blank_lines_and_trailing_commas_are_ignored(write_six, make_arrays) -> None:
    arrays = make_arrays()
    text = {
        f: "".join(",".join(repr(float(x)) for x in row) + ",\r\n" for row in arrays[f])
        + "\n\n"
        for f in SERIES
    }
    pairs = read_six_csv(write_six(text=text), dt=0.1)
    assert pairs.n_pairs == 3 and bool(pairs.mask.all())
    assert torch.equal(pairs.x_lead, torch.from_numpy(arrays["x_lead"]))


def _ragged_text(values: np.ndarray, lengths: list[int]) -> str:
    rows = []
    for t, row in enumerate(values):
        cells = [
            repr(float(x)) if t < n else "" for x, n in zip(row, lengths, strict=True)
        ]
        rows.append(",".join(cells).rstrip(","))  # short rows, as spreadsheets save
    return "\n".join(rows) + "\n"


def test_ragged_columns_are_masked_and_edge_padded(write_six, make_arrays) -> None:
    arrays = make_arrays()
    lengths = [5, 2, 4]
    text = {f: _ragged_text(arrays[f], lengths) for f in SERIES}
    pairs = read_six_csv(write_six(text=text), dt=0.1)
    assert pairs.lengths.tolist() == lengths
    assert pairs.v_lead[:, 1].tolist() == [11.0] * 5
    expected = arrays["x_lead"][:, 1].copy()
    expected[2:] = expected[1]
    assert pairs.x_lead[:, 1].tolist() == expected.tolist()


def test_ragged_lengths_must_agree(write_six, make_arrays) -> None:
    arrays = make_arrays()
    text = {f: _ragged_text(arrays[f], [5, 2, 4]) for f in SERIES}
    text["a_lead"] = _ragged_text(arrays["a_lead"], [5, 3, 4])
    with pytest.raises(
        DataError,
        match=r"column 2 ends at row 3 in 'Leading Acc.csv' but at row 2 in "
        r"'Leading Position.csv'",
    ):
        read_six_csv(write_six(text=text), dt=0.1)


def test_empty_cell_inside_a_column(write_six) -> None:
    folder = write_six(text={"x_lead": "100,200\n101,\n102,202\n"})
    with pytest.raises(
        DataError,
        match=r"empty cell at row 2, column 2 of 'Leading Position.csv' before a "
        r"value at row 3",
    ):
        read_six_csv(folder, dt=0.1)
