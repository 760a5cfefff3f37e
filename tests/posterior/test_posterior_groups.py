"""The hybrid's shares per group of training pairs (``--by``, ``--groups``)."""

from __future__ import annotations

import csv
import io
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from tests.data.test_extract import T, couple_rows, table_of
from tests.runs import exit_code
from torchcf.cli.posterior import main
from torchcf.config import TrainConfig
from torchcf.data import load_pairs
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.writer import write_extraction
from torchcf.posterior import ModelParticles, Posterior
from torchcf.posterior.tables import (
    ALL,
    NO_GROUP,
    SHARES_COLUMNS,
    Bootstrap,
    GroupError,
    grouped_shares,
    groups_by_column,
    groups_from_file,
    locate_index,
    pair_slots,
    read_index,
    shares_csv,
    shares_markdown,
    training_pairs,
)
from torchcf.runs.directory import RunDir
from torchcf.train import train

MODELS = ("idm", "llctg", "hl")
#: Training pair id -> slots held per model (top_n = 2): pairs 10-12 in group
#: A, 13-15 in group B; every pair but 15 has one winner.
SLOTS = {
    10: (2, 0, 0),
    11: (2, 0, 0),
    12: (0, 2, 0),
    13: (0, 0, 2),
    14: (0, 0, 2),
    15: (1, 0, 1),
}
GROUP = {10: "A", 11: "A", 12: "A", 13: "B", 14: "B", 15: "B"}


def _posterior(slots: dict[int, tuple[int, ...]], models=MODELS) -> Posterior:
    """A learned set whose hybrid holds ``slots[pair][m]`` particles of model m
    on each pair (parameters irrelevant here)."""
    hybrid = {}
    for m, model in enumerate(models):
        pair_ids = [p for p, held in slots.items() for _ in range(held[m])]
        n = len(pair_ids)
        hybrid[model] = ModelParticles(
            ("x",),
            torch.zeros(n, 1, dtype=torch.float64),
            torch.ones(n, dtype=torch.float64),
            torch.tensor(pair_ids, dtype=torch.int64),
            torch.arange(n, dtype=torch.int64),
        )
    total = sum(map(sum, slots.values()))
    shares = {
        model: sum(held[m] for held in slots.values()) / total
        for m, model in enumerate(models)
    }
    return Posterior(
        dataset="test",
        selection="per_pair",
        top_n=2,
        models=tuple(models),
        shares=shares,
        train_pair_ids=torch.tensor(list(slots), dtype=torch.int64),
        hybrid=hybrid,
        buffers={model: {} for model in models},
    )


def _groups(posterior: Posterior) -> list[str]:
    return [GROUP[int(p)] for p in posterior.train_pair_ids]


def _rows(result) -> dict[str, object]:
    return {row.group: row for row in result.rows}


# ------------------------------------------------------------------ the shares
def test_pair_slots_count_each_models_slots_per_pair() -> None:
    posterior = _posterior(SLOTS)
    np.testing.assert_array_equal(pair_slots(posterior), np.array(list(SLOTS.values())))


def test_grouped_shares_are_the_slots_of_each_groups_pairs() -> None:
    posterior = _posterior(SLOTS)
    result = grouped_shares(
        posterior, _groups(posterior), by="g", bootstrap=Bootstrap(seed=3)
    )
    rows = _rows(result)
    assert [row.group for row in result.rows] == [ALL, "A", "B"]
    assert rows["A"].n_pairs == 3 and rows["B"].n_pairs == 3
    assert rows["A"].slots == (4, 2, 0) and rows["B"].slots == (1, 0, 5)
    assert rows["A"].share == pytest.approx((4 / 6, 2 / 6, 0.0))
    assert rows["B"].share == pytest.approx((1 / 6, 0.0, 5 / 6))
    # over all pairs: the run's own shares
    assert rows[ALL].share == pytest.approx([posterior.shares[m] for m in MODELS])
    assert rows[ALL].n_pairs == 6 and rows[ALL].n_slots == 12


def test_intervals_hold_the_share_and_are_reproducible() -> None:
    posterior = _posterior(SLOTS)
    result = grouped_shares(
        posterior, _groups(posterior), by="g", bootstrap=Bootstrap(seed=3)
    )
    for row in result.rows:
        for share, low, high in zip(row.share, row.low, row.high, strict=True):
            assert low <= share + 1e-12 and share <= high + 1e-12
            assert 0.0 <= low and high <= 1.0
    # a model no pair of the group chose has no interval to speak of
    assert _rows(result)["A"].high[2] == 0.0
    again = grouped_shares(
        posterior, _groups(posterior), by="g", bootstrap=Bootstrap(seed=3)
    )
    assert again == result
    # a group's draws depend on its name and the seed, not on the other groups
    alone = grouped_shares(
        posterior, ["A"] * 3 + [NO_GROUP] * 3, by="g", bootstrap=Bootstrap(seed=3)
    ).rows[1]
    assert alone == _rows(result)["A"]


