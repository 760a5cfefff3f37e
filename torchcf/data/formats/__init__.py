"""Readers of raw trajectory formats, each returning a
:class:`~torchcf.data.trajectory.TrajectoryTable`.

=========  ==========================================  ===========================
format     source                                      module
=========  ==========================================  ===========================
ngsim      NGSIM vehicle trajectories (feet; the        :mod:`.ngsim`
           per-site ``trajectories-*.txt`` files or
           the data.transportation.gov CSV export)
openacc    OpenACC (JRC) platoon files: per-vehicle     :mod:`.openacc`
           speed and inter-vehicle spacing; a file
           or a folder of them
csv        any long CSV, with a column mapping and      :mod:`.generic`
           units given by the user
=========  ==========================================  ===========================

:func:`read_trajectories` dispatches on the format name.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from torchcf.data.formats.generic import read_csv_table
from torchcf.data.formats.ngsim import read_ngsim
from torchcf.data.formats.openacc import read_openacc
from torchcf.data.pairset import DataError
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["FORMATS", "read_trajectories"]

#: Format name -> its reader.
FORMATS: dict[str, Callable[..., TrajectoryTable]] = {
    "ngsim": read_ngsim,
    "openacc": read_openacc,
    "csv": read_csv_table,
}


def read_trajectories(
    source: str | os.PathLike[str], format: str, **options: Any
) -> TrajectoryTable:
    """Read ``source`` with the reader of ``format``.

    Args:
        source: a file or folder in that format.
        format: one of :data:`FORMATS`.
        **options: the reader's own keyword arguments (e.g. the column mapping
            and units of the ``csv`` format).

    Raises:
        DataError: unknown format, or what the reader raises.
    """
    if format not in FORMATS:
        raise DataError(
            f"unknown trajectory format {format!r} (known: {', '.join(FORMATS)})"
        )
    return FORMATS[format](source, **options)
