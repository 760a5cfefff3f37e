"""The refinement of an amortised run (``abc.amortised.refine``).

The amortised samples of a model, scored into its per-pair buffer
(:mod:`torchcf.train.amortised`), are round 0 of a short SMC per training pair
(:func:`torchcf.abc.smc.refine_population`): per pair the ``population`` best
samples of the model form the first population, and ``rounds`` rounds of
``per_pair`` proposals each move it with SMC's kernel, every proposal scored and
offered to the same buffer. So a pair whose amortised samples fit poorly (a
series unlike the training's simulations, a model the estimator rarely
proposes for it) is corrected by simulations on the pair itself, at a cost of
``rounds * per_pair`` simulations per pair and model.

The samples enter with equal weights (``log r = 0``): their importance weights
against the prior would need the estimator's density of every sample; the
weights steer only which population member a proposal moves, and the hybrid
reads the buffers' scores alone.

Budget of a model with Q samples (:func:`refine_budget`): its particle indices
``0 .. Q - 1`` are the samples, round ``t``'s proposals follow
(:class:`~torchcf.abc.smc.Budget` with ``prior = Q``).

What it changed (:func:`refinement_result`, ``summary.json``'s
``amortised.refinement``): per model the share of the hybrid and the median
per-pair best score before (:func:`scores_before`, taken once every model's
samples are scored and kept in the checkpoint) and after.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from ..abc.hybrid import select
from ..abc.smc import Budget, parameter_buffer
from ..abc.topn import TopN
from ..config import TrainConfig
from .summary import RefinedModel, RefinementResult


def refine_budget(cfg: TrainConfig, samples: int, n_pairs: int) -> Budget:
    """A model's refinement after its ``samples`` amortised samples on
    ``n_pairs`` training pairs (module docstring)."""
    refine = cfg.abc.amortised.refine
    return Budget(samples, refine.per_pair, refine.rounds, n_pairs)


def median_best(buffer: TopN) -> float | None:
    """The median over the pairs of a buffer's best score (pairs without one
    left out; the lower of the two central values); None if no pair has one."""
    best = buffer.score[:, 0]  # (N,)
    finite = best[torch.isfinite(best)]
    return float(finite.median()) if finite.numel() else None


def _shares(cfg: TrainConfig, buffers: Sequence[TopN]) -> dict[str, float]:
    """The hybrid's shares of the run's buffers (``log r`` columns dropped)."""
    names = [spec.name for spec in cfg.models]
    plain = [parameter_buffer(b) for b in buffers]
    selection = select(
        plain,
        names,
        cfg.abc.top_n,
        mode=cfg.abc.selection,
        global_size=cfg.abc.global_size,
    )
    return selection.shares()


def scores_before(
    cfg: TrainConfig, buffers: dict[str, TopN]
) -> dict[str, dict[str, float | None]]:
    """Per model, its share of the hybrid and its median best score on the
    amortised samples alone (the run's checkpoint keeps it)."""
    names = [spec.name for spec in cfg.models]
    shares = _shares(cfg, [buffers[name] for name in names])
    return {
        name: {"share": shares[name], "median_best": median_best(buffers[name])}
        for name in names
    }


def refinement_result(
    cfg: TrainConfig,
    before: dict[str, dict[str, float | None]],
    buffers: dict[str, TopN],
    n_pairs: int,
) -> RefinementResult:
    """What the refinement changed, from the record before it and the buffers
    after it."""
    refine = cfg.abc.amortised.refine
    names = [spec.name for spec in cfg.models]
    after = _shares(cfg, [buffers[name] for name in names])
    per_pair = len(names) * refine.rounds * refine.per_pair
    return RefinementResult(
        rounds=refine.rounds,
        per_pair=refine.per_pair,
        population=refine.population,
        quantile=refine.quantile,
        simulations=per_pair * n_pairs,
        simulations_per_pair=per_pair,
        per_model={
            name: RefinedModel(
                share_before=_rounded(before[name]["share"]),
                share_after=_rounded(after[name]),
                median_best_before=_rounded(before[name]["median_best"]),
                median_best_after=_rounded(median_best(buffers[name])),
            )
            for name in names
        },
    )


def _rounded(value: float | None) -> float | None:
    """A value for the summary (6 decimals; None for a missing or non-finite
    one)."""
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), 6)


__all__ = ["median_best", "refine_budget", "refinement_result", "scores_before"]
