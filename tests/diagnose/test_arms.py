"""The validation windows of the attribution: plain, and begun early with the
early steps unscored (:class:`torchcf.diagnose.arms.WarmedRollout`)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import prior_draws, synthetic_pairs
from torchcf.config import TrainConfig
from torchcf.diagnose.arms import (
    WarmedRollout,
    split_in_time,
    validation_rollout,
    warmed_validation,
)
from torchcf.models import get_model
from torchcf.sim import simulate

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
    out = simulate(model, theta, long, pair, dtype=torch.float64, return_traj=True)
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
    assert validation_rollout(_config(0.0), pairs) is None
    rollout = validation_rollout(_config(2.0), pairs)
    assert isinstance(rollout, WarmedRollout) and rollout.warm.n_steps == 20
    assert math.isclose(rollout.pairs.dt, pairs.dt)
