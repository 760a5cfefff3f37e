"""HybridSampler: draws follow the shares, one call equals every model's own step,
and the module survives compile, state_dict, dtype and device round trips."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from scipy.stats import chisquare

from tests.conftest import prior_draws
from tests.runs import run_summary
from torchcf import HybridSampler, get_model
from torchcf.models import FollowerState, Perception
from torchcf.posterior import ModelParticles, Posterior
from torchcf.sim.rollout import realise

#: A learned set with every kind of model: point masses, HL's lag, MPC's solver,
#: a perception delay (memory), an added lag, a road grade (position).
MIXED = {
    "idm": 9,
    "gfm": 7,
    "hl": 6,
    "mpc": 5,
    "llctg": 4,
    "idm+delay": 4,
    "llcs+lag": 3,
    "ovm+grade": 2,
    "fvdm": 0,
}
DT = 0.1
IDM = get_model("idm")


def make_posterior(counts: dict[str, int], seed: int = 0, dataset="car-model-2"):
    """A Posterior with ``counts[m]`` prior draws of each model as its hybrid set."""
    hybrid = {}
    for k, (name, count) in enumerate(counts.items()):
        model = get_model(name)
        theta = prior_draws(model, count, seed=seed + k)
        hybrid[name] = ModelParticles(
            model.param_names,
            theta,
            torch.arange(count, dtype=torch.float64),
            torch.zeros(count, dtype=torch.long),
            torch.arange(count),
        )
    total = sum(counts.values())
    # The per-pair buffers the set came from (not read by the sampler).
    buffers = {
        name: {
            "param_names": list(get_model(name).param_names),
            "score": torch.zeros(4, 0, dtype=torch.float64),
            "index": torch.zeros(4, 0, dtype=torch.long),
            "theta": torch.zeros(4, 0, get_model(name).n_params, dtype=torch.float64),
        }
        for name in counts
    }
    return Posterior(
        dataset=dataset,
        selection="per_pair",
        top_n=5,
        models=tuple(counts),
        shares={name: count / total for name, count in counts.items()},
        train_pair_ids=torch.arange(4),
        hybrid=hybrid,
        buffers=buffers,
    )


def make_sampler(counts=None, dtype=torch.float64) -> HybridSampler:
    return HybridSampler.from_posterior(
        make_posterior(counts or MIXED), dt=DT, dtype=dtype
    )


def random_state(shape, dtype, seed=0):
    """Plausible perceptions: spacing 8-40 m, speeds 0-25 m/s, |a| < 2 m/s^2."""
    g = torch.Generator().manual_seed(seed)

    def uniform(low, high):
        return low + (high - low) * torch.rand(shape, generator=g, dtype=dtype)

    return {
        "spacing": uniform(8.0, 40.0),
        "v": uniform(0.0, 25.0),
        "v_leader": uniform(0.0, 25.0),
        "a": uniform(-2.0, 2.0),
        "position": uniform(0.0, 1500.0),
    }


def assign_everything(sampler: HybridSampler, repeats: int = 2) -> None:
    """Every particle on ``repeats`` vehicles, in a shuffled order: mixed groups."""
    ids = torch.arange(sampler.n_particles).repeat(repeats)
    order = torch.randperm(ids.numel(), generator=torch.Generator().manual_seed(5))
    sampler.assign(ids[order])


# ------------------------------------------------------------------- drawing
def test_model_frequencies_follow_the_shares_chi_square():
    counts = {"idm": 40, "gfm": 25, "hl": 20, "mpc": 10, "llcs": 5}
    sampler = make_sampler(counts)
    assert sampler.shares == pytest.approx({k: v / 100 for k, v in counts.items()})
    n = 20_000
    model = sampler.sample(n, generator=torch.Generator().manual_seed(11))
    observed = torch.bincount(model, minlength=len(counts)).double()
    expected = torch.tensor(list(counts.values()), dtype=torch.float64) / 100 * n
    assert chisquare(observed.numpy(), expected.numpy()).pvalue > 1e-3
    # Within and across models, every particle is equally likely.
    per_particle = torch.bincount(sampler.vehicle_particle, minlength=100).double()
    flat = torch.full((100,), n / 100, dtype=torch.float64)
    assert chisquare(per_particle.numpy(), flat.numpy()).pvalue > 1e-3


def test_draws_are_reproducible_from_the_generator():
    sampler = make_sampler()
    first = sampler.sample((3, 50), generator=torch.Generator().manual_seed(4))
    particles = sampler.vehicle_particle.clone()
    second = sampler.sample((3, 50), generator=torch.Generator().manual_seed(4))
    assert first.shape == (3, 50)
    assert torch.equal(first, second)
    assert torch.equal(particles, sampler.vehicle_particle)


def test_resampling_every_k_seconds():
    sampler = make_sampler()
    sampler.sample(400, torch.Generator().manual_seed(0), resample_every=0.5)
    before = sampler.vehicle_particle.clone()
    state = random_state((400,), torch.float64)
    sampler(**state)
    assert sampler.memory is not None
    redrawn = [sampler.tick() for _ in range(5)]
    assert redrawn == [False] * 4 + [True]  # 5 steps of 0.1 s
    assert not torch.equal(before, sampler.vehicle_particle)
    assert sampler.memory is None  # the new drivers start from a steady past
    assert [sampler.tick() for _ in range(5)][-1]


def test_particle_ids_and_assign():
    sampler = make_sampler()
    ids = sampler.particle_ids("hl", [0, 5])
    sampler.assign(ids)
    assert sampler.model_names[int(sampler.vehicle_model[0])] == "hl"
    assert sampler.vehicle_shape == (2,)
    theta = sampler.particles("hl")
    assert theta.shape == (6, 6)
    assert sampler.particle_ids("idm+delay").numel() == 4
    assert sampler.particle_ids("fvdm").numel() == 0


# ------------------------------------------------------------------- stepping
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_forward_equals_each_models_own_step(dtype):
    """Two steps of the mixed batch against each vehicle alone, model by model."""
    sampler = make_sampler(dtype=dtype)
    assign_everything(sampler)
    n = sampler.n_vehicles
    states = [random_state((n,), dtype, seed) for seed in (1, 2)]
    commands = [sampler(**state) for state in states]
    moved = sampler.advance(
        torch.zeros(n, dtype=dtype), states[1]["v"], states[1]["a"], commands[1]
    )
    assert commands[0].dtype == dtype and commands[0].shape == (n,)

    # MPC's solver meets SPEC's accuracy; everything else is the same arithmetic.
    tolerance = {torch.float64: 1e-9, torch.float32: 1e-3}[dtype]
    for i in range(n):
        name, row = _particle_of(sampler, int(sampler.vehicle_particle[i]))
        model = get_model(name)
        theta = sampler.particles(name)[row : row + 1]
        prepared = model.prepare(model.unpack(theta, 1), DT, (1,))
        memory = None
        for k, state in enumerate(states):
            obs = Perception(
                state["spacing"][i : i + 1],
                state["v"][i : i + 1],
                state["v_leader"][i : i + 1],
                state["a"][i : i + 1],
                5.0,
                state["position"][i : i + 1] if model.uses_position else None,
            )
            if memory is None:
                memory = model.initial_memory(prepared, obs)
            u, memory = model.command_with_memory(prepared, obs, memory)
            torch.testing.assert_close(
                commands[k][i : i + 1], u, rtol=tolerance, atol=tolerance
            )
        alone = realise(
            model,
            prepared,
            FollowerState(
                torch.zeros(1, dtype=dtype),
                states[1]["v"][i : i + 1],
                states[1]["a"][i : i + 1],
            ),
            commands[1][i : i + 1],
            DT,
        )
        for got, want in zip(moved, alone, strict=True):
            torch.testing.assert_close(got[i : i + 1], want, rtol=0, atol=0)


def _particle_of(sampler: HybridSampler, index: int) -> tuple[str, int]:
    m = int(sampler.particle_model[index])
    return sampler.model_names[m], int(sampler.particle_row[index])


def test_recorded_acceleration_kind_per_vehicle():
    sampler = make_sampler()
    assign_everything(sampler, repeats=1)
    names = [sampler.model_names[int(m)] for m in sampler.vehicle_model]
    expected = [get_model(name).acceleration_is_state for name in names]
    assert sampler.acceleration_is_state.tolist() == expected
    assert any(expected) and not all(expected)


def test_vehicle_layout_is_kept():
    sampler = make_sampler()
    sampler.sample((4, 25), torch.Generator().manual_seed(2))
    state = random_state((4, 25), torch.float64)
    u = sampler(**state)
    assert u.shape == (4, 25)
    flat = make_sampler()
    flat.assign(sampler.vehicle_particle)
    torch.testing.assert_close(
        flat(**{k: v.reshape(-1) for k, v in state.items()}), u.reshape(-1)
    )


def test_equilibrium_speed_closed_forms():
    # LLCTG: u = ks (s - v tau - l) = 0 at v = (s - l) / tau; OVM: v = V(s - L).
    sampler = make_sampler({"llctg": 3, "ovm": 3, "hl": 3})
    sampler.assign(torch.arange(9))
    spacing = 30.0
    speed = sampler.equilibrium_speed(spacing, v_max=60.0, iterations=60)
    llctg, ovm, hl = (sampler.particles(name) for name in ("llctg", "ovm", "hl"))
    expected = torch.cat(
        (
            (spacing - llctg[:, 3]) / llctg[:, 0],
            ovm[:, 1] + ovm[:, 2] * torch.tanh(ovm[:, 3] * (spacing - 5.0) - ovm[:, 4]),
            (spacing - hl[:, 5]) / hl[:, 0],
        )
    ).clamp(0.0, 60.0)
    torch.testing.assert_close(speed, expected, rtol=0, atol=1e-9)
    assert sampler.memory is None  # the search leaves the memory alone


# -------------------------------------------------------------- round trips
def test_state_dict_round_trip(tmp_path):
    sampler = make_sampler()
    sampler.sample((2, 30), torch.Generator().manual_seed(3), resample_every=20.0)
    state = random_state((2, 30), torch.float64)
    u = sampler(**state)
    path = tmp_path / "sampler.pt"
    torch.save(sampler.state_dict(), path)

    fresh = make_sampler()  # no vehicles yet
    fresh.load_state_dict(torch.load(path, weights_only=True))
    assert fresh.vehicle_shape == (2, 30)
    assert fresh.resample_every == 20.0
    assert torch.equal(fresh.vehicle_particle, sampler.vehicle_particle)
    # The memory is transient: both start from the same steady past.
    sampler.reset_memory()
    torch.testing.assert_close(fresh(**state), u, rtol=0, atol=0)
    torch.testing.assert_close(sampler(**state), u, rtol=0, atol=0)

    other = make_sampler({"idm": 3, "hl": 2})
    with pytest.raises((ValueError, RuntimeError)):
        other.load_state_dict(sampler.state_dict())


def test_dtype_round_trip_keeps_vehicles_and_memory():
    sampler = make_sampler()
    assign_everything(sampler)
    n = sampler.n_vehicles
    state64 = random_state((n,), torch.float64)
    u64 = sampler(**state64)
    sampler.float()
    assert sampler.dtype == torch.float32
    assert sampler.particles("idm").dtype == torch.float32
    # The delay history and MPC's plan followed the conversion.
    leaves = torch.utils._pytree.tree_leaves(sampler.memory)
    tensors = [t for t in leaves if isinstance(t, torch.Tensor)]
    floats = [t for t in tensors if t.is_floating_point()]
    assert floats and all(t.dtype == torch.float32 for t in floats)
    # the delay's ring-buffer head stays an index
    assert all(t.dtype == torch.int64 for t in tensors if not t.is_floating_point())
    state32 = {k: v.float() for k, v in state64.items()}
    sampler.reset_memory()
    torch.testing.assert_close(sampler(**state32).double(), u64, rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="float64 but the sampler is torch.float32"):
        sampler(**state64)
    sampler.double()  # back, with the parameters rounded to float32
    sampler.reset_memory()
    torch.testing.assert_close(sampler(**state64), u64, rtol=1e-5, atol=1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_round_trip():
    sampler = make_sampler()
    sampler.sample((2, 40), torch.Generator().manual_seed(0))
    state = random_state((2, 40), torch.float64)
    u_cpu = sampler(**state)
    sampler.reset_memory()
    sampler.to("cuda")
    assert sampler.vehicle_particle.is_cuda and sampler.particles("mpc").is_cuda
    u_gpu = sampler(**{k: v.cuda() for k, v in state.items()})
    torch.testing.assert_close(u_gpu.cpu(), u_cpu, rtol=1e-9, atol=1e-6)
    moved = sampler.advance(
        torch.zeros_like(u_gpu), state["v"].cuda(), state["a"].cuda(), u_gpu
    )
    assert moved.x.is_cuda
    # Draws on the GPU from a GPU generator.
    sampler.sample(1000, torch.Generator(device="cuda").manual_seed(0))
    assert sampler.vehicle_particle.is_cuda
    sampler.cpu()
    assert not sampler.vehicle_particle.is_cuda


@pytest.mark.slow  # torch.compile of the sampler
@pytest.mark.compile
def test_compiled_forward_equals_eager():
    """Fused groups, MPC left out of the graph, the delay's memory carried."""
    counts = {"idm": 4, "hl": 3, "mpc": 3, "idm+delay": 3}
    eager, fused = make_sampler(counts), make_sampler(counts)
    for sampler in (eager, fused):
        sampler.sample(64, torch.Generator().manual_seed(1))
    compiled = torch.compile(fused)
    for seed in range(3):
        state = random_state((64,), torch.float64, seed)
        torch.testing.assert_close(
            compiled(**state), eager(**state), rtol=1e-9, atol=1e-9
        )


