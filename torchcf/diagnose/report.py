"""The loop's report (loop step 4): ``loop.md``, its figures, and writing them.

``RUN_DIR/loop.md`` (:func:`loop_markdown`) holds the candidate effects ranked,
the chosen ones with their learned parameters, the test-split error of the hybrid
before and after, and the residual diagnostics before and after; its figures go
to ``RUN_DIR/loop/`` and its text to TensorBoard. :func:`write_report` writes
``loop.json`` last (:meth:`torchcf.rundir.RunDir.write_loop`): its presence says
the loop finished.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..evaluation.plots import loop_figures, save_figure
from ..evaluation.report import METRIC_COLUMNS
from ..files import ensure_directory
from ..rundir import RunDir
from ..tblog import RunLogger

#: Which residual structure points to which effect (for the report only).
EFFECT_HINTS = {
    "delay": "cross-correlation with the leader's acceleration / speed difference "
    "at a lag > 0, autocorrelation",
    "lag": "autocorrelation, cross-correlation with the speed difference",
    "offset": "dependence on the spacing level, a constant spacing residual",
    "asymmetry": "dependence on the sign of the speed difference",
    "resistance": "dependence on own speed squared",
    "grade": "dependence on the position along the road",
    "saturation": "residuals concentrated at large accelerations",
}

Series = dict[str, list[np.ndarray]]


def write_report(
    run: RunDir,
    result: dict[str, Any],
    series_before: Series,
    series_after: Series | None,
    dt: float,
) -> None:
    """The figures in ``RUN_DIR/loop/``, the Markdown in TensorBoard and
    ``loop.md``, then ``loop.json`` (last)."""
    folder = ensure_directory(run.loop_dir, "loop directory")
    figures = loop_figures(result, series_before, series_after, dt)
    for name, figure in figures.items():
        save_figure(figure, folder / f"{name}.png")
    markdown = loop_markdown(result, {name: f"loop/{name}.png" for name in figures})
    with RunLogger(run.tb_dir) as logger:
        logger.text("loop", markdown)
    run.write_loop(result, markdown)


# ------------------------------------------------------------------- loop.md
def loop_markdown(result: dict[str, Any], figures: dict[str, str]) -> str:
    """``loop.md``: diagnostics, ranking, chosen effects, before/after table.

    Args:
        result: the loop's result (``loop.json``).
        figures: the path of each figure (``effects``, ``before_after``,
            ``residuals``) relative to the run directory.
    """
    lines = [
        *_ranking(result, figures["effects"]),
        *(_chosen(result) if result["chosen"] else _none_chosen()),
        *_before_after(result, figures["before_after"]),
        *_residuals(result, figures["residuals"]),
        f"Loop time: {result['seconds']:.0f} s.",
    ]
    return "\n".join(lines) + "\n"


def _ranking(result: dict[str, Any], figure: str) -> list[str]:
    """The title, the guard and the table of every step of the selection."""
    n_effects = len(result["effects_ranked"])
    lines = [
        f"# Closing the loop: {result.get('dataset')}",
        "",
        f"Pool models that got the effects: {', '.join(result['pool'])}.",
        "",
        "**Forward stepwise selection**: at each step every effect not yet chosen "
        "is tested against the current model (the pool plus the variants of the "
        "effects chosen before); the significant effect with the largest gain is "
        "chosen, and the others are tested again with it. **Guard**: the "
        "family-wise level counts every test the selection can make, "
        f"{n_effects} effects over at most {result['steps_at_most']} "
        f"steps = {result['tests']} tests, so an effect is significant at p < "
        f"alpha / {result['tests']} = {result['threshold']:.2g} (Bonferroni, "
        f"alpha {result['alpha']}) with a gain >= {result['min_gain']:.0%}.",
        "",
        "gain: relative drop of the summed validation score (last "
        f"{1 - result['fit_fraction']:.0%} of every training pair) when the current "
        "model's variants with the effect join it, at equal particle budget (small "
        "ABC, then local search); statistic: t of the per-pair log score ratios; "
        "p-value: one-sided sign-flip test; estimate: median of the effect's "
        "parameters over the picks that carry it (a road effect: its one profile, "
        "fitted jointly over the pairs).",
        "",
    ]
    lines += _road(result.get("road"))
    for step, rows in enumerate(result["steps"], start=1):
        before = result["chosen"][: step - 1]
        chosen_here = result["chosen"][step - 1 : step]
        lines += [
            f"## Step {step}: "
            + (f"with {' + '.join(before)}" if before else "the pool alone"),
            "",
            "| effect | gain | statistic | p-value | score before | score after "
            "| pairs | estimate | chosen |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for row in rows:
            estimate = row.get("shared", {}).get("value") or row.get("estimate") or {}
            lines.append(
                f"| {row['effect']} | {row['gain']:+.1%} | "
                f"{fmt(row['statistic'], 2)} | {row['p_value']:.2g} | "
                f"{fmt(row['score_before'])} | {fmt(row['score_after'])} | "
                f"{row['n_pairs']} | "
                + ", ".join(f"{k} {fmt(v)}" for k, v in estimate.items())
                + f" | {'**yes**' if row['effect'] in chosen_here else ''} |"
            )
        lines.append("")
    return [*lines, f"![effects, step 1]({figure})", ""]


def _road(road: dict[str, Any] | None) -> list[str]:
    """How road effects were offered: the frame decision and each profile's
    knot spacing with its cross-validated error."""
    if not road:
        return []
    offered = "offered" if road["frame"] else "not offered"
    lines = [
        f"**Road effects** {offered}: the pairs "
        + ("share one road frame" if road["frame"] else "have a frame each")
        + f" ({road['reason']})."
    ]
    if road["skipped"]:
        lines[-1] += f" Skipped: {', '.join(road['skipped'])}."
    for profile in road.get("profiles", []):
        errors = ", ".join(
            f"{spacing} m {error:.4g}" for spacing, error in profile["cv_error"].items()
        )
        lines.append(
            f"`{profile['effect']}`: knots {profile['spacing']:g} m apart, chosen "
            "by 5-fold cross-validation over pairs of the fit windows' one-step "
            f"acceleration residual on the profile (held-out squared error: "
            f"{errors})."
        )
    return [*lines, ""]


def _chosen(result: dict[str, Any]) -> list[str]:
    """The chosen effects' learned parameters and the shares after."""
    lines = ["## Chosen effects and their learned parameters", ""]
    for effect, summary in result["posterior"].items():
        lines.append(
            f"**{effect}** (share of the new hybrid: {summary['share']:.1%}; "
            f"residual signature: {EFFECT_HINTS.get(effect.split('(')[0], '')})"
        )
        lines += [
            "",
            "| parameter | median | 5 % | 95 % | particles |",
            "|---|---|---|---|---|",
        ]
        for name, stats in summary["params"].items():
            if stats["n"]:
                lines.append(
                    f"| {name} | {fmt(stats['median'])} | {fmt(stats['q05'])} | "
                    f"{fmt(stats['q95'])} | {stats['n']} |"
                )
        lines.append("")
    shares = ", ".join(
        f"{k} {v:.1%}" for k, v in result["shares_after"].items() if v > 0
    )
    return [*lines, f"Shares after: {shares}.", "", *_identifiability(result)]


