"""Figures of the hybrid model: shares, pairwise shares, radar charts, error evolution.

:func:`shares_figure` and :func:`pairwise_figure` show the learned hybrid (paper
Fig. 3), :func:`error_evolution_figure` the position error of the particles on one test
pair (Fig. 4) and :func:`radar_figure` the six normalised metrics per model (Figs. 5-6).

Every figure is a bare :class:`matplotlib.figure.Figure` with its own Agg canvas:
nothing touches ``pyplot``'s global state, so the functions are thread-safe and need
no display. :func:`figure_to_array` turns a figure into an ``(H, W, 3)`` image for
TensorBoard and :func:`save_figure` writes it as a PNG.
"""

from __future__ import annotations

import math
import os
import tempfile
import textwrap
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib import image as mpl_image
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from torch import Tensor

__all__ = [
    "RADAR_KEYS",
    "RADAR_LABELS",
    "before_after_figure",
    "calibration_figure",
    "effects_figure",
    "loop_figures",
    "residuals_figure",
    "error_evolution_figure",
    "figure_to_array",
    "hybrid_images",
    "pairwise_figure",
    "radar_area_share",
    "radar_figure",
    "radar_values",
    "save_figure",
    "save_image",
    "shares_figure",
]

_DPI = 100

RADAR_KEYS = ("e_p", "e_v", "e_a", "min", "beta_ws", "ws")
RADAR_LABELS = (
    "avg position error",
    "avg speed error",
    "avg acceleration error",
    "minimum distance",
    "0.15-WS",
    "WS",
)
_HYBRID = "hybrid"
_RADAR_COLUMNS = 3
# Above this many particles the individual error lines are replaced by a min-max band:
# hundreds of overlapping lines are slow to draw and read as one grey blob anyway.
_MAX_PARTICLE_LINES = 200
# The paper's red/blue/green/purple first; no grey, which is taken by "all particles".
_BEST_COLOURS = (
    "tab:red",
    "tab:blue",
    "tab:green",
    "tab:purple",
    "tab:orange",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
)


def _new_figure(width: float, height: float, constrained: bool = True) -> Figure:
    """An Agg figure; ``constrained=False`` leaves the margins to the caller
    (``subplots_adjust``): the constrained layout pass is most of a simple
    figure's draw (0.1-0.2 s of the evaluation's figures)."""
    fig = Figure(
        figsize=(width, height),
        dpi=_DPI,
        layout="constrained" if constrained else None,
    )
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

    Examples:
        >>> from torchcf.evaluation.plots import shares_figure
        >>> fig = shares_figure({"idm": 0.75, "ovm": 0.25})
        >>> low, high = fig.axes[0].get_ylim()
        >>> [ax.get_title() for ax in fig.axes], float(low), float(high)
        (['Hybrid model shares'], 0.0, 1.08)
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

    Examples:
        >>> from torchcf.evaluation.plots import pairwise_figure
        >>> fig = pairwise_figure(["idm", "ovm"], [[1.0, 0.7], [0.3, 1.0]])
        >>> [label.get_text() for label in fig.axes[0].get_yticklabels()]
        ['idm (row)', 'ovm (row)']
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


def _is_hybrid(name: str) -> bool:
    return name.lower() == _HYBRID


def _float_or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def radar_values(
    metrics: Mapping[str, Mapping[str, float]], keys: Sequence[str] = RADAR_KEYS
) -> dict[str, list[float]]:
    """Normalise each metric linearly across the entries to [0, 1], 1 = best.

    For metric ``k`` with finite values ranging over ``[lo, hi]`` across the entries,
    entry ``e`` scores ``(hi - v) / (hi - lo)``: the lowest error gets 1 and the
    highest 0. When all finite values are equal (or only one is finite) they all get 1.
    A non-finite value (``inf`` marks an infeasible or invalid fit) or a missing key
    counts as the worst, 0, and takes no part in ``lo`` and ``hi``.

    Args:
        metrics: entry name -> metric name -> value (lower is better).
        keys: the metrics to normalise, in vertex order.

    Returns:
        entry name -> one value in [0, 1] per key, entries in the order of ``metrics``.

    Examples:
        >>> from torchcf.evaluation.plots import radar_values
        >>> idm, hybrid = {"min": 0.5, "ws": 1.0}, {"min": 0.5, "ws": 0.5}
        >>> metrics = {"idm": idm, "hybrid": hybrid}
        >>> radar_values(metrics, keys=("min", "ws"))  # 1: best, 0: worst
        {'idm': [1.0, 0.0], 'hybrid': [1.0, 1.0]}
    """
    names = list(metrics)
    # (len(names), len(keys)) raw values; a missing key (or None) reads as NaN:
    # "not finite".
    raw = np.array(
        [[_float_or_nan(metrics[name].get(key)) for key in keys] for name in names],
        dtype=np.float64,
    ).reshape(len(names), len(keys))
    finite = np.isfinite(raw)
    normalised = np.zeros_like(raw)
    for j in range(len(keys)):
        column = raw[finite[:, j], j]
        if column.size == 0:
            continue
        lo, hi = column.min(), column.max()
        span = hi - lo
        scaled = (hi - raw[:, j]) / span if span > 0 else np.ones(len(names))
        normalised[:, j] = np.where(finite[:, j], scaled, 0.0)
    return {name: normalised[i].tolist() for i, name in enumerate(names)}


