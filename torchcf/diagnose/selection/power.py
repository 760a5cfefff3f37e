"""What the data could have shown: per tested effect, the smallest size its
test would have found.

An effect that is not chosen is not shown absent: its test may lack the power
to see it in these data. For every effect of a step's test with a one-number
size (:func:`size_path`: a one-parameter effect's value, a grade profile's
amplitude), the loop asks, on the data it has, how large the effect would have
had to be for its test to find it.

**The symmetric profile.** Fixed at a size ``s`` away from its neutral value,
an effect costs the model's fit, on data without it, about what the model
without it loses on data that carry it at ``s``: near its best value a fit's
profile is symmetric (fixing a parameter a distance ``s`` off its best costs
the same on either side). So each validation unit is refitted twice, with
the same random numbers (:mod:`torchcf.diagnose.arms.refit`): without the effect,
and with it pinned at ``s``, from the same start (the placebo's picks); their
per-unit log score ratios ``d_j(s)`` are what the test would see if the data
carried the effect at ``s``. The effect is *detectable* at ``s`` when the
one-sided sign-flip test of ``d(s)`` passes the level the effect is judged at
and the relative score drop reaches ``min_gain``, the two conditions of the
selection. The sizes tried form a ladder from the neutral value toward each
end of the prior (:data:`LADDER`); the smallest detectable one on each side is
reported, with the test's p-value and gain there.

The units are those of the test: held-out pairs refitted from the placebo's
pooled picks (validation ``"refit"``), or every pair's validation window
refitted from its own picks (``"time"``). On data that already carry some of
the effect (a gain below the threshold), the profile's best is off neutral and
the sizes on that side read smaller than they are; the gain the test measured
is reported beside them.

Shapes: U validation units (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ...models.effects import Effect, Grade
from ..arms.refit import Pin
from ..arms.search import INVALID_RATIO
from ..arms.validation import Judge
from ..significance import comparable, sign_flip_test
from .tested import Detectable, EffectTest, Rung

#: The sizes tried, as shares of the way from the neutral value to each end of
#: the effect's prior (a grade: of its prior's bound), smallest first.
LADDER = (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0)


def size_path(effect: Effect) -> list[tuple[str, list[tuple[float, Tensor]]]] | None:
    """The sizes an effect is tried at: per side (``"below"``, ``"above"`` the
    neutral value), ``(size, value (K_E,))`` pairs, smallest first; None for an
    effect with no one-number size (several parameters of their own meaning:
    asymmetry, saturation, action points, a bend).

    A one-parameter effect's size is its value; a grade's is the amplitude of a
    profile whose knots alternate in sign (+s, -s, ...), the rolling road of a
    test track, on the side ``"above"`` only (its sign is the profile's phase).
    """
    if isinstance(effect, Grade):
        bound = effect.param_specs[0].upper
        signs = torch.tensor(
            [(-1.0) ** k for k in range(len(effect.param_specs))], dtype=torch.float64
        )
        return [("above", [(f * bound, f * bound * signs) for f in LADDER])]
    if len(effect.param_specs) != 1:
        return None
    (param,), (neutral,) = effect.param_specs, effect.neutral
    sides = []
    for side, end in (("below", param.lower), ("above", param.upper)):
        reach = end - neutral
        if abs(reach) < 1e-12:
            continue
        ladder = [neutral + f * reach for f in LADDER]
        sides.append(
            (side, [(v, torch.tensor([v], dtype=torch.float64)) for v in ladder])
        )
    return sides


class Ladder:
    """An effect's tests at the sizes of :func:`size_path`, each run once, when
    first asked for (a refit per size)."""

    def __init__(
        self, judge: Judge, effect: Effect, before: np.ndarray, permutations: int
    ) -> None:
        self.judge, self.effect, self.before = judge, effect, before
        self.permutations = permutations
        self.path = dict(size_path(effect) or [])
        self.tried: dict[tuple[str, int], Rung] = {}

    def rung(self, side: str, i: int) -> Rung:
        if (side, i) not in self.tried:
            size, value = self.path[side][i]
            after = self.judge.profile(Pin(self.effect, value))
            self.tried[side, i] = _rung(size, self.before, after, self.permutations)
        return self.tried[side, i]

    def smallest(self, side: str, level: float, min_gain: float) -> float | None:
        """The smallest size on ``side`` whose test passes (None: not even at
        the end of the prior), by bisection over the ladder (a larger effect is
        taken to be at least as detectable)."""
        last = len(self.path[side]) - 1
        if not self.rung(side, last).passes(level, min_gain):
            return None
        low, high = -1, last  # rung ``high`` passes; ``low`` does not (or none)
        while high - low > 1:
            middle = (low + high) // 2
            if self.rung(side, middle).passes(level, min_gain):
                high = middle
            else:
                low = middle
        return self.rung(side, high).size

    def tried_rungs(self) -> dict[str, tuple[Rung, ...]]:
        """Per side, the sizes tried and their tests, smallest first."""
        out: dict[str, list[Rung]] = {}
        for (side, _), rung in sorted(self.tried.items()):
            out.setdefault(side, []).append(rung)
        return {side: tuple(rungs) for side, rungs in out.items()}


def _rung(size: float, before: np.ndarray, after: np.ndarray, perms: int) -> Rung:
    # a size at which every rollout of a unit collides is a loss there, not a
    # unit left out (testing.comparable)
    usable, before, after = comparable(before, after, INVALID_RATIO)
    if not usable.any():
        return Rung(size, 0.0, 1.0)
    drops = np.log(after[usable] / before[usable])
    gain = float((after[usable] - before[usable]).sum() / after[usable].sum())
    _, p_value = sign_flip_test(drops, perms)
    return Rung(size, gain, p_value)


def detectable_sizes(
    judge: Judge,
    rows: list[EffectTest],
    first_level: float,
    min_gain: float,
    permutations: int,
    progress: Callable[[str], None] = lambda label: None,
) -> None:
    """Add to every row its ``detectable``: per side of the neutral value, the
    smallest detectable size at the row's own level (its place in the order)
    and at the step's first level (had the residual pointed to it), with the
    sizes tried; None for an effect with no one-number size. ``progress`` is
    told each effect's name as its sizes are tried."""
    before = None
    for row in rows:
        if size_path(row.effect) is None:
            row.detectable = None
            continue
        progress(row.name)
        if before is None:
            before = judge.profile(None)
        found = Ladder(judge, row.effect, before, permutations)
        sides = list(found.path)
        row.detectable = Detectable(
            unit=_unit(row.effect),
            level=row.level,
            at_level={s: found.smallest(s, row.level, min_gain) for s in sides},
            first_level=first_level,
            if_first={s: found.smallest(s, first_level, min_gain) for s in sides},
            tried=found.tried_rungs(),
        )


def _unit(effect: Effect) -> str:
    if isinstance(effect, Grade):
        return "1 (grade amplitude)"
    return effect.param_specs[0].unit


__all__ = [
    "LADDER",
    "Detectable",
    "Ladder",
    "Rung",
    "detectable_sizes",
    "size_path",
]
