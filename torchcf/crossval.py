"""k-fold cross-validation: ``python -m torchcf.crossval CONFIG [--folds 3]``.

Trains and evaluates one run per fold (``data.split = "kfold"``, ``data.fold = i``,
pairs partitioned by ``data.split_seed``) into ``OUT/fold<i>/``, then aggregates the
folds' metrics by the mean, as the paper does (SPEC section 6), into
``OUT/metrics.json`` and ``OUT/report/table.md``. Each fold is an ordinary run
directory: an interrupted cross-validation continues with ``--resume`` (finished
folds are kept, the unfinished one resumes from its checkpoint).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .config import ConfigError, TrainConfig, load_config
from .evaluation.report import metrics_table
from .posterior import atomic_write_text, json_safe
from .train import USER_ERRORS, train

METRIC_KEYS = ("e_p", "e_v", "e_a", "min", "beta_ws", "ws", "sinkhorn")


def fold_config(cfg: TrainConfig, folds: int, fold: int) -> TrainConfig:
    """``cfg`` for fold ``fold`` of ``folds``."""
    data = cfg.data.model_copy(update={"split": "kfold", "folds": folds, "fold": fold})
    return cfg.model_copy(update={"data": data})


def aggregate(fold_metrics: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Mean over folds of every metric of every entry (models and "hybrid").

    An entry missing from a fold, or a non-finite value in any fold, makes that
    mean non-finite (reported, never dropped); ``folds_finite`` counts the folds
    that contributed finite values.
    """
    entries = [k for k, v in fold_metrics[0].items() if isinstance(v, dict)]
    result: dict[str, Any] = {"folds": len(fold_metrics)}
    for entry in entries:
        means: dict[str, Any] = {}
        for key in METRIC_KEYS:
            values = [_number(m.get(entry, {}).get(key)) for m in fold_metrics]
            finite = [v for v in values if math.isfinite(v)]
            means[key] = sum(values) / len(values)
            means[f"{key}_folds_finite"] = len(finite)
        result[entry] = means
    return result


def _number(value: Any) -> float:
    if value is None:
        return math.nan
    if isinstance(value, str):  # "inf" / "nan" in metrics.json
        return float(value)
    return float(value)


def crossval(
    cfg: TrainConfig, out: str | Path, *, folds: int, resume: bool = False
) -> dict[str, Any]:
    """Run every fold and aggregate; returns the aggregated metrics."""
    out = Path(out)
    fold_metrics = []
    for fold in range(folds):
        fold_dir = out / f"fold{fold}"
        fold_cfg = fold_config(cfg, folds, fold)
        if not (fold_dir / "metrics.json").exists():
            started = (fold_dir / "checkpoint.pt").exists()
            train(fold_cfg, fold_dir, resume=resume and started)
        fold_metrics.append(json.loads((fold_dir / "metrics.json").read_text()))
    result = aggregate(fold_metrics)
    atomic_write_text(
        out / "metrics.json", json.dumps(json_safe(result), indent=2) + "\n"
    )
    entries = [k for k, v in result.items() if isinstance(v, dict)]
    report = out / "report"
    report.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        report / "table.md",
        f"# {folds}-fold cross-validation (mean over folds)\n\n"
        + metrics_table({e: result[e] for e in entries}, entries)
        + "\n",
    )
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m torchcf.crossval",
        description="k-fold cross-validation: one training run per fold, metrics "
        "averaged over folds.",
    )
    parser.add_argument("config")
    parser.add_argument("--folds", type=int, default=None, help="default data.folds")
    parser.add_argument("--out", default=None)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--resume", action="store_true")
    args = parser.parse_args(argv)
    try:
        cfg = load_config(args.config, args.overrides)
        folds = args.folds if args.folds is not None else cfg.data.folds
        if folds < 2:
            raise ConfigError(f"--folds: need at least 2, got {folds}")
        out = Path(args.out) if args.out is not None else Path(f"{cfg.output}-cv")
        result = crossval(cfg, out, folds=folds, resume=args.resume)
    except USER_ERRORS as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: continue with --resume", file=sys.stderr)
        return 130
    hybrid = result["hybrid"]
    print(
        f"{folds}-fold mean, hybrid: WS {hybrid['ws']:.3f}, 0.15-WS "
        f"{hybrid['beta_ws']:.3f}, min {hybrid['min']:.3f}"
    )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
