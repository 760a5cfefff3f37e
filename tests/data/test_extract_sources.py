"""Extraction from real sources: the paper's NGSIM I-80 pairs written out as an NGSIM
table and read back, and the raw samples of ``../shared/data/raw`` (``TORCHCF_RAW``).
Each test skips when its data are absent; none of the data is in the repository.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from torchcf.data import load_pairs
from torchcf.data.extract import ExtractOptions, extract_pairs
from torchcf.data.formats import read_trajectories
from torchcf.data.formats.ngsim import read_ngsim, write_ngsim
from torchcf.data.pairset import SERIES
from torchcf.data.quality import QualityThresholds

RAW = Path(os.environ.get("TORCHCF_RAW", "/nonexistent"))
PEACHTREE = RAW / "ngsim-peachtree-fragment" / "peachtree_dotexport_first5000rows.csv"
OPENACC = RAW / "openacc"

ALL_OFF = QualityThresholds(
    jump=None,
    speed_mismatch=None,
    max_acceleration=None,
    gap_drift=None,
    standstill_speed=None,
    non_positive_gap=False,
)


@pytest.fixture(scope="module")
def i80_table(tmp_path_factory):
    if not os.environ.get("TORCHCF_DATA"):
        pytest.skip("TORCHCF_DATA not set")
    pairs = load_pairs("ngsim-i80", None, download=False)
    path = tmp_path_factory.mktemp("ngsim") / "trajectories-i80.txt"
    write_ngsim(pairs, path)
    return pairs, read_ngsim(path)


def test_i80_pairs_round_trip_through_an_ngsim_table(i80_table) -> None:
    pairs, table = i80_table
    result = extract_pairs(
        table, ExtractOptions(window=35.0, quality=ALL_OFF, test_fraction=0.0)
    )
    assert result.pairs.n_pairs == pairs.n_pairs == 150
    # write_ngsim gives pair j the follower id 2j + 2
    order = [int(f) // 2 - 1 for f in result.index["follower"]]
    assert sorted(order) == list(range(150))
    for name in SERIES:
        np.testing.assert_array_equal(
            getattr(result.pairs, name).numpy(), getattr(pairs, name).numpy()[:, order]
        )
    assert result.road_frame is True


def test_i80_pairs_through_the_filters(i80_table) -> None:
    """The filters find the position errors the registry reports (9 pairs with a
    front-to-front spacing under 15 ft) and the tracking jumps of I-80."""
    _, table = i80_table
    result = extract_pairs(table, ExtractOptions(window=35.0, test_fraction=0.3))
    assert result.summary["windows_dropped"] == {"non_positive_gap": 14, "jump": 14}
    assert result.pairs.n_pairs == 122
    flagged = {6, 13, 31, 61, 70, 95, 110, 117, 120}
    overlapping = result.dropped.loc[result.dropped["reason"] == "non_positive_gap"]
    assert {int(f) // 2 - 1 for f in overlapping["follower"]} >= flagged


@pytest.mark.skipif(not PEACHTREE.is_file(), reason="TORCHCF_RAW peachtree absent")
def test_peachtree_fragment_extracts_its_one_long_couple() -> None:
    table = read_ngsim(PEACHTREE)
    result = extract_pairs(table, ExtractOptions(window=20.0, test_fraction=0.0))
    assert result.summary["runs"] == 2 and result.summary["vehicles"] == 165
    assert result.pairs.n_pairs == 1
    row = result.index.iloc[0]
    assert (row["follower"], row["leader"]) == ("70", "69")
    assert row["run"].endswith(":1163018600")
    # most followers' leaders lie outside the 64 ft slice
    outside = result.summary["rows_outside_couples"]
    assert outside["the leader not recorded at that time"] > 4000
    # feet converted: a car is 4-6 m long
    assert 4.0 < row["leader_length"] < 6.0


@pytest.mark.skipif(not OPENACC.is_dir(), reason="TORCHCF_RAW openacc absent")
def test_openacc_windows_and_their_drops() -> None:
    table = read_trajectories(OPENACC, "openacc")
    result = extract_pairs(table, ExtractOptions())
    summary = result.summary
    assert summary["runs"] == 4 and summary["vehicles"] == 12
    assert summary["candidate_windows"] == 21
    # Vicolungo's last follower has a 23 m spacing jump in its first window
    # and steps 3.3 m/s off its speed in another, Cherasco's follower an 18 m
    # drift in its first: all dropped and named
    assert summary["windows_dropped"] == {
        "jump": 1, "speed_mismatch": 1, "gap_consistency": 1,
    }  # fmt: skip
    dropped = result.dropped.set_index("reason")
    assert dropped.loc["jump", "run"].startswith("Vicolungo")
    assert dropped.loc["jump", "value"] == pytest.approx(23.07, abs=0.05)
    assert dropped.loc["speed_mismatch", "run"].startswith("Vicolungo")
    assert dropped.loc["speed_mismatch", "value"] == pytest.approx(3.26, abs=0.01)
    assert dropped.loc["gap_consistency", "run"].startswith("Cherasco")
    assert result.pairs.n_pairs == 18
    assert result.index.groupby(["run", "follower"])["split"].nunique().max() == 1
    assert result.road_frame is False and result.train.road_frame is False  # 4 roads
    # accelerations were derived from the Doppler speeds
    assert np.isfinite(result.pairs.a_follow.numpy()).all()
    assert any("acceleration derived" in note for note in result.notes)
