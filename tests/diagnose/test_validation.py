"""The attribution's out-of-sample judges: validation windows in time (plain, and
begun early with the early steps unscored) and held-out pairs
(:mod:`torchcf.diagnose.arms.validation`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.conftest import prior_draws, synthetic_pairs
from torchcf.abc.particles import Particles
from torchcf.abc.rejection import Rollout
from torchcf.config import TrainConfig
from torchcf.diagnose import DiagnoseError, Population
from torchcf.diagnose.arms.validation import (
    Validation,
    WarmedRollout,
    coverage_scores,
    design,
    fit_part,
    resolve_validation,
    split_by_pair,
    split_in_time,
    validation_rollout,
    warmed_validation,
)
from torchcf.diagnose.setup import LoopSetup
from torchcf.models import get_model
from torchcf.sim.rollout import simulate

WEIGHTS = (0.5, 0.3, 0.2)


def _config(warmup: float) -> TrainConfig:
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm"],
            "dtype": "float64",
            "diagnose": {"validation_warmup": warmup, "fit_fraction": 0.6},
        }
    )


def _by_hand(model, theta, long, pair, skip: int) -> torch.Tensor:
    """The weighted RMSE over the long windows' steps ``skip ..``, from the
    simulated trajectories."""
    out = simulate(
        get_model(model), theta, long, pair, dtype=torch.float64, return_traj=True
    )
    scores = []
    for j, i in enumerate(pair.tolist()):
        n = int(long.mask[:, i].sum())
        rows = slice(skip, n)
        errors = (
            out.x[rows, j] - long.x_follow[rows, i],
            out.v[rows, j] - long.v_follow[rows, i],
            out.a[rows, j] - long.a_follow[rows, i],
        )
        rmse = [float(e.pow(2).mean().sqrt()) for e in errors]
        scores.append(sum(w * e for w, e in zip(WEIGHTS, rmse, strict=True)))
    return torch.tensor(scores, dtype=torch.float64)


@pytest.mark.parametrize("name", ["idm+delay", "hl+delay", "llcs+lag", "gfm"])
def test_a_warmed_validation_scores_only_the_steps_after_the_split(name):
    pairs = synthetic_pairs(n_pairs=5, n_steps=240, seed=3)
    model = get_model(name)
    long, warm = warmed_validation(pairs, 0.6, warmup=25)
    rollout = WarmedRollout(long, True, torch.float64, warm=warm)
    theta = prior_draws(model, 10, seed=2)
    pair = torch.arange(10) % pairs.n_pairs
    score, valid = rollout.score(model, theta, pair)
    expected = _by_hand(model, theta, long, pair, skip=25)
    finite = valid & torch.isfinite(expected)
    assert int(finite.sum()) >= 5
    torch.testing.assert_close(score[finite], expected[finite], rtol=1e-9, atol=1e-9)
    assert bool(torch.isinf(score[~valid]).all())


def test_the_warmed_windows_hold_the_pairs_of_the_plain_split():
    pairs = synthetic_pairs(n_pairs=4, n_steps=200, seed=1)
    fit, validation = split_in_time(pairs, 0.6)
    long, warm = warmed_validation(pairs, 0.6, warmup=30)
    assert long.n_steps == validation.n_steps + 30 and warm.n_steps == 30
    assert long.pair_ids == validation.pair_ids == warm.pair_ids
    # the long window's steps after the warm-up are the plain validation window
    torch.testing.assert_close(long.x_lead[30:], validation.x_lead)
    torch.testing.assert_close(warm.x_follow, fit.x_follow[-30:])
    # a warm-up longer than the fit window is cut to it (one step left to fit)
    long, warm = warmed_validation(pairs, 0.6, warmup=10_000)
    assert warm.n_steps == fit.n_steps - 1


def test_no_warmup_is_the_plain_validation_window():
    pairs = synthetic_pairs(n_pairs=4, n_steps=200, seed=1)
    assert validation_rollout(LoopSetup.of(_config(0.0)), pairs) is None
    rollout = validation_rollout(LoopSetup.of(_config(2.0)), pairs)
    assert isinstance(rollout, WarmedRollout) and rollout.warm.n_steps == 20
    assert math.isclose(rollout.pairs.dt, pairs.dt)


# ---------------------------------------------------------------- held-out pairs
def test_a_split_by_pair_is_seeded_disjoint_and_complete():
    pairs = synthetic_pairs(n_pairs=10, n_steps=60)
    fit, held = split_by_pair(pairs, 0.6, seed=3)
    assert (fit.n_pairs, held.n_pairs) == (6, 4)
    ids = sorted(fit.pair_ids + held.pair_ids)
    assert ids == sorted(pairs.pair_ids) and not set(fit.pair_ids) & set(held.pair_ids)
    again, _ = split_by_pair(pairs, 0.6, seed=3)
    other, _ = split_by_pair(pairs, 0.6, seed=4)
    assert again.pair_ids == fit.pair_ids != other.pair_ids
    # whole windows: the held-out pairs keep every step
    assert held.n_steps == pairs.n_steps


def test_a_split_by_pair_refuses_too_few_pairs():
    pairs = synthetic_pairs(n_pairs=3, n_steps=40)
    with pytest.raises(DiagnoseError, match="validation='time'"):
        split_by_pair(pairs, 0.6, seed=0)


def test_coverage_scores_are_the_minimum_distance_on_the_held_out_pairs():
    """Every pick on every held-out pair, its best: checked against the cost
    matrix of the picks simulated one model at a time (SPEC section 6)."""
    pairs = synthetic_pairs(n_pairs=8, n_steps=50)
    fit, held = split_by_pair(pairs, 0.5, seed=0)
    sets = [
        _particles(name, prior_draws(get_model(name), 12, seed=s), fit)
        for s, name in enumerate(("idm", "gfm"))
    ]
    population = Population.from_particles(sets, fit.n_pairs, 3)
    rollout = Rollout(held, True, torch.float64)
    got = coverage_scores(population, 2, rollout)
    picks = population.best(2)
    expected = torch.full((held.n_pairs,), math.inf, dtype=torch.float64)
    for name in picks.models:
        pair, slot = picks.model_slots(name)
        theta = picks.theta[pair, slot, : get_model(name).n_params]
        cost = simulate(
            get_model(name), theta, held, dtype=torch.float64
        ).score  # (Q, V)
        cost = torch.where(torch.isfinite(cost), cost, math.inf)
        expected = torch.minimum(expected, cost.min(0).values)
    torch.testing.assert_close(got, expected)
    # and Validation("pairs") gives the same numbers
    values = Validation("pairs", rollout).scores(population, 2)
    np.testing.assert_allclose(values, expected.numpy())


def test_the_design_follows_the_config():
    pairs = synthetic_pairs(n_pairs=10, n_steps=60)
    cfg = _config(0.0)
    fit, validation = design(LoopSetup.of(cfg), pairs, seed=0)
    assert validation.kind == "time" and fit.pairs.n_pairs == pairs.n_pairs
    assert fit.pairs.n_steps == 36
    cfg = cfg.model_copy(
        update={"diagnose": cfg.diagnose.model_copy(update={"validation": "pairs"})}
    )
    fit, validation = design(LoopSetup.of(cfg), pairs, seed=0)
    assert validation.kind == "pairs" and validation.units == "held-out pairs"
    assert (fit.pairs.n_pairs, validation.rollout.pairs.n_pairs) == (6, 4)
    assert fit.pairs.n_steps == pairs.n_steps


@pytest.mark.parametrize("kind", ["pairs", "refit"])
def test_a_warmup_with_held_out_pairs_is_refused(kind):
    with pytest.raises(ValueError, match="validation 'time' only"):
        TrainConfig.model_validate(
            {
                "data": {"name": "car-model-2"},
                "models": ["idm"],
                "diagnose": {"validation": kind, "validation_warmup": 2.0},
            }
        )
    # with "auto", a warm-up asks for windows in time
    cfg = TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm"],
            "diagnose": {"validation_warmup": 2.0},
        }
    )
    assert resolve_validation(cfg.diagnose, 327) == "time"


def _particles(name: str, theta: torch.Tensor, pairs) -> Particles:
    """Particles of ``name`` on pairs dealt round-robin, scored there."""
    pair = torch.arange(theta.shape[0]) % pairs.n_pairs
    score, _ = Rollout(pairs, True, torch.float64).score(get_model(name), theta, pair)
    return Particles(get_model(name), theta, pair, score, torch.arange(theta.shape[0]))


@pytest.mark.parametrize(
    ("n_pairs", "permutations", "warmup", "kind"),
    [
        (14, 20_000, 0.0, "time"),  # 2^-14 > 1/20 001
        (15, 20_000, 0.0, "crossfit"),  # every pair a unit: 2^-15 < 1/20 001
        (24, 20_000, 0.0, "crossfit"),
        (10, 1_000, 0.0, "crossfit"),  # 10 units reach 1/1 001
        (9, 1_000, 0.0, "time"),
        (327, 20_000, 2.0, "time"),  # a warm-up asks for windows in time
    ],
)
def test_auto_crossfits_where_the_pairs_reach_the_tests_resolution(
    n_pairs, permutations, warmup, kind
):
    settings = _config(warmup).diagnose.model_copy(
        update={"permutations": permutations}
    )
    assert settings.validation == "auto"
    assert resolve_validation(settings, n_pairs) == kind
    forced = settings.model_copy(update={"validation": "time"})
    assert resolve_validation(forced, n_pairs) == "time"


def test_what_is_decided_before_the_arms_sees_only_their_fit_part():
    """The knot spacing of a road profile is chosen on the part the arms are
    fitted on: the fit windows, the fit pairs whole (never a held-out pair),
    or every pair whole where every pair is fitted (cross-fitting)."""
    pairs = synthetic_pairs(n_pairs=40, n_steps=50)
    series = {"x": [pairs.x_follow[:, i].numpy() for i in range(pairs.n_pairs)]}
    cfg = _config(0.0)

    def validation(kind: str) -> TrainConfig:
        update = {"validation": kind}
        return cfg.model_copy(
            update={"diagnose": cfg.diagnose.model_copy(update=update)}
        )

    cut = fit_part(LoopSetup.of(validation("time")), 0, pairs.n_steps, series)
    assert len(cut["x"]) == 40 and all(len(a) == 30 for a in cut["x"])
    kept = fit_part(
        LoopSetup.of(validation("refit")), 7, pairs.n_steps, series
    )  # 16 held out
    fit, _ = split_by_pair(pairs, 0.6, seed=7)
    assert len(kept["x"]) == fit.n_pairs == 24
    for array, i in zip(kept["x"], fit.pair_ids, strict=True):
        np.testing.assert_array_equal(array, series["x"][i])
    whole = fit_part(
        LoopSetup.of(validation("auto")), 7, pairs.n_steps, series
    )  # crossfit
    assert len(whole["x"]) == 40 and all(len(a) == 50 for a in whole["x"])