# ------------------------------------------------------------------- errors
def test_from_file(tmp_path):
    posterior = make_posterior({"idm": 3, "hl": 2})
    posterior.save(tmp_path / "posterior.pt")
    sampler = HybridSampler.from_file(tmp_path)  # a run directory works too
    assert (sampler.dt, sampler.leader_length) == (0.1, 5.0)  # the registry's
    assert sampler.model_names == ("idm", "hl")
    assert sampler.dtype == torch.float32

    custom = make_posterior({"idm": 3}, dataset="my-road")
    custom.save(tmp_path / "custom.pt")
    with pytest.raises(ValueError, match="pass dt="):
        HybridSampler.from_file(tmp_path / "custom.pt")
    with pytest.raises(ValueError, match="pass leader_length="):  # never 5 m unsaid
        HybridSampler.from_file(tmp_path / "custom.pt", dt=0.04)
    given = HybridSampler.from_file(tmp_path / "custom.pt", dt=0.04, leader_length=4.5)
    assert (given.dt, given.leader_length) == (0.04, 4.5)
    run = tmp_path / "run"
    run.mkdir()
    custom.save(run / "posterior.pt")
    (run / "config.json").write_text(
        json.dumps({"data": {"dt": 0.2, "leader_length": 4.0}})
    )
    sampler = HybridSampler.from_file(run / "posterior.pt")
    assert (sampler.dt, sampler.leader_length) == (0.2, 4.0)
    # a folder run: the folder's meta.json, as its loader read it
    folder = tmp_path / "pairs"
    folder.mkdir()
    (folder / "meta.json").write_text(json.dumps({"dt": 0.05, "leader_length": 4.51}))
    (run / "config.json").write_text(json.dumps({"data": {"path": str(folder)}}))
    sampler = HybridSampler.from_file(run)
    assert (sampler.dt, sampler.leader_length) == (0.05, 4.51)
    # the run's summary.json, which records its training pairs' constants, first
    summary = run_summary(dataset="my-road", dt=0.1, leader_length=4.2)
    (run / "summary.json").write_text(json.dumps(summary.to_json()))
    sampler = HybridSampler.from_file(run)
    assert (sampler.dt, sampler.leader_length) == (0.1, 4.2)

    with pytest.raises(ValueError, match="no such posterior file"):
        HybridSampler.from_file(tmp_path / "missing.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a torchcf posterior"):
        HybridSampler.from_file(tmp_path / "other.pt")


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: HybridSampler([IDM], [torch.zeros(3, 5)], dt=0.1), r"\(P, 6\)"),
        (lambda: HybridSampler([IDM], [torch.zeros(0, 6)], dt=0.1), "no particle"),
        (lambda: HybridSampler([IDM], [torch.ones(2, 6)], dt=0.0), "dt must"),
        (
            lambda: HybridSampler([get_model("nope")], [torch.ones(2, 6)], dt=0.1),
            "unknown",
        ),
        (
            lambda: HybridSampler([IDM, get_model("hl")], [torch.ones(2, 6)], dt=0.1),
            "2 models but 1",
        ),
    ],
)
def test_bad_construction_is_one_line(build, message):
    with pytest.raises(ValueError, match=message):
        build()