def _identifiability(result: dict[str, Any]) -> list[str]:
    """Each chosen effect parameter's strongest partner among the model's."""
    report = result.get("identifiability") or {}
    rows = [
        f"| {effect} | {model} | {param} | {row['partner']} | {row['r']:+.2f} | "
        f"{'**traded off**' if row['traded_off'] else 'identified'} | "
        f"{row['n_pairs']} |"
        for effect, models in report.items()
        for model, params in models.items()
        for param, row in params.items()
    ]
    if not rows:
        return []
    return [
        "## Identifiability",
        "",
        "Within-pair correlation of each effect parameter with the model's own "
        "parameters over the re-calibrated buffers (the best particles of every "
        "augmented model on every training pair, centred per pair, pooled): its "
        "strongest partner. |r| >= 0.7 says the data trade the two off (a spacing "
        "offset against a standstill gap, a delay against a lag): the effect's "
        "value is then known only together with its partner.",
        "",
        "| effect | model | parameter | partner | r | | pairs |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]


def _none_chosen() -> list[str]:
    return [
        "**No effect chosen**: none has a significant out-of-sample gain, so "
        "nothing is re-calibrated ('after' = 'before').",
        "",
    ]


def _before_after(result: dict[str, Any], figure: str) -> list[str]:
    """The hybrid's test-split metrics before and after, and their change
    (against the pool searched as the re-calibration, where it was)."""
    rows = [("before (the run)", result["before"])]
    reference = result.get("before_same_search")
    if reference:
        rows.append(("before, searched as after (the pool alone)", reference))
    rows.append(("after", result["after"]))
    lines = [
        "## Test-split error of the hybrid, before and after",
        "",
        "| | " + " | ".join(label for _, label in METRIC_COLUMNS) + " |",
        "|---|" + "---|" * len(METRIC_COLUMNS),
    ]
    for label, metrics in rows:
        lines.append(
            f"| {label} | "
            + " | ".join(fmt(metrics.get(key)) for key, _ in METRIC_COLUMNS)
            + " |"
        )
    if reference:
        lines += [
            "",
            "The re-calibration searched otherwise than the run (`diagnose."
            "recalibrate_method` / `recalibrate_particles`), so the pool alone was "
            "searched the same way: the changes below are against it, the "
            "effect's own share of the improvement.",
        ]
    base = reference or result["before"]
    for key, label in (
        ("ws", "WS"),
        ("beta_ws", "0.15-WS"),
        ("min", "Minimum distance"),
    ):
        before, after = _metric(base.get(key)), _metric(result["after"].get(key))
        if before and after is not None and math.isfinite(before):
            lines += ["", f"{label} change: {(after - before) / before:+.1%}."]
        elif key == "ws":
            lines += [
                "",
                "WS: not finite (a hybrid particle is invalid on every "
                "test pair, SPEC); see the minimum distance.",
            ]
    return [*lines, "", f"![before and after]({figure})", ""]


def _residuals(result: dict[str, Any], figure: str) -> list[str]:
    """The residual tests before and after, side by side."""
    lines = [
        "## Residual diagnostics (training pairs, best hybrid particle per pair)",
        "",
        "| residual | test | p before | effect before | p after | effect after |",
        "|---|---|---|---|---|---|",
    ]
    after = {(r["channel"], r["test"]): r for r in result["residuals_after"]}
    for row in result["residuals_before"]:
        other = after.get((row["channel"], row["test"]), {})
        lines.append(
            f"| {row['channel']} | {row['test']} | {fmt(row['p_value'], 2)} | "
            f"{_effect_text(row['effect'])} | {fmt(other.get('p_value'), 2)} | "
            f"{_effect_text(other.get('effect'))} |"
        )
    return [*lines, "", f"![residuals]({figure})", ""]


# ----------------------------------------------------------------- formatting
def _metric(value: Any) -> float | None:
    """A metric from ``metrics.json`` as a float (non-finite ones are stored as the
    strings "inf" / "nan")."""
    if isinstance(value, (int, float, str)):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def fmt(value: Any, digits: int = 3) -> str:
    """A number for a table: ``digits`` decimals (significant digits under 1e-3),
    "inf" when not finite, "—" when missing."""
    if isinstance(value, str) and _metric(value) is not None:
        value = _metric(value)
    if value is None:
        return "—"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "inf"
        return (
            f"{value:.{digits}g}"
            if abs(value) < 1e-3 and value
            else f"{value:.{digits}f}"
        )
    return str(value)


def _effect_text(effect: Any) -> str:
    if isinstance(effect, dict):
        return ", ".join(f"{k} {fmt(v)}" for k, v in list(effect.items())[:2])
    return fmt(effect)


__all__ = ["EFFECT_HINTS", "fmt", "loop_markdown", "write_report"]
