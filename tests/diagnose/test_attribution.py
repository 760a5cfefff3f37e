"""The attribution's parts (torchcf.diagnose): populations, nested arms with
common random numbers, the fallback procedure, residual signatures, absorption,
the ledger's resume and the re-calibration.

The property the whole comparison rests on: an effect arm holds its base arm, so
an effect can never lose in sample; with the effect pinned at its neutral value
the two arms are the same search, step for step."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import torchcf.diagnose.arms.ledger as ledger
import torchcf.diagnose.arms.search as search_module
import torchcf.diagnose.selection.attribution as attribution
from torchcf.abc.particles import Particles
from torchcf.config import validate_config
from torchcf.diagnose import (
    Population,
    fallback_levels,
    merge,
    paired_change,
    sign_flip_test,
    step_levels,
)
from torchcf.diagnose.arms.absorption import profile_values
from torchcf.diagnose.arms.arena import (
    Arena,
    Arm,
    base_arm,
    effect_arm,
    first_steps_halved,
    fit_pool,
    parabola_minimum,
    placebo_arm,
    predicted,
    profile_interval,
)
from torchcf.diagnose.arms.population import pick_scores, rescore
from torchcf.diagnose.arms.search import Noise, lift, local_search, model_bounds
from torchcf.diagnose.recalibration import recalibration_config
from torchcf.diagnose.selection.attribution import _fit_statistic, attribute_effects
from torchcf.diagnose.setup import LoopSetup
from torchcf.diagnose.signatures.families import (
    POINTS_TO,
    Signature,
    family_of,
    response_lag,
    signatures,
    simulated_covariates,
)
from torchcf.diagnose.signatures.road import one_step_residual
from torchcf.diagnose.signatures.series import residual_series
from torchcf.diagnose.significance import comparable, fallback_weights
from torchcf.models import get_model
from torchcf.models.effects import EFFECTS, parse_effect
from torchcf.sim.synthetic import synthetic_pairs

from .rows import row_of

DELAY, OFFSET, ASYMMETRY = map(parse_effect, ("delay", "offset", "asymmetry"))

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
LLCS = [15.0, 0.5, 1.0]
#: The pool of the fitted arms.
POOL = [get_model("idm"), get_model("llcs")]
#: Road effects with their section (every effect of the library is tried).
TOKENS = [
    token if not EFFECTS[token].scope == "road" else f"{token}(start=0,end=1500)"
    for token in EFFECTS
]


def _config(models=("idm",), dtype="float32", **diagnose):
    settings = {
        "n_particles": 2000,
        "population": 5,
        "local_copies": 4,
        "rounds": 2,
        "permutations": 1000,
        **diagnose,
    }
    return validate_config(
        {
            "data": {"path": "synthetic"},
            "models": list(models),
            "abc": {"n_particles": 2000, "sensitivity_n": [5]},
            "compile": "off",
            "dtype": dtype,
            "diagnose": settings,
        }
    )


def _particles(name, theta, pair, score, index=None):
    score = torch.as_tensor(score, dtype=torch.float64)
    return Particles(
        get_model(name),
        torch.as_tensor(theta, dtype=torch.float64),
        torch.as_tensor(pair, dtype=torch.int64),
        score,
        torch.zeros(score.numel(), dtype=torch.int64)
        if index is None
        else torch.as_tensor(index, dtype=torch.int64),
    )


# ---------------------------------------------------------------- populations
def test_a_population_keeps_the_best_per_pair_by_the_tie_rule():
    a = _particles("idm", [[1.0] * 6, [2.0] * 6, [3.0] * 6], [0, 0, 1], [0.5, 0.2, 9])
    b = _particles("llcs", [[5.0] * 3, [6.0] * 3], [0, 1], [0.2, math.inf])
    population = Population.from_particles([a, b], 3, 2)
    assert tuple(m.name for m in population.models) == ("idm", "llcs")
    # pair 0: the tie at 0.2 goes to the earlier set (idm)
    assert population.score[0].tolist() == [0.2, 0.2]
    assert population.model[0].tolist() == [0, 1]
    assert population.score[1].tolist() == [9.0, math.inf]  # inf never kept
    assert population.model[2].tolist() == [-1, -1]
    assert math.isnan(float(population.theta[0, 1, 3]))  # llcs has 3 parameters


def test_merge_keeps_a_particle_once_and_prefers_the_earlier_population():
    a = Population.from_particles(
        [_particles("idm", [[1.0] * 6, [2.0] * 6], [0, 0], [0.3, 0.1], [4, 7])], 1, 3
    )
    assert torch.equal(merge([a, a], 3).score, a.score)
    b = Population.from_particles(
        [_particles("llcs", [[5.0] * 3], [0], [0.1], [7])], 1, 3
    )
    merged = merge([a, b], 3)
    assert tuple(m.name for m in merged.models) == ("idm", "llcs")
    assert merged.model[0].tolist() == [0, 1, 0]  # same score and index: a first
    assert merged.score[0].tolist() == [0.1, 0.1, 0.3]


def test_pick_scores_are_medians_with_invalid_picks_counted_worst():
    pairs = synthetic_pairs(get_model("idm"), IDM, 2, 120, seed=1)
    rollout = LoopSetup.of(_config(dtype="float64")).rollout(pairs)
    good = [IDM, [1.0, 2.5, 28.0, 1.5, 2.5, 4.0], [1.4, 1.5, 31.0, 1.1, 1.5, 4.0]]
    theta = good + [IDM]
    population = Population.from_particles(
        [_particles("idm", theta, [0, 0, 0, 1], [0.1, 0.2, 0.3, 0.1])], 2, 3
    )
    scores = pick_scores(population, 3, rollout)
    own = rescore(population, rollout).score
    assert float(scores[0]) == pytest.approx(float(own[0].median()))
    assert float(scores[1]) == pytest.approx(float(own[1, 0]))  # one pick only


# -------------------------------------------------------------------- testing
def test_fallback_passes_on_the_level_of_a_rejection():
    levels, rejected = fallback_levels([0.01, 0.02, 0.5], [True, True, True], 0.05)
    w = fallback_weights(3)
    assert levels[0] == pytest.approx(w[0] * 0.05)
    assert rejected == [True, True, False]
    assert levels[1] == pytest.approx(w[1] * 0.05 + levels[0])
    assert levels[2] == pytest.approx(w[2] * 0.05 + levels[1])
    # a first test that fails passes nothing on, and the others still run
    levels, rejected = fallback_levels([0.9, 0.01], [True, True], 0.05)
    assert rejected == [False, True]
    assert levels[1] == pytest.approx(fallback_weights(2)[1] * 0.05)
    # a gain below min_gain is not a rejection
    assert fallback_levels([0.0], [False], 0.05)[1] == [False]


def test_fallback_keeps_the_family_wise_error_under_the_null():
    rng = np.random.default_rng(0)
    trials, m, alpha = 20_000, 9, 0.05
    p = rng.uniform(size=(trials, m))
    errors = sum(any(fallback_levels(row, [True] * m, alpha)[1]) for row in p)
    assert errors / trials <= alpha + 3 * math.sqrt(alpha / trials)
    assert sum(fallback_weights(m)) == pytest.approx(1.0)


def test_step_levels_sum_to_alpha():
    assert step_levels(0.05, 3) == pytest.approx([0.025, 0.0125, 0.0125])
    assert sum(step_levels(0.05, 1)) == pytest.approx(0.05)
    assert step_levels(0.05, 0) == []


def test_sign_flip_test_calibration():
    rng = np.random.default_rng(0)
    p_null = [sign_flip_test(rng.normal(size=20), 2000, seed=i)[1] for i in range(200)]
    assert 0.02 < np.mean(np.array(p_null) < 0.05) < 0.09
    assert sign_flip_test(rng.normal(1.0, 1.0, size=20), 2000)[1] < 0.01
    assert sign_flip_test(-np.abs(rng.normal(size=20)), 2000)[1] > 0.9
    assert sign_flip_test(np.zeros(20), 2000) == (0.0, 1.0)  # the same particles


def test_paired_change_compares_two_runs_pair_by_pair():
    before = [1.0, 2.0, None, 4.0, 1.0]
    after = [0.5, 1.0, 3.0, 2.0, None]  # pairs 2 and 4: one run has no valid particle
    row = paired_change(before, after, 1000)
    assert row.pairs == 3 and row.better == 3
    assert row.change == pytest.approx(-0.5)
    assert row.p_value == pytest.approx(1 / 8, abs=0.04)  # 3 pairs: 2^-3 at best
    worse = paired_change(after[:2], before[:2], 1000)
    assert worse.better == 0 and worse.change == pytest.approx(1.0)
    assert worse.p_value > 0.7
    assert paired_change([1.0], [1.0, 2.0], 1000) is None  # other test pairs
    assert paired_change([None], [1.0], 1000) is None


# ---------------------------------------------------------------- nested arms
@pytest.fixture(scope="module")
def start():
    """A small arena on delayed IDM data and the pool's fit (IDM, LLCS)."""
    pairs = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 6, 200, seed=3, noise=0.05
    )
    cfg = _config(models=("idm", "llcs"))
    arena = Arena.of(LoopSetup.of(cfg), pairs)
    return arena, fit_pool(arena, POOL, lambda *_: None)


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("token", TOKENS)
def test_an_effect_never_loses_in_sample(start, token, seed):
    """Property: whatever the effect and the random numbers, the effect arm's
    k-th best fit score of every pair is at most the base arm's."""
    arena, arm = start
    arena = dataclasses.replace(arena, seed=seed)
    base = base_arm(arena, arm, 1, lambda: None)
    result = effect_arm(arena, arm, base, parse_effect(token), 1, lambda: None)
    assert bool((result.population.score <= base.score).all())
    assert bool((_fit_statistic(result.population, 5) <= _fit_statistic(base, 5)).all())


