"""Write extracted pairs as a six-CSV folder that ``load_pairs`` and a config read.

:func:`write_extraction` writes, into ``out``::

    Leading Position.csv ... Following Acc.csv   the full set (SI; rows = steps)
    Trajectory/  the six files of the training pairs
    Testing/     the six files of the test pairs (absent when there are none,
                 ``test_fraction=0``: the folder then has no test split)
    meta.json    {"dt", "units": "m", "leader_length", "road_frame"[, "road_period"]
                 [, "pairs": {"kind": "whole couples", "seconds": {"min",
                 "median", "max"}}]} (the last for whole couples only)
    index.csv    one row per pair of the full set: where it came from
    dropped.csv  one row per dropped window or short span: why
    extract.json the counts, the options, the notes and the command

The folder is built beside ``out`` under a temporary name and renamed into place
when complete, so an interrupted extraction never leaves a folder that looks
whole. An existing ``out`` is replaced only when it holds an earlier extraction
(its ``extract.json``) and ``overwrite=True``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from torchcf.data.extract import Extraction
from torchcf.data.pairset import DataError, PairSet
from torchcf.data.reader import FILES
from torchcf.system.errors import first_names
from torchcf.system.files import JSON, ensure_directory, write_json

__all__ = ["write_extraction", "write_record", "write_six_csv"]


def write_six_csv(pairs: PairSet, folder: str | os.PathLike[str]) -> None:
    """The six series of ``pairs`` as header-less CSVs in ``folder`` (SI units).

    Masked steps are left as empty cells, as :func:`read_six_csv` reads ragged
    columns. Values are written with 17 significant digits, so reading them back
    gives the same float64 numbers.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mask = pairs.mask.cpu().numpy()
    for field, file_name in FILES.items():
        values = getattr(pairs, field).detach().cpu().double().numpy()
        lines = []
        for row, valid in zip(values, mask, strict=True):
            lines.append(
                ",".join(
                    repr(float(v)) if ok else ""
                    for v, ok in zip(row, valid, strict=True)
                )
            )
        (folder / file_name).write_text("\n".join(lines) + "\n", encoding="utf-8")


#: What an extraction folder holds (module docstring): all that ``--overwrite``
#: may remove.
EXTRACTION_NAMES = frozenset(
    [*FILES.values(), "Trajectory", "Testing", "meta.json", "index.csv", "dropped.csv"]
    + ["extract.json"]
)


def write_extraction(
    extraction: Extraction,
    out: str | os.PathLike[str],
    *,
    record: JSON | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``extraction`` as a six-CSV folder with its index (module docstring).

    Args:
        extraction: the result of :func:`torchcf.data.extract.extract_pairs`.
        out: the folder to create.
        record: more entries for ``extract.json`` (the command, the options).
        overwrite: replace an earlier extraction in ``out``.

    Returns:
        ``out`` as a Path.

    Raises:
        DataError: ``out`` exists and is not an earlier extraction, or is one
            and ``overwrite`` is False, or holds other files beside one.
        RunFileError: the folder cannot be written.
    """
    out = Path(out)
    if out.exists():
        if not (out / "extract.json").is_file():
            if not out.is_dir() or any(out.iterdir()):
                raise DataError(
                    f"'{out}' exists and is not an extraction: choose a new --out"
                )
        elif not overwrite:
            raise DataError(
                f"'{out}' holds an earlier extraction: pass --overwrite to replace it"
            )
        else:
            others = sorted(
                p.name
                for p in out.iterdir()
                if p.name not in EXTRACTION_NAMES and not p.name.startswith(".")
            )
            if others:
                raise DataError(
                    f"'{out}' holds an extraction and other files "
                    f"({first_names(others)}): "
                    "--overwrite replaces an extraction alone; choose a new --out"
                )
    parent = ensure_directory(out.parent, "output directory")
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=parent))
    try:
        write_six_csv(extraction.pairs, staging)
        write_six_csv(extraction.train, staging / "Trajectory")
        if extraction.test is not None:
            write_six_csv(extraction.test, staging / "Testing")
        write_json(staging / "meta.json", _meta(extraction))
        write_record(extraction, staging, record)
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


def _meta(extraction: Extraction) -> JSON:
    """``meta.json``: what reading the folder needs, and for whole couples what
    the pairs are (ragged: their lengths in seconds)."""
    meta: dict = {
        "dt": extraction.dt,
        "units": "m",
        "leader_length": extraction.pairs.leader_length,
        "road_frame": extraction.road_frame,
    }
    if extraction.road_period is not None:
        meta["road_period"] = extraction.road_period
    if extraction.whole:
        meta["pairs"] = {
            "kind": extraction.summary["pairs_are"],
            "seconds": extraction.summary["pair_seconds"],
        }
    return meta


def write_record(
    extraction: Extraction,
    folder: str | os.PathLike[str],
    record: JSON | None = None,
) -> None:
    """``index.csv``, ``dropped.csv`` and ``extract.json`` of ``extraction`` in
    ``folder`` (a training run keeps them in ``<run>/data/``)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    extraction.index.to_csv(folder / "index.csv", index=False, float_format="%.6f")
    extraction.dropped.to_csv(folder / "dropped.csv", index=False, float_format="%.6f")
    write_json(
        folder / "extract.json",
        {
            **(record or {}),
            "summary": extraction.summary,
            "notes": list(extraction.notes),
        },
    )
