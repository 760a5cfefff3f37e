"""torchcf.traffic: a platoon is the calibration rollout; the ring obeys its physics."""

from __future__ import annotations

import pytest
import torch

from tests.conftest import synthetic_pairs
from tests.traffic.test_sampler import make_posterior
from torchcf import HybridSampler, PairSet, get_model, simulate
from torchcf.models import FollowerState
from torchcf.sim.synthetic import leader_profiles
from torchcf.traffic.scenarios import (
    RingStart,
    RingState,
    pair_leader,
    platoon,
    ring_initial_state,
    ring_road,
)

#: One of each kind: point masses, HL's lag, MPC, a delay (memory), an added lag
#: and a road grade (reads the road position).
KINDS = ("idm", "gfm", "hl", "mpc", "llctg+delay", "llcs+lag", "ovm+grade")


def sampler_of(models: dict[str, list[list[float]]], dtype=torch.float64):
    """A sampler whose learned set is exactly these parameter rows."""
    return HybridSampler(
        [get_model(name) for name in models],
        [torch.tensor(rows, dtype=torch.float64) for rows in models.values()],
        dt=0.1,
        dtype=dtype,
    )


# -------------------------------------------------------------------- platoon
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_platoon_of_one_reproduces_simulate(dtype):
    """Every model's particles on every pair, mixed in one platoon batch, equal
    the rollout of torchcf.simulate, step by step."""
    pairs = synthetic_pairs(n_pairs=2, n_steps=150)
    posterior = make_posterior({name: 2 for name in KINDS}, seed=3)
    sampler = HybridSampler.from_posterior(posterior, dt=pairs.dt, dtype=dtype)
    # Scenario = (particle, pair): every particle on every pair.
    particle = torch.arange(sampler.n_particles).repeat_interleave(pairs.n_pairs)
    pair = torch.arange(pairs.n_pairs).repeat(sampler.n_particles)
    sampler.assign(particle[:, None])  # (S, 1): one follower per scenario
    x_leader, v_leader, start = pair_leader(pairs, pair)
    out = platoon(sampler, x_leader, v_leader, start=start, safety=None)
    assert out.x.shape == (pairs.n_steps, particle.numel(), 1)
    assert out.x.dtype == dtype

    for name in KINDS:
        rows = sampler.particle_ids(name)
        theta = sampler.particles(name)
        mine = torch.isin(particle, rows)
        index = pair[mine]
        theta_per_scenario = theta[particle[mine] - rows[0]]
        ref = simulate(
            get_model(name),
            theta_per_scenario,
            pairs,
            index,
            dtype=dtype,
            return_traj=True,
        )
        for got, want in ((out.x, ref.x), (out.v, ref.v), (out.a, ref.a)):
            # The same arithmetic in the same order: equal, not merely close.
            torch.testing.assert_close(
                got[:, mine, 0], want, rtol=0, atol=0, equal_nan=True
            )
        assert torch.equal(out.valid[mine], ref.valid), name


def test_followers_follow_each_other_as_the_rollout_does():
    """Follower j's leader is follower j - 1: replaying follower 0's simulated
    trajectory as a pair's leader gives follower 1."""
    x_lead, v_lead, a_lead = leader_profiles(2, 300, 0.1, seed=2)
    sampler = sampler_of(
        {"idm": [[1.5, 2.0, 30.0, 1.2, 2.0, 4.0]], "hl": [[1.0, 0.3, 1, 1, -1, 5]]}
    )
    sampler.assign(torch.tensor([[0, 1, 0], [1, 0, 1]]))  # (S, n) = (2, 3)
    out = platoon(sampler, x_lead, v_lead, initial_spacing=torch.tensor([25.0, 30.0]))
    assert bool(out.valid.all())
    for j in (1, 2):
        # The previous follower's trajectory as the leader; follower j's start.
        ahead = PairSet.from_arrays(
            (
                out.x[:, :, j - 1],
                out.v[:, :, j - 1],
                out.a[:, :, j - 1],
                out.x[:, :, j],
                out.v[:, :, j],
                out.a[:, :, j],
            ),
            dt=0.1,
        )
        for s in range(2):
            particle = int(sampler.vehicle_particle.reshape(2, 3)[s, j])
            name = sampler.model_names[int(sampler.particle_model[particle])]
            theta = sampler.particles(name)[:1]
            ref = simulate(
                get_model(name),
                theta,
                ahead,
                [s],
                dtype=torch.float64,
                return_traj=True,
            )
            torch.testing.assert_close(out.x[:, s, j], ref.x[:, 0], rtol=0, atol=1e-9)
            torch.testing.assert_close(out.v[:, s, j], ref.v[:, 0], rtol=0, atol=1e-9)