@pytest.mark.parametrize(
    "token", [t for t in TOKENS if parse_effect(t).exactly_neutral]
)
def test_an_effect_at_its_neutral_value_is_the_same_rollout(start, token):
    arena, arm = start
    rollout = LoopSetup.of(_config(dtype="float64")).rollout(arena.fit.pairs)
    population = rescore(arm.population, rollout)
    neutral = torch.tensor(parse_effect(token).neutral, dtype=torch.float64)
    lifted, lifted_from = lift(population, parse_effect(token), neutral, rollout)
    assert {m.name for m in lifted_from.values()} <= {"idm", "llcs"}
    np.testing.assert_allclose(lifted.score, population.score, rtol=1e-9, atol=1e-12)


def test_a_pinned_neutral_effect_searches_as_its_base_step_for_step(start):
    """Common random numbers: the same key gives the base arm's steps to the
    lifted particles, so with the effect pinned at neutral both searches are
    one."""
    arena, arm = start
    current = {m: get_model(m).param_names for m in arm.population.models}
    key = (7, "step", 1)
    parents = {m: m for m in arm.population.models}
    bounds = {m: model_bounds(m, arena.priors) for m in arm.population.models}
    alone = local_search(
        arm.population, arena.fit, bounds, Noise(key, current), parents,
        rounds=3, copies=4,
    )  # fmt: skip
    zero = torch.zeros(1, dtype=torch.float64)
    lifted, lifted_from = lift(arm.population, parse_effect("offset"), zero)
    pinned = {"offset": zero}
    bounds = {m: model_bounds(m, arena.priors, pinned) for m in lifted.models}
    nested = local_search(
        lifted, arena.fit, bounds, Noise(key, current, parse_effect("offset")),
        parents | lifted_from, rounds=3, copies=4,
    )  # fmt: skip
    assert torch.equal(nested.score, alone.score)
    for j in range(alone.n_pairs):
        for s in range(alone.size):
            model = alone.models[int(alone.model[j, s])]
            k = get_model(model).n_params
            assert torch.equal(nested.theta[j, s, :k], alone.theta[j, s, :k])


