"""Raw source to extracted pairs in one call, shared by the CLI and the configs.

:func:`extract_source` reads a raw file or folder with its format's reader
(:mod:`torchcf.data.formats`) and cuts pairs from it (:mod:`torchcf.data.extract`).
A run reads its data several times (training, evaluation, the loop); the result
of one (source, settings) is kept for the life of the process, so they all see
the pairs of one extraction and the files are read once.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

from torchcf.data.extract import Extraction, ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.pairset import DataError
from torchcf.data.writer import write_record

__all__ = ["extract_source", "record_extraction"]

_EXTRACTED: dict[str, Extraction] = {}


def extract_source(
    source: str | os.PathLike[str],
    format: str,
    *,
    reader_options: dict[str, Any] | None = None,
    options: ExtractOptions | None = None,
) -> Extraction:
    """Read ``source`` as ``format`` and extract its pairs.

    Raises:
        DataError: a missing source, or what reading and extraction raise.
    """
    path = Path(source)
    if not path.exists():
        raise DataError(f"raw source '{source}' does not exist")
    options = options or ExtractOptions()
    key = json.dumps(
        [
            str(path.resolve()),
            format,
            reader_options or {},
            dataclasses.asdict(options),
        ],
        sort_keys=True,
        default=str,
    )
    if key not in _EXTRACTED:
        table = read_trajectories(path, format, **(reader_options or {}))
        _EXTRACTED[key] = extract_pairs(table, options)
    return _EXTRACTED[key]


def record_extraction(raw: Any, folder: str | os.PathLike[str]) -> None:
    """Write the record of a config's raw extraction (``index.csv``,
    ``dropped.csv``, ``extract.json``) into ``folder``.

    Args:
        raw: the ``data.raw`` section (:class:`torchcf.config.raw.RawSource`).
        folder: the folder, e.g. a run's ``data/``.
    """
    extraction = extract_source(
        raw.source,
        raw.format,
        reader_options=raw.reader_options(),
        options=raw.extract_options(),
    )
    write_record(extraction, folder, {"raw": raw.model_dump()})