def radar_area_share(values: Sequence[float]) -> float:
    """Area of the radar polygon over the area of the unit polygon, in [0, 1].

    With ``n`` vertices at equal angles, the polygon of radii ``r_i`` has area
    ``sin(2 pi / n) / 2 * sum_i r_i r_{i+1}`` (cyclic) and the unit polygon
    ``sin(2 pi / n) / 2 * n``, so the share is ``sum_i r_i r_{i+1} / n``.

    Examples:
        >>> from torchcf.evaluation.plots import radar_area_share
        >>> radar_area_share([1.0] * 6), radar_area_share([1.0, 0.5] * 3)
        (1.0, 0.5)
    """
    radii = np.asarray(values, dtype=np.float64)
    if radii.ndim != 1 or radii.size < 3:
        raise ValueError(f"a radar polygon needs at least 3 values, got {radii.shape}")
    return float(np.sum(radii * np.roll(radii, -1)) / radii.size)


def radar_figure(
    metrics: Mapping[str, Mapping[str, float]],
    keys: Sequence[str] = RADAR_KEYS,
    labels: Sequence[str] = RADAR_LABELS,
    title: str | None = None,
) -> Figure:
    """Small-multiple radar (hexagon) charts of the normalised metrics (Figs. 5-6).

    One panel per entry of ``metrics`` in its order, three per row. Each vertex is one
    metric normalised by :func:`radar_values` (1 = best at the outline, 0 = worst at
    the centre), so a larger shaded area is a better model. The ``"hybrid"`` entry is
    drawn in a distinct colour. Each panel's title gives the entry name and its
    ``overall`` score, the area share of :func:`radar_area_share`.

    Args:
        metrics: entry name -> metric name -> value (lower is better; ``inf`` =
            infeasible or invalid), e.g. the eight models and ``"hybrid"``.
        keys: the metrics, one vertex each, clockwise from the top.
        labels: vertex labels, one per key.
        title: optional figure title.

    Returns:
        The figure.

    Examples:
        >>> from torchcf.evaluation.plots import radar_figure
        >>> idm = dict(e_p=1.0, e_v=0.2, e_a=0.3, min=0.8, beta_ws=0.9, ws=1.0)
        >>> hybrid = dict(e_p=0.8, e_v=0.2, e_a=0.2, min=0.7, beta_ws=0.8, ws=0.9)
        >>> fig = radar_figure({"idm": idm, "hybrid": hybrid})
        >>> [ax.get_title() for ax in fig.axes]  # one panel each, its area share
        ['idm  (overall 0.00)', 'hybrid  (overall 1.00)']
    """
    if not metrics:
        raise ValueError("radar_figure needs at least one entry")
    if len(labels) != len(keys):
        raise ValueError(f"{len(labels)} labels for {len(keys)} keys")
    if len(keys) < 3:
        raise ValueError(f"a radar chart needs at least 3 metrics, got {len(keys)}")
    values = radar_values(metrics, keys)
    n_entries = len(values)
    n_cols = min(_RADAR_COLUMNS, n_entries)
    n_rows = math.ceil(n_entries / n_cols)
    height = 3.0 * n_rows + (0.3 if title else 0.0)
    fig = _new_figure(3.0 * n_cols, height, constrained=False)
    axes = fig.subplots(n_rows, n_cols, squeeze=False)
    # The panels hide their axes and fix their limits: fixed margins suffice.
    top = 1.0 - (0.55 if title else 0.25) / height
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=top, wspace=0.02)

    # Vertices clockwise from the top; the last vertex repeats the first to close.
    n_keys = len(keys)
    angles = np.pi / 2 - 2 * np.pi * np.arange(n_keys + 1) / n_keys  # (n_keys + 1,)
    cos, sin = np.cos(angles), np.sin(angles)
    wrapped = ["\n".join(textwrap.wrap(label, 12)) for label in labels]
    for ax, (name, radii) in zip(axes.flat, values.items(), strict=False):
        colour = "tab:blue" if _is_hybrid(name) else "tab:orange"
        for level in (0.25, 0.5, 0.75):
            ax.plot(level * cos, level * sin, color="0.85", lw=0.6)
        for k in range(n_keys):
            ax.plot([0.0, cos[k]], [0.0, sin[k]], color="0.85", lw=0.6)
        ax.plot(cos, sin, color="0.3", lw=1.0)
        closed = np.append(radii, radii[0])  # (n_keys + 1,)
        ax.fill(closed * cos, closed * sin, color=colour, alpha=0.45, lw=0)
        ax.plot(closed * cos, closed * sin, color=colour, lw=1.2)
        for k in range(n_keys):
            # Labels sit outside the outline, anchored on the side facing the centre.
            x, y = 1.12 * cos[k], 1.12 * sin[k]
            ha = "center" if abs(x) < 1e-6 else ("left" if x > 0 else "right")
            va = "center" if abs(y) < 0.5 else ("bottom" if y > 0 else "top")
            ax.text(x, y, wrapped[k], ha=ha, va=va, fontsize=6.5, color="0.25")
        share = radar_area_share(radii)
        ax.set_title(
            f"{name}  (overall {share:.2f})",
            fontsize=9,
            fontweight="bold" if _is_hybrid(name) else "normal",
            color=colour if _is_hybrid(name) else "black",
        )
        ax.set_xlim(-1.75, 1.75)
        ax.set_ylim(-1.45, 1.45)
        ax.set_aspect("equal")
        ax.axis("off")
    for ax in axes.flat[n_entries:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig


def _as_array(values: np.ndarray | Tensor | Sequence[float]) -> np.ndarray:
    if isinstance(values, Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)


def calibration_figure(
    curves: Mapping[str, Mapping[str, Sequence[float]]],
    variables: Sequence[str] = ("spacing", "speed"),
) -> Figure:
    """Calibration curves of the predictive bands: nominal level against the
    observed fraction of points inside, one panel per variable, one line per
    learned set (the hybrid bold black), the diagonal dashed.

    Args:
        curves: set -> ``{"levels": (L,), <variable>: (L,) observed fractions}``.
        variables: the panels.

    Examples:
        >>> from torchcf.evaluation.plots import calibration_figure
        >>> curve = {"levels": [0.5, 0.9], "spacing": [0.4, 0.85], "speed": [0.5, 0.9]}
        >>> fig = calibration_figure({"hybrid": curve})
        >>> [ax.get_xlabel() != "" for ax in fig.axes], len(fig.axes)
        ([True, True], 2)
    """
    # Fixed margins, no constrained layout: the layout pass is most of the draw.
    fig = Figure(figsize=(4.2 * len(variables) + 1.8, 4.2), dpi=_DPI)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(variables), squeeze=False)[0]
    fig.subplots_adjust(left=0.07, right=0.86, bottom=0.13, top=0.92, wspace=0.3)
    for ax, variable in zip(axes, variables, strict=True):
        ax.plot([0, 1], [0, 1], ls="--", color="grey", lw=1, label="calibrated")
        for k, (name, curve) in enumerate(curves.items()):
            hybrid = _is_hybrid(name)
            ax.plot(
                curve["levels"],
                curve[variable],
                marker="o",
                ms=3,
                lw=2.5 if hybrid else 1.2,
                color="black" if hybrid else _BEST_COLOURS[k % len(_BEST_COLOURS)],
                label="Hybrid" if hybrid else name.upper(),
                zorder=3 if hybrid else 2,
            )
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xlabel("nominal level of the central band")
        ax.set_ylabel("observed points inside")
        ax.set_title(f"Predictive coverage: {variable}")
        ax.grid(alpha=0.3)
    axes[-1].legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=8)
    return fig


