"""``device: "cuda"``: simulation, training, evaluation and the diagnosis loop.

Skipped without a CUDA GPU. On one (the lent device machine), run
``pytest -q tests/test_cuda.py``: the GPU must give the CPU's numbers (float64 to
rounding, float32 within its precision), the trainer's buffers on the GPU must
hold the particles the CPU run keeps, and the whole pipeline must run there. With
two GPUs or more, torchrun with nccl must equal one process.
"""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from tests.conftest import prior_draws, synthetic_pairs
from tests.runs import run_module, torchrun_train, write_config, write_data
from torchcf import MODELS, Execution, get_model, simulate
from torchcf.config import validate_config
from torchcf.posterior import Posterior
from torchcf.study.pipeline import run_study
from torchcf.train import train

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA GPU"
)
#: A rollout on the GPU (:class:`torchcf.Execution`).
ON_CUDA = Execution(device="cuda")


def _config(**top):
    raw = {
        "data": {"path": "synthetic"},  # unused: the tests pass the pairs
        "models": ["idm", "hl", "mpc"],
        "abc": {"n_particles": 6000, "top_n": 3, "sensitivity_n": [3], "seed": 4},
        "compile": "off",
        "device": "cuda",
        **top,
    }
    return validate_config(raw)


@pytest.mark.parametrize("layout", ["paired", "full"])
@pytest.mark.parametrize("name", list(MODELS))
def test_simulate_on_cuda_equals_cpu(name, layout):
    pairs = synthetic_pairs(n_pairs=5, n_steps=200, seed=3)
    theta = prior_draws(MODELS[name], 300, seed=1)
    index = torch.arange(300) % pairs.n_pairs if layout == "paired" else None
    for dtype, rtol in ((torch.float64, 1e-9), (torch.float32, 2e-3)):
        cpu = simulate(get_model(name), theta.to(dtype), pairs, index, dtype=dtype)
        gpu = simulate(
            get_model(name),
            theta.to(dtype),
            pairs,
            index,
            dtype=dtype,
            execution=ON_CUDA,
        )
        assert gpu.score.device.type == "cuda" and gpu.score.dtype == dtype
        both = cpu.valid & gpu.valid.cpu()
        # float32 rollouts at the edge of validity may tip either way; nearly all
        # must agree, and where both are valid the scores must match.
        assert float((cpu.valid != gpu.valid.cpu()).float().mean()) <= 0.01
        torch.testing.assert_close(
            gpu.score.cpu()[both], cpu.score[both], rtol=rtol, atol=1e-6
        )


@pytest.mark.parametrize(
    "name",
    [
        "idm+grade(start=0,end=600,knots=4)",
        "llctg+grade(start=-30,knots=4,period=250)+bend(period=250,knots=5)",
    ],
)
def test_road_profiles_on_cuda_equal_cpu(name):
    """A grade on an open road and profiles round a closed track (positions
    wrapped by the lap) give the CPU's scores on the GPU."""
    from torchcf.models import get_model

    pairs = synthetic_pairs(n_pairs=5, n_steps=200, seed=3)
    model = get_model(name)
    theta = prior_draws(model, 300, seed=1).double()
    cpu = simulate(get_model(name), theta, pairs, dtype=torch.float64)
    gpu = simulate(
        get_model(name), theta, pairs, dtype=torch.float64, execution=ON_CUDA
    )
    both = cpu.valid & gpu.valid.cpu()
    assert bool(both.any()) and bool((cpu.valid == gpu.valid.cpu()).all())
    torch.testing.assert_close(
        gpu.score.cpu()[both], cpu.score[both], rtol=1e-9, atol=1e-9
    )