def test_the_first_step_from_the_neutral_value_is_halved():
    delay = first_steps_halved(DELAY, profile_values(DELAY, 5))
    assert delay[:, 0].tolist() == [0.0, 0.375, 0.75, 1.5, 2.25, 3.0]
    offset = first_steps_halved(OFFSET, profile_values(OFFSET))
    assert offset[:, 0].tolist() == [-6, -4, -2, -1, 0, 1, 2, 4, 6]


def test_the_predictor_follows_the_secant_of_the_two_fits_before():
    """Pair 0's best (LLCS) moved by +1 m in s0 from the fit at 0 to the fit at
    -1 (the offset): at -3, twice that step on, its slots move by 2 m more
    (times the reach, clipped to the box); pair 1, whose best changed model,
    stays."""
    before = Population.from_particles(
        [_particles("llcs", [LLCS, LLCS], [0, 1], [0.1, 0.1])], 2, 2
    )
    moved = [LLCS[0] + 1.0, *LLCS[1:]]
    origin = Population.from_particles(
        [
            _particles("llcs", [moved, moved], [0, 0], [0.1, 0.2]),
            _particles("idm", [IDM], [1], [0.05]),
        ],
        2,
        2,
    )
    values = torch.tensor([[-3.0], [-1.0], [0.0]], dtype=torch.float64)
    llcs_box = torch.tensor([[1.0, 19.0], [0.0, 3.0], [0.0, 3.0]], dtype=torch.float64)
    bounds = {
        get_model("llcs"): llcs_box,
        get_model("idm"): torch.tensor([[0.0, 1e3]] * 6),
    }
    ahead = predicted(origin, before, values, 0, 2, bounds)
    assert ahead.theta[0, :, 0].tolist() == [LLCS[0] + 3.0] * 2
    assert torch.equal(ahead.theta[0, :, 1:3], origin.theta[0, :, 1:3])
    same = torch.nan_to_num(ahead.theta[1]) == torch.nan_to_num(origin.theta[1])
    assert bool(same.all())
    far = predicted(origin, before, values, 0, 2, bounds, reach=2.0)
    assert far.theta[0, :, 0].tolist() == [19.0, 19.0]  # clipped to the box


