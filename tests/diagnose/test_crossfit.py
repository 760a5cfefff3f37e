"""Cross-fitting (validation "crossfit"): every training pair is refitted as a
held-out pair, from the picks of the other groups (drivers, runs) only."""

from __future__ import annotations

import math

import pandas as pd
import torch

from torchcf.abc.particles import Particles
from torchcf.abc.rejection import Rollout
from torchcf.config import validate_config
from torchcf.diagnose import Population
from torchcf.diagnose.arms.refit import (
    Exclusion,
    Layout,
    Pin,
    RefitBudget,
    refit_scores,
    sourced_candidates,
    start,
)
from torchcf.diagnose.arms.validation import design, free_effect_windows, pair_groups
from torchcf.diagnose.setup import LoopSetup
from torchcf.models import get_model
from torchcf.models.effects import parse_effect
from torchcf.sim.synthetic import synthetic_pairs

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
PRIORS = {"idm": get_model("idm").prior_bounds(torch.float64)}


def _own_picks(n_pairs: int, per_pair: int) -> tuple[Population, torch.Tensor]:
    """Per pair ``per_pair`` IDM particles of its own (first parameter tells the
    pair: 1 + pair / 100), and those parameters (Q, K)."""
    q = n_pairs * per_pair
    pair = torch.arange(q) % n_pairs
    theta = torch.tensor(IDM, dtype=torch.float64).repeat(q, 1)
    theta[:, 0] = 1.0 + pair / 100 + (torch.arange(q) // n_pairs) / 1e4
    particles = Particles(
        get_model("idm"),
        theta,
        pair,
        torch.zeros(q, dtype=torch.float64),
        torch.arange(q),
    )
    return Population.from_particles([particles], n_pairs, per_pair), theta


def test_exclusion_allows_a_candidate_held_by_another_group():
    # candidate 0: held by group 0 alone; 1: by groups 0 and 1; 2: by group 1
    sources = torch.tensor([[1, 0], [1, 1], [0, 1]], dtype=torch.bool)
    held = Exclusion((sources,), torch.tensor([0, 1, 0]))
    allowed = held.allowed(0)  # (Q, V)
    assert allowed.tolist() == [
        [False, True, False],
        [True, True, True],
        [True, False, True],
    ]


def test_sourced_candidates_merge_repeats_and_keep_every_source():
    population, _ = _own_picks(4, 2)
    # pairs 0 and 1 share a particle: the same parameters kept by both
    population.theta[1, 0] = population.theta[0, 0]
    groups = torch.tensor([0, 1, 2, 2])
    found, sources = sourced_candidates(population, 2, {}, seed=0, groups=groups)
    theta = found[get_model("idm")]
    assert theta.shape[0] == 7  # 8 picks, one repeat
    row = (theta == population.theta[0, 0]).all(1).nonzero().item()
    assert sources[0][row].tolist() == [True, True, False]


def test_a_pair_never_starts_from_its_own_groups_picks():
    pairs = synthetic_pairs(get_model("idm"), IDM, n_pairs=6, n_steps=60)
    population, _ = _own_picks(6, 3)
    groups = torch.tensor([0, 0, 1, 1, 2, 2])  # two windows of each driver
    found, sources = sourced_candidates(population, 3, {}, seed=0, groups=groups)
    rollout = Rollout(pairs, True, torch.float64)
    started = start(found, rollout, 4, Exclusion(sources, groups))
    owner = torch.round((started.theta[..., 0] - 1.0) * 100)  # (V, S) source pair
    for pair in range(6):
        filled = started.filled[pair]
        assert filled.any()
        sources_of = groups[owner[pair, filled].long()]
        assert not (sources_of == groups[pair]).any()
    # without the exclusion a pair's own picks are among its candidates
    free = start(found, rollout, 18, None)
    own = torch.round((free.theta[..., 0] - 1.0) * 100)
    assert any((own[p][free.filled[p]] == p).any() for p in range(6))


def test_pair_groups_follow_the_index_run_and_follower():
    pairs = synthetic_pairs(get_model("idm"), IDM, n_pairs=4, n_steps=40)
    index = pd.DataFrame({"run": ["a", "a", "a", "b"], "follower": [1, 1, 2, 1]})
    assert pair_groups(pairs, index).tolist() == [0, 0, 1, 2]
    assert pair_groups(pairs, None).tolist() == [0, 1, 2, 3]
    short = index.iloc[:2]  # does not cover the pairs: each its own
    assert pair_groups(pairs, short).tolist() == [0, 1, 2, 3]


def test_crossfit_judges_every_training_pair():
    pairs = synthetic_pairs(get_model("idm"), IDM, n_pairs=16, n_steps=50)
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "abc": {"n_particles": 100},
            "diagnose": {"validation": "crossfit"},
        }
    )
    fit, validation = design(LoopSetup.of(cfg), pairs, seed=0)
    assert validation.kind == "crossfit"
    assert fit.pairs.n_pairs == validation.n_units == 16
    assert validation.groups.tolist() == list(range(16))
    assert "once" in validation.units
    one = torch.zeros(16, dtype=torch.int64)
    try:
        design(LoopSetup.of(cfg), pairs, seed=0, groups=one)
    except Exception as error:  # one group: nothing to hold out
        assert "crossfit" in str(error)
    else:  # pragma: no cover - the guard must fire
        raise AssertionError("one group was accepted")
    assert not math.isnan(float(fit.pairs.dt))


def test_a_free_driver_effect_is_searched_per_pair_and_judged_later_in_time():
    """refit_effect "free": the refit starts the delay at the pinned value and
    searches it on each pair's first steps; scored on the later steps, drivers
    who wait 1.2 s are fitted better than with the delay held at 0.2 s, every
    one of them."""
    delayed = get_model("idm+delay")
    pairs = synthetic_pairs(delayed, IDM + [1.2], n_pairs=4, n_steps=300, noise=0.02)
    judged, first, later = free_effect_windows(pairs, 0.6)
    assert judged.tolist() == [0, 1, 2, 3]
    assert (first.n_steps, later.n_steps) == (180, 120)
    found = {get_model("idm"): torch.tensor([IDM], dtype=torch.float64)}
    budget = RefitBudget(slots=2, copies=8, rounds=8)
    rollout, scored_on = (Rollout(p, True, torch.float64) for p in (first, later))
    value = torch.tensor([0.2], dtype=torch.float64)
    scores = {}
    for free in (False, True):
        pin = Pin(parse_effect("delay"), value, free=free)
        where = Layout(scored_on=scored_on)
        scores[free] = refit_scores(
            found, rollout, budget, PRIORS, {}, ("t",), pin, where
        )
    assert bool((scores[True] < scores[False]).all()), scores
    assert float(scores[True].sum()) < 0.6 * float(scores[False].sum()), scores
