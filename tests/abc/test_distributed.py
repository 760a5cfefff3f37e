"""Distributed training (torchcf.distributed): sharding, merging, torchrun.

The exactness argument has two halves, each tested here: the ranks simulate
exactly the chunks of a single process (``Group.shard``), and merging the ranks'
replicas of a top-N buffer gives the buffer of one process that saw everything
(``TopN.merge``). The end-to-end test then launches two processes with torchrun
(gloo on CPU) and compares every output with a single-process run.
"""

from __future__ import annotations

import json
import sys

import pytest
import torch

from tests.abc.interrupt import interrupt_after
from tests.runs import torchrun_train, write_config, write_data
from torchcf.abc.distributed import SINGLE, Group, GroupError, init_from_env
from torchcf.abc.topn import TopN
from torchcf.config import load_config
from torchcf.evaluation.evaluate import evaluate_run
from torchcf.posterior import Posterior
from torchcf.study.pipeline import run_study

# ------------------------------------------------------------------ the pieces


def _candidates(n: int, n_pairs: int, seed: int, ties: bool = True):
    generator = torch.Generator().manual_seed(seed)
    pair = torch.randint(0, n_pairs, (n,), generator=generator)
    score = torch.rand(n, generator=generator, dtype=torch.float64)
    if ties:  # many exact ties: the index must break them
        score = (score * 20).floor() / 20
    score[torch.rand(n, generator=generator) < 0.1] = torch.inf  # invalid
    theta = torch.rand(n, 3, generator=generator, dtype=torch.float64)
    return pair, score, torch.arange(n), theta


@pytest.mark.parametrize("world_size", [2, 3, 5])
def test_merged_replicas_equal_one_buffer(world_size):
    pair, score, index, theta = _candidates(4000, 7, seed=world_size)
    single = TopN(7, 6, 3)
    for part in torch.arange(4000).split(333):  # one process, chunk after chunk
        single.push(pair[part], score[part], index[part], theta[part])

    replicas = [TopN(7, 6, 3) for _ in range(world_size)]
    chunks = list(torch.arange(4000).split(333))
    for first in range(0, len(chunks), world_size):  # rounds, as the trainer does
        for rank, replica in enumerate(replicas):
            if first + rank < len(chunks):
                part = chunks[first + rank]
                replica.push(pair[part], score[part], index[part], theta[part])
        stacked = [
            torch.stack([getattr(r, key) for r in replicas])
            for key in ("score", "index", "theta")
        ]
        for replica in replicas:
            replica.merge(*stacked)
    for replica in replicas:
        for key in ("score", "index", "theta"):
            assert torch.equal(getattr(replica, key), getattr(single, key)), key


def test_pushing_held_entries_again_changes_nothing():
    pair, score, index, theta = _candidates(500, 4, seed=1)
    buffer = TopN(4, 5, 3)
    buffer.push(pair, score, index, theta)
    before = {k: v.clone() for k, v in buffer.state_dict().items()}
    buffer.push(pair, score, index, theta)  # every candidate offered twice
    both = torch.cat((pair, pair)), torch.cat((score, score))
    buffer.push(*both, torch.cat((index, index)), torch.cat((theta, theta)))
    for key, value in before.items():
        assert torch.equal(buffer.state_dict()[key], value), key
    # Full layout: one particle on several pairs is one entry per pair.
    full = TopN(3, 2, 1)
    full.push_full(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([0]), torch.ones(1, 1))
    full.merge(*(v[None] for v in full.state_dict().values()))
    assert full.index[:, 0].tolist() == [0, 0, 0] and full.index[:, 1].tolist() == [
        -1,
        -1,
        -1,
    ]


def test_merge_rejects_replicas_of_another_shape():
    buffer = TopN(4, 5, 3)
    with pytest.raises(ValueError, match="replicas must be"):
        buffer.merge(torch.zeros(2, 4, 6), torch.zeros(2, 4, 6).long(), torch.zeros(2))


@pytest.mark.parametrize(("world_size", "n", "chunk"), [(2, 3000, 500), (3, 2900, 400)])
def test_ranks_simulate_the_chunks_of_one_process(world_size, n, chunk):
    groups = [Group(rank, world_size) for rank in range(world_size)]
    seen = []
    for first in range(0, n, chunk * world_size):
        for group in groups:
            start, stop = group.shard(first, n, chunk)
            if start < stop:
                seen.append((start, stop))
    single = [(a, min(a + chunk, n)) for a in range(0, n, chunk)]
    assert sorted(seen) == single


def test_a_single_process_group_is_inert(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert init_from_env("cpu") is SINGLE
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert init_from_env("cuda") is SINGLE
    assert SINGLE.is_main and not SINGLE.distributed
    assert SINGLE.on_main(lambda a, b: a + b, 2, 3) == 5
    buffer = TopN(2, 2, 1)
    assert SINGLE.end_round(buffer, 7, True) == (7, True)
    assert SINGLE.run_device("cuda") == torch.device("cuda")
    assert Group(1, 4, 1).run_device("cuda") == torch.device("cuda", 1)
    assert Group(1, 4, 1).run_device("cuda:0") == torch.device("cuda", 0)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "two")
    with pytest.raises(GroupError, match="torchrun environment"):
        init_from_env("cpu")


