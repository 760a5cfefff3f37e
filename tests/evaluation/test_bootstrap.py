"""Bootstrap over test pairs (torchcf.evaluation.bootstrap)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from torchcf.evaluation.bootstrap import (
    cost_with_invalid,
    intervals,
    metric_draws,
    paired_differences,
    percentile_interval,
    resample_counts,
)
from torchcf.evaluation.metrics import beta_wasserstein, min_distance, wasserstein


def test_resamples_are_seeded_multinomial_draws_of_every_unit():
    a = resample_counts(17, 50, seed=3, stream="test pairs")
    assert a.shape == (50, 17) and (a.sum(axis=1) == 17).all()
    assert np.array_equal(a, resample_counts(17, 50, seed=3, stream="test pairs"))
    assert not np.array_equal(a, resample_counts(17, 50, seed=4, stream="test pairs"))
    assert not np.array_equal(a, resample_counts(17, 50, seed=3, stream="other"))
    assert resample_counts(5, 0, 0, "x").shape == (0, 5)


def test_interval_of_a_mean_is_the_binomial_closed_form():
    """0/1 data with k ones among n: a resample's mean is Binomial(n, k/n) / n,
    so the percentile interval is its quantiles (to a step 1/n)."""
    n, k = 40, 12
    x = np.r_[np.ones(k), np.zeros(n - k)]
    counts = resample_counts(n, 20000, seed=0, stream="mean")
    low, high = percentile_interval(counts @ x / n, 0.9)
    ref_low, ref_high = stats.binom.ppf([0.05, 0.95], n, k / n) / n
    assert abs(low - ref_low) <= 1 / n + 1e-12
    assert abs(high - ref_high) <= 1 / n + 1e-12


def test_interval_of_a_mean_agrees_with_scipy_percentile_bootstrap():
    rng = np.random.default_rng(1)
    x = rng.gamma(2.0, 1.0, size=30)
    counts = resample_counts(len(x), 4000, seed=1, stream="mean")
    low, high = percentile_interval(counts @ x / len(x), 0.95)
    ref = stats.bootstrap(
        (x,), np.mean, n_resamples=4000, method="percentile",
        confidence_level=0.95, random_state=np.random.default_rng(2),
    ).confidence_interval  # fmt: skip
    # two Monte Carlo estimates of the same quantiles: within a few % of the spread
    spread = x.std() / np.sqrt(len(x))
    assert low == pytest.approx(ref.low, abs=0.15 * spread)
    assert high == pytest.approx(ref.high, abs=0.15 * spread)


def _costs(seed: int, p: int = 12, n: int = 7) -> np.ndarray:
    return np.random.default_rng(seed).gamma(2.0, 1.0, size=(p, n))


def test_resampled_metrics_are_the_metrics_of_the_repeated_columns():
    """The definition: a resample is the cost matrix with pair j's column
    repeated k_j times (SPEC section 6 on it), solved here as pair masses."""
    cost = _costs(0)
    cost[2, 3] = np.inf  # an invalid cell
    counts = resample_counts(cost.shape[1], 30, seed=0, stream="t")
    draws = metric_draws(cost, counts, beta=0.15, n_transport=30)
    for b, k in enumerate(counts):
        columns = np.repeat(np.arange(cost.shape[1]), k)
        repeated = cost[:, columns]
        assert draws["min"][b] == pytest.approx(min_distance(repeated), rel=1e-12)
        assert draws["ws"][b] == pytest.approx(wasserstein(repeated).value, rel=1e-9)
        assert draws["beta_ws"][b] == pytest.approx(
            beta_wasserstein(repeated, 0.15).value, rel=1e-9
        )


def test_a_pair_without_valid_particle_is_infinite_only_when_drawn():
    cost = _costs(1)
    cost[:, 0] = np.inf
    counts = resample_counts(cost.shape[1], 60, seed=2, stream="t")
    draws = metric_draws(cost, counts, beta=0.15, n_transport=60)
    drawn = counts[:, 0] > 0
    assert drawn.any() and (~drawn).any()
    for key in ("min", "beta_ws", "ws"):
        assert np.isinf(draws[key][drawn]).all(), key
        assert np.isfinite(draws[key][~drawn]).all(), key


def test_transport_metrics_take_the_first_resamples_only():
    counts = resample_counts(7, 40, seed=0, stream="t")
    draws = metric_draws(_costs(2), counts, beta=0.15, n_transport=10)
    assert draws["min"].shape == (40,) and draws["ws"].shape == (10,)
    assert draws["beta_ws"].shape == (10,)


def test_cost_with_invalid_marks_any_non_finite_error():
    score = np.ones((2, 2))
    e = np.ones((2, 2))
    e_v = e.copy()
    e_v[1, 0] = np.nan
    cost = cost_with_invalid(score, e, e_v, e)
    assert np.isinf(cost[1, 0]) and np.isfinite(cost).sum() == 3


def test_paired_difference_sign_and_the_noise_it_cancels():
    """B = A + 1 on every cell: every resample's min differs by exactly 1 and
    the paired interval is the point; an independent (unpaired) comparison of
    the same two intervals overlaps."""
    a = _costs(3, p=10, n=15) * np.linspace(0.2, 5.0, 15)[None, :]  # hard pairs
    b = a + 1.0
    counts = resample_counts(15, 500, seed=0, stream="t")
    values = {
        "a": {"min": min_distance(a), "beta_ws": 0.0, "ws": wasserstein(a).value},
        "b": {"min": min_distance(b), "beta_ws": 0.0, "ws": wasserstein(b).value},
    }
    draws = {
        "a": metric_draws(a, counts, 0.15, 50),
        "b": metric_draws(b, counts, 0.15, 50),
    }
    diff = paired_differences(values, draws, "a", ["b"], 0.95, keys=("min", "ws"))
    for key in ("min", "ws"):
        d = diff["b"][key]
        assert d.value == pytest.approx(-1.0)
        assert d.low == pytest.approx(-1.0) and d.high == pytest.approx(-1.0)
        assert d.excludes_zero()
    alone = {
        s: intervals({"min": values[s]["min"]}, draws[s], 0.95)["min"] for s in "ab"
    }
    assert alone["a"].high > alone["b"].low  # the unpaired intervals overlap
    same = paired_differences(values, draws, "a", ["a"], 0.95, keys=("min",))
    assert same["a"]["min"].low == same["a"]["min"].high == 0.0
    assert not same["a"]["min"].excludes_zero()


def test_infinite_on_both_sides_gives_no_interval():
    low, high = percentile_interval(np.array([np.nan, 1.0]), 0.9)
    assert np.isnan(low) and np.isnan(high)
    low, high = percentile_interval(np.empty(0), 0.9)
    assert np.isnan(low) and np.isnan(high)


def test_an_interval_reaching_infinite_draws_is_infinite_not_nan():
    """Linear interpolation between two infinite draws is inf - inf; the bound
    is then the (infinite) draw itself. A NaN draw still makes it NaN."""
    from torchcf.evaluation.bootstrap import percentile_interval

    draws = np.array([1.0, 2.0, 3.0] + [np.inf] * 7)
    low, high = percentile_interval(draws, 0.95)
    assert float(low) == pytest.approx(1.225)  # 1 + 0.025 x 9 steps of 1
    assert float(high) == np.inf
    low, high = percentile_interval(np.array([1.0, np.nan, 2.0]), 0.95)
    assert np.isnan(low) and np.isnan(high)
