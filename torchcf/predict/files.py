"""A prediction's files: the per-pair table, the trajectories, the report.

    OUT/
    ├── pairs.csv          one row per pair: its length and every prediction's
    │                      spacing RMSE [m], min ADE / FDE [m], collided draws
    ├── trajectories.csv   one row per pair and step: the recorded spacing and
    │                      every prediction's [m] (long format, for pandas)
    ├── predict.md         the report: what each number answers
    └── predict.json       the scores; written LAST: the prediction finished

Every file is written atomically (:mod:`torchcf.system.files`), so a folder
without ``predict.json`` is an unfinished prediction, never a finished one.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from ..system.files import atomic_write_text, ensure_directory, write_json
from .predict import BandsResult, PopulationResult, Prediction, PredictionSummary
from .scores import SpacingRMSE

#: The report's name and the file that marks a finished prediction.
REPORT = "predict.md"
RESULT = "predict.json"


def write_prediction(prediction: Prediction, out: Path) -> None:
    """Every file of ``prediction`` into ``out`` (module docstring)."""
    ensure_directory(out, "prediction folder")
    atomic_write_text(out / "pairs.csv", _csv(pd.DataFrame(prediction.per_pair)))
    atomic_write_text(out / "trajectories.csv", _csv(trajectories(prediction)))
    atomic_write_text(out / REPORT, report(prediction.summary))
    write_json(out / RESULT, prediction.summary.to_json())  # last


def trajectories(prediction: Prediction) -> pd.DataFrame:
    """One row per pair and recorded step: the recorded and predicted spacing
    [m] (empty where a prediction has none)."""
    pairs = prediction.pairs
    mask = pairs.mask.cpu().numpy()
    steps, columns = np.nonzero(mask)  # row-major: step, then pair
    order = np.lexsort((steps, columns))  # pair-major
    steps, columns = steps[order], columns[order]
    gap = (pairs.x_lead - pairs.x_follow).double().cpu().numpy() - pairs.leader_length
    q = prediction.bands.quantiles.numpy()
    table = {
        "pair_id": np.asarray(pairs.pair_ids)[columns],
        "step": steps,
        "time_s": steps * pairs.dt,
        "observed": gap[steps, columns],
        "population": prediction.population.numpy()[steps, columns],
        "median": q[2][steps, columns],
        "band_05": q[0][steps, columns],
        "band_25": q[1][steps, columns],
        "band_75": q[3][steps, columns],
        "band_95": q[4][steps, columns],
    }
    if prediction.conditioned is not None:
        table["conditioned"] = prediction.conditioned.numpy()[steps, columns]
    return pd.DataFrame(table)


def report(summary: PredictionSummary) -> str:
    """``predict.md``: the three predictions' scores and what each answers."""
    return "\n".join(
        [
            *_scores_table(summary),
            *_meanings(summary),
            *_bands(summary.bands),
            *_fits(summary.population),
            "Files: `pairs.csv` (per pair), `trajectories.csv` (per pair and "
            "step), `predict.json` (these scores).",
            "",
        ]
    )


def _scores_table(summary: PredictionSummary) -> list[str]:
    population, bands, history = summary.population, summary.bands, summary.history
    lines = [
        f"# Prediction: {summary.data}",
        "",
        f"Run `{summary.run}`; {summary.pairs} pairs, "
        f"{summary.seconds_of_data:.0f} s of data at dt {summary.dt:g} s "
        f"(leader length {summary.leader_length:g} m); {summary.seconds:.1f} s. "
        "Every prediction starts from the pair's recorded follower state and "
        "follows its recorded leader; scores are of the spacing [m] on the "
        "pair's recorded steps.",
        "",
        "## Spacing RMSE per pair [m]",
        "",
        "| prediction | mean | median | pooled | pairs | collided |",
        "|---|---|---|---|---|---|",
        _row(
            f"population model ({population.chosen}, one vector for every driver)",
            population.spacing_rmse,
        ),
        _row(f"the hybrid's median over {bands.draws} draws per pair", bands.median),
    ]
    if history:
        lines += [
            _row(
                f"after {history.history:g} s of history: the driver's own "
                "prediction (the rest of the pair)",
                history.conditioned,
            ),
            _row(
                "after the same history: the population model restarted there",
                history.population,
            ),
        ]
    return [*lines, ""]


