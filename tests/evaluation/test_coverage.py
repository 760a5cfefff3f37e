"""Predictive coverage (torchcf.evaluation.coverage) against hand-derived references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcf import get_model
from torchcf.evaluation.coverage import (
    PredictiveCDF,
    add_draws,
    coverage_fractions,
    scored_steps,
    weighted_quantiles,
)

LEVELS = (0.1, 0.5, 0.9)


def _cdf(targets, mask=None):
    """A one-variable PredictiveCDF of targets (T, N)."""
    mask = torch.ones(targets.shape, dtype=torch.bool) if mask is None else mask
    return PredictiveCDF([targets], mask)


def test_draws_from_the_observations_law_cover_the_nominal_level():
    """Observations and draws from the same N(0, 1): the fraction inside the
    central q band is q within binomial error (points independent; P = 4000
    draws make the band's own error small beside it)."""
    gen = torch.Generator().manual_seed(0)
    T, P, N = 40, 4000, 25
    y = torch.randn(T, N, generator=gen, dtype=torch.float64)
    draws = torch.randn(T, P, N, generator=gen, dtype=torch.float64)
    cdf = _cdf(y)
    cdf.add([draws], torch.ones(P, N, dtype=torch.bool))
    counts = cdf.counts(LEVELS)
    points = T * N
    assert counts.points.sum() == points
    for q, fraction in zip(LEVELS, counts.fractions()[0], strict=True):
        sd = math.sqrt(q * (1 - q) / points)
        assert abs(fraction - q) < 4 * sd + 0.01, (q, fraction)


def test_a_too_narrow_predictive_distribution_undercovers():
    """Draws of N(0, 0.5^2) for observations of N(0, 1): the central q band
    covers P(|Z| < 0.5 z_q) = 2 Phi(0.5 Phi^-1((1 + q) / 2)) - 1 < q."""
    from scipy.stats import norm

    gen = torch.Generator().manual_seed(1)
    T, P, N = 40, 4000, 25
    y = torch.randn(T, N, generator=gen, dtype=torch.float64)
    draws = 0.5 * torch.randn(T, P, N, generator=gen, dtype=torch.float64)
    cdf = _cdf(y)
    cdf.add([draws], torch.ones(P, N, dtype=torch.bool))
    fractions = cdf.counts(LEVELS).fractions()[0]
    for q, fraction in zip(LEVELS, fractions, strict=True):
        expected = 2 * norm.cdf(0.5 * norm.ppf((1 + q) / 2)) - 1
        sd = math.sqrt(expected * (1 - expected) / (T * N))
        assert abs(fraction - expected) < 4 * sd + 0.01, (q, fraction, expected)


def test_a_degenerate_band_covers_nothing_unless_it_hits_the_point():
    T, P, N = 5, 7, 3
    y = torch.zeros(T, N, dtype=torch.float64)
    cdf = _cdf(y)
    cdf.add([torch.full((T, P, N), 1.0)], torch.ones(P, N, dtype=torch.bool))
    assert (cdf.counts(LEVELS).fractions() == 0).all()
    # every draw equal to the observation: Q(lo) = Q(hi) = y, inside
    exact = _cdf(y)
    exact.add([torch.zeros(T, P, N)], torch.ones(P, N, dtype=torch.bool))
    assert (exact.counts(LEVELS).fractions() == 1).all()


def test_membership_equals_the_band_of_weighted_quantiles():
    """inside <=> Q(lo) <= y <= Q(hi), with Q the inverted-CDF quantile of the
    weighted draws, on integer draws full of ties with the observations."""
    gen = torch.Generator().manual_seed(2)
    T, P, N = 30, 9, 6
    draws = torch.randint(0, 5, (T, P, N), generator=gen).double()
    y = torch.randint(0, 5, (T, N), generator=gen).double()
    weights = torch.randint(1, 4, (P,), generator=gen).double()
    cdf = _cdf(y)
    cdf.add([draws], torch.ones(P, N, dtype=torch.bool), weights)
    counts = cdf.counts(LEVELS)
    for k, q in enumerate(LEVELS):
        band = weighted_quantiles(draws, [(1 - q) / 2, (1 + q) / 2], weights)
        inside = (band[0] <= y) & (y <= band[1])  # (T, N)
        assert np.array_equal(counts.inside[0, k], inside.sum(dim=0).numpy()), q


def test_weighted_quantiles_are_numpys_inverted_cdf_with_equal_weights():
    gen = torch.Generator().manual_seed(3)
    draws = torch.randn(4, 11, 3, generator=gen, dtype=torch.float64)
    probs = [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0]
    ours = weighted_quantiles(draws, probs).numpy()  # (L, T, N)
    ref = np.quantile(draws.numpy(), probs, axis=1, method="inverted_cdf")
    np.testing.assert_array_equal(ours, ref)


def test_a_weight_of_two_is_a_particle_drawn_twice():
    gen = torch.Generator().manual_seed(4)
    T, P, N = 10, 6, 4
    draws = torch.randn(T, P, N, generator=gen, dtype=torch.float64)
    y = torch.randn(T, N, generator=gen, dtype=torch.float64)
    weights = torch.tensor([2.0, 1, 0, 1, 3, 1])
    weighted = _cdf(y)
    weighted.add([draws], torch.ones(P, N, dtype=torch.bool), weights)
    rows = torch.repeat_interleave(torch.arange(P), weights.long())
    repeated = _cdf(y)
    repeated.add([draws[:, rows]], torch.ones(len(rows), N, dtype=torch.bool))
    for a, b in zip(weighted.cdf(), repeated.cdf(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-15)


def test_invalid_rollouts_are_no_draws_and_a_pair_without_draws_is_not_covered():
    T, P, N = 6, 4, 2
    y = torch.zeros(T, N, dtype=torch.float64)
    draws = torch.zeros(T, P, N)
    draws[:, 0] = torch.nan  # an invalid rollout's garbage
    valid = torch.ones(P, N, dtype=torch.bool)
    valid[0] = False
    valid[:, 1] = False  # no particle valid on pair 1
    cdf = _cdf(y)
    cdf.add([draws], valid)
    counts = cdf.counts([0.5])
    assert counts.pairs_without_draws == 1
    assert counts.inside[0, 0].tolist() == [T, 0]
    assert counts.fractions()[0, 0] == pytest.approx(0.5)


def test_one_rollout_feeding_several_sets_equals_separate_adds():
    gen = torch.Generator().manual_seed(5)
    T, P, N = 12, 8, 3
    y = [torch.randn(T, N, generator=gen, dtype=torch.float64) for _ in range(2)]
    draws = [torch.randn(T, P, N, generator=gen) for _ in range(2)]  # float32
    valid = torch.rand(P, N, generator=gen) > 0.2
    mask = torch.ones(T, N, dtype=torch.bool)
    hybrid_weights = np.array([1, 0, 0, 2, 1, 0, 0, 1])
    together = [PredictiveCDF(y, mask), PredictiveCDF(y, mask)]
    add_draws([(together[0], None), (together[1], hybrid_weights)], draws, valid)
    alone = [PredictiveCDF(y, mask), PredictiveCDF(y, mask)]
    alone[0].add(draws, valid)
    alone[1].add(draws, valid, torch.as_tensor(hybrid_weights))
    for a, b in zip(together, alone, strict=True):
        assert torch.equal(a.below, b.below) and torch.equal(a.weight, b.weight)
        assert torch.equal(a.at_or_below, b.at_or_below)


def test_float32_draws_are_compared_with_the_observations_unrounded():
    """A float32 draw just below a float64 observation stays below (no rounding
    of the observation to float32)."""
    y = torch.tensor([[1.0 + 1e-12]], dtype=torch.float64)  # (T=1, N=1)
    draws = torch.ones(1, 1, 1, dtype=torch.float32)
    cdf = _cdf(y)
    cdf.add([draws], torch.ones(1, 1, dtype=torch.bool))
    below, at_or_below = cdf.cdf()
    assert below.item() == 1.0 and at_or_below.item() == 1.0


def test_step_zero_is_not_scored_and_masked_steps_are_not_points():
    mask = torch.ones(5, 2, dtype=torch.bool)
    mask[3:, 1] = False
    steps = scored_steps(mask)
    assert steps[0].sum() == 0 and steps.sum(dim=0).tolist() == [4, 2]
    assert mask.all(dim=0)[0]  # the input is not touched


def test_pooled_fractions_and_their_resamples():
    inside = np.array([[3, 0, 5]])  # (L=1, N=3)
    points = np.array([4, 2, 10])
    assert coverage_fractions(inside, points)[0] == pytest.approx(8 / 16)
    counts = np.array([[1, 1, 1], [3, 0, 0], [0, 1, 2]])  # (B, N)
    out = coverage_fractions(inside, points, counts)  # (B, L)
    np.testing.assert_allclose(out[:, 0], [8 / 16, 9 / 12, 10 / 22])


# ------------------------------------------------------------- end to end
SET_KEYS = (
    "min_low", "min_high", "beta_ws_low", "beta_ws_high", "ws_low", "ws_high",
    "coverage_spacing_50", "coverage_spacing_90", "coverage_speed_50",
    "coverage_speed_90", "coverage_spacing_90_low", "coverage_speed_50_high",
    "coverage_points", "coverage_pairs_without_draws", "coverage_curve",
)  # fmt: skip


def _check_metrics_json(result: dict, models: list[str]) -> None:
    for key in ("bootstrap", "coverage_levels", "hybrid_minus", "shares"):
        assert key in result, key
    assert result["bootstrap"]["resamples"] == 1000
    for entry in [*models, "hybrid"]:
        m = result[entry]
        for key in SET_KEYS:
            assert key in m, (entry, key)
        for key in ("min", "beta_ws", "ws"):
            if np.isfinite(m[key]) and np.isfinite(m[f"{key}_high"]):
                assert m[f"{key}_low"] <= m[key] <= m[f"{key}_high"], (entry, key)
        curve = m["coverage_curve"]
        assert len(curve["levels"]) == len(curve["spacing"]) == len(curve["speed"]) == 9
        assert np.all(np.diff(curve["spacing"]) >= 0)  # nested bands
        assert curve["spacing"][4] == m["coverage_spacing_50"]
    for model in models:
        d = result["hybrid_minus"][model]["min"]
        assert d["value"] == pytest.approx(
            result["hybrid"]["min"] - result[model]["min"]
        )
        assert d["excludes_zero"] == (d["low"] > 0 or d["high"] < 0)
        assert set(result["shares"][model]) == {"share", "low", "high"}


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A small run on synthetic pairs (no data needed), evaluated."""
    from tests.conftest import synthetic_pairs
    from tests.evaluation.test_evaluate import small_config
    from torchcf.evaluation.evaluate import evaluate_run
    from torchcf.train import train

    train_pairs = synthetic_pairs(n_pairs=6, n_steps=200, seed=1)
    test_pairs = synthetic_pairs(n_pairs=4, n_steps=200, seed=2)
    out = tmp_path_factory.mktemp("run")
    cfg = small_config()
    train(cfg, out, pairs=(train_pairs, test_pairs))
    result = evaluate_run(out, pairs=(train_pairs, test_pairs), progress=False)
    return cfg, out, test_pairs, result


def test_metrics_json_report_and_tensorboard_carry_the_new_numbers(evaluated):
    import json

    _, out, _, result = evaluated
    _check_metrics_json(result.to_json(), ["idm", "llctg"])
    assert json.loads((out / "metrics.json").read_text())["bootstrap"]["seed"] == 0
    table = (out / "report" / "table.md").read_text()
    assert "## Predictive coverage" in table and "Hybrid minus" in table
    assert (out / "report" / "calibration.png").is_file()
    from tensorboard.backend.event_processing.event_accumulator import (
        EventAccumulator,
    )

    tags = set()
    for events in (out / "tb").rglob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events))
        acc.Reload()
        tags |= set(acc.Tags()["scalars"])
    for tag in (
        "eval/coverage_spacing_90/hybrid",
        "eval/ws_low/hybrid",
        "eval/hybrid_minus_min/idm",
        "eval/share_high/llctg",
    ):
        assert tag in tags, tag


def test_hybrid_coverage_equals_its_own_rollout_and_bands(evaluated):
    """The hybrid's coverage, assembled from the single models' rollouts, equals
    the bands of a fresh rollout of its particles (weighted_quantiles)."""
    from torchcf.posterior import Posterior
    from torchcf.sim.rollout import simulate

    cfg, out, test, result = evaluated
    posterior = Posterior.load(out / "posterior.pt")
    spacing, speed, valid = [], [], []
    for name in posterior.models:
        theta = posterior.hybrid[name].theta
        if not len(theta):
            continue
        sim = simulate(get_model(name), theta.to(torch.float32), test, return_traj=True,
                       weights=cfg.abc.weights)  # fmt: skip
        spacing.append(test.x_lead.to(sim.x)[:, None, :] - sim.x)
        speed.append(sim.v)
        valid.append(sim.valid)
    steps = scored_steps(test.mask)
    valid_ = torch.cat(valid)  # (P, N)
    for variable, draws, target in (
        ("spacing", torch.cat(spacing, dim=1), test.x_lead - test.x_follow),
        ("speed", torch.cat(speed, dim=1), test.v_follow),
    ):
        for q in (0.5, 0.9):
            inside = 0
            for n in range(test.n_pairs):
                d = draws[:, valid_[:, n], n : n + 1]  # (T, P_n, 1)
                band = weighted_quantiles(d, [(1 - q) / 2, (1 + q) / 2])[..., 0]
                y = target[:, n].double()
                ok = (band[0] <= y) & (y <= band[1]) & steps[:, n]
                inside += int(ok.sum())
            fraction = inside / int(steps.sum())
            key = f"coverage_{variable}_{round(100 * q)}"
            band = result.sets["hybrid"].uncertainty.coverage[key]
            assert band.value == pytest.approx(fraction, abs=1e-12), key


@pytest.mark.slow  # the smoke study end to end
def test_smoke_config_end_to_end(tmp_path):
    """configs/smoke.json through `torchcf train`: metrics.json
    carries the coverage and bootstrap keys (real data: skips without
    TORCHCF_DATA)."""
    import json
    import os
    from pathlib import Path

    from torchcf.cli.train import main

    if not os.environ.get("TORCHCF_DATA"):
        pytest.skip("TORCHCF_DATA is not set: no real data to test against")
    config = Path(__file__).resolve().parents[2] / "configs" / "smoke.json"
    assert main([str(config), "--out", str(tmp_path / "run")]) == 0
    result = json.loads((tmp_path / "run" / "metrics.json").read_text())
    models = ["ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc"]
    _check_metrics_json(result, models)
    assert result["hybrid"]["coverage_points"] == 17 * 575


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_thresholds_turn_strict_and_weak_comparisons_into_one_kind(dtype):
    from torchcf.evaluation.coverage import thresholds

    gen = torch.Generator().manual_seed(6)
    x = torch.randn(5000, generator=gen).to(dtype)
    y = torch.cat(
        [
            torch.randn(3000, generator=gen, dtype=torch.float64),
            x[:1000].double(),  # exact ties
            x[1000:2000].double() + 1e-12,  # just above a draw
            x[2000:3000].double() - 1e-12,  # just below
        ]
    )
    lower, upper = thresholds(y[:, None], dtype)  # (Y, 1)
    exact_lt = x.double()[None, :] < y[:, None]
    exact_le = x.double()[None, :] <= y[:, None]
    assert torch.equal(x[None, :] <= lower, exact_lt)
    assert torch.equal(x[None, :] <= upper, exact_le)


def test_slicing_the_particles_changes_neither_costs_nor_coverage(
    evaluated, monkeypatch
):
    """Under a small trajectory budget the rollout runs in slices of particles:
    the same cost matrices and the same predictive sums."""
    import torchcf.evaluation.evaluate as evaluate
    from torchcf.posterior import Posterior

    cfg, out, test, _ = evaluated
    posterior = Posterior.load(out / "posterior.pt")
    whole: dict = {}
    _, costs = evaluate.evaluate_posterior(
        posterior,
        test,
        evaluate.EvaluationSettings.of(cfg),
        progress=False,
        predictive=whole,
    )
    per_particle = 6 * test.n_steps * test.n_pairs * 4
    monkeypatch.setattr(evaluate, "TRAJECTORY_BYTES", 3 * per_particle)
    sliced: dict = {}
    _, costs_sliced = evaluate.evaluate_posterior(
        posterior,
        test,
        evaluate.EvaluationSettings.of(cfg),
        progress=False,
        predictive=sliced,
    )
    for name in costs:
        for key in costs[name]:
            np.testing.assert_array_equal(costs[name][key], costs_sliced[name][key])
        assert torch.equal(whole[name].below, sliced[name].below), name
        assert torch.equal(whole[name].at_or_below, sliced[name].at_or_below), name
