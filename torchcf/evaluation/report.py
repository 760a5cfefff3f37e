"""Tables of the evaluation metrics, in the form of the paper's Appendix Tables 4-6.

:func:`metrics_table` writes the six errors and distances of each model and of the
hybrid as a Markdown table, optionally next to the paper's values;
:func:`relative_difference` compares our values with the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from ..runs.metrics import BootstrapSettings, Difference, ShareInterval
from ..runs.summary import PlausibilitySummary

__all__ = [
    "INTERVAL_COLUMNS",
    "METRIC_COLUMNS",
    "coverage_table",
    "differences_table",
    "intervals_table",
    "metrics_table",
    "plausibility_table",
    "relative_difference",
    "shares_interval_table",
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


#: What the metric table's columns are and why the hybrid is judged by the
#: distances (SPEC section 6), under every metric table of a report.
METRIC_NOTES = (
    "What the columns are (SPEC section 6, `docs/evaluation.md`): every particle "
    "is simulated on every test pair and scored as in training (the weighted RMSE "
    "of position, speed and acceleration). *Avg ... error*: the mean error over "
    "all (particle, test pair) cells; a particle fitted to one driver is charged "
    "on every other driver too, so a set whose particles fit different drivers "
    "(the hybrid, a mixture of models) scores badly here by construction. "
    "*Minimum distance*: the mean over test pairs of the best particle's score "
    "(can some particle reproduce each driver?). *WS distance*: the exact "
    "Wasserstein distance between the particles (weight 1/n each) and the test "
    "pairs (1/n_test each): the least cost of matching the whole set to the "
    "drivers, no particle left idle (does the set reproduce the drivers' "
    "spread?). *0.15-WS distance*: the same with each particle held to at least "
    "15 % of its weight (beta = 0.15), between the two. The hybrid is a "
    "distribution over drivers, so it is judged by the distances; the average "
    "errors are kept for comparison with the paper's tables."
)


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


def plausibility_table(per_model: Mapping[str, PlausibilitySummary]) -> str:
    """Markdown table of the plausibility battery on the hybrid's particles.

    Args:
        per_model: model -> its particles' record
            (:meth:`torchcf.traffic.battery.Plausibility.summary`; the
            ``plausibility`` of the run's summary).

    Returns:
        A heading line, the battery's settings, and one row per model, ending
        with a newline; an empty string when there is nothing to show.
    """
    if not per_model:
        return ""
    settings = next(iter(per_model.values())).settings
    decels = " / ".join(f"{d:g}" for d in settings.decelerations)
    lines = [
        "## Plausibility in closed loop",
        "",
        "The hybrid's particles through the battery "
        "(`torchcf.traffic.check_plausibility`) at "
        f"{settings.speed:.1f} m/s: the share that collide (leader braking to "
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
        ttc = row.min_ttc_median
        lines.append(
            f"| {_display_name(name)} | {row.n_particles} | "
            f"{row.collided:.1%} | {row.string_unstable:.1%} | "
            f"{row.no_equilibrium:.1%} | "
            f"{_MISSING if ttc is None else f'{ttc:.2f}'} |"
        )
    return "\n".join(lines + ["", *plausibility_meaning(per_model)]) + "\n"


def plausibility_meaning(per_model: Mapping[str, PlausibilitySummary]) -> list[str]:
    """What the battery's table means for using the hybrid, and what to do:
    a paragraph per finding (collisions, string instability, no equilibrium),
    naming the models concerned; one line when nothing was found."""

    def which(key: str) -> str:
        found = [
            f"{_display_name(m)} {getattr(r, key):.0%}"
            for m, r in per_model.items()
            if m.lower() != _HYBRID and getattr(r, key) > 0.0
        ]
        return ", ".join(found)

    collided, unstable, drifting = (
        which(k) for k in ("collided", "string_unstable", "no_equilibrium")
    )
    lines = []
    if collided:
        lines += [
            f"What it means. Particles that collide (of each model's: {collided}): "
            "run alone, they crash in at least one scenario, most often behind a "
            "leader braking hard to a stop, which the training data rarely hold. "
            "In torchcf's traffic simulations (`platoon`, `ring_road`) the safety "
            "layer (Gipps' safe speed, on by default) brakes them instead and "
            "`output.interventions` counts how often; SUMO bounds its vehicles by "
            "its own safe speed. Where the learned behaviour itself must not "
            'collide (a safety study), train with `"plausibility": {"filter": '
            "true}`: such particles never enter the hybrid, at a cost in fit and "
            'time (`docs/traffic.md`, "What the filter costs").',
            "",
        ]
    if unstable:
        lines += [
            f"String-unstable particles (of each model's: {unstable}): a platoon of "
            "them amplifies "
            "a speed disturbance from vehicle to vehicle, so dense traffic of one "
            "such model grows stop-and-go waves; in a mixed fleet, read the "
            "waves a simulation shows with this in mind.",
            "",
        ]
    if drifting:
        lines += [
            f"Particles without an equilibrium at some speed up to the battery's "
            f"(of each model's: {drifting}): following a steady leader at that "
            "speed, their gap "
            "never settles (it keeps opening or closing), usually a speed range "
            "the training pairs never reached. Keep simulations within the "
            "data's speeds, or screen them as above.",
            "",
        ]
    return lines or [
        "No particle collided, amplified a disturbance or lacked an "
        "equilibrium in the battery.",
        "",
    ]


# ------------------------------------------------------------- uncertainty
#: Metrics with a bootstrap interval, in table order.
INTERVAL_COLUMNS = (
    ("min", "Minimum distance"),
    ("beta_ws", "0.15-WS distance"),
    ("ws", "WS distance"),
)


def _interval_cell(value: float | None, low: float | None, high: float | None,
                   digits: int) -> str:  # fmt: skip
    cell = _format(value, digits)
    if low is None or high is None or math.isnan(low) or math.isnan(high):
        return cell
    return f"{cell} [{_format(low, digits)}, {_format(high, digits)}]"


def _interval_rows(
    metrics: Mapping[str, Mapping[str, float]],
    order: Sequence[str],
    columns: Sequence[tuple[str, str]],
    digits: int,
) -> list[str]:
    """One Markdown row per entry of ``order`` (the hybrid bold): each column's
    ``key`` as value [``key_low``, ``key_high``], and a closing empty line."""
    lines = []
    for name in order:
        strong = "**" if name.lower() == _HYBRID else ""
        cells = [f"{strong}{_display_name(name)}{strong}"]
        for key, _ in columns:
            cells.append(
                _interval_cell(
                    _lookup(metrics, name, key),
                    _lookup(metrics, name, f"{key}_low"),
                    _lookup(metrics, name, f"{key}_high"),
                    digits,
                )
            )
        lines.append("| " + " | ".join(cells) + " |")
    return lines + [""]


def intervals_table(
    metrics: Mapping[str, Mapping[str, float]],
    order: Sequence[str],
    bootstrap: BootstrapSettings,
    *,
    digits: int = 3,
) -> str:
    """Markdown table of the distances with their bootstrap interval over test
    pairs (``<key>_low``, ``<key>_high`` of each entry), one row per entry."""
    lines = [
        f"Each cell: value [{float(bootstrap.level):.0%} percentile bootstrap "
        f"interval over test pairs; {bootstrap.resamples} resamples, WS and "
        f"0.15-WS {bootstrap.resamples_transport}, seed {bootstrap.seed}].",
        "",
        "| Model | " + " | ".join(label for _, label in INTERVAL_COLUMNS) + " |",
        "|---" * (len(INTERVAL_COLUMNS) + 1) + "|",
    ]
    return "\n".join(lines + _interval_rows(metrics, order, INTERVAL_COLUMNS, digits))


def differences_table(
    hybrid_minus: Mapping[str, Mapping[str, Difference]],
    *,
    digits: int = 3,
) -> str:
    """Markdown table of the hybrid minus each model (paired bootstrap): the
    difference and its interval; ``†`` marks an interval that excludes 0 (the
    difference is larger than its noise; negative: the hybrid is closer)."""
    lines = [
        "Hybrid minus each model on the same resampled test pairs (negative: the "
        "hybrid is closer); `†`: the interval excludes 0.",
        "",
        "| Hybrid minus | " + " | ".join(label for _, label in INTERVAL_COLUMNS) + " |",
        "|---" * (len(INTERVAL_COLUMNS) + 1) + "|",
    ]
    for model, row in hybrid_minus.items():
        cells = [_display_name(model)]
        for key, _ in INTERVAL_COLUMNS:
            d = row.get(key)
            if d is None:
                cells.append(_MISSING)
                continue
            cell = _interval_cell(d.value, d.low, d.high, digits)
            cells.append(cell + (" †" if d.excludes_zero else ""))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def coverage_table(
    metrics: Mapping[str, Mapping[str, float]],
    order: Sequence[str],
    levels: Sequence[float],
    *,
    digits: int = 2,
) -> str:
    """Markdown table of the predictive coverage of each entry: the fraction of
    observed points of the test pairs inside the central bands of the follower's
    spacing and speed, with its bootstrap interval over test pairs."""
    columns = [
        (f"coverage_{variable}_{round(100 * q):d}", f"{variable} {q:.0%}")
        for variable in ("spacing", "speed")
        for q in levels
    ]
    lines = [
        "Fraction of the observed points (test pairs, steps >= 1) inside the "
        "central band of each nominal level of the set's predictive distribution "
        "(its particles simulated on the pair's leader; the hybrid's drawn by "
        "their weight); calibrated: the nominal level. [interval over test pairs]",
        "",
        "| Model | " + " | ".join(label for _, label in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    return "\n".join(lines + _interval_rows(metrics, order, columns, digits))


def shares_interval_table(
    shares: Mapping[str, ShareInterval], level: float, *, digits: int = 3
) -> str:
    """Markdown table of the hybrid's shares with their bootstrap interval over
    training pairs."""
    lines = [
        f"Hybrid shares [{level:.0%} percentile bootstrap interval over "
        "training pairs].",
        "",
        "| Model | Share |",
        "|---|---|",
    ]
    for model, s in shares.items():
        lines.append(
            f"| {_display_name(model)} | "
            f"{_interval_cell(s.share, s.low, s.high, digits)} |"
        )
    return "\n".join(lines) + "\n"
