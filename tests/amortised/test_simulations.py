"""The training set: leader windows of the data, followers by the rollout."""

from __future__ import annotations

import math

import pytest
import torch

from torchcf.amortised import (
    ParameterSpace,
    SimulatedSet,
    SimulationSettings,
    TrainingSimulator,
)
from torchcf.amortised.features import channel_features
from torchcf.models import get_model
from torchcf.sim.rollout import simulate

from .conftest import SIMULATION


def test_a_set_has_the_documented_shapes_and_counts(simulator, space):
    drawn = simulator.draw("shapes", 700)  # two chunks of 512
    assert drawn.n_drawn == 700
    assert len(drawn) == 700 - drawn.n_invalid
    assert drawn.features.shape == (len(drawn), 5, SIMULATION.window_steps)
    assert drawn.features.dtype == torch.float32
    assert torch.isfinite(drawn.features).all()
    # both models drawn, in about equal shares
    assert drawn.drawn.tolist()[0] == pytest.approx(350, abs=60)
    unit = drawn.unit
    ovm = drawn.model == 1
    assert unit[ovm, 5].isnan().all() and not unit[~ovm].isnan().any()
    assert bool(((unit[~unit.isnan()] >= 0) & (unit[~unit.isnan()] < 1)).all())
    theta = drawn.theta(space)
    assert torch.allclose(space.to_unit(0, theta[~ovm]), unit[~ovm])


def test_a_set_is_a_function_of_seed_and_name(simulator, space, leader_pairs):
    first = simulator.draw("again", 300)
    second = simulator.draw("again", 300)
    for a, b in zip(first, second, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    other = simulator.draw("other", 300)
    assert not torch.equal(first.unit[:5, 0], other.unit[:5, 0])
    reseeded = TrainingSimulator(space, leader_pairs, SIMULATION, seed=1)
    assert not torch.equal(reseeded.draw("again", 300).unit[:5, 0], first.unit[:5, 0])
    # a chunk's first examples do not depend on how many are drawn
    shorter = simulator.draw("again", 100)
    kept = first.model.shape[0] - (first.n_invalid - shorter.n_invalid)
    assert kept >= len(shorter)
    torch.testing.assert_close(
        shorter.unit, first.unit[: len(shorter)], rtol=0, atol=0, equal_nan=True
    )


def test_an_example_is_the_rollout_behind_its_leader_window(simulator, space):
    """Rebuild one example by hand: a window of a pair, the follower from the
    observed state at its start; equal to the set's features up to the noise."""
    quiet = TrainingSimulator(
        space,
        simulator.pairs,
        SimulationSettings(window_steps=200, noise=type(SIMULATION.noise)(0, 0, 0)),
        seed=3,
    )
    drawn = quiet.draw("by-hand", 40)
    example = 0
    model = int(drawn.model[example])
    theta = drawn.theta(space)[example : example + 1, : space.n_params[model]]
    pairs = simulator.pairs
    spacing = float(torch.sinh(drawn.features[example, 0, 0]) * 15.0 + 30.0)
    best = math.inf
    # the example's window: a start with its first spacing whose rollout matches
    for pair in range(pairs.n_pairs):
        for start in range(0, pairs.n_steps - 200 + 1):
            observed = float(pairs.x_lead[start, pair] - pairs.x_follow[start, pair])
            best = min(best, abs(observed - spacing))
            if abs(observed - spacing) > 1e-3:
                continue
            window = pairs.subset([pair])
            steps = slice(start, start + 200)
            sliced = type(pairs).from_arrays(
                {f: t[steps] for f, t in window.series().items()}, dt=pairs.dt
            )
            out = simulate(
                space.models[model], theta.float(), sliced, [0],
                dtype=torch.float32, return_traj=True,
            )  # fmt: skip
            rebuilt = channel_features(
                sliced.x_lead, sliced.v_lead, sliced.a_lead, (out.x, out.v, out.a)
            )
            if torch.allclose(rebuilt[0], drawn.features[example], atol=1e-4):
                return
    pytest.fail(f"no window of the data gives example {example} (closest {best})")


def test_pairs_shorter_than_the_window_are_skipped(simulator, space):
    pairs = simulator.pairs
    mask = pairs.mask.clone()
    mask[150:, 1:] = False  # every pair but the first is 150 steps long
    ragged = type(pairs).from_arrays(pairs.series(), dt=pairs.dt, mask=mask)
    windows = TrainingSimulator(space, ragged, SIMULATION, seed=0)
    assert windows.eligible.tolist() == [0]
    mask[150:, 0] = False
    short = type(pairs).from_arrays(pairs.series(), dt=pairs.dt, mask=mask)
    with pytest.raises(ValueError, match="no training pair has 200 valid steps"):
        TrainingSimulator(space, short, SIMULATION, seed=0)


def test_invalid_rollouts_are_discarded_and_counted(simulator):
    """Linear followers whose desired spacing is negative: every one crashes
    into its leader (non-positive spacing, SPEC section 2)."""
    llcs = get_model("llcs")
    into_the_leader = torch.tensor([[-60.0, -50.0], [0.3, 2.3], [0.3, 2.3]])
    rash = TrainingSimulator(
        ParameterSpace([llcs], [into_the_leader]), simulator.pairs, SIMULATION
    )
    drawn = rash.draw("crash", 64)
    assert drawn.n_invalid == 64 and len(drawn) == 0
    assert drawn.features.shape == (0, 5, 200)
    half = ParameterSpace(
        [llcs, get_model("idm")], [into_the_leader, get_model("idm").prior_bounds()]
    )
    mixed = TrainingSimulator(half, simulator.pairs, SIMULATION).draw("crash", 64)
    assert mixed.invalid.tolist() == [int(mixed.drawn[0]), 0]
    assert (mixed.model == 1).all() and torch.isfinite(mixed.features).all()


def test_sets_concatenate():
    empty = torch.zeros(0, 5, 3)
    one = SimulatedSet(
        empty, torch.zeros(0, dtype=torch.long), torch.zeros(0, 2),
        torch.tensor([2, 1]), torch.tensor([2, 0]),
    )  # fmt: skip
    both = SimulatedSet.concat([one, one])
    assert both.n_drawn == 6 and both.n_invalid == 4 and len(both) == 0
