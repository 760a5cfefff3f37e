"""Named datasets: where their files are, how to fetch them, and their quirks.

The three data sets released with Jiang, Zhou, Wang & Ahn, "A Generic Stochastic
Hybrid Car-following Model Based on Approximate Bayesian Computation" (TR-C 2024,
doi 10.1016/j.trc.2024.104799), are registered in :data:`DATASETS`:

=============  ===================  =====  =====  =========================  =======
name           folder               units  dt     full set (T x N)           splits
=============  ===================  =====  =====  =========================  =======
ngsim-i80      HDV/NGSIM I_80       ft     0.1 s  350 x 150 (35.0 s)         105/45
car-model-1    AV/CAR MODEL I       m      0.1 s  541 x 96 (54.1 s)          67/28
car-model-2    AV/CAR MODEL II      m      0.1 s  576 x 64 (57.6 s)          45/18
=============  ===================  =====  =====  =========================  =======

Each folder holds the full set as six CSV files (see :mod:`torchcf.data.reader`),
and the same six files in ``Trajectory/`` (the calibration, i.e. training, split)
and ``Testing/`` (the test split). NGSIM I-80 is in feet, ft/s and ft/s^2 and is
converted to SI on loading; the CAR MODEL sets are SI. The leader length is 5 m.

Where the files come from (:func:`resolve_data_root`), first match wins:

1. ``data_root=``: the folder holding ``HDV/`` and ``AV/`` (or one holding
   ``data/HDV``, ``data/AV``);
2. the environment variable ``TORCHCF_DATA``, same meaning;
3. the cache ``$TORCHCF_CACHE``, else ``$XDG_CACHE_HOME/torchcf``, else
   ``~/.cache/torchcf``, files under ``<cache>/abc-paper/data/``;
4. a download of the missing files from the authors' repository at a pinned
   commit into the cache, each checked against ``torchcf/data/SHA256SUMS``
   (``download=False`` forbids it). The files carry no licence, so torchcf does
   not ship them.

A split cannot be loaded alone: its columns are copies of full-set columns, and
``pair_ids`` name the full-set column, so loading a split reads (and if needed
downloads) the full set and both splits.

Quirks, found generically and reported in ``PairSet.notes`` (in full) every time
a set is loaded, and through the ``torchcf.data`` logger once per process, as one
line per load with each new note in its short form (:func:`short_note`; a note
the training and test splits share, or a second load of the same set, is not
repeated) and where the quirks are explained (:data:`EXPLAINED`):

* Duplicated pairs (CAR MODEL II: full-set columns 6 & 16 and 7 & 17, 0-based,
  are identical; ``Trajectory/`` holds both copies of 7/17, and one copy of 6/16
  is in ``Trajectory/`` and the other in ``Testing/``, a train-to-test leak). Two
  pairs are duplicates when all six series are exactly equal. With
  ``drop_duplicates=True`` (default, :class:`Cleaning`) a loaded set keeps the
  first copy only, and
  the test split also drops the pairs that duplicate a training pair; with
  ``False`` everything is kept and the duplicates are still reported.
* Full-set columns in neither split (CAR MODEL I: column 44), reported when a
  split is loaded.
* Implausibly short spacing: pairs whose minimum front-to-front spacing is under
  :data:`SUSPECT_SPACING` (15 ft = 4.572 m, a car length plus a minimal gap) are
  always reported (NGSIM I-80: 9 pairs, position errors). ``min_spacing``
  [m] (:class:`Cleaning`) drops the pairs whose minimum spacing is under it,
  for any data set.

Any other folder in the six-CSV layout loads by path: units default to "m", and
``dt`` comes from the argument or from a ``meta.json`` beside the files
(``{"dt": 0.1, "units": "m", "leader_length": 5.0, "road_frame": true}``;
``road_frame``: whether all pairs' positions are on one road, which road effects
need, see :func:`torchcf.diagnose.signatures.road.shares_road_frame`; ``road_period``,
with
it: the lap length [m] of a closed track, whose road profiles are periodic;
``pairs``, which reading ignores: an extraction of whole couples says so, with
their lengths). A folder with ``Trajectory/`` but no ``Testing/`` (extracted with
``--test-fraction 0``) has no test split (:func:`torchcf.data.splits.split_pairs`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import http.client
import json
import logging
import math
import os
import tempfile
import urllib.parse
import urllib.request
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from torchcf.data.pairset import DataError, PairSet
from torchcf.data.reader import FILES, read_six_csv, unit_factor

__all__ = [
    "DATASETS",
    "SPLITS",
    "SUSPECT_SPACING",
    "Cleaning",
    "DatasetSpec",
    "cache_dir",
    "load_pairs",
    "notes_deferred",
    "read_meta",
    "resolve_data_root",
]

logger = logging.getLogger("torchcf.data")

#: Sub-folder of each split; None is the full set.
SPLITS: dict[str | None, str] = {None: "", "train": "Trajectory", "test": "Testing"}

#: Front-to-front spacing [m] (15 ft) under which a pair is reported as suspect.
SUSPECT_SPACING = 4.572

#: Raw files of the source repository at the commit the checksums were taken from.
SOURCE_URL = (
    "https://raw.githubusercontent.com/jiangjiwan/"
    "Approximate-Bayesian-Computation-Hybrid-Car-following-Model/"
    "64a2872a7dc90cf59a137b3cbbcd57a1981f55f8/data"
)
FETCH_TIMEOUT = 30.0  # [s] per file


@dataclass(frozen=True)
class DatasetSpec:
    """How to read one named data set.

    Attributes:
        folder: path of the full set under the data root, e.g. "AV/CAR MODEL I".
        units: unit system of the files, "m" or "ft".
        dt: sampling interval [s].
        leader_length: leader vehicle length [m] (after unit conversion).
        description: one line for humans.
        road_frame: whether the positions of all pairs are on one road (None:
            the source does not say).

    Examples:
        >>> from torchcf.data import DATASETS
        >>> spec = DATASETS["ngsim-i80"]
        >>> spec.folder, spec.units, spec.dt, spec.leader_length  # dt [s], length [m]
        ('HDV/NGSIM I_80', 'ft', 0.1, 5.0)
    """

    folder: str
    units: str
    dt: float
    leader_length: float = 5.0
    description: str = ""
    road_frame: bool | None = None


@dataclass(frozen=True)
class Cleaning:
    """Which pairs a load drops (module docstring: the quirks).

    Attributes:
        drop_duplicates: keep only the first copy of identical pairs in the set
            loaded; for a named test split, also drop the pairs that duplicate a
            training pair. False keeps everything (still reported in ``notes``).
        min_spacing: drop pairs whose minimum front-to-front spacing
            ``x_lead - x_follow`` over valid steps is under this value [m];
            None drops none for it.

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import Cleaning, load_pairs
        >>> from torchcf.data.writer import write_six_csv
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(pairs.subset([0, 0, 1]), folder)  # pair 0 twice
        ...     kept = load_pairs(folder, dt=0.1)
        ...     every = load_pairs(
        ...         folder, dt=0.1, cleaning=Cleaning(drop_duplicates=False)
        ...     )
        >>> kept.n_pairs, every.n_pairs
        (2, 3)
    """

    drop_duplicates: bool = True
    min_spacing: float | None = None


DATASETS: dict[str, DatasetSpec] = {
    "ngsim-i80": DatasetSpec(
        folder="HDV/NGSIM I_80",
        units="ft",
        dt=0.1,
        # Local_Y: the distance along the I-80 section, the same road for all
        road_frame=True,
        description="NGSIM I-80, human drivers: 150 pairs x 35.0 s, US units",
    ),
    "car-model-1": DatasetSpec(
        folder="AV/CAR MODEL I",
        units="m",
        dt=0.1,
        description="ACC platoon experiments, car model I: 96 pairs x 54.1 s",
    ),
    "car-model-2": DatasetSpec(
        folder="AV/CAR MODEL II",
        units="m",
        dt=0.1,
        description="ACC platoon experiments, car model II: 64 pairs x 57.6 s",
    ),
}


# --------------------------------------------------------------------- loading
def load_pairs(
    name_or_path: str | os.PathLike[str],
    split: str | None = None,
    units: str | None = None,
    *,
    dt: float | None = None,
    leader_length: float | None = None,
    data_root: str | os.PathLike[str] | None = None,
    download: bool = True,
    cleaning: Cleaning = Cleaning(),
) -> PairSet:
    """Load a named data set or a six-CSV folder as a PairSet in SI units.

    Args:
        name_or_path: a key of :data:`DATASETS`, or a folder in the six-CSV layout.
        split: None (full set), "train" (``Trajectory/``) or "test" (``Testing/``).
        units: unit system of the files, "m" or "ft"; defaults to the registry's
            for a name, else to ``meta.json``'s, else "m".
        dt: sampling interval [s]; defaults to the registry's for a name, else to
            ``meta.json``'s.
        leader_length: leader length [m]; defaults to the registry's or
            ``meta.json``'s, else 5.0.
        data_root: folder holding ``HDV/`` and ``AV/`` (names only).
        download: allow fetching missing files of a named set into the cache.
        cleaning: which pairs are dropped (:class:`Cleaning`: duplicates,
            by default, and pairs of too short a spacing).

    Returns:
        (T, N) float64 PairSet; ``pair_ids`` are 0-based full-set columns for a
        name, columns of the files read for a folder; ``notes`` report quirks.

    Raises:
        DataError: unknown name, bad split/units/dt, missing or malformed files,
            or data that cannot be found or downloaded.

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import load_pairs
        >>> from torchcf.data.writer import write_six_csv
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(pairs, folder)  # a six-CSV folder, SI units
        ...     loaded = load_pairs(folder, dt=0.1)
        >>> loaded.n_steps, loaded.n_pairs, loaded.split, loaded.dtype
        (50, 4, None, torch.float64)
    """
    if split not in SPLITS:
        raise DataError(f"split must be None, 'train' or 'test', got {split!r}")
    if units is not None:
        unit_factor(units)
    drop_duplicates, min_spacing = cleaning.drop_duplicates, cleaning.min_spacing
    if min_spacing is not None and not (
        math.isfinite(min_spacing) and min_spacing >= 0
    ):
        raise DataError(f"min_spacing must be finite and >= 0 [m], got {min_spacing}")

    notes: list[tuple[int, str]] = []
    if isinstance(name_or_path, str) and name_or_path in DATASETS:
        spec = DATASETS[name_or_path]
        root = resolve_data_root(
            name_or_path, split, data_root=data_root, download=download
        )
        pairs = _load_named(
            name_or_path,
            root / spec.folder,
            split,
            units=units or spec.units,
            dt=spec.dt if dt is None else dt,
            leader_length=(
                spec.leader_length if leader_length is None else leader_length
            ),
            drop_duplicates=drop_duplicates,
            notes=notes,
        )
    elif Path(name_or_path).is_dir():
        pairs = _load_folder(
            Path(name_or_path),
            split,
            units=units,
            dt=dt,
            leader_length=leader_length,
            drop_duplicates=drop_duplicates,
            notes=notes,
        )
    else:
        raise DataError(
            f"unknown dataset {str(name_or_path)!r}: neither a registered name "
            f"({', '.join(DATASETS)}) nor an existing folder"
        )

    pairs = _check_spacing(pairs, min_spacing, notes)
    _announce(pairs.name, notes)
    return dataclasses.replace(pairs, notes=tuple(text for _, text in notes))


#: (data set, short note) pairs this process has logged: a command loads a data
#: set's training and test splits, often more than once (train, evaluate, the
#: loop), and its quirks are the same each time (``PairSet.notes`` keeps them
#: all, in full).
_ANNOUNCED: set[tuple[str, str]] = set()
#: Where the quirks of the data sets are explained (the logged line says so).
EXPLAINED = "docs/data.md, 'Errors and quirks'"
#: Characters of one note in the logged line.
_SHORT = 120


#: Notes held back by :func:`notes_deferred` (None: none is active).
_DEFERRED: list[tuple[int, str, str]] | None = None


def short_note(text: str) -> str:
    """A note's short form: its first clause (up to the first ``;``), at most
    :data:`_SHORT` characters. Both splits' notes of one quirk share it."""
    head = text.split("; ", 1)[0]
    return head if len(head) <= _SHORT else head[: _SHORT - 3] + "..."


