"""Read a pair set stored as six CSV files, the layout of the ABC paper's data.

A folder holds six files, one per series::

    Leading Position.csv    Leading Speed.csv    Leading Acc.csv
    Following Position.csv  Following Speed.csv  Following Acc.csv

Each is a plain CSV without a header: ROWS are time steps (every ``dt`` seconds),
COLUMNS are leader-follower pairs, and column j of the six files belongs together.
Positions are front-bumper positions along the road. The files are in one unit
system, given by ``units``: "m" (m, m/s, m/s^2) or "ft" (ft, ft/s, ft/s^2, as in
NGSIM), which is converted to SI by multiplying every series by 0.3048.

Pairs of different durations may be stored ragged: a column that ends early leaves
its remaining cells empty. Those steps are masked out and padded with the column's
last value (see :class:`~torchcf.data.pairset.PairSet`); the six files must agree
on where each column ends. Empty cells inside a column are an error, and trailing
blank lines or trailing all-empty columns (a comma at the end of every line) are
ignored.

Reading is fast (pandas, float64). Only when that fails or finds a non-finite value
does a slow cell-by-cell pass run, to name the exact file, row and column (1-based,
as a spreadsheet shows them) and the offending text.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from torchcf.data.pairset import DataError, PairSet, positive_float

__all__ = ["FILES", "UNITS", "read_six_csv", "unit_factor"]

#: The file holding each PairSet series (same order as ``pairset.SERIES``).
FILES: dict[str, str] = {
    "x_lead": "Leading Position.csv",
    "v_lead": "Leading Speed.csv",
    "a_lead": "Leading Acc.csv",
    "x_follow": "Following Position.csv",
    "v_follow": "Following Speed.csv",
    "a_follow": "Following Acc.csv",
}

#: Factor from a unit system to SI; it applies alike to positions, speeds and
#: accelerations because all three share the length unit.
UNITS: dict[str, float] = {"m": 1.0, "ft": 0.3048}


class _Table(NamedTuple):
    values: np.ndarray  # (T, N) float64, empty cells edge-padded
    lengths: np.ndarray  # (N,) int, leading non-empty cells of each column


def unit_factor(units: str) -> float:
    """The factor that converts ``units`` ("m" or "ft") to metres.

    Raises:
        DataError: unknown unit system.

    Examples:
        >>> from torchcf.data.reader import unit_factor
        >>> unit_factor("ft"), unit_factor("m")  # to metres
        (0.3048, 1.0)
    """
    if units not in UNITS:
        valid = ", ".join(repr(u) for u in UNITS)
        raise DataError(f"units must be one of {valid}, got {units!r}")
    return UNITS[units]


def read_six_csv(
    folder: str | os.PathLike[str],
    *,
    units: str = "m",
    dt: float,
    leader_length: float = 5.0,
    name: str = "",
) -> PairSet:
    """Read the six CSV files of ``folder`` into a PairSet in SI units.

    Args:
        folder: the folder holding the six files.
        units: unit system of the files, "m" (SI) or "ft" (converted x 0.3048).
        dt: sampling interval [s], > 0.
        leader_length: leader vehicle length [m], > 0.
        name: name of the set; defaults to the folder's name.

    Returns:
        A float64 PairSet of shape (T, N) with ``pair_ids`` = 0-based column in the
        files; the mask is all True unless columns are ragged.

    Raises:
        DataError: a missing, empty or malformed file (named with the 1-based row
            and column of the problem), files of different shapes, an invalid
            ``units``/``dt``/``leader_length``, or data that is not a valid
            PairSet (e.g. non-positive spacing, in metres).

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import read_six_csv
        >>> from torchcf.data.writer import write_six_csv
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(pairs, folder)
        ...     back = read_six_csv(folder, dt=0.1, name="demo")
        >>> back.name, back.n_steps, back.n_pairs, bool(back.x_lead.equal(pairs.x_lead))
        ('demo', 50, 4, True)
    """
    folder = Path(folder)
    factor = unit_factor(units)
    positive_float(dt, "dt", "s")
    if not folder.is_dir():
        raise DataError(f"not a folder: '{folder}'")
    tables: dict[str, _Table] = {}
    for field, file_name in FILES.items():
        path = folder / file_name
        if not path.is_file():
            raise DataError(f"missing file '{file_name}' in '{folder}'")
        tables[field] = _read_table(path)
    _check_agree(tables, folder)

    lengths = tables["x_lead"].lengths
    n_steps = tables["x_lead"].values.shape[0]
    mask = np.arange(n_steps)[:, None] < lengths[None, :]  # (T, N)
    series = [torch.from_numpy(tables[f].values * factor) for f in FILES]
    try:
        return PairSet.from_arrays(
            series,
            dt=dt,
            mask=torch.from_numpy(mask),
            leader_length=leader_length,
            name=name or folder.name,
        )
    except DataError as err:
        raise DataError(f"{err} in '{folder}'") from None


def _check_agree(tables: dict[str, _Table], folder: Path) -> None:
    """The six files must have one shape and end each column at the same row."""
    ref = tables["x_lead"]
    ref_file = FILES["x_lead"]
    for field, table in tables.items():
        if table.values.shape != ref.values.shape:
            raise DataError(
                f"'{FILES[field]}' has {_shape(table)} but '{ref_file}' has "
                f"{_shape(ref)} in '{folder}'"
            )
        differ = np.flatnonzero(table.lengths != ref.lengths)
        if differ.size:
            col = int(differ[0])
            raise DataError(
                f"column {col + 1} ends at row {table.lengths[col]} in "
                f"'{FILES[field]}' but at row {ref.lengths[col]} in '{ref_file}' "
                f"in '{folder}'"
            )


def _shape(table: _Table) -> str:
    rows, cols = table.values.shape
    return f"{rows} rows x {cols} columns"


def _read_table(path: Path) -> _Table:
    """Read one CSV of numbers; fall back to the exact slow pass on any problem."""
    try:
        values = pd.read_csv(
            path,
            header=None,
            dtype=np.float64,
            encoding="utf-8-sig",
            # Only an empty cell may be missing; "NaN", "NA" or "inf" text must
            # reach the slow pass, which names it.
            keep_default_na=False,
            na_values=[""],
            skip_blank_lines=False,
        ).to_numpy()
    except (ValueError, UnicodeDecodeError):  # includes pandas' parser errors
        return _read_table_slow(path)
    if values.size == 0 or not np.isfinite(values).all():
        return _read_table_slow(path)
    return _Table(values, np.full(values.shape[1], values.shape[0]))


def _read_table_slow(path: Path) -> _Table:
    """Parse cell by cell to locate the first bad cell, or accept ragged columns."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = [[cell.strip() for cell in row] for row in csv.reader(fh)]
    except UnicodeDecodeError as err:
        raise DataError(
            f"'{path.name}' is not UTF-8 text ({err}) in '{path.parent}'"
        ) from None
    # Trailing blank lines and a trailing comma on every line are formatting,
    # not missing data.
    while rows and not any(rows[-1]):
        rows.pop()
    n_cols = max((len(row) for row in rows), default=0)
    while n_cols and not any(len(row) >= n_cols and row[n_cols - 1] for row in rows):
        n_cols -= 1
    if not rows or not n_cols:
        raise DataError(f"'{path.name}' is empty in '{path.parent}'")

    values = np.full((len(rows), n_cols), np.nan)
    filled = np.zeros((len(rows), n_cols), dtype=bool)
    for i, row in enumerate(rows):
        for j, text in enumerate(row[:n_cols]):
            if text:
                values[i, j] = _parse_cell(text, path, i, j)
                filled[i, j] = True

    lengths = np.argmin(filled, axis=0)  # first empty cell = the column's length
    lengths[filled.all(axis=0)] = len(rows)
    after = filled & (np.arange(len(rows))[:, None] >= lengths[None, :])
    if after.any():
        row, col = np.argwhere(after)[0]
        raise DataError(
            f"empty cell at row {lengths[col] + 1}, column {col + 1} of "
            f"'{path.name}' before a value at row {row + 1}: only the last cells "
            f"of a column may be empty, in '{path.parent}'"
        )
    if (lengths == 0).any():
        col = int(np.flatnonzero(lengths == 0)[0])
        raise DataError(
            f"column {col + 1} of '{path.name}' has no value in '{path.parent}'"
        )
    last = values[lengths - 1, np.arange(n_cols)]  # (N,)
    values = np.where(filled, values, last[None, :])  # edge padding
    return _Table(values, lengths)


def _parse_cell(text: str, path: Path, row: int, col: int) -> float:
    where = f"at row {row + 1}, column {col + 1} of '{path.name}' in '{path.parent}'"
    shown = repr(text if len(text) <= 40 else text[:40] + "...")
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"not a number: {shown} {where}") from None
    if math.isnan(value):
        raise DataError(f"NaN ({shown}) {where}")
    if math.isinf(value):
        raise DataError(f"infinite value ({shown}) {where}")
    return value
