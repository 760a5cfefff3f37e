"""The calibrated set, readable: the parameters, and the shares per group of pairs.

A traffic engineer looks for the calibrated values first. ``posterior.pt`` holds
them as tensors; this module writes them where a spreadsheet or a report reader
finds them:

- **CSV** (:func:`parameters_csv`): one row per accepted particle of the hybrid
  (``Theta_hybrid``), columns ``model, pair_id, particle_index, score`` and then
  one column per parameter, named ``<model>.<parameter>`` (``idm.a``, ``hl.tau``:
  two models may use one name for different things), in SI units; a row leaves
  the other models' columns empty. ``pair_id`` is the training pair the particle
  was kept for (full-set column), ``particle_index`` its index in the model's
  stream (the stream regenerates it), ``score`` its weighted RMSE there.
- **Markdown** (:func:`parameters_markdown`): per model its share of the
  hybrid, its particles and pairs, and per parameter the unit, the median and
  the 5-95 % range over the model's hybrid particles (unweighted: every
  particle kept is one draw of the hybrid), the prior and the meaning.

- **Shares per group** (:func:`grouped_shares`, :func:`shares_markdown`,
  :func:`shares_csv`): the hybrid's slots of every training pair (its ``top_n``
  best across models; which model holds each), summed over the pairs of a group
  (any column of the data folder's ``index.csv``, e.g. ``mode`` or ``run``, or a
  user's mapping file), with the number of pairs per group and a bootstrap
  interval over pairs (or over clusters of pairs) for each share.

Shapes: h particles of one model in the hybrid, K its parameters; N training
pairs, M models, B bootstrap resamples, U resampled units (pairs or clusters).
"""

from __future__ import annotations

import csv
import io
import math
import re
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
import torch

from ..data import DataError
from ..data.formats.generic import require_header_line
from ..models import get_model
from ..system.errors import TorchcfError, did_you_mean
from ..system.files import atomic_write_text
from .bounds import EDGE_BAND, EDGE_SHARE, PiledAtBound, bounds_markdown
from .learned_set import Posterior

#: Quantiles of the Markdown table's range.
RANGE = (0.05, 0.95)
#: Significant digits of values in the CSV (float64 holds 17; 10 keeps a
#: parameter's value exact to well below any physical meaning).
CSV_DIGITS = 10
#: File names in the report folder.
CSV_NAME, MARKDOWN_NAME = "parameters.csv", "parameters.md"


@dataclass(frozen=True)
class ParameterInfo:
    """What the tables say about one parameter of a model."""

    name: str
    unit: str
    lower: float | None
    upper: float | None
    meaning: str


def parameter_info(model: str, names: tuple[str, ...]) -> list[ParameterInfo]:
    """Unit, prior and meaning of each of ``model``'s parameters ``names`` (as
    the posterior lists them); a model torchcf does not know (a name from a
    newer version) keeps its names with the rest blank."""
    try:
        specs = {s.name: s for s in get_model(model).param_specs}
    except (KeyError, ValueError):
        specs = {}
    out = []
    for name in names:
        s = specs.get(name)
        if s is None:
            out.append(ParameterInfo(name, "", None, None, ""))
        else:
            out.append(ParameterInfo(name, s.unit, s.lower, s.upper, s.description))
    return out


def csv_header(posterior: Posterior) -> list[str]:
    """``model, pair_id, particle_index, score`` and ``<model>.<parameter>`` for
    every model in run order, its parameters in the model's order."""
    columns = ["model", "pair_id", "particle_index", "score"]
    for model in posterior.models:
        columns += [f"{model}.{p}" for p in posterior.hybrid[model].param_names]
    return columns


