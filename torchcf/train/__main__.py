"""``python -m torchcf.train CONFIG``: ``torchcf train`` (the study of a config:
training, evaluation, the loop if configured), alone or under torchrun.

    python -m torchcf.train configs/carII.json
    python -m torchcf.train configs/smoke.json --set abc.n_particles=50000
    python -m torchcf.train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

The command is :mod:`torchcf.cli.train` (its options, output and exit codes).

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 bad config, data, arguments or
output directory, a corrupted checkpoint, or an output that cannot be written
(one line on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

from collections.abc import Sequence

from ..cli import train

#: The name this command has here.
PROG = "python -m torchcf.train"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torchcf.train``: :func:`torchcf.cli.train.main` named so."""
    return train.main(argv, prog=PROG)


if __name__ == "__main__":
    raise SystemExit(main())