def error_evolution_figure(
    time: np.ndarray | Tensor,
    errors: np.ndarray | Tensor,
    scores: np.ndarray | Tensor,
    best_fraction: float = 0.05,
    title: str | None = None,
    ylabel: str = "position error [m]",
) -> Figure:
    """Error evolution of all particles on one test pair (paper Fig. 4).

    All particles are drawn as thin light-grey lines, or as a min-max band when there
    are more than 200 of them, with their median; the best ``best_fraction`` of the
    particles by score are drawn on top in colour. NaN errors (invalid or padded steps)
    leave gaps.

    Args:
        time: (T,) time [s].
        errors: (P, T) simulated minus observed follower position [m] (or any error
            named by ``ylabel``), NaN where not defined.
        scores: (P,) particle scores, lower is better (NaN sorts last).
        best_fraction: share of particles highlighted, in (0, 1]; at least one.
        title: optional axes title.
        ylabel: y axis label.

    Returns:
        The figure.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.plots import error_evolution_figure
        >>> time = np.arange(5) * 0.1  # (T,) [s]
        >>> errors = np.array([[0.0, 0.1, 0.2, 0.3, 0.4]] * 3)  # (P, T) [m]
        >>> scores = np.array([0.3, 0.1, 0.2])  # (P,)
        >>> fig = error_evolution_figure(time, errors, scores)
        >>> fig.axes[0].get_ylabel()
        'position error [m]'
    """
    time = _as_array(time)
    errors = _as_array(errors)
    scores = _as_array(scores)
    if time.ndim != 1 or errors.ndim != 2 or errors.shape[1] != time.shape[0]:
        raise ValueError(
            f"errors must be (P, T) with T = len(time) = {time.shape}, "
            f"got {errors.shape}"
        )
    n_particles = errors.shape[0]
    if n_particles == 0:
        raise ValueError("error_evolution_figure needs at least one particle")
    if scores.shape != (n_particles,):
        raise ValueError(f"scores must be ({n_particles},), got {scores.shape}")
    if not 0.0 < best_fraction <= 1.0:
        raise ValueError(f"best_fraction must be in (0, 1], got {best_fraction}")
    n_best = min(n_particles, max(1, round(best_fraction * n_particles)))
    # Stable argsort puts NaN scores last, so invalid particles are never "best".
    best = np.argsort(scores, kind="stable")[:n_best]

    fig = _new_figure(7.0, 4.0, constrained=False)
    ax = fig.add_subplot()
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.12, top=0.92 if title else 0.97)
    all_label = f"all particles (n={n_particles})"
    if n_particles > _MAX_PARTICLE_LINES:
        finite = np.isfinite(errors)
        lower = np.where(finite, errors, np.inf).min(axis=0)  # (T,)
        upper = np.where(finite, errors, -np.inf).max(axis=0)  # (T,)
        # Steps with no finite error are gaps, not an infinite band.
        lower[~finite.any(axis=0)] = np.nan
        upper[~finite.any(axis=0)] = np.nan
        ax.fill_between(time, lower, upper, color="0.85", lw=0, label=all_label)
    else:
        lines = ax.plot(time, errors.T, color="0.75", lw=0.5, alpha=0.8)
        lines[0].set_label(all_label)
    with warnings.catch_warnings():
        # nanmedian warns on steps where every particle is NaN; those stay gaps.
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(errors, axis=0)  # (T,)
    # Above the coloured lines: with many particles the best ones hide the median.
    ax.plot(time, median, color="0.2", lw=1.2, ls="--", label="median (all)", zorder=3)
    colours = [_BEST_COLOURS[i % len(_BEST_COLOURS)] for i in range(n_best)]
    for rank, (index, colour) in enumerate(zip(best, colours, strict=True)):
        label = f"best {best_fraction * 100:g} % (n={n_best})" if rank == 0 else None
        ax.plot(time, errors[index], color=colour, lw=1.0, label=label)
    ax.axhline(0.0, color="black", lw=0.6)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return fig


