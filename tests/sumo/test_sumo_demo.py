"""The helpers of tools/sumo_network_demo.py: the fleet option, the data's time
headways from a PairSet, the two-sample KS distance (no SUMO needed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.runs import tool_module
from torchcf.data import PairSet


@pytest.fixture(scope="module")
def demo():
    yield from tool_module("sumo_network_demo")


def test_parse_fleet_normalises(demo):
    assert demo.parse_fleet(["runs/a:0.3", "runs/b:0.7"]) == [
        ("runs/a", pytest.approx(0.3)),
        ("runs/b", pytest.approx(0.7)),
    ]
    assert demo.parse_fleet(["a:1", "b:3"]) == [("a", 0.25), ("b", 0.75)]
    assert demo.parse_fleet(["runs/a"]) == [("runs/a", 1.0)]
    with pytest.raises(ValueError):
        demo.parse_fleet(["a:0"])
    with pytest.raises(ValueError):
        demo.parse_fleet(["a:-1", "b:2"])


def test_pair_headways_known_gaps_and_speeds(demo):
    # Two pairs, three steps, leader length 4 m. Front-to-front spacings and
    # follower speeds chosen so the bumper gaps are 10, 20, 30 and 6, 8, -1 m.
    x_follow = torch.tensor([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]], dtype=torch.float64)
    spacing = torch.tensor([[14.0, 10.0], [24.0, 12.0], [34.0, 3.0]])
    v_follow = torch.tensor([[5.0, 2.0], [0.5, 4.0], [10.0, 4.0]])
    mask = torch.tensor([[True, True], [True, True], [True, False]])
    zeros = torch.zeros(3, 2, dtype=torch.float64)
    pairs = PairSet.from_arrays(
        (x_follow + spacing, zeros + 10.0, zeros, x_follow, v_follow, zeros),
        dt=0.1, mask=mask, leader_length=4.0,
    )  # fmt: skip
    h = np.sort(demo.pair_headways(pairs, min_speed=1.0))
    # kept: 10/5, 6/2, 8/4, 30/10; dropped: v = 0.5 (slow), the masked step
    # (which also has a negative gap).
    np.testing.assert_allclose(h, [2.0, 2.0, 3.0, 3.0])
    assert demo.pair_headways(pairs, min_speed=0.1).size == 5  # 20 / 0.5 joins


def test_ks_distance(demo):
    a = np.array([1.0, 2.0, 3.0, 4.0])
    assert demo.ks_distance(a, a) == 0.0
    assert demo.ks_distance(a, a + 10.0) == 1.0
    # CDFs of {1,2,3,4} and {3,4,5,6} differ most (by 1/2) on [2, 3).
    assert demo.ks_distance(a, a + 2.0) == pytest.approx(0.5)
    assert math.isnan(demo.ks_distance(a, np.array([])))
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=300), rng.normal(0.5, 1.0, size=200)
    scipy_stats = pytest.importorskip("scipy.stats")
    assert demo.ks_distance(x, y) == pytest.approx(scipy_stats.ks_2samp(x, y).statistic)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--ring-vehicles", "-3"], "--ring-vehicles: expected a whole number >= 1"),
        (["--duration", "nan"], "--duration: expected a number > 0"),
        (["--demand", "inf"], "--demand: expected a number > 0"),
        (["--fleet", "RUN:0"], "--fleet: needs a run with a fraction > 0"),
        (["--fleet", "RUN:x"], "--fleet RUN:x: the fraction must be a number >= 0"),
        (["--fleet", "no/such/run:1"], "no/such/run"),
    ],
)
def test_bad_arguments_are_one_line_and_leave_no_folder(
    demo, tmp_path, argv, message, capsys
):
    out = tmp_path / "out"
    try:
        code = demo.main([*argv, "--out", str(out)])
    except SystemExit as stop:  # argparse's usage error
        code = stop.code
    err = capsys.readouterr().err
    assert code == 2
    assert message in err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()[-1]) < 200
    assert not out.exists()