@pytest.mark.compile
@pytest.mark.parametrize(
    "name", [m for m in MODELS if MODELS[m].compilable or MODELS[m].corrects]
)
def test_compiled_rollout_on_cuda(name):
    """Fused on the GPU = eager on the GPU, validity included: a compiler that
    contracts ``a*b - a*b`` into an FMA once made every OVM and IDM rollout
    invalid while their trajectories were right."""
    pairs = synthetic_pairs(n_pairs=5, n_steps=100, seed=3)
    theta = prior_draws(MODELS[name], 4096, seed=2, dtype=torch.float32)
    index = torch.arange(4096) % pairs.n_pairs
    eager = simulate(
        get_model(name), theta, pairs, index, execution=replace(ON_CUDA, compile=False)
    )
    fused = simulate(
        get_model(name), theta, pairs, index, execution=replace(ON_CUDA, compile=True)
    )
    assert float(eager.valid.float().mean()) > 0.2, "the test needs valid rollouts"
    assert float((eager.valid != fused.valid).float().mean()) <= 0.01
    # float32: the fused kernel rounds differently (FMAs), and a few rollouts of
    # a sensitive model drift apart over the steps (FVDM: 2 of 3706 by 0.2 %).
    both = eager.valid & fused.valid
    close = torch.isclose(fused.score[both], eager.score[both], rtol=1e-3, atol=1e-5)
    assert float(close.float().mean()) >= 0.99


def test_training_on_cuda_keeps_the_cpu_particles(tmp_path):
    """float64 on both: the same particles win on every pair."""
    pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    runs = []
    for i, device in enumerate(("cpu", "cuda")):
        cfg = _config(device=device, dtype="float64")
        train(cfg, tmp_path / f"run{i}", pairs=(pairs, pairs))
        runs.append(Posterior.load(tmp_path / f"run{i}" / "posterior.pt"))
    on_cpu, on_gpu = runs
    for name in on_cpu.models:
        cpu, gpu = on_cpu.buffers[name], on_gpu.buffers[name]
        assert torch.equal(cpu["index"], gpu["index"]), name
        torch.testing.assert_close(gpu["score"], cpu["score"], rtol=1e-9, atol=0)
    assert on_cpu.shares == on_gpu.shares


def test_training_evaluation_and_diagnosis_on_cuda(tmp_path):
    from torchcf.study.pipeline import close_loop

    train_pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    test_pairs = synthetic_pairs(n_pairs=4, n_steps=200, seed=2)
    cfg = _config(diagnose={"n_particles": 3000, "effects": ["delay", "lag"]})
    out = tmp_path / "run"
    summary = run_study(cfg, out, pairs=(train_pairs, test_pairs)).summary
    assert sum(summary.shares.values()) == pytest.approx(1.0)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_test"] == 4 and metrics["hybrid"]["ws"] != "inf"
    # The GPU's float32 scores of the kept particles, re-scored on the CPU.
    posterior = Posterior.load(out / "posterior.pt")
    for name, particles in posterior.hybrid.items():
        if not len(particles):
            continue
        positions = [train_pairs.pair_ids.index(int(p)) for p in particles.pair_ids]
        cpu = simulate(get_model(name), particles.theta, train_pairs, positions)
        torch.testing.assert_close(cpu.score, particles.score, rtol=2e-3, atol=1e-5)
    result = close_loop(out, pairs=(train_pairs, test_pairs), progress=False)
    assert (out / "loop.json").exists() and "effects_ranked" in result.to_json()


def test_recalibration_by_training_on_cuda_keeps_the_cpu_particles(tmp_path):
    """The loop's re-calibration by the run's sampler (float64): the reference
    (the run's streams continued) and after (a variant trained) keep the
    particles the CPU keeps."""
    from torchcf.diagnose.recalibration import FinalModel, retrain

    pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    results = []
    for i, device in enumerate(("cpu", "cuda")):
        cfg = _config(device=device, dtype="float64", models=["idm", "hl"])
        train(cfg, tmp_path / f"run{i}", pairs=(pairs, pairs))
        posterior = Posterior.load(tmp_path / f"run{i}" / "posterior.pt")
        models = [get_model(name) for name in ("idm", "hl", "idm+delay")]
        final = FinalModel(models)
        results.append(retrain(cfg, posterior, final, [get_model("idm")], pairs))
    for on_cpu, on_gpu in zip(*results, strict=True):
        for name, cpu in on_cpu.items():
            gpu = on_gpu[name]
            assert torch.equal(cpu["index"], gpu["index"]), name
            torch.testing.assert_close(gpu["score"], cpu["score"], rtol=1e-9, atol=0)


