"""Test-split evaluation and cross-validation of trained runs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from tests.conftest import synthetic_pairs
from tests.runs import evaluation, set_metrics
from torchcf.cli.evaluate import main as evaluate_command
from torchcf.config import TrainConfig
from torchcf.evaluation.evaluate import (
    EvaluationSettings,
    cost_matrices,
    evaluate_posterior,
    evaluate_run,
    hybrid_rows_in_single,
    single_model_particles,
)
from torchcf.evaluation.metrics import evaluate_costs, sinkhorn
from torchcf.models import get_model
from torchcf.posterior import Posterior
from torchcf.runs.directory import RunDir
from torchcf.runs.metrics import CrossvalResult, Evaluation
from torchcf.study.crossval import aggregate, crossval, fold_config
from torchcf.system.files import json_safe
from torchcf.train import train


def small_config(**abc) -> TrainConfig:
    settings = {
        "n_particles": 1500,
        "chunk_size": 500,
        "top_n": 3,
        "sensitivity_n": [3],
    }
    settings.update(abc)
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm", "llctg"],
            "abc": settings,
            "compile": "off",
        }
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A small finished run on synthetic train / test pairs, not yet evaluated."""
    train_pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    test_pairs = synthetic_pairs(n_pairs=4, n_steps=200, seed=2)
    out = tmp_path_factory.mktemp("run")
    cfg = small_config()
    train(cfg, out, pairs=(train_pairs, test_pairs))  # training only
    return cfg, out, train_pairs, test_pairs


def test_single_model_set_is_its_first_n_finite_buffer_entries(trained):
    _, out, train_pairs, _ = trained
    posterior = Posterior.load(out / "posterior.pt")
    theta = single_model_particles(posterior, "idm")
    buffer = posterior.buffers["idm"]
    finite = torch.isfinite(buffer["score"][:, :3])
    assert theta.shape == (int(finite.sum()), 6)
    assert torch.equal(theta, buffer["theta"][:, :3][finite])


def test_hybrid_rows_are_found_among_the_single_model_particles(trained):
    """Per-pair selection: every hybrid particle is one of its model's N best on
    its pair, and the row found holds that particle."""
    _, out, _, _ = trained
    posterior = Posterior.load(out / "posterior.pt")
    for name in posterior.models:
        rows = hybrid_rows_in_single(posterior, name)
        assert (rows >= 0).all(), name
        single = single_model_particles(posterior, name)
        assert torch.equal(single[torch.from_numpy(rows)], posterior.hybrid[name].theta)


def test_hybrid_costs_equal_their_own_rollout(trained):
    """The hybrid's rows taken from the single models equal simulating the hybrid
    particles themselves (float64: the same numbers)."""
    cfg, out, _, test_pairs = trained
    cfg = cfg.model_copy(update={"dtype": "float64"})
    posterior = Posterior.load(out / "posterior.pt")
    _, costs = evaluate_posterior(
        posterior, test_pairs, EvaluationSettings.of(cfg), progress=False
    )
    direct = [
        cost_matrices(
            get_model(name),
            posterior.hybrid[name].theta,
            test_pairs,
            dtype=torch.float64,
        )
        for name in posterior.models
        if len(posterior.hybrid[name])
    ]
    for key in ("score", "e_p", "e_v", "e_a"):
        expected = np.concatenate([d[key] for d in direct])
        np.testing.assert_allclose(costs["hybrid"][key], expected, rtol=1e-12)


def test_a_global_selection_particle_outside_the_first_n_is_simulated(trained):
    """A hybrid particle not among its model's first N slots (global selection
    can keep one) gets its own rollout, in its place among the hybrid rows."""
    cfg, out, _, test_pairs = trained
    cfg = cfg.model_copy(update={"dtype": "float64"})
    posterior = Posterior.load(out / "posterior.pt")
    name = next(n for n in posterior.models if len(posterior.hybrid[n]) >= 2)
    hybrid = posterior.hybrid[name]
    moved = hybrid.particle_index.clone()
    moved[1] = -7  # no such stream index: not found among the singles
    posterior.hybrid[name] = type(hybrid)(
        hybrid.param_names, hybrid.theta, hybrid.score, hybrid.pair_ids, moved
    )
    assert hybrid_rows_in_single(posterior, name)[1] == -1
    _, costs = evaluate_posterior(
        posterior, test_pairs, EvaluationSettings.of(cfg), progress=False
    )
    first = sum(
        len(posterior.hybrid[m])
        for m in posterior.models[: posterior.models.index(name)]
    )
    own = cost_matrices(
        get_model(name), hybrid.theta[1:2], test_pairs, dtype=torch.float64
    )
    np.testing.assert_allclose(costs["hybrid"]["score"][first + 1], own["score"][0])


