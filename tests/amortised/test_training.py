"""Training: it learns (the model head and a parameter, on held-out synthetic
pairs), it is deterministic, and a resumed run ends identical."""

from __future__ import annotations

import signal
from dataclasses import asdict

import pytest
import torch

from torchcf.amortised import (
    CheckpointError,
    Session,
    TrainingSettings,
    estimator_fingerprint,
    fingerprint_noise,
    infer,
    load_trained,
    new_estimator,
    train_estimator,
)
from torchcf.sim.synthetic import heterogeneous_pairs
from torchcf.system.signals import Stopped

from .conftest import MIXTURE, NOISE, TINY

#: A few thousand simulations: seconds of training.
LEARNING = TrainingSettings(
    simulations_per_epoch=2000,
    max_epochs=5,
    validation_simulations=400,
    batch_size=128,
    learning_rate=2e-3,
)
#: Five batches an epoch, three epochs.
SMALL = TrainingSettings(
    simulations_per_epoch=300,
    max_epochs=3,
    validation_simulations=100,
    batch_size=64,
    checkpoint_every=0.0,
)


@pytest.fixture(scope="module")
def trained(space, simulator):
    torch.set_num_threads(1)
    estimator = new_estimator(space, TINY, seed=0)
    result = train_estimator(
        estimator, simulator, LEARNING, Session(progress_bar=False)
    )
    return estimator, result


@pytest.fixture(scope="module")
def held_out():
    """40 synthetic pairs of 300 steps, half IDM and half OVM drivers drawn
    over their priors (plausible ones), with the training's noise: new leaders
    and drivers, the whole series (longer than the 200-step windows)."""
    return heterogeneous_pairs(MIXTURE, 40, 300, seed=7, noise=NOISE)


def test_the_training_spends_its_budget_and_reports(trained):
    _, result = trained
    progress = result.progress
    assert progress.finished == "epochs"
    assert len(progress.history) == 5
    assert progress.simulations == 5 * 2000 + 400
    losses = [record.validation_loss for record in progress.history]
    assert result.best_loss == min(losses)
    assert losses[-1] < losses[0]


def test_the_model_head_recovers_the_true_model_on_held_out_pairs(
    trained, held_out, space
):
    """Chance is 50 %; the head must name the true model of most pairs."""
    estimator, _ = trained
    pairs, drivers = held_out
    posterior = infer(estimator, pairs, 50, seed=0)
    truth = torch.tensor([space.names.index(m) for m in drivers.model])
    accuracy = float((posterior.probabilities.argmax(1) == truth).double().mean())
    assert accuracy >= 0.85, accuracy


def test_a_parameter_is_recovered_better_than_the_prior(trained, held_out, space):
    """IDM's time gap T (prior 0.8-2.5 s) sets the spacing the follower keeps:
    on held-out IDM pairs, the posterior median's error is well below the
    prior median's (a quarter of the box, 0.425 s)."""
    estimator, _ = trained
    pairs, drivers = held_out
    idm = [j for j, m in enumerate(drivers.model) if m == "idm"]
    posterior = infer(estimator, pairs.subset(idm), 200, seed=0)
    column = space.models[0].param_names.index("T")
    theta = posterior.theta[:, :, column].clone()
    theta[posterior.model != 0] = float("nan")
    median = theta.nanmedian(1).values
    error = (median.double() - drivers.theta[idm, column]).abs().mean()
    low, high = (float(b) for b in space.box(0)[column])
    prior_error = (high - low) / 4
    assert float(error) < 0.7 * prior_error, (float(error), prior_error)


def _weights_equal(a, b) -> bool:
    state_a, state_b = a.state_dict(), b.state_dict()
    return state_a.keys() == state_b.keys() and all(
        torch.equal(state_a[k], state_b[k]) for k in state_a
    )


def _history(result):
    return [
        (r.epoch, r.train_loss, r.validation_loss, r.validation_accuracy)
        for r in result.progress.history
    ]


class _KillAt:
    """A stop request whose ``requested`` raises KeyboardInterrupt at the n-th
    look (a kill between two batches, the last one not checkpointed), or asks
    to stop (``kill=False``)."""

    def __init__(self, n: int, kill: bool = True) -> None:
        self.n, self.kill, self.looks = n, kill, 0

    @property
    def requested(self) -> bool:
        self.looks += 1
        if self.looks >= self.n and self.kill:
            raise KeyboardInterrupt
        return self.looks >= self.n

    def stop(self, checkpointed: bool = True) -> None:
        raise Stopped(signal.SIGINT, checkpointed)


def test_the_training_is_deterministic_for_a_seed(space, simulator):
    runs = []
    for _ in range(2):
        estimator = new_estimator(space, TINY, seed=5)
        result = train_estimator(
            estimator, simulator, SMALL, Session(progress_bar=False)
        )
        runs.append((estimator, result))
    assert _weights_equal(runs[0][0], runs[1][0])
    assert _history(runs[0][1]) == _history(runs[1][1])