def test_collisions_are_flagged_and_the_dynamics_kept():
    """A sluggish follower runs into a leader that brakes to a stop."""
    n_steps = 400
    t = torch.arange(n_steps, dtype=torch.float64) * 0.1
    v_leader = torch.clamp(20.0 - 8.0 * torch.clamp(t - 5.0, min=0.0), min=0.0)
    x_leader = torch.cumsum(v_leader * 0.1, 0) - v_leader[0] * 0.1
    sampler = sampler_of(
        # LLCTG: tau, ks, kv, l: well tuned, then far too weak.
        {"llctg": [[1.2, 0.8, 1.5, 5.0], [1.0, 0.01, 0.01, 5.0]]}
    )
    sampler.assign(torch.tensor([[0], [1]]))
    out = platoon(
        sampler,
        x_leader[:, None].expand(-1, 2),
        v_leader[:, None].expand(-1, 2),
        initial_spacing=30.0,
        safety=None,
    )
    assert out.valid.tolist() == [True, False]
    step = int(out.collision_step[1, 0])
    assert step > 50 and float(out.spacing[step, 1, 0]) <= 0
    assert float(out.spacing[step - 1, 1, 0]) > 0
    # Nothing is clipped: the vehicle went on (no reversing, speed >= 0).
    assert float(out.spacing[-1, 1, 0]) < 0
    assert bool((out.v >= 0).all()) and bool((out.x.diff(dim=0) >= 0).all())


def test_the_safety_layer_stops_the_sluggish_follower_and_counts_it():
    """The same emergency stop with the layer on (the default): the weak
    follower stops behind the leader, a leader length back at least, and only
    it was overridden; the well-tuned one drives exactly as without a layer."""
    n_steps = 400
    t = torch.arange(n_steps, dtype=torch.float64) * 0.1
    v_leader = torch.clamp(20.0 - 8.0 * torch.clamp(t - 5.0, min=0.0), min=0.0)
    # Trapezoidal positions: a leader braking at 8 m/s^2 exactly (the
    # rectangular sum above stops it v dt / 2 = 1 m shorter, as if harder).
    x_leader = torch.cat(
        (
            torch.zeros(1, dtype=torch.float64),
            torch.cumsum(0.05 * (v_leader[1:] + v_leader[:-1]), 0),
        )
    )
    sampler = sampler_of({"llctg": [[1.2, 0.8, 1.5, 5.0], [1.0, 0.01, 0.01, 5.0]]})
    sampler.assign(torch.tensor([[0], [1]]))
    leaders = (x_leader[:, None].expand(-1, 2), v_leader[:, None].expand(-1, 2))
    safe = platoon(sampler, *leaders, initial_spacing=30.0)
    alone = platoon(sampler, *leaders, initial_spacing=30.0, safety=None)
    assert safe.valid.all()
    # to a few mm: the last braking step of the leader, cut at 0, is shorter
    assert float(safe.spacing[:, 1, 0].min()) >= sampler.leader_length - 0.01
    assert int(safe.interventions[1, 0]) > 0 and int(safe.interventions[0, 0]) == 0
    assert int(safe.interventions_moving[1, 0]) > 0  # it braked while driving
    assert torch.all(safe.interventions_moving <= safe.interventions)
    torch.testing.assert_close(safe.x[:, 0], alone.x[:, 0], rtol=0, atol=0)
    # braking no harder than the layer's 8 m/s^2
    assert float(safe.a[:, 1, 0].min()) >= -8.0 - 1e-9