def parameters_csv(posterior: Posterior) -> str:
    """The hybrid's particles as CSV text (module docstring), models in run
    order, each model's particles by training pair, then by score."""
    header = csv_header(posterior)
    column = {name: i for i, name in enumerate(header)}
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for model in posterior.models:
        particles = posterior.hybrid[model]
        names = [f"{model}.{p}" for p in particles.param_names]
        # (pair, score, stream index, parameters) per particle, as Python numbers
        rows = zip(
            particles.pair_ids.tolist(),
            particles.score.tolist(),
            particles.particle_index.tolist(),
            particles.theta.tolist(),
            strict=True,
        )
        for pair, score, index, theta in sorted(rows, key=lambda r: r[:3]):
            row = [""] * len(header)
            row[:4] = [model, str(pair), str(index), _number(score)]
            for name, value in zip(names, theta, strict=True):
                row[column[name]] = _number(value)
            writer.writerow(row)
    return buffer.getvalue()


def parameter_summary(posterior: Posterior, model: str) -> list[dict[str, object]]:
    """Per parameter of ``model``: its :class:`ParameterInfo` fields, the
    ``median``, ``low`` and ``high`` (:data:`RANGE` quantiles) over the model's
    hybrid particles, and ``near_lower`` / ``near_upper``: the share of them
    within :data:`EDGE_BAND` of the prior's width from each bound (None without
    particles or a known prior)."""
    particles = posterior.hybrid[model]
    theta = particles.theta.double()  # (h, K)
    out = []
    for k, info in enumerate(parameter_info(model, particles.param_names)):
        row: dict[str, object] = dict(info.__dict__)
        row.update(median=None, low=None, high=None, near_lower=None, near_upper=None)
        if len(particles):
            values = theta[:, k]
            q = torch.tensor([0.5, *RANGE], dtype=torch.float64)
            median, low, high = torch.quantile(values, q).tolist()
            row.update(median=median, low=low, high=high)
            if info.lower is not None and info.upper is not None:
                band = EDGE_BAND * (info.upper - info.lower)
                row["near_lower"] = float((values <= info.lower + band).double().mean())
                row["near_upper"] = float((values >= info.upper - band).double().mean())
        out.append(row)
    return out


def piled_at_bounds(posterior: Posterior) -> list[PiledAtBound]:
    """Every (model, parameter) whose hybrid particles pile up at a prior bound:
    more than :data:`EDGE_SHARE` of them within :data:`EDGE_BAND` of it (a
    uniform spread puts EDGE_BAND there). The data may prefer a value the prior
    cuts off, or the parameter trades off against another at its bound."""
    out = []
    for model in posterior.models:
        for row in parameter_summary(posterior, model):
            for side in ("lower", "upper"):
                share = row[f"near_{side}"]
                if share is not None and share > EDGE_SHARE:
                    out.append(
                        PiledAtBound(model, str(row["name"]), side, row[side], share)
                    )
    return out


def parameters_markdown(posterior: Posterior, heading: str = "##") -> str:
    """A Markdown table per model (module docstring), models in run order.

    Args:
        heading: the Markdown heading of the section; each model gets one level
            more.
    """
    low, high = (f"{q:.0%}" for q in RANGE)
    lines = [
        f"{heading} Calibrated parameters",
        "",
        f"Over each model's particles in the hybrid ({posterior.dataset}, "
        f"N = {posterior.top_n} per training pair): the median and the "
        f"{low}-{high} range, SI units. One row per particle: `{CSV_NAME}`.",
        "",
    ]
    for model in posterior.models:
        particles = posterior.hybrid[model]
        share = posterior.shares.get(model, 0.0)
        pairs = len(set(particles.pair_ids.tolist()))
        lines.append(
            f"{heading}# {model.upper()}: share {share:.1%}, "
            f"{len(particles)} particles on {pairs} training pairs"
        )
        lines.append("")
        if not len(particles):
            lines += ["No particle of this model is in the hybrid.", ""]
            continue
        lines.append(
            f"| Parameter | Unit | Median | {low} | {high} | Prior | Meaning |"
        )
        lines.append("|---|---|---|---|---|---|---|")
        for row in parameter_summary(posterior, model):
            prior = (
                f"[{_short(row['lower'])}, {_short(row['upper'])}]"
                if row["lower"] is not None
                else ""
            )
            lines.append(
                f"| {row['name']} | {row['unit']} | {_short(row['median'])} | "
                f"{_short(row['low'])} | {_short(row['high'])} | {prior} | "
                f"{row['meaning']} |"
            )
        lines.append("")
    lines += bounds_markdown(piled_at_bounds(posterior))
    return "\n".join(lines)


