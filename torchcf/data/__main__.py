"""``python -m torchcf.data extract``: raw trajectories to a six-CSV pair folder.

The command is :mod:`torchcf.cli.data` (``torchcf data``): its options, output
and exit codes; this module runs it under its ``python -m`` name.
"""

from __future__ import annotations

from ..cli.data import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
