"""The pieces of prediction against hand-computed and independent references
(torchcf.predict.scores, population, rollouts)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import differential_evolution

from tests.conftest import prior_draws, synthetic_pairs
from torchcf.models import get_model
from torchcf.predict.population import (
    PooledFit,
    pooled_fit,
    pooled_objective,
    population_model,
)
from torchcf.predict.rollouts import steps_between
from torchcf.predict.scores import coverage, displacement, summarize_rmse
from torchcf.sim.rollout import simulate


def test_spacing_rmse_per_pair_mean_median_and_pooled_by_hand():
    error = torch.tensor([[0.0, 0.0], [3.0, 1.0], [4.0, 1.0], [9.0, 1.0]])
    mask = torch.tensor([[True, True], [True, True], [True, True], [False, True]])
    summary, per_pair = summarize_rmse(error, mask)
    assert per_pair == pytest.approx([np.sqrt(25 / 3), np.sqrt(3 / 4)])
    assert summary.mean == pytest.approx(per_pair.mean())
    assert summary.median == pytest.approx(np.median(per_pair))
    assert summary.pooled == pytest.approx(np.sqrt((25 + 3) / 7))  # 7 steps
    broken = error.clone()
    broken[1, 1] = float("nan")  # a collided (blown-up) prediction is left out
    summary, per_pair = summarize_rmse(broken, mask)
    assert np.isnan(per_pair[1]) and (summary.pairs, summary.collided) == (1, 1)
    assert summary.mean == pytest.approx(np.sqrt(25 / 3))


def test_ade_fde_and_coverage_by_hand():
    error = torch.tensor([[0.0, 0.0], [-2.0, 1.0], [4.0, 3.0]])[:, None, :]  # (T, 1, D)
    mask = torch.tensor([[True], [True], [True]])
    ade, fde = displacement(error, mask)
    assert ade[0] == pytest.approx([2.0, 4.0 / 3.0])
    assert fde[0] == pytest.approx([4.0, 3.0])
    observed = torch.tensor([[5.0], [6.0], [9.0]])
    low, high = torch.full((3, 1), 5.5), torch.full((3, 1), 8.0)
    assert coverage(observed, low, high, mask) == pytest.approx(0.5)  # step 0 left out


def test_steps_between_start_the_follower_at_its_recorded_state():
    pairs = synthetic_pairs(n_pairs=3, n_steps=50)
    rest = steps_between(pairs, 20)
    assert rest.n_steps == 30 and rest.pair_ids == pairs.pair_ids
    assert torch.equal(rest.x_follow[0], pairs.x_follow[20])
    with pytest.raises(ValueError, match="fewer than 2"):
        steps_between(pairs, 49)


def _idm_pairs(theta: list[float], n_pairs: int = 5, n_steps: int = 150):
    """Pairs whose followers are one IDM driver behind synthetic leaders."""
    model = get_model("idm")
    leaders = synthetic_pairs(n_pairs=n_pairs, n_steps=n_steps, seed=3)
    out = simulate(
        model,
        torch.tensor([theta], dtype=torch.float64).expand(n_pairs, -1),
        leaders,
        torch.arange(n_pairs),
        dtype=torch.float64,
        return_traj=True,
    )
    series = leaders.series()
    series.update(x_follow=out.x, v_follow=out.v, a_follow=out.a)
    return type(leaders).from_arrays(series, dt=leaders.dt)


def test_the_pooled_search_never_loses_the_best_kept_particle_and_matches_de():
    """The pooled vector is at least as good as the best kept particle, and as
    good as scipy's differential evolution over the whole prior box (within
    5 %), from far fewer evaluations."""
    model = get_model("idm")
    pairs = _idm_pairs([1.4, 2.2, 30.0, 1.3, 2.5, 4.0])
    prior = model.prior_bounds(torch.float64)
    kept = prior_draws(model, 200, seed=1)
    _, value = pooled_objective(model, kept, pairs)
    fit = pooled_fit(model, kept, prior, pairs, seed=0)
    assert fit.collided == 0 and fit.objective <= float(value.min())

    def objective(theta: np.ndarray) -> np.ndarray:  # (K, S) vectorised
        collided, mean = pooled_objective(model, torch.from_numpy(theta.T), pairs)
        return torch.where(collided > 0, torch.full_like(mean, 1e3), mean).numpy()

    reference = differential_evolution(
        objective,
        prior.numpy(),
        vectorized=True,
        maxiter=60,
        popsize=15,
        seed=0,
        polish=False,
        tol=1e-8,
        updating="deferred",
    )
    assert fit.objective <= 1.05 * reference.fun + 0.05, (fit, reference.fun)
    de_vectors = (reference.nit + 1) * 15 * model.n_params  # generations x population
    assert fit.evaluated < de_vectors


def test_a_vector_that_collides_ranks_after_one_that_does_not():
    safe = PooledFit("idm", {"a": 1.0}, 3.0, 0, 1, 1, 0)
    crash = PooledFit("gfm", {"a": 1.0}, 1.0, 1, 1, 1, 0)
    assert population_model([crash, safe]) is safe