def test_holding_a_creeping_idm_at_a_stop_is_not_counted_as_moving():
    """SPEC's IDM keeps s0 front to front: behind a standing leader 5 m long
    it creeps into the leader's bumper, and the layer holds it there at a
    stop. Those overrides are counted, but not as interventions while moving."""
    n_steps = 600
    v_leader = torch.zeros(n_steps, dtype=torch.float64)
    x_leader = torch.zeros(n_steps, dtype=torch.float64)
    sampler = sampler_of({"idm": [[1.0, 2.0, 30.0, 1.5, 2.0, 4.0]]})
    sampler.assign(torch.tensor([[0]]))
    start = FollowerState(
        x=torch.tensor([-8.0], dtype=torch.float64),
        v=torch.zeros(1, dtype=torch.float64),
        a=torch.zeros(1, dtype=torch.float64),
    )
    safe = platoon(sampler, x_leader[:, None], v_leader[:, None], start=start)
    held = int(safe.interventions[0, 0]) - int(safe.interventions_moving[0, 0])
    assert held > 400  # most of the minute, standing at the bumper
    assert int(safe.interventions_moving[0, 0]) < 50
    # to a cm: the last creeping step ends inside the discrete safe speed
    assert float(safe.spacing[:, 0, 0].min()) >= sampler.leader_length - 0.01


# ----------------------------------------------------------------------- ring
def llctg_ring(stable: bool, n: int = 20, spacing: float = 20.0, steps: int = 1500):
    # String stability of u = ks (s - v tau - l) + kv dv with a point mass:
    # |G(jw)| <= 1 for all w  <=>  ks tau^2 + 2 kv tau - 2 >= 0.
    theta = [1.2, 0.5, 1.5, 5.0] if stable else [0.8, 0.3, 0.3, 5.0]
    tau, ks, kv, _ = theta
    assert (ks * tau**2 + 2 * kv * tau - 2 >= 0) == stable
    sampler = sampler_of({"llctg": [theta]})
    sampler.assign(torch.zeros(1, n, dtype=torch.long))
    return ring_road(
        sampler,
        n * spacing,
        steps,
        initial=RingStart(perturbation=1.0),
        record_every=10,
    )


def test_ring_string_stability_matches_linear_theory():
    stable, unstable = llctg_ring(True), llctg_ring(False)
    # The initial speed is the equilibrium speed (s - l) / tau at L / n.
    assert float(stable.v[0, 0, 0]) == pytest.approx(15.0 / 1.2)
    assert float(unstable.v[0, 0, 0]) == pytest.approx(15.0 / 0.8)
    spread = [out.spacing.std(dim=-1)[:, 0] for out in (stable, unstable)]
    assert float(spread[0][-1]) < 1e-3 * float(spread[0][0])  # the wave decays
    assert float(spread[1][-1]) > 10 * float(spread[1][0])  # ... or grows


def test_ring_conserves_its_length_and_wraps():
    sampler = HybridSampler.from_posterior(
        make_posterior({"idm": 3, "hl": 3, "mpc": 2}, seed=1), dt=0.1
    )
    sampler.double()
    sampler.sample((3, 15), torch.Generator().manual_seed(0))
    length = torch.tensor([300.0, 400.0, 500.0])
    out = ring_road(
        sampler, length, 300, initial=RingStart(v_init=8.0), record_every=25
    )
    torch.testing.assert_close(
        out.spacing.sum(-1), length[None].expand(out.spacing.shape[0], -1).double()
    )
    assert bool((out.x >= 0).all()) and bool((out.x < length[None, :, None]).all())
    torch.testing.assert_close(out.time, torch.arange(0, 300, 25).double() * 0.1)
    # The spacing is the ring distance to the vehicle ahead.
    ahead = torch.roll(out.x, -1, dims=-1)
    ring = length[None, :, None].double()
    mismatch = torch.remainder(ahead - out.x - out.spacing + ring / 2, ring) - ring / 2
    torch.testing.assert_close(mismatch, torch.zeros_like(mismatch), atol=1e-8, rtol=0)


