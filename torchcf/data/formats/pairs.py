"""Read pair-wide trajectory tables: one row per time step of a leader-follower couple.

Many car-following collections ship couples, not vehicles: each row holds the
leader's and the follower's state at one time step of one trajectory (a *pair*).
``columns`` maps the canonical names below to a file's columns (a dict, or the
text ``"pair=ID,time=t"``, as for the ``csv`` format); an item given overrides
one default, the others stay. The defaults are the names of ULTra-AV (Zhou et
al., "A unified longitudinal trajectory dataset for automated vehicle",
Scientific Data 11, 2024; arXiv:2406.00009), whose 13-14 automated-vehicle data
sets share one schema, then the canonical name itself:

=============  ==========================  =====  ================================
canonical      ULTra-AV column             unit   meaning
=============  ==========================  =====  ================================
pair           Trajectory_ID               -      trajectory id (required)
time           Time_Index                  s      time stamp on the trajectory's
                                                  clock (required)
x_lead         Pos_LV                      m      leader position (required)
v_lead         Speed_LV                    m/s    leader speed
a_lead         Acc_LV                      m/s^2  leader acceleration
x_follow       Pos_FAV                     m      follower position (required)
v_follow       Speed_FAV                   m/s    follower speed
a_follow       Acc_FAV                     m/s^2  follower acceleration
gap            Spatial_Gap or Space_Gap    m      bumper-to-bumper gap, leader's
                                                  rear to follower's front
leader_length  (none)                      m      leader length
run            (none)                      -      a group of trajectories (below)
=============  ==========================  =====  ================================

Units are converted with the ``csv`` format's tables
(:mod:`torchcf.data.formats.generic`); speeds and accelerations the file lacks
are derived at extraction.

What ULTra-AV says (its Table 1 and the released files): ``Time_Index`` is in
seconds on each trajectory's own clock (0.1, 0.2, ...: 10 Hz), not a step
count; ``Pos_LV`` and ``Pos_FAV`` are Frenet positions of the vehicle *centres*
(its ``Spatial_Headway = Pos_LV - Pos_FAV`` is "the distance between the centre
of two vehicles"); the gap is bumper to bumper,
``Spatial_Gap = Pos_LV - Pos_FAV - (l_lead + l_follow) / 2``. The files name the
gap column ``Spatial_Gap``; ``Space_Gap`` is read too.

**Leader length.** torchcf's spacing is ``x_lead - x_follow - L``
(:mod:`torchcf.data.trajectory`: positions of the front bumper, ``L`` the
leader's length). Whatever fixed point of each vehicle a position refers to, the
length ``L* = x_lead - x_follow - gap`` makes that spacing equal the recorded
gap: it is the leader's length for front-bumper positions, ``(l_lead +
l_follow) / 2`` for ULTra-AV's centres, the follower's length for rear
positions. So, per pair:

- positions and gap, no ``leader_length``: ``L`` is the median of ``L*`` over
  the pair's rows. Every row's ``L*`` must lie within ``length_tolerance`` of
  it (else the gap is not bumper to bumper between these positions, or one of
  them jumps) and ``L`` must be > 0 (else the gap is at least the headway: a
  headway mapped as the gap, or the vehicles swapped; 1 m in practice). Both
  are DataErrors.
- ``leader_length`` mapped too: it must stay within ``length_tolerance`` of its
  median within a pair, and agree with ``L*`` at every row within
  ``length_tolerance`` (a DataError otherwise: such positions are not front
  bumpers; leave ``leader_length`` unmapped and the length is derived).
- no gap: ``leader_length`` where mapped, else unknown (NaN: the extraction's
  ``default_length``).

Positions are kept as recorded and the recorded gap stays in the follower's
``gap`` column, so the extraction's gap-consistency filter still compares it
with the speeds.

**Long table.** Each pair becomes two vehicles of the long table,
``"<pair>:leader"`` and ``"<pair>:follower"`` (the follower names the leader),
in run ``"<pair>"``: a trajectory has its own clock and position frame. Mapping
``run`` puts the pairs of one value in one run instead (e.g. ``run=ID_FAV``, so
that ``--split-by run`` keeps all trajectories of one automated vehicle on one
side). In a folder, runs are prefixed by the file stem (``stem:run``). Lane and
mode are "" and the follower's length is unknown. Reading into the long table
rather than straight into pairs lets the extraction's time grid, unit checks,
derivatives, windows, quality filters and split serve pair tables unchanged.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pandas as pd

from torchcf.data.formats.generic import (
    SI_UNITS,
    TableUnits,
    column_map,
    read_header,
    read_selected,
    resolve_columns,
    source_files,
)
from torchcf.data.pairset import DataError, positive_float
from torchcf.data.trajectory import TrajectoryTable

__all__ = [
    "LENGTH_TOLERANCE",
    "MIN_LENGTH",
    "PAIR_COLUMNS",
    "QUANTITY",
    "ULTRA_AV",
    "leader_lengths",
    "pairs_to_long",
    "parse_numbers",
    "read_pairs",
]

#: Default column names of each canonical pair column (ULTra-AV's, then the
#: canonical name); the keys are the canonical columns, in their order.
ULTRA_AV: dict[str, tuple[str, ...]] = {
    "pair": ("Trajectory_ID", "pair"),
    "time": ("Time_Index", "time"),
    "x_lead": ("Pos_LV", "x_lead"),
    "v_lead": ("Speed_LV", "v_lead"),
    "a_lead": ("Acc_LV", "a_lead"),
    "x_follow": ("Pos_FAV", "x_follow"),
    "v_follow": ("Speed_FAV", "v_follow"),
    "a_follow": ("Acc_FAV", "a_follow"),
    "gap": ("Spatial_Gap", "Space_Gap", "gap"),
    "leader_length": ("leader_length",),
    "run": ("run",),
}
PAIR_COLUMNS: tuple[str, ...] = tuple(ULTRA_AV)
#: The quantity, hence the unit, of each numeric pair column.
QUANTITY: dict[str, str] = {
    "time": "time",
    "x_lead": "length",
    "v_lead": "speed",
    "a_lead": "acceleration",
    "x_follow": "length",
    "v_follow": "speed",
    "a_follow": "acceleration",
    "gap": "length",
    "leader_length": "length",
}
_TEXT = ("pair", "run")
_REQUIRED = ("pair", "time", "x_lead", "x_follow")
#: How far [m] a pair's leader length may stray from its median: a tenth of a
#: car's length, far above float noise and below any real mismatch of
#: reference points (a centre is 2 m from a bumper).
LENGTH_TOLERANCE = 0.5
#: Shortest leader length [m] positions and gap may imply (a motorbike is 2 m).
MIN_LENGTH = 1.0
_NOT_A_GAP = (
    "the gap is not bumper to bumper between these positions, or a position "
    "or the gap jumps"
)
_CHANGES = "a vehicle's length does not change within a trajectory"


def read_pairs(
    source: str | os.PathLike[str],
    *,
    columns: dict[str, str] | str | None = None,
    units: TableUnits = SI_UNITS,
    length_tolerance: float = LENGTH_TOLERANCE,
    sep: str = ",",
    road_frame: bool | None = None,
) -> TrajectoryTable:
    """Read a pair-wide CSV (or a folder of them) into a long trajectory table.

    Args:
        source: a CSV file, or a folder whose ``*.csv`` files are all read.
        columns: ``{canonical: source column}`` or its text form, over the
            defaults of :data:`ULTRA_AV`; canonical names of
            :data:`PAIR_COLUMNS`.
        units: the units of the columns
            (:class:`~torchcf.data.formats.generic.TableUnits`; default SI), as
            for :func:`torchcf.data.formats.generic.read_csv_table`.
        length_tolerance: largest spread [m] of a pair's leader length (module
            docstring), > 0.
        sep: field separator.
        road_frame: whether all positions lie on one road frame (None:
            unknown; ULTra-AV's do not: each trajectory has its own).

    Returns:
        The table, sorted, ``format="pairs"``, with a note on the lengths.

    Raises:
        DataError: what the ``csv`` reader raises, a required pair column
            missing, an empty pair id, or a leader length that positions, gap
            and ``leader_length`` do not agree on (module docstring).
    """
    given = column_map(columns, PAIR_COLUMNS)
    factors = units.factors()
    tolerance = positive_float(length_tolerance, "length_tolerance", "m")
    paths = source_files(source, (".csv",), "pairs")
    in_folder = Path(source).is_dir()
    frames, notes = [], []
    for path in paths:
        pairs = _read_one(path, given, factors, sep)
        long, note = pairs_to_long(
            pairs,
            source=str(path),
            tolerance=tolerance,
            prefix=path.stem if in_folder else "",
        )
        frames.append(long)
        notes.append(f"{path.name}: {note}")
    table = TrajectoryTable.from_frame(
        pd.concat(frames, ignore_index=True),
        source=str(source),
        format="pairs",
        road_frame=road_frame,
        notes=notes,
    )
    return table.sorted()


def pairs_to_long(
    pairs: pd.DataFrame, *, source: str, tolerance: float, prefix: str = ""
) -> tuple[pd.DataFrame, str]:
    """Pair-wide rows in SI to the long table's rows: a leader and a follower each.

    Args:
        pairs: (rows,) frame with text columns ``pair`` (and ``run``) and
            numeric columns of :data:`QUANTITY`, SI units; ``pair``, ``time``,
            ``x_lead`` and ``x_follow`` required, the others optional.
        source: the file, for messages.
        tolerance: largest spread of a pair's leader length [m].
        prefix: put before every run as ``prefix:run`` ("" for none).

    Returns:
        ``(frame, note)``: (2 * rows,) long-table rows (columns of
        :data:`torchcf.data.trajectory.COLUMNS`), leaders first; and one line
        on where the leader lengths came from.

    Raises:
        DataError: an empty pair id, or inconsistent leader lengths.
    """
    pair = pairs["pair"].astype(str)
    empty = (pair == "").to_numpy()
    if empty.any():
        row = int(np.flatnonzero(empty)[0])
        raise DataError(
            f"'{source}': {int(empty.sum())} row(s) without a pair id, first at "
            f"data row {row + 1}"
        )
    run = pairs["run"].astype(str) if "run" in pairs else pair
    if prefix:
        run = prefix + ":" + run
    keys = [run.rename("run"), pair.rename("pair")]
    length, note = leader_lengths(pairs, keys, source=source, tolerance=tolerance)
    leader = pair + ":leader"
    missing = pd.Series(np.nan, index=pairs.index)

    def numbers(column: str) -> pd.Series:
        return pairs[column] if column in pairs else missing

    lead = pd.DataFrame(
        {
            "run": run,
            "vehicle": leader,
            "time": pairs["time"],
            "position": pairs["x_lead"],
            "speed": numbers("v_lead"),
            "acceleration": numbers("a_lead"),
            "leader": "",
            "length": length,
        }
    )
    follow = pd.DataFrame(
        {
            "run": run,
            "vehicle": pair + ":follower",
            "time": pairs["time"],
            "position": pairs["x_follow"],
            "speed": numbers("v_follow"),
            "acceleration": numbers("a_follow"),
            "leader": leader,
            "gap": numbers("gap"),
        }
    )
    return pd.concat([lead, follow], ignore_index=True), note


def leader_lengths(
    pairs: pd.DataFrame, keys: list[pd.Series], *, source: str, tolerance: float
) -> tuple[np.ndarray, str]:
    """(rows,) leader length [m] of each row's pair, one value per pair.

    Args:
        pairs: as for :func:`pairs_to_long`.
        keys: the (rows,) series that name a pair (run and pair id).
        source: the file, for messages.
        tolerance: largest spread of a pair's leader length [m].

    Returns:
        ``(lengths, note)``; NaN where a pair has neither gap nor length.

    Raises:
        DataError: see the module docstring's rules.
    """
    implied = None  # x_lead - x_follow - gap: the L that makes spacing = gap
    if "gap" in pairs and pairs["gap"].notna().any():
        implied = (pairs["x_lead"] - pairs["x_follow"] - pairs["gap"]).to_numpy()
    given = pairs["leader_length"] if "leader_length" in pairs else None
    if given is not None and given.notna().any():
        length = _per_pair(
            given.to_numpy(), keys, "leader_length", _CHANGES, source, tolerance
        )
        if implied is not None:
            _check_agrees(pairs, implied, length, keys, source, tolerance)
        return length, _length_note(length, "the leader_length column", keys)
    if implied is not None:
        length = _per_pair(
            implied, keys, "x_lead - x_follow - gap", _NOT_A_GAP, source, tolerance
        )
        _check_positive(length, keys, source)
        return length, _length_note(length, "x_lead - x_follow - gap", keys)
    note = (
        "no gap and no leader_length: leader lengths unknown, the extraction's "
        "default length is used"
    )
    return np.full(len(pairs), np.nan), note


def parse_numbers(series: pd.Series, column: str, source: str) -> np.ndarray:
    """A column as float64; empty cells NaN, a text cell a DataError.

    Raises:
        DataError: naming the file, the column, the cell and its data row.
    """
    values = pd.to_numeric(series, errors="coerce").to_numpy(
        dtype=np.float64, copy=True
    )
    # Only cells that did not parse to a finite number are looked at as text:
    # string work on every cell of a million-row column would dominate.
    odd = np.flatnonzero(~np.isfinite(values))
    cells = series.iloc[odd]
    text = cells.astype(str).str.strip().str.lower()
    blank = cells.isna().to_numpy() | text.isin(("", "nan", "inf", "-inf")).to_numpy()
    if not blank.all():
        row = int(odd[np.flatnonzero(~blank)[0]])
        raise DataError(
            f"'{source}': column '{column}' holds {str(series.iloc[row])[:40]!r} at "
            f"data row {row + 1}, not a number"
        )
    values[odd] = np.nan
    return values


# ----------------------------------------------------------------- helpers
def _read_one(
    path: Path, given: dict[str, str], units: dict[str, float], sep: str
) -> pd.DataFrame:
    """One file's pair columns under canonical names: ids text, numbers in SI."""
    header = read_header(path, sep)
    chosen = resolve_columns(path, header, given, ULTRA_AV, _REQUIRED)
    raw = read_selected(path, chosen, _TEXT, sep)
    out = pd.DataFrame(index=raw.index)
    for column in raw.columns:
        if column in _TEXT:
            out[column] = raw[column].fillna("").astype(str).str.strip()
        else:
            factor = units[QUANTITY[column]]
            out[column] = parse_numbers(raw[column], column, str(path)) * factor
    return out


def _per_pair(
    values: np.ndarray,
    keys: list[pd.Series],
    label: str,
    hint: str,
    source: str,
    tolerance: float,
) -> np.ndarray:
    """(rows,) the median of ``values`` over each pair, after checking that no
    row strays from it by more than ``tolerance`` (else a DataError with
    ``hint``)."""
    series = pd.Series(values, index=keys[0].index)
    median = series.groupby(keys, sort=False).transform("median").to_numpy()
    stray = np.abs(values - median)
    worst = np.where(np.isfinite(stray), stray, -1.0)
    if worst.max(initial=-1.0) > tolerance:
        row = int(np.argmax(worst))
        pair = _pair_name(keys, row)
        low, high = _range_of(values, keys, row)
        raise DataError(
            f"{pair} of '{source}': {label}, the leader length, ranges over "
            f"{low:.2f}..{high:.2f} m, more than {tolerance:g} m from its median "
            f"{median[row]:.2f} m: {hint} (check the column map; "
            "--length-tolerance allows more)"
        )
    return median


def _check_agrees(
    pairs: pd.DataFrame,
    implied: np.ndarray,
    length: np.ndarray,
    keys: list[pd.Series],
    source: str,
    tolerance: float,
) -> None:
    """Positions, gap and leader_length must fit ``x_l - x_f - L = gap``."""
    off = np.abs(implied - length)
    off = np.where(np.isfinite(off), off, -1.0)
    if off.max(initial=-1.0) > tolerance:
        row = int(np.argmax(off))
        raise DataError(
            f"{_pair_name(keys, row)} of '{source}': leader_length is "
            f"{length[row]:.2f} m but x_lead - x_follow - gap is {implied[row]:.2f} m "
            f"at t = {pairs['time'].iat[row]:g} s (more than {tolerance:g} m apart): "
            "the positions are not front bumpers with that length (centres, as in "
            "ULTra-AV?); leave leader_length unmapped to derive it from the gap"
        )


def _check_positive(length: np.ndarray, keys: list[pd.Series], source: str) -> None:
    # Below MIN_LENGTH, not <= 0: a headway mapped as the gap gives 0 up to
    # float noise, and no reference point puts a vehicle's length under 1 m.
    bad = np.isfinite(length) & (length < MIN_LENGTH)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{_pair_name(keys, row)} of '{source}': the gap is nearly or more "
            f"than x_lead - x_follow (their difference, the leader length, is "
            f"{length[row]:.2f} m < {MIN_LENGTH:g} m): the gap column is not a "
            "bumper-to-bumper gap (a headway mapped as gap?), or leader and "
            "follower are swapped"
        )


def _length_note(length: np.ndarray, origin: str, keys: list[pd.Series]) -> str:
    known = np.isfinite(length)
    n_pairs = len(pd.DataFrame({"run": keys[0], "pair": keys[1]}).drop_duplicates())
    if not known.any():
        return f"leader lengths from {origin}: none known"
    return (
        f"leader lengths from {origin}: median {np.median(length[known]):.2f} m, "
        f"{length[known].min():.2f}..{length[known].max():.2f} m over "
        f"{n_pairs} pair(s)"
    )


def _pair_name(keys: list[pd.Series], row: int) -> str:
    run, pair = keys[0].iat[row], keys[1].iat[row]
    return f"pair {pair!r}" if run == pair else f"pair {pair!r} of run {run!r}"


def _range_of(
    values: np.ndarray, keys: Iterable[pd.Series], row: int
) -> tuple[float, float]:
    """Smallest and largest finite value of the pair of ``row``."""
    same = np.ones(len(values), dtype=bool)
    for key in keys:
        same &= (key == key.iat[row]).to_numpy()
    chosen = values[same & np.isfinite(values)]
    return float(chosen.min()), float(chosen.max())