# ----------------------------------------------------------- closing the loop
def effects_figure(ranked: Sequence[Mapping[str, object]]) -> Figure:
    """Out-of-sample gain of every candidate effect; chosen/significant in colour.

    Args:
        ranked: rows with ``effect``, ``gain`` (relative drop [1]), ``p_value`` and
            ``significant`` (``torchcf.diagnose.attribute_effects``).

    Examples:
        >>> from torchcf.evaluation.plots import effects_figure
        >>> ranked = [
        ...     {"effect": "delay", "gain": 0.1, "p_value": 0.01, "significant": True},
        ...     {"effect": "lag", "gain": 0.01, "p_value": 0.4, "significant": False},
        ... ]
        >>> fig = effects_figure(ranked)
        >>> [label.get_text() for label in fig.axes[0].get_xticklabels()]
        ['delay', 'lag']
    """
    labels = [str(r["effect"]) for r in ranked]
    gains = [100.0 * float(r["gain"]) for r in ranked]
    colours = ["tab:green" if r["significant"] else "tab:gray" for r in ranked]
    fig = _new_figure(max(4.5, 0.9 * len(labels) + 2.0), 3.6)
    ax = fig.add_subplot()
    bars = ax.bar(range(len(labels)), gains, color=colours)
    ax.bar_label(
        bars,
        labels=[f"p={float(r['p_value']):.2g}" for r in ranked],
        padding=2,
        fontsize=7,
    )
    ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right")
    ax.set_ylabel("out-of-sample score drop [%]")
    ax.set_title("Candidate effects (green: significant)")
    ax.grid(axis="y", alpha=0.3)
    return fig


