"""Road effects at the data's resolution (torchcf.diagnose.road): the road-frame
decision, the knot spacing chosen by cross-validation, the grade seed from the
residual regression, and road_frame in meta.json."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from torchcf.config import validate_config
from torchcf.data import DataError, load_pairs
from torchcf.data.reader import FILES
from torchcf.diagnose import candidate_effects
from torchcf.diagnose.road import (
    ROAD_SPACINGS,
    choose_spacing,
    grade_seed,
    shares_road_frame,
)
from torchcf.models.effects import GRAVITY, parse_effect
from torchcf.synthetic import synthetic_pairs

IDM_TRUTH = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]


def _wavy_grade(x: np.ndarray, wavelength: float) -> np.ndarray:
    return 0.04 * np.sin(2 * math.pi * x / wavelength)


def _series(grade, n_pairs=30, noise=0.05, seed=0):
    """Residual series of pairs driving over 0-1200 m where the model misses
    the grade: r_a = -g G(x) + noise."""
    rng = np.random.default_rng(seed)
    x, residual = [], []
    for _ in range(n_pairs):
        start = rng.uniform(0, 600)
        xi = start + np.linspace(0, 600, 300)
        x.append(xi)
        residual.append(-GRAVITY * grade(xi) + noise * rng.standard_normal(xi.size))
    return {"x": x, "acceleration": residual}


def test_fine_structure_gets_fine_knots_and_smooth_gets_coarse():
    wavy = choose_spacing("grade", 0.0, 1200.0, _series(lambda x: _wavy_grade(x, 200)))
    assert wavy.spacing <= 50.0, wavy.errors
    smooth = choose_spacing("grade", 0.0, 1200.0, _series(lambda x: 0.02 + 0 * x))
    assert smooth.spacing == max(ROAD_SPACINGS), smooth.errors
    medium = choose_spacing(
        "grade", 0.0, 1200.0, _series(lambda x: _wavy_grade(x, 800))
    )
    assert 100.0 <= medium.spacing <= 200.0, medium.errors
    assert parse_effect(wavy.token).knots == round(1200 / wavy.spacing) + 1


def test_the_grade_seed_is_the_profile_in_the_residual():
    series = _series(lambda x: _wavy_grade(x, 600), noise=0.2)
    choice = choose_spacing("grade", 0.0, 1200.0, series)
    effect = parse_effect(choice.token)
    truth = _wavy_grade(np.array(effect.knot_positions), 600)
    seed = grade_seed(effect, series["x"], series["acceleration"]).numpy()
    assert np.corrcoef(seed, truth)[0, 1] >= 0.95
    assert np.abs(seed - truth).max() < 0.01
    assert torch.equal(choice.seed, torch.from_numpy(seed))


def test_road_frame_declared_or_decided():
    pairs = synthetic_pairs("idm", IDM_TRUTH, 4, 100, seed=3)
    frame, why = shares_road_frame(pairs)
    assert frame and "spread" in why  # synthetic pairs start at different places
    same = dataclasses.replace(
        pairs,
        x_follow=pairs.x_follow - pairs.x_follow[0],
        x_lead=pairs.x_lead - pairs.x_follow[0],
    )
    assert shares_road_frame(same)[0] is False
    assert shares_road_frame(dataclasses.replace(same, road_frame=True)) == (
        True,
        "declared by the data",
    )
    assert shares_road_frame(dataclasses.replace(pairs, road_frame=False))[0] is False


def test_road_effects_are_not_offered_without_one_road():
    pairs = synthetic_pairs("idm", IDM_TRUTH, 6, 200, seed=3)
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "diagnose": {"effects": ["delay", "grade", "bend", "offset"]},
        }
    )
    series = _series(lambda x: 0 * x, n_pairs=6)
    effects, road, seeds = candidate_effects(
        cfg, dataclasses.replace(pairs, road_frame=False), series
    )
    assert effects == ["delay", "offset"]
    assert road["frame"] is False and road["skipped"] == ["grade", "bend"]
    effects, road, seeds = candidate_effects(cfg, pairs, series)
    assert [parse_effect(e).name for e in effects] == [
        "delay",
        "grade",
        "bend",
        "offset",
    ]
    assert [p["effect"] for p in road["profiles"]] == [effects[1], effects[2]]
    assert list(seeds) == [effects[1]]  # the grade's, from the regression


def test_meta_json_declares_the_road_frame(tmp_path):
    pairs = synthetic_pairs("idm", IDM_TRUTH, 3, 50, seed=1)
    folder = tmp_path / "set"
    folder.mkdir()
    for key, file in FILES.items():
        np.savetxt(folder / file, getattr(pairs, key).numpy(), delimiter=",")
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "road_frame": False}))
    assert load_pairs(str(folder)).road_frame is False
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "road_frame": "yes"}))
    with pytest.raises(DataError, match="road_frame"):
        load_pairs(str(folder))