def _announce(name: str, notes: list[tuple[int, str]]) -> None:
    """Log a load's notes as one line, each note in its short form, once per
    process and data set (a second load, or the other split, adds only what is
    new), with where they are explained and where they are kept in full."""
    fresh = []
    for level, text in notes:
        short = short_note(text)
        if (name, short) not in _ANNOUNCED:
            _ANNOUNCED.add((name, short))
            fresh.append((level, short))
    if not fresh:
        return
    level = max(lvl for lvl, _ in fresh)
    count = f"{len(fresh)} data note{'s' if len(fresh) > 1 else ''}"
    text = (
        f"{count}, handled as documented ({EXPLAINED}; in full in PairSet.notes): "
        + "; ".join(short for _, short in fresh)
    )
    if _DEFERRED is not None:
        _DEFERRED.append((level, name, text))
        return
    logger.log(level, "%s: %s", name, text)


@contextmanager
def notes_deferred() -> Iterator[None]:
    """Hold the data notes of the loads in the block back until it ends, and
    drop them if it raises: a command that loads its data and then checks the
    config against it (the particle budget per pair) shows the one error, not
    the data's quirks first."""
    global _DEFERRED
    outer, _DEFERRED = _DEFERRED, []
    held = _DEFERRED
    try:
        yield
    finally:
        _DEFERRED = outer
    for level, where, text in held:  # the block ended without an error
        if outer is not None:
            outer.append((level, where, text))
        else:
            logger.log(level, "%s: %s", where, text)


