"""``torchcf demo``: each model's prior particles
simulated on CAR MODEL II training pairs, as a table.

    torchcf demo [--particles 200000] [--dataset NAME] [--data-root DIR]

Prints :func:`torchcf.study.demo.prior_rollouts`: per model the best and median score,
the invalid fraction and the throughput.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 bad arguments or data that cannot
be loaded (one line on stderr); 130 interrupted.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import torch

from ..data import load_pairs
from ..study.demo import prior_rollouts
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    count,
    natural,
    run_main,
)
from ..system.process import tune_malloc


def build_parser() -> argparse.ArgumentParser:
    """``torchcf demo``'s parser."""
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf demo",
        description="A simulation demo: each model's prior particles on CAR MODEL "
        "II training pairs.",
    )
    parser.add_argument("--particles", type=count, default=200_000)
    parser.add_argument("--dataset", default="car-model-2")
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--seed", type=natural, default=0)
    parser.add_argument("--threads", type=count, default=None)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf demo``.

    Returns:
        0 done; 2 bad arguments or data; 130 interrupted.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.particles <= 0:
        parser.error(f"--particles must be positive, got {args.particles}")
    if args.threads:
        torch.set_num_threads(args.threads)
    tune_malloc()
    return run_main(lambda: _demo(args))


def _demo(args: argparse.Namespace) -> int:
    """Load the pairs, simulate and print the table (module docstring)."""
    pairs = load_pairs(args.dataset, split="train", data_root=args.data_root)
    print(
        f"{pairs.name} train: {pairs.n_pairs} pairs x {pairs.n_steps} steps "
        f"(dt {pairs.dt} s); {args.particles} particles per model, paired layout"
    )
    print(f"{'model':6s} {'best':>8s} {'median':>8s} {'invalid':>8s} {'steps/s':>10s}")
    for row in prior_rollouts(pairs, args.particles, args.seed):
        print(
            f"{row.model:6s} {row.best:8.3f} {row.median:8.3f} "
            f"{row.invalid:8.3%} {row.steps_per_second:10.3g}"
        )
    return 0
