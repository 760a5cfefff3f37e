"""The search's early rejection (torchcf.diagnose.arms.search): copies stopped above
their pair's admission ceiling leave every population as a search that runs
them to the end."""

from __future__ import annotations

import math

import pytest
import torch

import torchcf.diagnose.arms.search as search
from torchcf.abc.particles import Particles
from torchcf.abc.rejection import prior_stream
from torchcf.config import validate_config
from torchcf.diagnose import Population
from torchcf.diagnose.arms.candidates import (
    prior_particles,
)
from torchcf.diagnose.arms.population import merge
from torchcf.diagnose.arms.search import Noise, admission_ceiling, model_bounds
from torchcf.diagnose.setup import LoopSetup
from torchcf.models import get_model
from torchcf.sim.synthetic import synthetic_pairs

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]


def _start(n_pairs: int = 5, size: int = 4):
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},  # unused: the pairs are passed
            "models": ["idm", "llctg"],
            "abc": {"n_particles": 400},
            "compile": "off",
        }
    )
    pairs = synthetic_pairs(
        get_model("idm+delay"), IDM + [0.6], n_pairs, 200, seed=3, noise=0.05
    )
    rollout = LoopSetup.of(cfg).rollout(pairs)
    models = [get_model(m) for m in ("idm", "llctg")]
    bounds = {m: model_bounds(m, {}) for m in models}
    seed = LoopSetup.of(cfg).seed
    streams = [prior_stream(m, bounds[m], seed, rollout) for m in models]
    sets = [prior_particles(s, rollout, (150,), size)[0] for s in streams]
    return Population.from_particles(sets, n_pairs, size), rollout, bounds


def _searched(population, rollout, bounds, monkeypatch, *, pruned: bool):
    if not pruned:
        monkeypatch.setattr(
            search,
            "admission_ceiling",
            lambda p: torch.full((p.n_pairs,), math.inf, dtype=torch.float64),
        )
    current = {m: m.param_names for m in population.models}
    found = search.local_search(
        population, rollout, bounds, Noise((11,), current),
        {m: m for m in population.models}, rounds=3, copies=6,
    )  # fmt: skip
    monkeypatch.undo()
    return found


def test_early_rejection_leaves_the_searched_population_unchanged(monkeypatch):
    population, rollout, bounds = _start()
    stopped = []
    score_on = search.score_on

    def counted(rollout, model, theta, pair, ceiling=None):
        scores = score_on(rollout, model, theta, pair, ceiling)
        if ceiling is not None:
            full = score_on(rollout, model, theta, pair)
            # a stopped copy is one whose whole rollout scores above the ceiling
            gone = torch.isinf(scores) & torch.isfinite(full)
            assert bool((full[gone] > ceiling[gone]).all())
            stopped.append(int(gone.sum()))
        return scores

    monkeypatch.setattr(search, "score_on", counted)
    pruned = _searched(population, rollout, bounds, monkeypatch, pruned=True)
    assert sum(stopped) > 0  # the ceiling did stop copies
    full = _searched(population, rollout, bounds, monkeypatch, pruned=False)
    assert pruned.models == full.models
    for name in ("model", "score", "index"):
        assert torch.equal(getattr(pruned, name), getattr(full, name)), name
    assert torch.equal(pruned.theta.nan_to_num(-1.0), full.theta.nan_to_num(-1.0))


def test_the_ceiling_is_the_worst_distinct_kept_score_or_open():
    idm = get_model("idm")
    theta = torch.tensor([IDM] * 5, dtype=torch.float64)
    # pair 0 full of distinct particles; pair 1 holds one particle twice (the
    # merge drops the repeat: room for one more); pair 2 has an empty slot
    particles = Particles(
        idm,
        theta,
        torch.tensor([0, 0, 1, 1, 2]),
        torch.tensor([0.3, 0.5, 0.4, 0.4, 0.2], dtype=torch.float64),
        torch.tensor([0, 1, 2, 2, 4]),
    )
    population = Population.from_particles([particles], 3, 2)
    ceiling = admission_ceiling(population)
    assert ceiling[0] == pytest.approx(0.5)
    assert math.isinf(ceiling[1]) and math.isinf(ceiling[2])
    # what the ceiling promises: a particle above it does not enter the merge
    assert torch.equal(merge([population], 2).score[0], population.score[0])