def _load_named(
    name: str,
    base: Path,
    split: str | None,
    *,
    units: str,
    dt: float,
    leader_length: float,
    drop_duplicates: bool,
    notes: list[tuple[int, str]],
) -> PairSet:
    """Read a named set; map split columns to full-set ids and handle quirks."""

    def read(split_: str | None) -> PairSet:
        return dataclasses.replace(
            read_six_csv(
                base / SPLITS[split_],
                units=units,
                dt=dt,
                leader_length=leader_length,
                name=name,
            ),
            split=split_,
            road_frame=DATASETS[name].road_frame,
        )

    if split is None:
        full = read(None)
        return _drop_copies(full, _column_keys(full), drop_duplicates, notes)

    full, train, test = read(None), read("train"), read("test")
    keys = {
        s: _column_keys(p) for s, p in ((None, full), ("train", train), ("test", test))
    }
    ids = _match_to_full(keys, base, notes)
    unused = sorted(set(range(full.n_pairs)) - set(ids["train"]) - set(ids["test"]))
    if unused:
        notes.append(
            (
                logging.WARNING,
                f"full-set column{_s(unused)} {_join(unused)} (0-based pair "
                f"id{_s(unused)}) {'are' if len(unused) > 1 else 'is'} in neither "
                "Trajectory/ nor Testing/: "
                f"{len(ids['train'])} + {len(ids['test'])} = "
                f"{len(ids['train']) + len(ids['test'])} of {full.n_pairs} pairs "
                "are split",
            )
        )
    train = dataclasses.replace(train, pair_ids=tuple(ids["train"]))
    test = dataclasses.replace(test, pair_ids=tuple(ids["test"]))
    pairs = train if split == "train" else test
    pairs = _drop_copies(pairs, keys[split], drop_duplicates, notes)
    return _handle_leak(pairs, keys, train, test, drop_duplicates, notes)


