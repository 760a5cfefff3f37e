"""Tables of the evaluation metrics, in the form of the paper's Appendix Tables 4-6.

:func:`metrics_table` writes the six errors and distances of each model and of the
hybrid as a Markdown table, optionally next to the paper's values;
:func:`relative_difference` compares our values with the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

__all__ = [
    "METRIC_COLUMNS",
    "metrics_table",
    "plausibility_table",
    "relative_difference",
]

METRIC_COLUMNS = (
    ("e_p", "Avg position error [m]"),
    ("e_v", "Avg speed error [m/s]"),
    ("e_a", "Avg acceleration error [m/s²]"),
    ("min", "Minimum distance"),
    ("beta_ws", "0.15-WS distance"),
    ("ws", "WS distance"),
)
_HYBRID = "hybrid"
_MISSING = "–"


def _display_name(name: str) -> str:
    # The paper writes model names in capitals and the hybrid as "Hybrid".
    return "Hybrid" if name.lower() == _HYBRID else name.upper()


def _lookup(
    metrics: Mapping[str, Mapping[str, float]], name: str, key: str
) -> float | None:
    value = metrics.get(name, {}).get(key)
    return None if value is None else float(value)


def _format(value: float | None, digits: int) -> str:
    if value is None:
        return _MISSING
    # In this project a non-finite metric marks an infeasible or invalid fit.
    return f"{value:.{digits}f}" if math.isfinite(value) else "inf"


def metrics_table(
    metrics: Mapping[str, Mapping[str, float]],
    order: Sequence[str],
    *,
    paper: Mapping[str, Mapping[str, float]] | None = None,
    digits: int = 3,
) -> str:
    """Markdown table of the six metrics, one row per entry (paper Tables 4-6).

    The columns are :data:`METRIC_COLUMNS`. The ``"hybrid"`` row is bold. In each
    column the lowest finite value of ours is marked with a trailing ``*`` (all of
    them on a tie). A non-finite value prints as ``inf``, a missing entry or key as
    ``–``. With ``paper``, each cell reads ``ours / paper``. Entries with
    particles invalid on every test pair get a line under the table with WS
    and 0.15-WS over their other particles (``ws_valid``, ``beta_ws_valid``).

    Args:
        metrics: entry name -> metric key -> value (lower is better).
        order: the entries to show, in row order (the models, then ``"hybrid"``).
        paper: optional reference values with the same layout.
        digits: decimals shown.

    Returns:
        A note line, a blank line and the table, ending with a newline.
    """
    best: dict[str, float] = {}
    for key, _ in METRIC_COLUMNS:
        values = [_lookup(metrics, name, key) for name in order]
        finite = [v for v in values if v is not None and math.isfinite(v)]
        if finite:
            best[key] = min(finite)

    note = "A trailing `*` marks the lowest value of ours in each column."
    if paper is not None:
        note = "Each cell: ours / paper. " + note
    lines = [
        note,
        "",
        "| Model | " + " | ".join(label for _, label in METRIC_COLUMNS) + " |",
        "|---" * (len(METRIC_COLUMNS) + 1) + "|",
    ]
    for name in order:
        strong = "**" if name.lower() == _HYBRID else ""
        cells = [f"{strong}{_display_name(name)}{strong}"]
        for key, _ in METRIC_COLUMNS:
            ours = _lookup(metrics, name, key)
            cell = f"{strong}{_format(ours, digits)}{strong}"
            # The "*" goes after the closing "**" of a bold cell: CommonMark renders
            # "**1.0***" as a bold 1.0 followed by a literal "*".
            if ours is not None and key in best and ours == best[key]:
                cell += "*"
            if paper is not None:
                reference = _format(_lookup(paper, name, key), digits)
                cell += f" / {strong}{reference}{strong}"
            cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    dropped = _without_particles_never_valid(metrics, order, digits)
    return "\n".join(lines + (["", *dropped] if dropped else [])) + "\n"


def _without_particles_never_valid(
    metrics: Mapping[str, Mapping[str, float]], order: Sequence[str], digits: int
) -> list[str]:
    """A line per entry with particles invalid on every test pair: SPEC's WS
    and 0.15-WS are then infinite, so the same over the other particles."""
    lines = []
    for name in order:
        entry = metrics.get(name, {})
        count = int(entry.get("particles_never_valid") or 0)
        if count == 0:
            continue
        lines.append(
            f"{_display_name(name)}: {count} of {int(entry.get('n_particles', 0))} "
            "particles are invalid on every test pair, which makes WS and 0.15-WS "
            "infinite; over the other particles WS "
            f"{_format(_lookup(metrics, name, 'ws_valid'), digits)}, 0.15-WS "
            f"{_format(_lookup(metrics, name, 'beta_ws_valid'), digits)}."
        )
    return lines


def relative_difference(
    ours: Mapping[str, Mapping[str, float]], paper: Mapping[str, Mapping[str, float]]
) -> dict[str, dict[str, float]]:
    """Relative difference ``(ours - paper) / paper`` per entry and metric.

    Only pairs where both values are finite and the paper's is non-zero are kept;
    entries in both mappings appear (in the order of ``ours``), possibly empty.

    Returns:
        entry name -> metric key -> relative difference (0.1 = ours 10 % higher).
    """
    result: dict[str, dict[str, float]] = {}
    for name, our_entry in ours.items():
        if name not in paper:
            continue
        paper_entry = paper[name]
        result[name] = {}
        for key, value in our_entry.items():
            if key not in paper_entry:
                continue
            ours_value, paper_value = float(value), float(paper_entry[key])
            if math.isfinite(ours_value) and math.isfinite(paper_value) and paper_value:
                result[name][key] = (ours_value - paper_value) / paper_value
    return result


def plausibility_table(per_model: Mapping[str, Mapping[str, object]]) -> str:
    """Markdown table of the plausibility battery on the hybrid's particles.

    Args:
        per_model: model -> :meth:`torchcf.traffic.Plausibility.summary` (the
            ``plausibility`` entry of summary.json).

    Returns:
        A heading line, the battery's settings, and one row per model, ending
        with a newline; an empty string when there is nothing to show.
    """
    if not per_model:
        return ""
    settings = next(iter(per_model.values()))["settings"]
    decels = " / ".join(f"{d:g}" for d in settings["decelerations"])
    lines = [
        "## Plausibility in closed loop",
        "",
        "The hybrid's particles through the battery "
        "(`torchcf.traffic.check_plausibility`) at "
        f"{settings['speed']:.1f} m/s: the share that collide (leader braking to "
        f"a stop at {decels} m/s^2, stop-and-go, a cut-in, a standstill start), "
        "that amplify a disturbance down a platoon of their own kind, that have "
        "no equilibrium at some speed up to it, and the median least time to "
        "collision.",
        "",
        "| Model | Particles | Collided | String-unstable | No equilibrium | "
        "Median min TTC [s] |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in per_model.items():
        ttc = row.get("min_ttc_median")
        lines.append(
            f"| {_display_name(name)} | {row['n_particles']} | "
            f"{row['collided']:.1%} | {row['string_unstable']:.1%} | "
            f"{row['no_equilibrium']:.1%} | "
            f"{_MISSING if ttc is None else f'{ttc:.2f}'} |"
        )
    return "\n".join(lines) + "\n"
