"""Early rejection (``abc.early_rejection``): a rollout stopped once its score so
far exceeds what its buffer keeps.

The bound is a bound (never above the final score); a simulate call with a
ceiling gives every cell it did not stop exactly the result of a call without
one, for every model and both layouts, and stops only cells whose score does
exceed their ceiling; the engine's buffers (rejection and SMC, any chunk,
resumed or not) are those of a run without early rejection.
"""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tests.abc.interrupt import interrupt_after, same_buffers
from torchcf.abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from torchcf.abc.rounds import PILOT_ROUND, Plan, round_bounds
from torchcf.abc.topn import TopN
from torchcf.config import TrainConfig
from torchcf.models import MODELS, get_model
from torchcf.posterior import Posterior
from torchcf.sim.rollout import (
    Execution,
    _Accumulators,
    resolve_compile,
    score_so_far,
    simulate,
)
from torchcf.sim.synthetic import synthetic_pairs
from torchcf.train import train

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
N_PAIRS = 6


@pytest.fixture(scope="module")
def pairs():
    """Six noisy IDM pairs of 120 steps."""
    return synthetic_pairs(get_model("idm"), IDM, N_PAIRS, 120, seed=3, noise=0.1)


def _prior_draws(name: str, count: int, seed: int) -> torch.Tensor:
    model = get_model(name)
    box = model.prior_bounds(torch.float64)
    u = torch.rand(count, model.n_params, generator=torch.Generator().manual_seed(seed))
    return box[:, 0] + u.double() * (box[:, 1] - box[:, 0])


def _ceiling_of(score: torch.Tensor, pair: torch.Tensor | None) -> torch.Tensor:
    """Per pair the 5th best of ``score``: most cells lie above it."""
    if pair is None:
        return score.double().sort(0).values[4].expand_as(score).clone()
    tops = torch.full((N_PAIRS,), math.inf, dtype=torch.float64)
    for j in range(N_PAIRS):
        mine = score.double()[pair == j].sort().values
        tops[j] = mine[min(4, mine.numel() - 1)]
    return tops[pair]


# ------------------------------------------------------------------ the bound
def test_the_score_so_far_never_falls_in_floating_point():
    """The bound only rises as steps are added (so it never exceeds the final
    score, the same expression of the final sums), in float32 and float64,
    with squared errors spanning twelve orders of magnitude and counts of 1 to
    10^4 steps."""
    generator = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        counts = torch.randint(1, 10_000, (5000,), generator=generator)
        sums = [torch.zeros(5000, dtype=dtype) for _ in range(3)]
        acc = _Accumulators(*sums, invalid=torch.zeros(5000, dtype=torch.bool))
        before = score_so_far(acc, counts, (0.5, 0.3, 0.2))
        for _ in range(200):
            steps = [
                (10.0 ** torch.empty(5000).uniform_(-8, 4, generator=generator)).to(
                    dtype
                )
                for _ in range(3)
            ]
            acc = acc._replace(
                sq_x=acc.sq_x + steps[0],
                sq_v=acc.sq_v + steps[1],
                sq_a=acc.sq_a + steps[2],
            )
            now = score_so_far(acc, counts, (0.5, 0.3, 0.2))
            assert bool((now >= before).all())
            before = now


# --------------------------------------------------------------- simulate
@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("paired", [True, False])
def test_a_ceiling_stops_only_cells_above_it_and_leaves_the_rest_exact(
    pairs, name, paired
):
    """Cells not stopped score bit for bit as without a ceiling; the stopped
    ones are valid, score +inf, and without the ceiling score above it. Chunks
    of 100 (not whole vector lanes) against 256 with the ceiling."""
    count = 600 if paired else 40
    theta = _prior_draws(name, count, seed=2)
    pair = torch.arange(count) % N_PAIRS if paired else None
    # the MPC's solver rounds by batch size (batch_size_invariant): one chunk
    invariant = get_model(name).batch_size_invariant
    chunk = (100 if paired else 8) if invariant else 256
    plain = simulate(
        get_model(name), theta, pairs, pair, execution=Execution(chunk_size=chunk)
    )
    ceiling = _ceiling_of(plain.score, pair)
    cut = simulate(
        get_model(name),
        theta,
        pairs,
        pair,
        execution=Execution(chunk_size=256, ceiling=ceiling),
    )
    stopped = cut.pruned
    assert stopped is not None and stopped.shape == plain.score.shape
    assert int(stopped.sum()) > 0
    assert bool((plain.score.double()[stopped] > ceiling[stopped]).all())
    assert bool(cut.valid[stopped].all()) and bool(
        torch.isinf(cut.score[stopped]).all()
    )
    kept = ~stopped
    for field in ("score", "e_p", "e_v", "e_a", "valid"):
        assert torch.equal(getattr(cut, field)[kept], getattr(plain, field)[kept]), (
            field
        )
    # a cell at or under its ceiling is never stopped
    assert bool(kept[plain.score.double() <= ceiling].all())