def write_parameter_tables(posterior: Posterior, folder: str | Path) -> list[Path]:
    """``folder/parameters.csv`` and ``folder/parameters.md``, each written
    atomically (a reader never sees half a table).

    Raises:
        RunFileError: a file cannot be written.
    """
    folder = Path(folder)
    paths = [folder / CSV_NAME, folder / MARKDOWN_NAME]
    atomic_write_text(paths[0], parameters_csv(posterior))
    atomic_write_text(paths[1], parameters_markdown(posterior, heading="#") + "\n")
    return paths


# ------------------------------------------------------------ shares per group
#: Defaults of the shares per group: bootstrap resamples and interval level.
N_BOOTSTRAP = 2000
LEVEL = 0.95
#: The first row of every table: all training pairs.
ALL = "all"
#: The group of a pair without a value (an empty cell; a pair a mapping file
#: does not name).
NO_GROUP = "(none)"
#: The group column of a mapping file (``--groups``).
GROUP_COLUMN = "group"
#: Fewer units than this in a group: its interval is marked (a percentile
#: bootstrap over a handful of draws cannot see how much they vary: too narrow);
#: with one unit there is none.
FEW_UNITS = 5
#: File names of a grouped table in the report folder: ``shares_by_<name>``.
SHARES_STEM = "shares_by_"


class GroupError(TorchcfError, ValueError):
    """A grouping that cannot be made: an unknown column, a malformed mapping
    file, a run whose pairs have no index (one line; exit code 2 on the
    command line)."""


class PairIndex(NamedTuple):
    """A run's ``index.csv`` and how its training pair ids find their rows.

    Attributes:
        path: the ``index.csv`` (one row per pair of the extraction).
        by_position: the run's pair ids are positions among the index's
            training rows, not its ``pair`` column: a run on a six-CSV folder
            with its own split reads ``Trajectory/``, whose columns are the
            index's ``split == "train"`` rows in order
            (:func:`torchcf.data.writer.write_extraction`).
        train_columns: the pairs ``Trajectory/`` holds (None: not read), to
            check that the index is the one the run was trained on.
    """

    path: Path
    by_position: bool
    train_columns: int | None = None


def locate_index(
    data: Any, run_dir: str | Path, folder: str | Path | None = None
) -> PairIndex:
    """Where the ``index.csv`` of a run's pairs is, from the config's data section.

    - ``data.raw`` (extracted when the run started): ``RUN/data/index.csv``;
      the run's pair ids are its ``pair`` column.
    - ``data.path`` (a folder, as ``torchcf data extract`` writes
      it): ``PATH/index.csv`` (a relative path from the working directory, as
      training read it); with ``split = "dataset"`` the ids are positions in
      ``Trajectory/`` (:class:`PairIndex`), with ``"kfold"`` full-set columns,
      i.e. the ``pair`` column.
    - ``data.name`` (a registered set): none; group with a mapping file.

    Args:
        data: the run config's ``data`` section (:class:`torchcf.config.DataConfig`).
        run_dir: the run directory.
        folder: the data folder instead of the config's (e.g. one that moved).

    Raises:
        GroupError: a registered set (no index), or no ``index.csv`` there.
    """
    if folder is not None:
        base = Path(folder)
    elif data.raw is not None:
        base = Path(run_dir) / "data"
    elif data.path is not None:
        base = Path(data.path)
    else:
        raise GroupError(
            f"the run's data ({data.name}) have no index.csv: group its pairs with "
            f"a mapping file (--groups FILE.csv with columns pair,{GROUP_COLUMN})"
        )
    path = base / "index.csv"
    if not path.is_file():
        raise GroupError(
            f"no index.csv in '{base}' (the run's data folder): pass the "
            "extraction's folder with --data DIR"
        )
    by_position = data.raw is None and data.split == "dataset"
    columns = _csv_columns(base / "Trajectory" / "Leading Position.csv")
    return PairIndex(path, by_position, columns if by_position else None)


