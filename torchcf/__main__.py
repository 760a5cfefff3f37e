"""``torchcf COMMAND ...`` (and ``python -m torchcf COMMAND ...``): one entry to
every command line.

Each command is the module that ``python -m torchcf.<module>`` runs, called with
the rest of the arguments, so ``torchcf train configs/carII.json`` is
``python -m torchcf.train configs/carII.json``: the same options, help, output
and exit codes (:mod:`torchcf.cli`). A command's module is imported only when it
is run, so ``torchcf --help`` answers at once.

``train`` runs the study of a config: training, the test-split evaluation and,
where ``diagnose.run_after_training`` asks, the loop (as ``python -m
torchcf.train`` always has; ``--no-eval`` skips the evaluation).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from .cli import EXIT_USER_ERROR, print_error
from .errors import did_you_mean

#: command -> (the module ``python -m`` runs, one line of help)
COMMANDS = {
    "train": (
        "torchcf.train.__main__",
        "the study of a config: training, evaluation, the loop if configured",
    ),
    "evaluate": ("torchcf.evaluate", "evaluate a trained run on its test split"),
    "diagnose": ("torchcf.diagnose.__main__", "close the loop on a trained run"),
    "crossval": ("torchcf.crossval", "k-fold cross-validation of a config"),
    "data": ("torchcf.data.__main__", "extract pairs from raw trajectory files"),
    "config": ("torchcf.config.__main__", "check a config, print its schema"),
    "posterior": (
        "torchcf.posterior.__main__",
        "a run's parameters and shares, as tables",
    ),
    "sumo": ("torchcf.sumo.__main__", "the learned hybrid in Eclipse SUMO"),
    "demo": ("torchcf.demo", "a small end-to-end example"),
}


def usage() -> str:
    """The command list ``torchcf --help`` prints."""
    width = max(map(len, COMMANDS))
    lines = [
        "usage: torchcf COMMAND [ARGS ...]   (torchcf COMMAND --help for its options)",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
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
    if name not in COMMANDS:
        hint = did_you_mean(name, COMMANDS)
        print_error(f"unknown command {name!r}{hint}; commands: {', '.join(COMMANDS)}")
        return EXIT_USER_ERROR
    module = importlib.import_module(COMMANDS[name][0])
    return int(module.main(rest))


if __name__ == "__main__":
    sys.exit(main())