@pytest.mark.parametrize("kill", [True, False], ids=["killed", "stop-requested"])
def test_a_resumed_training_ends_identical_to_an_uninterrupted_one(
    space, simulator, tmp_path, kill
):
    whole = new_estimator(space, TINY, seed=0)
    expected = train_estimator(whole, simulator, SMALL, Session(progress_bar=False))
    checkpoint = tmp_path / "amortised.pt"
    interrupted = new_estimator(space, TINY, seed=0)
    # batch 8: the middle of the second epoch
    session = Session(checkpoint, stop=_KillAt(8, kill), progress_bar=False)
    with pytest.raises(KeyboardInterrupt) as stopped:
        train_estimator(interrupted, simulator, SMALL, session)
    if not kill:
        assert isinstance(stopped.value, Stopped) and stopped.value.checkpointed
    resumed = new_estimator(space, TINY, seed=99)  # the checkpoint's weights win
    result = train_estimator(
        resumed,
        simulator,
        SMALL,
        Session(checkpoint, resume=True, progress_bar=False),
    )
    assert _weights_equal(resumed, whole)
    assert _history(result) == _history(expected)
    assert result.progress.simulations == expected.progress.simulations


def test_a_checkpoint_of_another_training_is_refused(space, simulator, tmp_path):
    checkpoint = tmp_path / "amortised.pt"
    one_epoch = TrainingSettings(
        simulations_per_epoch=100, max_epochs=1, validation_simulations=50
    )
    estimator = new_estimator(space, TINY, seed=0)
    train_estimator(
        estimator, simulator, one_epoch, Session(checkpoint, progress_bar=False)
    )
    other = TrainingSettings(
        simulations_per_epoch=100, max_epochs=1, validation_simulations=50, seed=1
    )
    with pytest.raises(CheckpointError, match="another training's checkpoint"):
        train_estimator(
            estimator,
            simulator,
            other,
            Session(checkpoint, resume=True, progress_bar=False),
        )


def test_the_fingerprint_is_plain_data_and_an_older_format_is_refused(
    space, simulator, tmp_path
):
    """The checkpoint's fingerprint holds the settings as plain data: the noise
    read back by ``fingerprint_noise``, the estimator's sizes matched by a new
    estimator's fingerprint. A checkpoint of format /1 (settings as their
    ``repr``) is refused in one line, resumed or reused."""
    checkpoint = tmp_path / "amortised.pt"
    one_epoch = TrainingSettings(
        simulations_per_epoch=100, max_epochs=1, validation_simulations=50
    )
    estimator = new_estimator(space, TINY, seed=0)
    train_estimator(
        estimator, simulator, one_epoch, Session(checkpoint, progress_bar=False)
    )
    raw = torch.load(checkpoint, weights_only=True)
    assert fingerprint_noise(raw["fingerprint"]) == simulator.settings.noise
    assert raw["fingerprint"]["estimator"] == asdict(TINY)
    fresh = estimator_fingerprint(new_estimator(space, TINY, seed=3))
    assert load_trained(checkpoint, fresh)["fingerprint"] == raw["fingerprint"]
    raw["format"] = "torchcf.amortised.checkpoint/1"
    raw["fingerprint"]["noise"] = repr(simulator.settings.noise)
    raw["fingerprint"]["estimator"] = repr(TINY)
    old = tmp_path / "old.pt"
    torch.save(raw, old)
    resume = Session(old, resume=True, progress_bar=False)
    for read in (
        lambda: load_trained(old, fresh),
        lambda: train_estimator(estimator, simulator, one_epoch, resume),
    ):
        with pytest.raises(CheckpointError, match=r"checkpoint/1: .*train the") as e:
            read()
        assert "\n" not in str(e.value)
    with pytest.raises(CheckpointError, match="older torchcf"):
        fingerprint_noise(raw["fingerprint"])


def test_early_stopping_and_the_time_budget_end_a_training(space, simulator):
    """A learning rate of zero never improves: patience ends it after the
    first epoch plus ``patience``; a time budget of zero ends the first epoch
    after its first batch."""
    frozen = TrainingSettings(
        simulations_per_epoch=100,
        max_epochs=10,
        validation_simulations=50,
        learning_rate=1e-30,
        patience=2,
    )
    estimator = new_estimator(space, TINY, seed=0)
    result = train_estimator(estimator, simulator, frozen, Session(progress_bar=False))
    assert result.progress.finished == "patience"
    assert len(result.progress.history) == 3
    timed = TrainingSettings(
        simulations_per_epoch=300,
        max_epochs=10,
        validation_simulations=50,
        batch_size=64,
        max_seconds=0.0,
    )
    result = train_estimator(estimator, simulator, timed, Session(progress_bar=False))
    assert result.progress.finished == "seconds"
    assert len(result.progress.history) == 1


def test_a_finished_training_resumed_hands_back_its_weights(space, simulator, tmp_path):
    """Nothing is simulated again: the checkpoint's best weights are the result."""
    checkpoint = tmp_path / "amortised.pt"
    trained = new_estimator(space, TINY, seed=0)
    first = train_estimator(
        trained, simulator, SMALL, Session(checkpoint, progress_bar=False)
    )
    again = new_estimator(space, TINY, seed=7)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(simulator, "draw", lambda *a, **k: pytest.fail("simulated"))
        result = train_estimator(
            again,
            simulator,
            SMALL,
            Session(checkpoint, resume=True, progress_bar=False),
        )
    assert _weights_equal(again, trained)
    assert _history(result) == _history(first)
