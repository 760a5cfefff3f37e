"""``torchcf data extract --window whole`` and ``--test-fraction 0``,
then training on what it wrote.

The raw file is the user's CSV of :mod:`tests.data.test_data_cli` (feet, km/h)
with couples of different durations: 60, 35 and 22 s, one of 6 s (under the
minimum), and a GNSS jump that cuts the 60 s couple in two.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.cli.test_bad_input import one_error_line
from tests.data.test_data_cli import FOOT, extract_args, raw_config
from tests.data.test_extract import couple_rows
from tests.runs import exit_code
from torchcf.cli import evaluate as evaluate_cli
from torchcf.cli import train as train_cli
from torchcf.cli.data import main as data_main
from torchcf.config import load_split, validate_config
from torchcf.data import DataError, load_pairs

#: follower -> duration [s] of its couple
DURATIONS = {"F0": 60.0, "F1": 35.0, "F2": 22.0, "F3": 6.0}


def write_ragged_log(path: Path) -> Path:
    """Four couples of different durations as a user's CSV (ft, km/h); the
    first follower's position jumps 3 m at 25 s."""
    frames = []
    for k, (follower, duration) in enumerate(DURATIONS.items()):
        t = np.round(np.arange(0.0, duration, 0.1), 10)
        frames += couple_rows(t, leader=f"L{k}", follower=follower, lane=str(k))
    follow = frames[1]
    late = follow["time"] >= 25.0 - 1e-9
    follow.loc[late, "position"] += 3.0
    follow.loc[late, "gap"] -= 3.0
    frame = pd.concat(frames, ignore_index=True)
    pd.DataFrame(
        {
            "ID": frame["vehicle"],
            "t": frame["time"],
            "y": frame["position"] / FOOT,
            "kmh": frame["speed"] * 3.6,
            "ahead": frame["leader"],
            "lane": frame["lane"],
            "space": frame["gap"] / FOOT,
        }
    ).to_csv(path, index=False)
    return path


def whole_args(log: Path, out: Path, test_fraction: str, *more: str) -> list[str]:
    args = extract_args(log, out, *more)
    args[args.index("--window") + 1] = "whole"
    args[args.index("--test-fraction") + 1] = test_fraction
    return args


def test_extract_whole_couples(tmp_path, capsys) -> None:
    log = write_ragged_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    assert data_main(whole_args(log, out, "0.25", "--split-by", "couple")) == 0
    printed = capsys.readouterr().out
    assert "4 pairs (3 train, 1 test), whole couples of 22.0-35.0 s" in printed
    assert "couples cut at: jump 1" in printed
    assert "1 couple spans and 0 stretches shorter than 10 s" in printed
    index = pd.read_csv(out / "index.csv", keep_default_na=False)
    # F0 cut at the jump (25 s + 35 s), F1 and F2 whole, F3 (6 s) dropped
    assert index["steps"].tolist() == [250, 350, 350, 220]
    assert index["follower"].tolist() == ["F0", "F0", "F1", "F2"]
    assert load_pairs(out).lengths.tolist() == [250, 350, 350, 220]
    test = load_pairs(out, "test")
    assert (
        test.lengths.tolist() == index.loc[index["split"] == "test", "steps"].tolist()
    )
    record = json.loads((out / "extract.json").read_text())
    assert record["raw"]["window"] == "whole"
    summary = record["summary"]
    assert summary["pairs_are"] == "whole couples"
    assert summary["pair_seconds"] == pytest.approx(
        {"min": 22.0, "median": 30.0, "max": 35.0}
    )
    assert summary["spans_short"] == 1 and summary["seconds_in_short_spans"] == 6.0
    assert json.loads((out / "meta.json").read_text())["pairs"]["seconds"]["max"] == 35


@pytest.mark.parametrize(
    "change, needles",
    [
        (["--stride", "5"], ["stride", "window 'whole'"]),
        (["--window", "holes"], ["--window", "'whole'"]),
    ],
)
def test_bad_whole_input_is_one_line_and_exit_2(
    tmp_path, capsys, change, needles
) -> None:
    log = write_ragged_log(tmp_path / "log.csv")
    args = whole_args(log, tmp_path / "pairs", "0")
    if change[0] in args:
        args[args.index(change[0]) + 1] = change[1]
    else:
        args += change
    assert exit_code(data_main, args) == 2
    one_error_line(capsys.readouterr().err, *needles)
    assert not (tmp_path / "pairs").exists()


def test_train_on_whole_couples_without_a_test_split(tmp_path, capsys) -> None:
    """``--test-fraction 0`` writes no Testing/; a run trains on the folder,
    says in one line that it is not evaluated, and an evaluation asked for
    later is a one-line error."""
    log = write_ragged_log(tmp_path / "log.csv")
    pairs = tmp_path / "pairs"
    assert data_main(whole_args(log, pairs, "0")) == 0
    assert (pairs / "Trajectory").is_dir() and not (pairs / "Testing").exists()
    config = tmp_path / "cfg.json"
    config.write_text(json.dumps({**raw_config(log), "data": {"path": str(pairs)}}))
    run = tmp_path / "run"
    capsys.readouterr()
    assert train_cli.main([str(config), "--out", str(run)]) == 0
    printed = capsys.readouterr().out
    assert "note: no test split in the data" in printed
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["n_train"], summary["n_test"]) == (4, 0)
    assert not (run / "metrics.json").exists()

    assert exit_code(evaluate_cli.main, [str(run)]) == 2
    one_error_line(capsys.readouterr().err, "no test split", "Testing/")


def test_a_raw_source_without_a_test_split(tmp_path) -> None:
    """``data.raw.test_fraction = 0``: training gets its pairs, a step that
    needs test pairs gets a one-line error."""
    log = write_ragged_log(tmp_path / "log.csv")
    cfg = raw_config(log)
    cfg["data"]["raw"].update(window="whole", test_fraction=0)
    data = validate_config(cfg).data
    train, test = load_split(data, require_test=False)
    assert test is None and train.lengths.tolist() == [250, 350, 350, 220]
    with pytest.raises(DataError, match="no test split: data.raw.test_fraction is 0"):
        load_split(data)
    cfg["data"]["raw"]["stride"] = 5.0
    with pytest.raises(ValueError, match="stride: not used with window 'whole'"):
        validate_config(cfg)
