"""``torchcf predict`` and :func:`torchcf.predict.predict` on a tiny trained run."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from tests.runs import exit_code, write_config, write_data
from torchcf.cli.predict import main
from torchcf.cli.train import main as train
from torchcf.data import load_pairs
from torchcf.predict import PredictSettings, TrainedRun, predict
from torchcf.predict.history import driver_posterior, predict_rest
from torchcf.sim.rollout import simulate


@pytest.fixture(scope="module")
def trained(tmp_path_factory, one_thread):
    """A run of IDM and LLCS on 12 synthetic pairs of 15 s (k-fold: 8 / 4)."""
    root = tmp_path_factory.mktemp("predict")
    data = write_data(root / "data", n_pairs=12, n_steps=150)
    config = write_config(root / "config.json", data)
    assert train([str(config), "--out", str(root / "run"), "--no-eval"]) == 0
    return root / "run", data


def test_the_cli_predicts_the_run_test_pairs_and_writes_every_file(
    trained, tmp_path, capsys
):
    run, _ = trained
    out = tmp_path / "out"
    argv = [str(run), "--out", str(out), "--draws", "20", "--history", "5"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "population model" in printed and "predict.md" in printed
    summary = json.loads((out / "predict.json").read_text())
    assert summary["pairs"] == 4 and summary["bands"]["draws"] == 20
    assert summary["history"]["pairs"] == 4  # 15 s: 10 s after the history
    per_pair = pd.read_csv(out / "pairs.csv")
    assert len(per_pair) == 4 and per_pair["population_rmse"].notna().all()
    steps = pd.read_csv(out / "trajectories.csv")
    assert len(steps) == 4 * 150
    first = steps[steps["step"] == 0]
    assert np.allclose(first["population"], first["observed"])  # the recorded start
    history_steps = steps[steps["time_s"] < 5.0]
    assert history_steps["conditioned"].isna().all()
    assert "It answers" in (out / "predict.md").read_text()
    # an earlier prediction is kept unless asked
    assert exit_code(main, argv) == 2
    err = capsys.readouterr().err.strip()
    assert "--overwrite" in err and "\n" not in err
    assert main([*argv, "--overwrite"]) == 0


def test_pairs_of_another_time_step_are_refused_in_one_line(trained, tmp_path, capsys):
    run, _ = trained
    other = write_data(tmp_path / "other", n_pairs=3, n_steps=100)
    (other / "meta.json").write_text(json.dumps({"dt": 0.2, "units": "m"}))
    assert exit_code(main, [str(run), str(other), "--split", "all"]) == 2
    err = capsys.readouterr().err.strip()
    assert "time step is 0.2 s, the run's 0.1 s" in err and "\n" not in err
    assert not (run / "predict").exists()


def test_a_folder_without_constants_is_read_at_the_run_s(trained, tmp_path):
    run, _ = trained
    other = write_data(tmp_path / "bare", n_pairs=3, n_steps=100)
    (other / "meta.json").unlink()
    out = tmp_path / "out"
    argv = [str(run), str(other), "--split", "all", "--out", str(out), "--draws", "5"]
    assert main([*argv, "--no-history"]) == 0
    assert json.loads((out / "predict.json").read_text())["history"] is None


@pytest.mark.parametrize(
    "bad", [["--draws", "0"], ["--history", "-1"], ["--keep", "x"]]
)
def test_bad_options_end_in_one_line(trained, bad, capsys):
    run, _ = trained
    assert exit_code(main, [str(run), *bad]) == 2
    assert "\n" not in capsys.readouterr().err.strip()


def test_ragged_pairs_are_predicted_on_their_own_steps_and_independently(trained):
    run_dir, data = trained
    run = TrainedRun.load(run_dir)
    pairs = load_pairs(data).subset([0, 5, 9])
    mask = pairs.mask.clone()
    mask[80:, 1] = False  # pair 5 ends at 8 s
    series = pairs.series()
    ragged = type(pairs).from_arrays(
        series, dt=pairs.dt, mask=mask, pair_ids=pairs.pair_ids
    )
    settings = PredictSettings(draws=16, history=3.0, keep=10)
    found = predict(run, ragged, settings)
    assert found.per_pair["seconds"].tolist() == pytest.approx([14.9, 7.9, 14.9])
    assert torch.isnan(found.bands.median[80:, 1]).all()
    assert torch.isfinite(found.bands.median[:80, 1]).all()
    # a pair's draws and history search do not depend on the pairs beside it
    alone = predict(run, ragged.subset([2]), settings)
    assert torch.allclose(alone.bands.median[:, 0], found.bands.median[:, 2])
    assert torch.allclose(
        alone.conditioned[:, 0], found.conditioned[:, 2], equal_nan=True
    )


def test_a_driver_that_is_a_hybrid_particle_is_found_from_its_history(trained):
    """A follower driven by one of the hybrid's particles: its own history
    picks that particle, and the rest is predicted exactly."""
    run_dir, data = trained
    run = TrainedRun.load(run_dir)
    model = run.hybrid_models[0]
    truth = run.particles(model)[3:4]
    leaders = load_pairs(data).subset([1])
    out = simulate(
        model, truth, leaders, torch.tensor([0]), dtype=torch.float64, return_traj=True
    )
    series = leaders.series()
    series.update(x_follow=out.x, v_follow=out.v, a_follow=out.a)
    driven = type(leaders).from_arrays(series, dt=leaders.dt)
    posterior = driver_posterior(run, driven, 5.0, keep=1)
    assert posterior.score[0, 0] == pytest.approx(0.0, abs=1e-9)
    rest, median, _ = predict_rest(posterior, driven)
    gap = rest.x_lead - rest.x_follow - rest.leader_length
    assert torch.allclose(median[:, 0], gap[:, 0].double(), atol=1e-6)
