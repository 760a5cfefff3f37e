"""k-fold cross-validation (the command line ``torchcf crossval CONFIG [--folds 3]``:
:mod:`torchcf.cli.crossval`).

Trains and evaluates one run per fold (``data.split = "kfold"``, ``data.fold = i``,
pairs partitioned by ``data.split_seed``; :func:`torchcf.study.pipeline.run_study`, the
loop included with ``diagnose.run_after_training``) into ``OUT/fold<i>/``, then
aggregates the folds' metrics by the mean, as the paper does (SPEC section 6),
into ``OUT/report/table.md`` and, last, ``OUT/metrics.json``. Each fold is an
ordinary run directory: an interrupted cross-validation continues with
``--resume`` (finished folds are kept, the unfinished one resumes from its
checkpoint). The layout is :mod:`torchcf.runs.directory`'s; the result, and
``OUT/metrics.json``, a :class:`~torchcf.runs.metrics.CrossvalResult`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from ..config import TrainConfig
from ..evaluation.report import metrics_table
from ..runs.directory import RunDir
from ..runs.metrics import CrossvalResult, Evaluation, FoldMeans
from ..system.errors import first_names
from ..system.files import RunFileError, atomic_write_text, ensure_directory
from .pipeline import run_study

#: The metrics averaged over the folds (those of
#: :class:`~torchcf.runs.metrics.FoldMeans`, each with its ``_folds_finite``).
METRIC_KEYS = ("e_p", "e_v", "e_a", "min", "beta_ws", "ws", "sinkhorn")


def fold_config(cfg: TrainConfig, folds: int, fold: int) -> TrainConfig:
    """``cfg`` for fold ``fold`` of ``folds``.

    Examples:
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.study.crossval import fold_config
        >>> cfg = fold_config(TrainConfig(data={"path": "demo"}), folds=3, fold=1)
        >>> cfg.data.split, cfg.data.folds, cfg.data.fold
        ('kfold', 3, 1)
    """
    data = cfg.data.model_copy(update={"split": "kfold", "folds": folds, "fold": fold})
    return cfg.model_copy(update={"data": data})


def aggregate(evaluations: Sequence[Evaluation]) -> CrossvalResult:
    """Mean over folds of every metric of every learned set (models and
    "hybrid").

    Args:
        evaluations: each fold's evaluation (its ``metrics.json``).

    A set missing from a fold, or a non-finite value in any fold, makes that
    mean non-finite (reported, never dropped); ``folds_finite`` counts the folds
    that contributed finite values.

    Examples:
        >>> from dataclasses import fields
        >>> from types import SimpleNamespace
        >>> from torchcf.runs.metrics import SetEvaluation, SetMetrics
        >>> def fold(value):  # a fold's evaluation (its sets are what is read)
        ...     metrics = SetMetrics(**{f.name: value for f in fields(SetMetrics)})
        ...     return SimpleNamespace(sets={"hybrid": SetEvaluation(metrics)})
        >>> result = aggregate([fold(1.0), fold(2.0), fold(float("inf"))])
        >>> hybrid = result.entries["hybrid"]  # a non-finite fold is reported
        >>> hybrid.ws, hybrid.ws_folds_finite
        (inf, 2)
    """
    result = {}
    for entry in evaluations[0].sets:
        means: dict[str, float | int] = {}
        for key in METRIC_KEYS:
            values = [_value(evaluation, entry, key) for evaluation in evaluations]
            finite = [v for v in values if math.isfinite(v)]
            means[key] = sum(values) / len(values)
            means[f"{key}_folds_finite"] = len(finite)
        result[entry] = FoldMeans(**means)
    return CrossvalResult(folds=len(evaluations), entries=result)


def _value(evaluation: Evaluation, entry: str, key: str) -> float:
    """A set's metric in one fold (NaN: the fold has no such set)."""
    found = evaluation.sets.get(entry)
    return math.nan if found is None else float(getattr(found.metrics, key))


def _check_folder(out: RunDir, resume: bool) -> None:
    """A cross-validation's folder: new, empty, or an earlier one's (``fold<i>/``,
    its report and metrics); never a run's or someone else's.

    Raises:
        RunFileError: ``out`` holds a run, other files, or (with ``resume``)
            nothing to resume.
    """
    path = out.path
    if resume and not any(path.glob("fold*")):
        raise RunFileError(f"{path}: no cross-validation to resume (no fold<i>/)")
    if out.config_json.exists() or out.holds_run():
        raise RunFileError(
            f"{path} holds a run, not a cross-validation: choose another --out"
        )
    if path.is_dir():
        own = {"report", "metrics.json"}
        others = sorted(
            p.name
            for p in path.iterdir()
            if not (p.name.startswith((".", "fold")) or p.name in own)
        )
        if others:
            raise RunFileError(
                f"{path} holds files that are not a cross-validation's "
                f"({first_names(others)}): choose an empty or a new --out"
            )


def crossval(
    cfg: TrainConfig, out: str | Path | RunDir, *, folds: int, resume: bool = False
) -> CrossvalResult:
    """Run every fold and aggregate; returns the aggregated metrics (also in
    ``OUT/metrics.json``).

    Raises:
        RunFileError: a fold's files cannot be read (a corrupted metrics.json),
            or an output cannot be written.
        ConfigError, DataError, ...: as the training of a fold raises them.

    Examples:
        >>> import tempfile
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.data.writer import write_six_csv
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(synthetic_pairs(get_model("idm"), idm, 4, 60), folder)
        ...     cfg = TrainConfig(data={"path": folder, "dt": 0.1}, models=["idm"],
        ...                       abc={"n_particles": 600, "sensitivity_n": [5]},
        ...                       eval={"bootstrap": 0, "bootstrap_transport": 0},
        ...                       plausibility={"report": False})
        ...     result = crossval(cfg, f"{folder}/cv", folds=2)
        >>> result.folds, list(result.entries)
        (2, ['idm', 'hybrid'])
    """
    out = RunDir(out)
    _check_folder(out, resume)
    out.probe()  # a full disk or a missing permission fails before any fold
    out.discard_metrics()  # an earlier mean must not pass for this one's
    fold_metrics = []
    for fold in range(folds):
        fold_dir = out.fold(fold)
        if not fold_dir.is_evaluated():
            started = fold_dir.has_checkpoint()
            run_study(
                fold_config(cfg, folds, fold), fold_dir, resume=resume and started
            )
        fold_metrics.append(fold_dir.read_metrics())
    result = aggregate(fold_metrics)
    rows = {name: means.to_json() for name, means in result.entries.items()}
    report = ensure_directory(out.report_dir, "report directory")
    atomic_write_text(
        report / "table.md",
        f"# {folds}-fold cross-validation (mean over folds)\n\n"
        + metrics_table(rows, list(rows))
        + "\n",
    )
    # last: its presence says the cross-validation ended
    out.write_metrics(result)
    return result