def _meanings(summary: PredictionSummary) -> list[str]:
    """What each row answers."""
    objective = summary.settings["objective"]
    lines = [
        "- *Population model*: a pooled calibration, one parameter vector per "
        "model minimising the mean "
        f"{'spacing RMSE' if objective == 'spacing' else 'score'} "
        "over the training pairs, searched from the run's kept particles; the "
        "model of the lowest training objective predicts. It answers: how well "
        "does one calibrated driver stand for every driver? (the figure "
        "published calibration studies report).",
        "- *The hybrid's median*: per step, the median spacing of draws from "
        "the hybrid (each model at its share). It answers: knowing nothing of "
        "this driver, what is the population's typical follower here?",
        f"- *One draw at a time*: {_f(summary.bands.per_draw)} m mean spacing "
        "RMSE: a draw is one driver of the population, not a prediction of this "
        "one (the spread of drivers, not an error of the model).",
        "- *Pooled*: the RMSE over all pairs' steps together (long pairs weigh "
        "more); *collided*: pairs the prediction collides on (left out of "
        "the means).",
    ]
    history = summary.history
    if history:
        how = (
            "the hybrid's particles that reproduce the history best, "
            f"{summary.settings['keep']} kept, their median; candidates: "
            f"{history.source}"
            if history.design == "rejection"
            else f"{history.source} vector moved toward the history against a "
            "Gaussian prior around it"
        )
        change = "not measured" if history.change is None else f"{history.change:+.1%}"
        judged = ", ".join(f"{k} {_f(v)}" for k, v in history.judged_on_train.items())
        lines.append(
            f"- *After a history*: the first {history.history:g} s of each pair "
            f"condition the driver's own prediction of the rest, by "
            f"**{history.design}** ({how}). Beside it the population model "
            "restarted at the same recorded state, so that the two differ by "
            f"the parameters only: {change} ({history.pairs} pairs; "
            f"{history.too_short} too short for a rest of 5 s). The design was "
            "judged on the training pairs as if new (mean rest spacing RMSE "
            f"[m]: {judged})."
        )
    return [*lines, ""]


def _bands(bands: BandsResult) -> list[str]:
    return [
        "## The bands and the draws",
        "",
        f"Coverage (share of recorded steps inside the band): 50 % band "
        f"{bands.coverage_50:.1%}, 90 % band {bands.coverage_90:.1%} "
        "(a calibrated spread covers about its nominal share). min ADE / FDE "
        f"over a pair's draws: {_f(bands.min_ade)} / {_f(bands.min_fde)} m "
        "(mean over pairs; the best draw's mean and final displacement). Draws "
        f"that collided: {bands.collisions:.1%}.",
        "",
    ]


def _fits(population: PopulationResult) -> list[str]:
    lines = [
        "## Each model's pooled vector",
        "",
        "| model | training objective | collided (training) | search rounds "
        "(0: its best kept particle) | test mean | test median | parameters |",
        "|---|---|---|---|---|---|---|",
    ]
    for fit in population.fits:
        test = population.by_model[fit.model]
        params = ", ".join(f"{k} {v:.4g}" for k, v in fit.params.items())
        lines.append(
            f"| {fit.model} | {_f(fit.objective)} | {fit.collided} | {fit.rounds} "
            f"| {_f(test.mean)} | {_f(test.median)} | {params} |"
        )
    return [*lines, ""]


def _row(label: str, rmse: SpacingRMSE) -> str:
    return (
        f"| {label} | {_f(rmse.mean)} | {_f(rmse.median)} | {_f(rmse.pooled)} | "
        f"{rmse.pairs} | {rmse.collided} |"
    )


def _f(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _csv(frame: pd.DataFrame) -> str:
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False, float_format="%.4f")
    return buffer.getvalue()


__all__ = ["REPORT", "RESULT", "report", "trajectories", "write_prediction"]
