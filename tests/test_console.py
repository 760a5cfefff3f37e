"""``torchcf COMMAND``: one entry to every command line (``torchcf/__main__.py``)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from torchcf.__main__ import COMMANDS, main

ROOT = Path(__file__).resolve().parents[1]


def test_the_console_script_is_this_entry():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert scripts["scripts"]["torchcf"] == "torchcf.__main__:main"


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_is_a_module_with_main(name):
    module = importlib.import_module(COMMANDS[name][0])
    assert callable(module.main)


def test_help_lists_every_command(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert f"  {name} " in out


def test_a_command_gets_the_rest_of_the_arguments(capsys):
    """``torchcf config --help`` is ``python -m torchcf.config --help``."""
    with pytest.raises(SystemExit) as stop:
        main(["config", "--help"])
    assert stop.value.code == 0
    assert "python -m torchcf.config" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "give a command"),
        (["trian"], "unknown command 'trian' (did you mean 'train'?)"),
        (["wobble"], "unknown command 'wobble'; commands: train, evaluate"),
    ],
)
def test_a_missing_or_unknown_command_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and message in err[-1]


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