def test_evaluation_reuses_the_training_figures(trained, tmp_path):
    """Training wrote shares.png and pairwise.png; evaluating into the run's
    report leaves them, evaluating into another folder draws them there."""
    _, out, _, test_pairs = trained
    shares = out / "report" / "shares.png"
    assert shares.is_file() and (out / "report" / "pairwise.png").is_file()
    before = shares.stat().st_mtime_ns
    evaluate_run(out, pairs=(test_pairs, test_pairs), progress=False)
    assert shares.stat().st_mtime_ns == before
    elsewhere = tmp_path / "elsewhere"
    evaluate_run(
        out, report_dir=elsewhere, pairs=(test_pairs, test_pairs), progress=False
    )
    names = {p.name for p in elsewhere.glob("*.png")}
    assert names == {
        "shares.png", "pairwise.png", "error_evolution.png", "radar.png",
        "calibration.png",
    }  # fmt: skip


def test_metrics_equal_a_direct_computation(trained):
    cfg, out, train_pairs, test_pairs = trained
    result = evaluate_run(out, pairs=(train_pairs, test_pairs), tensorboard=False)
    posterior = Posterior.load(out / "posterior.pt")
    # hybrid: every model's hybrid particles, stacked in model order
    parts = [
        cost_matrices(get_model(name), posterior.hybrid[name].theta, test_pairs)
        for name in posterior.models
        if len(posterior.hybrid[name])
    ]
    stacked = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    expect = evaluate_costs(
        stacked["score"], stacked["e_p"], stacked["e_v"], stacked["e_a"], beta=0.15
    )
    hybrid = result.sets["hybrid"].metrics
    for key in ("e_p", "min", "beta_ws", "ws", "sinkhorn"):
        assert getattr(hybrid, key) == pytest.approx(getattr(expect, key), rel=1e-12)
    # the batched Sinkhorn of all sets = one solve per set
    assert hybrid.sinkhorn_iterations == expect.sinkhorn_iterations
    on_disk = json.loads((out / "metrics.json").read_text())
    assert set(on_disk) >= {"hybrid", "idm", "llctg", "n_test", "test_pair_ids"}
    assert on_disk["n_test"] == 4
    assert 0 < on_disk["seconds"] < 600  # the evaluation's own wall time
    for name in ("table.md", "shares.png", "pairwise.png", "radar.png"):
        assert (out / "report" / name).exists()
    table = (out / "report" / "table.md").read_text()
    assert "WS" in table and "IDM" in table
    assert "What the columns are" in table  # every metric defined where shown


def test_metrics_json_is_the_evaluation_and_reads_back(trained):
    """evaluate_run returns the typed record of metrics.json: its to_json is the
    file (key order included), and from_json reads the file back to it."""
    _, out, train_pairs, test_pairs = trained
    result = evaluate_run(
        out, pairs=(train_pairs, test_pairs), tensorboard=False, progress=False
    )
    assert isinstance(result, Evaluation)
    text = (out / "metrics.json").read_text()
    assert json.dumps(json_safe(result.to_json()), indent=2) + "\n" == text
    back = Evaluation.from_json(json.loads(text))
    assert json.dumps(json_safe(back.to_json()), indent=2) + "\n" == text
    assert RunDir(out).read_metrics().to_json() == back.to_json()  # the run's
    assert list(back.sets) == ["idm", "llctg", "hybrid"]
    assert back.hybrid.metrics == result.hybrid.metrics
    assert back.shares == result.shares and back.bootstrap == result.bootstrap
    with pytest.raises(ValueError, match="not an evaluation"):
        Evaluation.from_json(
            {k: v for k, v in json.loads(text).items() if k != "n_test"}
        )


