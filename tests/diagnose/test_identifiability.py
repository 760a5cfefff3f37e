"""Identifiability of a found effect (torchcf.diagnose.arms.identifiability): the
within-pair correlation against NumPy, and a case where an effect trades off
against a model parameter (LLCS perceives s + d_offset - s0: only the difference
is identified)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from torchcf.abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from torchcf.abc.topn import TopN
from torchcf.diagnose.arms.identifiability import (
    effect_identifiability,
    within_pair_correlation,
)
from torchcf.models import get_model
from torchcf.models.effects import parse_effect
from torchcf.sim.synthetic import synthetic_pairs


def test_within_pair_correlation_matches_numpy():
    g = torch.Generator().manual_seed(0)
    theta = torch.randn(5, 8, 3, generator=g, dtype=torch.float64)
    theta[..., 2] += 0.8 * theta[..., 0] + torch.arange(5.0)[:, None]  # pair shifts
    score = torch.rand(5, 8, generator=g, dtype=torch.float64)
    score[1, 5:] = float("inf")  # empty slots
    score[4, 1:] = float("inf")  # a pair with one particle: left out
    correlation, n_pairs = within_pair_correlation(theta, score)
    centred = []
    for n in range(5):
        held = np.isfinite(score[n].numpy())
        if held.sum() < 3:
            continue
        rows = theta[n].numpy()[held]
        centred.append(rows - rows.mean(0))
    pooled = np.concatenate(centred)
    covariance = pooled.T @ pooled
    scale = np.sqrt(np.diag(covariance))
    expected = covariance / np.outer(scale, scale)
    assert n_pairs == 4
    np.testing.assert_allclose(correlation.numpy(), expected, rtol=1e-12)
    assert float(correlation[0, 2]) > 0.5  # the planted dependence, pair shifts removed


def test_an_offset_against_a_standstill_gap_is_reported_traded_off():
    """LLCS with a spacing offset: the accepted particles lie on d_offset - s0 =
    const per pair, so the two are strongly positively correlated."""
    name = "llcs+offset"
    pairs = synthetic_pairs(get_model(name), [20.0, 0.15, 0.8, -3.0], 6, 300, seed=2)
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    rollout = Rollout(pairs, dtype=torch.float64, compile="off")
    buffer = TopN(pairs.n_pairs, 15, model.n_params)
    run_rejection(
        prior_stream(model, bounds, 0, rollout),
        buffer,
        rollout,
        60_000,
        ModelProgress(),
    )
    posterior = SimpleNamespace(
        buffers={
            name: {"theta": buffer.theta, "score": buffer.score, "index": buffer.index}
        }
    )
    report = effect_identifiability(posterior, [parse_effect("offset")])
    row = report["offset"][name]["d_offset"]
    assert row.partner == "s0"
    assert row.r >= 0.7 and row.traded_off
    assert row.n_pairs == pairs.n_pairs