def test_a_group_that_agrees_has_a_point_interval_and_one_cluster_none() -> None:
    slots = {0: (2, 0, 0), 1: (2, 0, 0), 2: (0, 1, 1), 3: (1, 1, 0)}
    posterior = _posterior(slots)
    groups = ["same", "same", "mixed", "mixed"]
    rows = _rows(grouped_shares(posterior, groups, by="g"))
    assert rows["same"].share == (1.0, 0.0, 0.0)
    assert rows["same"].low == (1.0, 0.0, 0.0) and rows["same"].high == (1.0, 0.0, 0.0)
    assert rows["mixed"].low[0] == 0.0 and rows["mixed"].high[0] == 0.5
    clustered = grouped_shares(
        posterior, groups, by="g", clusters=["c1", "c1", "c2", "c2"], unit="c"
    )
    rows = _rows(clustered)
    assert rows["mixed"].n_units == 1 and rows[ALL].n_units == 2
    assert np.isnan(rows["mixed"].low).all() and np.isnan(rows["mixed"].high).all()
    assert rows[ALL].low[0] == 0.25 and rows[ALL].high[0] == 1.0
    text = shares_markdown(clustered)
    assert "| mixed † | 2 | 1 | 25.0 | 50.0 | 25.0 |" in text
    assert "† fewer than 5 clusters" in text


def test_no_bootstrap_and_bad_settings() -> None:
    posterior = _posterior(SLOTS)
    result = grouped_shares(
        posterior, _groups(posterior), by="g", bootstrap=Bootstrap(n_bootstrap=0)
    )
    assert all(np.isnan(row.low).all() for row in result.rows)
    assert "66.7 |" in shares_markdown(result)
    with pytest.raises(GroupError, match="level"):
        grouped_shares(
            posterior, _groups(posterior), by="g", bootstrap=Bootstrap(level=1.0)
        )
    with pytest.raises(GroupError, match="for each of 6 pairs"):
        grouped_shares(posterior, ["A"], by="g")


def test_csv_and_markdown_tables() -> None:
    posterior = _posterior(SLOTS)
    result = grouped_shares(
        posterior, _groups(posterior), by="setting", bootstrap=Bootstrap(seed=1)
    )
    rows = list(csv.DictReader(io.StringIO(shares_csv(result))))
    assert tuple(rows[0]) == SHARES_COLUMNS
    assert len(rows) == 3 * len(MODELS)
    b_hl = next(r for r in rows if r["group"] == "B" and r["model"] == "hl")
    assert b_hl["pairs"] == "3" and b_hl["slots"] == "5" and b_hl["slots_total"] == "6"
    assert float(b_hl["share"]) == pytest.approx(5 / 6)
    text = shares_markdown(result)
    assert text.startswith("## Shares by setting")
    assert "| setting | pairs | IDM | LLCTG | HL |" in text
    line = next(t for t in text.splitlines() if t.startswith("| A † |"))
    assert line.startswith("| A † | 3 | 66.7 [") and line.endswith("| 0 |")


