"""tools/bench_amortised.py and tools/amortised_quality.py at tiny sizes: each
writes its report (.json and .md) with every part it measures."""

from __future__ import annotations

import json

import pytest
import torch

from tests.runs import tool_module


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def bench():
    yield from tool_module("bench_amortised")


@pytest.fixture(scope="module")
def quality():
    yield from tool_module("amortised_quality")


@pytest.mark.slow
def test_the_bench_reports_training_sizes_and_quality(bench, tmp_path):
    out = tmp_path / "amortised"
    argv = [
        "--models", "idm", "hl", "--sizes", "30", "--steps", "200",
        "--train-pairs", "10", "--window", "150", "--simulations", "200",
        "--validation", "100", "--epochs", "1", "--samples", "10",
        "--refine-rounds", "1", "--refine-per-pair", "5", "--refine-population", "3",
        "--common", "6", "--smc-per-pair", "200", "--smc-population", "10",
        "--smc-rounds", "2", "--threads", "1", "--compile", "off", "--out", str(out),
    ]  # fmt: skip
    assert bench.main(argv) == 0
    payload = json.loads(out.with_suffix(".json").read_text())
    results = payload["results"]
    assert results["training"]["epochs"] == 1
    (row,) = results["sizes"]
    assert {"infer_s_per_1000", "score_s_per_1000", "refine_s_per_1000"} <= set(row)
    common = results["common"]
    assert set(common["against_smc"]) == {"amortised", "refined"}
    # the refinement only adds particles: its pairs' best never get worse
    assert common["refined"]["mean_best"] <= common["amortised"]["mean_best"]
    assert "Quality against per-pair SMC" in out.with_suffix(".md").read_text()


def test_the_bench_pairs_cycle_through_the_pool_and_gipps(bench):
    makers = bench.generators(["idm", "hl"])
    pairs, label = bench.make_pairs(makers, 7, 100, seed=0)
    assert pairs.n_pairs == 7
    assert label.tolist() == [0, 1, 2, 0, 1, 2, 0]
    assert makers[-1].name == "gipps"


@pytest.mark.slow
def test_the_quality_study_reports_calibration_and_recovery(quality, tmp_path):
    out = tmp_path / "quality"
    argv = [
        "--parts", "synthetic", "--pairs", "2", "--steps", "200", "--draws", "20",
        "--samples", "10", "--simulations", "300", "--validation", "100",
        "--epochs", "1", "--refine-rounds", "1", "--refine-per-pair", "5",
        "--threads", "1", "--work", str(tmp_path / "work"), "--out", str(out),
    ]  # fmt: skip
    assert quality.main(argv) == 0
    synthetic = json.loads(out.with_suffix(".json").read_text())["results"]["synthetic"]
    assert set(synthetic["calibration"]) == set(quality.MODELS)
    matrix = synthetic["recovery"]["estimator_top_model"]
    assert len(matrix) == 8 and all(len(row) == 8 for row in matrix)
    assert synthetic["refinement"]["rounds"] == 1
    assert "Model recovery" in out.with_suffix(".md").read_text()
