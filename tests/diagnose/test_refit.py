"""Held-out pairs refitted (torchcf.diagnose.arms.refit, validation "refit"): the
effect pinned at one value, the model's own parameters refitted per pair, both
sides with common random numbers."""

from __future__ import annotations

import math

import numpy as np
import torch

from torchcf.abc.particles import Particles
from torchcf.abc.rejection import Rollout
from torchcf.config import validate_config
from torchcf.diagnose import Population
from torchcf.diagnose.arms.arena import Arena
from torchcf.diagnose.arms.refit import (
    Pin,
    RefitBudget,
    candidates,
    lifted,
    refit_scores,
    start,
)
from torchcf.diagnose.arms.search import CONVERGED
from torchcf.diagnose.arms.validation import design
from torchcf.diagnose.setup import LoopSetup
from torchcf.models import get_model
from torchcf.models.effects import parse_effect
from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs, synthetic_pairs

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
PRIORS = {"idm": get_model("idm").prior_bounds(torch.float64)}
BUDGET = RefitBudget(slots=3, copies=4, rounds=3)


def _population(theta: torch.Tensor, n_pairs: int, name: str = "idm") -> Population:
    """Particles of ``name`` dealt round-robin to ``n_pairs`` pairs (scored 0)."""
    q = theta.shape[0]
    particles = Particles(
        get_model(name),
        theta.double(),
        torch.arange(q) % n_pairs,
        torch.zeros(q, dtype=torch.float64),
        torch.arange(q),
    )
    return Population.from_particles([particles], n_pairs, q // n_pairs + 1)


def _prior_draws(q: int, seed: int) -> dict:
    """``q`` IDM particles drawn uniformly over its prior, as refit candidates."""
    box = PRIORS["idm"]
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(q, box.shape[0], generator=g, dtype=torch.float64)
    return {get_model("idm"): box[:, 0] + u * (box[:, 1] - box[:, 0])}


def test_candidates_drop_the_effect_and_lifting_pins_it():
    theta = torch.tensor([IDM + [0.7], IDM + [0.9]], dtype=torch.float64)
    arm = _population(theta, 2, "idm+delay")
    idm, delayed = get_model("idm"), get_model("idm+delay")
    found = candidates(arm, 1, {delayed: idm}, seed=0)
    assert [m.name for m in found] == ["idm"]
    torch.testing.assert_close(found[idm], torch.tensor([IDM], dtype=torch.float64))
    pinned = lifted(
        found, Pin(parse_effect("delay"), torch.tensor([0.4], dtype=torch.float64))
    )
    assert [m.name for m in pinned] == ["idm+delay"]
    assert pinned[delayed][:, -1].tolist() == [0.4]
    # an effect that cannot wrap a model leaves it as it is (HL has its own lag)
    hl = {get_model("hl"): get_model("hl").prior_bounds(torch.float64).mean(1)[None]}
    unwrapped = lifted(hl, Pin(parse_effect("lag"), torch.tensor([0.5])))
    assert [m.name for m in unwrapped] == ["hl"]


def test_candidates_stay_within_their_cap_from_the_same_fit_pairs():
    n_pairs = 40
    theta = torch.tensor(IDM, dtype=torch.float64).repeat(3 * n_pairs, 1)
    theta[:, 0] += torch.arange(3 * n_pairs, dtype=torch.float64) / 1000
    arm = _population(theta, n_pairs)
    found = candidates(arm, 3, {}, seed=5, cap=25)
    again = candidates(arm, 3, {}, seed=5, cap=25)
    idm = get_model("idm")
    assert found[idm].shape[0] == 25
    torch.testing.assert_close(found[idm], again[idm])


def test_the_effect_pinned_at_its_neutral_value_refits_as_without_it():
    """At the neutral value the lifted particles are the model itself, and the
    two refits draw the same steps: the scores agree exactly."""
    pairs = synthetic_pairs(get_model("idm"), IDM, 4, 120, seed=1, noise=0.05)
    rollout = Rollout(pairs, True, torch.float64)
    members = _prior_draws(12, seed=0)
    key = ("test", 1)
    without = refit_scores(members, rollout, BUDGET, PRIORS, {}, key)
    neutral = Pin(parse_effect("delay"), torch.tensor([0.0], dtype=torch.float64))
    with_neutral = refit_scores(members, rollout, BUDGET, PRIORS, {}, key, neutral)
    torch.testing.assert_close(with_neutral, without)
    assert bool(torch.isfinite(without).all())


def test_a_true_effect_pinned_at_its_value_fits_new_drivers_better():
    """Drivers who differ, all 0.8 s late: refitted from the same starts, the
    model with the delay pinned at 0.8 s fits every held-out driver better than
    the model without it; pinned where it is not (3 s), worse."""
    late = DriverMixture(["idm"], "delay", [0.8])
    pairs, drivers = heterogeneous_pairs(late, 6, 200, seed=2, noise=0.02)
    rollout = Rollout(pairs, True, torch.float64)
    members = {get_model("idm"): drivers.theta[:, :6]}  # each driver's own parameters
    budget = RefitBudget(slots=3, copies=8, rounds=3)
    key = ("test", 2)
    without = refit_scores(members, rollout, budget, PRIORS, {}, key)
    truth = Pin(parse_effect("delay"), torch.tensor([0.8], dtype=torch.float64))
    with_truth = refit_scores(members, rollout, budget, PRIORS, {}, key, truth)
    assert bool((with_truth < without).all())
    wrong = Pin(parse_effect("delay"), torch.tensor([3.0], dtype=torch.float64))
    with_wrong = refit_scores(members, rollout, budget, PRIORS, {}, key, wrong)
    assert float(with_wrong.sum()) > float(with_truth.sum())


def test_the_refit_never_moves_the_pinned_effect():
    pairs = synthetic_pairs(get_model("idm"), IDM, 3, 80, seed=3)
    rollout = Rollout(pairs, True, torch.float64)
    members = lifted(
        {get_model("idm"): torch.tensor([IDM], dtype=torch.float64)},
        Pin(parse_effect("offset"), torch.tensor([-2.0], dtype=torch.float64)),
    )
    population = start(members, rollout, slots=1)
    assert tuple(m.name for m in population.models) == ("idm+offset",)
    assert bool((population.theta[..., -1] == -2.0).all())


def test_the_refit_design_judges_an_arm_against_the_placebo():
    """validation "refit": the step's judge refits the held-out pairs from the
    placebo's picks once, and from each effect arm's picks with its pin."""
    pairs, _ = heterogeneous_pairs(DriverMixture(["idm"]), 12, 100, seed=4, noise=0.05)
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "compile": "off",
            "dtype": "float64",
            "diagnose": {"validation": "refit", "refit_rounds": 1},
        }
    )
    _, validation = design(LoopSetup.of(cfg), pairs, seed=0)
    assert validation.kind == "refit" and validation.units == "held-out pairs"
    assert validation.budget.rounds == 1
    arena = Arena.of(LoopSetup.of(cfg), pairs)
    box = PRIORS["idm"]
    theta = box.mean(1).repeat(arena.fit.pairs.n_pairs * 2, 1)
    placebo = _population(theta, arena.fit.pairs.n_pairs)
    judge = validation.judge(placebo, 2, step=1)
    assert judge.before.shape == (validation.n_units,)
    before, after = judge(placebo, {}, Pin(parse_effect("offset"), torch.tensor([0.0])))
    np.testing.assert_allclose(before, judge.before)
    np.testing.assert_allclose(after, before)  # neutral, same picks: the same
    assert all(math.isfinite(v) for v in before)


