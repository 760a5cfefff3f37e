"""torchcf.traffic.battery (plausibility of particles) and torchcf.traffic.safety
(the collision-avoidance bound of the scenes)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.traffic.test_traffic import sampler_of
from torchcf.models import FollowerState, get_model
from torchcf.traffic import (
    Battery,
    SafetyLayer,
    battery_speed,
    check_plausibility,
    interventions_per_model,
    ring_road,
)
from torchcf.traffic.battery import (
    braking_leader,
    collides,
    equilibrium_gap,
    rejects,
    standstill_leader,
    stop_and_go_leader,
)

#: LLCTG (tau, ks, kv, l): point-mass string stability <=> ks tau^2 + 2 kv tau >= 2
STABLE = [1.2, 0.5, 1.5, 5.0]  # 0.72 + 3.6 >= 2
UNSTABLE = [0.8, 0.3, 0.3, 5.0]  # 0.19 + 0.48 < 2
SLUGGISH = [1.0, 0.01, 0.01, 5.0]  # barely reacts: runs into a braking leader


def test_the_leaders_do_what_the_battery_says():
    dt = 0.1
    brake = braking_leader(25.0, 6.0, dt)
    deceleration = -brake.diff() / dt
    assert float(brake[0]) == 25.0 and float(brake[-1]) == 0.0
    assert float(deceleration.max()) == pytest.approx(6.0)
    assert float(brake[-int(10 / dt) :].abs().max()) == 0.0  # stands at the end
    stop_go = stop_and_go_leader(20.0, dt)
    assert float(stop_go.min()) == pytest.approx(0.0, abs=1e-9)
    assert float(stop_go.max()) == pytest.approx(20.0)
    start = standstill_leader(20.0, dt)
    assert float(start[0]) == 0.0 and float(start[-1]) == 20.0


def test_a_sluggish_follower_collides_and_a_tuned_one_does_not():
    theta = torch.tensor([STABLE, SLUGGISH], dtype=torch.float64)
    result = check_plausibility(get_model("llctg"), theta, Battery(speed=20.0))
    assert result.collided.tolist() == [False, True]
    assert result.scenario_collided["brake_8"].tolist() == [False, True]
    assert float(result.min_ttc[1]) == 0.0 and float(result.min_ttc[0]) > 0.5
    assert float(result.min_spacing[1]) <= 0.0 < float(result.min_spacing[0])
    assert result.started.tolist() == [True, True]
    summary = result.summary()
    assert summary.collided == 0.5 and summary.n_particles == 2


def test_the_string_ratio_matches_linear_theory():
    theta = torch.tensor([STABLE, UNSTABLE], dtype=torch.float64)
    ratio = check_plausibility(
        get_model("llctg"), theta, Battery(speed=15.0)
    ).string_ratio
    assert float(ratio[0]) < 1.0 < float(ratio[1])


def test_an_equilibrium_is_missing_above_the_models_desired_speed():
    """IDM with v0 = 20 m/s cannot follow at 25 m/s; with v0 = 40 it can."""
    idm = [[1.2, 2.0, v0, 1.3, 2.0, 4.0] for v0 in (20.0, 40.0)]
    theta = torch.tensor(idm, dtype=torch.float64)
    result = check_plausibility(get_model("idm"), theta, Battery(speed=25.0))
    assert result.equilibrium.tolist() == [False, True]
    assert math.isnan(float(result.string_ratio[0]))
    sampler = sampler_of({"idm": idm})
    sampler.assign(torch.tensor([[0], [1]]))
    gap, found = equilibrium_gap(sampler, 15.0)
    assert found.tolist() == [True, True]
    speed = torch.full((2, 1), 15.0, dtype=torch.float64)
    steady = sampler(gap[:, None], speed, speed, torch.zeros_like(speed))
    torch.testing.assert_close(steady, torch.zeros_like(steady), atol=1e-6, rtol=0)


@pytest.mark.slow  # the battery at three chunk sizes
def test_outcomes_do_not_depend_on_the_chunk():
    g = torch.Generator().manual_seed(3)
    low = torch.tensor([0.8, 0.3, 0.3, 1.0], dtype=torch.float64)
    high = torch.tensor([1.2, 2.3, 2.3, 11.0], dtype=torch.float64)
    theta = low + (high - low) * torch.rand(40, 4, generator=g, dtype=torch.float64)
    battery = Battery(speed=20.0, decelerations=(6.0,))
    whole = check_plausibility(get_model("llctg"), theta, battery)
    pieces = check_plausibility(get_model("llctg"), theta, battery, chunk=7)
    assert torch.equal(whole.collided, pieces.collided)
    # to rounding: vectorised kernels round a batch's tail differently
    torch.testing.assert_close(whole.min_ttc, pieces.min_ttc, rtol=1e-12, atol=0)
    torch.testing.assert_close(
        whole.string_ratio, pieces.string_ratio, rtol=1e-12, atol=0, equal_nan=True
    )
    # and each particle alone gives its row of the batch
    alone = check_plausibility(get_model("llctg"), theta[5:6], battery)
    assert float(alone.min_spacing[0]) == pytest.approx(float(whole.min_spacing[5]))


@pytest.mark.slow  # the whole battery per model
@pytest.mark.parametrize("name", ["hl", "fvdm", "llcs", "mpc"])
def test_the_filters_fast_test_agrees_with_the_whole_battery(name):
    """``collides`` (hardest braking first, survivors only, no platoon) says
    what ``check_plausibility(...).collided`` says, and the strict filter adds
    exactly the string-unstable particles."""
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    g = torch.Generator().manual_seed(11)
    unit = torch.rand(60, model.n_params, generator=g, dtype=torch.float64)
    theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * unit
    battery = Battery(speed=25.0)
    whole = check_plausibility(model, theta, battery)
    fast = collides(model, theta, battery, chunk=25)
    assert torch.equal(fast, whole.collided)
    strict = rejects(battery, reject_string_unstable=True)(model, theta)
    assert torch.equal(strict, whole.collided | whole.string_unstable())
    assert torch.equal(rejects(battery)(model, theta), whole.collided)


def test_battery_speed_and_bad_settings():
    v = torch.arange(100, dtype=torch.float64)[:, None].expand(-1, 2)
    assert battery_speed(v) == pytest.approx(float(torch.quantile(v[:, 0], 0.95)))
    assert battery_speed(torch.zeros(5, 2)) == 5.0
    for bad in ({"speed": -1.0}, {"decelerations": ()}, {"collision_spacing": -1.0},
                {"platoon_size": 1}, {"dt": 0.0}):  # fmt: skip
        with pytest.raises(ValueError):
            Battery(**bad)
    with pytest.raises(ValueError, match="theta must be"):
        check_plausibility(get_model("llctg"), torch.zeros(3, 5))


# ------------------------------------------------------------------ safety layer
def test_safe_speed_is_gipps_bound():
    layer = SafetyLayer(max_decel=6.0, leader_decel=7.0)
    s, v, v_lead, dt, length = 30.0, 20.0, 15.0, 0.1, 5.0
    b = 6.0
    by_hand = -b * dt / 2 + math.sqrt(
        b * b * dt * dt / 4 + b * (2 * (s - length) - v * dt + v_lead**2 / 7.0)
    )
    f64 = torch.float64
    got = layer.safe_speed(
        *(torch.tensor([x], dtype=f64) for x in (s, v, v_lead)), dt, length
    )
    assert float(got[0]) == pytest.approx(by_hand, rel=1e-12)
    # Stopping from v_safe at b after the step ends stop_spacing behind the
    # leader's own stop: the bound is tight.
    travelled = (v + by_hand) * dt / 2 + by_hand**2 / (2 * b)
    assert s - length + v_lead**2 / (2 * 7.0) - travelled == pytest.approx(
        0.0, abs=1e-9
    )
    # too close to stop at all: 0
    assert (
        float(
            layer.safe_speed(*(torch.tensor([x]) for x in (4.0, 0.0, 0.0)), dt, length)
        )
        == 0.0
    )


def test_the_layer_leaves_a_safe_step_alone_and_brakes_an_unsafe_one():
    layer = SafetyLayer()
    state = FollowerState(*(torch.tensor([0.0, 0.0], dtype=torch.float64),
                            torch.tensor([20.0, 20.0], dtype=torch.float64),
                            torch.zeros(2, dtype=torch.float64)))  # fmt: skip
    moved = FollowerState(
        torch.tensor([2.0, 2.0], dtype=torch.float64),
        torch.tensor([20.0, 20.0], dtype=torch.float64),
        torch.zeros(2, dtype=torch.float64),
    )
    spacing = torch.tensor([60.0, 12.0], dtype=torch.float64)  # far, then close
    v_lead = torch.tensor([20.0, 5.0], dtype=torch.float64)
    out, overridden = layer.apply(state, moved, spacing, v_lead, 0.1, 5.0)
    assert overridden.tolist() == [False, True]
    assert float(out.x[0]) == 2.0 and float(out.v[0]) == 20.0
    assert float(out.v[1]) == pytest.approx(20.0 - 0.8)  # full braking: 8 m/s^2
    assert float(out.a[1]) == pytest.approx(-8.0)
    assert float(out.x[1]) == pytest.approx(0.1 * (20.0 + 19.2) / 2)
    with pytest.raises(ValueError, match="max_decel"):
        SafetyLayer(max_decel=0.0)


def test_an_unstable_ring_collides_alone_and_not_with_the_layer():
    sampler = sampler_of(
        {"llctg": [UNSTABLE], "idm": [[1.2, 2.0, 30.0, 1.3, 2.0, 4.0]]}
    )
    model = torch.zeros(2, 20, dtype=torch.long)
    model[1] = 1  # ring 0: all LLCTG (unstable), ring 1: all IDM
    sampler.assign(model)
    alone = ring_road(sampler, 20 * 20.0, 3000, safety=None, record_every=None)
    safe = ring_road(sampler, 20 * 20.0, 3000, record_every=None)
    assert bool(alone.collided[0].any())
    assert not bool(safe.collided.any())
    assert int(safe.interventions[0].sum()) > 0
    counts = interventions_per_model(
        sampler.vehicle_model, safe.interventions, sampler.model_names
    )
    assert set(counts) == {"llctg", "idm"}
    assert counts["llctg"]["vehicles"] == 20
    assert counts["llctg"]["per_vehicle"] > 0
