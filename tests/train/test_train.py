"""The trainer: mixture recovery, streaming = brute force, invariances, resume, CLI."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.conftest import synthetic_pairs
from torchcf import PairSet, get_model, simulate
from torchcf.abc.streams import ParticleStream
from torchcf.cli.train import main
from torchcf.config import TrainConfig
from torchcf.posterior import Posterior
from torchcf.study.pipeline import run_study
from torchcf.train import train

REPO = Path(__file__).resolve().parents[2]

#: The mixture the recovery test generates: model, true parameters, pairs.
TRUTH = {
    "idm": ([1.2, 2.0, 30.0, 1.5, 2.0, 4.0], range(0, 6)),
    "hl": ([1.0, 0.3, 1.0, 1.0, -1.0, 5.0], range(6, 10)),
}


def mixture_pairs() -> PairSet:
    """10 synthetic leaders; followers 0-5 driven by IDM, 6-9 by HL (TRUTH)."""
    base = synthetic_pairs(n_pairs=10, n_steps=300, seed=3)
    x, v, a = (base.x_follow.clone(), base.v_follow.clone(), base.a_follow.clone())
    for name, (theta, rows) in TRUTH.items():
        rows = list(rows)
        params = torch.tensor([theta] * len(rows), dtype=torch.float64)
        out = simulate(get_model(name), params, base, rows, return_traj=True)
        assert bool(out.valid.all()), name
        x[:, rows], v[:, rows], a[:, rows] = out.x, out.v, out.a
    return PairSet.from_arrays(
        (base.x_lead, base.v_lead, base.a_lead, x, v, a), dt=base.dt, name="mixture"
    )


def config(**abc) -> TrainConfig:
    settings = {"n_particles": 4000, "top_n": 5, "sensitivity_n": [5], "seed": 1}
    settings.update(abc)
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm", "hl"],
            "abc": settings,
            "compile": "off",
        }
    )


@pytest.fixture(scope="module")
def mixture() -> PairSet:
    return mixture_pairs()


def test_recovers_a_known_mixture(mixture, tmp_path):
    cfg = config(n_particles=30000, chunk_size=8192)
    summary = train(cfg, tmp_path / "run", pairs=(mixture, mixture))
    shares = summary.shares
    assert shares["idm"] == pytest.approx(0.6, abs=0.1)
    assert shares["hl"] == pytest.approx(0.4, abs=0.1)
    posterior = Posterior.load(tmp_path / "run" / "posterior.pt")
    for name, (theta, _) in TRUTH.items():
        accepted = posterior.hybrid[name].theta
        assert accepted.shape[0] > 0
        low, high = accepted.min(0).values, accepted.max(0).values
        truth = torch.tensor(theta, dtype=torch.float64)
        inside = (low <= truth) & (truth <= high)
        assert bool(inside.all()), (name, low, truth, high)


def test_buffers_equal_a_brute_force_sort(mixture, tmp_path):
    cfg = config(n_particles=3000, chunk_size=700)
    train(cfg, tmp_path / "run", pairs=(mixture, mixture))
    posterior = Posterior.load(tmp_path / "run" / "posterior.pt")
    for name in ("idm", "hl"):
        spec = next(s for s in cfg.models if s.name == name)
        stream = ParticleStream(
            get_model(name), spec.bounds(torch.float64), 1, mixture.n_pairs
        )
        theta, pair = stream.draw(0, 3000)
        score = simulate(
            get_model(name), theta.float(), mixture, pair, dtype=torch.float32
        ).score
        buffer = posterior.buffers[name]
        for p in range(mixture.n_pairs):
            rows = (pair == p) & torch.isfinite(score)
            candidates = sorted(
                zip(
                    score[rows].double().tolist(),
                    rows.nonzero()[:, 0].tolist(),
                    strict=True,
                )
            )[: buffer["score"].shape[1]]
            assert buffer["index"][p, : len(candidates)].tolist() == [
                j for _, j in candidates
            ]
            assert buffer["score"][p, : len(candidates)].tolist() == [
                s for s, _ in candidates
            ]


@pytest.mark.slow  # trainings at several chunk sizes
@pytest.mark.parametrize("layout", ["paired", "full"])
def test_result_does_not_depend_on_the_chunk_size(mixture, tmp_path, layout):
    results = []
    for chunk in (257, 1000):
        cfg = config(n_particles=1500, chunk_size=chunk, layout=layout)
        out = tmp_path / f"{layout}-{chunk}"
        summary = train(cfg, out, pairs=(mixture, mixture))
        results.append((summary.shares, Posterior.load(out / "posterior.pt")))
    (shares_a, post_a), (shares_b, post_b) = results
    assert shares_a == shares_b
    for name in ("idm", "hl"):
        for key in ("score", "index", "theta"):
            assert torch.equal(post_a.buffers[name][key], post_b.buffers[name][key])


@pytest.mark.slow  # trainings at 1 and 2 threads
def test_result_does_not_depend_on_the_number_of_threads(mixture, tmp_path):
    before = torch.get_num_threads()
    try:
        posteriors = []
        for threads in (1, 2):
            cfg = config(n_particles=1500, chunk_size=600).model_copy(
                update={"threads": threads}
            )
            train(cfg, tmp_path / f"t{threads}", pairs=(mixture, mixture))
            posteriors.append(Posterior.load(tmp_path / f"t{threads}" / "posterior.pt"))
    finally:
        torch.set_num_threads(before)
    for name in ("idm", "hl"):
        for key in ("score", "index", "theta"):
            assert torch.equal(
                posteriors[0].buffers[name][key], posteriors[1].buffers[name][key]
            )


@pytest.mark.slow  # a training with TensorBoard
def test_outputs_and_event_tags(mixture, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import (
        EventAccumulator,
    )

    cfg = config(n_particles=2000, chunk_size=500, sensitivity_n=[5, 10])
    out = tmp_path / "run"
    result = run_study(cfg, out, pairs=(mixture, mixture))
    on_disk = json.loads((out / "summary.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    for entry in ("idm", "hl", "hybrid"):
        assert set(metrics[entry]) >= {"e_p", "e_v", "e_a", "min", "beta_ws", "ws"}
    for name in ("table.md", "shares.png", "pairwise.png", "radar.png"):
        assert (out / "report" / name).stat().st_size > 0
    assert (out / "report" / "error_evolution.png").exists()
    assert on_disk["shares"] == result.summary.shares
    assert set(on_disk["per_model"]["idm"]) >= {
        "best_score",
        "threshold",
        "invalid",
        "particles_per_s",
    }
    assert len(on_disk["pairwise"]["table"]) == 2
    assert set(on_disk["sensitivity"]) == {"5", "10"}
    assert on_disk["config_hash"] and on_disk["versions"]["torch"]
    resolved = json.loads((out / "config.json").read_text())
    assert resolved["abc"]["n_particles"] == 2000
    events = EventAccumulator(str(out / "tb"), size_guidance={"scalars": 0})
    events.Reload()
    tags = events.Tags()
    assert {"abc/particles/idm", "abc/threshold/hl", "hybrid/share/idm"} <= set(
        tags["scalars"]
    )
    assert "posterior/idm/v0" in tags["histograms"]
    assert {"hybrid/shares", "hybrid/pairwise", "eval/radar"} <= set(tags["images"])
    assert "eval/ws/hybrid" in tags["scalars"]


def test_existing_run_is_refused_and_resume_of_a_finished_run_is_idempotent(
    mixture, tmp_path
):
    from torchcf.train import RunError

    cfg = config(n_particles=1000, chunk_size=500)
    out = tmp_path / "run"
    first = train(cfg, out, pairs=(mixture, mixture))
    with pytest.raises(RunError, match="already holds a run"):
        train(cfg, out, pairs=(mixture, mixture))
    again = train(cfg, out, resume=True, pairs=(mixture, mixture))
    assert again.shares == first.shares
    other = config(n_particles=1000, chunk_size=500, seed=2)
    with pytest.raises(RunError, match="different config"):
        train(other, out, resume=True, pairs=(mixture, mixture))


# --------------------------------------------------------------------------------------
# Command line (real data)


def write_config(path: Path, **abc) -> Path:
    settings = {"n_particles": 30000, "chunk_size": 1000, "checkpoint_every": 0.001}
    settings.update(abc)
    path.write_text(
        json.dumps(
            {
                "data": {"name": "car-model-2"},
                "models": ["idm", "llcs"],
                "abc": settings,
                "compile": "off",
                "threads": 1,
            }
        )
    )
    return path


def run_cli(*args: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **(env_extra or {})}
    return subprocess.run(
        [sys.executable, "-m", "torchcf", "train", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=600,
    )


@pytest.mark.slow  # three trainings in subprocesses
def test_resume_after_kill_9_equals_an_uninterrupted_run(data_root, tmp_path):
    cfg_path = write_config(tmp_path / "cfg.json")
    reference = run_cli(str(cfg_path), "--out", str(tmp_path / "ref"))
    assert reference.returncode == 0, reference.stderr
    out = tmp_path / "killed"
    process = subprocess.Popen(
        [sys.executable, "-m", "torchcf", "train", str(cfg_path), "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    checkpoint = out / "checkpoint.pt"
    deadline = time.monotonic() + 300
    while not checkpoint.exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    time.sleep(0.3)  # into the run, past a few checkpoints
    killed = process.poll() is None
    if killed:
        os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert killed, "the run finished before it could be killed; make it longer"
    assert not (out / "summary.json").exists()
    resumed = run_cli(str(cfg_path), "--out", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming from checkpoint.pt: " in resumed.stderr  # says what it reuses
    a = Posterior.load(tmp_path / "ref" / "posterior.pt")
    b = Posterior.load(out / "posterior.pt")
    assert a.shares == b.shares
    for name in a.models:
        for key in ("score", "index", "theta"):
            assert torch.equal(a.buffers[name][key], b.buffers[name][key])
        assert torch.equal(a.hybrid[name].theta, b.hybrid[name].theta)
    summary_a = json.loads((tmp_path / "ref" / "summary.json").read_text())
    summary_b = json.loads((out / "summary.json").read_text())
    for name in a.models:
        assert (
            summary_a["per_model"][name]["invalid"]
            == summary_b["per_model"][name]["invalid"]
        )


def test_cli_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"data": {"name": "car-model-2"}, "abc": {"n_particles": -1}}')
    assert main([str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "n_particles" in err and "\n" not in err
    assert main([str(tmp_path / "missing.json")]) == 2
    unknown = tmp_path / "unknown.json"
    unknown.write_text('{"data": {"name": "car-model-2"}, "abc": {"n_particle": 5}}')
    assert main([str(unknown)]) == 2
    assert "n_particle" in capsys.readouterr().err


@pytest.mark.slow  # trainings in subprocesses
def test_cli_resume_with_a_different_config_is_refused(data_root, tmp_path):
    cfg_path = write_config(tmp_path / "cfg.json", n_particles=2000)
    out = tmp_path / "run"
    assert run_cli(str(cfg_path), "--out", str(out)).returncode == 0
    refused = run_cli(
        str(cfg_path), "--out", str(out), "--resume", "--set", "abc.seed=5"
    )
    assert refused.returncode == 2
    assert "different config" in refused.stderr
    assert [line for line in refused.stderr.splitlines() if "error" in line] == [
        refused.stderr.strip()
    ]


def test_cuda_chunks_are_larger_by_default():
    """On CUDA a chunk holds at least CUDA_CHUNK_CELLS cells (launch overhead),
    unless the config sets one; no GPU is touched."""
    from torchcf.abc.rejection import CUDA_CHUNK_CELLS
    from torchcf.calibration.of_config import setup_of
    from torchcf.models import get_model

    pairs = synthetic_pairs(n_pairs=4, n_steps=50)
    model = get_model("idm")
    cuda, cpu = torch.device("cuda"), torch.device("cpu")

    def _chunk_size(cfg, model, pairs, compiled, device):
        rollout = setup_of(cfg, pairs, device).rollout
        return rollout.chunk(model, cfg.abc.n_particles, compiled)

    big = config(n_particles=10_000_000)
    assert _chunk_size(big, model, pairs, False, cpu) == model.chunk_cells
    assert _chunk_size(big, model, pairs, False, cuda) == CUDA_CHUNK_CELLS
    full = config(n_particles=10_000_000, layout="full")
    assert _chunk_size(full, model, pairs, False, cuda) == CUDA_CHUNK_CELLS // 4
    assert _chunk_size(config(n_particles=1000), model, pairs, False, cuda) == 1000
    fixed = config(n_particles=10_000_000, chunk_size=4096)
    assert _chunk_size(fixed, model, pairs, False, cuda) == 4096
