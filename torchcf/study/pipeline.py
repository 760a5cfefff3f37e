"""The study, in one place: train -> evaluate -> close the loop.

Each stage is a library function that does its own work only:
:func:`torchcf.train.train` writes the learned set, :func:`torchcf.evaluation.evaluate.
evaluate_run` the test-split metrics, :mod:`torchcf.diagnose.loop` the diagnosis
(:func:`~torchcf.diagnose.loop.plan_loop` up to the choice of effects,
:func:`~torchcf.diagnose.loop.finish_loop` after the re-calibration). This module
chains them; the command lines (``torchcf train``, ``crossval``,
``diagnose``) call it, and nothing below it runs another stage.

The run directory (:class:`~torchcf.runs.directory.RunDir`) is held and the
pairs are loaded once (on rank 0, after the output directory has been checked),
and both are handed to every stage.

:func:`train_and_evaluate` and :func:`run_study` return a :class:`StudyResult`:
the training summary (:class:`~torchcf.runs.summary.RunSummary`) and what the
call did (evaluated, closed the loop); callers read its attributes
(``result.summary.shares``, ``result.summary.smc``).
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

from torch import Tensor

from ..abc.distributed import SINGLE, Group
from ..calibration.of_config import setup_of
from ..config import TrainConfig, config_hash, load_split
from ..data import PairSet
from ..data.registry import notes_deferred
from ..diagnose.loop import finish_loop, plan_loop, run_recalibration
from ..diagnose.report.outcome import LoopResult
from ..evaluation.evaluate import evaluate_run
from ..runs.directory import RunDir
from ..runs.summary import RunSummary
from ..traffic.configured import plausibility_screen
from ..train import check_setup, open_run, run_device, train


@dataclass(frozen=True)
class StudyResult:
    """What a study of a config left in its run directory.

    Attributes:
        run: the run directory.
        summary: the training summary (``summary.json``), on every rank.
        evaluated: this call evaluated the run on the test pairs (rank 0; a
            finished run resumed is not evaluated again).
        loop: the loop's result (``loop.json``) when this call closed the loop
            (rank 0, ``diagnose.run_after_training``), else None.
        skipped: why the evaluation (and the loop) asked for did not run, one
            line (the data have no test split: :data:`NO_TEST_SPLIT`), else
            None.

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.study.pipeline import StudyResult
        >>> [f.name for f in fields(StudyResult)]
        ['run', 'summary', 'evaluated', 'loop', 'skipped']
    """

    run: Path
    summary: RunSummary
    evaluated: bool = False
    loop: LoopResult | None = None
    skipped: str | None = None


#: Why a study of data without a test split (``--test-fraction 0``) is not
#: evaluated: the evaluation and the loop score the test pairs.
NO_TEST_SPLIT = (
    "no test split in the data (a test fraction of 0): the run is trained, not "
    "evaluated (the evaluation and the loop need test pairs)"
)


def _checked_pairs(
    cfg: TrainConfig, run: RunDir, resume: bool, group: Group
) -> tuple[PairSet, PairSet | None]:
    """The config's ``(train, test)`` pairs, read on rank 0 once the output
    directory is known to be usable (fail fast: :func:`torchcf.train.open_run`;
    training checks it again, cheaply, as it must when called alone). Test
    None: the data have no test split, which training does not need."""
    group.on_main(open_run, config_hash(cfg), run.path, resume)
    run_device(cfg.device, group)  # a missing GPU is said before the data are read
    with notes_deferred():  # a budget short for these pairs: the error alone
        pairs = group.on_main(partial(load_split, require_test=False), cfg.data)
        check_setup(setup_of(cfg, pairs[0]), run, resume, group)
    return pairs


def _held(run: RunDir, group: Group) -> AbstractContextManager[Any]:
    """The run directory held by rank 0 for the whole stage
    (:meth:`~torchcf.runs.directory.RunDir.locked`): a second study started into it
    meanwhile is refused instead of mixing its files with this one's."""
    return run.locked() if group.is_main else nullcontext()


def train_and_evaluate(
    cfg: TrainConfig,
    out: str | Path | RunDir,
    *,
    resume: bool = False,
    pairs: tuple[PairSet, PairSet | None] | None = None,
    evaluate: bool = True,
    group: Group = SINGLE,
) -> StudyResult:
    """Train ``cfg`` into ``out``, then (rank 0) evaluate it on the test pairs.

    Args:
        cfg: the run's configuration.
        out: output directory.
        resume: continue the run in ``out``; a run that finished is not trained
            again, and not evaluated again if it was (delete its
            ``metrics.json`` to evaluate it again).
        pairs: ``(train, test)`` instead of loading ``cfg.data``; test None:
            no test split (the evaluation is skipped: ``result.skipped``).
        evaluate: run the test-split evaluation after training.
        group: the processes sharing the training (:mod:`torchcf.abc.distributed`).

    Returns:
        the training summary (``summary.json``) and whether this call evaluated
        the run, on every rank (:class:`StudyResult`).

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> train, test = (synthetic_pairs(get_model("idm"), idm, n_pairs=3, n_steps=60,
        ...                                seed=seed) for seed in (0, 1))
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm", "ovm"],
        ...                   abc={"n_particles": 600, "sensitivity_n": [5]},
        ...                   eval={"bootstrap": 0, "bootstrap_transport": 0},
        ...                   plausibility={"report": False})
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     result = train_and_evaluate(cfg, folder, pairs=(train, test))
        ...     print(result.evaluated, sorted(RunDir(folder).read_metrics().sets))
        True ['hybrid', 'idm', 'ovm']
    """
    run = RunDir(out)
    with _held(run, group):
        if pairs is None:
            pairs = _checked_pairs(cfg, run, resume, group)
        return _train_and_evaluate(cfg, run, resume, pairs, evaluate, group)


