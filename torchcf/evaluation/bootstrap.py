"""Bootstrap over test pairs: intervals on the headline numbers, and whether the
hybrid's lead over a single model is larger than its noise.

A resample draws the N test pairs with replacement; it is held as the counts
``k`` (N,) of how often each pair was drawn (a multinomial draw, the scheme of
:func:`torchcf.posterior.tables.grouped_shares`). Every metric is recomputed on
the resample *as SPEC section 6 defines it* on the cost matrix whose column
``j`` is repeated ``k_j`` times:

- minimum distance: ``sum_j k_j min_i C_ij / N``;
- WS and beta-WS: the exact LP again, with pair marginals ``k / N`` (identical
  columns merged, which changes no optimum:
  :func:`torchcf.evaluation.metrics._pair_mass`).
  These cost one network simplex per resample and set, so they take the first
  ``n_transport`` resamples only (config ``eval.bootstrap_transport``).
- predictive coverage: pooled points inside over points, per-pair counts
  weighted by ``k`` (:func:`torchcf.evaluation.coverage.coverage_fractions`).

Paired differences (hybrid minus model m) use the *same* resamples for both
sets, so what the two share (hard pairs are hard for both) cancels. The
interval is the percentile interval of the resampled values; a difference
whose interval excludes 0 is "larger than its interval".

Shapes: P particles, N test pairs, ``n_bootstrap`` resamples (``n_transport``
of them for WS and beta-WS), U resampled units.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from ..runs.metrics import METRICS, Interval
from .metrics import beta_wasserstein, wasserstein

#: Those that need an LP per resample.
TRANSPORT = ("beta_ws", "ws")


def resample_counts(
    n_units: int, n_bootstrap: int, seed: int, stream: str
) -> np.ndarray:
    """(n_bootstrap, U) int64: how often each of ``n_units`` units each resample draws.

    The draws come from ``(seed, crc32(stream))``, so each kind of resample
    (test pairs, training pairs) has its own stream of the run's seed.

    Examples:
        >>> from torchcf.evaluation.bootstrap import resample_counts
        >>> counts = resample_counts(3, n_bootstrap=5, seed=0, stream="test pairs")
        >>> counts.shape, counts.sum(axis=1).tolist()  # each resample draws 3 pairs
        ((5, 3), [3, 3, 3, 3, 3])
    """
    rng = np.random.default_rng([seed, zlib.crc32(stream.encode("utf-8"))])
    if n_bootstrap == 0 or n_units == 0:
        return np.zeros((n_bootstrap, n_units), dtype=np.int64)
    return rng.multinomial(n_units, np.full(n_units, 1.0 / n_units), size=n_bootstrap)


def percentile_interval(
    draws: np.ndarray, level: float
) -> tuple[np.ndarray, np.ndarray]:
    """Percentile interval along axis 0 of ``draws`` (n_bootstrap, ...).

    An infinite draw stays in (an infeasible resample is a real outcome); a
    NaN one (inf - inf) makes the interval NaN. No draws: NaN.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.bootstrap import percentile_interval
        >>> low, high = percentile_interval(np.arange(1.0, 102.0), level=0.9)
        >>> round(float(low), 3), round(float(high), 3)
        (6.0, 96.0)
    """
    if draws.shape[0] == 0:
        nan = np.full(draws.shape[1:], np.nan)
        return nan, nan.copy()
    tail = (1.0 - level) / 2.0
    with np.errstate(invalid="ignore"):
        low, high = np.quantile(draws, [tail, 1.0 - tail], axis=0)
        # Interpolating between two infinite draws gives inf - inf = NaN; the
        # neighbouring draw itself (both infinite there) is the bound.
        low = np.where(
            np.isnan(low), np.quantile(draws, tail, axis=0, method="lower"), low
        )
        high = np.where(
            np.isnan(high),
            np.quantile(draws, 1.0 - tail, axis=0, method="higher"),
            high,
        )
    return low, high


def cost_with_invalid(
    score: np.ndarray, e_p: np.ndarray, e_v: np.ndarray, e_a: np.ndarray
) -> np.ndarray:
    """(P, N) float64 score with every invalid cell at ``+inf`` (as
    :func:`torchcf.evaluation.metrics.evaluate_costs` sees it).

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.bootstrap import cost_with_invalid
        >>> score = np.array([[1.0, 2.0], [0.5, 3.0]])  # (P, N)
        >>> e_p = np.array([[0.1, np.nan], [0.2, 0.3]])  # [m]; NaN: an invalid rollout
        >>> cost_with_invalid(score, e_p, e_p, e_p).tolist()
        [[1.0, inf], [0.5, 3.0]]
    """
    cost = np.asarray(score, dtype=np.float64)
    valid = np.isfinite(cost)
    for e in (e_p, e_v, e_a):
        valid &= np.isfinite(np.asarray(e))
    return np.where(valid, cost, np.inf)


def metric_draws(
    cost: np.ndarray, counts: np.ndarray, beta: float, n_transport: int
) -> dict[str, np.ndarray]:
    """The metrics of one learned set on each resample.

    Args:
        cost: (P, N) costs, ``inf`` = invalid cell.
        counts: (n_bootstrap, N) resamples (:func:`resample_counts`).
        beta: beta of beta-WS.
        n_transport: resamples (the first ones) for WS and beta-WS.

    Returns:
        ``{"min": (n_bootstrap,), "beta_ws": (n_transport,), "ws": (n_transport,)}``
        (``n_transport`` capped at ``n_bootstrap``).

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.bootstrap import metric_draws
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N) costs
        >>> counts = np.array([[1, 1, 1], [3, 0, 0], [0, 0, 3]])  # 3 resamples of N = 3
        >>> draws = metric_draws(C, counts, beta=0.15, n_transport=2)
        >>> draws["min"].round(3).tolist(), draws["ws"].round(3).tolist()
        ([0.833, 1.0, 0.5], [1.0, 1.5])
    """
    n_test = cost.shape[1]
    best = cost.min(axis=0)  # (N,)
    # a pair drawn 0 times adds nothing, even when it has no valid particle
    with np.errstate(invalid="ignore"):  # 0 * inf, replaced by 0
        drawn = np.where(counts > 0, counts * best[None, :], 0.0)  # (n_bootstrap, N)
    out = {"min": drawn.sum(axis=1) / n_test}
    mass = list(counts[:n_transport] / n_test)  # n_transport of (N,)
    out["beta_ws"] = np.array(
        side_by_side(lambda b: beta_wasserstein(cost, beta, pair_mass=b).value, mass)
    )
    out["ws"] = np.array(
        side_by_side(lambda b: wasserstein(cost, pair_mass=b).value, mass)
    )
    return out


def side_by_side(solve: Callable[[np.ndarray], float], items: Sequence) -> list:
    """``[solve(item) for item in items]``, on as many threads as torch may use
    (the run's ``threads``): POT's network simplex releases the GIL, so two
    cores solve two resamples at once (ZalaZONE's 1 635 x 143 LPs: 20 ms each
    one at a time, 10 ms each two at a time). Each LP is solved alone, so the
    values are those of the loop."""
    workers = min(torch.get_num_threads(), len(items))
    if workers <= 1:
        return [solve(item) for item in items]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(solve, items))


def intervals(
    values: Mapping[str, float], draws: Mapping[str, np.ndarray], level: float
) -> dict[str, Interval]:
    """``{metric: Interval}`` from the full-sample values and their draws.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.bootstrap import intervals
        >>> draws = {"min": np.array([0.5, 1.0, 0.8])}  # 3 resamples
        >>> found = intervals({"min": 0.8}, draws, level=0.9)
        >>> found["min"].value, round(found["min"].low, 3), round(found["min"].high, 3)
        (0.8, 0.53, 0.98)
    """
    out = {}
    for key, value in values.items():
        low, high = percentile_interval(np.asarray(draws[key]), level)
        out[key] = Interval(float(value), float(low), float(high))
    return out


def paired_differences(
    values: Mapping[str, Mapping[str, float]],
    draws: Mapping[str, Mapping[str, np.ndarray]],
    reference: str,
    others: Sequence[str],
    level: float,
    keys: Sequence[str] = METRICS,
) -> dict[str, dict[str, Interval]]:
    """``reference`` minus each of ``others`` on the same resamples.

    Args:
        values: set -> metric -> full-sample value.
        draws: set -> metric -> (n_bootstrap,) resampled values, the same resamples for
            every set.
        reference: the set compared (the hybrid).
        others: the sets it is compared with.
        level: the interval's coverage.
        keys: the metrics.

    Returns:
        ``{other: {metric: Interval(reference - other, low, high)}}``; a
        negative difference of a distance favours the reference.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.bootstrap import paired_differences
        >>> values = {"hybrid": {"min": 0.8}, "idm": {"min": 1.0}}
        >>> draws = {
        ...     "hybrid": {"min": np.array([0.7, 0.8, 0.9])},  # the same 3 resamples
        ...     "idm": {"min": np.array([1.0, 1.1, 1.2])},
        ... }
        >>> found = paired_differences(values, draws, "hybrid", ["idm"], 0.9, ["min"])
        >>> difference = found["idm"]["min"]
        >>> round(difference.value, 3), difference.excludes_zero()  # the hybrid leads
        (-0.2, True)
    """
    out: dict[str, dict[str, Interval]] = {}
    for other in others:
        row = {}
        for key in keys:
            with np.errstate(invalid="ignore"):
                diff = np.asarray(draws[reference][key]) - np.asarray(draws[other][key])
                value = float(values[reference][key]) - float(values[other][key])
            low, high = percentile_interval(diff, level)
            row[key] = Interval(value, float(low), float(high))
        out[other] = row
    return out


__all__ = [
    "TRANSPORT",
    "cost_with_invalid",
    "intervals",
    "metric_draws",
    "paired_differences",
    "percentile_interval",
    "resample_counts",
]