def test_mixed_ring_starts_at_its_equilibrium_and_stays_there():
    """Different vehicles at one speed v*, each at its own steady spacing."""
    sampler = sampler_of(
        {
            "idm": [[1.5, 2.0, 30.0, 1.2, 2.0, 4.0]],
            # LLCTG (tau, ks, kv, l): steady spacing l + v tau.
            "llctg": [[1.2, 0.5, 1.5, 5.0], [0.9, 0.6, 1.2, 8.0]],
        }
    )
    sampler.assign(torch.tensor([[0, 1, 2] * 4, [1, 1, 2] * 4]))  # (2, 12)
    out = ring_road(
        sampler, torch.tensor([300.0, 400.0]), 300, initial=RingStart(perturbation=0.0)
    )
    v_star = out.v[0, :, 0]  # (S,)
    assert bool((out.v[0] == v_star[:, None]).all())
    # Ring 1 is LLCTG only: sum_i (l_i + v tau_i) = L in closed form.
    tau = torch.tensor([1.2, 1.2, 0.9] * 4, dtype=torch.float64)
    standstill = torch.tensor([5.0, 5.0, 8.0] * 4, dtype=torch.float64)
    expected = (400.0 - standstill.sum()) / tau.sum()
    assert float(v_star[1]) == pytest.approx(float(expected), abs=1e-8)
    torch.testing.assert_close(
        out.spacing[0, 1], standstill + expected * tau, rtol=0, atol=1e-8
    )
    # Stationary: nothing moves but the ring as a whole.
    torch.testing.assert_close(out.v, out.v[:1].expand_as(out.v), atol=1e-7, rtol=0)
    torch.testing.assert_close(
        out.spacing, out.spacing[:1].expand_as(out.spacing), atol=1e-6, rtol=0
    )


def test_the_slowest_vehicle_is_the_rings_bottleneck():
    """An OVM vehicle that never exceeds v1 + v2 = 5 m/s sets the ring's speed
    and takes the road the faster LLCTG vehicles leave it."""
    sampler = sampler_of(
        {"ovm": [[1.0, 2.0, 3.0, 0.1, 1.5]], "llctg": [[1.2, 0.5, 1.5, 5.0]]}
    )
    sampler.assign(torch.tensor([[0] + [1] * 9]))
    start = ring_initial_state(sampler, 600.0, perturbation=0.0)
    assert float(start.v[0, 0]) == pytest.approx(5.0, abs=1e-6)
    torch.testing.assert_close(
        start.spacing[0, 1:], torch.full((9,), 5.0 + 5.0 * 1.2).double()
    )
    assert float(start.spacing[0, 0]) == pytest.approx(600.0 - 9 * 11.0)
    # The bottleneck holds: speeds stay at 5 m/s (to the tanh's tail).
    out = ring_road(sampler, 600.0, 200, initial=start)
    assert float((out.v - 5.0).abs().max()) < 1e-3


def test_a_ring_too_short_for_its_vehicles_is_refused():
    sampler = sampler_of({"llctg": [[1.2, 0.5, 1.5, 5.0]]})
    sampler.assign(torch.zeros(1, 10, dtype=torch.long))
    with pytest.raises(ValueError, match="too short"):
        ring_road(sampler, 40.0, 10, initial=RingStart(v_init=5.0, perturbation=4.5))
    # At standstill LLCTG keeps l = 5 m: 10 vehicles in 40 m are jammed (v* = 0)
    # but every spacing stays positive.
    jam = ring_initial_state(sampler, 40.0, perturbation=0.0)
    assert float(jam.v.abs().max()) < 1e-9
    torch.testing.assert_close(jam.spacing.sum(), torch.tensor(40.0).double())