def read_index(path: str | Path) -> pd.DataFrame:
    """An ``index.csv`` (or any CSV with a header) as text cells, as written
    ("" for an empty cell), whitespace stripped.

    Raises:
        GroupError: it cannot be read, or is not a table with a header.
    """
    try:
        require_header_line(Path(path))
    except DataError as error:
        raise GroupError(str(error)) from None
    try:
        frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (OSError, UnicodeDecodeError, pd.errors.ParserError) as error:
        reason = " ".join(str(error).split())
        raise GroupError(f"'{path}' cannot be read as CSV ({reason})") from None
    except pd.errors.EmptyDataError:
        raise GroupError(f"'{path}' is empty") from None
    frame.columns = [str(c).strip() for c in frame.columns]
    return frame.apply(lambda column: column.str.strip())


def training_pairs(
    posterior: Posterior,
    index: pd.DataFrame | None = None,
    *,
    by_position=False,
    train_columns: int | None = None,
    source: str = "index.csv",
) -> pd.DataFrame:
    """One row per training pair of ``posterior`` (``train_pair_ids`` order):
    the pair's row of ``index`` (text cells).

    Args:
        posterior: the learned set.
        index: the extraction's index (:func:`read_index`); None: the table is
            the one column ``pair``, the posterior's pair ids.
        by_position: the ids are positions among the ``split == "train"`` rows
            (:class:`PairIndex`); else values of the ``pair`` column.
        train_columns: the pairs ``Trajectory/`` holds, checked against the
            index's training rows (``by_position`` only).
        source: the index's name in messages.

    Raises:
        GroupError: an id the index does not hold, or an index that is not the
            one of the run's data.
    """
    ids = [int(i) for i in posterior.train_pair_ids.tolist()]
    if index is None:
        return pd.DataFrame({"pair": [str(i) for i in ids]})
    if "pair" not in index.columns:
        raise GroupError(f"{source}: no 'pair' column (not an extraction's index)")
    try:
        pair = [int(p) for p in index["pair"]]
    except ValueError:
        raise GroupError(f"{source}: a 'pair' cell is not an integer") from None
    # row[i]: the row of index holding pair id i (-1: none)
    if by_position:
        if "split" not in index.columns:
            raise GroupError(f"{source}: no 'split' column (not an extraction's index)")
        row = np.flatnonzero(index["split"].to_numpy() == "train")
        if train_columns is not None and train_columns != len(row):
            raise GroupError(
                f"{source} lists {len(row)} training pairs, Trajectory/ holds "
                f"{train_columns}: not the index of these pairs"
            )
        take = [int(row[i]) if 0 <= i < len(row) else -1 for i in ids]
        where = f"{len(row)} training rows"
    else:
        position = {p: k for k, p in enumerate(pair)}
        if len(position) < len(pair):
            raise GroupError(f"{source}: a pair id is listed twice")
        take = [position.get(i, -1) for i in ids]
        where = f"{len(pair)} pairs"
    missing = [i for i, k in zip(ids, take, strict=True) if k < 0]
    if missing:
        raise GroupError(
            f"the run's training pair {missing[0]} is not among the {where} of "
            f"{source}: not the index of the run's data"
        )
    return index.iloc[take].reset_index(drop=True)


def groups_by_column(
    table: pd.DataFrame, column: str, source: str = "index.csv"
) -> list[str]:
    """The group of every pair of ``table``: its ``column`` cell (an empty cell
    is :data:`NO_GROUP`).

    Raises:
        GroupError: ``table`` has no such column (the message lists them).
    """
    _require_columns(table, [column], source)
    return [_label(v) for v in table[column]]