def _load_folder(
    folder: Path,
    split: str | None,
    *,
    units: str | None,
    dt: float | None,
    leader_length: float | None,
    drop_duplicates: bool,
    notes: list[tuple[int, str]],
) -> PairSet:
    """Read a six-CSV folder (or its split sub-folder), settings from meta.json."""
    meta = read_meta(folder)
    dt = dt if dt is not None else meta.get("dt")
    if dt is None:
        raise DataError(
            f"dt missing: pass dt= or write meta.json with the sampling interval "
            f"(e.g. {{\"dt\": 0.1}}) in '{folder}'"
        )
    pairs = read_six_csv(
        folder / SPLITS[split],
        units=units or meta.get("units", "m"),
        dt=dt,
        leader_length=(
            leader_length
            if leader_length is not None
            else meta.get("leader_length", 5.0)
        ),
        name=str(folder),
    )
    pairs = dataclasses.replace(
        pairs,
        split=split,
        road_frame=meta.get("road_frame"),
        road_period=meta.get("road_period"),
    )
    return _drop_copies(pairs, _column_keys(pairs), drop_duplicates, notes)


def read_meta(folder: Path) -> dict:
    """A pair folder's ``meta.json`` (empty where it has none): the keys it
    states of ``dt``, ``units``, ``leader_length``, ``road_frame``,
    ``road_period`` and ``pairs``.

    Raises:
        DataError: not valid JSON, or keys it may not hold.
    """
    path = folder / "meta.json"
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DataError(f"'{path}' is not valid JSON: {err}") from None
    # "pairs" describes an extraction's pairs (whole couples: their lengths);
    # reading needs none of it.
    allowed = {"dt", "units", "leader_length", "road_frame", "road_period", "pairs"}
    if not isinstance(meta, dict) or set(meta) - allowed:
        extra = sorted(set(meta) - allowed) if isinstance(meta, dict) else meta
        raise DataError(
            f"'{path}' must be an object with keys {sorted(allowed)}, got {extra!r}"
        )
    return meta


