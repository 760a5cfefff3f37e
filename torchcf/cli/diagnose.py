"""``torchcf diagnose RUN_DIR [--set diagnose.KEY=VALUE ...]``: close the loop
on a finished, evaluated run (:func:`torchcf.study.pipeline.close_loop`).

    torchcf diagnose runs/carII --set diagnose.n_particles=100000

Exit codes (:mod:`torchcf.system.console`): 0 done; 2 a run that is not trained or
evaluated, a corrupted file, a bad override or a run that cannot be diagnosed
(one line on stderr, no traceback); 130 interrupted (run it again: the
attribution continues after its last finished arm,
``RUN_DIR/loop/attribution.pt``).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from operator import attrgetter

import torch

from ..diagnose.report.markdown import fmt
from ..diagnose.report.outcome import LoopResult
from ..runs.directory import RunDir
from ..study.pipeline import close_loop
from ..system.console import (
    DefaultsHelpFormatter,
    OneLineParser,
    add_overrides,
    count,
    run_main,
)


def _parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        formatter_class=DefaultsHelpFormatter,
        prog="torchcf diagnose",
        description="Close the loop on a finished run: residual diagnosis, effect "
        "attribution, re-calibration; writes RUN_DIR/loop.json and loop.md.",
    )
    parser.add_argument("run_dir", help="a trained and evaluated run directory")
    add_overrides(parser, "diagnose.KEY=VALUE", "diagnose.n_particles=100000")
    parser.add_argument("--threads", type=count, default=None, help="CPU threads")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``torchcf diagnose``.

    Returns:
        0 done; 2 an error of the user's making or of the machine; 130
        interrupted.
    """
    args = _parser().parse_args(argv)
    if args.threads is not None:  # >= 1 by its type
        torch.set_num_threads(args.threads)

    def body() -> int:
        _print_result(close_loop(args.run_dir, args.overrides), args.run_dir)
        return 0

    return run_main(body, interrupted="interrupted: run it again to resume")


def _print_result(result: LoopResult, run_dir: str) -> None:
    selection = result.selection
    found = [m for m in (selection.signatures or [[]])[0] if m.found]
    if found:
        print("residual signatures (fit windows):")
        for mark in found:
            to = ", ".join(mark.points_to) or f"no effect: {mark.family}"
            print(
                f"  {mark.signature:<20} {fmt(mark.mean)} {mark.unit:<6} "
                f"p {mark.p_value:.2g}  -> {to}"
            )
    print(f"forward selection ({result.dataset}; alpha {result.settings.alpha}):")
    for step, rows in enumerate(selection.steps, start=1):
        before = [effect.token for effect in result.chosen[: step - 1]]
        level = selection.levels[step - 1]
        print(
            f" step {step}"
            + (f" (with {' + '.join(before)})" if before else "")
            + f", level {level:.3g}"
        )
        for row in rows:
            mark = "  <- chosen" if row.chosen else ""
            family = (
                f"  family p {row.family_p_value:.4f}"
                if row.family_p_value is not None
                else ""
            )
            print(
                f"  {row.order:>2}. {row.token:<28} gain {row.gain:+7.1%}"
                f"  p {row.p_value:.4f}{family} (level {row.level:.2g}){mark}"
            )
    on_test = result.class_on_test
    if on_test is not None:
        print(
            "new drivers (test pairs, each refitted): the model class with "
            f"{' + '.join(e.token for e in result.chosen)} fits "
            f"{on_test.change:+.1%} per pair, better on {on_test.better} of "
            f"{on_test.pairs} (p {on_test.p_value:.2g})"
        )
    times = result.response_before
    if times is not None:
        after = result.recalibrated.response_after if result.recalibrated else None
        print(
            "response time [s], perturbation (as published for ACCs): the "
            f"hybrid {fmt(times.perturbation)}"
            + (f", after {fmt(after.perturbation)}" if after else "")
            + f"; on the data's braking events ({times.events}): the data "
            f"{fmt(times.event_data)}, the hybrid {fmt(times.event_model)}"
            + (f", after {fmt(after.event_model)}" if after else "")
            + f"; on the recorded pairs: the data {fmt(times.data)}, the hybrid "
            f"{fmt(times.model)}" + (f", after {fmt(after.model)}" if after else "")
        )
    done = result.recalibrated
    for key, label in (("ws", "WS"), ("min", "minimum distance")):
        metric = attrgetter(f"metrics.{key}")
        line = f"test {label}: the run {fmt(metric(result.before))}"
        if done is not None:
            line += f", searched as after {fmt(metric(done.before_same_search))}"
        print(f"{line}, after {fmt(metric(result.after))}")
    print(f"wrote {RunDir(run_dir).loop_json} and loop.md")
