"""Figures of the hybrid model: per-model shares and the pairwise share table.

Every figure is a bare :class:`matplotlib.figure.Figure` with its own Agg canvas:
nothing touches ``pyplot``'s global state, so the functions are thread-safe and need
no display. :func:`figure_to_array` turns a figure into an ``(H, W, 3)`` image for
TensorBoard and :func:`save_figure` writes it as a PNG.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from torch import Tensor

__all__ = ["figure_to_array", "pairwise_figure", "save_figure", "shares_figure"]

_DPI = 100


def _new_figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=_DPI, layout="constrained")
    # Attaching the Agg canvas explicitly is what makes the figure independent of
    # the pyplot backend (and of any display).
    FigureCanvasAgg(fig)
    return fig


def shares_figure(
    shares: Mapping[str, float], title: str = "Hybrid model shares"
) -> Figure:
    """Bar chart of the hybrid model's shares, one bar per model in the given order.

    Args:
        shares: model name -> share in [0, 1].
        title: axes title.

    Returns:
        The figure (y axis fixed to [0, 1], each bar labelled with its value).
    """
    names = list(shares)
    values = [float(shares[name]) for name in names]
    fig = _new_figure(max(4.0, 0.9 * len(names) + 2.0), 3.5)
    ax = fig.add_subplot()
    bars = ax.bar(range(len(names)), values, color="tab:blue")
    ax.bar_label(bars, labels=[f"{v:.2f}" for v in values], padding=2)
    ax.set_xticks(range(len(names)), names)
    # Headroom above 1 keeps the label of a share of 1.0 inside the axes.
    ax.set_ylim(0.0, 1.08)
    ax.set_yticks(np.linspace(0.0, 1.0, 6))
    ax.set_ylabel("share")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    return fig


def pairwise_figure(
    models: Sequence[str], table: Sequence[Sequence[float]] | Tensor | np.ndarray
) -> Figure:
    """Heatmap of the pairwise share table.

    Args:
        models: the M model names, in the order of the table's rows and columns.
        table: (M, M) ``table[i][j]`` is the share of model ``i`` in the hybrid built
            from models ``{i, j}`` only; the diagonal is 1.

    Returns:
        The figure: rows ``"<m> (row)"``, columns ``"against <m>"``, each cell
        annotated with two decimals, colour scale [0, 1].
    """
    if isinstance(table, Tensor):
        table = table.detach().cpu().numpy()
    values = np.asarray(table, dtype=np.float64)  # (M, M)
    n_models = len(models)
    if values.shape != (n_models, n_models):
        raise ValueError(
            f"pairwise table has shape {values.shape}, expected "
            f"({n_models}, {n_models}) for models {list(models)}"
        )
    size = max(3.5, 0.9 * n_models + 2.5)
    fig = _new_figure(size + 1.0, size)
    ax = fig.add_subplot()
    image = ax.imshow(values, vmin=0.0, vmax=1.0, cmap="viridis")
    ticks = range(n_models)
    ax.set_xticks(ticks, [f"against {m}" for m in models], rotation=30, ha="right")
    ax.set_yticks(ticks, [f"{m} (row)" for m in models])
    for i in range(n_models):
        for j in range(n_models):
            value = values[i, j]
            # viridis is dark at the bottom of the scale: white text there, black
            # text on the light top (NaN cells are drawn blank by imshow).
            colour = "white" if not value >= 0.6 else "black"
            ax.text(j, i, f"{value:.2f}", ha="center", va="center", color=colour)
    ax.set_title("Pairwise shares (row model vs column model)")
    fig.colorbar(image, ax=ax, label="share of row model")
    return fig


def figure_to_array(fig: Figure) -> np.ndarray:
    """Render a figure with the Agg canvas.

    Returns:
        (H, W, 3) uint8 RGB image (alpha dropped).
    """
    canvas = fig.canvas
    if not isinstance(canvas, FigureCanvasAgg):
        canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())  # (H, W, 4)
    # Copy: the buffer is a view of the canvas memory, reused on the next draw.
    return np.ascontiguousarray(rgba[..., :3])


def save_figure(fig: Figure, path: str | os.PathLike[str]) -> None:
    """Write the figure as a PNG atomically.

    The image goes to a temporary file in the destination folder, which then replaces
    ``path`` in one rename, so a reader never sees a half-written file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
    )
    try:
        with os.fdopen(fd, "wb") as fh:
            fig.savefig(fh, format="png", dpi=_DPI)
        # mkstemp creates the file as 0600; give the PNG ordinary permissions.
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