def before_after_figure(
    before: Mapping[str, float | None], after: Mapping[str, float | None]
) -> Figure:
    """Test-split metrics of the hybrid before and after the loop, side by side.

    Examples:
        >>> from torchcf.evaluation.plots import before_after_figure
        >>> fig = before_after_figure({"min": 1.0, "ws": 2.0}, {"min": 0.8, "ws": 1.5})
        >>> [label.get_text() for label in fig.axes[0].get_xticklabels()]
        ['minimum distance', 'WS']
    """
    keys = [k for k in RADAR_KEYS if k in before]
    fig = _new_figure(max(5.0, 1.1 * len(keys) + 1.5), 3.4)
    ax = fig.add_subplot()
    x = np.arange(len(keys))
    for offset, (label, metrics, colour) in zip(
        (-0.2, 0.2),
        (("before", before, "tab:gray"), ("after", after, "tab:blue")),
        strict=True,
    ):
        values = np.array([_float_or_nan(metrics.get(k)) for k in keys])
        # An infinite metric (a particle invalid on every test pair, SPEC) has no
        # bar height; it is drawn as a marked gap so the figure does not lie.
        infinite = np.isinf(values)
        values[infinite] = math.nan
        ax.bar(x + offset, values, width=0.4, label=label, color=colour)
        for xi in x[infinite]:
            ax.annotate("inf", (xi + offset, 0.0), ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [RADAR_LABELS[RADAR_KEYS.index(k)] for k in keys], fontsize=8)
    ax.set_xlim(-0.6, len(keys) - 0.4)  # NaN bars do not widen the axis
    ax.set_title("Hybrid on the test split")
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    return fig


def residuals_figure(
    before: Sequence[np.ndarray],
    after: Sequence[np.ndarray] | None,
    dt: float,
    n_pairs: int = 3,
    unit: str = "m",
) -> Figure:
    """Residual series of the first ``n_pairs`` pairs, before (and after) the loop.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.plots import residuals_figure
        >>> before = [np.zeros(10), np.ones(10)]  # per pair, spacing residual [m]
        >>> fig = residuals_figure(before, after=None, dt=0.1)
        >>> len(fig.axes), fig.axes[-1].get_xlabel()
        (2, 'time [s]')
    """
    shown = min(n_pairs, len(before))
    fig = _new_figure(7.0, 1.9 * max(shown, 1) + 0.6)
    for i in range(shown):
        ax = fig.add_subplot(shown, 1, i + 1)
        t = np.arange(len(before[i])) * dt
        ax.plot(t, before[i], color="tab:gray", linewidth=1.0, label="before")
        if after is not None and i < len(after):
            t_after = np.arange(len(after[i])) * dt
            ax.plot(t_after, after[i], color="tab:blue", linewidth=1.0, label="after")
        ax.axhline(0.0, color="black", linewidth=0.6)
        ax.set_ylabel(f"residual [{unit}]")
        if i == 0:
            ax.legend(fontsize=8)
            ax.set_title("Spacing residual (observed - simulated), training pairs")
    if fig.axes:
        fig.axes[-1].set_xlabel("time [s]")
    return fig