def _as_rank(monkeypatch, rank: int, payload: list) -> Group:
    """A rank of a two-process group whose broadcast hands out ``payload``."""
    import torchcf.abc.distributed as module

    def broadcast(objects, src, device=None):
        assert src == 0
        if rank:
            objects[0] = payload[0]
        else:
            payload[0] = objects[0]

    monkeypatch.setattr(module.dist, "broadcast_object_list", broadcast)
    return Group(rank, 2)


def test_rank_0_results_and_errors_reach_every_rank(monkeypatch):
    from torchcf.config import ConfigError
    from torchcf.train import RunError

    payload: list = [None]
    ran = []
    main = _as_rank(monkeypatch, 0, payload)
    assert main.on_main(lambda x: ran.append(x) or x * 2, 21) == 42
    other = _as_rank(monkeypatch, 1, payload)
    assert other.on_main(lambda x: ran.append(x), 21) == 42
    assert ran == [21]  # rank 1 never ran it

    def refuse():
        raise RunError("out holds another run")

    main = _as_rank(monkeypatch, 0, payload)
    with pytest.raises(RunError, match="out holds another run") as on_main:
        main.on_main(refuse)
    assert not getattr(on_main.value, "from_main", False)  # rank 0 reports it
    other = _as_rank(monkeypatch, 1, payload)
    with pytest.raises(RunError, match="out holds another run") as on_other:
        other.on_main(refuse)
    assert on_other.value.from_main  # ... the others stay quiet

    class Odd(Exception):
        def __init__(self, a, b):
            super().__init__(f"{a}/{b}")

    def odd():
        raise Odd(1, 2)

    main = _as_rank(monkeypatch, 0, payload)
    with pytest.raises(Odd):
        main.on_main(odd)
    other = _as_rank(monkeypatch, 1, payload)
    with pytest.raises(GroupError, match="rank 0 failed: Odd: 1/2"):
        other.on_main(odd)
    assert issubclass(ConfigError, ValueError)


# ------------------------------------------------------------------ torchrun


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A single-process reference run, and a run cut short after two chunks."""
    root = tmp_path_factory.mktemp("dist")
    data = write_data(root / "pairs")
    config = write_config(root / "cfg.json", data, abc={"checkpoint_every": 1e-9})
    cfg = load_config(config)
    reference = root / "single"
    run_study(cfg, reference)

    partial = root / "partial"
    interrupt_after(2, lambda: run_study(cfg, partial))
    saved = torch.load(partial / "checkpoint.pt", weights_only=True)
    # early rejection's pilot round (1/16 of a chunk), then a chunk of 500
    assert 500 < saved["progress"]["idm"]["next"] < cfg.abc.n_particles
    assert "llcs" not in saved["progress"] or not saved["progress"]["llcs"]["next"]
    return config, reference, partial


@pytest.mark.slow  # torchrun: three trainings in subprocesses
@pytest.mark.skipif(sys.platform == "win32", reason="torchrun on POSIX only")
def test_two_processes_resume_and_equal_a_single_process(runs):
    """torchrun, 2 ranks (gloo): resumes the run cut short (rank 0 reads the
    checkpoint), shares the rest of IDM and all of LLCS, and ends with the outputs
    of the uninterrupted single-process run, bit for bit."""
    config, reference, partial = runs
    two = torchrun_train(str(config), "--out", str(partial), "--resume", "--no-eval")
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count("hybrid shares") == 1, two.stdout  # rank 0 alone reports
    # The evaluation is rank 0's alone, a single-process step: run here, it saves
    # the 2 x 10 s of importing the plotting stack in the children.
    evaluate_run(partial)

    a = Posterior.load(reference / "posterior.pt")
    b = Posterior.load(partial / "posterior.pt")
    assert a.shares == b.shares
    for name in a.models:
        for key in ("score", "index", "theta"):
            assert torch.equal(a.buffers[name][key], b.buffers[name][key])
        for key in ("theta", "score", "pair_ids", "particle_index"):
            assert torch.equal(
                getattr(a.hybrid[name], key), getattr(b.hybrid[name], key)
            )
    summary_a = json.loads((reference / "summary.json").read_text())
    summary_b = json.loads((partial / "summary.json").read_text())
    assert summary_b["processes"] == 2
    timing = {"seconds", "particles_per_s"}
    # With early rejection (the default) which rollouts stop depends on the
    # thresholds a chunk starts from, which the ranks' schedule and the resume
    # set (SPEC section 2: the counts, not the buffers).
    schedule = {"stopped", "invalid", "invalid_rate"}
    for name in a.models:
        for key, value in summary_a["per_model"][name].items():
            if key not in timing | schedule:
                assert summary_b["per_model"][name][key] == value, (name, key)
    for key in ("shares", "pairwise", "sensitivity", "config_hash"):
        assert summary_a[key] == summary_b[key], key
    metrics_a = json.loads((reference / "metrics.json").read_text())
    metrics_b = json.loads((partial / "metrics.json").read_text())
    assert metrics_a.pop("seconds") > 0 and metrics_b.pop("seconds") > 0  # timings
    assert metrics_a == metrics_b
    final_a = torch.load(reference / "checkpoint.pt", weights_only=True)
    final_b = torch.load(partial / "checkpoint.pt", weights_only=True)
    for name in a.models:
        assert final_a["progress"][name]["next"] == final_b["progress"][name]["next"]
        for key in ("score", "index", "theta"):
            assert torch.equal(
                final_a["buffers"][name][key], final_b["buffers"][name][key]
            )
    leftovers = [p.name for p in partial.iterdir() if ".tmp" in p.name]
    assert not leftovers
