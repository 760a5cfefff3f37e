"""``torchcf COMMAND [ARGS ...]`` (and ``python -m torchcf COMMAND ...``): one
entry to every command line.

    torchcf --help
    torchcf train configs/carII.json
    torchcf evaluate runs/carII
    python -m torchcf train configs/carII.json    # the same command
    torchrun --standalone --nproc-per-node 4 -m torchcf train configs/carII.json

Each command is a module of :mod:`torchcf.cli` whose ``main`` gets the rest of
the arguments. These two are the only entries: the console script
``torchcf`` and ``python -m torchcf`` (:mod:`torchcf.__main__`), the same
dispatcher (the same options, help, output and exit codes); no package below
``torchcf`` runs under ``python -m``. A command's module is imported only when
it is run, so ``torchcf --help`` answers at once.

``train`` runs the study of a config (training, the test-split evaluation and,
where ``diagnose.run_after_training`` asks, the loop; ``--no-eval``: training
only).

Exit codes: the command's own; 0 for ``--help``; 2 for a missing or unknown
command (one line on stderr).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from ..system.console import EXIT_USER_ERROR, print_error
from ..system.errors import did_you_mean

#: command -> (its module, one line of help)
COMMANDS = {
    "train": (
        "torchcf.cli.train",
        "the study of a config: train, evaluate, the loop if configured",
    ),
    "evaluate": ("torchcf.cli.evaluate", "evaluate a trained run on its test split"),
    "diagnose": ("torchcf.cli.diagnose", "close the loop on a trained run"),
    "predict": (
        "torchcf.cli.predict",
        "predict pairs from a trained run: population, bands, after a history",
    ),
    "crossval": ("torchcf.cli.crossval", "k-fold cross-validation of a config"),
    "data": ("torchcf.cli.data", "extract pairs from raw trajectory files"),
    "config": ("torchcf.cli.config", "check a config, print its schema"),
    "posterior": ("torchcf.cli.posterior", "a run's parameters and shares, as tables"),
    "sumo": ("torchcf.cli.sumo", "the learned hybrid in Eclipse SUMO"),
    "demo": ("torchcf.cli.demo", "a small end-to-end example"),
}

#: Names that commands had before, and what a user types instead (the error
#: says so; the old name runs nothing).
FORMER = {"study": "the study is 'torchcf train'"}


def usage() -> str:
    """The command list ``torchcf --help`` prints."""
    width = max(map(len, COMMANDS))
    lines = [
        "usage: torchcf COMMAND [ARGS ...]   (torchcf COMMAND --help for its options)",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "python -m torchcf COMMAND runs the same commands."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``argv[0]``'s command with the rest; 0 for ``--help``, 2 for a
    missing or unknown command (one line on stderr)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] in ("-h", "--help"):
        print(usage())
        return 0
    if not args:
        print(usage(), file=sys.stderr)
        print_error("give a command")
        return EXIT_USER_ERROR
    name, rest = args[0], args[1:]
    if name in FORMER:
        print_error(f"unknown command {name!r}: {FORMER[name]}")
        return EXIT_USER_ERROR
    if name not in COMMANDS:
        hint = did_you_mean(name, COMMANDS)
        print_error(f"unknown command {name!r}{hint}; commands: {', '.join(COMMANDS)}")
        return EXIT_USER_ERROR
    module = importlib.import_module(COMMANDS[name][0])
    return int(module.main(rest))
