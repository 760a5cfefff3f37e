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
parameters), so a new reader is one line in :data:`FORMATS`. A reader may group
options that travel together in a settings object (``units``, a
:class:`~torchcf.data.formats.generic.TableUnits`): a keyword-only parameter
whose default is a dataclass. Its fields are the options then, by their own
names, as ``data.raw`` and ``torchcf data extract`` spell them
(``length_unit``, ``time_unit``...); :func:`read_trajectories` puts them back
into the object.
"""

from __future__ import annotations

import dataclasses
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
        **options: the reader's options (:func:`reader_options`: e.g. the
            column mapping and the units of the ``csv`` format, ``columns``,
            ``length_unit``...); a grouped option's object may be given whole
            too (``units=TableUnits(...)``).

    Raises:
        DataError: unknown format, or what the reader raises.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.data.formats import read_trajectories
        >>> lines = [  # t [s], x_lead, x_fol [m], v_lead, v_fol [m/s], L_lead [m]
        ...     f"{0.1 * k:.1f},{30.0 + 1.5 * k},{1.5 * k},15,15,5" for k in range(20)
        ... ]
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "pair.txt"
        ...     _ = path.write_text("\\n".join(lines) + "\\n")
        ...     table = read_trajectories(path, "punzo")
        >>> table.format, table.n_vehicles, len(table.frame)
        ('punzo', 2, 40)
    """
    reader = _reader(format)
    return reader(source, **_grouped(reader, options))


def reader_options(format: str) -> tuple[str, ...]:
    """The keyword options of the reader of ``format``, in signature order: its
    keyword-only parameters, a grouped one's by its fields (module docstring).

    Raises:
        DataError: unknown format.

    Examples:
        >>> from torchcf.data.formats import reader_options
        >>> reader_options("punzo")
        ('length_unit', 'speed_unit', 'time_unit', 'frame_rate', 'length_tolerance')
    """
    names: list[str] = []
    for parameter in _keyword_only(_reader(format)):
        if dataclasses.is_dataclass(parameter.default):
            names += [field.name for field in dataclasses.fields(parameter.default)]
        else:
            names.append(parameter.name)
    return tuple(names)


def _keyword_only(reader: Callable[..., TrajectoryTable]) -> list[inspect.Parameter]:
    parameters = inspect.signature(reader).parameters.values()
    return [p for p in parameters if p.kind is p.KEYWORD_ONLY]


def _grouped(
    reader: Callable[..., TrajectoryTable], options: dict[str, Any]
) -> dict[str, Any]:
    """``options`` with the fields of each of the reader's grouped options put
    into its object (over the object given, else over its default)."""
    options = dict(options)
    for parameter in _keyword_only(reader):
        default = parameter.default
        if not dataclasses.is_dataclass(default):
            continue
        names = [field.name for field in dataclasses.fields(default)]
        fields = {name: options.pop(name) for name in names if name in options}
        if fields:
            base = options.get(parameter.name, default)
            options[parameter.name] = dataclasses.replace(base, **fields)
    return options


def _reader(format: str) -> Callable[..., TrajectoryTable]:
    if format not in FORMATS:
        raise DataError(
            f"unknown trajectory format {format!r} (known: {', '.join(FORMATS)})"
        )
    return FORMATS[format]
