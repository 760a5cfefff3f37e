"""``torchcf data extract`` and a training config naming a raw source.

The raw file is a generic long CSV written here: four leader-follower couples in
four lanes for 60 s, positions in feet and speeds in km/h, as a user's own log
might be. The real OpenACC samples are used where ``TORCHCF_RAW`` points to them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.cli.test_bad_input import one_error_line
from tests.data.test_extract import couple_rows
from tests.runs import exit_code
from torchcf.cli import train as train_cli
from torchcf.cli.data import main as data_main
from torchcf.config import ConfigError, load_split, validate_config
from torchcf.data import load_pairs

FOOT = 0.3048
COLUMNS = "vehicle=ID,time=t,position=y,speed=kmh,leader=ahead,lane=lane,gap=space"


def write_log(path: Path, *, kmh_as_ms: bool = False) -> Path:
    """Four couples over 60 s as a user's CSV (ft, km/h, no acceleration)."""
    t = np.round(np.arange(0.0, 60.0, 0.1), 10)
    frames = []
    for k in range(4):
        frames += couple_rows(t, leader=f"L{k}", follower=f"F{k}", lane=str(k), phase=k)
    frame = pd.concat(frames, ignore_index=True)
    log = pd.DataFrame(
        {
            "ID": frame["vehicle"],
            "t": frame["time"],
            "y": frame["position"] / FOOT,
            "kmh": frame["speed"] * (1.0 if kmh_as_ms else 3.6),
            "ahead": frame["leader"],
            "lane": frame["lane"],
            "space": frame["gap"] / FOOT,
        }
    )
    log.to_csv(path, index=False)
    return path


def extract_args(log: Path, out: Path, *more: str) -> list[str]:
    return [
        "extract",
        str(log),
        "--format",
        "csv",
        "--columns",
        COLUMNS,
        "--length-unit",
        "ft",
        "--speed-unit",
        "km/h",
        "--window",
        "20",
        "--test-fraction",
        "0.25",
        "--out",
        str(out),
        *more,
    ]


def test_extract_writes_a_loadable_folder(tmp_path, capsys) -> None:
    log = write_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    assert data_main(extract_args(log, out)) == 0
    printed = capsys.readouterr().out
    assert "12 pairs (9 train, 3 test) of 200 steps" in printed
    for name in ("meta.json", "index.csv", "dropped.csv", "extract.json"):
        assert (out / name).is_file()
    assert (out / "Trajectory").is_dir() and (out / "Testing").is_dir()
    record = json.loads((out / "extract.json").read_text())
    assert record["command"].startswith("torchcf data extract")
    assert record["raw"]["speed_unit"] == "km/h"
    index = pd.read_csv(out / "index.csv", keep_default_na=False)
    # the follower ids split whole: three windows each, one follower tested
    assert index.groupby("follower")["split"].nunique().max() == 1
    assert (index["split"] == "test").sum() == 3
    # feet and km/h converted: the follower's mean speed is ~15 m/s
    assert index["mean_speed"].between(12.0, 18.0).all()


@pytest.mark.parametrize(
    "change, needles",
    [
        (["--columns", "vehicle=ID,time=t,position=nope"], ["nope"]),
        (["--speed-unit", "knots"], ["speed_unit", "knots"]),
        (["--window", "90"], ["lasts one window", "--window"]),
        (["--max-acceleration", "0.1"], ["no window", "acceleration"]),
        (["--test-fraction", "1.5"], ["--test-fraction", ">= 0 and < 1"]),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, change, needles) -> None:
    log = write_log(tmp_path / "log.csv")
    args = extract_args(log, tmp_path / "pairs")
    flag = change[0]
    if flag in args:
        args[args.index(flag) + 1] = change[1]
    else:
        args += change
    assert exit_code(data_main, args) == 2
    one_error_line(capsys.readouterr().err, *needles)
    assert not (tmp_path / "pairs").exists()


def test_speeds_in_kmh_read_as_ms_are_refused(tmp_path, capsys) -> None:
    log = write_log(tmp_path / "log.csv")
    args = extract_args(log, tmp_path / "pairs")
    args[args.index("--speed-unit") + 1] = "m/s"  # the column holds km/h
    assert data_main(args) == 2
    one_error_line(capsys.readouterr().err, "units")


def test_road_frame_is_declared_in_meta_json(tmp_path) -> None:
    log = write_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    assert data_main(extract_args(log, out, "--road-frame", "yes")) == 0
    assert json.loads((out / "meta.json").read_text())["road_frame"] is True
    assert load_pairs(out, "train").road_frame is True


def test_existing_output_needs_overwrite(tmp_path, capsys) -> None:
    log = write_log(tmp_path / "log.csv")
    out = tmp_path / "pairs"
    assert data_main(extract_args(log, out)) == 0
    assert data_main(extract_args(log, out)) == 2
    one_error_line(capsys.readouterr().err, "--overwrite")
    assert data_main(extract_args(log, out, "--overwrite")) == 0


def raw_config(log: Path, **data) -> dict:
    return {
        "data": {
            "raw": {
                "source": str(log),
                "format": "csv",
                "columns": dict(item.split("=") for item in COLUMNS.split(",")),
                "length_unit": "ft",
                "speed_unit": "km/h",
                "window": 20,
                "test_fraction": 0.25,
            },
            **data,
        },
        "models": ["idm", "llcs"],
        "abc": {
            "n_particles": 2000,
            "chunk_size": 500,
            "top_n": 2,
            "sensitivity_n": [2],
        },
        "compile": "off",
        "threads": 1,
    }


def test_config_raw_source_gives_the_cli_pairs(tmp_path) -> None:
    log = write_log(tmp_path / "log.csv")
    assert data_main(extract_args(log, tmp_path / "pairs")) == 0
    cfg = validate_config(raw_config(log))
    train, test = load_split(cfg.data)
    by_hand = validate_config(
        {**raw_config(log), "data": {"path": str(tmp_path / "pairs")}}
    )
    train_files, test_files = load_split(by_hand.data)
    assert train.x_follow.allclose(train_files.x_follow, rtol=0, atol=1e-9)
    assert test.v_lead.allclose(test_files.v_lead, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "data, needle",
    [
        ({"name": "car-model-2"}, "exactly one of name"),
        ({"split": "kfold"}, "kfold"),
        ({"dt": 0.1}, "not used with raw"),
    ],
)
def test_config_raw_conflicts(tmp_path, data, needle) -> None:
    with pytest.raises(ConfigError, match=needle):
        validate_config(raw_config(tmp_path / "log.csv", **data))


def test_openacc_option_refused_for_csv(tmp_path) -> None:
    cfg = raw_config(tmp_path / "log.csv")
    cfg["data"]["raw"]["format"] = "openacc"
    with pytest.raises(ConfigError, match="only used with format='csv'"):
        validate_config(cfg)


def test_train_on_a_raw_file(tmp_path) -> None:
    log = write_log(tmp_path / "log.csv")
    config = tmp_path / "cfg.json"
    config.write_text(json.dumps(raw_config(log)))
    out = tmp_path / "run"
    assert train_cli.main([str(config), "--out", str(out)]) == 0
    assert (out / "metrics.json").is_file()
    record = json.loads((out / "data" / "extract.json").read_text())
    assert record["summary"]["pairs"] == 12
    assert (out / "data" / "index.csv").is_file()