# ---------------------------------------------------------------------- quirks
def _column_keys(pairs: PairSet) -> list[bytes]:
    """One bytes key per pair; equal keys <=> all six series and mask equal."""
    # + 0.0 maps -0.0 to 0.0, so numerically equal columns give equal bytes.
    values = np.stack([_numpy(t) for t in pairs.series().values()]) + 0.0  # (6, T, N)
    cols = values.transpose(2, 0, 1).copy()  # (N, 6, T)
    mask = _numpy(pairs.mask).T.copy()  # (N, T)
    return [c.tobytes() + m.tobytes() for c, m in zip(cols, mask, strict=True)]


def _min_spacing(pairs: PairSet) -> list[float]:
    """(N,) minimum front-to-front spacing x_lead - x_follow over valid steps [m]."""
    spacing = _numpy(pairs.x_lead) - _numpy(pairs.x_follow)  # (T, N)
    return np.where(_numpy(pairs.mask), spacing, np.inf).min(axis=0).tolist()


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().double().numpy()


def _match_to_full(
    keys: dict[str | None, list[bytes]],
    base: Path,
    notes: list[tuple[int, str]],
) -> dict[str, list[int]]:
    """Full-set column of every split column, by exact equality.

    Identical full-set columns are handed out in order (training split first), so
    that the copies in the splits get distinct ids.
    """
    pool: dict[bytes, list[int]] = defaultdict(list)
    for j, key in enumerate(keys[None]):
        pool[key].append(j)
    used: set[int] = set()
    ids: dict[str, list[int]] = {}
    shared: dict[str, list[int]] = {}
    for split in ("train", "test"):
        ids[split], shared[split] = [], []
        for col, key in enumerate(keys[split]):
            candidates = pool.get(key)
            if not candidates:
                raise DataError(
                    f"column {col + 1} of '{base / SPLITS[split]}' equals no column "
                    "of the full set, so it has no pair id"
                )
            free = [j for j in candidates if j not in used]
            pick = free[0] if free else candidates[0]
            used.add(pick)
            ids[split].append(pick)
            if len(candidates) > 1:
                shared[split].append(pick)
    if shared["train"] or shared["test"]:
        groups = sorted({tuple(g) for g in pool.values() if len(g) > 1})
        notes.append(
            (
                logging.INFO,
                f"full-set columns {_groups(groups)} are identical; the split "
                "columns that copy them got distinct pair ids in order "
                f"(Trajectory/: {_join(shared['train']) or 'none'}; "
                f"Testing/: {_join(shared['test']) or 'none'})",
            )
        )
    return ids


