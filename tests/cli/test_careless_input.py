"""Careless input, every command: each case a user met refused in one line with
exit code 2, nothing written, no traceback (the everyday path's sweep of bad
arguments, folders and files; tests/cli/test_bad_input.py holds the config's and
the run's)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from tests.cli.test_bad_input import data, finished, one_error_line  # noqa: F401
from tests.data.test_data_cli import extract_args, write_log
from tests.runs import REPO, write_config
from torchcf.cli import crossval as crossval_cli
from torchcf.cli import data as data_cli
from torchcf.cli import demo as demo_cli
from torchcf.cli import evaluate as evaluate_cli
from torchcf.cli import posterior as posterior_cli
from torchcf.cli import train as train_cli
from torchcf.data.formats.generic import LONGEST_HEADER
from torchcf.posterior.tables import GroupError, groups_from_file, read_index
from torchcf.system.console import LONGEST_ERROR, one_line


def refused(capsys, main, argv: list[str], *needles: str) -> str:
    """``main(argv)`` exits 2 (returned or raised by argparse) with one error
    line naming every needle, and no traceback."""
    try:
        code = main(argv)
    except SystemExit as stop:
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    line = [x for x in err.splitlines() if x.strip()][-1]
    assert "error:" in line, err
    for needle in needles:
        assert needle in line, (needle, line)
    return line


@pytest.fixture(scope="module")
def raw_csv(tmp_path_factory) -> Path:
    """A user's long trajectory table (tests/data/test_data_cli.py's)."""
    return write_log(tmp_path_factory.mktemp("raw") / "log.csv")


def extract(raw: Path, out: Path, *more: str) -> list[str]:
    """``data extract`` of ``raw`` into ``out`` (its columns and units)."""
    return extract_args(raw, out, *more)


# ------------------------------------------------------------ numeric options
@pytest.mark.parametrize(
    ("main", "argv", "needle"),
    [
        (demo_cli.main, ["--threads", "-1"], "--threads"),
        (demo_cli.main, ["--threads", "0"], "--threads"),
        (demo_cli.main, ["--seed", "-1"], "--seed"),
        (evaluate_cli.main, ["RUN", "--pair", "-1"], "--pair"),
        (posterior_cli.main, ["RUN", "--seed", "-1"], "--seed"),
        (posterior_cli.main, ["RUN", "--level", "1.5"], "--level"),
        (crossval_cli.main, ["CFG", "--folds", "nan"], "--folds"),
    ],
)
def test_a_bad_number_is_a_usage_error(capsys, main, argv, needle):
    refused(capsys, main, argv, needle)


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--seed", "-1"),
        ("--window", "1e99"),
        ("--window", "nan"),
        ("--window", "0"),
        ("--test-fraction", "1"),
        ("--stride", "-2"),
    ],
)
def test_data_extract_refuses_a_bad_number(capsys, tmp_path, raw_csv, option, value):
    out = tmp_path / "o"
    refused(capsys, data_cli.main, extract(raw_csv, out, option, value), option)
    assert not out.exists()


# ------------------------------------------------------------- output folders
def test_an_empty_out_is_refused(capsys, tmp_path, data, monkeypatch):  # noqa: F811
    """``--out ''`` would write the run into the working directory."""
    monkeypatch.chdir(tmp_path)
    config = write_config(tmp_path / "cfg.json", data)
    refused(capsys, train_cli.main, [str(config), "--out", ""], "empty")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.json"]


def test_train_refuses_a_folder_of_someone_else(capsys, tmp_path, data):  # noqa: F811
    """A folder with files and no run in it (notes, a pair extraction) is not
    written into; a hidden file alone does not count."""
    config = write_config(tmp_path / "cfg.json", data)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    refused(capsys, train_cli.main, [str(config), "--out", str(out)], "notes.txt")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_overwrite_replaces_an_extraction_alone(capsys, tmp_path, raw_csv):
    """``--overwrite`` on an extraction that a run was later written into keeps
    the run's files and refuses."""
    out = tmp_path / "pairs"
    argv = extract(raw_csv, out)
    assert data_cli.main(argv) == 0
    (out / "checkpoint.pt").write_bytes(b"a run's")
    capsys.readouterr()
    refused(capsys, data_cli.main, [*argv, "--overwrite"], "checkpoint.pt")
    assert (out / "checkpoint.pt").read_bytes() == b"a run's"


def test_crossval_refuses_a_run_folder(capsys, tmp_path, finished):  # noqa: F811
    config, run = finished
    before = (run / "metrics.json").read_bytes()
    refused(capsys, crossval_cli.main, [str(config), "--out", str(run)], "holds a run")
    assert (run / "metrics.json").read_bytes() == before


