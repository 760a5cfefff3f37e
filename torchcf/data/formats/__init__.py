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
pairs      pair-wide CSV, one row per time step of a    :mod:`.pairs`
           leader-follower couple; ULTra-AV's column
           names by default, a column mapping over them
punzo      Punzo et al.'s six-column files (t, x_lead,  :mod:`.punzo`
           x_fol, v_lead, v_fol, L_lead), one pair per
           file; a file or a folder of them
highd      highD drone recordings (XX_tracks.csv,       :mod:`.highd`
           XX_tracksMeta.csv, XX_recordingMeta.csv); a
           folder of recordings or one file of one
gps        GPS logs: time, latitude, longitude (and     :mod:`.gps`
           speed) per vehicle, one file per car or a
           long table, put on one road path
=========  ==========================================  ===========================

:func:`read_trajectories` dispatches on the format name; :func:`reader_options`
names the keyword options a format's reader takes (its signature's keyword-only
parameters), so a new reader is one line in :data:`FORMATS`.
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from typing import Any

from torchcf.data.formats.generic import read_csv_table
from torchcf.data.formats.gps import read_gps
from torchcf.data.formats.highd import read_highd
from torchcf.data.formats.ngsim import read_ngsim
from torchcf.data.formats.openacc import read_openacc
from torchcf.data.formats.pairs import read_pairs
from torchcf.data.formats.punzo import read_punzo
from torchcf.data.pairset import DataError
from torchcf.data.trajectory import TrajectoryTable

__all__ = ["FORMATS", "read_trajectories", "reader_options"]

#: Format name -> its reader.
FORMATS: dict[str, Callable[..., TrajectoryTable]] = {
    "ngsim": read_ngsim,
    "openacc": read_openacc,
    "csv": read_csv_table,
    "pairs": read_pairs,
    "punzo": read_punzo,
    "highd": read_highd,
    "gps": read_gps,
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
    return _reader(format)(source, **options)


def reader_options(format: str) -> tuple[str, ...]:
    """The keyword options of the reader of ``format``, in signature order.

    Raises:
        DataError: unknown format.
    """
    parameters = inspect.signature(_reader(format)).parameters.values()
    return tuple(p.name for p in parameters if p.kind is p.KEYWORD_ONLY)


def _reader(format: str) -> Callable[..., TrajectoryTable]:
    if format not in FORMATS:
        raise DataError(
            f"unknown trajectory format {format!r} (known: {', '.join(FORMATS)})"
        )
    return FORMATS[format]