def groups_from_file(
    table: pd.DataFrame, path: str | Path, source: str = "index.csv"
) -> list[str]:
    """The group of every pair of ``table`` from a mapping file.

    The file is a CSV with a header: a ``group`` column and one or more key
    columns, each a column of ``table`` (``pair``: the data set's pair id, or
    e.g. ``run,follower``). A pair takes the group of the row whose keys equal
    its own, compared as text; a pair no row names is :data:`NO_GROUP`.

    Raises:
        GroupError: no ``group`` or key column, an empty ``group`` cell, a key
            ``table`` lacks, two rows giving one key different groups, or no
            row naming any pair
            (a file of other pairs' keys is a mistake, not a grouping).
    """
    mapping = read_index(path)
    if GROUP_COLUMN not in mapping.columns:
        raise GroupError(
            f"'{path}': no '{GROUP_COLUMN}' column (columns: "
            f"{', '.join(mapping.columns)})"
        )
    keys = [c for c in mapping.columns if c != GROUP_COLUMN]
    if not keys:
        raise GroupError(f"'{path}': no key column beside '{GROUP_COLUMN}'")
    empty = mapping.index[mapping[GROUP_COLUMN] == ""]
    if len(empty):
        raise GroupError(
            f"'{path}': row {int(empty[0]) + 2} has an empty '{GROUP_COLUMN}' cell "
            f"({len(empty)} such rows; line numbers count the header as 1)"
        )
    _require_columns(table, keys, source, prefix=f"'{path}': key ")
    mapping = mapping.drop_duplicates()
    twice = mapping.duplicated(keys, keep=False)
    if twice.any():
        first = mapping.loc[twice, keys].iloc[0].tolist()
        raise GroupError(
            f"'{path}': key {dict(zip(keys, first, strict=True))} has two groups"
        )
    joined = table[keys].merge(mapping, on=keys, how="left", validate="many_to_one")
    if joined[GROUP_COLUMN].isna().all():
        example = table[keys].iloc[0].tolist() if len(table) else []
        raise GroupError(
            f"'{path}': no row names a training pair of {source} "
            f"({len(mapping)} rows; {source}'s keys look like "
            f"{dict(zip(keys, example, strict=True))})"
        )
    return [_label(v) for v in joined[GROUP_COLUMN].fillna("")]


@dataclass(frozen=True)
class GroupRow:
    """One group's shares (model order of :class:`GroupedShares`).

    Attributes:
        group: its name (:data:`ALL`: every training pair).
        n_pairs: its training pairs.
        n_units: the units resampled (pairs, or clusters of pairs).
        slots: (M,) hybrid slots each model holds on the group's pairs.
        share: (M,) each model's fraction of the group's slots (NaN: none).
        low, high: (M,) the bootstrap interval (NaN: no bootstrap, or a
            single unit).
    """

    group: str
    n_pairs: int
    n_units: int
    slots: tuple[int, ...]
    share: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    @property
    def n_slots(self) -> int:
        return sum(self.slots)


@dataclass(frozen=True)
class GroupedShares:
    """The shares per group of training pairs (:func:`grouped_shares`)."""

    by: str
    source: str
    models: tuple[str, ...]
    top_n: int
    selection: str
    rows: tuple[GroupRow, ...]  # ALL first, then the groups, NO_GROUP last
    unit: str  # "pair", or the cluster columns
    n_bootstrap: int
    level: float
    seed: int


def pair_slots(posterior: Posterior) -> np.ndarray:
    """(N, M) int64: the hybrid's slots on each training pair (``train_pair_ids``
    order) held by each model (run order).

    Raises:
        GroupError: a hybrid particle kept for a pair the run does not train on.
    """
    position = {int(p): k for k, p in enumerate(posterior.train_pair_ids.tolist())}
    counts = np.zeros((len(position), len(posterior.models)), dtype=np.int64)
    for m, model in enumerate(posterior.models):
        try:
            rows = [position[int(p)] for p in posterior.hybrid[model].pair_ids.tolist()]
        except KeyError as error:
            raise GroupError(
                f"the hybrid holds a {model} particle for pair {error}, not a "
                "training pair of the run"
            ) from None
        np.add.at(counts[:, m], rows, 1)
    return counts