@pytest.mark.compile
@pytest.mark.parametrize(
    "name, paired, graphs",
    [("idm", True, 1), ("mpc", False, 2)],  # MPC: draft, finish
)
def test_compiled_blocks_stop_exactly_with_one_graph(pairs, name, paired, graphs):
    """Compiled, a ceiling stops the same cells and leaves the rest bit for bit
    as the compiled rollout without it, the shrinking batches all run by one
    graph per function (the particle dimension traced dynamic) rather than one
    compiled per batch size."""
    count = 1200 if paired else 160
    theta = _prior_draws(name, count, seed=6)
    pair = torch.arange(count) % N_PAIRS if paired else None
    compiled = Execution(chunk_size=256, compile=True)
    plain = simulate(get_model(name), theta, pairs, pair, execution=compiled)
    ceiling = _ceiling_of(plain.score, pair)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    cut = simulate(
        get_model(name),
        theta,
        pairs,
        pair,
        execution=replace(compiled, ceiling=ceiling),
    )
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs
    stopped = cut.pruned
    assert 0 < int(stopped.sum()) < stopped.numel()
    assert bool((plain.score.double()[stopped] > ceiling[stopped]).all())
    for field in ("score", "e_p", "e_v", "e_a", "valid"):
        assert torch.equal(
            getattr(cut, field)[~stopped], getattr(plain, field)[~stopped]
        )


def test_float64(pairs):
    theta = _prior_draws("hl", 500, seed=4)
    pair = torch.arange(500) % N_PAIRS
    plain = simulate(get_model("hl"), theta, pairs, pair, dtype=torch.float64)
    ceiling = _ceiling_of(plain.score, pair)
    cut = simulate(
        get_model("hl"),
        theta,
        pairs,
        pair,
        dtype=torch.float64,
        execution=Execution(ceiling=ceiling),
    )
    assert int(cut.pruned.sum()) > 0
    assert torch.equal(cut.score[~cut.pruned], plain.score[~cut.pruned])


#: Models with effects of every kind of memory and preparation: a perception
#: history (delay, sync), a held command (action points), knot values (grade),
#: a realisation (lag), plain parameters, and the MPC's memory under a delay.
WITH_EFFECTS = [
    "idm+delay",
    "gfm+sync",
    "hl+action",
    "idm+grade(start=0,end=400,knots=3)",
    "ovm+offset+anticipation+lag",
    "mpc+delay",
]


@pytest.mark.parametrize("name", WITH_EFFECTS)
@pytest.mark.parametrize("paired", [True, False])
def test_models_with_effects_stop_exactly_too(pairs, name, paired):
    model = get_model(name)
    box = model.prior_bounds(torch.float64)
    count = 400 if paired else 24
    u = torch.rand(count, model.n_params, generator=torch.Generator().manual_seed(8))
    theta = box[:, 0] + u.double() * (box[:, 1] - box[:, 0])
    pair = torch.arange(count) % N_PAIRS if paired else None
    plain = simulate(model, theta, pairs, pair, execution=Execution(chunk_size=128))
    ceiling = _ceiling_of(plain.score, pair)
    cut = simulate(
        model, theta, pairs, pair, execution=Execution(chunk_size=128, ceiling=ceiling)
    )
    assert int(cut.pruned.sum()) > 0
    kept = ~cut.pruned
    assert torch.equal(cut.score[kept], plain.score[kept])
    assert torch.equal(cut.valid[kept], plain.valid[kept])
    assert bool((plain.score.double()[cut.pruned] > ceiling[cut.pruned]).all())


def test_a_ceiling_of_the_wrong_shape_is_refused(pairs):
    theta = _prior_draws("idm", 10, seed=6)
    with pytest.raises(ValueError, match="ceiling must have the score's shape"):
        simulate(
            get_model("idm"),
            theta,
            pairs,
            torch.zeros(10, dtype=torch.long),
            execution=Execution(ceiling=torch.zeros(3)),
        )


# ----------------------------------------------------------------- the engine
def _stream(name: str, rollout: Rollout, n: int, chunk_rollout=None):
    model = get_model(name)
    buffer = TopN(N_PAIRS, 5, model.n_params)
    progress = ModelProgress()
    stream = prior_stream(model, model.prior_bounds(torch.float64), 7, rollout)
    run_rejection(stream, buffer, chunk_rollout or rollout, n, progress)
    return buffer, progress