def _drop_copies(
    pairs: PairSet,
    keys: list[bytes],
    drop: bool,
    notes: list[tuple[int, str]],
) -> PairSet:
    """Report (and with ``drop``, remove) later copies of identical pairs."""
    first: dict[bytes, int] = {}
    groups: dict[int, list[int]] = defaultdict(list)
    for pos, key in enumerate(keys):
        groups[first.setdefault(key, pos)].append(pos)
    groups = {k: v for k, v in groups.items() if len(v) > 1}
    if not groups:
        return pairs
    ids = pairs.pair_ids
    copies = [pos for g in groups.values() for pos in g[1:]]
    where = _set_label(pairs)
    text = (
        f"{where} holds exact duplicates (all six series equal): pair ids "
        f"{_groups([[ids[p] for p in g] for g in groups.values()])}; "
    )
    if drop:
        keep = [p for p in range(pairs.n_pairs) if p not in set(copies)]
        notes.append(
            (
                logging.WARNING,
                text + f"dropped the later cop{'ies' if len(copies) > 1 else 'y'} "
                f"(pair id{_s(copies)} {_join(ids[p] for p in copies)}), "
                f"{len(keep)} of {pairs.n_pairs} pairs kept (drop_duplicates=True)",
            )
        )
        return pairs.subset(keep)
    notes.append((logging.WARNING, text + "all kept (drop_duplicates=False)"))
    return pairs


def _handle_leak(
    pairs: PairSet,
    keys: dict[str | None, list[bytes]],
    train: PairSet,
    test: PairSet,
    drop: bool,
    notes: list[tuple[int, str]],
) -> PairSet:
    """Report test pairs that copy a training pair; drop them from the test split."""
    train_ids: dict[bytes, int] = {}
    for key, pid in zip(keys["train"], train.pair_ids, strict=True):
        train_ids.setdefault(key, pid)
    leaks = [
        (pid, train_ids[key])
        for key, pid in zip(keys["test"], test.pair_ids, strict=True)
        if key in train_ids
    ]
    if not leaks:
        return pairs
    text = (
        "Testing/ pair id"
        f"{_s(leaks)} {_join(t for t, _ in leaks)} exactly duplicate"
        f"{'' if len(leaks) > 1 else 's'} Trajectory/ pair id{_s(leaks)} "
        f"{_join(t for _, t in leaks)} (a train-to-test leak); "
    )
    if pairs.split == "train":
        notes.append(
            (
                logging.WARNING,
                text
                + f"the test split drops the cop{'ies' if len(leaks) > 1 else 'y'} "
                "when drop_duplicates=True",
            )
        )
        return pairs
    if not drop:
        notes.append((logging.WARNING, text + "kept (drop_duplicates=False)"))
        return pairs
    leaked = {t for t, _ in leaks}
    keep = [p for p, pid in enumerate(pairs.pair_ids) if pid not in leaked]
    notes.append(
        (
            logging.WARNING,
            text + f"dropped from the test split, {len(keep)} of {test.n_pairs} "
            "pairs kept (drop_duplicates=True)",
        )
    )
    return pairs.subset(keep)