# ----------------------------------------------------------------- signatures
def test_the_response_lag_points_to_a_delay():
    """IDM data with a 1 s delay, driven by the same IDM without it: the
    follower answers its leader later than the model, by about the delay."""
    pairs = synthetic_pairs(get_model("idm+delay"), IDM + [1.0], 12, 400, seed=5)
    idm = get_model("idm")
    best = {idm: (torch.tensor([IDM] * 12, dtype=torch.float64), torch.arange(12))}
    closed = residual_series(best, pairs)
    lag = response_lag(closed, pairs.dt)
    assert lag.size >= 8 and 0.5 <= float(np.median(lag)) <= 1.5
    marks = {
        s.name: s for s in signatures(closed, one_step_residual(best, pairs), pairs.dt)
    }
    assert marks["response lag"].found
    assert "delay" in marks["response lag"].points_to
    # the same data driven by the model that made them: nothing to point to
    delayed = get_model("idm+delay")
    truth = {delayed: (torch.tensor([IDM + [1.0]] * 12), torch.arange(12))}
    clean = residual_series(truth, pairs)
    assert np.abs(response_lag(clean, pairs.dt)).max() <= 0.1


def test_a_signature_no_effect_leaves_names_the_family_of_its_own_sign():
    """A found signature points to the library's effects of its sign, and only
    where none leaves it to a family: positive drag (the follower gains at
    speed) is not "a resistance", which the library has."""
    values = np.full(12, 0.02)
    up = Signature("drag", values, 0.02, 0.001)
    down = Signature("drag", -values, -0.02, 0.001)
    assert down.points_to == ("resistance",) and down.family is None
    assert up.points_to == () and "resistance" not in up.family
    assert up.family == family_of("drag", 0.02) != family_of("drag", -0.02)
    weaker = Signature("command strength", -values, -0.5, 0.001)
    stronger = Signature("command strength", values, 0.5, 0.001)
    assert weaker.points_to == ("saturation", "lag") and weaker.family is None
    assert stronger.family == "a response stronger than the model's command " + (
        "(a gain above one)"
    )
    # every found signature names effects or a family, whichever sign
    for name in POINTS_TO:
        for mean in (-1.0, 1.0):
            mark = Signature(name, np.full(12, mean), mean, 0.001)
            assert bool(mark.points_to) != bool(mark.family), (name, mean)
    assert Signature("drag", values, 0.02, 0.5).family is None  # not found


