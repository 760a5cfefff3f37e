"""A training run with ``abc.method = "amortised"``: the estimator trained on
the run's models, its samples scored into the same buffers as rejection's
particles, the same outputs, and a resume that ends identical."""

from __future__ import annotations

import json

import pytest
import torch

import torchcf.amortised.simulations as simulations_module
from tests.abc.interrupt import interrupt_after, same_buffers
from tests.train.test_train import config as train_config
from tests.train.test_train import mixture_pairs
from torchcf.abc.rejection import Rollout
from torchcf.calibration.estimator_samples import amortised_samples
from torchcf.calibration.of_config import method_of
from torchcf.config import ConfigError, validate_config
from torchcf.posterior import Posterior
from torchcf.runs.summary import RunSummary
from torchcf.train import train

pytestmark = pytest.mark.usefixtures("one_thread")

#: Seconds of training: three epochs of 1000 simulations.
AMORTISED = {
    "samples_per_pair": 40,
    "window_steps": 200,
    "simulations_per_epoch": 1000,
    "max_epochs": 3,
    "validation_simulations": 300,
    "batch_size": 128,
}


def config(**abc):
    """The trainer tests' config (IDM and HL, seed 1), the amortised method."""
    return train_config(**{"method": "amortised", "amortised": AMORTISED, **abc})


@pytest.fixture(scope="module")
def mixture():
    return mixture_pairs()


@pytest.fixture(scope="module")
def finished(mixture, tmp_path_factory):
    out = tmp_path_factory.mktemp("amortised") / "run"
    summary = train(config(), out, pairs=(mixture, mixture))
    return out, summary


def test_the_run_writes_the_outputs_of_rejection(finished):
    out, summary = finished
    for name in ("posterior.pt", "summary.json", "amortised.pt", "checkpoint.pt"):
        assert (out / name).exists(), name
    assert (out / "report" / "parameters.csv").exists()
    assert summary.method == "amortised"
    assert sum(summary.shares.values()) == pytest.approx(1.0)
    # every training pair's samples, split between the models, were offered
    offered = sum(result.particles for result in summary.per_model.values())
    assert offered == 10 * AMORTISED["samples_per_pair"]
    posterior = Posterior.load(out / "posterior.pt")
    assert set(posterior.hybrid) == {"idm", "hl"}
    assert summary.hybrid_size == 10 * 5
    # the estimator's record, read back from summary.json as it was written
    record = summary.amortised
    assert record.epochs == 3 and record.finished == "epochs"
    assert record.simulations == 3 * 1000 + 300
    assert 0.0 <= record.validation_accuracy <= 1.0
    raw = json.loads((out / "summary.json").read_text())
    assert list(raw)[-5:-3] == ["method", "amortised"]  # then plausibility, dt, length
    assert (raw["dt"], raw["leader_length"]) == (0.1, 5.0)  # the training pairs'
    assert RunSummary.from_json(raw).amortised == record


def test_the_buffers_keep_each_pairs_best_samples(finished, mixture, tmp_path):
    """The buffers equal an independent scoring of every sample (one rollout
    each) and a sort per pair: the amortised samples enter as rejection's
    particles do."""
    out, _ = finished
    cfg = config()
    priors = {spec.model: spec.bounds() for spec in cfg.models}
    checkpoint = tmp_path / "amortised.pt"
    method = method_of(cfg)
    samples = amortised_samples(
        method, priors, mixture, cfg.abc.seed, checkpoint
    ).samples
    rollout = Rollout(mixture, compile="off")
    posterior = Posterior.load(out / "posterior.pt")
    for m, spec in enumerate(cfg.models):
        pair, theta = samples.of_model(m)
        score, _ = rollout.score(spec.model, theta.double(), pair)
        buffer = posterior.buffers[spec.name]
        for j in range(mixture.n_pairs):
            mine = score[pair == j]
            best = torch.sort(mine).values[: buffer["score"].shape[1]]
            kept = buffer["score"][j, : best.numel()]
            finite = torch.isfinite(best)
            torch.testing.assert_close(kept[finite], best[finite])


@pytest.mark.parametrize("where", ["training", "streams"])
def test_a_resumed_run_ends_identical(finished, mixture, tmp_path, where):
    """Killed while the estimator trains (a checkpoint after every batch) or
    while a model's samples are scored: ``--resume`` gives the same buffers."""
    _, expected = finished
    cfg = config(checkpoint_every=1e-6, chunk_size=64)
    out = tmp_path / "run"

    def run():
        train(cfg, out, pairs=(mixture, mixture))

    if where == "streams":
        interrupt_after(2, run)
    else:
        calls = [0]
        real = simulations_module.simulate

        def killed(*args, **kwargs):
            calls[0] += 1
            if calls[0] > 6:  # drawing the third epoch's set
                raise KeyboardInterrupt
            return real(*args, **kwargs)

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(simulations_module, "simulate", killed)
            with pytest.raises(KeyboardInterrupt):
                run()
        assert (out / "amortised.pt").exists()
    summary = train(cfg, out, resume=True, pairs=(mixture, mixture))
    finished_out, _ = finished
    same_buffers(Posterior.load(out / "posterior.pt"),
                 Posterior.load(finished_out / "posterior.pt"))  # fmt: skip
    assert summary.shares == expected.shares


