"""``python -m torchcf.train CONFIG``: the study of a config, alone or under torchrun.

    python -m torchcf.train configs/carII.json
    python -m torchcf.train configs/smoke.json --set abc.n_particles=50000
    python -m torchcf.train configs/carII.json --resume      # after a crash or kill -9
    torchrun --standalone --nproc-per-node 4 -m torchcf.train configs/carII.json

Runs :func:`torchcf.pipeline.run_study` (training, then the test-split evaluation
unless ``--no-eval``, then the diagnosis loop if ``diagnose.run_after_training``)
and prints the shares and the hybrid's test metrics.

Exit codes (:mod:`torchcf.cli`): 0 done; 2 bad config, data, arguments or output
directory, a corrupted checkpoint, or an output that cannot be written (one line
on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..abc.distributed import SINGLE, Group, init_from_env
from ..cli import DefaultsHelpFormatter, add_overrides, one_line, run_main
from ..config import TrainConfig, load_config
from ..pipeline import run_study
from ..rundir import RunDir


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m torchcf.train``, alone or under ``torchrun``: the study
    (training, evaluation, and the loop if configured; :mod:`torchcf.pipeline`).

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.train",
        formatter_class=DefaultsHelpFormatter,
        description="ABC rejection and hybrid model selection on car-following data.",
        epilog=(
            "Distributed: torchrun --standalone --nproc-per-node K -m torchcf.train "
            "CONFIG (README, 'Distributed runs')."
        ),
    )
    parser.add_argument(
        "config", nargs="?", help="JSON config (see configs/ and --schema)"
    )
    parser.add_argument(
        "--schema",
        action="store_true",
        help="print the JSON schema of a config (every field) and exit",
    )
    parser.add_argument("--out", default=None, help="output directory")
    add_overrides(parser, "KEY=JSON", "abc.n_particles=200000")
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in the output directory"
    )
    parser.add_argument(
        "--no-eval",
        action="store_true",
        help="skip the test-split evaluation (python -m torchcf.evaluate DIR later)",
    )
    args = parser.parse_args(argv)
    if args.schema:
        print(json.dumps(TrainConfig.model_json_schema(), indent=2))
        return 0
    if args.config is None:
        parser.error("give a CONFIG file (or --schema)")
    group = SINGLE

    def body() -> int:
        nonlocal group
        cfg = load_config(args.config, args.overrides)
        out = Path(args.out) if args.out is not None else Path(cfg.output)
        group = init_from_env(cfg.device)
        done = args.resume and group.is_main and RunDir(out).is_evaluated()
        summary = run_study(
            cfg, out, resume=args.resume, evaluate=not args.no_eval, group=group
        )
        if group.is_main:
            if done:
                print(
                    f"{out} is finished (trained and evaluated): nothing to do "
                    "(delete its metrics.json to evaluate it again)"
                )
            _print_result(
                summary, RunDir(out), evaluated=not args.no_eval, wrote=not done
            )
        return 0

    try:
        return run_main(
            body,
            report=lambda error: _report(error, group),
            interrupted="interrupted: continue with --resume"
            if int(os.environ.get("RANK", "0")) == 0
            else "",
        )
    finally:
        group.close()


def _print_result(
    summary: dict[str, Any], run: RunDir, evaluated: bool, wrote: bool = True
) -> None:
    """The shares, and the hybrid's test metrics when the run was evaluated;
    ``wrote``: this command wrote the run (not so for a finished run resumed)."""
    width = max(len(name) for name in summary["shares"])
    print(f"hybrid shares ({summary['dataset']}, N = {summary['top_n']}):")
    for name, share in summary["shares"].items():
        seconds = summary["per_model"][name]["seconds"]
        print(f"  {name:<{width}}  {share:6.1%}   ({seconds:.1f} s)")
    if "smc" in summary:
        evidence = summary["smc"]["evidence_shares"]
        shown = ", ".join(f"{m} {v:.1%}" for m, v in evidence.items() if v >= 0.0005)
        print(f"evidence shares (prior mass within the hybrid's thresholds): {shown}")
    if evaluated and run.is_evaluated():
        metrics = run.read_metrics()
        hybrid = {k: _fmt(v) for k, v in metrics["hybrid"].items()}
        print(
            f"test split ({metrics['n_test']} pairs), hybrid: WS {hybrid['ws']}, "
            f"0.15-WS {hybrid['beta_ws']}, minimum distance {hybrid['min']}"
        )
    if wrote:
        print(f"wrote {run.path}")


def _report(error: BaseException, group: Group) -> None:
    """``error: <one line>`` on stderr; an error rank 0 already reports is left to
    it, and another rank's own error names the rank."""
    if getattr(error, "from_main", False):
        return
    rank = int(os.environ.get("RANK", "0")) if group is SINGLE else group.rank
    where = f"rank {rank}: " if rank else ""
    print(f"error: {where}{one_line(error)}", file=sys.stderr)


def _fmt(value: Any) -> str:
    """A metric for the console: 3 decimals, or as stored ("inf")."""
    return f"{value:.3f}" if isinstance(value, int | float) else str(value)


if __name__ == "__main__":
    raise SystemExit(main())
