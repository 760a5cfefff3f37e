"""Every pair calibrated, at scale: the small versions of what
``tools/bench_scale.py`` measures over thousands of pairs.

A refinement's state has the size of its per-pair populations whatever the
rounds, and nothing once it is finished; a chunk's merge and its simulate call
touch the pairs it reaches, not all of them, with the same result; a run over a
few hundred pairs does not depend on the chunk size (SMC, and rejection in the
full layout) and resumes identical. No timings: those are the benchmark's.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchcf.abc.smc as smc
from tests.abc.interrupt import interrupt_after, same_buffers
from torchcf.abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from torchcf.abc.smc import SMCSettings, new_state, run_smc, smc_budget
from torchcf.abc.topn import TopN
from torchcf.config import TrainConfig
from torchcf.models import get_model
from torchcf.posterior import Posterior
from torchcf.sim.rollout import simulate
from torchcf.sim.synthetic import synthetic_pairs
from torchcf.train import train

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
SETTINGS = {"population": 10, "rounds": 3, "prior_fraction": 0.3, "quantile": 0.5}
N_PAIRS = 300


@pytest.fixture(scope="module")
def many():
    """300 short IDM pairs (40 steps): a few hundred pairs in a second."""
    return synthetic_pairs(get_model("idm"), IDM, N_PAIRS, 40, seed=4, noise=0.05)


def _config(**abc) -> TrainConfig:
    settings = {
        "method": "smc",
        "smc": SETTINGS,
        "n_particles": 60 * N_PAIRS,
        "top_n": 3,
        "sensitivity_n": [3],
        "seed": 2,
    }
    return TrainConfig.model_validate(
        {
            "data": {"path": "synthetic"},
            "models": ["idm", "llcs"],
            "abc": {**settings, **abc},
            "compile": "off",
            "plausibility": {"report": False},
        }
    )


def _tensor_bytes(value) -> int:
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(_tensor_bytes(v) for v in value.values())
    return 0


def _same_buffers(a: Posterior, b: Posterior) -> None:
    assert a.shares == b.shares
    same_buffers(a, b)


# ------------------------------------------------------------ state size
@pytest.mark.parametrize("rounds", [2, 6])
def test_the_refinement_state_does_not_grow_with_rounds(many, monkeypatch, rounds):
    """At every round's end the state holds two per-pair populations, the same
    bytes in round 1 as in round R; finished, it holds no tensor."""
    pairs = many.subset(torch.arange(60))
    settings = SMCSettings(**{**SETTINGS, "rounds": rounds})
    sizes = []
    real = smc._next_population

    def record(state, *args):
        real(state, *args)
        sizes.append(_tensor_bytes(state.state_dict()))

    monkeypatch.setattr(smc, "_next_population", record)
    state = new_state(pairs.n_pairs, settings, 6)
    assert state.accepted is None  # built when the refinement runs
    rollout = Rollout(pairs, dtype=torch.float64, compile="off")
    run_smc(
        prior_stream(
            get_model("idm"), get_model("idm").prior_bounds(torch.float64), 0, rollout
        ),
        TopN(pairs.n_pairs, 3, 7),
        rollout,
        40 * pairs.n_pairs,
        settings,
        ModelProgress(),
        state,
    )
    per_pair = 2 * settings.population * (7 * 8 + 8 + 8)  # theta, score, index
    assert len(sizes) == rounds + 1
    assert set(sizes) == {pairs.n_pairs * per_pair}
    assert _tensor_bytes(state.state_dict()) == 0
    assert state.accepted is None and state.population == {}


def test_a_checkpoint_of_the_box_kernel_is_not_continued():
    state = new_state(4, SMCSettings(), 6)
    saved = {"round": 2, "next": 0, "accepted": None, "population": {}}  # no space
    with pytest.raises(ValueError, match="'box' space"):
        state.load_state_dict(saved)
    state.load_state_dict({**saved, "space": "logit"})
    assert state.round == 2


# ------------------------------------------------------ chunks touch slices
def test_a_push_reaching_few_pairs_equals_a_full_sort():
    """Candidates pushed in chunks that reach a slice of the pairs (a
    refinement round's) or all of them (the prior round's) leave every pair's
    best ``capacity`` by (score, index), as one sort of everything."""
    g = torch.Generator().manual_seed(3)
    n_pairs, capacity, total = 500, 4, 12_000
    pair = torch.cat(
        (
            torch.randint(0, n_pairs, (total // 2,), generator=g),
            torch.arange(total // 2) // (total // 2 // n_pairs),  # pair-major
        )
    )
    score = torch.randint(0, 50, (total,), generator=g).double()  # many ties
    score[torch.rand(total, generator=g) < 0.05] = math.inf
    index = torch.arange(total)
    theta = torch.randn(total, 2, generator=g, dtype=torch.float64)
    buffer = TopN(n_pairs, capacity, 2)
    for start in range(0, total, 997):
        rows = slice(start, start + 997)
        buffer.push(pair[rows], score[rows], index[rows], theta[rows])
    for p in range(n_pairs):
        mine = ((pair == p) & torch.isfinite(score)).nonzero().squeeze(1)
        order = sorted(mine.tolist(), key=lambda j: (float(score[j]), j))[:capacity]
        held = buffer.index[p][buffer.index[p] >= 0].tolist()
        assert held == order, p
        assert torch.equal(buffer.theta[p, : len(order)], theta[order])


def test_a_chunk_on_a_slice_of_the_pairs_scores_as_on_the_whole_set(many):
    """Rollout.score simulates on the pairs its particles reach only; the scores
    are those of a simulate call given every pair."""
    model = get_model("idm")
    g = torch.Generator().manual_seed(1)
    bounds = model.prior_bounds(torch.float64)
    theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * torch.rand(
        64, 6, generator=g, dtype=torch.float64
    )
    pair = torch.randint(120, 140, (64,), generator=g)
    rollout = Rollout(many, dtype=torch.float32, compile="off")
    score, valid = rollout.score(model, theta, pair)
    whole = simulate(model, theta.float(), many, pair, dtype=torch.float32)
    assert torch.equal(score, whole.score.double())
    assert torch.equal(valid, whole.valid)


def test_a_round_is_cut_in_equal_chunks():
    """A refinement round is simulated in equal chunks no larger than the
    rollout's, never a whole chunk padded for a remainder."""
    pairs = synthetic_pairs(get_model("idm"), IDM, 4, 20, seed=1)
    model = get_model("mpc")  # simulates whole chunks (not batch-size invariant)
    for cap, per_round, expected in (
        (1000, 2500, 834),
        (1000, 1000, 1000),
        (97, 50, 50),
    ):
        rollout = Rollout(pairs, compile="off", chunk_size=cap)
        assert smc._round_chunk(rollout, model, per_round, False) == expected
    rollout = Rollout(pairs, compile="off", chunk_size=1000)
    assert smc._round_chunk(rollout, model, 2500, True) == 896  # lanes of 64