def _check_spacing(
    pairs: PairSet,
    min_spacing: float | None,
    notes: list[tuple[int, str]],
) -> PairSet:
    """Report suspect pairs and drop those under ``min_spacing`` [m]."""
    smallest = _min_spacing(pairs)
    ids = pairs.pair_ids
    suspect = [p for p, s in enumerate(smallest) if s < SUSPECT_SPACING]
    if suspect:
        worst = min(suspect, key=lambda p: smallest[p])
        notes.append(
            (
                logging.WARNING,
                f"{len(suspect)} pair{_s(suspect)} with a minimum front-to-front "
                f"spacing under {SUSPECT_SPACING} m (15 ft), likely position errors: "
                f"pair id{_s(suspect)} {_join(ids[p] for p in suspect)} (smallest "
                f"{smallest[worst]:.3g} m, pair id {ids[worst]}); "
                "min_spacing= drops them",
            )
        )
    if min_spacing is None:
        return pairs
    drop = [p for p, s in enumerate(smallest) if s < min_spacing]
    if len(drop) == pairs.n_pairs:
        raise DataError(
            f"min_spacing={min_spacing} m drops all {pairs.n_pairs} pairs "
            f"(largest minimum spacing {max(smallest):.3g} m)"
        )
    if drop:
        notes.append(
            (
                logging.INFO,
                f"dropped {len(drop)} pair{_s(drop)} with a minimum spacing under "
                f"{min_spacing} m (min_spacing): pair id{_s(drop)} "
                f"{_join(ids[p] for p in drop)}; "
                f"{pairs.n_pairs - len(drop)} of {pairs.n_pairs} pairs kept",
            )
        )
    return pairs.subset([p for p in range(pairs.n_pairs) if p not in set(drop)])


def _set_label(pairs: PairSet) -> str:
    return {None: "the full set", "train": "Trajectory/", "test": "Testing/"}[
        pairs.split
    ]


def _s(items: Sequence[object]) -> str:
    return "s" if len(items) > 1 else ""


def _join(items: Iterable[object]) -> str:
    return ", ".join(str(i) for i in items)


def _groups(groups: Sequence[Sequence[int]]) -> str:
    return ", ".join(" & ".join(str(i) for i in g) for g in groups)


