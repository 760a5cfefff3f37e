"""Road effects at the data's resolution (torchcf.diagnose.signatures.road): the
road-frame
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
from torchcf.diagnose.setup import LoopSetup
from torchcf.diagnose.signatures.families import road_share
from torchcf.diagnose.signatures.road import (
    BEND_SEED_MARGIN,
    MIN_LAP_KNOTS,
    ROAD_SPACINGS,
    bend_seed,
    choose_spacing,
    grade_seed,
    pair_weights,
    profile_agreement,
    shares_road_frame,
)
from torchcf.models import get_model
from torchcf.models.effects import GRAVITY, Grade, parse_effect
from torchcf.sim.synthetic import Scene, synthetic_pairs

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
    wavy = choose_spacing(Grade, 0.0, 1200.0, _series(lambda x: _wavy_grade(x, 200)))
    assert wavy.spacing <= 50.0, wavy.errors
    smooth = choose_spacing(Grade, 0.0, 1200.0, _series(lambda x: 0.02 + 0 * x))
    assert smooth.spacing == max(ROAD_SPACINGS), smooth.errors
    # at a measured residual's noise (0.3 m/s^2; the ZalaZONE pairs' is 0.5) a
    # smooth wave gets a middle spacing; with almost none, finer knots pay
    medium = choose_spacing(
        Grade, 0.0, 1200.0, _series(lambda x: _wavy_grade(x, 800), noise=0.3)
    )
    assert 100.0 <= medium.spacing <= 200.0, medium.errors
    assert wavy.effect.knots == round(1200 / wavy.spacing) + 1


def test_a_tilted_circle_gets_a_profile_round_the_lap():
    """On a closed track (ZalaZONE's tilted platform: radius ~143 m, slope ~1 %)
    the odometers run over many laps; the profile is periodic with the lap,
    never fewer than MIN_LAP_KNOTS knots (two could both sit where the circle is
    level), and its seed follows the grade ``slope sin(s / R)``."""
    radius, slope = 143.4, 0.0102
    lap = 2 * math.pi * radius
    rng = np.random.default_rng(3)
    x, residual = [], []
    for _ in range(40):
        xi = rng.uniform(0, 8 * lap) + np.linspace(0, 600, 400)
        x.append(xi)
        grade = slope * np.sin(xi / radius)
        residual.append(-GRAVITY * grade + 0.3 * rng.standard_normal(xi.size))
    choice = choose_spacing(
        Grade, 0.0, 0.0, {"x": x, "acceleration": residual}, period=lap
    )
    effect = choice.effect
    assert effect.period == lap and effect.knots >= MIN_LAP_KNOTS
    assert effect.knots == max(MIN_LAP_KNOTS, round(lap / choice.spacing))
    s = torch.linspace(0, lap, 200, dtype=torch.float64)
    learned = effect.profile((choice.seed[:, None],), s)
    truth = slope * torch.sin(s / radius)
    assert float(torch.corrcoef(torch.stack([learned, truth]))[0, 1]) > 0.95
    assert float(learned.abs().max()) == pytest.approx(slope, rel=0.35)


def test_a_residual_the_model_cannot_give_is_left_out_of_the_choice():
    """A non-finite one-step residual (a command the model cannot give at the
    observed state) drops its sample: the choice equals the one without it."""
    series = _series(lambda x: _wavy_grade(x, 800), noise=0.3)
    spoiled = {k: [a.copy() for a in v] for k, v in series.items()}
    spoiled["acceleration"][3][10] = np.nan
    spoiled["acceleration"][7][-1] = np.inf
    without = {
        k: [
            np.delete(a, 10) if i == 3 else a[:-1] if i == 7 else a
            for i, a in enumerate(v)
        ]
        for k, v in series.items()
    }
    got = choose_spacing(Grade, 0.0, 1200.0, spoiled)
    expected = choose_spacing(Grade, 0.0, 1200.0, without)
    assert got.effect == expected.effect and got.errors == expected.errors
    assert torch.equal(got.seed, expected.seed)


def test_the_grade_seed_is_the_profile_in_the_residual():
    series = _series(lambda x: _wavy_grade(x, 600), noise=0.2)
    choice = choose_spacing(Grade, 0.0, 1200.0, series)
    effect = choice.effect
    truth = _wavy_grade(np.array(effect.knot_positions), 600)
    seed = grade_seed(effect, series["x"], series["acceleration"]).numpy()
    assert np.corrcoef(seed, truth)[0, 1] >= 0.95
    assert np.abs(seed - truth).max() < 0.01
    assert torch.equal(choice.seed, torch.from_numpy(seed))


def _with_a_wild_pair(series, scale=60.0, seed=1):
    """The series with pair 0's residual replaced by noise of ``scale`` m/s^2
    (a stiff model commanding from a state it never reaches in closed loop)."""
    rng = np.random.default_rng(seed)
    wild = {k: list(v) for k, v in series.items()}
    wild["acceleration"][0] = scale * rng.standard_normal(wild["x"][0].size)
    return wild


def test_pair_weights_weigh_down_only_the_far_noisier_pairs():
    rng = np.random.default_rng(0)
    scales = [0.1, 0.2, 0.25, 0.3, 6.0]
    residual = [s * rng.standard_normal(4000) for s in scales]
    # a slow profile in a pair's residual is not noise: it keeps its weight
    residual[1] = residual[1] + 3.0 * np.sin(np.linspace(0, 6, 4000))
    weights = pair_weights(residual + [np.array([1.0])])
    assert weights[:4].tolist() == [1.0, 1.0, 1.0, 1.0]
    # 6.0 against 3 x the median scale (0.25): counted as a pair of 0.75
    assert weights[4] == pytest.approx((3 * 0.25 / 6.0) ** 2, rel=0.1)
    assert weights[5] == 0.0  # one sample: no scale, no weight
    # a few wild steps do not make a pair noisy
    spiked = residual[0].copy()
    spiked[:40] = 1e3
    assert pair_weights([spiked] + residual[1:4])[0] == 1.0


def test_one_wild_pair_does_not_hide_the_profile():
    """One pair of 30 with a residual of tens of m/s^2 (measured ZalaZONE pairs
    had one such FVDM pair of 50) neither moves the seed off the profile nor
    coarsens the spacing nor makes the road signature negative: every pair is
    weighted by its own scale."""
    series = _series(lambda x: _wavy_grade(x, 600), noise=0.2)
    wild = _with_a_wild_pair(series)
    clean = choose_spacing(Grade, 0.0, 1200.0, series)
    choice = choose_spacing(Grade, 0.0, 1200.0, wild)
    assert choice.spacing == clean.spacing, (choice.errors, clean.errors)
    effect = choice.effect
    truth = _wavy_grade(np.array(effect.knot_positions), 600)
    seed = choice.seed.numpy()
    assert np.corrcoef(seed, truth)[0, 1] >= 0.95
    assert np.abs(seed - truth).max() < 0.01
    # unweighted, the wild pair alone would set the profile: the check bites
    x = np.concatenate(wild["x"])
    design = effect.basis(torch.from_numpy(x)).numpy()
    plain = np.linalg.lstsq(design, np.concatenate(wild["acceleration"]), rcond=None)
    assert np.abs(-plain[0] / GRAVITY - truth).max() > 0.01
    shares = road_share(wild, effect)
    assert np.median(shares) > 0.2 and shares.mean() > 0.0


def test_road_frame_declared_or_decided():
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 4, 100, seed=3)
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
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 6, 200, seed=3)
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "diagnose": {"effects": ["delay", "grade", "bend", "offset"]},
        }
    )
    series = _series(lambda x: 0 * x, n_pairs=6)
    apart = candidate_effects(
        LoopSetup.of(cfg), dataclasses.replace(pairs, road_frame=False), series
    )
    tokens = [effect.token for effect in apart.effects]
    assert tokens == ["delay", "offset"] and apart.profile is None
    skipped = [effect.token for effect in apart.road.skipped]
    assert apart.road.frame is False and skipped == ["grade", "bend"]
    shared = candidate_effects(LoopSetup.of(cfg), pairs, series)
    effects = [effect.token for effect in shared.effects]
    road, seeds = shared.road, [effect.token for effect in shared.seeds]
    assert shared.profile is not None and shared.profile.token == effects[1]
    assert [parse_effect(e).name for e in effects] == [
        "delay",
        "grade",
        "bend",
        "offset",
    ]
    assert [p.effect.token for p in road.profiles] == [effects[1], effects[2]]
    assert list(seeds) == [effects[1]]  # the grade's, from the regression


def test_meta_json_declares_the_road_frame(tmp_path):
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 3, 50, seed=1)
    folder = tmp_path / "set"
    folder.mkdir()
    for key, file in FILES.items():
        np.savetxt(folder / file, getattr(pairs, key).numpy(), delimiter=",")
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "road_frame": False}))
    assert load_pairs(str(folder)).road_frame is False
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "road_frame": "yes"}))
    with pytest.raises(DataError, match="road_frame"):
        load_pairs(str(folder))


def test_profile_agreement_compares_profiles_whatever_their_knots():
    positions = torch.linspace(0.0, 1000.0, 101, dtype=torch.float64)
    # One line on [0, 1000] m, written with 2 and with 5 knots: the same profile.
    coarse = {"grade_0": 0.02, "grade_1": -0.02}
    fine = {f"grade_{k}": 0.02 - 0.01 * k for k in range(5)}
    two, five = "grade(start=0,end=1000,knots=2)", "grade(start=0,end=1000,knots=5)"
    assert profile_agreement(two, coarse, five, fine, positions) == pytest.approx(1.0)
    flipped = {k: -v for k, v in fine.items()}
    assert profile_agreement(two, coarse, five, flipped, positions) == pytest.approx(
        -1.0
    )
    # A bump the coarse line cannot follow: correlation well below 1.
    bump = {f"grade_{k}": [0.0, 0.0, 0.05, 0.0, 0.0][k] for k in range(5)}
    assert abs(profile_agreement(two, coarse, five, bump, positions)) < 0.1
    with pytest.raises(ValueError, match="not a road effect"):
        profile_agreement("delay", {"t_delay": 1.0}, two, coarse, positions)


def test_bend_seed_finds_the_speed_limit_the_followers_press_against():
    """Followers slowed to 12 m/s at 600 m by a bend the leaders ignore: the
    seed's knot there is the limit plus the margin; where no pair drives, the
    prior's top (no limit)."""
    limit = [25.0, 12.0, 25.0]
    pairs = synthetic_pairs(
        get_model("idm+bend(start=0,end=1200)"), IDM_TRUTH + limit, 12, 500, seed=4
    )
    x = [pairs.x_follow[:, j].numpy() for j in range(pairs.n_pairs)]
    v = [pairs.v_follow[:, j].numpy() for j in range(pairs.n_pairs)]
    bend = parse_effect("bend(start=0,end=2400,knots=5)")  # knots 600 m apart
    seed = bend_seed(bend, x, v)
    # Within 50 m of the knot the limit reaches 13.1 m/s, and speeds trail a
    # falling limit (the driver brakes towards it over 1 s).
    assert seed[1].item() == pytest.approx(limit[1] + BEND_SEED_MARGIN, abs=1.5)
    assert seed[4].item() == bend.param_specs[4].upper  # 2400 m: nobody gets there
    assert seed[0].item() > seed[1].item() + 2.0


def test_bend_seed_round_a_lap_reads_both_sides_of_the_join():
    """On a closed track a knot at the lap's start is also where the lap ends:
    a slow stretch just before the end (and a lap later) sets knot 0."""
    bend = parse_effect("bend(period=900,knots=9)")  # knots 100 m apart
    x = [np.array([700.0, 720.0, 895.0, 1795.0]), np.array([300.0, 310.0])]
    v = [np.array([30.0, 30.0, 9.0, 8.5]), np.array([20.0, 21.0])]
    seed = bend_seed(bend, x, v)
    assert seed[0].item() == pytest.approx(9.0 + BEND_SEED_MARGIN)
    assert seed[3].item() == pytest.approx(21.0 + BEND_SEED_MARGIN)
    assert seed[7].item() == pytest.approx(30.0 + BEND_SEED_MARGIN)


@pytest.mark.parametrize("lag", [0.2, 0.5])
def test_a_grade_under_an_actuation_lag_is_whole_in_the_one_step_residual(lag):
    """HL realises its command through a lag: a grade on the command reaches the
    next step's speed only as ~dt / (2 lag) of itself, but the command-space
    residual (the acceleration missed, over da/du) carries it whole, so the
    grade seed recovers the planted knots."""
    from torchcf.diagnose.signatures.road import one_step_residual

    effect = parse_effect("grade(start=0,end=1200,knots=7)")
    truth = np.array([0.02, -0.03, 0.03, -0.01, 0.025, -0.02, 0.01])
    hl = [1.0, lag, 0.8, 1.2, -0.5, 5.0]  # tau, TT, ks, kv, ka, l
    theta = torch.tensor(hl + truth.tolist(), dtype=torch.float64)
    road = Scene(start=(0, 700))
    pairs = synthetic_pairs(
        get_model(f"hl+{effect.token}"),
        theta,
        n_pairs=12,
        n_steps=400,
        seed=3,
        scene=road,
    )
    best = {
        get_model("hl"): (
            torch.tensor([hl] * 12, dtype=torch.float64),
            torch.arange(12),
        )
    }
    series = one_step_residual(best, pairs)
    seed = grade_seed(effect, series["x"], series["acceleration"]).numpy()
    reached = [0.0 <= k <= 1000.0 for k in effect.knot_positions]
    np.testing.assert_allclose(seed[reached], truth[reached], atol=2e-3)
