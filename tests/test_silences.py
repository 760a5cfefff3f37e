"""tools/silences.py: the longest stretch without output of a command."""

from __future__ import annotations

import sys

import pytest

from tests.runs import tool_module


@pytest.fixture(scope="module")
def silences():
    yield from tool_module("silences")


def test_the_longest_gap_between_writes_with_what_framed_it(silences):
    code = (
        "import sys, time\n"
        "print('start', flush=True)\n"
        "time.sleep(0.1)\n"
        "sys.stderr.write('bar 10%\\r'); sys.stderr.flush()\n"
        "time.sleep(0.6)\n"
        "sys.stderr.write('bar 100%\\r'); sys.stderr.flush()\n"
        "print('done')\n"
    )
    writes, exit_code = silences.timed_writes([sys.executable, "-c", code], 60.0)
    assert exit_code == 0
    gap = silences.longest_silence(writes)
    assert 0.5 <= gap["seconds"] < 3.0
    assert gap["before"] == "bar 10%" and gap["after"] == "bar 100%"


def test_a_silent_command_is_silent_from_start_to_end(silences):
    writes, _ = silences.timed_writes(
        [sys.executable, "-c", "import time; time.sleep(0.3)"], 60.0
    )
    gap = silences.longest_silence(writes)
    assert gap["from_s"] == 0.0 and gap["seconds"] >= 0.3 and gap["before"] == ""
