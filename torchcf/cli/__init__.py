"""The command lines: ``torchcf COMMAND [ARGS ...]``, one module per command.

    torchcf --help                        # the commands, one line each
    torchcf study configs/carII.json      # train, evaluate, close the loop
    torchcf train configs/carII.json      # train only
    python -m torchcf.train configs/carII.json   # torchcf study, its old name

- :mod:`torchcf.cli.main`: the dispatcher (the ``torchcf`` console script and
  ``python -m torchcf``);
- one module per command, each holding its parser and ``main(argv) -> int``:
  :mod:`~torchcf.cli.train`, :mod:`~torchcf.cli.study`,
  :mod:`~torchcf.cli.evaluate`, :mod:`~torchcf.cli.diagnose`,
  :mod:`~torchcf.cli.crossval`, :mod:`~torchcf.cli.data`,
  :mod:`~torchcf.cli.config`, :mod:`~torchcf.cli.posterior`,
  :mod:`~torchcf.cli.sumo`, :mod:`~torchcf.cli.demo`. They parse the arguments,
  call the library (:mod:`torchcf.pipeline` and the stages below it) and print;
  ``python -m torchcf.<x>`` runs the same ``main``.

The commands sit at the top of the house: nothing in torchcf imports them. This
package's own ``__init__`` imports none of them; it re-exports the plumbing of
:mod:`torchcf.console` (``from torchcf.cli import run_main`` and the like keep
working), and is layered with it (tests/test_layout.py).

Exit codes (:mod:`torchcf.console`): 0 done; 2 an error of the user's making or
of the machine (one line on stderr); 130 interrupted, 143 terminated.
"""

from ..console import (
    EXIT_INTERRUPTED,
    EXIT_USER_ERROR,
    DefaultsHelpFormatter,
    add_overrides,
    one_line,
    print_error,
    run_main,
)

__all__ = [
    "DefaultsHelpFormatter",
    "EXIT_INTERRUPTED",
    "EXIT_USER_ERROR",
    "add_overrides",
    "one_line",
    "print_error",
    "run_main",
]
