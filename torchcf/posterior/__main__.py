"""``python -m torchcf.posterior RUN``: a run's calibrated parameters, and its
shares per group of pairs.

The command is :mod:`torchcf.cli.posterior` (``torchcf posterior``): its options,
output and exit codes; this module runs it under its ``python -m`` name.
"""

from __future__ import annotations

from ..cli.posterior import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
