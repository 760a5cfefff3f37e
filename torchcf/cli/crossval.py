"""``torchcf crossval CONFIG [--folds 3]``:
k-fold cross-validation of a config.

    torchcf crossval configs/carII.json --folds 3 --out runs/carII-cv
    torchcf crossval configs/carII.json --out runs/carII-cv --resume

Runs :func:`torchcf.study.crossval.crossval` (one study per fold into ``OUT/fold<i>/``,
the folds' metrics averaged into ``OUT/metrics.json``) and prints the hybrid's
mean metrics.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 bad config (fewer than 2 folds
included), data, arguments or output directory, or a corrupted fold (one line
on stderr, no traceback); 130 interrupted (continue with ``--resume``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from ..config import ConfigError, load_config
from ..study.crossval import crossval
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    add_overrides,
    count,
    folder,
    run_main,
)
from ..system.files import no_empty_folder_left


def build_parser() -> argparse.ArgumentParser:
    """``torchcf crossval``'s parser."""
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf crossval",
        description="k-fold cross-validation: one training run per fold, metrics "
        "averaged over folds.",
    )
    parser.add_argument("config")
    parser.add_argument("--folds", type=count, default=None, help="default data.folds")
    parser.add_argument("--out", type=folder, default=None)
    add_overrides(parser, "KEY=VALUE", "abc.n_particles=200000")
    parser.add_argument("--resume", action="store_true")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf crossval``.

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    args = build_parser().parse_args(argv)

    def body() -> int:
        cfg = load_config(args.config, args.overrides)
        folds = args.folds if args.folds is not None else cfg.data.folds
        if folds < 2:
            raise ConfigError(f"--folds: need at least 2, got {folds}")
        out = Path(args.out) if args.out is not None else Path(f"{cfg.output}-cv")
        with no_empty_folder_left(out):
            result = crossval(cfg, out, folds=folds, resume=args.resume)
        hybrid = result.entries["hybrid"]
        print(
            f"{folds}-fold mean, hybrid: WS {hybrid.ws:.3f}, 0.15-WS "
            f"{hybrid.beta_ws:.3f}, min {hybrid.min:.3f}"
        )
        print(f"wrote {out}")
        return 0

    return run_main(body, interrupted="interrupted: continue with --resume")
