"""An amortised run's refinement (``abc.amortised.refine``): a short SMC per
training pair and model from the pair's best amortised samples, what it
changed in ``summary.json``, and a resume after a kill mid-refinement that ends
identical."""

from __future__ import annotations

import json

import pytest
import torch

import torchcf.abc.rejection as rejection_module
from tests.abc.interrupt import interrupt_after, same_buffers
from tests.train.test_amortised_run import AMORTISED
from tests.train.test_amortised_run import config as amortised_config
from tests.train.test_train import mixture_pairs
from torchcf.abc.smc import SMCSettings, new_state, seed_population
from torchcf.abc.topn import TopN
from torchcf.posterior import Posterior
from torchcf.runs.summary import RunSummary
from torchcf.train import train

pytestmark = pytest.mark.usefixtures("one_thread")

REFINE = {"rounds": 2, "per_pair": 10, "population": 5}


def config(**abc):
    """The amortised run's config, refined."""
    return amortised_config(amortised={**AMORTISED, "refine": REFINE}, **abc)


@pytest.fixture(scope="module")
def mixture():
    return mixture_pairs()


@pytest.fixture(scope="module")
def refined(mixture, tmp_path_factory):
    out = tmp_path_factory.mktemp("refined") / "run"
    calls = [0]
    real = rejection_module.simulate

    def counted(*args, **kwargs):
        calls[0] += 1
        return real(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(rejection_module, "simulate", counted)
        summary = train(config(chunk_size=64), out, pairs=(mixture, mixture))
    return out, summary, calls[0]


def test_the_refinement_spends_its_budget_and_says_what_it_changed(refined):
    out, summary, _ = refined
    record = summary.amortised.refinement
    per_pair = 2 * REFINE["rounds"] * REFINE["per_pair"]  # two models
    assert record.simulations_per_pair == per_pair
    assert record.simulations == 10 * per_pair
    # every sample, then the refinement's proposals, offered per model
    offered = sum(result.particles for result in summary.per_model.values())
    assert offered == 10 * AMORTISED["samples_per_pair"] + record.simulations
    for name, model in record.per_model.items():
        assert model.share_after == pytest.approx(summary.shares[name], abs=1e-6)
        # the buffers keep the best of everything offered: never worse
        assert model.median_best_after <= model.median_best_before
    assert sum(m.share_before for m in record.per_model.values()) == pytest.approx(1)
    raw = json.loads((out / "summary.json").read_text())
    assert list(raw["amortised"])[-1] == "refinement"
    assert RunSummary.from_json(raw).amortised == summary.amortised
    # the hybrid holds parameters alone (the weights' column dropped)
    posterior = Posterior.load(out / "posterior.pt")
    assert posterior.hybrid["idm"].theta.shape[1] == len(
        posterior.hybrid["idm"].param_names
    )


def test_without_refinement_the_record_has_no_refinement_key(tmp_path):
    from torchcf.runs.summary import AmortisedResult

    record = AmortisedResult(40, (0.1, 0.1, 0.1), 3, "epochs", 10, 0, 1.0, 0.5, 0.9)
    assert "refinement" not in record.to_json()
    assert AmortisedResult.from_json(record.to_json()) == record


def test_a_run_killed_mid_refinement_resumes_identical(refined, mixture, tmp_path):
    finished_out, expected, calls = refined
    cfg = config(checkpoint_every=1e-6, chunk_size=64)
    out = tmp_path / "run"

    def run():
        train(cfg, out, pairs=(mixture, mixture))

    interrupt_after(calls - 3, run)  # within the last model's refinement
    checkpoint = torch.load(out / "checkpoint.pt", weights_only=False)
    assert "refinement_before" in checkpoint
    summary = train(cfg, out, resume=True, pairs=(mixture, mixture))
    same_buffers(Posterior.load(out / "posterior.pt"),
                 Posterior.load(finished_out / "posterior.pt"))  # fmt: skip
    assert summary.shares == expected.shares
    assert summary.amortised.refinement == expected.amortised.refinement


def test_the_first_population_is_each_pairs_best_entries():
    buffer = TopN(2, 6, 2)
    score = torch.tensor([3.0, 1.0, 2.0, 5.0, 4.0, 0.5], dtype=torch.float64)
    pair = torch.tensor([0, 0, 0, 1, 1, 1])
    theta = torch.stack((score, torch.zeros(6, dtype=torch.float64)), 1)
    buffer.push(pair, score, torch.arange(6), theta)
    settings = SMCSettings(population=2, rounds=1)
    state = new_state(2, settings, 1)
    seed_population(state, buffer, settings)
    assert state.round == 1
    assert state.population["score"].tolist() == [[1.0, 2.0], [0.5, 4.0]]
    assert state.population["index"].tolist() == [[1, 2], [5, 4]]


def test_the_trained_estimator_is_read_back_from_the_run(refined, mixture):
    """The run's kept weights, read back, give the run's own samples."""
    from torchcf.amortised import infer
    from torchcf.calibration.estimator_samples import trained_estimator
    from torchcf.calibration.of_config import method_of
    from torchcf.runs.directory import RunDir

    out, summary, _ = refined
    cfg = config()
    priors = {spec.model: spec.bounds() for spec in cfg.models}
    checkpoint = RunDir(out).amortised_checkpoint
    estimator = trained_estimator(method_of(cfg), priors, checkpoint)
    samples = infer(estimator, mixture, AMORTISED["samples_per_pair"], seed=1)
    counts = torch.bincount(samples.model.reshape(-1), minlength=2)
    refine = summary.amortised.refinement.simulations // 2  # per model
    for m, name in enumerate(("idm", "hl")):
        assert summary.per_model[name].particles == int(counts[m]) + refine


def test_the_networks_size_is_the_configs():
    from torchcf.amortised import EstimatorSettings
    from torchcf.calibration.of_config import estimator_settings
    from torchcf.config import AmortisedNetworkConfig

    assert estimator_settings(AmortisedNetworkConfig()) == EstimatorSettings()
    small = estimator_settings(
        AmortisedNetworkConfig(encoder_depth=2, embedding=16, transforms=1)
    )
    assert small.encoder.strided == 2 and small.encoder.embedding == 16
    assert small.transforms == 1