def _one_step_marks(model: str, theta: list[float], noise: float, lead_noise=0.0):
    """Signatures of 30 pairs made by ``model`` (theta), driven by the plain IDM
    at the truth's own parameters."""
    pairs = synthetic_pairs(get_model(model), theta, 30, 400, seed=1, noise=noise)
    if lead_noise:
        g = torch.Generator().manual_seed(5)
        lead = {k: v for k, v in pairs.series().items() if k.endswith("_lead")}
        noisy = {
            k: v + lead_noise * torch.randn(v.shape, generator=g).to(v)
            for k, v in lead.items()
        }
        pairs = dataclasses.replace(pairs, **noisy)
    idm = get_model("idm")
    best = {idm: (torch.tensor([IDM] * 30, dtype=torch.float64), torch.arange(30))}
    closed = residual_series(best, pairs)
    found = signatures(closed, one_step_residual(best, pairs), pairs.dt)
    return {s.name: s for s in found}


ONE_STEP_SIGNATURES = ("closing vs opening", "drag", "command strength")


@pytest.mark.parametrize("lead_noise", [0.0, 0.1])
def test_measurement_noise_alone_leaves_no_one_step_signature(lead_noise):
    """The model that made the data, position noise of 5 cm (and white noise of
    0.1 on the leader's series): nothing is missing, so nothing is found. With
    the observed state's covariates all three were found at p 0.0005 (the
    residual and its covariates share the state's noise)."""
    marks = _one_step_marks("idm", IDM, noise=0.05, lead_noise=lead_noise)
    for name in ONE_STEP_SIGNATURES:
        assert not marks[name].found, (name, marks[name].mean, marks[name].p_value)


@pytest.mark.parametrize(
    ("model", "extra", "signature", "effect"),
    [
        ("idm+saturation", [-3.0, 0.8], "command strength", "saturation"),
        ("idm+lag", [0.5], "command strength", "lag"),
        ("idm+asymmetry", [1.6, 0.7], "closing vs opening", "asymmetry"),
        ("idm+resistance", [0.0015], "drag", "resistance"),
    ],
)
def test_one_step_signatures_point_to_their_effects(model, extra, signature, effect):
    marks = _one_step_marks(model, IDM + extra, noise=0.05)
    assert effect in marks[signature].points_to, (
        marks[signature].mean,
        marks[signature].p_value,
    )


def test_simulated_covariates_lag_the_simulated_follower():
    closed = {
        "v": [np.array([10.0, 11.0, 12.0, 13.0]), np.array([5.0])],
        "speed": [np.array([1.0, 1.0, 2.0, 2.0]), np.array([0.0])],
        "dv": [np.array([0.5, 0.0, -0.5, -1.0]), np.array([0.0])],
        "a": [np.array([1.0, 1.0, 1.0, 1.0]), np.array([0.0])],
        "acceleration": [np.array([0.5, 0.0, -0.5, 0.0]), np.array([0.0])],
    }
    one_step = {"acceleration": [np.array([0.1, 0.2, 0.3])]}  # pair 0 only
    got = simulated_covariates(closed, one_step, lag=1)
    np.testing.assert_array_equal(got["acceleration"][0], [0.2, 0.3])
    np.testing.assert_array_equal(got["v"][0], [9.0, 10.0])  # 10 - 1, 11 - 1
    np.testing.assert_array_equal(got["dv"][0], [1.5, 1.0])  # v_lead - v_sim
    np.testing.assert_array_equal(got["predicted"][0], [0.5, 1.0])
    with pytest.raises(ValueError, match="one-step series"):
        simulated_covariates(closed, {"acceleration": []}, lag=1)