def test_bad_calls_are_one_line():
    sampler = make_sampler()
    state = random_state((10,), torch.float64)
    with pytest.raises(ValueError, match="call sample"):
        sampler(**state)
    with pytest.raises(ValueError, match="positive count"):
        sampler.sample(0)
    with pytest.raises(ValueError, match="resample_every"):
        sampler.sample(5, resample_every=-1.0)
    with pytest.raises(ValueError, match="particle indices must lie"):
        sampler.assign(torch.tensor([0, sampler.n_particles]))
    with pytest.raises(ValueError, match="not in the learned set"):
        sampler.particle_ids("llcs")
    sampler.sample(10)
    with pytest.raises(ValueError, match=r"vehicles' shape \(10,\)"):
        sampler(**random_state((11,), torch.float64))
    sampler.assign(sampler.particle_ids("ovm+grade"))
    state = random_state((2,), torch.float64)
    del state["position"]
    with pytest.raises(ValueError, match="reads position"):
        sampler(**state)


def test_the_readme_snippet_runs(tmp_path):
    """The README's lines for embedding the sampler, run as written.

    docs/traffic.md shows the same lines under the same heading.
    """
    root = Path(__file__).resolve().parents[2]
    heading = "## Using the learned model in a simulation"
    snippets = []
    for page in (root / "README.md", root / "docs" / "traffic.md"):
        section = page.read_text().split(heading, 1)[1]
        snippets.append(section.split("```python\n", 1)[1].split("```", 1)[0])
    code = snippets[0]
    assert snippets[1] == code, "docs/traffic.md's snippet is not the README's"
    make_posterior({"idm": 4, "hl": 3}).save(tmp_path / "posterior.pt")
    code = code.replace("runs/carII/posterior.pt", str(tmp_path / "posterior.pt"))
    n = 6

    def your_leaders(x, v):  # a platoon behind a vehicle at 15 m/s
        return torch.cat((x[:1] + 30.0, x[:-1])), torch.cat(
            (v.new_full((1,), 15.0), v[:-1])
        )

    scope = {
        "n": n,
        "n_steps": 610,  # past one redraw at 60 s
        "x0": -30.0 * torch.arange(n, dtype=torch.float32),
        "v0": torch.full((n,), 15.0),
        "your_leaders": your_leaders,
    }
    exec(compile(code, "README.md", "exec"), scope)  # noqa: S102
    assert scope["u"].shape == (n,) and bool(torch.isfinite(scope["x"]).all())
