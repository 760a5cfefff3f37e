"""Road networks for SUMO runs, written with SUMO's ``netconvert``.

- :func:`straight_edges`: ``n`` parallel, unconnected single-lane straight edges
  ``e0 .. e{n-1}`` of one length, each its own road (a replayed pair per edge: no
  vehicle of one edge ever sees another edge's). Lane ``i`` is ``e{i}_0``; a lane
  position is the distance [m] from the edge's start, which is SPEC's road
  position up to a shift.
- :func:`ring`: a single-lane ring of ``n`` edges ``e0 .. e{n-1}`` (chords of a
  circle, each given the length ``L / n``, so the ring is exactly ``L`` long).
- :func:`highway`: a straight multi-lane road, ``h0`` up to a lane drop and ``h1``
  after it, one lane fewer.

Every network is built without internal junction lanes (``--no-internal-links``):
a vehicle passes from one edge to the next with no junction length in between,
so road positions add up.
"""

from __future__ import annotations

import math
import os
import subprocess
from pathlib import Path

from ..system.files import atomic_write_text
from .backend import SumoError, binary

#: Spacing [m] between parallel edges (drawing only: unconnected edges never
#: interact).
EDGE_SPACING = 10.0


def lane_id(edge: int) -> str:
    """The lane of edge ``edge`` of :func:`straight_edges`."""
    return f"e{edge}_0"


def straight_edges(
    n_edges: int,
    length: float,
    out_dir: str | os.PathLike[str],
    *,
    speed: float = 100.0,
    name: str = "straight",
) -> Path:
    """``n_edges`` parallel straight edges of ``length`` [m] and speed limit
    ``speed`` [m/s], as ``out_dir/<name>.net.xml``.

    Raises:
        SumoError: bad sizes, or netconvert failed (its last message).
        SumoMissingError: SUMO is not installed.

    Examples:
        >>> import tempfile
        >>> from torchcf.sumo import straight_edges
        >>> with tempfile.TemporaryDirectory() as folder:  # doctest: +SKIP
        ...     net = straight_edges(2, length=500.0, out_dir=folder)  # runs netconvert
        ...     print(net.name)
        straight.net.xml
    """
    if n_edges < 1:
        raise SumoError(f"a network needs at least one edge, got {n_edges}")
    for what, value in (("length", length), ("speed", speed)):
        if not (math.isfinite(value) and value > 0):
            raise SumoError(f"edge {what} must be > 0, got {value}")
    nodes = [
        f'    <node id="a{i}" x="0" y="{i * EDGE_SPACING!r}"/>\n'
        f'    <node id="b{i}" x="{length!r}" y="{i * EDGE_SPACING!r}"/>'
        for i in range(n_edges)
    ]
    edges = [
        f'    <edge id="e{i}" from="a{i}" to="b{i}" numLanes="1" speed="{speed!r}" '
        f'length="{length!r}"/>'
        for i in range(n_edges)
    ]
    return _netconvert(nodes, edges, Path(out_dir), name)


def ring(
    length: float,
    out_dir: str | os.PathLike[str],
    *,
    n_edges: int = 4,
    speed: float = 30.0,
    name: str = "ring",
) -> Path:
    """A single-lane ring ``e0 -> e1 -> ... -> e{n-1} -> e0`` of ``length`` [m].

    Raises:
        SumoError: bad sizes, or netconvert failed.
    """
    if n_edges < 3:
        raise SumoError(f"a ring needs at least 3 edges, got {n_edges}")
    for what, value in (("length", length), ("speed", speed)):
        if not (math.isfinite(value) and value > 0):
            raise SumoError(f"ring {what} must be > 0, got {value}")
    radius = length / (2 * math.pi)
    nodes = [
        f'    <node id="r{k}" x="{radius * math.cos(2 * math.pi * k / n_edges)!r}" '
        f'y="{radius * math.sin(2 * math.pi * k / n_edges)!r}"/>'
        for k in range(n_edges)
    ]
    edges = [
        f'    <edge id="e{k}" from="r{k}" to="r{(k + 1) % n_edges}" numLanes="1" '
        f'speed="{speed!r}" length="{length / n_edges!r}"/>'
        for k in range(n_edges)
    ]
    return _netconvert(nodes, edges, Path(out_dir), name)


def highway(
    length: float,
    lanes: int,
    out_dir: str | os.PathLike[str],
    *,
    drop_at: float,
    speed: float = 33.33,
    name: str = "highway",
) -> Path:
    """A straight road of ``lanes`` lanes, ``h0`` on ``[0, drop_at)`` and ``h1``
    on ``[drop_at, length]`` with one lane fewer (a bottleneck).

    Raises:
        SumoError: bad sizes, or netconvert failed.
    """
    if lanes < 2:
        raise SumoError(f"a lane drop needs at least 2 lanes, got {lanes}")
    if not (0 < drop_at < length and math.isfinite(length)):
        raise SumoError(f"drop_at must lie in (0, {length}), got {drop_at}")
    nodes = [
        '    <node id="a" x="0" y="0"/>',
        f'    <node id="b" x="{drop_at!r}" y="0"/>',
        f'    <node id="c" x="{length!r}" y="0"/>',
    ]
    edges = [
        f'    <edge id="h0" from="a" to="b" numLanes="{lanes}" speed="{speed!r}" '
        f'length="{drop_at!r}"/>',
        f'    <edge id="h1" from="b" to="c" numLanes="{lanes - 1}" speed="{speed!r}" '
        f'length="{length - drop_at!r}"/>',
    ]
    return _netconvert(nodes, edges, Path(out_dir), name)


def _netconvert(nodes: list[str], edges: list[str], out: Path, name: str) -> Path:
    """Write the plain node and edge files and convert them to ``<name>.net.xml``."""
    node_file, edge_file = out / f"{name}.nod.xml", out / f"{name}.edg.xml"
    atomic_write_text(node_file, "<nodes>\n" + "\n".join(nodes) + "\n</nodes>\n")
    atomic_write_text(edge_file, "<edges>\n" + "\n".join(edges) + "\n</edges>\n")
    net = out / f"{name}.net.xml"
    done = subprocess.run(
        [
            str(binary("netconvert")),
            "--node-files",
            str(node_file),
            "--edge-files",
            str(edge_file),
            "--output-file",
            str(net),
            "--no-turnarounds",
            "true",
            "--no-internal-links",
            "true",
            "--precision",
            "6",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines() or ["no message"]
        raise SumoError(f"netconvert failed: {lines[-1]}")
    return net


__all__ = ["EDGE_SPACING", "highway", "lane_id", "ring", "straight_edges"]