def test_crossval_resume_needs_a_crossval(capsys, tmp_path, data):  # noqa: F811
    config = write_config(tmp_path / "cfg.json", data)
    out = tmp_path / "cv"
    argv = [str(config), "--out", str(out), "--resume"]
    refused(capsys, crossval_cli.main, argv, "no cross-validation to resume")
    assert not out.exists()


# --------------------------------------------------------------- the --pair
def test_evaluate_refuses_a_pair_beyond_the_split(capsys, tmp_path, finished):  # noqa: F811
    """Checked before anything is computed or written: the run keeps its
    evaluation."""
    _, run = finished
    before = (run / "metrics.json").read_bytes()
    report = tmp_path / "report"
    argv = [str(run), "--pair", "999", "--report", str(report)]
    refused(capsys, evaluate_cli.main, argv, "--pair 999", "test split has")
    assert (run / "metrics.json").read_bytes() == before
    assert not report.exists()


# ---------------------------------------------------------- long and huge input
def test_an_error_line_is_cut_around_its_middle():
    text = "unknown key '" + "k" * 100_000 + "'; did you mean 'n_particles'?"
    line = one_line(ValueError(text))
    assert len(line) <= LONGEST_ERROR + 40
    assert line.startswith("unknown key 'kkk") and line.endswith("'n_particles'?")
    assert "characters ...]" in line
    assert one_line(ValueError("short\nmessage")) == "short message"


def test_a_huge_config_key_is_one_short_line(capsys, tmp_path, data):  # noqa: F811
    config = write_config(tmp_path / "cfg.json", data, abc={"k" * 100_000: 1})
    line = refused(capsys, train_cli.main, [str(config), "--out", str(tmp_path / "r")])
    assert len(line) < LONGEST_ERROR + 60


def test_a_one_line_file_of_megabytes_is_no_table(capsys, tmp_path):
    """Refused at once (a parser would spend minutes naming its 'columns')."""
    huge = tmp_path / "huge.csv"
    huge.write_text("a," * (LONGEST_HEADER * 4))
    out = tmp_path / "o"
    argv = ["extract", str(huge), "--format", "csv", "--out", str(out)]
    refused(capsys, data_cli.main, argv, "no line break")
    assert not out.exists()


def test_groups_refuse_a_huge_line_and_an_empty_group(tmp_path):
    huge = tmp_path / "huge.csv"
    huge.write_text("pair," * (LONGEST_HEADER // 2))
    with pytest.raises(GroupError, match="line break"):
        read_index(huge)
    empty = tmp_path / "groups.csv"
    empty.write_text("pair,group\n1,a\n2,\n")
    table = pd.DataFrame({"pair": ["1", "2"]})
    with pytest.raises(GroupError, match="row 3 has an empty 'group' cell"):
        groups_from_file(table, empty, "the run's pair ids")


def test_an_empty_cluster_is_refused(capsys, tmp_path, raw_csv):
    """``--cluster ''`` names no column (it read as 'no clusters')."""
    pairs = tmp_path / "pairs"
    assert data_cli.main(extract(raw_csv, pairs)) == 0
    config = write_config(tmp_path / "cfg.json", pairs)
    run = tmp_path / "run"
    assert train_cli.main([str(config), "--out", str(run), "--no-eval"]) == 0
    capsys.readouterr()
    argv = [str(run), "--by", "lane", "--cluster", ""]
    refused(capsys, posterior_cli.main, argv, "names no column")


# ------------------------------------------------------------------ the tools
def _tool(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(REPO / "tools" / f"{name}.py"), *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


@pytest.mark.slow  # a Python process with torch per tool
@pytest.mark.parametrize(
    ("tool", "args", "needle"),
    [
        ("coverage_report", ["/nonexistent", "--out", "t"], "/nonexistent"),
        (
            "paper_report",
            ["/nonexistent", "--dataset", "carII", "--out", "t"],
            "/nonexistent",
        ),
        ("paired_models", ["/nonexistent", "--compare", "idm", "--out", "t"], "A:B"),
        ("paired_models", ["/nonexistent", "--compare", "a:b", "--out", "t"], "/nonex"),
        ("bench_qp", ["--horizons", "abc"], "--horizons"),
        ("smc_report", ["/nonexistent", "--out", "t"], "no evaluated SMC run"),
        ("bench_train", ["/nonexistent.json", "--out", "t/x"], "/nonexistent.json"),
    ],
)
def test_a_tool_refuses_bad_input_in_one_line(tmp_path, tool, args, needle):
    done = _tool(tool, *args, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    last = done.stderr.splitlines()[-1]
    assert "error:" in last and needle in last, done.stderr
    assert not [p for p in tmp_path.iterdir()], "a refused tool left files"
