"""Simulation-based calibration (SBC) and model recovery: the helpers.

**SBC** (Talts, Betancourt, Simpson, Vehtari & Gelman 2018). Draw a true
parameter from the prior, simulate data with it, calibrate on the data and keep
``L`` posterior draws (here: a pair's accepted particles). The truth's rank among
the draws, ``r = #{draws < truth}`` in ``0 .. L``, is uniform over its ``L + 1``
values when the posterior is the exact one. A posterior *too wide* (ABC's
tolerance) puts the truth near the middle of its draws too often: a hump in the
rank histogram, central intervals that cover the truth more often than their
nominal level. One *too narrow* (or biased) puts it outside: a U (or a slope).

**Coverage from ranks.** With ``L`` draws the central ``q`` interval has no exact
order statistics for every ``q``; the randomised probability integral transform
``u = (r + U) / (L + 1)``, ``U ~ Uniform(0, 1)``, is exactly uniform on (0, 1)
under calibration, so ``|u - 1/2| <= q / 2`` happens with probability ``q``
exactly: the observed fraction against ``q`` is the coverage of the central
``q`` interval, for any ``L``.

**Model recovery.** Pairs made by model ``i``, calibrated with a pool: each
pair's share of its ``N`` best by model; the confusion matrix's row ``i`` is the
mean over model ``i``'s pairs (each row sums to 1 where every pair has a fit).

Shapes: N pairs (or SBC replicates), L draws per pair, K parameters, M models.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from scipy import stats
from torch import Tensor


def sbc_ranks(
    truth: Tensor, draws: Tensor, *, generator: torch.Generator | None = None
) -> Tensor:
    """Rank of each true parameter among its posterior draws.

    Args:
        truth: (N, K) true parameters.
        draws: (N, L, K) posterior draws of each replicate (non-finite rows are
            not allowed: pass only accepted particles).
        generator: breaks ties (a draw equal to the truth) uniformly at random;
            ties have probability 0 for continuous draws.

    Returns:
        (N, K) int64 ranks in ``0 .. L``: draws strictly below the truth, plus a
        uniform share of the ties.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import sbc_ranks
        >>> truth = torch.tensor([[0.5], [2.5]])  # (N, K): 2 replicates, 1 parameter
        >>> draws = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 2)[:, :, None]  # (N, L, K)
        >>> sbc_ranks(truth, draws)[:, 0].tolist()  # draws below each truth
        [1, 3]
    """
    if truth.ndim != 2 or draws.ndim != 3 or draws.shape[::2] != truth.shape:
        raise ValueError(
            f"truth (N, K) and draws (N, L, K) expected, got {tuple(truth.shape)} "
            f"and {tuple(draws.shape)}"
        )
    below = (draws < truth[:, None, :]).sum(1)  # (N, K)
    ties = (draws == truth[:, None, :]).sum(1)  # (N, K)
    if bool((ties > 0).any()):
        unit = torch.rand(ties.shape, generator=generator, dtype=torch.float64)
        below = below + torch.floor(unit * (ties + 1)).to(below.dtype)
    return below


def rank_pit(
    ranks: Tensor, n_draws: int, *, generator: torch.Generator | None = None
) -> Tensor:
    """Randomised probability integral transform ``(r + U) / (L + 1)``.

    Args:
        ranks: (N, K) ranks in ``0 .. L``.
        n_draws: L.

    Returns:
        (N, K) float64 in (0, 1), uniform under calibration.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import sbc_ranks
        >>> truth = torch.tensor([[0.5], [2.5]])  # (N, K): 2 replicates, 1 parameter
        >>> draws = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 2)[:, :, None]  # (N, L, K)
        >>> from torchcf.evaluation.sbc import rank_pit
        >>> pit = rank_pit(sbc_ranks(truth, draws), n_draws=4)  # (r + U) / (L + 1)
        >>> pit.shape, bool(0.2 <= pit[0, 0] < 0.4), bool(0.6 <= pit[1, 0] < 0.8)
        (torch.Size([2, 1]), True, True)
    """
    unit = torch.rand(ranks.shape, generator=generator, dtype=torch.float64)
    return (ranks.to(torch.float64) + unit) / (n_draws + 1)


def central_coverage(pit: Tensor, levels: Sequence[float]) -> Tensor:
    """Fraction of replicates whose truth lies in the central ``q`` interval.

    Args:
        pit: (N, K) probability integral transforms (:func:`rank_pit`).
        levels: nominal levels ``q`` in (0, 1).

    Returns:
        (levels, K) float64 observed coverage; ``> q``: the posterior is too wide,
        ``< q``: too narrow or biased.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import central_coverage
        >>> pit = torch.tensor([[0.5], [0.1]])  # (N, K)
        >>> central_coverage(pit, [0.5, 0.9])[:, 0].tolist()  # 0.1 is only in the 90 %
        [0.5, 1.0]
    """
    level = torch.as_tensor(list(levels), dtype=torch.float64)  # (levels,)
    distance = (pit.to(torch.float64) - 0.5).abs()  # (N, K)
    return (distance[None] <= level[:, None, None] / 2).to(torch.float64).mean(1)


def rank_histogram(ranks: Tensor, n_draws: int) -> Tensor:
    """(L + 1, K) int64 counts of each rank per parameter.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import sbc_ranks
        >>> truth = torch.tensor([[0.5], [2.5]])  # (N, K): 2 replicates, 1 parameter
        >>> draws = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 2)[:, :, None]  # (N, L, K)
        >>> from torchcf.evaluation.sbc import rank_histogram
        >>> rank_histogram(sbc_ranks(truth, draws), n_draws=4)[:, 0].tolist()
        [0, 1, 0, 1, 0]
    """
    columns = [torch.bincount(r, minlength=n_draws + 1) for r in ranks.T]
    return torch.stack(columns, 1)


def uniformity_pvalue(ranks: Tensor, n_draws: int) -> np.ndarray:
    """(K,) chi-square p-values of the ranks against a uniform on ``0 .. L``.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import uniformity_pvalue
        >>> ranks = torch.arange(5)[:, None]  # every rank of 0 .. 4 once
        >>> uniformity_pvalue(ranks, n_draws=4).round(3).tolist()
        [1.0]
    """
    counts = rank_histogram(ranks, n_draws).numpy()
    return np.asarray(stats.chisquare(counts, axis=0).pvalue, dtype=np.float64)


def interval_width(draws: Tensor, level: float) -> Tensor:
    """(N, K) width of the draws' central ``level`` interval (linear quantiles).

    With a handful of draws this is a rough estimate of the posterior's width;
    divide by the prior's width for a scale-free number.

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.sbc import sbc_ranks
        >>> truth = torch.tensor([[0.5], [2.5]])  # (N, K): 2 replicates, 1 parameter
        >>> draws = torch.tensor([[0.0, 1.0, 2.0, 3.0]] * 2)[:, :, None]  # (N, L, K)
        >>> from torchcf.evaluation.sbc import interval_width
        >>> interval_width(draws, level=0.5)[:, 0].tolist()  # quartiles 0.75 and 2.25
        [1.5, 1.5]
    """
    lo, hi = (1.0 - level) / 2.0, (1.0 + level) / 2.0
    q = torch.tensor([lo, hi], dtype=draws.dtype)
    bounds = torch.quantile(draws, q, dim=1)  # (2, N, K)
    return bounds[1] - bounds[0]


def gaussian_coverage(scale: float, level: float, n_draws: int) -> float:
    """Expected rank-PIT coverage of the central ``level`` interval when the
    truth is ``N(0, 1)`` around the posterior and the ``n_draws`` draws are
    ``N(0, scale^2)``: a posterior ``scale`` times as wide as the exact one.

    ``scale = 1`` gives ``level`` exactly; the coverage rises with ``scale`` (to
    the binomial ranks' limit at ``scale -> inf``) and falls to 0 as it shrinks.

    Examples:
        >>> from torchcf.evaluation.sbc import gaussian_coverage
        >>> round(gaussian_coverage(1.0, 0.9, n_draws=10), 3)  # the exact width
        0.9
        >>> round(gaussian_coverage(2.0, 0.9, n_draws=10), 3)  # twice as wide
        0.98
    """
    z = np.linspace(-9.0, 9.0, 3601)  # the truth, standardised
    weight = stats.norm.pdf(z) * (z[1] - z[0])
    r = np.arange(n_draws + 1)
    # P(rank = r | z): each draw falls below the truth with probability Phi(z / scale)
    below = stats.norm.cdf(z / scale)[None]  # (1, grid)
    # the binomial pmf written out: scipy's overflows at probabilities of 0 or 1
    choose = np.array([math.comb(n_draws, k) for k in r], dtype=np.float64)
    pmf = (
        choose[:, None] * below ** r[:, None] * (1.0 - below) ** (n_draws - r)[:, None]
    )
    lo, hi = (1.0 - level) / 2.0, (1.0 + level) / 2.0
    left, right = r / (n_draws + 1), (r + 1) / (n_draws + 1)
    inside = np.clip(np.minimum(right, hi) - np.maximum(left, lo), 0.0, None)
    return float((pmf * weight).sum(1) @ (inside * (n_draws + 1)))


def width_factor(coverage: float, level: float, n_draws: int) -> float:
    """How many times wider than the exact posterior the draws are, read from an
    observed coverage under the Gaussian model of :func:`gaussian_coverage`
    (``< 1``: narrower). ``inf`` or ``0`` where the coverage lies beyond what any
    scale gives (the ranks' limits with few draws).

    Examples:
        >>> from torchcf.evaluation.sbc import width_factor
        >>> round(width_factor(0.9, 0.9, n_draws=10), 3)  # nominal coverage: width 1
        1.0
        >>> round(width_factor(0.98, 0.9, n_draws=10), 1)
        2.0
    """
    low, high = np.log(1e-3), np.log(1e3)
    if coverage >= gaussian_coverage(np.exp(high), level, n_draws):
        return math.inf
    if coverage <= gaussian_coverage(np.exp(low), level, n_draws):
        return 0.0
    for _ in range(60):  # bisection in log scale: coverage rises with the scale
        mid = 0.5 * (low + high)
        if gaussian_coverage(np.exp(mid), level, n_draws) < coverage:
            low = mid
        else:
            high = mid
    return float(np.exp(0.5 * (low + high)))


def pair_shares(slots: Tensor | np.ndarray) -> np.ndarray:
    """(N, M) each pair's share of its kept particles by model (rows sum to 1;
    a pair with no finite fit gets a row of NaN).

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.sbc import pair_shares
        >>> slots = np.array([[3, 1], [0, 0]])  # (N, M) kept particles by model
        >>> pair_shares(slots).tolist()  # the second pair has no fit
        [[0.75, 0.25], [nan, nan]]
    """
    counts = np.asarray(slots, dtype=np.float64)
    total = counts.sum(1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, counts / total, np.nan)


def confusion_matrix(
    shares: np.ndarray, label: Sequence[int], n_labels: int
) -> np.ndarray:
    """(n_labels, M) row ``i``: the mean share of each pool model over the pairs
    made by model ``i`` (pairs without a fit skipped; a label without pairs gets
    a row of NaN). Each row with pairs sums to 1.

    Args:
        shares: (N, M) per-pair shares (:func:`pair_shares`).
        label: (N,) generating model of each pair, in ``0 .. n_labels - 1``.
        n_labels: number of generating models.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.sbc import confusion_matrix
        >>> shares = np.array([[0.75, 0.25], [0.25, 0.75], [1.0, 0.0]])  # (N, M)
        >>> confusion_matrix(shares, label=[0, 1, 0], n_labels=2).tolist()
        [[0.875, 0.125], [0.25, 0.75]]
    """
    label = np.asarray(label)
    out = np.full((n_labels, shares.shape[1]), np.nan)
    for i in range(n_labels):
        rows = shares[label == i]
        rows = rows[np.isfinite(rows).all(1)]
        if len(rows):
            out[i] = rows.mean(0)
    return out
