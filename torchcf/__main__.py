"""``python -m torchcf COMMAND [ARGS ...]``: the ``torchcf`` console script
(:mod:`torchcf.cli.main`, where the commands are listed), under ``python -m``.

    python -m torchcf --help
    python -m torchcf train configs/carII.json

Exit codes: the command's own; 0 for ``--help``; 2 for a missing or unknown
command.
"""

from __future__ import annotations

import sys

from .cli.main import COMMANDS, main, usage

__all__ = ["COMMANDS", "main", "usage"]

if __name__ == "__main__":
    sys.exit(main())