def test_held_out_coverage_on_cuda_equals_cpu():
    """The loop's held-out-pair scores (diagnose.validation = "pairs"): every
    pick on every held-out pair, its best, on the GPU as on the CPU."""
    from torchcf.abc.particles import Particles
    from torchcf.abc.rejection import Rollout
    from torchcf.diagnose import Population
    from torchcf.diagnose.arms.validation import coverage_scores, split_by_pair
    from torchcf.models import get_model

    pairs = synthetic_pairs(n_pairs=10, n_steps=150, seed=6)
    fit, held = split_by_pair(pairs, 0.6, seed=1)
    sets = []
    for s, name in enumerate(("idm", "hl")):
        theta = prior_draws(get_model(name), 24, seed=s)
        at = torch.arange(24) % fit.n_pairs
        rollout = Rollout(fit, True, torch.float64, compile="off")
        score, _ = rollout.score(get_model(name), theta, at)
        sets.append(Particles(get_model(name), theta, at, score, torch.arange(24)))
    population = Population.from_particles(sets, fit.n_pairs, 4)
    on = {
        device: coverage_scores(
            population,
            3,
            Rollout(held, True, torch.float64, torch.device(device), compile="off"),
        )
        for device in ("cpu", "cuda")
    }
    torch.testing.assert_close(on["cuda"], on["cpu"], rtol=1e-9, atol=1e-12)


@pytest.mark.skipif(
    torch.cuda.device_count() < 2, reason="torchrun with nccl needs two GPUs"
)
def test_two_gpus_equal_one(tmp_path):
    data = write_data(tmp_path / "pairs")
    config = write_config(tmp_path / "cfg.json", data, device="cuda")
    one = run_module("torchcf", "train", str(config), "--out", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr[-3000:]
    two = torchrun_train(str(config), "--out", str(tmp_path / "two"))
    assert two.returncode == 0, two.stderr[-3000:]
    a = Posterior.load(tmp_path / "one" / "posterior.pt")
    b = Posterior.load(tmp_path / "two" / "posterior.pt")
    for name in a.models:
        for key in ("score", "index", "theta"):
            assert torch.equal(a.buffers[name][key], b.buffers[name][key])


def _on_cpu(out):
    return type(out)(*(None if t is None else t.cpu() for t in out))


@pytest.mark.parametrize(
    "name, compile",
    [(name, "off") for name in MODELS] + [("idm", "on"), ("mpc", "on")],
)
def test_a_ceiling_on_cuda_stops_only_cells_above_it(name, compile):
    """Early rejection's rollout on the GPU (float64; eager, and compiled with
    the particle dimension dynamic): the cells it does not stop score bit for bit
    as without a ceiling (the live batch is compacted as it goes), and every
    stopped cell scores above its ceiling."""
    pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    theta = prior_draws(MODELS[name], 3000, seed=5)
    pair = torch.arange(3000) % 6
    run = Execution(device="cuda", chunk_size=4096, compile=compile)
    plain = _on_cpu(simulate(get_model(name), theta, pairs, pair, execution=run))
    per_pair = torch.stack(
        [plain.score.double()[pair == j].sort().values[20] for j in range(6)]
    )
    ceiling = per_pair[pair]
    cut = _on_cpu(
        simulate(
            get_model(name), theta, pairs, pair, execution=replace(run, ceiling=ceiling)
        )
    )
    stopped = cut.pruned
    assert int(stopped.sum()) > 0
    assert bool((plain.score.double()[stopped] > ceiling[stopped]).all())
    kept = ~stopped
    for field in ("score", "e_p", "e_v", "e_a", "valid"):
        assert torch.equal(getattr(cut, field)[kept], getattr(plain, field)[kept]), (
            field
        )


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_early_rejection_on_cuda_keeps_the_same_particles(tmp_path, dtype):
    """Training on the GPU with and without ``abc.early_rejection`` (eager):
    the same shares and the same buffers; rollouts were stopped."""
    pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    runs = []
    for on in (False, True):
        abc = {"n_particles": 6000, "top_n": 3, "sensitivity_n": [3], "seed": 4,
               "chunk_size": 2048, "early_rejection": on}  # fmt: skip
        summary = train(_config(dtype=dtype, abc=abc), tmp_path / f"run{on}",
                        pairs=(pairs, pairs))  # fmt: skip
        runs.append((summary, Posterior.load(tmp_path / f"run{on}" / "posterior.pt")))
    (plain, a), (fast, b) = runs
    assert fast.shares == plain.shares
    for name in a.models:
        for key in ("index", "score"):
            assert torch.equal(a.buffers[name][key], b.buffers[name][key]), (name, key)
    assert fast.per_model["idm"].stopped > 0
