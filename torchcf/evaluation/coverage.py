"""Predictive coverage: does a learned set know what it knows?

A learned set (the hybrid, or one model's particles) is a predictive
distribution of the follower on a test pair: draw a particle by its weight,
simulate it on the pair's leader (SPEC section 2), read the follower's spacing
``x_l(t) - x(t)`` and speed ``v(t)`` at every step. Its central ``q`` band at
step ``t`` runs from the ``(1 - q) / 2`` to the ``(1 + q) / 2`` quantile of
those draws; a calibrated set puts a fraction ``q`` of the observed points
inside its ``q`` bands (the calibration curve: nominal against observed).

Shapes (letters of :mod:`torchcf.typing`): T steps, P particles, N test pairs;
``2`` the variables (spacing, speed: :data:`VARIABLES`), ``levels`` the nominal
levels asked for, ``feeds`` the sets one batch of draws feeds, ``n_bootstrap``
the resamples of a bootstrap.

**Quantile.** ``Q(p) = inf {x : F(x) >= p}`` of the weighted draws' CDF
``F(x) = sum_i w_i [x_i <= x] / sum_i w_i`` (numpy's ``inverted_cdf`` when the
weights are equal). So an observation ``y`` lies in ``[Q(lo), Q(hi)]`` exactly
when ``F(y) >= lo`` and ``F(y-) < hi``, ``F(y-) = sum_i w_i [x_i < y] / sum w``:
coverage needs the two CDF values at the observation, one comparison pass over
the draws, and no sort (:class:`PredictiveCDF`); every level of the curve then
comes free. :func:`weighted_quantiles` draws the bands themselves (a figure,
the tests).

**What is counted.** The observed points of a pair are its valid steps
``t >= 1`` (step 0 is the observed initial state every rollout starts from, not
a prediction). An invalid rollout (SPEC section 2) is no draw on that pair
(weight 0 there). A pair on which no particle of the set is valid has no
predictive distribution: its points count as not covered. The fraction is
pooled over the points of all test pairs (longer pairs weigh more); its
bootstrap resamples pairs (:func:`coverage_fractions` takes per-pair counts).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

#: Variables of the predictive distribution, in the order of the ``2`` axis.
VARIABLES = ("spacing", "speed")
#: Slack on the CDF's comparisons with a level: ``k / P`` and a level such as
#: ``0.05`` differ by rounding where they are mathematically equal.
LEVEL_TOL = 1e-9


class CoverageCounts(NamedTuple):
    """Per test pair, the observed points inside each central band.

    Attributes:
        levels: (levels,) nominal levels, in (0, 1).
        inside: (2, levels, N) int64 observed points inside the band.
        points: (N,) int64 observed points of each pair (the same for every
            variable and level).
        pairs_without_draws: test pairs on which no particle is valid.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import PredictiveCDF, scored_steps
        >>> spacing = torch.tensor([[30.0], [31.0], [32.0]])  # (T, N) observed [m]
        >>> speed = torch.full((3, 1), 20.0)  # [m/s]
        >>> offset = torch.tensor([-2.0, -1.0, 1.0, 2.0])[None, :, None]  # P = 4 draws
        >>> draws = [spacing[:, None] + offset, speed[:, None] + offset.abs()]
        >>> valid = torch.ones(4, 1, dtype=torch.bool)  # (P, N)
        >>> cdf = PredictiveCDF([spacing, speed], scored_steps(torch.ones(3, 1).bool()))
        >>> cdf.add(draws, valid)
        >>> counts = cdf.counts([0.5, 0.9])
        >>> counts.points.tolist(), counts.inside[:, :, 0].tolist()  # steps 1 and 2
        ([2], [[2, 2], [0, 0]])
        >>> counts.fractions().tolist()  # (spacing, speed) x levels
        [[1.0, 1.0], [0.0, 0.0]]
    """

    levels: np.ndarray
    inside: np.ndarray
    points: np.ndarray
    pairs_without_draws: int

    def fractions(self) -> np.ndarray:
        """(2, levels) the fraction of all observed points inside each band."""
        return self.inside.sum(axis=-1) / max(int(self.points.sum()), 1)


def observed(
    x_lead: Tensor, x_follow: Tensor, v_follow: Tensor
) -> tuple[Tensor, Tensor]:
    """The observed ``(spacing, speed)``, (T, N) each, from a pair set's columns.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import observed
        >>> x_lead, x_follow = torch.tensor([[40.0]]), torch.tensor([[10.0]])  # [m]
        >>> spacing, speed = observed(x_lead, x_follow, torch.tensor([[20.0]]))
        >>> spacing.tolist(), speed.tolist()  # [m], [m/s]
        ([[30.0]], [[20.0]])
    """
    return x_lead - x_follow, v_follow


def predicted(x_lead: Tensor, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """The simulated ``(spacing, speed)``, (T, P, N) each, of trajectories
    ``x, v`` (T, P, N) on leaders ``x_lead`` (T, N).

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import predicted
        >>> x_lead = torch.tensor([[40.0]])  # (T, N) [m]
        >>> x = torch.tensor([[[10.0], [12.0]]])  # (T, P, N): two particles [m]
        >>> spacing, speed = predicted(x_lead, x, torch.full_like(x, 20.0))
        >>> spacing[0, :, 0].tolist()
        [30.0, 28.0]
    """
    return x_lead[:, None, :] - x, v  # (T, P, N)


class PredictiveCDF:
    """Streams weighted draws into ``F(y-)`` and ``F(y)`` at the observations.

    Draws may come in several batches (:meth:`add`: one model's particles at a
    time; the hybrid's from several models), so no trajectory is kept: the
    state is the unnormalised sums, (2, T, N) each, and the weight of each pair
    (N,).

    Args:
        targets: per variable, the observations (T, N).
        mask: (T, N) bool, the observed steps to score (:func:`scored_steps`).

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import PredictiveCDF, scored_steps
        >>> spacing = torch.tensor([[30.0], [31.0], [32.0]])  # (T, N) observed [m]
        >>> speed = torch.full((3, 1), 20.0)  # [m/s]
        >>> offset = torch.tensor([-2.0, -1.0, 1.0, 2.0])[None, :, None]  # P = 4 draws
        >>> draws = [spacing[:, None] + offset, speed[:, None] + offset.abs()]
        >>> valid = torch.ones(4, 1, dtype=torch.bool)  # (P, N)
        >>> cdf = PredictiveCDF([spacing, speed], scored_steps(torch.ones(3, 1).bool()))
        >>> cdf.add(draws, valid)
        >>> below, at_or_below = cdf.cdf()  # F(y-), F(y): (2, T, N)
        >>> below[0, :, 0].tolist(), at_or_below[1, :, 0].tolist()
        ([0.5, 0.5, 0.5], [0.0, 0.0, 0.0])
        >>> cdf.counts([0.5]).fractions().tolist()  # the speeds all overshoot
        [[1.0], [0.0]]
    """

    def __init__(self, targets: Sequence[Tensor], mask: Tensor) -> None:
        self.targets = torch.stack([t.double() for t in targets])  # (2, T, N)
        self.mask = mask.bool()
        shape = self.targets.shape
        self.below = torch.zeros(shape, dtype=torch.float64)  # sum w [x < y]
        self.at_or_below = torch.zeros(shape, dtype=torch.float64)  # sum w [x <= y]
        self.weight = torch.zeros(shape[-1], dtype=torch.float64)  # (N,)

    def add(
        self, draws: Sequence[Tensor], valid: Tensor, weights: Tensor | None = None
    ) -> None:
        """Add a batch of P draws (:func:`add_draws` with this CDF alone).

        Args:
            draws: per variable, (T, P, N) simulated values.
            valid: (P, N) bool, the rollout is valid on that pair.
            weights: (P,) non-negative weight of each particle (None: 1 each).
        """
        add_draws([(self, weights)], draws, valid)

    def cdf(self) -> tuple[Tensor, Tensor]:
        """``F(y-), F(y)``: (2, T, N) each; NaN on a pair without draws."""
        w = torch.where(self.weight > 0, self.weight, torch.nan)  # (N,)
        return self.below / w, self.at_or_below / w

    def counts(self, levels: Sequence[float]) -> CoverageCounts:
        """Observed points inside each central band, per pair
        (:class:`CoverageCounts`)."""
        levels_ = np.asarray(sorted(levels), dtype=np.float64)  # (levels,)
        below, at_or_below = self.cdf()  # (2, T, N)
        lo = torch.as_tensor((1 - levels_) / 2)[
            :, None, None, None
        ]  # (levels, 1, 1, 1)
        hi = torch.as_tensor((1 + levels_) / 2)[:, None, None, None]
        inside = (at_or_below[None] >= lo - LEVEL_TOL) & (
            below[None] < hi - LEVEL_TOL
        )  # (levels, 2, T, N); NaN (no draws) compares False: not covered
        inside &= self.mask[None, None]
        return CoverageCounts(
            levels=levels_,
            inside=inside.sum(dim=2).transpose(0, 1).numpy().astype(np.int64),
            points=self.mask.sum(dim=0).numpy().astype(np.int64),
            pairs_without_draws=int((self.weight == 0).sum()),
        )


def add_draws(
    feeds: Sequence[tuple[PredictiveCDF, Tensor | np.ndarray | None]],
    draws: Sequence[Tensor],
    valid: Tensor,
) -> None:
    """Add one batch of P draws to several CDFs of the same observations, each
    with its own particle weights (a model's rollout feeds the model's CDF and,
    weighted by which rows the hybrid keeps, the hybrid's): the comparisons with
    the observations are made once, and each CDF's sums are one batched
    product with its weights.

    Args:
        feeds: ``(cdf, weights)``; weights (P,) non-negative (None: 1 each).
        draws: per variable, (T, P, N) simulated values.
        valid: (P, N) bool, the rollout is valid on that pair.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import PredictiveCDF, scored_steps
        >>> spacing = torch.tensor([[30.0], [31.0], [32.0]])  # (T, N) observed [m]
        >>> speed = torch.full((3, 1), 20.0)  # [m/s]
        >>> offset = torch.tensor([-2.0, -1.0, 1.0, 2.0])[None, :, None]  # P = 4 draws
        >>> draws = [spacing[:, None] + offset, speed[:, None] + offset.abs()]
        >>> valid = torch.ones(4, 1, dtype=torch.bool)  # (P, N)
        >>> cdf = PredictiveCDF([spacing, speed], scored_steps(torch.ones(3, 1).bool()))
        >>> from torchcf.evaluation.coverage import add_draws
        >>> kept = PredictiveCDF([spacing, speed], cdf.mask)  # draws 1 and 2 only
        >>> weights = torch.tensor([0.0, 1.0, 1.0, 0.0])  # (P,)
        >>> add_draws([(cdf, None), (kept, weights)], draws, valid)
        >>> cdf.weight.tolist(), kept.weight.tolist()
        ([4.0], [2.0])
    """
    n_particles = valid.shape[0]
    cells = torch.stack(
        [
            (
                torch.ones(n_particles, dtype=torch.float64)
                if w is None
                else torch.as_tensor(w, dtype=torch.float64)
            )[:, None]
            * valid.cpu().double()
            for _, w in feeds
        ]
    )  # (feeds, P, N)
    keep = (cells > 0).any(dim=(0, 2))  # (P,) particles that weigh somewhere
    if not keep.any():
        return
    cells = cells[:, keep]  # (feeds, P', N)
    for cdf, cell in zip((c for c, _ in feeds), cells, strict=True):
        cdf.weight += cell.sum(dim=0)
    # The products run in float32 when every weight is a small integer (a count
    # of draws: then exact), else in float64.
    integral = bool((cells == cells.round()).all() and cells.sum() < 2**24)
    work = torch.float32 if integral else torch.float64
    by_pair = cells.permute(2, 1, 0).to(work)  # (N, P', feeds)
    targets = feeds[0][0].targets  # (2, T, N), the same for every feed
    every = bool(keep.all())
    for k, (draw, target) in enumerate(zip(draws, targets, strict=True)):
        d = (draw if every else draw[:, keep]).to("cpu")  # (T, P', N)
        lower, upper = thresholds(target[:, None, :], d.dtype)  # (T, 1, N) each
        # NaN draws (an invalid rollout) compare False and weigh 0 anyway; the
        # comparison writes 0/1 straight into the product's dtype. Compared in
        # the draws' own layout, then summed over particles pair by pair: the
        # product reads (T, P') of pair n in place (a strided batch), where a
        # copy of the draws into (N, T, P') cost more than the comparisons
        indicator = torch.empty(d.shape, dtype=work)
        below = torch.bmm(
            torch.le(d, lower, out=indicator).permute(2, 0, 1), by_pair
        )  # (N, T, feeds)
        at_or_below = torch.bmm(
            torch.le(d, upper, out=indicator).permute(2, 0, 1), by_pair
        )
        below, at_or_below = below.double(), at_or_below.double()
        for f, (cdf, _) in enumerate(feeds):
            cdf.below[k] += below[:, :, f].T
            cdf.at_or_below[k] += at_or_below[:, :, f].T


def thresholds(y: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``x < y`` and ``x <= y`` as ``x <= lower`` and ``x <= upper`` for every
    ``x`` of ``dtype``: ``upper`` the largest value of ``dtype`` ``<= y``,
    ``lower`` the largest ``< y``. The draws (float32 in a float32 run) are
    then compared in their own dtype, exactly as with the float64 ``y``,
    without casting every draw up.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import thresholds
        >>> y = torch.tensor([0.1, 0.5], dtype=torch.float64)
        >>> lower, upper = thresholds(y, torch.float32)
        >>> (upper.double() <= y).tolist()  # x <= y iff x <= upper, in float32
        [True, True]
        >>> (lower < upper).tolist()  # 0.1 is no float32: x < y iff x <= y there
        [False, True]
    """
    y = y.double()
    upper = y.to(dtype)  # nearest: one step above y at most
    down = torch.tensor(-math.inf, dtype=dtype)
    upper = torch.where(upper.double() > y, torch.nextafter(upper, down), upper)
    lower = torch.where(upper.double() == y, torch.nextafter(upper, down), upper)
    return lower, upper


def scored_steps(mask: Tensor) -> Tensor:
    """(T, N) bool: the observed steps whose coverage counts (``t >= 1``).

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import scored_steps
        >>> mask = torch.tensor([[True], [True], [False]])  # (T, N): 2 valid steps
        >>> scored_steps(mask)[:, 0].tolist()  # step 0 is the given start
        [False, True, False]
    """
    out = mask.bool().clone()
    out[0] = False
    return out


def coverage_fractions(
    inside: np.ndarray, points: np.ndarray, counts: np.ndarray | None = None
) -> np.ndarray:
    """Pooled fractions of observed points inside the bands.

    Args:
        inside: (..., N) points inside, per pair.
        points: (N,) points per pair.
        counts: (n_bootstrap, N) how often each pair is drawn per resample (None: once).

    Returns:
        (...) or, with ``counts``, (n_bootstrap, ...) fractions; NaN without points.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.coverage import coverage_fractions
        >>> inside, points = np.array([2, 1]), np.array([2, 2])  # per pair, N = 2
        >>> float(coverage_fractions(inside, points))
        0.75
        >>> resamples = np.array([[2, 0], [0, 2]])  # each pair drawn twice
        >>> coverage_fractions(inside, points, resamples).tolist()
        [1.0, 0.5]
    """
    if counts is None:
        total = points.sum()
        return (
            inside.sum(axis=-1) / total if total else np.full(inside.shape[:-1], np.nan)
        )
    total = counts @ points  # (n_bootstrap,)
    drawn = np.tensordot(counts, inside, axes=([1], [-1]))  # (n_bootstrap, ...)
    with np.errstate(invalid="ignore", divide="ignore"):
        return drawn / np.where(total > 0, total, np.nan).reshape(
            (-1,) + (1,) * (drawn.ndim - 1)
        )


def weighted_quantiles(
    draws: Tensor, probs: Sequence[float], weights: Tensor | None = None
) -> Tensor:
    """``Q(p) = inf {x : F(x) >= p}`` of weighted draws along the particle axis.

    Args:
        draws: (T, P, N) values (no NaN).
        probs: (len(probs),) probabilities in [0, 1].
        weights: (P,) or (P, N) non-negative weights (None: equal).

    Returns:
        (len(probs), T, N) quantiles.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.coverage import weighted_quantiles
        >>> draws = torch.tensor([[[1.0], [2.0], [3.0], [4.0]]])  # (T, P, N)
        >>> weighted_quantiles(draws, [0.25, 0.5, 1.0]).flatten().tolist()
        [1.0, 2.0, 4.0]
        >>> weights = torch.tensor([0.0, 0.0, 1.0, 1.0])  # (P,)
        >>> weighted_quantiles(draws, [0.5], weights).flatten().tolist()
        [3.0]
    """
    n_particles = draws.shape[1]
    w = (
        torch.ones(n_particles, dtype=torch.float64)
        if weights is None
        else torch.as_tensor(weights, dtype=torch.float64)
    )
    if w.ndim == 1:
        w = w[:, None].expand(n_particles, draws.shape[2])  # (P, N)
    values, order = torch.sort(draws.double(), dim=1)  # (T, P, N)
    sorted_w = w[None].expand_as(values).gather(1, order)  # (T, P, N)
    cum = sorted_w.cumsum(dim=1)
    cum = cum / cum[:, -1:]  # (T, P, N) F at each sorted draw
    p = torch.as_tensor(list(probs), dtype=torch.float64)  # (levels,)
    # first sorted index whose F reaches p (tolerance as in PredictiveCDF)
    reached = cum[None] >= (p - LEVEL_TOL)[:, None, None, None]  # (len(probs), T, P, N)
    first = reached.double().argmax(dim=2, keepdim=True)  # (len(probs), T, 1, N)
    return values[None].expand(len(p), *values.shape).gather(2, first).squeeze(2)


__all__ = [
    "LEVEL_TOL",
    "VARIABLES",
    "CoverageCounts",
    "add_draws",
    "PredictiveCDF",
    "coverage_fractions",
    "observed",
    "predicted",
    "scored_steps",
    "thresholds",
    "weighted_quantiles",
]