# ----------------------------------------------------------------- absorption
def test_an_offset_is_absorbed_by_the_standstill_gap():
    """LLCS perceives s + d_offset - s0: only the difference is identified. The
    offset's profile says so: s0 follows the offset one for one."""
    pairs = synthetic_pairs(get_model("llcs"), LLCS, 6, 200, seed=2)
    cfg = _config(models=("llcs",), rounds=4, local_copies=8, population=5)
    arena = Arena.of(LoopSetup.of(cfg), pairs)
    truth = _particles("llcs", [LLCS] * 6, range(6), [0.01] * 6)
    pool = Population.from_particles([truth], 6, 5)
    arm = Arm((), merge([rescore(pool, arena.fit)], 5), {})
    base = base_arm(arena, arm, 1, lambda: None)
    placebo = placebo_arm(arena, arm, base, 1, lambda: None)
    result = effect_arm(arena, arm, base, OFFSET, 1, lambda: None)
    judge = arena.validation.judge(placebo, 5, 1)
    row = attribution.effect_row(arena, OFFSET, result, base, placebo, judge)
    found = row.absorbed_by
    assert found.parameter == "s0" and found.absorbed
    assert found.correlation > 0.9
    assert found.slope == pytest.approx(1.0, abs=0.25)
    assert len(found.profile.values) >= len(profile_values(OFFSET))


def test_an_invalid_side_counts_as_a_large_loss_not_a_dropped_pair():
    before = np.array([1.0, 2.0, np.inf, np.inf, 4.0])
    after = np.array([0.5, np.inf, 3.0, np.inf, 0.0])
    usable, b, a = comparable(before, after, 10.0)
    assert usable.tolist() == [True, True, True, False, False]
    assert b[:3].tolist() == [1.0, 2.0, 30.0] and a[:3].tolist() == [0.5, 20.0, 3.0]


def test_a_shared_value_is_refined_between_the_values_tried():
    """The local profile's least-squares parabola puts the value between the
    values tried; a profile that keeps falling gives its end; the interval
    over resampled pairs holds the value and narrows with sharper pairs."""
    x = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64)
    assert parabola_minimum(x, (x - 0.3) ** 2 + 2, best=0.5) == pytest.approx(0.3)
    assert parabola_minimum(x, -x, best=0.0) == pytest.approx(1.0)
    assert parabola_minimum(x[:2], x[:2], best=-0.5) == -0.5  # too few points
    g = torch.Generator().manual_seed(0)
    centres = 0.3 + 0.2 * torch.randn(60, generator=g, dtype=torch.float64)
    ratios = 1 + (x[:, None] - centres[None, :]) ** 2  # (G, N) per-pair profiles
    low, high = profile_interval(x, ratios, 0.5, ("test",)).tolist()
    assert low < parabola_minimum(x, ratios.mean(1), 0.5) < high
    assert high - low < 0.3
    sharp = 1 + (x[:, None] - (0.3 + 0.02 * (centres[None, :] - 0.3) / 0.2)) ** 2
    narrow = profile_interval(x, sharp, 0.5, ("test",))
    assert float(narrow[1] - narrow[0]) < (high - low) / 5


# --------------------------------------------------------- ledger and resume
@pytest.mark.slow  # attributions interrupted and resumed
def test_an_interrupted_attribution_resumes_to_the_same_result(tmp_path, monkeypatch):
    pairs = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 6, 200, seed=4, noise=0.05
    )
    cfg = _config(max_effects=2)
    effects = [DELAY, OFFSET, parse_effect("lag")]
    whole = attribute_effects(
        LoopSetup.of(cfg),
        [get_model("idm")],
        effects,
        pairs,
        ledger=tmp_path / "a.pt",
        progress=False,
    )
    calls = {"n": 0}
    real = attribution.effect_arm  # as the selection calls it

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(attribution, "effect_arm", interrupted)
    with pytest.raises(KeyboardInterrupt):
        attribute_effects(
            LoopSetup.of(cfg),
            [get_model("idm")],
            effects,
            pairs,
            ledger=tmp_path / "b.pt",
            progress=False,
        )
    monkeypatch.setattr(attribution, "effect_arm", real)
    resumed = attribute_effects(
        LoopSetup.of(cfg),
        [get_model("idm")],
        effects,
        pairs,
        ledger=tmp_path / "b.pt",
        progress=False,
    )
    assert resumed.chosen == whole.chosen
    assert resumed.steps == whole.steps
    assert "stages kept (pool" in attribution.resuming(
        attribution.Ledger(
            tmp_path / "a.pt",
            attribution.ledger_key(LoopSetup.of(cfg), ["idm"], effects),
        )
    )
    # another setting is another attribution: nothing is read back
    other = _config(max_effects=2, rounds=1)
    mine = attribution.ledger_key(LoopSetup.of(cfg), ["idm"], effects)
    assert attribution.ledger_key(LoopSetup.of(other), ["idm"], effects) != mine


