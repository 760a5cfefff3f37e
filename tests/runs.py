"""Tiny runs for the command-line tests: a six-CSV data folder and a config; and
small records of a run's files (:func:`run_summary`, :func:`evaluation`) for the
tests that write a run directory without training or evaluating it.

The data are synthetic (``tests.conftest.synthetic_pairs``), so the tests that use
them need neither ``TORCHCF_DATA`` nor the network, and they are small enough that
a whole run (two models, a few thousand particles, evaluation) takes seconds.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from tests.conftest import synthetic_pairs
from torchcf.data.reader import FILES
from torchcf.runs.metrics import (
    BootstrapSettings,
    Evaluation,
    SetEvaluation,
    SetMetrics,
)
from torchcf.runs.summary import ModelResult, Pairwise, RunSummary, Versions

REPO = Path(__file__).resolve().parents[1]


def write_data(folder: Path, n_pairs: int = 8, n_steps: int = 120) -> Path:
    """Write a synthetic pair set as six CSV files plus ``meta.json`` (dt = 0.1 s).

    Returns:
        ``folder`` (created).
    """
    folder.mkdir(parents=True, exist_ok=True)
    pairs = synthetic_pairs(n_pairs=n_pairs, n_steps=n_steps, seed=7)
    for field, name in FILES.items():
        values = getattr(pairs, field).numpy()  # (T, N)
        np.savetxt(folder / name, values, delimiter=",", fmt="%.17g")
    (folder / "meta.json").write_text(json.dumps({"dt": 0.1, "units": "m"}))
    return folder


def write_config(
    path: Path, data: Path, *, abc: dict[str, Any] | None = None, **top: Any
) -> Path:
    """A run config on the folder ``data`` (k-fold split: 3 folds, fold 0).

    Args:
        path: where to write the JSON.
        data: a folder from :func:`write_data`.
        abc: overrides of the ``abc`` section.
        top: overrides of top-level keys.
    """
    settings = {
        "n_particles": 3000,
        "chunk_size": 500,
        "top_n": 3,
        "sensitivity_n": [3],
        "seed": 2,
        "checkpoint_every": 1000.0,
    }
    settings.update(abc or {})
    raw = {
        "data": {"path": str(data), "split": "kfold", "folds": 3, "fold": 0},
        "models": ["idm", "llcs"],
        "abc": settings,
        "compile": "off",
        "threads": 1,
        **top,
    }
    path.write_text(json.dumps(raw))
    return path


def run_module(
    module: str, *args: str, env: dict[str, str] | None = None, timeout: float = 300
) -> subprocess.CompletedProcess[str]:
    """``python -m module args`` from the repository root, output captured."""
    return subprocess.run(
        [sys.executable, "-m", module, *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        env={**os.environ, **(env or {})},
        timeout=timeout,
    )


def torchrun_train(*args: str) -> subprocess.CompletedProcess[str]:
    """``torchrun --standalone --nproc-per-node 2 -m torchcf train args``, one
    thread per process, output captured."""
    return run_module(
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "torchcf",
        "train",
        *args,
        env={"OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"},
    )


def tool_module(name: str) -> Iterator[ModuleType]:
    """``tools/<name>.py`` imported as a module for a test (a generator for a
    fixture: the module is dropped from ``sys.modules`` afterwards)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(spec.name, None)


def exit_code(main, argv: list[str]) -> int:
    """A command's exit code for ``argv``: returned by ``main``, or raised by
    its parser (a usage error is ``SystemExit(2)``, one line on stderr)."""
    try:
        return int(main(argv))
    except SystemExit as stop:
        return int(stop.code)


# ------------------------------------------------------ records of a run's files
def run_summary(
    models: tuple[str, ...] = ("idm", "llcs"), **changes: Any
) -> RunSummary:
    """A training's summary of ``models`` (shares 0.6 / 0.4 for two), without
    a training; ``changes``: fields to set (``config_hash`` of the run's config
    where :meth:`~torchcf.runs.directory.RunDir.load_run` checks it)."""
    shares = {m: round(1.0 / len(models), 6) for m in models}
    if len(models) == 2:
        shares = dict(zip(models, (0.6, 0.4), strict=True))
    record = ModelResult(
        particles=100,
        invalid=0,
        invalid_rate=0.0,
        implausible=0,
        seconds=0.5,
        particles_per_s=200.0,
        best_score=0.25,
        threshold=0.5,
        threshold_max=0.75,
        thresholds=(0.5, 0.5),
        pairs_short_of_n=0,
    )
    fields = {
        "dataset": "synthetic",
        "layout": "paired",
        "selection": "per_pair",
        "top_n": 2,
        "n_particles": 100,
        "n_train": 2,
        "n_test": 1,
        "train_pair_ids": (0, 1),
        "test_pair_ids": (2,),
        "models": tuple(models),
        "shares": shares,
        "hybrid_size": 4,
        "pairwise": Pairwise(
            models=tuple(models),
            table=tuple(
                tuple(1.0 if i == j else 0.5 for j in range(len(models)))
                for i in range(len(models))
            ),
        ),
        "sensitivity": {2: dict(shares)},
        "per_model": dict.fromkeys(models, record),
        "seconds_total": 1.0,
        "seconds_wall_this_process": 1.5,
        "processes": 1,
        "config_hash": "0123456789abcdef",
        "versions": Versions.current(),
        "method": "rejection",
    }
    return RunSummary(**{**fields, **changes})


def set_metrics(**changes: Any) -> SetMetrics:
    """One learned set's metrics (WS 1.5, beta-WS infinite, minimum 0.25)."""
    fields = {
        "e_p": 1.0,
        "e_v": 0.1,
        "e_a": 0.01,
        "valid_cells": 6,
        "invalid_cells": 0,
        "min": 0.25,
        "beta_ws": math.inf,
        "ws": 1.5,
        "sinkhorn": 1.6,
        "sinkhorn_gap": 0.1,
        "sinkhorn_iterations": 12,
        "sinkhorn_converged": True,
        "sinkhorn_marginal_error": 1e-9,
        "n_particles": 6,
        "n_test": 3,
        "ws_valid": 1.5,
        "beta_ws_valid": 1.25,
        "particles_never_valid": 0,
    }
    return SetMetrics(**{**fields, **changes})


def evaluation(sets: dict[str, SetMetrics] | None = None, **changes: Any) -> Evaluation:
    """A run's evaluation on 3 test pairs, without one: ``sets`` (learned set ->
    its metrics; default the hybrid alone, :func:`set_metrics`), no
    uncertainty; ``changes``: fields to set."""
    sets = {"hybrid": set_metrics()} if sets is None else sets
    fields = {
        "dataset": "synthetic",
        "n_test": 3,
        "test_pair_ids": (5, 6, 7),
        "beta": 0.15,
        "sinkhorn_reg": 0.05,
        "sinkhorn_max_iter": 1000,
        "bootstrap": BootstrapSettings(
            unit="test pair",
            resamples=0,
            resamples_transport=0,
            transport_metrics=("beta_ws", "ws"),
            level=0.9,
            seed=0,
            method="percentile",
        ),
        "coverage_levels": (0.5, 0.9),
        "sets": {name: SetEvaluation(m) for name, m in sets.items()},
        "hybrid_minus": {},
        "shares": {},
        "hybrid_min_by_pair": (0.25, None, 0.5),
        "seconds": 1.25,
    }
    return Evaluation(**{**fields, **changes})
