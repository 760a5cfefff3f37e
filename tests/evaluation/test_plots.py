"""Radar and error-evolution figures render headless; the radar normalisation and the
metrics tables match hand-computed examples."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from torchcf.evaluation.plots import (
    RADAR_KEYS,
    before_after_figure,
    error_evolution_figure,
    figure_to_array,
    radar_area_share,
    radar_figure,
    radar_values,
)
from torchcf.evaluation.report import (
    METRIC_COLUMNS,
    metrics_table,
    plausibility_table,
    relative_difference,
)
from torchcf.runs.summary import PlausibilitySettings, PlausibilitySummary

MODELS = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc", "hybrid")


def _assert_rgb(image: np.ndarray) -> None:
    assert image.ndim == 3 and image.shape[2] == 3
    assert image.dtype == np.uint8
    assert image.shape[0] > 100 and image.shape[1] > 100
    assert image.min() < 128  # something was drawn on the white background


def _nine_entries() -> dict[str, dict[str, float]]:
    rng = np.random.default_rng(0)
    metrics = {
        name: dict(zip(RADAR_KEYS, rng.uniform(1.0, 10.0, 6).tolist(), strict=True))
        for name in MODELS
    }
    metrics["llcs"]["ws"] = math.inf
    return metrics


def test_radar_values_by_hand() -> None:
    metrics = {
        "a": {"x": 1.0, "y": 5.0, "z": 2.0},
        "b": {"x": 3.0, "y": 5.0, "z": math.inf},
        "c": {"x": 2.0, "y": 5.0, "z": 4.0},
        "d": {"x": 3.0, "y": math.inf},  # "z" missing: worst, like inf
    }
    values = radar_values(metrics, ("x", "y", "z"))
    assert list(values) == ["a", "b", "c", "d"]
    # x: range [1, 3], ties at the worst both get 0.
    # y: all finite values equal -> 1; inf -> 0.
    # z: finite values {2, 4} only; inf and missing -> 0.
    expected = {
        "a": [1.0, 1.0, 1.0],
        "b": [0.0, 1.0, 0.0],
        "c": [0.5, 1.0, 0.0],
        "d": [0.0, 0.0, 0.0],
    }
    for name, row in expected.items():
        np.testing.assert_allclose(values[name], row)


def test_radar_values_single_finite_and_all_infinite() -> None:
    metrics = {"a": {"x": 7.0, "y": math.nan}, "b": {"x": math.inf, "y": None}}
    values = radar_values(metrics, ("x", "y"))  # type: ignore[arg-type]
    assert values == {"a": [1.0, 0.0], "b": [0.0, 0.0]}


def test_radar_area_share() -> None:
    assert radar_area_share([1.0] * 6) == pytest.approx(1.0)
    assert radar_area_share([0.5] * 6) == pytest.approx(0.25)
    # Alternate vertices at 0: every adjacent product vanishes.
    assert radar_area_share([1.0, 0.0] * 3) == pytest.approx(0.0)
    # Square with radii (1, 1, 0, 0): one triangle of the four, area 1/2 of 2.
    assert radar_area_share([1.0, 1.0, 0.0, 0.0]) == pytest.approx(0.25)
    with pytest.raises(ValueError):
        radar_area_share([1.0, 1.0])


def test_radar_figure_renders() -> None:
    _assert_rgb(figure_to_array(radar_figure(_nine_entries(), title="NGSIM")))


def test_before_after_figure_marks_infinite_metrics(recwarn) -> None:
    """An infinite WS (NGSIM: a particle invalid on every test pair) is drawn as a
    marked gap, without numerical warnings from matplotlib."""
    before = dict(zip(RADAR_KEYS, [6.9, 1.2, 0.6, 1.26, 1.3, math.inf], strict=True))
    after = {**before, "min": 1.24}
    fig = before_after_figure(before, after)
    _assert_rgb(figure_to_array(fig))
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts.count("inf") == 2
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_radar_figure_rejects_bad_labels() -> None:
    with pytest.raises(ValueError, match="labels"):
        radar_figure(_nine_entries(), labels=("only one",))
    with pytest.raises(ValueError):
        radar_figure({})


@pytest.mark.parametrize("n_particles", [20, 500])
def test_error_evolution_figure_renders(n_particles: int) -> None:
    rng = np.random.default_rng(1)
    n_steps = 150
    time = np.arange(n_steps) * 0.1
    errors = np.cumsum(rng.normal(0.0, 0.3, (n_particles, n_steps)), axis=1)
    errors[:, 40:45] = np.nan  # a step invalid for every particle
    errors[2, 100:] = np.nan  # a shorter (padded) particle
    scores = np.nanmean(np.abs(errors), axis=1)
    scores[0] = np.nan  # an invalid particle is never among the best
    fig = error_evolution_figure(time, errors, scores, title="pair #27")
    _assert_rgb(figure_to_array(fig))
    labels = [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    n_best = max(1, round(0.05 * n_particles))
    assert f"all particles (n={n_particles})" in labels
    assert f"best 5 % (n={n_best})" in labels


def test_error_evolution_figure_accepts_tensors_and_checks_shapes() -> None:
    time = torch.arange(10, dtype=torch.float64)
    errors = torch.zeros(4, 10, dtype=torch.float64)
    scores = torch.arange(4, dtype=torch.float64)
    _assert_rgb(figure_to_array(error_evolution_figure(time, errors, scores)))
    with pytest.raises(ValueError, match="errors"):
        error_evolution_figure(time, errors[:, :9], scores)
    with pytest.raises(ValueError, match="scores"):
        error_evolution_figure(time, errors, scores[:3])
    with pytest.raises(ValueError, match="best_fraction"):
        error_evolution_figure(time, errors, scores, best_fraction=0.0)


def _table_rows(table: str) -> list[list[str]]:
    rows = [line for line in table.splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in row.strip("|").split("|")] for row in rows]


OURS = {
    "ovm": {"e_p": 2.0, "e_v": 0.5, "e_a": 1.0, "min": math.inf, "beta_ws": 3.0},
    "gfm": {"e_p": 1.5, "e_v": 0.7, "e_a": 1.0, "min": 1.2, "beta_ws": 1.25},
    "hybrid": {"e_p": 1.0, "e_v": 0.6, "e_a": 1.1, "min": 1.0, "beta_ws": 1.3},
}


def test_metrics_table() -> None:
    table = metrics_table(OURS, ["ovm", "gfm", "hybrid"])
    rows = _table_rows(table)
    assert rows[0] == ["Model"] + [label for _, label in METRIC_COLUMNS]
    assert set(rows[1]) == {"---"}
    assert len(rows) == 2 + 3
    assert rows[2] == ["OVM", "2.000", "0.500*", "1.000*", "inf", "3.000", "–"]
    assert rows[3] == ["GFM", "1.500", "0.700", "1.000*", "1.200", "1.250*", "–"]
    assert rows[4] == [
        "**Hybrid**",
        "**1.000***",
        "**0.600**",
        "**1.100**",
        "**1.000***",
        "**1.300**",
        "**–**",
    ]
    assert "ours / paper" not in table


def test_metrics_table_notes_ws_without_the_particles_never_valid() -> None:
    metrics = {
        "hybrid": {"ws": math.inf, "beta_ws": math.inf, "ws_valid": 1.6234,
                   "beta_ws_valid": 1.3621, "particles_never_valid": 3,
                   "n_particles": 480},
        "gfm": {"ws": 2.0, "particles_never_valid": 0},
    }  # fmt: skip
    table = metrics_table(metrics, ["gfm", "hybrid"])
    assert table.rstrip().splitlines()[-1] == (
        "Hybrid: 3 of 480 particles are invalid on every test pair, which makes "
        "WS and 0.15-WS infinite; over the other particles WS 1.623, 0.15-WS 1.362."
    )
    assert "GFM:" not in table


def test_plausibility_table() -> None:
    row = PlausibilitySummary(
        n_particles=40, collided=0.25, per_scenario={"brake_4": 0.25},
        string_unstable=0.5, string_untested=0.0, no_equilibrium=0.0,
        not_started=0.0, min_ttc_median=None, string_ratio_median=1.1,
        settings=PlausibilitySettings(
            speed=29.4, decelerations=(4.0, 8.0), collision_spacing=0.0,
            platoon_size=10,
        ),
    )  # fmt: skip
    table = plausibility_table({"hl": row, "idm": replace(row, collided=0.0)})
    assert "at 29.4 m/s" in table and "4 / 8 m/s^2" in table
    rows = _table_rows(table)
    assert rows[-2] == ["HL", "40", "25.0%", "50.0%", "0.0%", "–"]
    assert rows[-1][2] == "0.0%"
    assert plausibility_table({}) == ""
    # what it means, for the models concerned only, and what to do
    assert "Particles that collide (of each model's: HL 25%)" in table
    assert '"plausibility": {"filter": true}' in table and "safety layer" in table
    assert "String-unstable particles (of each model's: HL 50%, IDM 50%)" in table
    assert "without an equilibrium" not in table
    calm = replace(row, collided=0.0, string_unstable=0.0)
    assert "No particle collided" in plausibility_table({"idm": calm})


def test_every_report_table_says_what_its_columns_are() -> None:
    from torchcf.evaluation.report import METRIC_NOTES

    for column in ("Minimum distance", "WS distance", "0.15-WS distance", "Avg"):
        assert f"*{column}" in METRIC_NOTES
    assert "beta = 0.15" in METRIC_NOTES and "judged by the distances" in METRIC_NOTES


def test_metrics_table_with_paper() -> None:
    paper = {"ovm": {"e_p": 4.0}, "hybrid": {"e_p": 0.8, "ws": 5.0}}
    table = metrics_table(OURS, ["ovm", "hybrid"], paper=paper, digits=2)
    assert "ours / paper" in table
    rows = _table_rows(table)
    assert rows[2][:3] == ["OVM", "2.00 / 4.00", "0.50* / –"]
    assert rows[3][1] == "**1.00*** / **0.80**"
    assert rows[3][6] == "**–** / **5.00**"


def test_relative_difference_by_hand() -> None:
    ours = {
        "ovm": {"e_p": 2.0, "e_v": 1.0, "min": math.inf, "ws": 1.0},
        "gfm": {"e_p": 3.0},
        "hybrid": {"e_p": 1.5, "e_v": 0.5},
    }
    paper = {
        "ovm": {"e_p": 4.0, "e_v": 0.0, "min": 1.0, "ws": math.inf},
        "hybrid": {"e_p": 1.0, "e_a": 1.0},
    }
    assert relative_difference(ours, paper) == {
        "ovm": {"e_p": pytest.approx(-0.5)},
        "hybrid": {"e_p": pytest.approx(0.5)},
    }
