"""torchcf.sim.synthetic: the Gipps follower outside the pool, and data it drives."""

from __future__ import annotations

import math

import pytest
import torch

from torchcf.models import MODELS, AugmentedModel, Perception, get_model, parse_effect
from torchcf.sim.synthetic import Gipps, synthetic_pairs

#: a, b, b_lead, v0, tau, size
THETA = [1.5, 2.5, 3.0, 30.0, 0.8, 7.0]


def _command(spacing: float, v: float, v_lead: float) -> float:
    model = Gipps()
    p = model.unpack(torch.tensor([THETA], dtype=torch.float64))
    obs = Perception(
        spacing=torch.tensor([spacing], dtype=torch.float64),
        v=torch.tensor([v], dtype=torch.float64),
        v_lead=torch.tensor([v_lead], dtype=torch.float64),
        a=torch.zeros(1, dtype=torch.float64),
        leader_length=5.0,
    )
    return float(model.command(p, obs)[0])


def _by_hand(spacing: float, v: float, v_lead: float) -> float:
    """Gipps (1981), eqs. (2) and (5), with b > 0 as braking, over one tau."""
    a, b, b_lead, v0, tau, size = THETA
    v_free = v + 2.5 * a * tau * (1 - v / v0) * math.sqrt(0.025 + v / v0)
    root = b * b * tau * tau + b * (2 * (spacing - size) - v * tau + v_lead**2 / b_lead)
    v_safe = -b * tau + math.sqrt(max(root, 0.0))
    return (max(min(v_free, v_safe), 0.0) - v) / tau


@pytest.mark.parametrize(
    "spacing, v, v_lead",
    [
        (200.0, 15.0, 15.0),  # free road: the acceleration branch
        (25.0, 15.0, 15.0),  # following: the safe-speed branch
        (12.0, 15.0, 5.0),  # closing in fast: hard braking
        (4.0, 10.0, 0.0),  # too close to stop: the root reads 0, target 0
        (50.0, 0.0, 0.0),  # standing start
    ],
)
def test_gipps_command_matches_the_hand_formula(spacing, v, v_lead):
    assert _command(spacing, v, v_lead) == pytest.approx(
        _by_hand(spacing, v, v_lead), rel=1e-12, abs=1e-12
    )


def test_gipps_is_outside_the_pool_but_takes_effects():
    assert "gipps" not in MODELS
    delayed = AugmentedModel(Gipps(), [parse_effect("delay")])
    assert delayed.param_names == Gipps().param_names + ("t_delay",)
    assert get_model(delayed) is delayed


def test_a_delayed_gipps_follower_reacts_later():
    """Data driven by a model object: valid followers, and a 1.2 s delay shows
    as a later response to the leader's braking."""
    plain = synthetic_pairs(Gipps(), THETA, 6, 500, seed=3)
    delayed = synthetic_pairs(
        AugmentedModel(Gipps(), [parse_effect("delay")]), THETA + [1.2], 6, 500, seed=3
    )
    assert torch.equal(plain.x_lead, delayed.x_lead)
    for pairs in (plain, delayed):
        assert bool((pairs.x_lead - pairs.x_follow > 0).all())

    def lag_of_best_match(pairs) -> float:
        lags = range(0, 40)
        lead, follow = pairs.a_lead, pairs.a_follow
        fit = [float((follow[k:] * lead[: lead.shape[0] - k]).sum()) for k in lags]
        return 0.1 * max(lags, key=lambda k: fit[k])

    assert lag_of_best_match(delayed) - lag_of_best_match(plain) == pytest.approx(
        1.2, abs=0.3
    )
    assert "gipps+delay" in delayed.notes[0]


# ------------------------------------------------- drivers who differ
def test_every_heterogeneous_pair_has_its_own_plausible_driver():
    """A two-model mixture in equal shares, every driver its own parameters
    within the prior, replayable from its parameters, following plausibly;
    ragged prefix masks; the same seed the same pairs."""
    from torchcf.sim.rollout import simulate
    from torchcf.sim.synthetic import (
        PLAUSIBLE_MIN_GAP,
        DriverMixture,
        heterogeneous_pairs,
    )

    mixture = DriverMixture(["idm", "gfm"], "delay", [0.5])
    pairs, drivers = heterogeneous_pairs(mixture, 8, 200, seed=3, lengths=(0.6, 1.0))
    assert drivers.model == ("idm+delay", "gfm+delay") * 4
    idm = drivers.theta[::2, :7]
    assert len({tuple(row) for row in idm.tolist()}) == 4  # all differ
    box = get_model("idm").prior_bounds(torch.float64)
    assert bool(((idm[:, :6] >= box[:, 0]) & (idm[:, :6] <= box[:, 1])).all())
    assert bool((idm[:, 6] == 0.5).all())
    valid = pairs.mask.sum(0)
    assert int(valid.min()) >= 120 and int(valid.max()) <= 200
    assert bool((pairs.mask[:-1] >= pairs.mask[1:]).all())  # prefix masks
    # without noise, each follower is its driver's rollout behind its leader
    index = torch.arange(0, 8, 2)
    replay = simulate(
        get_model("idm+delay"), idm, pairs, index, dtype=torch.float64, return_traj=True
    )
    observed = pairs.x_follow[:, index]
    torch.testing.assert_close(
        torch.where(pairs.mask[:, index], replay.x - observed, 0.0),
        torch.zeros_like(observed), atol=1e-6, rtol=0,
    )  # fmt: skip
    gap = pairs.x_lead - pairs.x_follow - pairs.leader_length
    assert float(gap[pairs.mask].min()) >= PLAUSIBLE_MIN_GAP
    again, _ = heterogeneous_pairs(mixture, 8, 200, seed=3, lengths=(0.6, 1.0))
    torch.testing.assert_close(again.x_follow, pairs.x_follow)


def test_heterogeneous_pairs_refuse_a_box_without_plausible_drivers():
    from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs

    # IDM with a desired time gap of 10 s: no plausible follower (time gap <= 4 s)
    box = get_model("idm").prior_bounds(torch.float64).clone()
    box[3] = torch.tensor([9.9, 10.0])
    with pytest.raises(ValueError, match="too few plausible drivers of idm"):
        heterogeneous_pairs(DriverMixture(["idm"], boxes={"idm": box}), 4, 200, seed=0)
