"""Fixtures for the data tests: the real data (when available) and synthetic CSVs."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from torchcf.data.reader import FILES

SixWriter = Callable[..., Path]


@pytest.fixture
def real_data() -> Path:
    """The folder holding HDV/ and AV/ (``$TORCHCF_DATA``); skips when unset."""
    root = os.environ.get("TORCHCF_DATA")
    if not root:
        pytest.skip("TORCHCF_DATA is not set: no real data to test against")
    return Path(root)


@pytest.fixture(scope="session")
def zalazone() -> Path:
    """The ZalaZONE dynamic-platform campaign (``$TORCHCF_RAW/openacc-zalazone-
    dynamic``); skips when it is not there."""
    root = os.environ.get("TORCHCF_RAW")
    folder = Path(root or "/nonexistent") / "openacc-zalazone-dynamic"
    if not root or not folder.is_dir():
        pytest.skip("TORCHCF_RAW is not set or holds no openacc-zalazone-dynamic/")
    return folder


def six_arrays(n_steps: int = 5, n_pairs: int = 3) -> dict[str, np.ndarray]:
    """A small valid pair set: followers 20 m + 3 m per pair behind the leaders.

    Returns:
        The six (T, N) series by PairSet field name, SI units.
    """
    t = np.arange(n_steps)[:, None] * 0.1  # (T, 1) [s]
    v = 10.0 + np.arange(n_pairs)[None, :]  # (1, N) [m/s]
    x_lead = 100.0 + v * t  # (T, N)
    gap = 20.0 + 3.0 * np.arange(n_pairs)[None, :]  # (1, N)
    zeros = np.zeros((n_steps, n_pairs))
    return {
        "x_lead": x_lead,
        "v_lead": zeros + v,
        "a_lead": zeros,
        "x_follow": x_lead - gap,
        "v_follow": zeros + v,
        "a_follow": zeros + 0.25,
    }


def csv_text(values: np.ndarray) -> str:
    return "".join(",".join(repr(float(x)) for x in row) + "\n" for row in values)


@pytest.fixture
def write_six(tmp_path: Path) -> SixWriter:
    """Write the six CSV files of a synthetic pair set into a folder.

    Call as ``write_six(folder_name="set", arrays=None, text=None, skip=())``:
    ``arrays`` overrides series (by field name), ``text`` replaces a file's whole
    content (by field name), ``skip`` leaves files out. Returns the folder.
    """

    def write(
        folder_name: str = "set",
        arrays: dict[str, np.ndarray] | None = None,
        text: dict[str, str] | None = None,
        skip: tuple[str, ...] = (),
    ) -> Path:
        folder = tmp_path / folder_name
        folder.mkdir(parents=True, exist_ok=True)
        series = six_arrays() | (arrays or {})
        for field, file_name in FILES.items():
            if field in skip:
                continue
            content = (text or {}).get(field)
            if content is None:
                content = csv_text(series[field])
            (folder / file_name).write_text(content, encoding="utf-8")
        return folder

    return write


@pytest.fixture
def make_arrays() -> Callable[..., dict[str, np.ndarray]]:
    """The :func:`six_arrays` factory: ``make_arrays(n_steps=5, n_pairs=3)``."""
    return six_arrays