def test_an_interrupted_pool_fit_resumes_from_its_last_state(tmp_path, monkeypatch):
    """The pool's fit keeps each model's ABC result and its search's state as
    it goes: stopped in the middle of its search, it resumes from the last
    state kept, not from the start, and ends where an uninterrupted fit ends."""
    pairs = synthetic_pairs(get_model("idm"), IDM, 6, 200, seed=4, noise=0.05)
    cfg = _config(max_rounds=6)
    arena = Arena.of(LoopSetup.of(cfg), pairs)
    real = search_module.search_round
    calls = {"n": 0, "stop": 0}

    def counted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == calls["stop"]:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(search_module, "search_round", counted)
    whole = fit_pool(arena, POOL, lambda *_: None).population
    rounds, calls["n"], calls["stop"] = calls["n"], 0, 3
    assert rounds > 3
    monkeypatch.setattr(ledger, "CHECKPOINT_SECONDS", 0.0)  # keep every round
    book = attribution.Ledger(tmp_path / "a.pt", "key")
    with pytest.raises(KeyboardInterrupt):
        fit_pool(arena, POOL, lambda *_: None, book.within("pool"))
    reread = attribution.Ledger(tmp_path / "a.pt", "key")
    assert attribution.resuming(reread).endswith("pool midway")
    assert reread.get("pool/abc/idm") is not None
    assert reread.get("pool/abc/llcs") is not None
    assert reread.get("pool/converge/pool")["rounds"] == 2
    calls["n"], calls["stop"] = 0, 0
    resumed = fit_pool(arena, POOL, lambda *_: None, reread.within("pool"))
    assert calls["n"] == rounds - 2  # from the third round on
    for got, want in zip(
        (resumed.population.score, resumed.population.theta),
        (whole.score, whole.theta),
        strict=True,
    ):
        torch.testing.assert_close(got, want, equal_nan=True)


@pytest.mark.slow  # two attributions
@pytest.mark.parametrize("validation", ["time", "crossfit"])
def test_the_effect_arms_are_the_same_in_worker_processes(validation):
    """Arms searched side by side in two worker processes give the selection
    one process gives (every arm draws from its own seeded streams), the
    cross-fitted refits of every pair included."""
    pairs = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 6, 200, seed=4, noise=0.05
    )
    effects = [DELAY, OFFSET, parse_effect("lag")]
    alone, side_by_side = (
        attribute_effects(
            LoopSetup.of(_config(max_effects=1, workers=w, validation=validation)),
            [get_model("idm")],
            effects,
            pairs,
            progress=False,
        )
        for w in (1, 2)
    )
    assert side_by_side.chosen == alone.chosen
    assert side_by_side.steps == alone.steps
    assert alone.validation.kind == validation


# ------------------------------------------------------------ re-calibration
def test_road_effects_come_last_in_a_name_and_recording_effects_are_shared():
    scopes = [cls.scope for cls in EFFECTS.values()]
    assert scopes.index("road") > max(
        i for i, scope in enumerate(scopes) if scope != "road"
    )
    assert {n for n, cls in EFFECTS.items() if cls.scope == "recording"} == {
        "offset",
        "sync",
    }
    grade = "grade(start=100,end=900,knots=4)"
    model = get_model(f"idm+{grade}+delay+lag")
    assert model.name == f"idm+delay+lag+{grade}"
    assert list(model.param_names[-4:]) == ["grade_0", "grade_1", "grade_2", "grade_3"]