@dataclass(frozen=True)
class Bootstrap:
    """How a share's interval is drawn: the percentile bootstrap over a
    group's units (:func:`grouped_shares`).

    Attributes:
        n_bootstrap: resamples (0: no interval).
        level: the interval's coverage, in (0, 1).
        seed: the bootstrap's seed.
    """

    n_bootstrap: int = N_BOOTSTRAP
    level: float = LEVEL
    seed: int = 0


def grouped_shares(
    posterior: Posterior,
    groups: Sequence[str],
    *,
    by: str,
    source: str = "",
    clusters: Sequence[str] | None = None,
    unit: str = "pair",
    bootstrap: Bootstrap = Bootstrap(),
) -> GroupedShares:
    """Each model's share of the hybrid's slots on the training pairs of each group.

    A group's share of model m is the slots m holds on the group's pairs over
    the group's slots (per-pair selection: ``top_n`` per pair, so the mean over
    its pairs of the per-pair shares); over all pairs it is the run's share.
    The interval is the percentile bootstrap: the group's units (its pairs, or
    its clusters of pairs: pairs from one follower share a driver and a day)
    drawn with replacement, ``n_bootstrap`` times, the share computed each
    time. Each group's draws come from ``(seed, group name)``, so a group's
    interval does not depend on the other groups.

    Args:
        posterior: the learned set.
        groups: (N,) the group of each training pair (``train_pair_ids`` order).
        by: what the groups are, for the table (a column, a file).
        source: where they come from, for the table.
        clusters: (N,) the cluster of each pair (None: each pair is a unit).
        unit: what a unit is, for the table.
        bootstrap: the intervals' resamples, level and seed (:class:`Bootstrap`).

    Raises:
        GroupError: ``groups`` or ``clusters`` of the wrong length, or bad
            ``n_bootstrap`` or ``level``.
    """
    n_bootstrap, level, seed = bootstrap.n_bootstrap, bootstrap.level, bootstrap.seed
    counts = pair_slots(posterior)  # (N, M)
    n_pairs = counts.shape[0]
    if len(groups) != n_pairs or (clusters is not None and len(clusters) != n_pairs):
        raise GroupError(
            f"a group and a cluster are needed for each of {n_pairs} pairs"
        )
    if n_bootstrap < 0:
        raise GroupError(f"bootstrap resamples must be >= 0, got {n_bootstrap}")
    if not 0 < level < 1:
        raise GroupError(f"the interval's level must be in (0, 1), got {level}")
    units = list(clusters) if clusters is not None else [str(k) for k in range(n_pairs)]
    labels = np.asarray(list(groups), dtype=object)
    names = sorted(set(labels.tolist()) - {NO_GROUP}, key=_natural)
    names += [NO_GROUP] if NO_GROUP in set(labels.tolist()) else []
    rows = [
        _group_row(ALL, counts, units, n_bootstrap, level, seed),
        *(
            _group_row(
                name,
                counts[labels == name],
                [u for u, g in zip(units, labels, strict=True) if g == name],
                n_bootstrap,
                level,
                seed,
            )
            for name in names
        ),
    ]
    return GroupedShares(
        by=by,
        source=source,
        models=tuple(posterior.models),
        top_n=posterior.top_n,
        selection=posterior.selection,
        rows=tuple(rows),
        unit=unit,
        n_bootstrap=n_bootstrap,
        level=level,
        seed=seed,
    )


