"""Honest uncertainty of an evaluation: predictive coverage and bootstrap intervals.

Assembles, from what :func:`torchcf.evaluation.evaluate.evaluate_posterior` already
simulated (no second rollout), the numbers metrics.json, the report and
TensorBoard carry (an :class:`Uncertainty`, of the records of
:mod:`torchcf.runs.metrics`; here by their keys in metrics.json):

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
from dataclasses import dataclass

import numpy as np

from ..config import EvalConfig
from ..posterior import Posterior
from ..posterior.tables import ALL, Bootstrap, grouped_shares
from ..runs.metrics import (
    METRICS,
    BootstrapSettings,
    CoverageCurve,
    Difference,
    Interval,
    SetMetrics,
    SetUncertainty,
    ShareInterval,
)
from .bootstrap import (
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


@dataclass(frozen=True)
class Uncertainty:
    """The coverage and bootstrap numbers of an evaluation
    (:func:`torchcf.evaluation.uncertainty.uncertainty`).

    Attributes:
        per_set: set -> its intervals and coverage.
        hybrid_minus: model -> metric -> the hybrid minus the model.
        shares: model -> the hybrid's share with its interval.
        bootstrap: how the intervals were made.

    Examples:
        What the record holds (:func:`uncertainty`'s example makes one):

        >>> import dataclasses
        >>> [f.name for f in dataclasses.fields(Uncertainty)]
        ['per_set', 'hybrid_minus', 'shares', 'bootstrap']
    """

    per_set: dict[str, SetUncertainty]
    hybrid_minus: dict[str, dict[str, Difference]]
    shares: dict[str, ShareInterval]
    bootstrap: BootstrapSettings


def level_key(variable: str, level: float) -> str:
    """``coverage_<variable>_<pct>``, e.g. ``coverage_spacing_90``.

    Examples:
        >>> from torchcf.evaluation.uncertainty import level_key
        >>> level_key("spacing", 0.9)
        'coverage_spacing_90'
    """
    return f"coverage_{variable}_{round(100 * level):d}"


def uncertainty(
    costs: Mapping[str, Mapping[str, np.ndarray]],
    metrics: Mapping[str, SetMetrics],
    predictive: Mapping[str, PredictiveCDF],
    posterior: Posterior,
    settings: EvalConfig,
    seed: int,
) -> Uncertainty:
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
        per set its intervals and coverage, the hybrid minus each model, the
        shares with their intervals, and the bootstrap's settings.

    Examples:
        >>> import numpy as np
        >>> import torch
        >>> from torchcf.config import EvalConfig
        >>> from torchcf.evaluation.metrics import evaluate_costs
        >>> from torchcf.evaluation.uncertainty import uncertainty
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N) costs
        >>> costs = {
        ...     "idm": dict(score=C, e_p=C, e_v=C, e_a=C),
        ...     "hybrid": dict(score=C[1:], e_p=C[1:], e_v=C[1:], e_a=C[1:]),
        ... }
        >>> metrics = {name: evaluate_costs(**c) for name, c in costs.items()}
        >>> idm = ModelParticles(
        ...     ("a", "b", "v0", "T", "s0", "delta"),
        ...     theta=torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 2).double(),
        ...     score=torch.tensor([0.4, 0.6]).double(),
        ...     pair_ids=torch.tensor([0, 1]),
        ...     particle_index=torch.tensor([7, 3]),
        ... )
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 1, ("idm",), {"idm": 1.0}, torch.tensor([0, 1]),
        ...     {"idm": idm}, {"idm": {}},
        ... )
        >>> settings = EvalConfig(bootstrap=50, bootstrap_transport=10)
        >>> found = uncertainty(costs, metrics, {}, posterior, settings, seed=0)
        >>> interval = found.per_set["idm"].intervals["min"]
        >>> round(interval.value, 3), interval.low <= interval.value <= interval.high
        (0.833, True)
        >>> round(found.hybrid_minus["idm"]["min"].value, 3)  # the hybrid minus IDM
        0.333
        >>> found.shares["idm"].share
        1.0
    """
    beta, n_bootstrap, level = settings.beta, settings.bootstrap, settings.level
    n_transport = settings.bootstrap_transport
    coverage_levels, coverage_curve = settings.coverage_levels, settings.coverage_curve
    names = list(costs)
    n_test = next(iter(costs.values()))["score"].shape[1]
    counts = resample_counts(n_test, n_bootstrap, seed, TEST_STREAM)  # (n_bootstrap, N)
    n_transport = min(n_transport, n_bootstrap)
    all_levels = sorted({*coverage_levels, *coverage_curve})
    values = {name: {k: getattr(metrics[name], k) for k in METRICS} for name in names}
    draws: dict[str, dict[str, np.ndarray]] = {}
    per_set: dict[str, SetUncertainty] = {}
    for name in names:
        c = costs[name]
        cost = cost_with_invalid(c["score"], c["e_p"], c["e_v"], c["e_a"])
        draws[name] = metric_draws(cost, counts, beta, n_transport)
        bounds = intervals(values[name], draws[name], level)
        per_set[name] = (
            _with_coverage(
                bounds,
                predictive[name],
                all_levels,
                coverage_levels,
                coverage_curve,
                counts,
                level,
            )  # fmt: skip
            if name in predictive
            else SetUncertainty(bounds)
        )
    others = [n for n in names if n != HYBRID]
    differences = (
        paired_differences(values, draws, HYBRID, others, level)
        if HYBRID in names
        else {}
    )
    hybrid_minus = {
        other: {key: Difference.of(interval) for key, interval in row.items()}
        for other, row in differences.items()
    }
    return Uncertainty(
        per_set=per_set,
        hybrid_minus=hybrid_minus,
        shares=_shares(posterior, n_bootstrap, level, seed),
        bootstrap=BootstrapSettings(
            unit="test pair",
            resamples=int(n_bootstrap),
            resamples_transport=int(n_transport),
            transport_metrics=TRANSPORT,
            level=float(level),
            seed=int(seed),
            method="percentile",
        ),
    )


def _with_coverage(
    bounds: dict[str, Interval],
    cdf: PredictiveCDF,
    all_levels: Sequence[float],
    headline: Sequence[float],
    curve: Sequence[float],
    counts: np.ndarray,
    level: float,
) -> SetUncertainty:
    """One set's intervals ``bounds`` with its coverage (module docstring)."""
    cov = cdf.counts(all_levels)
    fractions = cov.fractions()  # (2, levels)
    column = {q: k for k, q in enumerate(cov.levels.tolist())}
    bands: dict[str, Interval] = {}
    heads = [column[q] for q in headline]
    resampled = coverage_fractions(
        cov.inside[:, heads], cov.points, counts
    )  # (n_bootstrap, 2, headline)
    low, high = percentile_interval(resampled, level)  # (2, headline)
    for v, variable in enumerate(VARIABLES):
        for h, q in enumerate(headline):
            bands[level_key(variable, q)] = Interval(
                float(fractions[v, column[q]]), float(low[v, h]), float(high[v, h])
            )
    return SetUncertainty(
        intervals=bounds,
        coverage=bands,
        coverage_points=int(cov.points.sum()),
        coverage_pairs_without_draws=cov.pairs_without_draws,
        coverage_curve=CoverageCurve(
            levels=tuple(float(q) for q in curve),
            **{
                variable: tuple(float(fractions[v, column[q]]) for q in curve)
                for v, variable in enumerate(VARIABLES)
            },
        ),
    )


def _shares(
    posterior: Posterior, n_bootstrap: int, level: float, seed: int
) -> dict[str, ShareInterval]:
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
        model: ShareInterval(share=row.share[m], low=row.low[m], high=row.high[m])
        for m, model in enumerate(result.models)
    }