# ------------------------------------------------- a few hundred pairs, whole
def test_smc_over_hundreds_of_pairs_does_not_depend_on_the_chunk(many, tmp_path):
    """The default chunk (a round in one call, every pair in it) against chunks
    of 997 proposals (each a slice of the pairs): the same buffers."""
    posteriors = []
    for chunk in (None, 997):
        out = tmp_path / f"c{chunk}"
        train(_config(chunk_size=chunk), out, pairs=(many, many.subset([0, 1])))
        posteriors.append(Posterior.load(out / "posterior.pt"))
    _same_buffers(*posteriors)


def test_rejection_in_the_full_layout_does_not_depend_on_the_chunk(many):
    """Every particle on every one of 300 pairs: chunks of 7 and of 64 particles
    leave the same buffers."""
    model = get_model("llcs")
    bounds = model.prior_bounds(torch.float64)
    buffers = []
    for chunk in (7, 64):
        rollout = Rollout(many, paired=False, compile="off", chunk_size=chunk)
        buffer = TopN(N_PAIRS, 3, model.n_params)
        stream = prior_stream(get_model("llcs"), bounds, 5, rollout)
        run_rejection(stream, buffer, rollout, 150, ModelProgress())
        buffers.append(buffer)
    a, b = buffers
    assert bool(torch.isfinite(a.score).all())
    for key in ("score", "index", "theta"):
        assert torch.equal(getattr(a, key), getattr(b, key))


def test_smc_over_hundreds_of_pairs_resumes_identical(many, tmp_path):
    """Killed inside the first model's second round and resumed: the run ends as
    one never stopped; the checkpoint holds no refinement state of a finished
    model."""
    # Without early rejection: its pilot round adds a rollout call the count of
    # calls below would have to know of (its own resume: test_early_rejection).
    cfg = _config(chunk_size=2000, checkpoint_every=1e-9, early_rejection=False)
    test = many.subset([0, 1])
    reference = train(cfg, tmp_path / "ref", pairs=(many, test))
    budget = smc_budget(cfg.abc.n_particles, N_PAIRS, SMCSettings(**SETTINGS))
    first_round_calls = -(-budget.prior // 2000)
    out = tmp_path / "cut"
    # inside IDM's round 1
    interrupt_after(first_round_calls + 2, lambda: train(cfg, out, pairs=(many, test)))
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["smc"]["idm"]["round"] == 1 and saved["smc"]["idm"]["next"] > 0
    resumed = train(cfg, out, resume=True, pairs=(many, test))
    assert resumed.shares == reference.shares
    assert resumed.smc == reference.smc
    _same_buffers(
        Posterior.load(tmp_path / "ref" / "posterior.pt"),
        Posterior.load(out / "posterior.pt"),
    )
    final = torch.load(out / "checkpoint.pt", weights_only=True)
    for name in ("idm", "llcs"):
        assert _tensor_bytes(final["smc"][name]) == 0, name
