"""What the data could have shown (torchcf.diagnose.selection.power): the sizes tried,
the bisection of the ladder, and the rows it fills, with a judge whose
refitted scores are made here (the refits themselves: tests/diagnose/
test_refit.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcf.diagnose.selection.power import LADDER, Ladder, detectable_sizes, size_path
from torchcf.models.effects import parse_effect

from .rows import row_of

DELAY = parse_effect("delay")

UNITS = 40


class CostlyJudge:
    """A judge whose validation units each score 1 without an effect and
    ``1 + slope * |value - neutral|`` (times a little per-unit spread) with the
    effect pinned at a value: a symmetric profile, as :mod:`torchcf.diagnose.
    power` assumes. Counts its refits."""

    def __init__(self, slope: float) -> None:
        self.slope, self.calls = slope, 0
        self.spread = 1 + 0.01 * np.random.default_rng(0).random(UNITS)

    def profile(self, pin):
        self.calls += 1
        if pin is None:
            return np.ones(UNITS)
        spec = pin.effect
        off = float((pin.value - torch.tensor(spec.neutral)).abs().max())
        return 1 + self.slope * off * self.spread


def test_the_sizes_run_from_the_neutral_value_to_each_end_of_the_prior():
    sides = dict(size_path(parse_effect("delay")))
    (param,) = parse_effect("delay").param_specs
    assert list(sides) == ["above"]  # a delay's neutral value is its lower end
    sizes = [size for size, _ in sides["above"]]
    assert sizes == pytest.approx([f * param.upper for f in LADDER])
    offset = dict(size_path(parse_effect("offset")))
    assert set(offset) == {"below", "above"}
    assert offset["below"][-1][0] == parse_effect("offset").param_specs[0].lower
    # a grade: knots alternating in sign at the amplitude; an effect of two
    # parameters with meanings of their own has no one-number size
    ((side, rungs),) = size_path(parse_effect("grade(start=0,end=400,knots=5)"))
    assert side == "above"
    amplitude, value = rungs[-1]
    assert (
        amplitude == parse_effect("grade(start=0,end=400,knots=5)").param_specs[0].upper
    )
    assert value.tolist() == pytest.approx([amplitude, -amplitude] * 2 + [amplitude])
    assert size_path(parse_effect("asymmetry")) is None


def test_the_ladder_finds_the_smallest_size_that_passes_by_bisection():
    """Gain at size s: s * slope / (1 + s * slope). With min_gain 0.05 and a
    slope of 1 per second, a delay is detectable from s >= 0.0526 s: the
    smallest rung at or above it."""
    judge = CostlyJudge(slope=1.0)
    ladder = Ladder(judge, DELAY, judge.profile(None), permutations=2000)
    smallest = ladder.smallest("above", level=0.01, min_gain=0.05)
    sizes = [size for size, _ in dict(size_path(parse_effect("delay")))["above"]]
    want = min(s for s in sizes if s / (1 + s) >= 0.05)
    assert smallest == pytest.approx(want)
    # bisection: far fewer refits than rungs
    assert judge.calls - 1 <= 1 + int(np.ceil(np.log2(len(sizes)))) + 1
    # an effect the data could not show even at the end of its prior
    flat = CostlyJudge(slope=1e-4)
    ladder = Ladder(flat, parse_effect("delay"), flat.profile(None), permutations=2000)
    assert ladder.smallest("above", level=0.01, min_gain=0.05) is None


def test_every_row_with_a_size_gets_its_detectable_sizes():
    judge = CostlyJudge(slope=1.0)
    rows = [
        row_of("delay", level=0.0125),
        row_of("asymmetry", level=0.00625),
        row_of("offset", level=0.003),
    ]
    detectable_sizes(judge, rows, first_level=0.0125, min_gain=0.05, permutations=2000)
    delay, asymmetry, offset = (row.detectable for row in rows)
    assert asymmetry is None
    assert delay.unit == "s" and delay.at_level["above"] is not None
    assert set(offset.if_first) == {"below", "above"}
    assert offset.tried["below"] and offset.tried["above"]


class CollidingJudge(CostlyJudge):
    """Beyond half the prior every rollout of every unit collides (``inf``)."""

    def profile(self, pin):
        scores = super().profile(pin)
        if pin is not None and float(pin.value.abs().max()) > 1.5:
            return np.full(UNITS, np.inf)
        return scores


def test_a_size_that_makes_every_rollout_collide_counts_as_a_loss():
    """A unit whose refit with the effect has no valid rollout is a loss there
    (an invalid side counts INVALID_RATIO times the valid one), not a unit
    left out: such a size is detectable."""
    judge = CollidingJudge(slope=1e-4)  # no gain anywhere before the collisions
    ladder = Ladder(judge, DELAY, judge.profile(None), permutations=2000)
    assert ladder.smallest("above", level=0.01, min_gain=0.05) == pytest.approx(3.0)
    top = ladder.rung("above", len(LADDER) - 1)
    assert top.gain == pytest.approx(0.9) and top.p_value < 0.01