def _group_row(
    name: str,
    counts: np.ndarray,
    units: list[str],
    n_bootstrap: int,
    level: float,
    seed: int,
) -> GroupRow:
    """One group's :class:`GroupRow` from its pairs' slots ``counts`` (n, M)."""
    held = counts.sum(axis=0)  # (M,)
    total = int(held.sum())
    share = held / total if total else np.full(held.shape, np.nan)
    codes, unit_of = np.unique(np.asarray(units, dtype=object), return_inverse=True)
    low = high = np.full(held.shape, np.nan)
    if n_bootstrap and total and len(codes) > 1:
        per_unit = np.zeros((len(codes), counts.shape[1]))  # (U, M)
        np.add.at(per_unit, unit_of, counts)
        rng = np.random.default_rng([seed, zlib.crc32(name.encode("utf-8"))])
        # Drawing U units with replacement = multinomial counts of each unit.
        weights = rng.multinomial(
            len(codes), np.full(len(codes), 1 / len(codes)), size=n_bootstrap
        )  # (B, U)
        drawn = weights @ per_unit  # (B, M)
        slots = drawn.sum(axis=1, keepdims=True)  # (B, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            shares = np.where(slots > 0, drawn / slots, np.nan)  # (B, M)
        tail = (1 - level) / 2
        low, high = np.nanquantile(shares, [tail, 1 - tail], axis=0)
    return GroupRow(
        group=name,
        n_pairs=int(counts.shape[0]),
        n_units=len(codes),
        slots=tuple(int(h) for h in held),
        share=tuple(float(s) for s in share),
        low=tuple(float(v) for v in low),
        high=tuple(float(v) for v in high),
    )


#: Columns of :func:`shares_csv`, one row per group and model.
SHARES_COLUMNS = (
    "by",
    "group",
    "pairs",
    "units",
    "slots_total",
    "model",
    "slots",
    "share",
    "low",
    "high",
)


def shares_csv(result: GroupedShares) -> str:
    """:data:`SHARES_COLUMNS` as CSV text: one row per group and model (shares
    as fractions; empty where undefined)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(SHARES_COLUMNS)
    for row in result.rows:
        for m, model in enumerate(result.models):
            writer.writerow(
                [
                    result.by,
                    row.group,
                    row.n_pairs,
                    row.n_units,
                    row.n_slots,
                    model,
                    row.slots[m],
                    *(_fraction(v[m]) for v in (row.share, row.low, row.high)),
                ]
            )
    return buffer.getvalue()


def shares_markdown(result: GroupedShares, heading: str = "##") -> str:
    """The shares per group as a Markdown table: a row per group (all pairs
    first), its training pairs (and clusters), then per model its share of the
    group's slots in % with the bootstrap interval."""
    per_pair = (
        f"its {result.top_n} best across models"
        if result.selection == "per_pair"
        else "its particles among the hybrid's"
    )
    if result.n_bootstrap:
        interval = (
            f", with a {result.level:.0%} percentile bootstrap interval over "
            f"{'pairs' if result.unit == 'pair' else _clusters(result.unit)} "
            f"({result.n_bootstrap} resamples within each group, seed {result.seed})"
        )
    else:
        interval = ""
    clustered = result.unit != "pair"
    lines = [
        f"{heading} Shares by {result.by}",
        "",
        f"The hybrid's slots on each training pair ({per_pair}), summed over the "
        f"pairs of each group ({result.source or result.by}): each model's share "
        f"of a group's slots, in %{interval}.",
        "",
        f"| {result.by} | pairs |"
        + (" clusters |" if clustered else "")
        + "".join(f" {m.upper()} |" for m in result.models),
        "|---|---:|" + ("---:|" if clustered else "") + "---|" * len(result.models),
    ]
    few = False
    for row in result.rows:
        cells = [
            _percent_cell(row.share[m], row.low[m], row.high[m])
            for m in range(len(result.models))
        ]
        name = f"**{row.group}**" if row.group == ALL else row.group
        if result.n_bootstrap and row.n_units < FEW_UNITS:
            name += " †"
            few = True
        lines.append(
            f"| {name} | {row.n_pairs} |"
            + (f" {row.n_units} |" if clustered else "")
            + "".join(f" {c} |" for c in cells)
        )
    if few:
        unit = "pairs" if result.unit == "pair" else "clusters"
        lines += [
            "",
            f"† fewer than {FEW_UNITS} {unit}: the bootstrap sees too few draws to "
            "tell how much they vary, so the interval is too narrow (none for one).",
        ]
    return "\n".join(lines)