def test_ring_scenarios_are_independent():
    """Rings batched together equal the same rings run one by one."""
    posterior = make_posterior({"idm": 4, "gfm": 3, "hl": 3, "mpc": 2}, seed=4)
    together = HybridSampler.from_posterior(posterior, dt=0.1, dtype=torch.float64)
    together.sample((3, 12), torch.Generator().manual_seed(6))
    particles = together.vehicle_particle.reshape(3, 12).clone()
    out = ring_road(together, 360.0, 80, initial=RingStart(v_init=8.0))
    alone = HybridSampler.from_posterior(posterior, dt=0.1, dtype=torch.float64)
    for s in range(3):
        alone.assign(particles[s : s + 1])
        one = ring_road(alone, 360.0, 80, initial=RingStart(v_init=8.0))
        torch.testing.assert_close(one.v[:, 0], out.v[:, s], rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(
            one.spacing[:, 0], out.spacing[:, s], rtol=1e-9, atol=1e-9
        )


def test_ring_continues_from_its_final_state_and_redraws():
    sampler = HybridSampler.from_posterior(
        make_posterior({"idm": 5, "llctg": 5}, seed=2), dt=0.1, dtype=torch.float64
    )
    sampler.sample((2, 10), torch.Generator().manual_seed(3), resample_every=5.0)
    first = sampler.vehicle_particle.clone()
    part = ring_road(
        sampler, 300.0, 40, initial=RingStart(v_init=10.0), record_every=None
    )
    assert part.x is None and part.final.v.shape == (2, 10)
    assert torch.equal(first, sampler.vehicle_particle)
    more = ring_road(sampler, 300.0, 20, initial=part.final)
    assert not torch.equal(first, sampler.vehicle_particle)  # redrawn at 5 s
    torch.testing.assert_close(more.v[0], part.final.v)
    torch.testing.assert_close(
        more.final.spacing.sum(-1), torch.full((2,), 300.0).double()
    )


def test_float32_ring_stays_accurate_on_a_long_road():
    """Spacings, not positions, are the state: float32 follows float64 closely
    on a 100 km ring where float32 positions would be 8 mm apart."""
    theta = {"llctg": [[1.2, 0.5, 1.5, 5.0]]}
    results = []
    for dtype in (torch.float32, torch.float64):
        sampler = sampler_of(theta, dtype=dtype)
        sampler.assign(torch.zeros(1, 4000, dtype=torch.long))
        out = ring_road(sampler, 100_000.0, 300, record_every=None)
        results.append(out.final.spacing.double())
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=1e-4)


@pytest.mark.compile
def test_compiled_ring_equals_eager():
    posterior = make_posterior({"idm": 3, "hl": 3}, seed=5)
    runs = []
    for use_compile in (False, True):
        sampler = HybridSampler.from_posterior(posterior, dt=0.1, dtype=torch.float64)
        sampler.sample((2, 16), torch.Generator().manual_seed(1))
        runs.append(
            ring_road(
                sampler, 400.0, 30, initial=RingStart(v_init=10.0), compile=use_compile
            )
        )
    torch.testing.assert_close(runs[1].v, runs[0].v, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(runs[1].spacing, runs[0].spacing, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------- errors
def test_bad_inputs_are_one_line():
    sampler = sampler_of({"idm": [[1.5, 2.0, 30.0, 1.2, 2.0, 4.0]]})
    with pytest.raises(ValueError, match=r"sample\(\(S, n\)\)"):
        ring_road(sampler, 100.0, 10)
    sampler.assign(torch.zeros(5, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\(S, n\)"):
        ring_road(sampler, 100.0, 10)
    sampler.assign(torch.zeros(2, 5, dtype=torch.long))
    with pytest.raises(ValueError, match="ring length"):
        ring_road(sampler, -5.0, 10)
    with pytest.raises(ValueError, match=r"\(S,\) = \(2,\)"):
        ring_road(sampler, torch.tensor([100.0, 200.0, 300.0]), 10)
    with pytest.raises(ValueError, match="perturbation"):
        ring_road(sampler, 100.0, 10, initial=RingStart(perturbation=-1.0))
    with pytest.raises(ValueError, match="record_every"):
        ring_road(sampler, 100.0, 10, record_every=0)
    with pytest.raises(ValueError, match="n_steps"):
        ring_road(sampler, 100.0, -1)
    with pytest.raises(ValueError, match="initial must hold"):
        ring_road(sampler, 100.0, 1, initial=RingState(*(torch.zeros(3, 5),) * 4))
    x = torch.zeros(50, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="S = 2"):
        platoon(sampler, x, x)
    x = torch.zeros(50, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="behind the leader"):
        platoon(sampler, x, x, initial_spacing=-1.0)
    with pytest.raises(ValueError, match="out of range"):
        pair_leader(synthetic_pairs(n_pairs=2), [0, 2])
    assert ring_initial_state(sampler, 100.0, v_init=3.0).v.shape == (2, 5)