def test_a_refit_until_calm_is_the_fixed_refit_cut_where_it_settles():
    """``until_calm``: every round draws the numbers of its number, so a refit
    that settles after r rounds gives the fixed refit of r rounds; a search that
    cannot settle in its rounds runs them all."""
    pairs = synthetic_pairs(get_model("idm"), IDM, 4, 120, seed=5, noise=0.05)
    rollout = Rollout(pairs, True, torch.float64)
    members = _prior_draws(12, seed=3)
    key = ("test", 5)

    def refit(rounds: int, calm: bool) -> torch.Tensor:
        budget = RefitBudget(slots=3, copies=4, rounds=rounds, until_calm=calm)
        return refit_scores(members, rollout, budget, PRIORS, {}, key)

    summed = [float(refit(r, False).sum()) for r in range(41)]  # after r rounds
    calm = [summed[r - 1] - summed[r] < CONVERGED * summed[r - 1] for r in range(1, 41)]
    settled = next(r + 1 for r in range(1, 40) if calm[r - 1] and calm[r])
    assert settled < 40, "the search should settle within 40 rounds here"
    assert settled > 3, "a start this far off should need a few rounds"
    torch.testing.assert_close(refit(40, True), refit(settled, False))
    torch.testing.assert_close(refit(2, True), refit(2, False))
