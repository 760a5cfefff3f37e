"""``torchcf COMMAND``: one entry to every command line (:mod:`torchcf.cli`).

The dispatcher (``torchcf/cli/main.py``), the commands' modules, ``train``
(the study, ``--no-eval`` training only), and the one entry rule: ``torchcf
COMMAND`` and ``python -m torchcf COMMAND``, no ``python -m torchcf.<package>``.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import torchcf.__main__
import torchcf.system.console
from tests.runs import write_config, write_data
from torchcf import cli
from torchcf.cli import train as train_cli
from torchcf.cli.main import COMMANDS, main

ROOT = Path(__file__).resolve().parents[2]

#: The packages that had their own ``python -m torchcf.<package>`` entry.
FORMER_ENTRIES = ["train", "diagnose", "data", "config", "posterior", "sumo"]


def test_the_console_script_is_this_entry():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert scripts["scripts"]["torchcf"] == "torchcf.cli.main:main"


def test_python_dash_m_torchcf_is_the_same_entry():
    assert torchcf.__main__.main is main
    assert torchcf.__main__.COMMANDS is COMMANDS


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_is_a_module_with_main(name):
    module = importlib.import_module(COMMANDS[name][0])
    assert module.__name__ == f"torchcf.cli.{name}"
    assert callable(module.main)


def test_help_lists_every_command(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert f"  {name} " in out


def test_help_lists_train_with_one_line(capsys):
    assert main(["--help"]) == 0
    lines = capsys.readouterr().out.splitlines()
    train = [line for line in lines if line.startswith("  train ")]
    assert len(train) == 1 and "evaluate" in train[0] and "loop" in train[0]
    assert not [line for line in lines if line.startswith("  study ")]


def test_a_command_gets_the_rest_of_the_arguments(capsys):
    """``torchcf config --help`` is the config command's help."""
    with pytest.raises(SystemExit) as stop:
        main(["config", "--help"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.startswith("usage: torchcf config")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "give a command"),
        (["trian"], "unknown command 'trian' (did you mean 'train'?)"),
        (["wobble"], "unknown command 'wobble'; commands: train, evaluate"),
        (["evalute"], "unknown command 'evalute' (did you mean 'evaluate'?)"),
        (["study"], "unknown command 'study': the study is 'torchcf train'"),
    ],
)
def test_a_missing_or_unknown_command_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and message in err[-1]


