"""``python -m torchcf.diagnose RUN_DIR``: close the loop on a finished,
evaluated run.

The command is :mod:`torchcf.cli.diagnose` (``torchcf diagnose``): its options,
output and exit codes; this module runs it under its ``python -m`` name.
"""

from __future__ import annotations

from ..cli.diagnose import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
