"""``torchcf train CONFIG`` (and ``python -m torchcf train CONFIG``): the study of
a config, alone or under torchrun: training, then the test-split evaluation, then
the loop where configured.

    torchcf train configs/carII.json
    torchcf train configs/smoke.json --set abc.n_particles=50000 --out runs/smoke
    torchcf train configs/carII.json --resume      # after a crash or kill -9
    torchcf train configs/carII.json --no-eval     # training only
    torchrun --standalone --nproc-per-node 4 -m torchcf train configs/carII.json

Runs :func:`torchcf.study.pipeline.run_study` (the output directory, data and
budget checked first, then :func:`torchcf.train.train`, then the test-split
evaluation unless ``--no-eval``, then the diagnosis loop if
``diagnose.run_after_training``) and prints the shares and the hybrid's test
metrics. With ``--no-eval`` nothing runs after the training: ``torchcf evaluate
OUT`` and ``torchcf diagnose OUT`` take the run from there. Data without a test
split (a folder extracted with ``--test-fraction 0``, or ``data.raw.test_fraction``
0) are trained on, and a one-line note says the evaluation is skipped.

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 bad config, data, arguments or
output directory, a corrupted checkpoint, or an output that cannot be written
(one line on stderr, no traceback); 130 interrupted (resume with ``--resume``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..abc.distributed import SINGLE, Group, init_from_env
from ..config import TrainConfig, load_config
from ..posterior.tables import piled_at_bounds
from ..runs.directory import RunDir
from ..runs.summary import RunSummary
from ..study.pipeline import StudyResult, run_study
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    add_overrides,
    folder,
    one_line,
    run_main,
)

#: A command's work on a loaded config: (cfg, out, resume, group) -> its result.
Step = Callable[[TrainConfig, Path, bool, Group], StudyResult]


def run_parser(prog: str, description: str, epilog: str) -> argparse.ArgumentParser:
    """The command's options but ``--no-eval``: CONFIG, --schema, --out, --set,
    --resume."""
    parser = OneLineParser(
        prog=prog,
        formatter_class=DefaultsHelpFormatter,
        description=description,
        epilog=epilog,
    )
    parser.add_argument(
        "config", nargs="?", help="JSON config (see configs/ and --schema)"
    )
    parser.add_argument(
        "--schema",
        action="store_true",
        help="print the JSON schema of a config (every field) and exit",
    )
    parser.add_argument("--out", type=folder, default=None, help="output directory")
    add_overrides(parser, "KEY=JSON", "abc.n_particles=200000")
    parser.add_argument(
        "--resume", action="store_true", help="continue the run in the output directory"
    )
    return parser


#: The prog of ``torchcf train``.
PROG = "torchcf train"

#: What the command does, in its help.
DESCRIPTION = (
    "The study of a config: ABC rejection and hybrid model selection on "
    "car-following data (training), then the test-split evaluation, then the "
    "loop where diagnose.run_after_training asks. With --no-eval, training "
    "only: 'torchcf evaluate OUT' evaluates the run later."
)


def build_parser() -> argparse.ArgumentParser:
    """The command's parser."""
    parser = run_parser(
        PROG,
        DESCRIPTION,
        "Distributed: torchrun --standalone --nproc-per-node K -m torchcf train "
        "CONFIG (docs/training.md, 'Distributed runs').",
    )
    parser.add_argument(
        "--no-eval",
        action="store_true",
        help="train only: no test-split evaluation and no loop (torchcf evaluate "
        "OUT later)",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf train``, alone or under ``torchrun`` (``torchrun ... -m
    torchcf train CONFIG``): training, evaluation, and the loop if configured
    (:mod:`torchcf.study.pipeline`); training only with ``--no-eval``.

    Returns:
        0 done; 2 an error of the user's making or of the machine (one line on
        stderr); 130 interrupted.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    evaluate = not args.no_eval

    def study(cfg: TrainConfig, out: Path, resume: bool, group: Group) -> StudyResult:
        return run_study(cfg, out, resume=resume, evaluate=evaluate, group=group)

    if evaluate:
        finished, note = (
            RunDir.is_evaluated,
            (
                "finished (trained and evaluated): nothing to do (delete its "
                "metrics.json to evaluate it again)"
            ),
        )
    else:
        finished, note = (
            RunDir.is_trained,
            ("trained: nothing to do (torchcf evaluate {out} evaluates it)"),
        )
    return run_config(
        parser, args, study, evaluated=evaluate, finished=finished, finished_note=note
    )