def tensorboard_scalars(result: Uncertainty) -> dict[str, dict[str, float]]:
    """``{model: {key: value}}`` for
    :meth:`torchcf.runs.tensorboard.RunLogger.evaluation` (tags
    ``eval/<key>/<model>``): the hybrid's differences as
    ``hybrid_minus_<metric>[_low|_high]`` and the shares as ``share[_low|_high]``;
    the per-set keys travel with the set's metrics.

    Examples:
        >>> import numpy as np
        >>> import torch
        >>> from torchcf.config import EvalConfig
        >>> from torchcf.evaluation.metrics import evaluate_costs
        >>> from torchcf.evaluation.uncertainty import uncertainty
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N) costs
        >>> costs = {
        ...     "idm": dict(score=C, e_p=C, e_v=C, e_a=C),
        ...     "hybrid": dict(score=C[1:], e_p=C[1:], e_v=C[1:], e_a=C[1:]),
        ... }
        >>> metrics = {name: evaluate_costs(**c) for name, c in costs.items()}
        >>> idm = ModelParticles(
        ...     ("a", "b", "v0", "T", "s0", "delta"),
        ...     theta=torch.tensor([[1.5, 2.0, 33.0, 1.2, 2.0, 4.0]] * 2).double(),
        ...     score=torch.tensor([0.4, 0.6]).double(),
        ...     pair_ids=torch.tensor([0, 1]),
        ...     particle_index=torch.tensor([7, 3]),
        ... )
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 1, ("idm",), {"idm": 1.0}, torch.tensor([0, 1]),
        ...     {"idm": idm}, {"idm": {}},
        ... )
        >>> settings = EvalConfig(bootstrap=50, bootstrap_transport=10)
        >>> found = uncertainty(costs, metrics, {}, posterior, settings, seed=0)
        >>> from torchcf.evaluation.uncertainty import tensorboard_scalars
        >>> scalars = tensorboard_scalars(found)
        >>> round(scalars["idm"]["hybrid_minus_min"], 3), scalars["idm"]["share"]
        (0.333, 1.0)
    """
    out: dict[str, dict[str, float]] = {}
    for model, row in result.hybrid_minus.items():
        for key, d in row.items():
            entry = out.setdefault(model, {})
            entry[f"hybrid_minus_{key}"] = d.value
            entry[f"hybrid_minus_{key}_low"] = d.low
            entry[f"hybrid_minus_{key}_high"] = d.high
    for model, s in result.shares.items():
        entry = out.setdefault(model, {})
        entry["share"], entry["share_low"], entry["share_high"] = s.share, s.low, s.high
    return out


__all__ = ["HYBRID", "Uncertainty", "level_key", "tensorboard_scalars", "uncertainty"]
