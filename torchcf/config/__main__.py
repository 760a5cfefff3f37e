"""``python -m torchcf.config``: validate a run configuration, or print the schema.

The command is :mod:`torchcf.cli.config` (``torchcf config``): its options,
output and exit codes; this module runs it under its ``python -m`` name. It
lives apart from the schema (:mod:`torchcf.config.schema`) so that ``import
torchcf`` may load the schema without ``python -m torchcf.config`` then
running a module already imported.
"""

from __future__ import annotations

from ..cli.config import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