def _train_and_evaluate(
    cfg: TrainConfig,
    run: RunDir,
    resume: bool,
    pairs: tuple[PairSet, PairSet | None],
    evaluate: bool,
    group: Group,
) -> StudyResult:
    """:func:`train_and_evaluate` with the run directory held and the pairs
    read."""
    summary = train(cfg, run, resume=resume, pairs=pairs, group=group)
    if evaluate and pairs[1] is None:
        return StudyResult(run.path, summary, skipped=NO_TEST_SPLIT)
    done = resume and run.is_evaluated()
    evaluated = evaluate and group.is_main and not done
    if evaluated:
        evaluate_run(run, pairs=pairs)
    return StudyResult(run.path, summary, evaluated=evaluated)


def run_study(
    cfg: TrainConfig,
    out: str | Path | RunDir,
    *,
    resume: bool = False,
    pairs: tuple[PairSet, PairSet | None] | None = None,
    evaluate: bool = True,
    group: Group = SINGLE,
) -> StudyResult:
    """The study of a config: :func:`train_and_evaluate`, then, with
    ``diagnose.run_after_training`` (and an evaluation), :func:`close_loop` on
    rank 0. Data without a test split are trained only (``result.skipped``).

    Returns:
        the training summary, whether this call evaluated the run and the loop's
        result if it closed the loop (:class:`StudyResult`), on every rank.

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=3, n_steps=60)
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm", "ovm"],
        ...                   abc={"n_particles": 600, "sensitivity_n": [5]},
        ...                   plausibility={"report": False})
        >>> with tempfile.TemporaryDirectory() as folder:  # no test pairs: trained only
        ...     result = run_study(cfg, folder, pairs=(pairs, None))
        >>> result.summary.models, result.evaluated, result.skipped == NO_TEST_SPLIT
        (('idm', 'ovm'), False, True)
    """
    run = RunDir(out)
    with _held(run, group):
        if pairs is None:
            pairs = _checked_pairs(cfg, run, resume, group)
        result = _train_and_evaluate(cfg, run, resume, pairs, evaluate, group)
        looped = resume and run.is_looped()  # a finished loop is not rerun
        tested = result.skipped is None  # the loop scores the test pairs too
        if evaluate and tested and cfg.diagnose.run_after_training and group.is_main:
            if not looped:
                result = replace(result, loop=close_loop(run, pairs=pairs))
    return result


def close_loop(
    run_dir: str | Path | RunDir,
    overrides: Sequence[str] = (),
    *,
    pairs: tuple[PairSet, PairSet] | None = None,
    groups: Tensor | None = None,
    progress: bool = True,
) -> LoopResult:
    """Close the loop on a finished, evaluated run (:mod:`torchcf.diagnose`).

    Diagnose and attribute (:func:`~torchcf.diagnose.loop.plan_loop`); if effects
    are chosen, re-calibrate the run's particles with them into
    ``RUN_DIR/loop/after`` and without them into ``RUN_DIR/loop/reference``
    (:func:`~torchcf.diagnose.loop.run_recalibration`) and evaluate both; then
    report (:func:`~torchcf.diagnose.loop.finish_loop`).

    Args:
        run_dir: a trained and evaluated run directory.
        overrides: ``diagnose.key=VALUE`` items applied to the run's config.
        pairs: ``(train, test)`` instead of loading the run's data.
        groups: (N,) each training pair's driver or run, which cross-fitting
            keeps apart (None: read from the data's index where the run loads
            its data, else each pair its own).
        progress: show progress bars.

    Returns:
        the loop result (also in ``RUN_DIR/loop.json``).

    Examples:
        >>> import inspect
        >>> from torchcf.study.pipeline import close_loop
        >>> list(inspect.signature(close_loop).parameters)
        ['run_dir', 'overrides', 'pairs', 'groups', 'progress']
        >>> loop = close_loop("runs/smoke", ["diagnose.models=all"])  # doctest: +SKIP
    """
    run = RunDir(run_dir)
    with run.locked():
        plan = plan_loop(run, overrides, pairs=pairs, groups=groups, progress=progress)
        if plan.recalibration is not None and not plan.resume_recalibration:
            # the re-calibration trains as the run did: with its plausibility
            # filter, handed down (the loop does not build a battery)
            screen = plausibility_screen(plan.cfg.plausibility, plan.train_pairs)
            run_recalibration(plan, progress=progress, screen=screen)
            for out in (plan.reference_dir, plan.recalibration_dir):
                evaluate_run(
                    out, pairs=(plan.train_pairs, plan.test_pairs), progress=progress
                )
        return finish_loop(plan)


__all__ = [
    "NO_TEST_SPLIT",
    "StudyResult",
    "close_loop",
    "run_study",
    "train_and_evaluate",
]
