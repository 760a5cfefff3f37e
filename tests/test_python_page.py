"""The page "torchcf from Python" (docs/python.md) runs as it stands."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "python.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)


def test_the_page_has_its_sections():
    assert len(_blocks()) >= 6


@pytest.mark.slow  # a calibration, a training run with its evaluation, a prediction
def test_every_block_runs_in_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for number, block in enumerate(_blocks(), start=1):
        try:
            exec(compile(block, f"{PAGE.name}, block {number}", "exec"), namespace)
        except Exception as error:  # the block's number in the failure
            raise AssertionError(f"block {number} failed: {error!r}") from error
