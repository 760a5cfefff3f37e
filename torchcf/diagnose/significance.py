"""The attribution's tests: a per-pair sign-flip test, and a procedure that keeps
the family-wise guard while spending its power where the fit windows point.

**The test of one effect.** Each pair gives one number, the log ratio of its
validation score without and with the effect (:mod:`torchcf.diagnose.
attribution`); pairs are independent, so under "the effect does not improve the
out-of-sample fit" each pair's log ratio is as likely negative as positive, and
the one-sided sign-flip permutation test (:func:`sign_flip_test`) is exact
whatever the distribution of the ratios. The arms are fitted on the fit windows
only, so the validation windows they are judged on are out of sample, and the
p-value is valid conditionally on everything the fit windows decided (the
particles, the order of the tests below).

**The procedure** (:func:`fallback_levels`). The effects of a step are tested in
an order fixed by the fit windows (the residual signatures, then the in-sample
gain: :func:`torchcf.diagnose.selection.attribution.test_order`), with the *fallback
procedure* (Wiens 2003; Wiens & Dmitrienko 2005): the i-th effect of the order
gets the weight ``w_i = 2^-i / (1 - 2^-E)`` (i = 1..E) of the step's level
``alpha_s``, and is tested at ``alpha_i = w_i alpha_s``, plus ``alpha_(i-1)``
when the one before it was rejected. It is a closed test built from weighted
Bonferroni tests, so it keeps the family-wise error rate of the step at
``alpha_s`` under any dependence between the tests; unlike a fixed sequence it
does not stop at the first effect that fails, and unlike Bonferroni it gives
half the level to the effect the fit windows point to first. Why not Holm: Holm
ignores the order, so it cannot spend the level where the residual points.

**Families** (:func:`max_flip_test`). Effects that one residual signature
points to (a response lag: a reaction delay, a clock offset, an actuation
lag) are twins: they explain much the same residual, and tested one by one
they split the level between them. They are tested as one family at the
place of the first: the largest of their statistics under common sign flips
(exact for the family), the member then chosen within it, its twins named.

**Steps** (:func:`step_levels`). Forward selection tests the remaining effects
again once one is chosen; step s gets ``alpha_s = alpha 2^-s`` (the last step
the rest), so the steps' levels sum to ``alpha``: the chance that any chosen
effect does not help out of sample is at most ``alpha`` however many steps run
(a union bound over the steps).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..system.records import Record


def sign_flip_test(
    drops: np.ndarray, permutations: int, seed: int = 0
) -> tuple[float, float]:
    """One-sided test of a positive mean per-pair drop by random sign flips.

    Under "the effect does not help", each pair's drop is as likely negative as
    positive; the p-value is ``(1 + #{flipped mean >= observed}) / (1 +
    n_perm)``. Pairs whose drop is exactly 0 (the same particles with and
    without the effect) add nothing to either side.

    Returns:
        ``(t statistic, p-value)``; the t statistic ``mean / (sd / sqrt(n))`` is
        reported for scale only.
    """
    drops = np.asarray(drops, dtype=np.float64)
    n = drops.size
    if n == 0 or not np.any(drops):
        return 0.0, 1.0
    observed = drops.mean()
    rng = np.random.default_rng(seed)
    signs = rng.choice(np.array([-1.0, 1.0]), size=(permutations, n))
    flipped = (signs * drops).mean(axis=1)
    p_value = (1.0 + np.count_nonzero(flipped >= observed - 1e-15)) / (
        1.0 + permutations
    )
    sd = drops.std(ddof=1) if n > 1 else 0.0
    statistic = observed / (sd / math.sqrt(n)) if sd > 0 else 0.0
    return float(statistic), float(min(p_value, 1.0))


def max_flip_test(
    drops: Sequence[np.ndarray], permutations: int, seed: int = 0
) -> tuple[float, int]:
    """One-sided test of a family of effects by the largest of their
    self-normalised statistics under common sign flips.

    Every member m gives per unit u a drop ``d_mu`` (the same units for all,
    0 where a member's unit is not usable); its statistic is ``T_m = sum_u d_mu
    / sqrt(sum_u d_mu^2)``, whose denominator sign flips leave unchanged. Under
    "no member helps" the vector ``(d_1u, ..., d_Mu)`` of a unit is as likely
    negated as not, so flipping every member's drop of a unit together keeps
    the members' dependence, and the p-value of ``max_m T_m`` is exact for the
    family: ``(1 + #{max_m T_m(flipped) >= max_m T_m}) / (1 + n_perm)``. With
    one member it is :func:`sign_flip_test`'s p-value.

    Returns:
        ``(p-value, the member of the largest statistic)``.
    """
    matrix = np.array([np.asarray(d, dtype=np.float64) for d in drops])  # (M, U)
    if matrix.size == 0 or not np.any(matrix):
        return 1.0, 0
    norm = np.sqrt((matrix**2).sum(axis=1))
    norm[norm == 0] = np.inf  # a member that never moves: statistic 0
    observed = matrix.sum(axis=1) / norm  # (M,)
    rng = np.random.default_rng(seed)
    signs = rng.choice(np.array([-1.0, 1.0]), size=(permutations, matrix.shape[1]))
    flipped = (signs @ matrix.T) / norm  # (P, M)
    top = observed.max()
    count = np.count_nonzero(flipped.max(axis=1) >= top - 1e-12)
    p_value = (1.0 + count) / (1.0 + permutations)
    return float(min(p_value, 1.0)), int(observed.argmax())


def two_sided_sign_flip(values: np.ndarray, permutations: int, seed: int = 0) -> float:
    """Two-sided sign-flip p-value of a zero mean of per-pair ``values``."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0 or not np.any(values):
        return 1.0
    observed = abs(values.mean())
    rng = np.random.default_rng(seed)
    signs = rng.choice(np.array([-1.0, 1.0]), size=(permutations, values.size))
    flipped = np.abs((signs * values).mean(axis=1))
    return float(
        (1.0 + np.count_nonzero(flipped >= observed - 1e-15)) / (1.0 + permutations)
    )


@dataclass(frozen=True)
class PairedChange(Record):
    """Two runs compared pair by pair on the same test pairs (:func:`paired_change`).

    Attributes:
        pairs: the pairs both cover.
        better: those where the second run is lower.
        change: the geometric mean of ``after / before`` minus 1 (negative:
            after covers the pairs better).
        p_value: one-sided sign flips of the per-pair log ratios, "after no
            better than before" (exact, the test pairs being independent of
            both runs' training).
    """

    pairs: int
    better: int
    change: float
    p_value: float


def paired_change(
    before: Sequence[float | None],
    after: Sequence[float | None],
    permutations: int,
    seed: int = 0,
) -> PairedChange | None:
    """Two runs compared pair by pair on the same test pairs: their minimum
    distance per pair (None: no valid particle there, that pair left out).

    Returns:
        the comparison; None when the lists differ in length or no pair is
        usable.
    """
    if len(before) != len(after):
        return None
    ratios = np.array(
        [
            math.log(b / a)
            for a, b in zip(before, after, strict=True)
            if a is not None and b is not None and a > 0 and b > 0
        ]
    )
    if ratios.size == 0:
        return None
    _, p_value = sign_flip_test(-ratios, permutations, seed)
    return PairedChange(
        pairs=int(ratios.size),
        better=int(np.count_nonzero(ratios < 0)),
        change=float(math.expm1(ratios.mean())),
        p_value=p_value,
    )


def comparable(
    before: np.ndarray, after: np.ndarray, invalid_ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two sides' scores per unit made comparable: where one side has no valid
    rollout (``inf``: every particle collided or left the road) and the other
    has, the invalid side counts ``invalid_ratio`` times the valid one (a loss
    as large as the search counts it, not a unit dropped: an effect that makes
    every rollout of a pair collide must lose there, and one that rescues a
    pair must win); units invalid on both sides, or not positive, are left out.

    Returns:
        the usable units' mask (U,), and both sides over all units (U,) with
        the invalid side replaced.
    """
    before = np.asarray(before, dtype=np.float64)
    after = np.asarray(after, dtype=np.float64)
    finite_b, finite_a = np.isfinite(before), np.isfinite(after)
    before = np.where(~finite_b & finite_a, invalid_ratio * after, before)
    after = np.where(~finite_a & finite_b, invalid_ratio * before, after)
    usable = np.isfinite(before) & np.isfinite(after) & (before > 0) & (after > 0)
    return usable, before, after


def step_levels(alpha: float, steps: int) -> list[float]:
    """The level of each forward-selection step: ``alpha / 2, alpha / 4, ...``,
    the last step the rest (they sum to ``alpha``)."""
    if steps < 1:
        return []
    levels = [alpha * 2.0 ** -(s + 1) for s in range(steps - 1)]
    return [*levels, alpha - sum(levels)]


def fallback_weights(n_tests: int) -> list[float]:
    """The fallback weights ``2^-i / (1 - 2^-E)``, i = 1..E (they sum to 1)."""
    total = 1.0 - 2.0**-n_tests
    return [2.0 ** -(i + 1) / total for i in range(n_tests)]


#: The ways a step's level is shared among its tests (``diagnose.levels``).
LEVEL_SCHEMES = ("halving", "pointed", "equal")


def level_weights(pointed: Sequence[bool], scheme: str = "halving") -> list[float]:
    """Each test's share of its step's level, in the order of testing (they sum
    to 1).

    Args:
        pointed: per test, whether a found residual signature points to its
            effect (such tests come first in the order).
        scheme: ``"halving"``: ``2^-i`` (:func:`fallback_weights`), the first
            test half the level whatever pointed to it; ``"pointed"``: the
            tests a signature points to share half the level equally, the
            others the other half equally (all of it where none, or all, are
            pointed to); ``"equal"``: ``1/E`` each (Bonferroni's shares).
    """
    n = len(pointed)
    if n == 0:
        return []
    if scheme == "halving":
        return fallback_weights(n)
    if scheme == "equal":
        return [1.0 / n] * n
    if scheme != "pointed":
        raise ValueError(f"unknown level scheme {scheme!r}; one of {LEVEL_SCHEMES}")
    k = sum(pointed)
    if k in (0, n):
        return [1.0 / n] * n
    return [0.5 / k if mark else 0.5 / (n - k) for mark in pointed]


def fallback_levels(
    p_values: Sequence[float],
    passes: Sequence[bool],
    alpha: float,
    weights: Sequence[float] | None = None,
) -> tuple[list[float], list[bool]]:
    """The fallback procedure over tests in their order (module docstring).

    Args:
        p_values: the tests' p-values, in the order of testing.
        passes: whether each test's other condition holds (a gain of at least
            ``diagnose.min_gain``); a test that fails it is not rejected and
            passes no level on.
        alpha: the step's level.
        weights: each test's share of ``alpha`` (:func:`level_weights`;
            default: :func:`fallback_weights`).

    Returns:
        the level each test was judged at, and whether it was rejected
        (significant).
    """
    levels, rejected = [], []
    carried = 0.0
    if weights is None:
        weights = fallback_weights(len(p_values))
    for w, p, ok in zip(weights, p_values, passes, strict=True):
        level = w * alpha + carried
        significant = bool(ok and p <= level)
        levels.append(level)
        rejected.append(significant)
        carried = level if significant else 0.0
    return levels, rejected


__all__ = [
    "LEVEL_SCHEMES",
    "PairedChange",
    "comparable",
    "fallback_levels",
    "fallback_weights",
    "level_weights",
    "max_flip_test",
    "paired_change",
    "sign_flip_test",
    "step_levels",
    "two_sided_sign_flip",
]