def loop_figures(
    result: Mapping[str, object],
    series_before: Mapping[str, Sequence[np.ndarray]],
    series_after: Mapping[str, Sequence[np.ndarray]] | None,
    dt: float,
) -> dict[str, Figure]:
    """The figures of ``loop.md``: effects, before_after, residuals.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.plots import loop_figures
        >>> delay = dict(effect="delay", gain=0.1, p_value=0.01, significant=True)
        >>> result = {"effects_ranked": [delay], "before": {"min": 1.0}}
        >>> result["after"] = {"min": 0.8}
        >>> figures = loop_figures(result, {"spacing": [np.zeros(10)]}, None, dt=0.1)
        >>> sorted(figures)
        ['before_after', 'effects', 'residuals']
    """
    return {
        "effects": effects_figure(result["effects_ranked"]),
        "before_after": before_after_figure(result["before"], result["after"]),
        "residuals": residuals_figure(
            series_before["spacing"],
            series_after["spacing"] if series_after is not None else None,
            dt,
        ),
    }


def hybrid_images(
    shares: Mapping[str, float],
    pairwise_models: Sequence[str],
    pairwise_table: Sequence[Sequence[float]] | Tensor | np.ndarray,
) -> dict[str, np.ndarray]:
    """The training's figures, rendered once: ``"shares"`` (:func:`shares_figure`)
    and ``"pairwise"`` (:func:`pairwise_figure`), each ``(H, W, 3)`` uint8, for
    the report's PNGs and TensorBoard alike.

    Examples:
        >>> from torchcf.evaluation.plots import hybrid_images
        >>> images = hybrid_images(
        ...     {"idm": 0.75, "ovm": 0.25}, ["idm", "ovm"], [[1.0, 0.7], [0.3, 1.0]]
        ... )
        >>> {name: image.shape[2] for name, image in images.items()}  # (H, W, 3) RGB
        {'shares': 3, 'pairwise': 3}
    """
    return {
        "shares": figure_to_array(shares_figure(shares)),
        "pairwise": figure_to_array(pairwise_figure(pairwise_models, pairwise_table)),
    }


def figure_to_array(fig: Figure) -> np.ndarray:
    """Render a figure with the Agg canvas.

    Returns:
        (H, W, 3) uint8 RGB image (alpha dropped).

    Examples:
        >>> from torchcf.evaluation.plots import figure_to_array, shares_figure
        >>> image = figure_to_array(shares_figure({"idm": 1.0}))  # 4 x 3.5 in, 100 dpi
        >>> image.shape, image.dtype
        ((350, 400, 3), dtype('uint8'))
    """
    canvas = fig.canvas
    if not isinstance(canvas, FigureCanvasAgg):
        canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())  # (H, W, 4)
    # Copy: the buffer is a view of the canvas memory, reused on the next draw.
    return np.ascontiguousarray(rgba[..., :3])


def save_figure(fig: Figure, path: str | os.PathLike[str]) -> None:
    """Write the figure as a PNG atomically (see :func:`save_image`).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.evaluation.plots import save_figure, shares_figure
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     save_figure(shares_figure({"idm": 1.0}), Path(folder) / "shares.png")
        ...     print(sorted(p.name for p in Path(folder).iterdir()))
        ['shares.png']
    """
    save_image(figure_to_array(fig), path)


def save_image(image: np.ndarray, path: str | os.PathLike[str]) -> None:
    """Write an ``(H, W, 3)`` uint8 image (:func:`figure_to_array`) as a PNG
    atomically.

    A figure rendered once serves both the PNG and TensorBoard: the Agg draw is
    most of a figure's cost, and ``savefig`` would draw it again. The image goes
    to a temporary file in the destination folder, which then replaces ``path``
    in one rename, so a reader never sees a half-written file.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np
        >>> from torchcf.evaluation.plots import save_image
        >>> image = np.zeros((4, 6, 3), dtype=np.uint8)  # (H, W, 3)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     save_image(image, Path(folder) / "figures" / "black.png")
        ...     print((Path(folder) / "figures" / "black.png").is_file())
        True
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
    )
    try:
        with os.fdopen(fd, "wb") as fh:
            mpl_image.imsave(fh, image, format="png", dpi=_DPI)
        # mkstemp creates the file as 0600; give the PNG ordinary permissions.
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
