"""``python -m torchcf.sumo export RUN --out DIR`` and ``python -m torchcf.sumo
verify RUN``: the learned hybrid in Eclipse SUMO.

The command is :mod:`torchcf.cli.sumo` (``torchcf sumo``): its options, output
and exit codes; this module runs it under its ``python -m`` name.
"""

from __future__ import annotations

from ..cli.sumo import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