def test_model_bounds_pin_shared_effects_by_name():
    value = torch.tensor([-2.5], dtype=torch.float64)
    box = model_bounds(get_model("idm+offset+delay"), {}, {"offset": value})
    names = get_model("idm+offset+delay").param_names
    assert box[names.index("d_offset")].tolist() == [-2.5, -2.5]
    assert box[names.index("t_delay")].tolist() == [0.0, 3.0]


def test_the_recalibration_config_lists_the_variants_with_their_boxes():
    cfg = _config()
    grade = "grade(start=100,end=900,knots=4)"
    after = recalibration_config(
        cfg,
        [get_model(n) for n in ("idm+delay", f"idm+delay+{grade}", "idm")],
        {grade: {"grade_0": (0.0, 0.01)}},
    )
    names = [m.name for m in after.models]
    assert names == ["idm", "idm+delay", f"idm+delay+{grade}"]
    composite = next(m for m in after.models if m.name == f"idm+delay+{grade}")
    assert composite.prior["grade_0"] == (0.0, 0.01)
    assert after.diagnose.run_after_training is False


def _verdict(effect, gain, scope, significant=True):
    row = row_of(effect, gain=gain, significant=significant)
    assert row.scope == scope
    return row


def test_a_recording_effect_needs_a_clear_margin_over_a_behavioural_one():
    delay = _verdict("delay", 0.24, "driver")
    sync = _verdict("sync", 0.27, "recording")
    assert attribution.choose([sync, delay], 0.05) is delay  # 3 % is no margin
    assert (
        attribution.choose([_verdict("sync", 0.40, "recording"), delay], 0.05).token
        == "sync"
    )
    assert attribution.choose([sync], 0.05) is sync  # alone, it is chosen
    not_significant = dataclasses.replace(delay, significant=False)
    assert attribution.choose([not_significant], 0.05) is None


def test_an_effect_at_its_neutral_value_is_no_effect():
    assert not attribution.active(parse_effect("resistance"), {"c_drag": 1.3e-5})
    assert attribution.active(DELAY, {"t_delay": 0.5})
    assert not attribution.active(ASYMMETRY, {"g_close": 1.02, "g_open": 0.99})
    assert attribution.active(ASYMMETRY, {"g_close": 1.02, "g_open": 1.3})
    assert not attribution.active(OFFSET, {"d_offset": 0.0})


def test_the_forward_selection_has_one_name():
    """``EffectSelection`` (the loop's) is not the hybrid's ``Selection``, and
    the loop has no second name for it."""
    import torchcf.diagnose
    from torchcf.abc import Selection as HybridSelection
    from torchcf.diagnose import EffectSelection

    assert not hasattr(torchcf.diagnose, "Selection")
    assert EffectSelection is not HybridSelection
    assert EffectSelection.__name__ == "EffectSelection"


@pytest.mark.parametrize("c_gap", [0.01, -0.02])
def test_a_time_gap_changing_with_speed_points_to_timegap(c_gap):
    """Followers that keep ``c_gap v^2`` more than IDM's spacing, driven by the
    plain IDM at their own parameters: the spacing error trends with the speed
    within pairs, so ``gap vs speed`` is found and points to ``timegap`` (either
    sign: in closed loop the trend's sign depends on the transients, here it is
    opposite to c_gap's; the plain IDM's own data give p 0.8)."""
    mark = _one_step_marks("idm+timegap", IDM + [c_gap], noise=0.05)["gap vs speed"]
    assert mark.found, (mark.mean, mark.p_value)
    assert mark.points_to == ("timegap",)


def test_an_effect_seeds_the_random_numbers_as_its_token_did():
    """Random draws are keyed by labels: an effect object stands for its token,
    wherever it sits in the labels, so a search's numbers do not depend on
    whether the effect travels as an object or as its name."""
    from torchcf.diagnose.arms.search import derive_seed

    grade = parse_effect("grade(start=0,end=900,knots=4)")
    assert derive_seed(1, "step", DELAY, 3) == derive_seed(1, "step", "delay", 3)
    assert derive_seed((7, [grade]), OFFSET) == derive_seed(
        (7, [grade.token]), "offset"
    )
    assert derive_seed(1, DELAY) != derive_seed(1, OFFSET)