# ----------------------------------------------------------- pairs and groups
def _index(splits: str) -> pd.DataFrame:
    """An extraction's index: pair i with split 'train'/'test' from ``splits``
    ('r' / 't'), run and follower made up."""
    return pd.DataFrame(
        {
            "pair": [str(i) for i in range(len(splits))],
            "split": ["train" if s == "r" else "test" for s in splits],
            "run": [f"run{i % 2}" for i in range(len(splits))],
            "follower": [str(i // 2) for i in range(len(splits))],
            "mode": ["ACC:S", "", "ACC:L", "ACC:S", "ACC:L", "ACC:S"][: len(splits)],
        }
    )


def test_positions_in_trajectory_are_the_indexs_training_rows() -> None:
    index = _index("rtrrtr")  # training rows: pairs 0, 2, 3, 5
    posterior = _posterior({k: (2, 0, 0) for k in range(4)})
    table = training_pairs(posterior, index, by_position=True, train_columns=4)
    assert table["pair"].tolist() == ["0", "2", "3", "5"]
    with pytest.raises(GroupError, match="lists 4 training pairs, Trajectory/ holds 5"):
        training_pairs(posterior, index, by_position=True, train_columns=5)
    five = _posterior({k: (2, 0, 0) for k in range(5)})
    with pytest.raises(GroupError, match="training pair 4 is not among"):
        training_pairs(five, index, by_position=True)


def test_pair_ids_are_the_indexs_pair_column() -> None:
    index = _index("rtrrtr")
    posterior = _posterior({5: (2, 0, 0), 1: (0, 2, 0)})
    table = training_pairs(posterior, index)
    assert table["pair"].tolist() == ["5", "1"]
    assert groups_by_column(table, "mode") == ["ACC:S", NO_GROUP]
    with pytest.raises(GroupError, match="training pair 9 is not among the 6 pairs"):
        training_pairs(_posterior({9: (2, 0, 0)}), index)
    assert training_pairs(posterior)["pair"].tolist() == ["5", "1"]


def test_a_bad_column_names_the_columns() -> None:
    table = _index("rr")
    with pytest.raises(GroupError, match=r"no column 'mod' in x.*did you mean 'mode'"):
        groups_by_column(table, "mod", "x")


def test_mapping_file_joins_on_its_key_columns(tmp_path) -> None:
    table = _index("rrrrrr")
    path = tmp_path / "make.csv"
    path.write_text("run,follower,group\nrun0,0,tesla\nrun1, 0 ,tesla\nrun0,1,bmw\n")
    groups = groups_from_file(table, path)
    # pairs: (run0,0) (run1,0) (run0,1) (run1,1) (run0,2) (run1,2)
    assert groups == ["tesla", "tesla", "bmw", NO_GROUP, NO_GROUP, NO_GROUP]
    path.write_text("pair,group\n0,x\n0,y\n")
    with pytest.raises(GroupError, match="has two groups"):
        groups_from_file(table, path)
    path.write_text("pair,make\n0,x\n")
    with pytest.raises(GroupError, match="no 'group' column"):
        groups_from_file(table, path)
    path.write_text("vehicle,group\n0,x\n")
    with pytest.raises(GroupError, match="key no column 'vehicle'"):
        groups_from_file(table, path)


@pytest.mark.parametrize(
    "text", ["pair,group\n", "pair,group\n1000,a\n-1,b\n2.5,c\n", "pair,group\nx,a\n"]
)
def test_a_mapping_file_naming_no_pair_is_refused(tmp_path, text) -> None:
    """A file of other pairs' keys (or none) would put every pair in
    ``(none)``: an error naming the keys the pairs have, not a table."""
    table = _index("rrrrrr")
    path = tmp_path / "g.csv"
    path.write_text(text)
    with pytest.raises(GroupError, match=r"no row names a training pair.*'pair': '0'"):
        groups_from_file(table, path)


def test_locate_index_follows_the_data_section(tmp_path) -> None:
    data = SimpleNamespace(raw=None, path=str(tmp_path), name=None, split="dataset")
    with pytest.raises(GroupError, match="no index.csv in"):
        locate_index(data, tmp_path / "run")
    (tmp_path / "index.csv").write_text("pair,split\n0,train\n")
    where = locate_index(data, tmp_path / "run")
    assert where.path == tmp_path / "index.csv" and where.by_position
    kfold = SimpleNamespace(raw=None, path=str(tmp_path), name=None, split="kfold")
    assert not locate_index(kfold, tmp_path / "run").by_position
    raw = SimpleNamespace(raw=object(), path=None, name=None, split="dataset")
    with pytest.raises(GroupError, match="run/data"):
        locate_index(raw, tmp_path / "run")
    named = SimpleNamespace(raw=None, path=None, name="car-model-2", split="dataset")
    with pytest.raises(GroupError, match="--groups"):
        locate_index(named, tmp_path / "run")
    assert locate_index(named, tmp_path / "run", folder=tmp_path).path.is_file()
    assert read_index(tmp_path / "index.csv")["split"].tolist() == ["train"]


# ------------------------------------------------------------- a whole run
@pytest.fixture(scope="module")
def extracted_run(tmp_path_factory):
    """Twelve pairs extracted from four synthetic couples in two runs (a
    follower's three windows each, one follower's on the test side), the
    folder written as ``torchcf data extract`` writes it, and a tiny
    run trained on its own split."""
    root = tmp_path_factory.mktemp("groups")
    frames = []
    for k in range(4):
        pair = couple_rows(
            T, run=f"r{k % 2}", leader=f"L{k}", follower=f"F{k}", lane="1", phase=k
        )
        for frame in pair:
            frame["mode"] = "ACC:S" if k < 2 else "ACC:L"
        frames += pair
    options = ExtractOptions(window=10.0, test_fraction=0.25, seed=1)
    folder = write_extraction(extract_pairs(table_of(frames), options), root / "pairs")
    cfg = TrainConfig.model_validate(
        {
            "data": {"path": str(folder), "split": "dataset"},
            "models": ["idm", "llcs"],
            "abc": {"n_particles": 900, "chunk_size": 450, "top_n": 2},
            "compile": "off",
            "plausibility": {"report": False},
        }
    )
    train(cfg, root / "run")
    return folder, RunDir(root / "run")


def test_the_run_finds_its_pairs_rows_in_the_index(extracted_run) -> None:
    folder, run = extracted_run
    index = read_index(folder / "index.csv")
    assert index["split"].tolist() != sorted(index["split"].tolist(), reverse=True)
    where = locate_index(run.read_config().data, run.path)
    assert where.by_position and where.train_columns == 9
    posterior = run.load_posterior()
    table = training_pairs(
        posterior, index, by_position=True, train_columns=where.train_columns
    )
    # each training pair is the full-set column its index row names
    full, trained = load_pairs(folder), load_pairs(folder, "train")
    for k, pair in enumerate(table["pair"]):
        column = trained.pair_ids.index(int(posterior.train_pair_ids[k]))
        assert trained.x_follow[:, column].equal(full.x_follow[:, int(pair)])
    assert set(table["split"]) == {"train"}


def test_command_line_groups_by_a_column(extracted_run, capsys) -> None:
    folder, run = extracted_run
    posterior = run.load_posterior()
    table = training_pairs(
        posterior, read_index(folder / "index.csv"), by_position=True
    )
    assert main([str(run.path), "--by", "mode", "--csv", "-"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    slots = pair_slots(posterior)  # (N, M)
    for mode in ("ACC:S", "ACC:L"):
        held = slots[(table["mode"] == mode).to_numpy()].sum(axis=0)
        for m, model in enumerate(posterior.models):
            row = next(r for r in rows if r["group"] == mode and r["model"] == model)
            assert int(row["slots"]) == held[m]
            assert int(row["pairs"]) == int((table["mode"] == mode).sum())
    assert main([str(run.path), "--by", "follower", "--cluster", "run"]) == 0
    text = capsys.readouterr().out
    assert "## Shares by follower" in text and "clusters (run)" in text
    assert main([str(run.path), "--by", "run", "--csv"]) == 0
    assert (run.report_dir / "shares_by_run.csv").is_file()
    assert (run.report_dir / "shares_by_run.md").read_text().startswith("# Shares")
    assert (
        main([str(run.path), "--by", "mode", "--cluster", "run,follower", "--csv"]) == 0
    )
    text = (run.report_dir / "shares_by_mode-clusters-run-follower.md").read_text()
    assert "clusters (run, follower)" in text


def test_command_line_groups_from_a_mapping_file(extracted_run, tmp_path, capsys):
    _, run = extracted_run
    path = tmp_path / "make.csv"
    path.write_text("run,follower,group\nr0,F0,tesla\nr1,F1,tesla\nr0,F2,bmw\n")
    assert main([str(run.path), "--groups", str(path), "--bootstrap", "0"]) == 0
    captured = capsys.readouterr()
    assert "## Shares by make" in captured.out and "| tesla |" in captured.out
    assert "training pairs are in no row of" in captured.err  # the others


@pytest.mark.parametrize(
    "args, message",
    [
        (["--by", "colour"], "no column 'colour' in"),
        (["--groups", "missing.csv"], "missing.csv"),
        (["--by", "mode", "--cluster", "nope"], "no column 'nope' in"),
        (
            ["--by", "mode", "--level", "2"],
            "--level: expected a number between 0 and 1",
        ),
    ],
)
def test_bad_grouping_is_one_line_and_exit_code_2(
    extracted_run, capsys, args, message
) -> None:
    _, run = extracted_run
    assert exit_code(main, [str(run.path), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err


def test_a_registered_set_groups_by_pair_only(tmp_path, capsys) -> None:
    (tmp_path / "run").mkdir()
    run = RunDir(tmp_path / "run")
    run.write_config(TrainConfig.model_validate({"data": {"name": "car-model-2"}}))
    run.save_posterior(_posterior(SLOTS))
    assert main([str(run.path), "--by", "mode"]) == 2
    assert "--groups" in capsys.readouterr().err
    path = tmp_path / "g.csv"
    path.write_text("pair,group\n" + "".join(f"{p},{g}\n" for p, g in GROUP.items()))
    assert main([str(run.path), "--groups", str(path), "--csv", "-"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    a_idm = next(r for r in rows if r["group"] == "A" and r["model"] == "idm")
    assert float(a_idm["share"]) == pytest.approx(4 / 6)
