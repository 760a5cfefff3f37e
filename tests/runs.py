"""Tiny runs for the command-line tests: a six-CSV data folder and a config.

The data are synthetic (``tests.conftest.synthetic_pairs``), so the tests that use
them need neither ``TORCHCF_DATA`` nor the network, and they are small enough that
a whole run (two models, a few thousand particles, evaluation) takes seconds.
"""

from __future__ import annotations

import importlib.util
import json
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
    """``torchrun --standalone --nproc-per-node 2 -m torchcf.train args``, one
    thread per process, output captured."""
    return run_module(
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "torchcf.train",
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
