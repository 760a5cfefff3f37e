"""Rounds are the unit of progress and checkpoints: a long stream of any model,
the MPC's above all, advances in many of them, and the buffers do not depend on
how it was cut.

A million MPC particles used to be one chunk (``chunk_cells = 1 << 20``): the
progress bar stood at 0 % until the model was done and no checkpoint could fall
inside it. The pairs here are short (a few steps) so that streams of a few
default chunks simulate in a second or two.
"""

from __future__ import annotations

import math

import pytest
import torch
from tqdm import tqdm

import torchcf.train.run as run_module
from torchcf.abc.rejection import (
    CUDA_CHUNK_CELLS,
    ModelProgress,
    Rollout,
    prior_stream,
    run_rejection,
)
from torchcf.abc.rounds import PILOT_ROUND, RoundHooks
from torchcf.abc.topn import TopN
from torchcf.config import TrainConfig
from torchcf.models import MODELS, get_model
from torchcf.models.mpc import MPC
from torchcf.posterior import Posterior
from torchcf.runs.directory import RunDir
from torchcf.sim.synthetic import synthetic_pairs
from torchcf.train import train

#: The MPC's chunk before rounds were made small: a million particles in one.
OLD_MPC_CHUNK_CELLS = 1 << 20
MPC_TRUTH = [1.0, 1.0, 1.0, 5.0, -4.0, 4.0]


def _short_pairs(n_pairs: int = 4, n_steps: int = 30):
    return synthetic_pairs(get_model("mpc"), MPC_TRUTH, n_pairs, n_steps, seed=2)


def _mpc_stream(
    rollout: Rollout, n: int, stop_after: int | None = None
) -> tuple[TopN, ModelProgress, list[int]]:
    """MPC's prior stream of ``n`` particles through a buffer; the progress seen
    after every round. ``stop_after`` rounds, then a restart from a copy of the
    state at that point (what ``--resume`` reads from a checkpoint)."""
    model = get_model("mpc")
    bounds = model.prior_bounds(torch.float64)
    buffer = TopN(rollout.pairs.n_pairs, 5, model.n_params)
    progress = ModelProgress()
    seen: list[int] = []

    class Killed(Exception):
        pass

    def after_round(state: ModelProgress, due: bool) -> None:
        seen.append(state.next)
        if stop_after is not None and len(seen) == stop_after:
            raise Killed

    def stream() -> None:
        run_rejection(
            prior_stream(get_model("mpc"), bounds, 0, rollout),
            buffer,
            rollout,
            n,
            progress,
            hooks=RoundHooks(after_round=after_round),
        )

    try:
        stream()
    except Killed:
        saved = (progress.as_dict(), buffer.state_dict())
        progress = ModelProgress(**saved[0])
        buffer = TopN(rollout.pairs.n_pairs, 5, model.n_params)
        buffer.load_state_dict({k: v.clone() for k, v in saved[1].items()})
        stop_after = None
        stream()
    return buffer, progress, seen


def test_a_million_paired_mpc_particles_are_many_rounds():
    pairs = _short_pairs(n_pairs=44)  # CAR MODEL II's training pairs
    rollout = Rollout(pairs, compile="off")
    mpc = get_model("mpc")
    chunk = rollout.chunk(mpc, 1_000_000, compiled=False)
    assert chunk == mpc.chunk_cells  # a cell is a particle in the paired layout
    assert math.ceil(1_000_000 / chunk) >= 16
    old = min(OLD_MPC_CHUNK_CELLS, 1_000_000)
    assert math.ceil(1_000_000 / old) == 1
    # The full layout keeps the batch of QPs: a particle is a cell per pair.
    full = Rollout(pairs, paired=False, compile="off")
    assert full.chunk(mpc, 1_000_000, compiled=False) == mpc.chunk_cells // 44
    for name in MODELS:  # no model takes a million particles in fewer than 4
        model = get_model(name)
        assert math.ceil(1_000_000 / rollout.chunk(model, 1_000_000, False)) >= 4


def test_cuda_chunks_are_unchanged():
    """On CUDA every model still gets at least CUDA_CHUNK_CELLS cells a chunk
    (the CPU budgets are below it); no GPU is touched."""
    pairs = _short_pairs(n_pairs=44)
    rollout = Rollout(pairs, device=torch.device("cuda"), compile="off")
    for name in MODELS:
        model = get_model(name)
        assert model.chunk_cells <= CUDA_CHUNK_CELLS
        assert rollout.chunk(model, 10_000_000, False) == CUDA_CHUNK_CELLS


@pytest.mark.slow  # MPC streams
def test_the_mpc_stream_reports_every_round_with_the_buffers_of_one_chunk(
    monkeypatch,
):
    rollout = Rollout(_short_pairs(), compile="off")
    chunk = get_model("mpc").chunk_cells
    n = 2 * chunk + 1000
    buffer, progress, seen = _mpc_stream(rollout, n)
    assert seen == [chunk, 2 * chunk, n]
    assert progress.next == n

    # Before: one chunk held the whole stream, one report at its end.
    monkeypatch.setattr(MPC, "chunk_cells", OLD_MPC_CHUNK_CELLS)
    one_chunk, _, seen_before = _mpc_stream(rollout, n)
    assert seen_before == [n]
    for key in ("score", "index", "theta"):
        assert torch.equal(getattr(buffer, key), getattr(one_chunk, key)), key


@pytest.mark.slow  # MPC streams cut and resumed
def test_an_mpc_stream_cut_between_rounds_resumes_to_the_same_buffers():
    rollout = Rollout(_short_pairs(), compile="off")
    chunk = get_model("mpc").chunk_cells
    n = 2 * chunk + 1000
    whole, progress, _ = _mpc_stream(rollout, n)
    resumed, resumed_progress, seen = _mpc_stream(rollout, n, stop_after=1)
    assert seen == [chunk, 2 * chunk, n]
    assert resumed_progress.as_dict() | {"seconds": 0} == progress.as_dict() | {
        "seconds": 0
    }
    for key in ("score", "index", "theta"):
        assert torch.equal(getattr(whole, key), getattr(resumed, key)), key


@pytest.mark.slow  # a training with MPC
def test_training_moves_the_mpc_bar_and_checkpoints_inside_the_model(
    monkeypatch, tmp_path
):
    updates: list[int] = []
    saves: list[dict] = []

    class CountingBar(tqdm):
        def update(self, n=1):
            if n:
                updates.append(n)
            return super().update(n)

    save_checkpoint = RunDir.save_checkpoint

    def counting_save(self, checkpoint):
        saves.append(checkpoint["progress"]["mpc"])
        return save_checkpoint(self, checkpoint)

    monkeypatch.setattr(run_module, "tqdm", CountingBar)
    monkeypatch.setattr(RunDir, "save_checkpoint", counting_save)
    chunk = get_model("mpc").chunk_cells
    n = 2 * chunk + 1000
    cfg = TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["mpc"],
            "abc": {
                "n_particles": n,
                "top_n": 5,
                "sensitivity_n": [5],
                "checkpoint_every": 1e-9,
            },
            "compile": "off",
        }
    )
    pairs = _short_pairs()
    train(cfg, tmp_path / "run", pairs=(pairs, pairs))
    # early rejection (the default) opens with a pilot round of 1/16 of a chunk
    pilot = chunk // PILOT_ROUND
    assert updates == [pilot, chunk, n - pilot - chunk]
    inside = [s["next"] for s in saves if not s["done"]]
    assert inside == [pilot, pilot + chunk, n]
    assert Posterior.load(tmp_path / "run" / "posterior.pt").buffers["mpc"]
