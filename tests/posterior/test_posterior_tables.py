"""The calibrated parameters, readable: CSV, Markdown tables, the command line."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest
import torch

from tests.conftest import synthetic_pairs
from torchcf.cli.posterior import main
from torchcf.config import TrainConfig
from torchcf.posterior import ModelParticles, Posterior
from torchcf.posterior.tables import (
    csv_header,
    parameter_summary,
    parameters_csv,
    parameters_markdown,
    piled_at_bounds,
)
from torchcf.runs.directory import RunDir
from torchcf.train import train


def _particles(names, theta, pair_ids, scores):
    n = len(theta)
    return ModelParticles(
        tuple(names),
        torch.tensor(theta, dtype=torch.float64),
        torch.tensor(scores, dtype=torch.float64),
        torch.tensor(pair_ids, dtype=torch.int64),
        torch.arange(n, dtype=torch.int64) * 7,
    )


@pytest.fixture
def posterior() -> Posterior:
    """IDM with 21 particles (values 0..20 in 'a'), LLCTG with 2, OVM with none."""
    generator = np.random.default_rng(0)
    idm = np.column_stack(
        [np.arange(21.0), *(generator.uniform(1, 2, 21) for _ in range(5))]
    )
    idm_names = ("a", "b", "v0", "T", "s0", "delta")
    llctg_names = ("tau", "ks", "kv", "l")
    llctg = [[1.0, 0.5, 0.6, 5.0], [1.1, 0.4, 0.7, 4.5]]
    ovm_names = ("kappa", "v1", "v2", "c1", "c2")
    return Posterior(
        dataset="test",
        selection="per_pair",
        top_n=3,
        models=("ovm", "idm", "llctg"),
        shares={"ovm": 0.0, "idm": 21 / 23, "llctg": 2 / 23},
        train_pair_ids=torch.arange(8),
        hybrid={
            "ovm": _particles(ovm_names, np.zeros((0, 5)), [], []),
            "idm": _particles(
                idm_names, idm, [i % 7 for i in range(21)], np.linspace(2, 1, 21)
            ),
            "llctg": _particles(llctg_names, llctg, [7, 7], [0.3, 0.2]),
        },
        buffers={"ovm": {}, "idm": {}, "llctg": {}},
    )


def _rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def test_csv_has_one_row_per_particle_with_its_values(posterior):
    rows = _rows(parameters_csv(posterior))
    assert len(rows) == 23
    assert list(rows[0]) == csv_header(posterior)
    assert csv_header(posterior)[:4] == ["model", "pair_id", "particle_index", "score"]
    assert "idm.a" in rows[0] and "llctg.tau" in rows[0] and "ovm.kappa" in rows[0]
    idm = posterior.hybrid["idm"]
    by_index = {int(r["particle_index"]): r for r in rows if r["model"] == "idm"}
    for i in range(len(idm)):
        row = by_index[int(idm.particle_index[i])]
        assert int(row["pair_id"]) == int(idm.pair_ids[i])
        assert float(row["score"]) == pytest.approx(float(idm.score[i]), rel=1e-9)
        values = [float(row[f"idm.{p}"]) for p in idm.param_names]
        np.testing.assert_allclose(values, idm.theta[i].numpy(), rtol=1e-9)
        assert row["llctg.tau"] == "" and row["ovm.kappa"] == ""


def test_csv_orders_particles_by_pair_then_score(posterior):
    rows = [r for r in _rows(parameters_csv(posterior)) if r["model"] == "idm"]
    keys = [(int(r["pair_id"]), float(r["score"])) for r in rows]
    assert keys == sorted(keys)


def test_markdown_quantiles_agree_with_numpy(posterior):
    summary = {row["name"]: row for row in parameter_summary(posterior, "idm")}
    theta = posterior.hybrid["idm"].theta.numpy()
    assert summary["a"]["median"] == pytest.approx(10.0)
    assert summary["a"]["low"] == pytest.approx(1.0)  # 5 % of 0..20
    assert summary["a"]["high"] == pytest.approx(19.0)
    for k, name in enumerate(posterior.hybrid["idm"].param_names):
        low, median, high = np.percentile(theta[:, k], [5, 50, 95])
        assert summary[name]["median"] == pytest.approx(median)
        assert summary[name]["low"] == pytest.approx(low)
        assert summary[name]["high"] == pytest.approx(high)
    assert summary["a"]["unit"] == "m/s^2"
    assert summary["T"]["meaning"] == "desired time gap"
    assert (summary["v0"]["lower"], summary["v0"]["upper"]) == (20.0, 40.0)


def test_markdown_has_a_table_per_model_and_says_when_one_is_empty(posterior):
    text = parameters_markdown(posterior)
    assert "### IDM: share 91.3%, 21 particles on 7 training pairs" in text
    assert "### LLCTG: share 8.7%, 2 particles on 1 training pairs" in text
    assert "| a | m/s^2 | 10 | 1 | 19 | [0.5, 2] | maximum acceleration |" in text
    assert "No particle of this model is in the hybrid." in text.split("### OVM")[1]


def test_a_model_torchcf_does_not_know_keeps_its_names(posterior):
    posterior.hybrid["zzz"] = posterior.hybrid["llctg"]
    object.__setattr__(posterior, "models", (*posterior.models, "zzz"))
    text = parameters_markdown(posterior)
    assert "| tau |  | 1.05 |" in text.split("### ZZZ")[1]


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    cfg = TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm", "llctg"],
            "abc": {"n_particles": 800, "chunk_size": 400, "top_n": 2},
            "compile": "off",
            "plausibility": {"report": False},
        }
    )
    pairs = (synthetic_pairs(n_pairs=4, n_steps=120, seed=1),) * 2
    train(cfg, out, pairs=pairs)
    return RunDir(out)


def test_training_writes_the_tables_into_the_report(trained_run):
    posterior = trained_run.load_posterior()
    rows = _rows((trained_run.report_dir / "parameters.csv").read_text())
    assert len(rows) == sum(len(p) for p in posterior.hybrid.values())
    text = (trained_run.report_dir / "parameters.md").read_text()
    assert text.startswith("# Calibrated parameters")
    assert "## IDM" in text


def test_command_line_exports_csv_and_markdown(trained_run, tmp_path, capsys):
    assert main([str(trained_run.path)]) == 0
    assert "### IDM" in capsys.readouterr().out
    assert main([str(trained_run.path), "--csv", "-"]) == 0
    streamed = capsys.readouterr().out
    target = tmp_path / "sub" / "p.csv"
    assert main([str(trained_run.path), "--csv", str(target)]) == 0
    assert target.read_text() == streamed
    (trained_run.report_dir / "parameters.csv").unlink()
    assert main([str(trained_run.path), "--csv"]) == 0
    assert (trained_run.report_dir / "parameters.csv").read_text() == streamed


def test_command_line_on_a_folder_without_a_run_is_one_line(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1


def test_a_posterior_piled_at_a_prior_bound_is_flagged():
    """IDM's v0 prior is [20, 40]: 12 of 20 particles within 5 % of its width
    (1 m/s) of 40 is a pile (60 % against the 5 % a uniform spread puts
    there); LLCTG's l spread evenly over [1, 11] is not, nor is a share at
    the threshold (5 of 20 = 25 %, not more)."""
    idm = np.tile([1.0, 2.0, 30.0, 1.5, 1.5, 3.0], (20, 1))  # a b v0 T s0 delta
    idm[:12, 2] = 39.5  # 12 of 20 within 1 m/s of v0's upper bound 40
    idm[:5, 4] = 0.55  # 5 of 20 within 0.125 m of s0's lower bound 0.5: 25 %
    llctg = np.tile([1.0, 1.0, 1.0, 0.0], (20, 1))  # tau ks kv l
    llctg[:, 3] = np.linspace(1.0, 11.0, 20)
    names = {
        "idm": ("a", "b", "v0", "T", "s0", "delta"),
        "llctg": ("tau", "ks", "kv", "l"),
    }
    posterior = Posterior(
        dataset="test", selection="per_pair", top_n=1, models=("idm", "llctg"),
        shares={"idm": 0.5, "llctg": 0.5}, train_pair_ids=torch.arange(20),
        hybrid={
            m: _particles(names[m], theta, list(range(20)), np.ones(20))
            for m, theta in (("idm", idm), ("llctg", llctg))
        },
        buffers={"idm": {}, "llctg": {}},
    )  # fmt: skip
    piled = piled_at_bounds(posterior)
    assert [(p.model, p.parameter, p.side, p.bound) for p in piled] == [
        ("idm", "v0", "upper", 40.0)
    ]
    assert piled[0].share == pytest.approx(12 / 20)
    text = parameters_markdown(posterior)
    assert (
        "**At a prior bound.** IDM `v0`: 60% of its particles within 5% of the" in text
    )
    assert "upper bound 40" in text and "widen that prior" in text
    # l at 1.0 and 11.0 exactly: 1 particle at each end of 20 (5 %) is not a pile
    assert "`l`" not in text