@pytest.mark.slow  # a command in a subprocess
def test_python_dash_m_torchcf_runs_a_command():
    """As a process: a command's own exit code comes back (its bad input: 2)."""
    done = subprocess.run(
        [sys.executable, "-m", "torchcf", "evaluate", "/nonexistent/run"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2
    assert done.stderr.strip().startswith("error:")
    assert "\n" not in done.stderr.strip()


#: Runs each module of argv[1:] with ``--help`` as ``python -m`` does
#: (:func:`runpy.run_module` as ``__main__``) in one process (torch is imported
#: once) and prints ``<module> <exit code>`` per module, or ``<module>
#: refused`` where Python will not run it (a package without ``__main__``).
RUN_HELPS = """
import contextlib, io, runpy, sys
for module in sys.argv[1:]:
    sys.argv = [module, "--help"]
    with contextlib.redirect_stdout(io.StringIO()) as out:
        try:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
            code = "no exit"
        except SystemExit as stop:
            code = stop.code
        except ImportError as error:
            code = "refused" if "cannot be directly executed" in str(error) else error
    usage = out.getvalue().startswith("usage: ")
    print(module, code if code == "refused" or usage else "no usage")
"""


def test_python_dash_m_runs_torchcf_alone():
    """``python -m torchcf --help`` answers; ``python -m torchcf.train`` and the
    other former package entries are refused by Python itself ("... is a
    package and cannot be directly executed")."""
    former = [f"torchcf.{package}" for package in FORMER_ENTRIES]
    done = subprocess.run(
        [sys.executable, "-c", RUN_HELPS, "torchcf", *former],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    expected = ["torchcf 0"] + [f"{module} refused" for module in former]
    assert done.stdout.splitlines() == expected


def test_only_torchcf_main_is_a_main_module():
    """One entry rule: no ``__main__`` module under a package of torchcf, and
    no module but ``torchcf/__main__.py`` runs as a script (an ``if __name__ ==
    "__main__"`` block)."""
    for package in FORMER_ENTRIES:
        assert importlib.util.find_spec(f"torchcf.{package}.__main__") is None
    scripts = []
    for path in sorted((ROOT / "torchcf").rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            test = node.test if isinstance(node, ast.If) else None
            if (
                isinstance(test, ast.Compare)
                and isinstance(test.left, ast.Name)
                and test.left.id == "__name__"
            ):
                scripts.append(str(path.relative_to(ROOT)))
    assert scripts == ["torchcf/__main__.py"]


def test_train_is_one_command(capsys):
    """``torchcf train`` through the dispatcher (as ``python -m torchcf train``
    and ``torchrun ... -m torchcf train`` run it) is :mod:`torchcf.cli.train`:
    the study, ``--no-eval`` training only."""
    helps = []
    for run in (lambda argv: main(["train", *argv]), train_cli.main):
        with pytest.raises(SystemExit) as stop:
            run(["--help"])
        assert stop.value.code == 0
        helps.append(" ".join(capsys.readouterr().out.split()))
    assert helps[0] == helps[1]
    assert helps[0].startswith("usage: torchcf train")
    assert "then the test-split evaluation" in helps[0] and "--no-eval" in helps[0]
    assert "-m torchcf train CONFIG" in helps[0]  # torchrun's form
    assert "study" not in COMMANDS  # one name, one meaning


def test_the_command_modules_are_reached_through_cli_only():
    """No plumbing through :mod:`torchcf.cli`, no ``main`` left in the
    library modules that had one."""
    assert not hasattr(cli, "run_main")
    for module in ("evaluation.evaluate", "study.crossval", "study.demo"):
        assert not hasattr(importlib.import_module(f"torchcf.{module}"), "main")


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    """A tiny config that asks for the loop after training."""
    root = tmp_path_factory.mktemp("console")
    data = write_data(root / "pairs")
    return write_config(root / "cfg.json", data, diagnose={"run_after_training": True})


def test_train_no_eval_trains_only(config, tmp_path, capsys):
    """No evaluation and no loop, though the config asks for the loop."""
    out = tmp_path / "run"
    assert main(["train", str(config), "--out", str(out), "--no-eval"]) == 0
    assert (out / "summary.json").is_file() and (out / "posterior.pt").is_file()
    assert not (out / "metrics.json").exists()
    assert not (out / "loop.json").exists() and not (out / "loop").exists()
    printed = capsys.readouterr().out
    assert "hybrid shares" in printed and "test split" not in printed
    assert printed.splitlines()[-1] == f"wrote {out}"

    assert main(["train", str(config), "--out", str(out), "--resume", "--no-eval"]) == 0
    assert f"{out} is trained: nothing to do" in capsys.readouterr().out
    assert not (out / "metrics.json").exists()


def test_train_trains_and_evaluates(config, tmp_path, capsys):
    out = tmp_path / "run"
    no_loop = ["--set", "diagnose.run_after_training=false"]  # the slow test's
    assert main(["train", str(config), "--out", str(out), *no_loop]) == 0
    assert (out / "summary.json").is_file() and (out / "metrics.json").is_file()
    assert not (out / "loop.json").exists()
    assert "test split" in capsys.readouterr().out


@pytest.mark.slow
def test_train_closes_the_loop_where_the_config_asks(config, tmp_path, capsys):
    """The whole chain, as ``torchcf train`` runs it (about 20 s)."""
    out = tmp_path / "run"
    assert main(["train", str(config), "--out", str(out)]) == 0
    for name in ("summary.json", "metrics.json", "loop.json"):
        assert (out / name).is_file(), name


@pytest.mark.parametrize(
    ("kind", "good", "bad"),
    [
        (
            "count",
            {"3": 3, "2e5": 200_000, "1": 1},
            ["0", "-3", "1.5", "nan", "x", "inf"],
        ),
        ("natural", {"0": 0, "7": 7, "1e3": 1000}, ["-1", "2.5", "nan", ""]),
        ("positive", {"0.5": 0.5, "1e6": 1e6}, ["0", "-1", "nan", "inf", "-inf", "x"]),
        ("nonnegative", {"0": 0.0, "2.5": 2.5}, ["-0.1", "nan", "inf"]),
        ("finite", {"-3": -3.0, "0": 0.0}, ["nan", "inf", "y"]),
        ("open_fraction", {"0.3": 0.3}, ["0", "1", "1.5", "-0.2", "nan"]),
    ],
)
def test_checked_numeric_options(kind, good, bad):
    """Each checked ``type=`` keeps what it promises and refuses the rest with
    a usage error (argparse's one line and exit code 2, never a traceback)."""
    import argparse

    convert = getattr(torchcf.system.console, kind)
    for text, value in good.items():
        assert convert(text) == value
        assert type(convert(text)) is type(value)
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError, match="expected"):
            convert(text)
    parser = argparse.ArgumentParser(prog="p")
    parser.add_argument("--n", type=convert)
    with pytest.raises(SystemExit) as stop:
        parser.parse_args(["--n", bad[0]])
    assert stop.value.code == 2


def test_a_long_bad_value_is_quoted_short():
    import argparse

    with pytest.raises(argparse.ArgumentTypeError) as error:
        torchcf.system.console.count("9" * 5000 + "x")
    assert len(str(error.value)) < 80


def test_a_bar_in_a_log_file_moves_at_least_every_10_s(monkeypatch):
    """Live on a terminal; in a log or a pipe one line at most every 9 s, so a
    stage's progress never stays still for 10 s without flooding the log."""
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert torchcf.system.console.bar_interval() == 0.1
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    assert (
        torchcf.system.console.bar_interval()
        == torchcf.system.console.LOG_INTERVAL
        < 10.0
    )
