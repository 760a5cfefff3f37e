"""Honest uncertainty of an evaluation: predictive coverage and bootstrap intervals.

Assembles, from what :func:`torchcf.evaluation.evaluate.evaluate_posterior` already
simulated (no second rollout), the numbers metrics.json, the report and
TensorBoard carry:

- per learned set (a model or ``"hybrid"``), flat keys added to its metrics:
  ``<metric>_low, <metric>_high`` for ``min, beta_ws, ws``: the percentile
  bootstrap interval over test pairs (:mod:`torchcf.evaluation.bootstrap`);
  ``coverage_<variable>_<pct>`` (variable ``spacing`` or ``speed``, pct the
  nominal level in %, e.g. ``coverage_spacing_90``) the fraction of observed
  points inside the central band, with ``_low, _high``; ``coverage_points``
  (observed points scored) and ``coverage_pairs_without_draws``; and
  ``coverage_curve``: ``{"levels": [...], "spacing": [...], "speed": [...]}``
  (:mod:`torchcf.evaluation.coverage`);
- ``hybrid_minus``: ``{model: {metric: {"value", "low", "high",
  "excludes_zero"}}}``, the paired bootstrap of the hybrid minus each model
  (negative: the hybrid is closer);
- ``shares``: ``{model: {"share", "low", "high"}}``, the hybrid's shares with
  their interval over training pairs
  (:func:`torchcf.posterior.tables.grouped_shares`, its ``all`` row);
- ``bootstrap``: how the intervals were made (resamples, level, seed).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..config import EvalConfig
from ..posterior import Posterior
from ..posterior.tables import ALL, Bootstrap, grouped_shares
from .bootstrap import (
    METRICS,
    TRANSPORT,
    cost_with_invalid,
    intervals,
    metric_draws,
    paired_differences,
    percentile_interval,
    resample_counts,
)
from .coverage import VARIABLES, PredictiveCDF, coverage_fractions

#: Streams of the run's seed, one per kind of resample.
TEST_STREAM, TRAIN_STREAM = "test pairs", "training pairs"
HYBRID = "hybrid"


def level_key(variable: str, level: float) -> str:
    """``coverage_<variable>_<pct>``, e.g. ``coverage_spacing_90``."""
    return f"coverage_{variable}_{round(100 * level):d}"


def uncertainty(
    costs: Mapping[str, Mapping[str, np.ndarray]],
    metrics: Mapping[str, Mapping[str, Any]],
    predictive: Mapping[str, PredictiveCDF],
    posterior: Posterior,
    settings: EvalConfig,
    seed: int,
) -> dict[str, Any]:
    """The coverage and bootstrap numbers of an evaluation (module docstring).

    Args:
        costs: per set, its (P, N) ``score, e_p, e_v, e_a`` on the test pairs.
        metrics: per set, :func:`~torchcf.evaluation.metrics.evaluate_costs`.
        predictive: per set, its CDF at the observations.
        posterior: the learned set (its shares over training pairs).
        settings: the run's ``eval`` section: ``beta`` of beta-WS, the
            resamples (``bootstrap``: all; ``bootstrap_transport``: those for
            WS and beta-WS), the intervals' coverage ``level``, the headline
            ``coverage_levels`` and the ``coverage_curve``'s levels.
        seed: the bootstrap's seed (``eval.seed``, or the run's ``abc.seed``
            when it is not set).

    Returns:
        ``{"per_set": {set: flat keys}, "hybrid_minus", "shares", "bootstrap"}``.
    """
    beta, n_bootstrap, level = settings.beta, settings.bootstrap, settings.level
    n_transport = settings.bootstrap_transport
    coverage_levels, coverage_curve = settings.coverage_levels, settings.coverage_curve
    names = list(costs)
    n_test = next(iter(costs.values()))["score"].shape[1]
    counts = resample_counts(n_test, n_bootstrap, seed, TEST_STREAM)  # (n_bootstrap, N)
    n_transport = min(n_transport, n_bootstrap)
    all_levels = sorted({*coverage_levels, *coverage_curve})
    draws: dict[str, dict[str, np.ndarray]] = {}
    per_set: dict[str, dict[str, Any]] = {}
    for name in names:
        c = costs[name]
        cost = cost_with_invalid(c["score"], c["e_p"], c["e_v"], c["e_a"])
        draws[name] = metric_draws(cost, counts, beta, n_transport)
        row: dict[str, Any] = {}
        for key, interval in intervals(
            {k: metrics[name][k] for k in METRICS}, draws[name], level
        ).items():
            row[f"{key}_low"], row[f"{key}_high"] = interval.low, interval.high
        if name in predictive:
            row.update(_coverage_keys(predictive[name], all_levels, coverage_levels,
                                      coverage_curve, counts, level))  # fmt: skip
        per_set[name] = row
    others = [n for n in names if n != HYBRID]
    differences = (
        paired_differences(metrics, draws, HYBRID, others, level)
        if HYBRID in names
        else {}
    )
    hybrid_minus = {
        other: {
            key: {**interval._asdict(), "excludes_zero": interval.excludes_zero()}
            for key, interval in row.items()
        }
        for other, row in differences.items()
    }
    return {
        "per_set": per_set,
        "hybrid_minus": hybrid_minus,
        "shares": _shares(posterior, n_bootstrap, level, seed),
        "bootstrap": {
            "unit": "test pair",
            "resamples": int(n_bootstrap),
            "resamples_transport": int(n_transport),
            "transport_metrics": list(TRANSPORT),
            "level": float(level),
            "seed": int(seed),
            "method": "percentile",
        },
    }


def _coverage_keys(
    cdf: PredictiveCDF,
    all_levels: Sequence[float],
    headline: Sequence[float],
    curve: Sequence[float],
    counts: np.ndarray,
    level: float,
) -> dict[str, Any]:
    """One set's coverage keys (module docstring)."""
    cov = cdf.counts(all_levels)
    fractions = cov.fractions()  # (2, levels)
    column = {q: k for k, q in enumerate(cov.levels.tolist())}
    out: dict[str, Any] = {}
    heads = [column[q] for q in headline]
    resampled = coverage_fractions(
        cov.inside[:, heads], cov.points, counts
    )  # (n_bootstrap, 2, headline)
    low, high = percentile_interval(resampled, level)  # (2, headline)
    for v, variable in enumerate(VARIABLES):
        for h, q in enumerate(headline):
            key = level_key(variable, q)
            out[key] = float(fractions[v, column[q]])
            out[f"{key}_low"], out[f"{key}_high"] = float(low[v, h]), float(high[v, h])
    out["coverage_points"] = int(cov.points.sum())
    out["coverage_pairs_without_draws"] = cov.pairs_without_draws
    out["coverage_curve"] = {
        "levels": [float(q) for q in curve],
        **{
            variable: [float(fractions[v, column[q]]) for q in curve]
            for v, variable in enumerate(VARIABLES)
        },
    }
    return out