def test_metrics_json_records_the_sinkhorn_solve(trained, capsys):
    cfg, out, train_pairs, test_pairs = trained
    evaluate_run(
        out, pairs=(train_pairs, test_pairs), tensorboard=False, progress=False
    )
    assert capsys.readouterr().err == ""  # progress off: no bars
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["sinkhorn_max_iter"] == cfg.eval.sinkhorn_max_iter
    for entry in ("idm", "llctg", "hybrid"):
        metrics = on_disk[entry]
        assert metrics["sinkhorn_converged"] is True
        assert 0 < metrics["sinkhorn_iterations"] <= cfg.eval.sinkhorn_max_iter
        assert 0 <= metrics["sinkhorn_marginal_error"] < 1e-9
        assert metrics["sinkhorn_gap"] == pytest.approx(
            metrics["sinkhorn"] - metrics["ws"], abs=1e-12
        )


def test_sinkhorn_iteration_cap_comes_from_the_config(trained, capsys):
    cfg, out, _, test_pairs = trained
    capped = cfg.model_copy(
        update={"eval": cfg.eval.model_copy(update={"sinkhorn_max_iter": 3})}
    )
    posterior = Posterior.load(out / "posterior.pt")
    metrics, costs = evaluate_posterior(
        posterior, test_pairs, EvaluationSettings.of(capped), progress=True
    )
    err = capsys.readouterr().err
    assert "evaluate: simulate" in err and "evaluate: metrics" in err
    for entry, m in metrics.items():
        assert m.sinkhorn_iterations == 3 and not m.sinkhorn_converged, entry
        cost = costs[entry]
        valid = np.isfinite(np.stack([cost[k] for k in ("e_p", "e_v", "e_a")]))
        score = np.where(valid.all(axis=0), cost["score"], np.inf)
        alone = sinkhorn(score, cfg.eval.sinkhorn_reg, max_iter=3)
        assert m.sinkhorn == pytest.approx(alone.value, rel=1e-12)
        assert m.sinkhorn_marginal_error == pytest.approx(alone.marginal_error)


def test_evaluate_cli_refuses_an_unfinished_run(tmp_path, capsys):
    assert evaluate_command([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "no finished run" in err and "\n" not in err


def test_aggregate_is_the_mean_over_folds_and_keeps_inf():
    folds = [
        evaluation({"hybrid": set_metrics(ws=1.0, min=0.5)}),
        evaluation({"hybrid": set_metrics(ws=3.0, min=math.inf)}),
    ]
    result = aggregate(folds)
    assert result.folds == 2
    hybrid = result.entries["hybrid"]
    assert hybrid.ws == 2.0 and hybrid.ws_folds_finite == 2
    assert math.isinf(hybrid.min)
    assert hybrid.min_folds_finite == 1
    # its JSON is OUT/metrics.json's, read back as written ("inf", "nan")
    on_disk = json.loads(json.dumps(json_safe(result.to_json())))
    assert list(on_disk) == ["folds", "hybrid"]
    assert json_safe(CrossvalResult.from_json(on_disk).to_json()) == on_disk


def test_aggregate_averages_the_learned_sets_alone():
    """The sets of the first fold, in its order; a set missing from a fold
    makes its means non-finite, counted as no finite fold."""
    both = evaluation({"idm": set_metrics(ws=2.0), "hybrid": set_metrics()})
    alone = evaluation({"hybrid": set_metrics(ws=0.5)})
    result = aggregate([both, alone])
    assert list(result.to_json()) == ["folds", "idm", "hybrid"]
    assert math.isnan(result.entries["idm"].ws)
    assert result.entries["idm"].ws_folds_finite == 1
    assert result.entries["hybrid"].ws == 1.0


def test_fold_config():
    cfg = fold_config(small_config(), 3, 2)
    assert (cfg.data.split, cfg.data.folds, cfg.data.fold) == ("kfold", 3, 2)


@pytest.mark.slow  # a cross-validation on real data
def test_crossval_runs_every_fold_on_real_data(data_root, tmp_path):
    cfg = small_config(n_particles=600, chunk_size=600)
    result = crossval(cfg, tmp_path / "cv", folds=2)
    assert result.folds == 2
    for fold in range(2):
        metrics = json.loads(
            (tmp_path / "cv" / f"fold{fold}" / "metrics.json").read_text()
        )
        assert "hybrid" in metrics
    on_disk = json.loads((tmp_path / "cv" / "metrics.json").read_text())
    assert on_disk["hybrid"]["ws"] == pytest.approx(result.entries["hybrid"].ws)
    assert (tmp_path / "cv" / "report" / "table.md").exists()
