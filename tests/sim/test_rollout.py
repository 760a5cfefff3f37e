"""The rollout (SPEC sections 2 and 4) against the independent scalar reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchcf
from tests.conftest import prior_draws, synthetic_pairs
from tests.reference import simulate_pair
from torchcf import MODELS, Execution, PairSet, get_model, simulate

NAMES = list(MODELS)


def reference(
    name, theta_row, pairs: PairSet, n: int, weights=(0.5, 0.3, 0.2), shift: float = 0.0
):
    """The scalar reference on pair n; ``shift`` moves the follower back [m]."""
    series = [
        s[:, n].numpy()
        for s in (
            pairs.x_lead,
            pairs.v_lead,
            pairs.x_follow,
            pairs.v_follow,
            pairs.a_follow,
        )
    ]
    series[2] = series[2] - shift
    return simulate_pair(
        name,
        [float(v) for v in theta_row],
        *series,
        pairs.dt,
        pairs.leader_length,
        weights,
        mask=pairs.mask[:, n].numpy(),
    )


def well_conditioned(name, theta_row, pairs, n, ref) -> bool:
    """Whether the rollout is insensitive to rounding.

    Some prior draws (FVDM with a tiny interaction length, say) are numerically
    unstable: a 1e-14 m difference grows exponentially. Starting the follower
    1e-11 m further back tells them apart: there, two correct implementations that
    round differently disagree by more than any useful tolerance.
    """
    moved = reference(name, theta_row, pairs, n, shift=1e-11)
    if moved["valid"] != ref["valid"]:
        return False
    if not ref["valid"]:
        return True
    return abs(moved["score"] - ref["score"]) < 1e-9


@pytest.mark.slow  # every model against the loop reference in the full layout
@pytest.mark.parametrize("name", NAMES)
def test_full_layout_matches_reference(name, pairs):
    theta = prior_draws(MODELS[name], 12, seed=7)
    out = simulate(get_model(name), theta, pairs, dtype=torch.float64, return_traj=True)
    assert out.score.shape == (12, pairs.n_pairs)
    assert out.x.shape == (pairs.n_steps, 12, pairs.n_pairs)
    compared = 0
    for j in range(12):
        for n in range(pairs.n_pairs):
            ref = reference(name, theta[j], pairs, n)
            if not well_conditioned(name, theta[j], pairs, n, ref):
                continue
            compared += 1
            assert bool(out.valid[j, n]) == ref["valid"]
            if not ref["valid"]:
                assert math.isinf(float(out.score[j, n]))
                continue
            for key in ("score", "e_p", "e_v", "e_a"):
                assert float(getattr(out, key)[j, n]) == pytest.approx(
                    ref[key], rel=1e-9, abs=1e-9
                )
            for key in ("x", "v", "a"):
                np.testing.assert_allclose(
                    getattr(out, key)[:, j, n].numpy(), ref[key], rtol=0, atol=1e-6
                )
    assert compared >= 0.75 * 12 * pairs.n_pairs


@pytest.mark.parametrize("name", NAMES)
def test_paired_equals_gathered_full_layout(name, pairs):
    theta = prior_draws(MODELS[name], 40, seed=11)
    index = torch.randint(0, pairs.n_pairs, (40,))
    full = simulate(
        get_model(name), theta, pairs, dtype=torch.float64, return_traj=True
    )
    paired = simulate(
        get_model(name), theta, pairs, index, dtype=torch.float64, return_traj=True
    )
    rows = torch.arange(40)
    for key in ("score", "e_p", "e_v", "e_a", "valid"):
        torch.testing.assert_close(
            getattr(paired, key), getattr(full, key)[rows, index]
        )
    for key in ("x", "v", "a"):
        torch.testing.assert_close(
            getattr(paired, key), getattr(full, key)[:, rows, index]
        )


@pytest.mark.slow  # every model, one particle at a time
@pytest.mark.parametrize("name", NAMES)
def test_batched_equals_looped(name, pairs):
    theta = prior_draws(MODELS[name], 6, seed=5)
    batched = simulate(get_model(name), theta, pairs, dtype=torch.float64)
    for j in range(6):
        for n in range(pairs.n_pairs):
            single = simulate(
                get_model(name),
                theta[j : j + 1],
                pairs.subset([n]),
                dtype=torch.float64,
            )
            assert torch.equal(single.score[0, 0], batched.score[j, n])


@pytest.mark.parametrize("name", NAMES)
def test_float32_close_to_float64(name):
    pairs = synthetic_pairs(n_pairs=3, n_steps=576, seed=2)
    theta = prior_draws(MODELS[name], 64, seed=9)
    high = simulate(get_model(name), theta, pairs, dtype=torch.float64)
    low = simulate(get_model(name), theta.float(), pairs)
    assert low.score.dtype == torch.float32 and high.score.dtype == torch.float64
    both = high.valid & low.valid
    # a rollout on the edge of collision may flip validity in float32; rarely
    assert float((high.valid != low.valid).float().mean()) < 0.02
    torch.testing.assert_close(
        low.score[both].double(), high.score[both], rtol=1e-3, atol=1e-3
    )


@pytest.mark.slow  # every model at several chunk sizes
@pytest.mark.parametrize("chunk_size", [1, 7, 64, 1000])
def test_result_independent_of_chunk_size(chunk_size, pairs):
    theta = prior_draws(MODELS["idm"], 40, seed=1, dtype=torch.float32)
    index = torch.randint(0, pairs.n_pairs, (40,))
    reference_out = simulate(get_model("idm"), theta, pairs, index)
    chunks = Execution(chunk_size=chunk_size)
    chunked = simulate(get_model("idm"), theta, pairs, index, execution=chunks)
    assert torch.equal(chunked.score, reference_out.score)
    full = simulate(get_model("idm"), theta, pairs, execution=chunks)
    assert torch.equal(full.score, simulate(get_model("idm"), theta, pairs).score)


def test_permuting_pairs_permutes_outputs(pairs):
    theta = prior_draws(MODELS["gfm"], 10)
    order = torch.tensor([2, 0, 3, 1])
    out = simulate(get_model("gfm"), theta, pairs, dtype=torch.float64)
    permuted = simulate(
        get_model("gfm"), theta, pairs.subset(order), dtype=torch.float64
    )
    torch.testing.assert_close(permuted.score, out.score[:, order])


def test_initial_state_is_observed(pairs):
    theta = prior_draws(MODELS["hl"], 3)
    out = simulate(get_model("hl"), theta, pairs, dtype=torch.float64, return_traj=True)
    torch.testing.assert_close(out.x[0], pairs.x_follow[0].expand(3, -1))
    torch.testing.assert_close(out.v[0], pairs.v_follow[0].expand(3, -1))
    # HL records its acceleration state, which starts at the observed value
    torch.testing.assert_close(out.a[0], pairs.a_follow[0].expand(3, -1))


def test_perfect_model_scores_zero():
    """Observations generated by the engine itself are reproduced exactly."""
    base = synthetic_pairs(n_pairs=3, n_steps=200, seed=4)
    theta = torch.tensor([[1.2, 2.0, 30.0, 1.4, 2.0, 4.0]], dtype=torch.float64)
    sim = simulate(get_model("idm"), theta, base, dtype=torch.float64, return_traj=True)
    observed = PairSet.from_arrays(
        (base.x_lead, base.v_lead, base.a_lead, sim.x[:, 0], sim.v[:, 0], sim.a[:, 0]),
        dt=base.dt,
    )
    again = simulate(get_model("idm"), theta, observed, dtype=torch.float64)
    assert float(again.score.max()) < 1e-9


def test_score_weights():
    pairs = synthetic_pairs(n_pairs=2, n_steps=100)
    theta = prior_draws(MODELS["ovm"], 4)
    out = simulate(
        get_model("ovm"), theta, pairs, dtype=torch.float64, weights=(1.0, 0.0, 0.0)
    )
    torch.testing.assert_close(out.score, out.e_p)


class TestInvalid:
    def test_collision_is_invalid_and_scores_inf(self):
        pairs = synthetic_pairs(n_pairs=2, n_steps=200)
        # LLCS with a 5 m desired spacing and weak damping drives into the leader
        # on an oscillating leader; a big desired spacing does not.
        theta = torch.tensor([[5.0, 2.3, 0.3], [25.0, 0.5, 1.5]], dtype=torch.float64)
        out = simulate(
            get_model("llcs"), theta, pairs, dtype=torch.float64, return_traj=True
        )
        for j in range(2):
            for n in range(2):
                ref = reference("llcs", theta[j], pairs, n)
                assert bool(out.valid[j, n]) == ref["valid"]
        collided = ~out.valid
        assert bool(collided.any()) and bool(out.valid.any())
        for key in ("score", "e_p", "e_v", "e_a"):
            assert bool(torch.isinf(getattr(out, key)[collided]).all())

    def test_spacing_equal_to_zero_is_invalid(self):
        pairs = synthetic_pairs(n_pairs=1, n_steps=100)
        # huge spacing gain: the follower reaches the leader within the run
        theta = torch.tensor([[0.0, 2.3, 0.0]], dtype=torch.float64)
        out = simulate(
            get_model("llcs"), theta, pairs, dtype=torch.float64, return_traj=True
        )
        spacing = pairs.x_lead[:, 0] - out.x[:, 0, 0]
        assert bool((spacing <= 0).any()) and not bool(out.valid[0, 0])

    def test_non_finite_rollout_is_invalid(self):
        pairs = synthetic_pairs(n_pairs=1, n_steps=50)
        # FVDM with tiny tau explodes numerically (|u| ~ 1/tau each step)
        theta = torch.tensor([[1e-30, 0.0, 30.0, 30.0, 0.1, 0.0]], dtype=torch.float32)
        out = simulate(get_model("fvdm"), theta, pairs)
        assert not bool(out.valid[0, 0]) and math.isinf(float(out.score[0, 0]))

    def test_failure_after_the_valid_prefix_is_ignored(self):
        full = synthetic_pairs(n_pairs=1, n_steps=200)
        theta = torch.tensor([[5.0, 2.3, 0.3]], dtype=torch.float64)
        out = simulate(
            get_model("llcs"), theta, full, dtype=torch.float64, return_traj=True
        )
        spacing = full.x_lead[:, 0] - out.x[:, 0, 0]
        first_bad = int(torch.nonzero(spacing <= 0)[0])
        mask = torch.zeros(200, 1, dtype=torch.bool)
        mask[:first_bad] = True
        prefix = PairSet.from_arrays(full.series(), dt=full.dt, mask=mask)
        masked = simulate(get_model("llcs"), theta, prefix, dtype=torch.float64)
        assert bool(masked.valid[0, 0])


def test_ragged_pair_equals_truncated_pair():
    pairs = synthetic_pairs(n_pairs=2, n_steps=150, seed=3)
    lengths = [150, 97]
    mask = torch.arange(150)[:, None] < torch.tensor(lengths)[None, :]
    ragged = PairSet.from_arrays(pairs.series(), dt=pairs.dt, mask=mask)
    theta = prior_draws(MODELS["hl"], 5)
    out = simulate(get_model("hl"), theta, ragged, dtype=torch.float64)
    short = pairs.subset([1])
    truncated = PairSet.from_arrays(
        [s[:97] for s in short.series().values()], dt=pairs.dt
    )
    alone = simulate(get_model("hl"), theta, truncated, dtype=torch.float64)
    torch.testing.assert_close(out.score[:, 1], alone.score[:, 0])
    for j in range(5):
        ref = reference("hl", theta[j], ragged, 1)
        assert float(out.score[j, 1]) == pytest.approx(ref["score"], rel=1e-9)


class TestArguments:
    def test_theta_shape(self, pairs):
        with pytest.raises(ValueError, match=r"theta must be \(P, 6\) for idm"):
            simulate(get_model("idm"), torch.zeros(3, 5), pairs)

    def test_theta_non_finite(self, pairs):
        theta = prior_draws(MODELS["idm"], 2)
        theta[1, 0] = math.nan
        with pytest.raises(ValueError, match="non-finite"):
            simulate(get_model("idm"), theta, pairs)

    def test_pair_index(self, pairs):
        theta = prior_draws(MODELS["idm"], 3)
        with pytest.raises(ValueError, match="out of range"):
            simulate(get_model("idm"), theta, pairs, torch.tensor([0, 1, 4]))
        with pytest.raises(ValueError, match="pair_index must have shape"):
            simulate(get_model("idm"), theta, pairs, torch.tensor([0, 1]))

    def test_unknown_model(self, pairs):
        with pytest.raises(torchcf.UnknownModelError, match="valid names"):
            simulate(get_model("krauss"), torch.zeros(1, 3), pairs)

    def test_dtype(self, pairs):
        with pytest.raises(ValueError, match="float32 or torch.float64"):
            simulate(
                get_model("idm"),
                prior_draws(MODELS["idm"], 1),
                pairs,
                dtype=torch.float16,
            )

    def test_default_dtype_follows_theta(self, pairs):
        theta = prior_draws(MODELS["idm"], 2, dtype=torch.float64)
        assert simulate(get_model("idm"), theta, pairs).score.dtype == torch.float64
        assert (
            simulate(get_model("idm"), theta.float(), pairs).score.dtype
            == torch.float32
        )

    def test_empty_theta(self, pairs):
        out = simulate(
            get_model("idm"), torch.zeros(0, 6), pairs, torch.zeros(0, dtype=torch.long)
        )
        assert out.score.shape == (0,)


def test_real_data_matches_reference(data_root):
    pairs = torchcf.load_pairs("car-model-2", split="test", data_root=data_root)
    for name in NAMES:
        theta = prior_draws(MODELS[name], 3, seed=13)
        index = torch.tensor([0, 5, pairs.n_pairs - 1])
        out = simulate(get_model(name), theta, pairs, index, dtype=torch.float64)
        for j in range(3):
            ref = reference(name, theta[j], pairs, int(index[j]))
            assert bool(out.valid[j]) == ref["valid"]
            if ref["valid"]:
                assert float(out.score[j]) == pytest.approx(ref["score"], rel=1e-9)


@pytest.mark.compile
@pytest.mark.parametrize("name", ["idm", "hl"])
def test_compiled_equals_eager(name):
    pairs = synthetic_pairs(n_pairs=5, n_steps=120)
    theta = prior_draws(MODELS[name], 256, seed=3, dtype=torch.float32)
    index = torch.randint(0, 5, (256,))
    eager = simulate(
        get_model(name), theta, pairs, index, execution=Execution(compile=False)
    )
    compiled = simulate(
        get_model(name), theta, pairs, index, execution=Execution(compile=True)
    )
    assert torch.equal(eager.valid, compiled.valid)
    torch.testing.assert_close(compiled.score, eager.score, rtol=1e-5, atol=1e-5)


@pytest.mark.compile
@pytest.mark.parametrize(
    "name, paired",
    [
        ("mpc", True),
        ("mpc", False),
        ("mpc+delay+saturation", True),
        ("mpc+lag+action", True),
    ],
)
def test_a_correcting_model_compiles_around_its_correction(name, paired):
    """MPC (and MPC under effects) compiles every step but its QP
    (``CFModel.corrects``): the same scores, validity and trajectory as eager,
    with the QP reached on many steps (the prior's tight limits)."""
    from torchcf.models import get_model

    model = get_model(name)
    pairs = synthetic_pairs(n_pairs=4, n_steps=90, seed=5)
    theta = prior_draws(model, 192, seed=6, dtype=torch.float64)
    theta[::2, 4:6] = torch.tensor([-0.3, 0.3], dtype=torch.float64)  # box active
    index = torch.randint(0, 4, (192,)) if paired else None
    eager, fused = (
        simulate(
            model, theta, pairs, index, return_traj=True, execution=Execution(compile=c)
        )
        for c in (False, True)
    )
    assert bool(eager.valid.any())
    assert torch.equal(eager.valid, fused.valid)
    torch.testing.assert_close(fused.score, eager.score, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(fused.a, eager.a, rtol=1e-8, atol=1e-8)
    saturated = (eager.a.abs() >= 0.3 - 1e-9).float().mean()
    assert float(saturated) > 0.05, "the QP must be exercised"


def test_a_correcting_models_command_is_its_draft_corrected():
    """``command_with_memory = correct(draft_with_memory)``, with memory, for MPC
    and MPC under a perception and a command effect."""
    from torchcf.models import Perception, get_model

    for name in ("mpc", "mpc+delay+action"):
        model = get_model(name)
        theta = prior_draws(model, 64, seed=8)
        params = model.prepare(model.unpack(theta), 0.1, (64,))
        generator = torch.Generator().manual_seed(9)
        spacing, v, v_lead = (
            torch.rand(64, generator=generator, dtype=torch.float64) * scale + low
            for low, scale in ((5.0, 40.0), (0.0, 25.0), (0.0, 25.0))
        )
        obs = Perception(spacing, v, v_lead, torch.zeros(64, dtype=torch.float64), 5.0)
        memory = model.initial_memory(params, obs)
        for _ in range(3):
            whole, whole_memory = model.command_with_memory(params, obs, memory)
            split, memory = model.correct(
                params, *model.draft_with_memory(params, obs, memory)
            )
            assert torch.equal(whole, split), name
            torch.testing.assert_close(whole_memory, memory, rtol=0, atol=0)
            obs = obs._replace(spacing=obs.spacing + 0.5, v=obs.v + 0.2)


@pytest.mark.compile
@pytest.mark.parametrize("name", ["fvdm", "mpc"])  # fused whole; around its QP
def test_compiled_result_independent_of_chunk_size(name):
    pairs = synthetic_pairs(n_pairs=5, n_steps=64)
    theta = prior_draws(MODELS[name], 300, seed=4, dtype=torch.float32)
    index = torch.randint(0, 5, (300,))
    outs = [
        simulate(
            get_model(name),
            theta,
            pairs,
            index,
            execution=Execution(chunk_size=size, compile=True),
        )
        for size in (100, 300)
    ]
    assert torch.equal(outs[0].score, outs[1].score)


@pytest.mark.compile
@pytest.mark.parametrize("name, graphs", [("idm", 1), ("mpc", 2)])  # draft, finish
def test_a_padded_last_chunk_reuses_the_compiled_graph(name, graphs):
    """Three chunks, the last padded: one trace of the block (or of MPC's two
    step functions). The padded chunk's inputs once came out of inference mode
    as another kind of tensor, and each model compiled a second graph."""
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    pairs = synthetic_pairs(n_pairs=5, n_steps=32)
    theta = prior_draws(MODELS[name], 300, seed=5, dtype=torch.float32)
    index = torch.arange(300) % 5
    simulate(
        get_model(name),
        theta,
        pairs,
        index,
        execution=Execution(chunk_size=128, compile=True),
    )
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs


def test_compile_cache_holds_every_model_and_shape():
    """More than dynamo's default 8 graphs of _block must stay compiled."""
    from torchcf.sim.rollout import _compiled_block

    _compiled_block(MODELS["llcs"], True, 0.1, 5.0, False)
    assert torch._dynamo.config.recompile_limit >= 64


@pytest.mark.compile
def test_the_vector_isa_probed_once_is_the_one_inductor_picks():
    """configure_compiler probes the first ISA the CPU reports and spares the
    rest: the kernels must use the ISA that inductor's full probe would pick.
    Each side in a fresh process (inductor caches its probe per process)."""
    import platform
    import subprocess
    import sys

    if platform.machine() not in ("x86_64", "AMD64") or sys.platform != "linux":
        pytest.skip("the probe is trimmed on x86 Linux only")
    pick = "from torch._inductor.cpu_vec_isa import pick_vec_isa; print(pick_vec_isa())"

    def run(code: str) -> list[str]:
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        )
        return done.stdout.strip().splitlines()

    probed, trusted, trimmed = run(
        "import torch; from torchcf.sim.compiled import configure_compiler, "
        "_probe_vector_isa; configure_compiler(); print(_probe_vector_isa()); "
        "print(torch._inductor.config.cpp.vec_isa_ok); " + pick
    )[-3:]
    full = run("import torch; " + pick)[-1]
    assert trimmed == full
    if probed != "None":  # the first ISA passed: the others were spared
        assert (probed, trusted) == (full, "True")


@pytest.mark.parametrize(
    "fused", [False, pytest.param(True, marks=pytest.mark.compile)]
)
def test_not_finite_flags_exactly_nan_and_inf(fused):
    """The rollout's finiteness test, eager and inside a compiled block: True
    exactly where x, v or a is NaN or +-inf, False for finite products (a fused
    ``u - u`` of a product can be an FMA's rounding error, not 0)."""
    from torchcf.sim.rollout import _not_finite

    a, b = torch.rand(1000, dtype=torch.float32) * 7, torch.rand(1000) * 3
    x = torch.tensor([1.0, math.nan, 2.0, 3.0, 4.0, 5.0]).repeat(200)[:1000]
    v = torch.tensor([0.0, 0.0, math.inf, 0.0, -math.inf, 1.0]).repeat(200)[:1000]

    def check(x, v, a, b):
        return _not_finite(x, v, a * b)

    fn = torch.compile(check, fullgraph=True) if fused else check
    expected = ~(torch.isfinite(x) & torch.isfinite(v))
    assert torch.equal(fn(x, v, a, b), expected)


def test_auto_compiles_from_a_threshold_per_device(monkeypatch):
    """ "auto" compiles long rollouts only: from COMPILE_MIN_STEPS particle-steps
    on the CPU (with a C++ compiler), from COMPILE_MIN_STEPS_CUDA on CUDA (where
    eager rollouts are fast and compiling pays later); "on"/"off" and bools as
    asked; a model that cannot be traced, not even around a correction, never
    compiles."""
    import torchcf.sim.compiled as sim

    monkeypatch.setattr(sim, "compiler_available", lambda: True)
    idm, cpu, cuda = MODELS["idm"], torch.device("cpu"), torch.device("cuda")
    cpu_limit, cuda_limit = int(sim.COMPILE_MIN_STEPS), int(sim.COMPILE_MIN_STEPS_CUDA)
    assert cpu_limit < cuda_limit
    assert not sim.resolve_compile(idm, "auto", cpu, cpu_limit - 1)
    assert sim.resolve_compile(idm, "auto", cpu, cpu_limit)
    assert not sim.resolve_compile(idm, "auto", cuda, cpu_limit)
    assert not sim.resolve_compile(idm, "auto", cuda, cuda_limit - 1)
    assert sim.resolve_compile(idm, "auto", cuda, cuda_limit)
    for asked, expected in ((True, True), ("on", True), (False, False), ("off", False)):
        assert sim.resolve_compile(idm, asked, cpu, 1) is expected
    mpc = MODELS["mpc"]  # traced around its eager QP (CFModel.corrects)
    assert sim.resolve_compile(mpc, True, cpu, 1)
    assert sim.resolve_compile(mpc, "auto", cpu, cpu_limit)
    untraceable = type("Untraceable", (type(mpc),), {"corrects": False})()
    assert not sim.resolve_compile(untraceable, True, cpu, cuda_limit)
    monkeypatch.setattr(sim, "compiler_available", lambda: False)
    assert not sim.resolve_compile(idm, "auto", cpu, cuda_limit)


@pytest.mark.parametrize("asked", ["no", "yes", "", 1])
def test_a_compile_mode_of_another_spelling_is_refused(asked):
    with pytest.raises(ValueError, match="compile must be"):
        torchcf.sim.rollout.resolve_compile(
            MODELS["idm"], asked, torch.device("cpu"), 1
        )