# --------------------------------------------------------- finding the files
def cache_dir() -> Path:
    """The user cache: ``$TORCHCF_CACHE``, ``$XDG_CACHE_HOME/torchcf`` or
    ``~/.cache/torchcf``."""
    if os.environ.get("TORCHCF_CACHE"):
        return Path(os.environ["TORCHCF_CACHE"]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "torchcf"
    return Path.home() / ".cache" / "torchcf"


def _needed_files(name: str, split: str | None) -> list[str]:
    """Paths under the data root that loading ``name``/``split`` reads."""
    folder = DATASETS[name].folder
    # A split needs the full set (pair ids) and the other split (quirks).
    subs = [""] if split is None else list(SPLITS.values())
    return [
        "/".join(p for p in (folder, sub, f) if p)
        for sub in subs
        for f in FILES.values()
    ]


def _data_dir(root: Path, name: str) -> Path:
    """``root`` itself, or ``root/data`` when ``root`` is the abc-paper folder."""
    folder = DATASETS[name].folder
    if not (root / folder).is_dir() and (root / "data" / folder).is_dir():
        return root / "data"
    return root


def _first_missing(root: Path, files: list[str]) -> str | None:
    return next((f for f in files if not (root / f).is_file()), None)


def resolve_data_root(
    name: str,
    split: str | None = None,
    *,
    data_root: str | os.PathLike[str] | None = None,
    download: bool = True,
) -> Path:
    """The folder holding ``HDV/`` and ``AV/`` with every file ``name`` needs.

    Looks in ``data_root``, then ``$TORCHCF_DATA``, then the cache; else downloads
    the missing files into the cache (see the module doc).

    Args:
        name: a key of :data:`DATASETS`.
        split: None, "train" or "test" (a split also needs the full set and the
            other split).
        data_root: explicit data folder; when given it must hold the files.
        download: allow the download.

    Returns:
        The data root (the folder that contains ``HDV/`` and ``AV/``).

    Raises:
        DataError: the files are nowhere and cannot be downloaded, a download
            fails its checksum, or ``data_root`` lacks a file.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import resolve_data_root
        >>> from torchcf.data.writer import write_six_csv
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(pairs, Path(folder, "AV", "CAR MODEL I"))  # the full set
        ...     root = resolve_data_root("car-model-1", data_root=folder)
        ...     print(root == Path(folder))
        True
    """
    if name not in DATASETS:
        raise DataError(f"unknown dataset {name!r}: one of {', '.join(DATASETS)}")
    if split not in SPLITS:
        raise DataError(f"split must be None, 'train' or 'test', got {split!r}")
    files = _needed_files(name, split)
    if data_root is not None:
        root = _data_dir(Path(data_root).expanduser(), name)
        missing = _first_missing(root, files)
        if missing:
            raise DataError(f"data_root='{data_root}' has no file '{missing}'")
        return root

    looked = ["data_root= (not given)"]
    env = os.environ.get("TORCHCF_DATA")
    if env:
        root = _data_dir(Path(env).expanduser(), name)
        missing = _first_missing(root, files)
        if missing is None:
            return root
        logger.warning(
            "TORCHCF_DATA='%s' has no file '%s'; trying the cache", env, missing
        )
        looked.append(f"$TORCHCF_DATA='{env}' (no '{missing}')")
    else:
        looked.append("$TORCHCF_DATA (not set)")

    cache = cache_dir() / "abc-paper" / "data"
    missing_files = [f for f in files if not (cache / f).is_file()]
    if not missing_files:
        return cache
    looked.append(f"the cache '{cache}' (no '{missing_files[0]}')")
    if not download:
        reason = "the download is off (download=False)"
    else:
        try:
            for rel in missing_files:
                _download(rel, cache / rel)
            return cache
        except (OSError, http.client.HTTPException) as err:
            reason = f"the download failed ({type(err).__name__}: {err})"
    raise DataError(
        f"dataset {name!r} not found: looked in {', '.join(looked)}, and {reason}. "
        "Set TORCHCF_DATA to the folder holding HDV/ and AV/, pass data_root=, "
        "or allow the download (download=True, needs network)"
    )


@cache
def _checksums() -> dict[str, str]:
    """SHA-256 of each released file, keyed like ``data/AV/CAR MODEL I/x.csv``."""
    text = resources.files("torchcf.data").joinpath("SHA256SUMS").read_text("utf-8")
    sums = {}
    for line in text.splitlines():
        if line.strip():
            digest, path = line.split(maxsplit=1)
            sums[path.strip().removeprefix("./")] = digest.lower()
    return sums


def _fetch(url: str) -> bytes:
    """GET ``url`` (replaced in tests to work offline)."""
    with urllib.request.urlopen(url, timeout=FETCH_TIMEOUT) as response:
        return response.read()


def _download(rel: str, dest: Path) -> None:
    """Fetch ``data/<rel>``, check its SHA-256, and only then write ``dest``."""
    expected = _checksums().get(f"data/{rel}")
    if expected is None:
        raise DataError(f"no checksum for 'data/{rel}' in torchcf/data/SHA256SUMS")
    url = f"{SOURCE_URL}/{urllib.parse.quote(rel)}"
    logger.info("downloading %s", url)
    payload = _fetch(url)
    digest = hashlib.sha256(payload).hexdigest()
    if digest != expected:
        raise DataError(
            f"checksum mismatch for 'data/{rel}' downloaded from {url}: sha256 "
            f"{digest}, expected {expected}; nothing was saved"
        )
    dest.parent.mkdir(parents=True, exist_ok=True)
    # A temp file + atomic rename: an interrupted write never leaves a file
    # under the final name, which the next call would take as complete.
    fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
        os.replace(tmp, dest)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