def _same(a: TopN, b: TopN) -> None:
    for key in ("score", "index", "theta"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key


@pytest.mark.parametrize("name", ["ovm", "idm", "hl", "mpc"])
def test_rejection_keeps_the_same_buffers(pairs, name):
    """3 000 paired particles with early rejection, in chunks of 512 and of
    1 000 (512 only for the MPC): the buffers of the run without it; rollouts
    were stopped."""
    n = 3000
    plain, counted = _stream(name, Rollout(pairs, compile="off", chunk_size=512), n)
    # the MPC's solver rounds by batch size (batch_size_invariant): one chunk
    for chunk in (512, 1000) if get_model(name).batch_size_invariant else (512,):
        rollout = Rollout(pairs, compile="off", chunk_size=chunk, early_rejection=True)
        buffer, progress = _stream(name, rollout, n)
        _same(buffer, plain)
        assert progress.stopped > n // 2
        assert progress.invalid <= counted.invalid


def test_rejection_in_the_full_layout_keeps_the_same_buffers(pairs):
    plain, _ = _stream(
        "llcs", Rollout(pairs, paired=False, compile="off", chunk_size=64), 600
    )
    rollout = Rollout(
        pairs, paired=False, compile="off", chunk_size=64, early_rejection=True
    )
    buffer, progress = _stream("llcs", rollout, 600)
    _same(buffer, plain)
    assert progress.stopped > 0


def test_a_pilot_round_starts_a_stretch_from_nothing():
    """With early rejection (eager or compiled): a pilot round of 1/PILOT_ROUND
    of a chunk, then whole rounds; none when resuming or off."""
    rollout = Rollout(None, compile="off", early_rejection=True)  # type: ignore[arg-type]
    plan = Plan(rollout, get_model("idm"), 1024, compiled=False)
    pilot = 1024 // PILOT_ROUND
    assert round_bounds(plan, 0, 3000, 1) == [
        (0, pilot, pilot),
        (pilot, pilot + 1024, 1024),
        (pilot + 1024, pilot + 2048, 1024),
        (pilot + 2048, 3000, 1024),
    ]
    assert round_bounds(plan, 100, 1200, 1) == [(100, 1124, 1024), (1124, 1200, 1024)]
    compiled = Plan(rollout, get_model("idm"), 1024, compiled=True)
    assert round_bounds(compiled, 0, 2048, 1) == [
        (0, pilot, pilot),
        (pilot, pilot + 1024, 1024),
        (pilot + 1024, 2048, 1024),
    ]
    off = Plan(Rollout(None, compile="off"), get_model("idm"), 1024, compiled=False)  # type: ignore[arg-type]
    assert round_bounds(off, 0, 2048, 1) == [(0, 1024, 1024), (1024, 2048, 1024)]
    assert round_bounds(plan, 0, 2000, 2) == [(0, 2 * pilot, pilot), (128, 2000, 1024)]


def test_auto_compile_stays_eager_with_early_rejection(pairs):
    """ "auto" would compile a long stream; with early rejection it stays eager
    on the CPU and on CUDA (faster there on a cold compile cache: see
    ``Rollout.compiled``); "on" compiles with it."""
    idm, long = get_model("idm"), 10**9
    for device in (torch.device("cpu"), torch.device("cuda")):
        fast = Rollout(pairs, compile="auto", early_rejection=True, device=device)
        assert not fast.compiled(idm, long)
        assert Rollout(pairs, compile="auto", device=device).compiled(idm, long) == (
            resolve_compile(idm, "auto", device, long * pairs.n_steps)
        )
    assert not Rollout(pairs, compile="off").compiled(idm, long)
    assert Rollout(pairs, compile="on", early_rejection=True).compiled(idm, long)


def _config(method: str, **abc) -> TrainConfig:
    settings = {"method": method, "n_particles": 3000, "top_n": 3, "sensitivity_n": [3],
                "seed": 2, "chunk_size": 700}  # fmt: skip
    if method == "smc":
        settings["smc"] = {"population": 8, "rounds": 2, "prior_fraction": 0.4}
    return TrainConfig.model_validate(
        {
            "data": {"path": "synthetic"},
            "models": ["idm", "mpc"],
            "abc": {**settings, **abc},
            "compile": "off",
        }
    )


@pytest.mark.parametrize("method", ["rejection", "smc"])
def test_a_trained_run_is_the_same_with_early_rejection(pairs, tmp_path, method):
    """Training (its plausibility filter at its default) with and without early
    rejection: the same shares and buffers; the summary counts the stopped."""
    test = pairs.subset([0, 1])
    runs = {}
    for on in (False, True):
        out = tmp_path / f"{method}{on}"
        summary = train(_config(method, early_rejection=on), out, pairs=(pairs, test))
        runs[on] = (summary, Posterior.load(out / "posterior.pt"))
    (plain, a), (fast, b) = runs[False], runs[True]
    assert fast.shares == plain.shares
    same_buffers(a, b)
    assert fast.per_model["idm"].stopped > 0
    assert plain.per_model["idm"].stopped == 0


def test_an_interrupted_run_with_early_rejection_resumes_identical(pairs, tmp_path):
    """Killed after a few chunks, checkpoints after every round: resumed, the
    run is the one never stopped (the pilot round only at the very start)."""
    cfg = _config("rejection", early_rejection=True, checkpoint_every=1e-9)
    test = pairs.subset([0, 1])
    reference = train(cfg, tmp_path / "ref", pairs=(pairs, test))
    out = tmp_path / "cut"
    interrupt_after(3, lambda: train(cfg, out, pairs=(pairs, test)))
    resumed = train(cfg, out, resume=True, pairs=(pairs, test))
    assert resumed.shares == reference.shares
    same_buffers(
        Posterior.load(tmp_path / "ref" / "posterior.pt"),
        Posterior.load(out / "posterior.pt"),
    )
