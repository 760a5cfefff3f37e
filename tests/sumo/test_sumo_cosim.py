"""torchcf.sumo.cosim: SUMO vehicles driven by the sampler move as torchcf's own
rollout does (every model and effect, with and without the safety layer)."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

pytest.importorskip(
    "libsumo", reason="SUMO is not installed: pip install -e '.[sumo]' (or '.[dev]')"
)

from tests.conftest import synthetic_pairs  # noqa: E402
from tests.traffic.test_sampler import make_posterior  # noqa: E402
from tests.traffic.test_traffic import KINDS  # noqa: E402
from torchcf import HybridSampler, PairSet, get_model, simulate  # noqa: E402
from torchcf.sumo import backend  # noqa: E402
from torchcf.sumo.backend import SumoError  # noqa: E402
from torchcf.sumo.cosim import CoSimulation  # noqa: E402
from torchcf.sumo.network import straight_edges  # noqa: E402
from torchcf.sumo.verify import replay  # noqa: E402
from torchcf.traffic import DEFAULT_SAFETY, pair_leader, platoon  # noqa: E402

#: The largest position difference [m] from torchcf's rollout allowed (the issue's
#: bound); measured: 5.0e-10 m, the FCD's 9 decimals.
TOLERANCE = 1e-6


def _cells(sampler: HybridSampler, pairs: PairSet) -> tuple[Tensor, Tensor]:
    """Every particle on every pair: particle-major cells."""
    particle = torch.arange(sampler.n_particles).repeat_interleave(pairs.n_pairs)
    pair = torch.arange(pairs.n_pairs).repeat(sampler.n_particles)
    return particle, pair


def test_cosimulation_is_the_calibration_rollout(tmp_path):
    """Every kind of model (point masses, HL's lag, MPC, a delay, an added lag, a
    grade), mixed in one co-simulation, moves as torchcf.simulate does."""
    pairs = synthetic_pairs(n_pairs=2, n_steps=120)
    posterior = make_posterior({name: 2 for name in KINDS}, seed=3)
    sampler = HybridSampler.from_posterior(posterior, dt=pairs.dt, dtype=torch.float64)
    particle, pair = _cells(sampler, pairs)
    sampler.assign(particle)

    calls = []
    forward = sampler.forward
    sampler.forward = lambda *a, **k: calls.append(1) or forward(*a, **k)
    run = replay(pairs, pair.tolist(), workdir=tmp_path, sampler=sampler)
    assert len(calls) == pairs.n_steps  # batched: one sampler call per step

    worst = 0.0
    for name in KINDS:
        rows = sampler.particle_ids(name)
        ref = simulate(
            get_model(name),
            sampler.particles(name),
            pairs,
            dtype=torch.float64,
            return_traj=True,
        )  # (T, 2, N)
        mine = torch.isin(particle, rows)
        x = run.x[:, mine].reshape(pairs.n_steps, 2, pairs.n_pairs)
        v = run.v[:, mine].reshape(pairs.n_steps, 2, pairs.n_pairs)
        worst = max(worst, float((x - ref.x).abs().max()))
        assert torch.allclose(v, ref.v, atol=1e-8, rtol=0), name
    assert worst < TOLERANCE
    assert run.collisions == 0


def test_cosimulation_with_the_safety_layer_is_the_platoon(tmp_path):
    """Safety layer on (the default): a leader braking hard to a stop makes it
    intervene, and SUMO's vehicles still move as torchcf.traffic.platoon's."""
    n_steps, dt = 120, 0.1
    t = torch.arange(n_steps, dtype=torch.float64) * dt
    v_lead = torch.clamp(20.0 - 8.0 * torch.clamp(t - 2.0, min=0.0), min=0.0)
    x_lead = 60.0 + torch.cumsum(torch.cat([torch.zeros(1), v_lead[:-1] * dt]), 0)
    a_lead = torch.zeros_like(t)
    zeros = torch.zeros_like(t)
    pairs = PairSet.from_arrays(
        (x_lead[:, None], v_lead[:, None], a_lead[:, None],
         (x_lead - 25.0)[:, None], (zeros + 20.0)[:, None], zeros[:, None]),
        dt=dt,
    )  # fmt: skip
    # Slow-reacting point masses: the bound must brake for them.
    posterior = make_posterior({"llcs": 2, "idm": 2, "hl": 2}, seed=5)
    posterior.hybrid["llcs"].theta[:, 1:] = torch.tensor([[0.05, 0.1], [0.02, 0.2]])
    sampler = HybridSampler.from_posterior(posterior, dt=dt, dtype=torch.float64)
    particle, pair = _cells(sampler, pairs)

    sampler.assign(particle[:, None])  # (S, 1): torchcf's own platoon
    x_leader, v_leader, start = pair_leader(pairs, pair)
    ref = platoon(sampler, x_leader, v_leader, start=start, safety=DEFAULT_SAFETY)
    assert int(ref.interventions.sum()) > 0

    sampler.assign(particle)  # (V,): the co-simulation
    run = replay(
        pairs, pair.tolist(), workdir=tmp_path, sampler=sampler, safety=DEFAULT_SAFETY
    )
    assert float((run.x - ref.x[:, :, 0]).abs().max()) < TOLERANCE
    assert torch.allclose(run.v, ref.v[:, :, 0], atol=1e-8, rtol=0)


def _start(tmp_path, ballistic: bool = True, step: float = 0.1):
    net = straight_edges(1, 2000.0, tmp_path)
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        '<routes><vType id="t" length="5" minGap="0"/><route id="r" edges="e0"/>'
        '<vehicle id="A" type="t" route="r" depart="0" departPos="10" '
        'departSpeed="10" insertionChecks="none"/></routes>'
    )
    return backend.running(
        [
            "--net-file", str(net), "--route-files", str(routes),
            "--step-length", repr(step),
            "--step-method.ballistic", "true" if ballistic else "false",
            "--no-step-log", "true",
        ]
    )  # fmt: skip


def test_a_vehicle_without_leader_follows_a_ghost_at_the_speed_limit(tmp_path):
    """Free road: a ghost leader at the lane's limit, at the particle's own
    equilibrium spacing for it; for LLCS (``ks (s - s0) + kv dv``) that is
    ``s0``, so the command is ``kv (v_limit - v)``, by hand."""
    posterior = make_posterior({"llcs": 1})
    posterior.hybrid["llcs"].theta[0] = torch.tensor([8.0, 0.5, 0.4])  # s0 ks kv
    sampler = HybridSampler.from_posterior(posterior, dt=0.1, dtype=torch.float64)
    sampler.assign(torch.zeros(1, dtype=torch.long))
    with _start(tmp_path) as sumo:
        sumo.simulationStep()
        v_limit = sumo.vehicle.getAllowedSpeed("A")
        cosim = CoSimulation(sumo, sampler, ["A"], safety=None, lookahead=100.0)
        seen = cosim.step()
        assert float(seen.spacing[0]) == pytest.approx(8.0, abs=1e-9)
        assert float(seen.v_leader[0]) == v_limit
        u = 0.4 * (v_limit - 10.0)
        # SUMO keeps a speed set through TraCI to a few 1e-9 (relative).
        v_next, x_next = 10.0 + u * 0.1, 10.0 + 10.0 * 0.1 + u * 0.1**2 / 2
        assert sumo.vehicle.getSpeed("A") == pytest.approx(v_next, rel=1e-8)
        assert sumo.vehicle.getLanePosition("A") == pytest.approx(x_next, rel=1e-9)


@pytest.mark.parametrize(
    "ballistic, step, vehicles, message",
    [
        (False, 0.1, ["A"], "--step-method.ballistic true"),
        (True, 0.2, ["A"], "--step-length 0.1"),
        (True, 0.1, ["A", "B"], "sampler.sample\\(2\\)"),
    ],
)
def test_mismatches_are_refused(tmp_path, ballistic, step, vehicles, message):
    sampler = HybridSampler.from_posterior(
        make_posterior({"idm": 1}), dt=0.1, dtype=torch.float64
    )
    sampler.sample(1)
    with _start(tmp_path, ballistic, step) as sumo:
        sumo.simulationStep()
        with pytest.raises(SumoError, match=message):
            CoSimulation(sumo, sampler, vehicles)


def test_one_simulation_at_a_time(tmp_path):
    with _start(tmp_path) as sumo:
        with pytest.raises(SumoError, match="already runs"):
            with backend.running(["--net-file", "unused.net.xml"]):
                pass
        sumo.simulationStep()  # the first one still runs


def test_every_model_drives_a_sumo_ring(tmp_path):
    """One vehicle of each kind on a 4-edge SUMO ring, co-simulated with the
    safety layer: the perceived front-to-front spacings add up to the ring's
    length at every step (the leaders found across edges), and all move."""
    from torchcf.sumo.network import ring

    length, n = 280.0, len(KINDS)
    net = ring(length, tmp_path)
    routes = tmp_path / "ring.rou.xml"
    vehicles = []
    for i in range(n):
        at = i * length / n
        edge = int(at // (length / 4))
        route = " ".join(f"e{(edge + k) % 4}" for k in range(4))
        vehicles.append(
            f'<vehicle id="v{i}" type="t" depart="0" departSpeed="0" '
            f'departPos="{at - edge * length / 4!r}" insertionChecks="none">'
            f'<route edges="{" ".join([route] * 5)}"/></vehicle>'
        )
    routes.write_text(
        '<routes><vType id="t" length="5" minGap="0"/>'
        + "".join(vehicles)
        + "</routes>"
    )
    posterior = make_posterior({name: 1 for name in KINDS}, seed=2)
    sampler = HybridSampler.from_posterior(posterior, dt=0.1, dtype=torch.float64)
    sampler.assign(torch.arange(n))
    arguments = [
        "--net-file", str(net), "--route-files", str(routes),
        "--step-length", "0.1", "--step-method.ballistic", "true",
        "--collision.action", "warn", "--collision.mingap-factor", "0",
        "--no-step-log", "true",
    ]  # fmt: skip
    with backend.running(arguments) as sumo:
        sumo.simulationStep()
        cosim = CoSimulation(sumo, sampler, [f"v{i}" for i in range(n)])
        for _ in range(150):
            seen = cosim.step()
            assert float(seen.spacing.sum()) == pytest.approx(length, abs=1e-6)
        moved = [sumo.vehicle.getDistance(f"v{i}") for i in range(n)]
        assert min(moved) > 1.0
        assert sumo.simulation.getCollidingVehiclesNumber() == 0


def test_redraws_keep_both_rows_on_one_particle(tmp_path):
    """The sampler runs as (2, V), following and free-road rows; a redraw
    (``resample_every``) gives each vehicle one particle in both again."""
    sampler = HybridSampler.from_posterior(
        make_posterior({"idm": 5, "gfm": 5}), dt=0.1, dtype=torch.float64
    )
    sampler.sample(1, torch.Generator().manual_seed(1), resample_every=0.2)
    with _start(tmp_path) as sumo:
        sumo.simulationStep()
        cosim = CoSimulation(sumo, sampler, ["A"])
        assert sampler.vehicle_shape == (2, 1)
        drawn = set()
        for _ in range(20):
            cosim.step()
            rows = sampler.vehicle_particle.reshape(2, 1)
            assert int(rows[0, 0]) == int(rows[1, 0])
            drawn.add(int(rows[0, 0]))
        assert len(drawn) > 1