def run_config(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    step: Step,
    *,
    evaluated: bool,
    finished: Callable[[RunDir], bool],
    finished_note: str,
) -> int:
    """Run ``step`` on the config of ``args`` (``--schema``: print it instead)
    under the one policy (:func:`torchcf.system.console.run_main`), then print
    the result.

    Args:
        parser: for ``parser.error`` on a missing CONFIG.
        args: the parsed options of :func:`run_parser`.
        step: the work (the study, or its training only).
        evaluated: the step evaluated the run (print its test metrics).
        finished: on ``--resume``, the run needs nothing more (checked before).
        finished_note: then printed as ``OUT is <finished_note>``.

    Returns:
        the exit code.
    """
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
        done = args.resume and group.is_main and finished(RunDir(out))
        result = step(cfg, out, args.resume, group)
        if group.is_main:
            if done:
                print(f"{out} is " + finished_note.format(out=out))
            if result.skipped is not None:  # e.g. no test split to evaluate on
                print(f"note: {result.skipped}")
            print_result(
                result.summary, RunDir(out), evaluated=evaluated, wrote=not done
            )
        return 0

    try:
        return run_main(
            body,
            report=lambda error: report_error(error, group),
            interrupted="interrupted: continue with --resume"
            if int(os.environ.get("RANK", "0")) == 0
            else "",
        )
    finally:
        group.close()


def print_result(
    summary: RunSummary, run: RunDir, evaluated: bool, wrote: bool = True
) -> None:
    """The shares, and the hybrid's test metrics when the run was evaluated;
    ``wrote``: this command wrote the run (not so for a finished run resumed)."""
    width = max(len(name) for name in summary.shares)
    print(f"hybrid shares ({summary.dataset}, N = {summary.top_n}):")
    for name, share in summary.shares.items():
        print(f"  {name:<{width}}  {share:6.1%}   ({_counts(summary, name)})")
    if run.posterior_pt.is_file():
        for piled in piled_at_bounds(run.load_posterior()):
            print(f"  at a prior bound: {piled.sentence()} (see parameters.md)")
    if summary.smc is not None:
        evidence = summary.smc.evidence_shares
        shown = ", ".join(f"{m} {v:.1%}" for m, v in evidence.items() if v >= 0.0005)
        print(f"evidence shares (prior mass within the hybrid's thresholds): {shown}")
    if evaluated and run.is_evaluated():
        evaluation = run.read_metrics()
        hybrid = evaluation.hybrid.metrics
        print(
            f"test split ({evaluation.n_test} pairs), hybrid: WS {_fmt(hybrid.ws)}, "
            f"0.15-WS {_fmt(hybrid.beta_ws)}, minimum distance {_fmt(hybrid.min)} "
            f"({evaluation.seconds:.1f} s)"
        )
    if wrote:
        print(f"wrote {run.path}")


def _counts(summary: RunSummary, name: str) -> str:
    """A model's time and its rollouts' fates (SPEC section 2): invalid, and
    rejected early (stopped once they could not enter a buffer), each as a
    share of the rollouts run (cells, in the full layout)."""
    model = summary.per_model[name]
    cells = model.particles * (1 if summary.layout == "paired" else summary.n_train)
    text = f"{model.seconds:.1f} s, invalid {model.invalid_rate:.1%}"
    if model.stopped:
        text += f", rejected early {model.stopped / max(cells, 1):.0%}"
    return text


def report_error(error: BaseException, group: Group) -> None:
    """``error: <one line>`` on stderr; an error rank 0 already reports is left to
    it, and another rank's own error names the rank."""
    if getattr(error, "from_main", False):
        return
    rank = int(os.environ.get("RANK", "0")) if group is SINGLE else group.rank
    where = f"rank {rank}: " if rank else ""
    print(f"error: {where}{one_line(error)}", file=sys.stderr)


def _fmt(value: Any) -> str:
    """A metric for the console: 3 decimals ("inf", "nan" as such)."""
    return f"{value:.3f}" if isinstance(value, int | float) else str(value)
