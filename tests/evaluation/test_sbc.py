"""SBC rank statistics, coverage and the confusion matrix (torchcf.evaluation.sbc)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from torchcf.evaluation import sbc

N, L, K = 4000, 5, 2


def _replicates(scale: float, shift: float = 0.0, seed: int = 0):
    """Truth ~ N(0, 1); draws ~ N(shift, scale^2), N replicates of L draws."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.randn(N, K, generator=g, dtype=torch.float64)
    draws = shift + scale * torch.randn(N, L, K, generator=g, dtype=torch.float64)
    return truth, draws, g


def test_ranks_count_the_draws_below_the_truth():
    truth = torch.tensor([[0.5, 10.0]])
    draws = torch.tensor([[[0.1, 11.0], [0.9, 12.0], [0.4, 9.0]]])
    assert sbc.sbc_ranks(truth, draws).tolist() == [[2, 1]]


def test_ties_are_split_uniformly():
    truth = torch.zeros(6000, 1, dtype=torch.float64)
    draws = torch.zeros(6000, 2, 1, dtype=torch.float64)  # every draw ties
    ranks = sbc.sbc_ranks(truth, draws, generator=torch.Generator().manual_seed(1))
    counts = torch.bincount(ranks[:, 0], minlength=3).numpy()
    assert stats.chisquare(counts).pvalue > 0.01


def test_calibrated_posterior_gives_uniform_ranks_and_nominal_coverage():
    """Truth and draws from the same law: ranks uniform, coverage = level."""
    truth, draws, g = _replicates(1.0)
    ranks = sbc.sbc_ranks(truth, draws, generator=g)
    assert (sbc.uniformity_pvalue(ranks, L) > 0.01).all()
    pit = sbc.rank_pit(ranks, L, generator=g)
    assert stats.kstest(pit[:, 0].numpy(), "uniform").pvalue > 0.01
    coverage = sbc.central_coverage(pit, (0.5, 0.9))
    # binomial standard error at N = 4000 is <= 0.008
    assert torch.allclose(
        coverage[0], torch.tensor(0.5, dtype=torch.float64), atol=0.03
    )
    assert torch.allclose(
        coverage[1], torch.tensor(0.9, dtype=torch.float64), atol=0.02
    )
    assert sbc.rank_histogram(ranks, L).shape == (L + 1, K)
    assert int(sbc.rank_histogram(ranks, L).sum()) == N * K


def test_too_narrow_posterior_gives_u_shaped_ranks_and_low_coverage():
    truth, draws, g = _replicates(0.2)
    ranks = sbc.sbc_ranks(truth, draws, generator=g)
    counts = sbc.rank_histogram(ranks, L)[:, 0].numpy()
    assert counts[0] > 2 * counts[L // 2] and counts[L] > 2 * counts[L // 2]
    assert (sbc.uniformity_pvalue(ranks, L) < 1e-6).all()
    coverage = sbc.central_coverage(sbc.rank_pit(ranks, L, generator=g), (0.5,))
    assert (coverage < 0.4).all()


def test_too_wide_posterior_covers_more_than_nominal():
    truth, draws, g = _replicates(3.0)
    ranks = sbc.sbc_ranks(truth, draws, generator=g)
    counts = sbc.rank_histogram(ranks, L)[:, 0].numpy()
    assert counts[L // 2] > 2 * counts[0]  # a hump
    coverage = sbc.central_coverage(sbc.rank_pit(ranks, L, generator=g), (0.5, 0.9))
    assert (coverage[0] > 0.6).all() and (coverage[1] > 0.95).all()


def test_biased_posterior_gives_a_slope():
    truth, draws, g = _replicates(1.0, shift=1.0)
    counts = sbc.rank_histogram(sbc.sbc_ranks(truth, draws, generator=g), L)[:, 0]
    assert counts[0] > 3 * counts[L]  # the draws sit above the truth


def test_interval_width_of_uniform_draws():
    draws = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)[None, :, None]
    width = sbc.interval_width(draws, 0.9)
    assert width.shape == (1, 1)
    assert float(width) == pytest.approx(0.9)


def test_pair_shares_and_confusion_rows_sum_to_one():
    rng = np.random.default_rng(0)
    slots = rng.multinomial(5, [0.2] * 5, size=30)  # (N, M), 5 per pair
    slots[3] = 0  # a pair without any fit
    shares = sbc.pair_shares(slots)
    assert np.isnan(shares[3]).all()
    assert np.allclose(np.delete(shares, 3, 0).sum(1), 1.0)
    label = np.repeat(np.arange(3), 10)
    label[:10] = 0
    matrix = sbc.confusion_matrix(shares, label, 4)
    assert matrix.shape == (4, 5)
    assert np.allclose(matrix[:3].sum(1), 1.0)
    assert np.isnan(matrix[3]).all()  # no pairs made by label 3
    # row 0 is the mean over its pairs with a fit (pair 3 skipped)
    rows = [i for i in range(10) if i != 3]
    assert np.allclose(matrix[0], shares[rows].mean(0))


def test_confusion_of_a_perfect_recovery_is_the_identity():
    label = np.array([0, 0, 1, 2, 2])
    slots = np.eye(3)[label] * 5
    matrix = sbc.confusion_matrix(sbc.pair_shares(slots), label, 3)
    assert np.array_equal(matrix, np.eye(3))


def test_gaussian_coverage_is_nominal_at_the_exact_width():
    for n_draws in (5, 20):
        for level in (0.5, 0.9):
            assert sbc.gaussian_coverage(1.0, level, n_draws) == pytest.approx(
                level, abs=1e-6
            )


def test_width_factor_recovers_the_scale_of_the_draws():
    """Draws 2x (and 0.5x) as wide as the truth's law: the factor read from the
    observed coverage is within sampling error of 2 (0.5)."""
    for scale in (2.0, 0.5):
        truth, draws, g = _replicates(scale, seed=3)
        ranks = sbc.sbc_ranks(truth, draws, generator=g)
        coverage = sbc.central_coverage(sbc.rank_pit(ranks, L, generator=g), (0.5,))
        factor = sbc.width_factor(float(coverage.mean()), 0.5, L)
        assert factor == pytest.approx(scale, rel=0.2)
