"""torchcf.abc.screen: the plausibility filter keeps the buffers exactly as if
every particle had been tested, whatever the chunking, in both layouts and in
SMC; and training reports what it rejected."""

from __future__ import annotations

import pytest
import torch

from torchcf.abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from torchcf.abc.rounds import RoundHooks
from torchcf.abc.screen import PlausibilityScreen
from torchcf.abc.topn import TopN
from torchcf.config import validate_config
from torchcf.models import get_model
from torchcf.posterior import Posterior
from torchcf.sim.synthetic import synthetic_pairs
from torchcf.traffic import Battery, check_plausibility
from torchcf.traffic.battery import rejects
from torchcf.train import train

#: LLCTG's prior holds both sluggish particles (that collide with a leader
#: braking to a stop) and tuned ones; the data come from a sluggish one, so
#: that many of the best fits are implausible.
MODEL = "llctg"
TRUTH = [1.0, 0.3, 0.3, 5.0]
BATTERY = Battery(speed=20.0, decelerations=(6.0,))


def _pairs():
    return synthetic_pairs(get_model(MODEL), TRUTH, 4, 200, seed=3)


def _buffers(paired: bool, chunk: int, screen, n: int = 1500):
    pairs = _pairs()
    model = get_model(MODEL)
    bounds = model.prior_bounds(torch.float64)
    rollout = Rollout(
        pairs, paired=paired, dtype=torch.float64, compile="off", chunk_size=chunk
    )
    buffer = TopN(pairs.n_pairs, 5, model.n_params)
    progress = ModelProgress()
    run_rejection(
        prior_stream(get_model(MODEL), bounds, 0, rollout),
        buffer,
        rollout,
        n,
        progress,
        hooks=RoundHooks(screen=screen),
    )
    return buffer, progress, rollout, bounds


def _reference(paired: bool, n: int = 1500) -> TopN:
    """Every particle scored and tested, the implausible ones scored +inf."""
    pairs = _pairs()
    model = get_model(MODEL)
    bounds = model.prior_bounds(torch.float64)
    rollout = Rollout(pairs, paired=paired, dtype=torch.float64, compile="off")
    theta, pair = prior_stream(get_model(MODEL), bounds, 0, rollout).draw(0, n)
    score, _ = rollout.score(model, theta, pair if paired else None)
    bad = check_plausibility(get_model(MODEL), theta, BATTERY).collided
    assert 0 < int(bad.sum()) < n  # the test needs both kinds
    score = score.clone()
    score[bad] = torch.inf
    buffer = TopN(pairs.n_pairs, 5, model.n_params)
    index = torch.arange(n)
    if paired:
        buffer.push(pair, score, index, theta)
    else:
        buffer.push_full(score, index, theta)
    return buffer


@pytest.mark.slow  # two trainings with the battery on every particle
@pytest.mark.parametrize("paired", [True, False])
def test_the_screen_gives_the_buffers_of_testing_every_particle(paired):
    screen = PlausibilityScreen(rejects(BATTERY))
    reference = _reference(paired)
    for chunk in (128, 700):
        buffer, progress, *_ = _buffers(paired, chunk, screen)
        assert torch.equal(buffer.index, reference.index), chunk
        assert torch.equal(buffer.score, reference.score)
        assert progress.implausible > 0
    # and none of what it kept collides
    kept = buffer.theta.reshape(-1, buffer.theta.shape[-1])[
        buffer.index.reshape(-1) >= 0
    ]
    assert not bool(check_plausibility(get_model(MODEL), kept, BATTERY).collided.any())


def test_without_the_screen_implausible_particles_enter():
    buffer, progress, *_ = _buffers(True, 700, None)
    kept = buffer.theta.reshape(-1, buffer.theta.shape[-1])
    assert bool(check_plausibility(get_model(MODEL), kept, BATTERY).collided.any())
    assert progress.implausible == 0


def test_string_unstable_particles_are_rejected_when_asked():
    screen = PlausibilityScreen(rejects(BATTERY, reject_string_unstable=True))
    buffer, *_ = _buffers(True, 700, screen)
    kept = buffer.theta.reshape(-1, buffer.theta.shape[-1])
    result = check_plausibility(get_model(MODEL), kept, BATTERY)
    assert not bool((result.collided | result.string_unstable()).any())


@pytest.mark.slow  # a training with the screen
def test_training_with_the_filter_reports_it(tmp_path):
    pairs = _pairs()
    test = synthetic_pairs(get_model(MODEL), TRUTH, 2, 200, seed=4)
    base = {
        "data": {"path": "synthetic"},
        "models": [MODEL, "idm"],
        "abc": {"n_particles": 1500, "sensitivity_n": [5], "seed": 0},
        "compile": "off",
    }
    on = {**base, "plausibility": {"filter": True, "speed": 20.0, "decelerations": [6]}}
    summary = train(validate_config(on), tmp_path / "on", pairs=(pairs, test))
    plain = train(validate_config(base), tmp_path / "off", pairs=(pairs, test))
    assert summary.per_model[MODEL].implausible > 0
    assert plain.per_model[MODEL].implausible == 0
    # the battery on the learned hybrid, per model: none collides when filtered
    assert summary.plausibility[MODEL].collided == 0.0
    assert plain.plausibility[MODEL].n_particles > 0
    quiet = {**base, "plausibility": {"report": False}}
    assert (
        "plausibility"
        not in train(
            validate_config(quiet), tmp_path / "quiet", pairs=(pairs, test)
        ).to_json()
    )
    assert summary.config_hash != plain.config_hash
    with pytest.raises(ValueError):
        validate_config({**base, "plausibility": {"decelerations": [-1]}})


@pytest.mark.slow  # about 20 s: SMC rounds with the whole battery
def test_smc_with_the_filter_keeps_implausible_particles_out(tmp_path):
    pairs = _pairs()
    test = synthetic_pairs(get_model(MODEL), TRUTH, 2, 200, seed=4)
    config = {
        "data": {"path": "synthetic"},
        "models": [MODEL],
        "abc": {"n_particles": 20_000, "sensitivity_n": [5], "method": "smc"},
        "compile": "off",
        "plausibility": {"filter": True, "speed": 20.0, "decelerations": [6]},
    }
    summary = train(validate_config(config), tmp_path / "run", pairs=(pairs, test))
    assert summary.per_model[MODEL].implausible > 0
    kept = Posterior.load(tmp_path / "run" / "posterior.pt").hybrid[MODEL].theta
    assert not bool(check_plausibility(get_model(MODEL), kept, BATTERY).collided.any())