def shares_stem(by: str, unit: str = "pair") -> str:
    """``shares_by_<by>``, and ``-clusters-<columns>`` for a bootstrap over
    clusters, made a safe file name (no dot: the stem has no suffix to lose)."""
    stem = _safe(by) or "group"
    if unit != "pair":
        stem += "-clusters-" + "-".join(_safe(c) for c in unit.split(","))
    return SHARES_STEM + stem


def write_grouped_shares(
    result: GroupedShares, folder: str | Path, stem: str | None = None
) -> list[Path]:
    """``folder/<stem>.csv`` and ``folder/<stem>.md`` (default stem:
    :func:`shares_stem` of ``result.by`` and its unit), each written atomically.

    Raises:
        RunFileError: a file cannot be written.
    """
    folder = Path(folder)
    stem = stem or shares_stem(result.by, result.unit)
    paths = [folder / f"{stem}.csv", folder / f"{stem}.md"]
    atomic_write_text(paths[0], shares_csv(result))
    atomic_write_text(paths[1], shares_markdown(result, heading="#") + "\n")
    return paths


def _require_columns(
    table: pd.DataFrame, columns: Sequence[str], source: str, prefix: str = ""
) -> None:
    for column in columns:
        if column not in table.columns:
            raise GroupError(
                f"{prefix}no column {column!r} in {source}"
                f"{did_you_mean(column, table.columns)} (columns: "
                f"{', '.join(table.columns)})"
            )


def _clusters(unit: str) -> str:
    return f"clusters ({unit.replace(',', ', ')})"


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name.strip()).strip("_")


def _csv_columns(path: Path) -> int | None:
    """The cells in the first line of a header-less CSV (None: no such file)."""
    try:
        with path.open(encoding="utf-8") as handle:
            return len(handle.readline().rstrip("\r\n").split(","))
    except (OSError, UnicodeDecodeError):
        return None


def _label(value: object) -> str:
    text = (
        ""
        if value is None or (isinstance(value, float) and math.isnan(value))
        else str(value).strip()
    )
    return text or NO_GROUP


def _natural(name: str) -> list[object]:
    """Sort key: digits as numbers ("run2" before "run10")."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def _fraction(value: float) -> str:
    return "" if math.isnan(value) else f"{value:.6g}"


def _percent_cell(share: float, low: float, high: float) -> str:
    if math.isnan(share):
        return "–"
    if share == 0 and not high > 0:
        return "0"
    if math.isnan(low):
        return f"{100 * share:.1f}"
    return f"{100 * share:.1f} [{100 * low:.1f}, {100 * high:.1f}]"


def _number(value: float) -> str:
    return f"{value:.{CSV_DIGITS}g}"


def _short(value: object) -> str:
    """A value for the Markdown table: 4 significant digits."""
    if value is None:
        return ""
    return f"{float(value):.4g}"


__all__ = [
    "ALL",
    "EDGE_BAND",
    "EDGE_SHARE",
    "PiledAtBound",
    "bounds_markdown",
    "piled_at_bounds",
    "CSV_NAME",
    "FEW_UNITS",
    "GROUP_COLUMN",
    "LEVEL",
    "MARKDOWN_NAME",
    "NO_GROUP",
    "N_BOOTSTRAP",
    "RANGE",
    "SHARES_COLUMNS",
    "Bootstrap",
    "GroupError",
    "GroupRow",
    "GroupedShares",
    "PairIndex",
    "ParameterInfo",
    "csv_header",
    "grouped_shares",
    "groups_by_column",
    "groups_from_file",
    "locate_index",
    "pair_slots",
    "parameter_info",
    "parameter_summary",
    "parameters_csv",
    "parameters_markdown",
    "read_index",
    "shares_csv",
    "shares_markdown",
    "shares_stem",
    "training_pairs",
    "write_grouped_shares",
    "write_parameter_tables",
]
