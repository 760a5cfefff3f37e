"""``torchcf study CONFIG``: the study of a config, alone or under torchrun:
training, then the test-split evaluation, then the loop where configured.

    torchcf study configs/carII.json
    torchcf study configs/smoke.json --set abc.n_particles=50000
    torchcf study configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

Runs :func:`torchcf.pipeline.run_study` (training, then the test-split evaluation
unless ``--no-eval``, then the diagnosis loop if ``diagnose.run_after_training``)
and prints the shares and the hybrid's test metrics. ``python -m torchcf.train``
is this command under its old name (:mod:`torchcf.train.__main__`);
``torchcf train`` (:mod:`torchcf.cli.train`) trains only, with the same options.

Exit codes (:mod:`torchcf.console`): 0 done; 2 bad config, data, arguments or
output directory, a corrupted checkpoint, or an output that cannot be written
(one line on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..abc.distributed import Group
from ..config import TrainConfig
from ..pipeline import run_study
from ..rundir import RunDir
from .train import run_config, run_parser

#: The prog of ``torchcf study``.
PROG = "torchcf study"


#: What the study does, in its help.
DESCRIPTION = (
    "The study of a config: ABC rejection and hybrid model selection on "
    "car-following data (training), then the test-split evaluation (unless "
    "--no-eval), then the loop where diagnose.run_after_training asks. "
    "'torchcf train' trains only."
)


def build_parser(prog: str = PROG) -> argparse.ArgumentParser:
    """The study's parser, named ``prog``: its help says which name it has
    (``torchcf study``, or ``python -m torchcf.train``, its old name)."""
    if prog == PROG:
        description = (
            f"{DESCRIPTION} 'python -m torchcf.train' is this command under its "
            "old name."
        )
    else:
        description = f"'{PROG}', kept under its old name. {DESCRIPTION}"
    parser = run_parser(
        prog,
        description,
        "Distributed: torchrun --standalone --nproc-per-node K -m torchcf.train "
        "CONFIG (docs/training.md, 'Distributed runs').",
    )
    parser.add_argument(
        "--no-eval",
        action="store_true",
        help="skip the test-split evaluation (python -m torchcf.evaluate DIR later)",
    )
    return parser


def main(argv: Sequence[str] | None = None, *, prog: str = PROG) -> int:
    """``torchcf study`` (``python -m torchcf.train``), alone or under
    ``torchrun``: training, evaluation, and the loop if configured
    (:mod:`torchcf.pipeline`).

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    parser = build_parser(prog)
    args = parser.parse_args(argv)

    def study(
        cfg: TrainConfig, out: Path, resume: bool, group: Group
    ) -> Mapping[str, Any]:
        evaluate = not args.no_eval
        return run_study(cfg, out, resume=resume, evaluate=evaluate, group=group)

    return run_config(
        parser,
        args,
        study,
        evaluated=not args.no_eval,
        finished=RunDir.is_evaluated,
        finished_note="finished (trained and evaluated): nothing to do "
        "(delete its metrics.json to evaluate it again)",
    )