def test_the_config_guards_the_method(mixture, tmp_path):
    raw = config().model_dump(mode="json")
    raw["abc"]["layout"] = "full"
    with pytest.raises(ConfigError, match="method='amortised' proposes per pair"):
        validate_config(raw)
    short = config(amortised={**AMORTISED, "samples_per_pair": 3})
    with pytest.raises(ConfigError, match="abc.amortised.samples_per_pair = 3"):
        train(short, tmp_path / "short", pairs=(mixture, mixture))
    long = config(amortised={**AMORTISED, "window_steps": 301})
    with pytest.raises(ConfigError, match="abc.amortised.window_steps: 301"):
        train(long, tmp_path / "long", pairs=(mixture, mixture))


def test_a_run_reusing_a_trained_estimator_draws_the_same_samples(
    finished, mixture, tmp_path
):
    """``abc.amortised.estimator``: no training (its settings unused), the
    earlier run's weights copied in, the same samples and buffers, the
    earlier training's record marked reused."""
    finished_out, expected = finished
    reuse = {**AMORTISED, "estimator": str(finished_out), "simulations_per_epoch": 7}
    out = tmp_path / "run"

    def no_simulation(*args, **kwargs):
        raise AssertionError("a reusing run trains nothing")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(simulations_module, "simulate", no_simulation)
        summary = train(config(amortised=reuse), out, pairs=(mixture, mixture))
    same_buffers(Posterior.load(out / "posterior.pt"),
                 Posterior.load(finished_out / "posterior.pt"))  # fmt: skip
    assert summary.shares == expected.shares
    record = summary.amortised.to_json()
    assert record.pop("reused") == str(finished_out)
    assert record == expected.amortised.to_json()  # the earlier training's
    copied = torch.load(out / "amortised.pt", weights_only=True)
    original = torch.load(finished_out / "amortised.pt", weights_only=True)
    assert copied["fingerprint"] == original["fingerprint"]
    assert all(torch.equal(copied["best"][k], v) for k, v in original["best"].items())


def test_a_reused_estimator_must_be_the_configs_and_finished(
    finished, mixture, tmp_path
):
    """A bad ``abc.amortised.estimator`` is a one-line config error, found
    before the run writes anything."""
    finished_out, _ = finished

    def refused(estimator, match, **settings):
        amortised = {**AMORTISED, "estimator": str(estimator), **settings}
        out = tmp_path / "refused"
        with pytest.raises(ConfigError, match=match):
            train(config(amortised=amortised), out, pairs=(mixture, mixture))
        assert not (out / "config.json").exists()

    refused(tmp_path / "nowhere", "abc.amortised.estimator: .*no such file")
    refused(
        finished_out,
        r"abc.amortised.estimator: .*another estimator \(estimator: ",
        network={"embedding": 8},
    )
    raw = torch.load(finished_out / "amortised.pt", weights_only=True)
    raw["progress"]["finished"] = ""
    torch.save(raw, tmp_path / "unfinished.pt")
    refused(tmp_path / "unfinished.pt", "has not finished; resume its run first")
    raw["fingerprint"]["models"] = ["idm", "gfm"]
    raw["progress"]["finished"] = "epochs"
    torch.save(raw, tmp_path / "other.pt")
    refused(tmp_path / "other.pt", r"another estimator \(models: \['idm', 'gfm'\]")


def test_a_prediction_after_a_history_draws_from_the_estimator(finished, mixture):
    """``torchcf.predict`` on an amortised run: a history's candidates hold
    the estimator's draws of ``q(m, theta | history)`` beside the hybrid's."""
    from torchcf.predict import PredictSettings, TrainedRun, predict
    from torchcf.predict.history import AMORTISED_SAMPLES, _candidates
    from torchcf.predict.rollouts import steps_between

    out, _ = finished
    run = TrainedRun.load(out, train=mixture)
    assert run.estimator is not None
    pairs = mixture.subset([1, 7])
    past = steps_between(pairs, 0, 51)
    _, theta, source = _candidates(run, run.hybrid_models, past, seed=0)
    assert int((source == -1).sum(1)[0]) == AMORTISED_SAMPLES
    drawn = theta[source == -1]
    assert torch.isfinite(drawn[:, :6]).any(1).all()  # every draw a model's vector
    settings = PredictSettings(draws=8, history=5.0, keep=20, conditioning="rejection")
    found = predict(run, pairs, settings)
    assert found.summary.history.source == "hybrid + amortised"
    assert found.summary.history.pairs == 2
