"""SUMO's floating car data (``--fcd-output``) read back into tensors.

SUMO writes, at every step, one ``<vehicle>`` per vehicle in the network with its
lane position ``pos`` [m], ``speed`` [m/s] and, with
``--fcd-output.acceleration``, ``acceleration`` [m/s^2]: ``(v(t) - v(t - dt)) /
dt``, the step that *led to* t. Positions keep ``--precision`` digits after the
comma (torchcf's runs ask for 9: 1e-9 m).
"""

from __future__ import annotations

import math
import os
import sys
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor
from tqdm import tqdm

from ..system.console import bar_interval
from .backend import SumoError

#: The options torchcf adds to a SUMO run whose FCD it reads back.
FCD_OPTIONS = ("--fcd-output.acceleration", "true", "--precision", "9")


class Fcd(NamedTuple):
    """The FCD of chosen vehicles on a time grid, ``(T, V)`` float64 each.

    Attributes:
        time: ``(T,)`` simulation time [s] of each row.
        pos: lane position [m]; NaN where the vehicle is not in the network.
        speed: [m/s]; NaN where absent.
        acceleration: [m/s^2]; NaN where absent.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.sumo import read_fcd
        >>> xml = (  # SUMO's --fcd-output: F0 at two steps
        ...     '<fcd-export><timestep time="0.00">'
        ...     '<vehicle id="F0" pos="10.0" speed="20.0" acceleration="0.0"/>'
        ...     '</timestep><timestep time="0.10">'
        ...     '<vehicle id="F0" pos="12.0" speed="20.1" acceleration="1.0"/>'
        ...     "</timestep></fcd-export>"
        ... )
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "fcd.xml"
        ...     _ = path.write_text(xml)
        ...     fcd = read_fcd(path, ["F0", "F1"], begin=0.0, dt=0.1, n_steps=2)
        >>> fcd.pos.shape, fcd.time.tolist()  # (T, V), [s]
        (torch.Size([2, 2]), [0.0, 0.1])
    """

    time: Tensor
    pos: Tensor
    speed: Tensor
    acceleration: Tensor


def read_fcd(
    path: str | os.PathLike[str],
    vehicles: Sequence[str],
    *,
    begin: float,
    dt: float,
    n_steps: int,
    progress: str | None = None,
) -> Fcd:
    """The rows ``begin + k dt``, ``k = 0 .. n_steps - 1``, of ``vehicles``.

    Args:
        path: SUMO's FCD file.
        vehicles: the vehicle ids (column order).
        begin: the time of the first row [s].
        dt: the step [s].
        n_steps: rows.
        progress: the label of a progress bar over the file's time steps on
            stderr (None: none): a big replay's file takes tens of seconds.

    Raises:
        SumoError: the file cannot be read or parsed.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.sumo import read_fcd
        >>> xml = (  # SUMO's --fcd-output: F0 at two steps
        ...     '<fcd-export><timestep time="0.00">'
        ...     '<vehicle id="F0" pos="10.0" speed="20.0" acceleration="0.0"/>'
        ...     '</timestep><timestep time="0.10">'
        ...     '<vehicle id="F0" pos="12.0" speed="20.1" acceleration="1.0"/>'
        ...     "</timestep></fcd-export>"
        ... )
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "fcd.xml"
        ...     _ = path.write_text(xml)
        ...     fcd = read_fcd(path, ["F0", "F1"], begin=0.0, dt=0.1, n_steps=2)
        >>> fcd.pos[:, 0].tolist(), fcd.speed[:, 0].tolist()  # F0 [m], [m/s]
        ([10.0, 12.0], [20.0, 20.1])
        >>> fcd.pos[:, 1].isnan().all().item()  # F1 never in the network
        True
    """
    column = {vid: i for i, vid in enumerate(vehicles)}
    shape = (n_steps, len(vehicles))
    out = {k: torch.full(shape, math.nan, dtype=torch.float64) for k in Fcd._fields[1:]}
    pos, speed, acc = (out[k].numpy() for k in ("pos", "speed", "acceleration"))
    row = -1
    bar = tqdm(
        total=n_steps, desc=progress, unit="step", file=sys.stderr,
        mininterval=bar_interval(), disable=progress is None,
    )  # fmt: skip
    try:
        for event, element in ET.iterparse(os.fspath(path), events=("start", "end")):
            if event == "start":
                if element.tag == "timestep":
                    row = round((float(element.get("time")) - begin) / dt)
                continue
            if element.tag == "vehicle":
                j = column.get(element.get("id"))
                if j is not None and 0 <= row < n_steps:
                    pos[row, j] = float(element.get("pos"))
                    speed[row, j] = float(element.get("speed"))
                    acc[row, j] = float(element.get("acceleration", "nan"))
            elif element.tag == "timestep":
                element.clear()
                bar.update(1)
    except (ET.ParseError, OSError, TypeError, ValueError) as error:
        raise SumoError(f"{path}: unreadable FCD output ({error})") from None
    finally:
        bar.close()
    return Fcd(torch.arange(n_steps, dtype=torch.float64) * dt + begin, **out)


__all__ = ["FCD_OPTIONS", "Fcd", "read_fcd"]