def _shares(
    posterior: Posterior, n_bootstrap: int, level: float, seed: int
) -> dict[str, dict[str, float]]:
    """The hybrid's shares with their bootstrap interval over training pairs."""
    n_train = len(posterior.train_pair_ids)
    result = grouped_shares(
        posterior,
        [ALL] * n_train,
        by=ALL,
        bootstrap=Bootstrap(n_bootstrap, level, seed),
    )
    row = result.rows[0]  # every training pair
    return {
        model: {"share": row.share[m], "low": row.low[m], "high": row.high[m]}
        for m, model in enumerate(result.models)
    }


def tensorboard_scalars(result: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """``{model: {key: value}}`` for
    :meth:`torchcf.runs.tensorboard.RunLogger.evaluation` (tags
    ``eval/<key>/<model>``): the hybrid's differences as
    ``hybrid_minus_<metric>[_low|_high]`` and the shares as ``share[_low|_high]``;
    the per-set keys travel with the set's metrics."""
    out: dict[str, dict[str, float]] = {}
    for model, row in result["hybrid_minus"].items():
        for key, d in row.items():
            entry = out.setdefault(model, {})
            entry[f"hybrid_minus_{key}"] = d["value"]
            entry[f"hybrid_minus_{key}_low"] = d["low"]
            entry[f"hybrid_minus_{key}_high"] = d["high"]
    for model, s in result["shares"].items():
        entry = out.setdefault(model, {})
        entry["share"], entry["share_low"], entry["share_high"] = (
            s["share"], s["low"], s["high"],
        )  # fmt: skip
    return out


__all__ = ["HYBRID", "level_key", "tensorboard_scalars", "uncertainty"]
