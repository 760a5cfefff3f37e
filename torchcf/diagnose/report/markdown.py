"""The loop's report (loop step 4): ``loop.md``, its figures, and writing them.

``RUN_DIR/loop.md`` (:func:`loop_markdown`) holds the candidate effects ranked,
the chosen ones with their learned parameters, the test-split error of the hybrid
before and after, and the residual diagnostics before and after; its figures go
to ``RUN_DIR/loop/`` and its text to TensorBoard. :func:`write_report` writes
``loop.json`` last (:meth:`torchcf.runs.directory.RunDir.write_loop`): its presence says
the loop finished.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ...evaluation.plots import loop_figures, save_figure
from ...evaluation.report import METRIC_COLUMNS
from ...models.effects import parse_effect
from ...runs.directory import RunDir
from ...runs.tensorboard import RunLogger
from ...system.files import JSON, ensure_directory
from .method import method_text

Series = dict[str, list[np.ndarray]]


def write_report(
    run: RunDir,
    result: JSON,
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
def loop_markdown(result: JSON, figures: dict[str, str]) -> str:
    """``loop.md``: the trace from the residual to the effects, the tests, the
    absorption, the chosen effects and the error before and after.

    Args:
        result: the loop's result (``loop.json``).
        figures: the path of each figure (``effects``, ``before_after``,
            ``residuals``) relative to the run directory.
    """
    lines = [
        f"# Closing the loop: {result.get('dataset')}",
        "",
        f"Pool models that got the effects: {', '.join(result['pool'])}.",
        "",
        *_for_a_new_driver(result),
        *method_text(result),
        *_road(result.get("road")),
        *_signatures(result),
        *_steps(result, figures["effects"]),
        *_absorption(result),
        *_recording(result),
        *_unexplained(result),
        *(_chosen(result) if result["chosen"] else _none_chosen()),
        *_detectable(result),
        *_before_after(result, figures["before_after"]),
        *_residuals(result, figures["residuals"]),
        *_effort(result),
    ]
    return "\n".join(lines) + "\n"


def _for_a_new_driver(result: JSON) -> list[str]:
    """The report's lead: the model class with and without the chosen effects
    on the test pairs, each refitted, and the response times beside it."""
    lines = ["## For a new driver: the model class on the test pairs", ""]
    found = result.get("class_on_test")
    if found:
        pinned = "; ".join(
            f"{token} at " + ", ".join(f"{k} {fmt(v)}" for k, v in values.items())
            for token, values in found["pinned"].items()
        )
        lines += [
            "Every test pair (drivers the run never saw) refitted by a short "
            "search of its own, once by the model class without the chosen "
            f"effects and once with them ({pinned}), same start budget and "
            "random numbers. It answers: *for a new driver of this "
            "population, once its own parameters are found, does the model "
            "with the effects fit better?*",
            "",
            "| test pairs | score without | score with | change per pair | "
            "better | p-value |",
            "|---|---|---|---|---|---|",
            f"| {found['pairs']} | {fmt(found['mean_without'])} (median "
            f"{fmt(found['median_without'])}) | {fmt(found['mean_with'])} "
            f"(median {fmt(found['median_with'])}) | {found['change']:+.1%} | "
            f"{found['better']} of {found['pairs']} | {found['p_value']:.2g} |",
            "",
            "Score: SPEC section 4's weighted RMSE of position, speed and "
            "acceleration (lower fits better); change: the geometric mean "
            "of with / without minus 1; p-value: one-sided sign flips over "
            "the test pairs (exact). The hybrid's test metrics further down "
            "(WS, minimum distance) answer another question: how well the "
            "training drivers' particles, pooled, stand in for new drivers.",
            "",
        ]
    elif not result.get("chosen"):
        lines += ["Nothing chosen: the model class is the run's.", ""]
    else:
        lines += ["Not measured.", ""]
    return lines + _response_lines(result.get("response_times") or {}, result)


def _response_lines(times: JSON, result: JSON) -> list[str]:
    """loop.md's response times: the perturbation response of the calibrated
    models (the published figure's measure) and the correlation lag of the
    data and the models on the recorded pairs, before and after."""
    before, after = times.get("before"), times.get("after")
    if not before:
        return []
    after = after if result.get("chosen") else None

    def both(key: str, quartiles: str) -> str:
        text = f"{fmt(before.get(key))} s{_iqr(before.get(quartiles))} before"
        if after:
            text += f", {fmt(after.get(key))} s{_iqr(after.get(quartiles))} after"
        return text

    lines = [
        "**Response time**, median over the training pairs:",
        "",
        "- *the calibrated models behind a standard perturbation* (each pair's "
        "best particle cruising at the pair's median speed; the leader brakes "
        "at 1 m/s^2 by a quarter of that speed, at most 5 m/s, holds 10 s and "
        "comes back; the shift of the leader's speed the follower's matches "
        f"best, over {before.get('perturbation_pairs', 0)} pairs): "
        f"{both('perturbation', 'perturbation_quartiles')}. This is how "
        "published response times of commercial ACCs (0.8-2.5 s) are "
        "measured;",
        f"- *on the recorded leaders' braking events* ({before.get('events', 0)} "
        "events: the leader, steady for 2 s, loses at least 2 m/s within 5 s; "
        "the same shift over 15 s from the onset): the data "
        f"{fmt(before.get('event_data'))} s{_iqr(before.get('event_data_quartiles'))}; "
        "the calibrated models behind the recorded leaders "
        f"{both('event_model', 'event_model_quartiles')}: the data's own "
        "perturbations, where it has them;",
        "- *on the recorded pairs* (the lag, up to 8 s, of the follower's best "
        "correlation with its leader's acceleration, over the "
        f"{before['pairs']} pairs whose follower correlates at least 0.3): the "
        f"data {fmt(before['data'])} s{_iqr(before['data_quartiles'])}; the "
        "calibrated models behind the recorded leaders "
        f"{both('model', 'model_quartiles')}. "
        "In everyday driving the leader's changes are small and slow and a "
        "follower that lets its spacing absorb them answers late: this lag "
        "can exceed the perturbation response; the two rows compare the "
        "models with the data on the data's own terms.",
        "",
        "| model | before: pairs, perturbation / recorded [s] | after: pairs, "
        "perturbation / recorded [s] |",
        "|---|---|---|",
    ]
    models = sorted(
        set(before.get("perturbation_by_model") or {})
        | set((after or {}).get("perturbation_by_model") or {})
    )
    for name in models:
        lines.append(
            f"| {name} | {_by_model(before, name)} | {_by_model(after, name)} |"
        )
    return [*lines, ""]


def _by_model(times: JSON | None, name: str) -> str:
    if not times or name not in (times.get("perturbation_by_model") or {}):
        return "-"
    step = times["perturbation_by_model"][name]
    recorded = times.get("by_model", {}).get(name)
    return f"{times.get('per_model', {}).get(name, 0)}, {fmt(step)} / {fmt(recorded)}"


def _iqr(quartiles: Any) -> str:
    if not quartiles:
        return ""
    return f" (quartiles {fmt(quartiles[0])}-{fmt(quartiles[1])})"


def _road(road: JSON | None) -> list[str]:
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
            "by 5-fold cross-validation over pairs of the one-step acceleration "
            "residual on the profile, on the part the arms are fitted on (the "
            "fit windows, or the fit pairs) (held-out squared error: "
            f"{errors})."
        )
    return [*lines, ""]


def _signatures(result: JSON) -> list[str]:
    """The residual signatures of the pool (and after the chosen effects), and
    the trace from each found one to the effects it points to and their tests."""
    marks = result.get("signatures") or []
    if not marks:
        return []
    final = marks[-1] if len(marks) > 1 and result["chosen"] else None
    lines = [
        "## From the residual to the effects",
        "",
        "Signatures of the pool's best particle per pair on the fit windows: each "
        "pair gives one value, tested across pairs (two-sided sign flips; found "
        "at p < 0.05)."
        + (" Last column: the same after the chosen effects." if final else ""),
        "",
        "| signature | mean | median | pairs | p | found | points to |"
        + (" after the effects |" if final else ""),
        "|---|---|---|---|---|---|---|" + ("---|" if final else ""),
    ]
    after = {m["signature"]: m for m in final} if final else {}
    for mark in marks[0]:
        points = ", ".join(mark["points_to"]) or (mark["family"] or "")
        if mark["family"]:
            points = f"no effect: *{mark['family']}*"
        row = (
            f"| {mark['signature']} | {fmt(mark['mean'])} {mark['unit']} | "
            f"{fmt(mark['median'])} | {mark['n_pairs']} | {fmt(mark['p_value'], 2)} "
            f"| {'**yes**' if mark['found'] else 'no'} | {points} |"
        )
        if final:
            other = after.get(mark["signature"], {})
            row += (
                f" {fmt(other.get('mean'))} {mark['unit']}, p "
                f"{fmt(other.get('p_value'), 2)} |"
            )
        lines.append(row)
    lines.append("")
    rows = {r["name"]: r for r in result["steps"][0]} if result["steps"] else {}
    trace = []
    for mark in marks[0]:
        for effect in mark["points_to"]:
            row = rows.get(effect)
            if row is None:
                trace.append(
                    f"- {mark['signature']} -> {effect}: not a candidate here."
                )
                continue
            verdict = _verdict(row)
            trace.append(
                f"- {mark['signature']} ({fmt(mark['mean'])} {mark['unit']}) -> "
                f"`{row['effect']}`: tested {_ordinal(row['order'])}, gain "
                f"{row['gain']:+.1%} (in sample {row['fit_gain']:+.1%}), p "
                f"{row['p_value']:.2g} at level {row['level']:.2g}: {verdict}."
            )
    if trace:
        lines += ["Trace (step 1):", "", *trace, ""]
    return lines


def _ordinal(n: int) -> str:
    return f"{n}{'st' if n == 1 else 'nd' if n == 2 else 'rd' if n == 3 else 'th'}"


def _steps(result: JSON, figure: str) -> list[str]:
    """The table of every step of the selection, in the order tested."""
    lines = []
    for step, rows in enumerate(result["steps"], start=1):
        before = result["chosen"][: step - 1]
        level = result["levels"][step - 1]
        lines += [
            f"## Step {step}: "
            + (f"with {' + '.join(before)}" if before else "the pool alone")
            + f" (level {level:.3g})",
            "",
            "| order | effect | scope | pointed to by | family (p) | in-sample gain "
            "| gain | p-value | level | pairs changed | estimate | chosen |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in rows:
            estimate = row.get("estimate") or {}
            mark = (
                "**yes**"
                if row.get("chosen")
                else "significant"
                if row["significant"]
                else ""
            )
            family = row.get("family") or []
            twins = (
                f"{', '.join(t for t in family if t != row['effect'])} "
                f"({row['family_p_value']:.2g})"
                if family
                else ""
            )
            lines.append(
                f"| {row['order']} | {row['effect']} | {row['scope']} | "
                f"{', '.join(row['pointed_by'])} | {twins} | {row['fit_gain']:+.1%} | "
                f"{row['gain']:+.1%} | {row['p_value']:.2g} | {row['level']:.2g} | "
                f"{row['pairs_changed']} of {row['n_pairs']} | "
                + ", ".join(f"{k} {fmt(v)}" for k, v in list(estimate.items())[:4])
                + ("" if row.get("active", True) else " (neutral: no effect)")
                + f" | {mark} |"
            )
        lines.append("")
    if not result["steps"]:
        lines += ["No candidate effect to test.", ""]
    return [*lines, f"![effects, step 1]({figure})", ""]


def _absorption(result: JSON) -> list[str]:
    """Which of the pool's own parameters takes each effect up (step 1)."""
    rows = []
    for effect, found in (result.get("absorption") or {}).items():
        if not found:
            rows.append(f"| {effect} | — | | | | | |")
            continue
        verdict = (
            f"**absorbed by {found['parameter']}**"
            if found["absorbed"]
            else "separable"
        )
        rows.append(
            f"| {effect} | {found['model']}: {found['parameter']} | "
            f"{found['correlation']:+.2f} | {fmt(found.get('slope'))} | "
            f"{fmt(found.get('shift'))} | {found['n_pairs']} | {verdict} |"
        )
    if not rows:
        return []
    return [
        "## Absorption",
        "",
        "Which of the pool's own parameters takes each effect up. A driver "
        "effect: the within-pair correlation of the effect's parameter with the "
        "model's over the effect arm's particles (centred per pair, pooled), the "
        "ridge's slope (partner per unit of the effect) and the partner's shift "
        "between the best particle without and with the effect (median over "
        "pairs). A one-parameter recording effect: its profile (fixed at 7 "
        "values over its prior and half a step on either side of the best, each "
        "pair refitted), the same read off each pair's best particle along it "
        "(shift: between the neutral value and the value found). |r| >= 0.7 "
        "reads 'absorbed': the data tell the effect from that parameter only "
        "together, and an effect not chosen is then not separable in these "
        "data rather than absent.",
        "",
        "| effect | partner | r | slope | shift | pairs | |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
    ]


#: Per recording effect: its behavioural twin in equilibrium, and what data
#: would tell the two apart (:func:`_recording`).
RECORDING_READINGS = {
    "offset": (
        "a constant error of the recorded spacing and drivers who keep a "
        "standstill gap that much longer (or shorter) give the same "
        "equilibrium: an offset d_offset is a standstill gap -d_offset",
        "a stop in the data (the gap at rest, which a sensor offset shifts and "
        "a standstill gap sets), or a second measurement of the spacing (a "
        "radar range beside the positions)",
    ),
    "sync": (
        "a leader log running t ahead of the follower's, and drivers who keep a "
        "time gap t longer and react t late, move the follower nearly alike: a "
        "clock offset t_sync is a time gap +t_sync with a delay of the leader's "
        "speed",
        "a log known to be synchronised (both vehicles on one GPS time base), "
        "or a second sensor on the follower (its own range to the leader, which "
        "no clock offset between two logs touches)",
    ),
}


def _verdict(row: JSON) -> str:
    """A tested effect's verdict in words."""
    if row.get("chosen"):
        return "**chosen**"
    return "significant" if row["significant"] else "not significant"


def _recording(result: JSON) -> list[str]:
    """Each recording effect of step 1: its estimate, its interval, and, where
    the pool takes it up, the behavioural reading with the sizes of both and
    what would separate them."""
    rows = [r for r in (result["steps"][0] if result["steps"] else [])]
    rows = [r for r in rows if r["scope"] == "recording" and r.get("shared")]
    if not rows:
        return []
    lines = [
        "## Recording effects: the data's fault or the drivers' habit?",
        "",
        "A recording effect (one for the whole data set) has a behavioural "
        "twin the pool can play itself; the profile says how much of it the "
        "pool's own parameters took up (its steady state read at the fit "
        "pairs' median speed, each pair's best particle at every fixed value). "
        "Interval: 90 % of the pairs resampled put the profile's minimum "
        "there.",
        "",
    ]
    for row in rows:
        name = row["name"]
        (param, value), *_ = row["shared"]["value"].items()
        interval = (row["shared"].get("interval") or {}).get(param)
        reading, separation = RECORDING_READINGS.get(name, ("", ""))
        verdict = _verdict(row)
        text = (
            f"- **{name}**: {param} {fmt(value)}"
            + (f" [{fmt(interval[0])}, {fmt(interval[1])}]" if interval else "")
            + f"; held out {row['gain']:+.1%}, p {row['p_value']:.2g} at level "
            f"{row['level']:.2g}: {verdict}."
        )
        found = row.get("absorbed_by") or {}
        steady = found.get("steady")
        if found:
            text += (
                f" Along its profile {found['model']}'s {found['parameter']} "
                f"moves {fmt(found.get('slope'))} per unit (r "
                f"{found['correlation']:+.2f}; shifted {fmt(found.get('shift'))} "
                "at the value found)"
                + (": **absorbed**" if found.get("absorbed") else "")
                + "."
            )
        if steady:
            text += (
                f" The pool's equilibrium gap at {steady['speed']:.1f} m/s moves "
                f"{fmt(steady['gap_slope'])} m (r {_signed(steady['gap_r'])}) and "
                f"its time gap {fmt(steady['time_gap_slope'])} s (r "
                f"{_signed(steady['time_gap_r'])}) per unit of {param}."
            )
        if reading:
            text += f" In a user's terms: {reading}. To separate them: {separation}."
        lines.append(text)
    return [*lines, ""]


def _signed(value: Any) -> str:
    return "—" if value is None else f"{value:+.2f}"


def _unexplained(result: JSON) -> list[str]:
    """Structure still in the residual that no chosen effect explains."""
    items = result.get("unexplained") or []
    if not items:
        return []
    lines = ["## Structure the library does not explain", ""]
    for item in items:
        tested = item["tested_not_chosen"]
        lines.append(
            f"- **{item['signature']}** ({fmt(item['mean'])} {item['unit']}, p "
            f"{fmt(item['p_value'], 2)}): suggests *{item['family']}*"
            + (
                f"; {', '.join(tested)} tested and not chosen."
                if tested
                else "; no effect of the library leaves it."
            )
        )
    return [*lines, ""]


def _effort(result: JSON) -> list[str]:
    search = result.get("search") or {}
    lines = []
    if search:
        lines.append(
            f"Search effort per arm: {search['population']} particles x "
            f"{search['local_copies']} copies x {search['rounds']} rounds per pair "
            f"({search['n_train']} pairs); the attribution starts from "
            f"{search['n_particles']} prior draws per pool model. "
            + _recalibration_effort(result, search["run_particles"])
        )
        lines.append("")
    return [*lines, f"Loop time: {result['seconds']:.0f} s."]


def _recalibration_effort(result: JSON, run_particles: int) -> str:
    """How the re-calibration searched, in one sentence."""
    if result.get("recalibration", "search") == "train":
        return (
            "The re-calibration trains every pool model's variant as the run "
            f"trained its models ({run_particles} draws each, the run's sampler), "
            f"and gives the pool models {run_particles} more draws each for the "
            "reference."
        )
    return (
        "The re-calibration searches from the run's own buffers "
        f"({run_particles} draws per model)."
    )


def _chosen(result: JSON) -> list[str]:
    """The chosen effects' learned parameters and the shares after."""
    lines = ["## Chosen effects and their learned parameters", ""]
    for effect, summary in result["posterior"].items():
        lines.append(f"**{effect}** (share of the new hybrid: {summary['share']:.1%})")
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


def _identifiability(result: JSON) -> list[str]:
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


def _detectable(result: JSON) -> list[str]:
    """Per tested effect of the last step, the smallest size its test would
    have found in these data (:mod:`torchcf.diagnose.selection.power`)."""
    steps = result.get("steps") or []
    rows = [r for r in (steps[-1] if steps else []) if r.get("detectable")]
    if not rows:
        return []
    last = len(steps)
    given = result["chosen"][: last - 1]
    lines = [
        "## What these data could have shown",
        "",
        f"Step {last}"
        + (f" (with {' + '.join(given)})" if given else "")
        + " chose nothing more. Would its tests have found an effect that was "
        "there? Per tested effect with a one-number size, the smallest size "
        "at which its test passes, on these data: each validation unit "
        "refitted with the effect fixed at the size against refitted without "
        "it, from the same start with the same random numbers. A fit's profile "
        "is symmetric near its best (fixing a parameter a distance off its best "
        "costs about the same on either side), so that is what the test would "
        "see if the data carried the effect at that size. Sizes tried: 1/64 to "
        "all of the way from the neutral value to each end of the prior (a "
        "grade: the amplitude of a profile whose knots alternate in sign); "
        "'beyond the prior': not even at its end. *At its place*: at the level "
        "the effect was tested at; *tested first*: at the step's first level, "
        "had the residual pointed to it.",
        "",
        "| effect | neutral | at its place (level) | tested first (level) | "
        "its test here |",
        "|---|---|---|---|---|",
    ]
    for row in rows:
        found = row["detectable"]
        unit = found["unit"]
        neutral = _neutral_text(row)
        lines.append(
            f"| {row['name']} | {neutral} | "
            f"{_sides(found['at_level'], unit)} ({found['level']:.2g}) | "
            f"{_sides(found['if_first'], unit)} ({found['first_level']:.2g}) | "
            f"{row['gain']:+.1%}, p {row['p_value']:.2g} |"
        )
    return [*lines, ""]


def _neutral_text(row: JSON) -> str:
    spec = parse_effect(row["effect"])
    if len(spec.neutral) == 1:
        return fmt(float(spec.neutral[0]))
    return "0 (flat)"


def _sides(sides: dict[str, float | None], unit: str) -> str:
    """``>= 0.4 s`` / ``<= -1.5 m or >= 3 m`` / ``beyond the prior``."""
    parts = []
    for side, size in sides.items():
        if size is None:
            continue
        sign = "<=" if side == "below" else ">="
        parts.append(f"{sign} {fmt(size)}")
    if not parts:
        return "beyond the prior"
    unit = unit.split(" ")[0]
    return " or ".join(parts) + ("" if unit == "1" else f" {unit}")


def _none_chosen() -> list[str]:
    return [
        "**No effect chosen**: none has a significant out-of-sample gain, so "
        "nothing is re-calibrated ('after' = 'before').",
        "",
    ]


def _before_after(result: JSON, figure: str) -> list[str]:
    """The hybrid's test-split metrics before and after, and their change
    (against the pool searched as the re-calibration, where it was)."""
    rows = [("before (the run)", result["before"])]
    reference = result.get("before_same_search")
    if reference:
        rows.append(("before, searched as after", reference))
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
    if reference and result.get("recalibration", "search") == "train":
        lines += [
            "",
            "*Before, searched as after*: the run with as many more draws per "
            "pool model, by the run's sampler, as after spent on the variants "
            "(rejection: the run's own streams continued). After holds the run "
            "and the variants trained exactly as the run trained a model, so the "
            "change against the reference is the effects'; against the run it "
            "adds the extra draws'.",
        ]
    elif reference:
        lines += [
            "",
            "*Before, searched as after*: the run's particles searched on the "
            "training windows by the same local search as after, without the "
            "effects. After holds all of them, so the change against it is the "
            "effects' share; the change against the run adds the search's.",
        ]
    against = [("the run", result["before"])]
    if reference:
        against.append(("the run searched as after", reference))
    for key, label in (
        ("ws", "WS"),
        ("beta_ws", "0.15-WS"),
        ("min", "Minimum distance"),
    ):
        after = _metric(result["after"].get(key))
        changes = []
        for name, base in against:
            before = _metric(base.get(key))
            if before and after is not None and math.isfinite(before):
                changes.append(f"{(after - before) / before:+.1%} against {name}")
        if changes:
            lines += ["", f"{label} change: {', '.join(changes)}."]
        elif key == "ws":
            lines += [
                "",
                "WS: not finite (a hybrid particle is invalid on every "
                "test pair, SPEC); see the minimum distance.",
            ]
    return [*lines, *_per_test_pair(result), "", f"![before and after]({figure})", ""]


def _per_test_pair(result: JSON) -> list[str]:
    """After against the run and the reference, test pair by test pair."""
    paired = result.get("test_pairs") or {}
    parts = [
        f"against {label}: better on {row['better']} of {row['pairs']} pairs, "
        f"geometric mean change {row['change']:+.1%}, p {row['p_value']:.2g}"
        for label, row in (
            ("the run", paired.get("run")),
            ("the reference", paired.get("reference")),
        )
        if row
    ]
    if not parts:
        return []
    return [
        "",
        "Minimum distance per test pair (one-sided sign flips of the per-pair log "
        "ratios, 'after no better'; exact, the test pairs being independent of "
        f"the training): {'; '.join(parts)}.",
    ]


def _residuals(result: JSON, figure: str) -> list[str]:
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


__all__ = ["fmt", "loop_markdown", "write_report"]
