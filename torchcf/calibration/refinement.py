"""The refinement of an amortised calibration (``Amortised.refine``).

The amortised samples of a model, scored into its per-pair buffer
(:mod:`torchcf.calibration.estimator_samples`), are round 0 of a short SMC per training
pair (:func:`torchcf.abc.smc.refine_population`): per pair the ``population``
best samples of the model form the first population, and ``rounds`` rounds of
``per_pair`` proposals each move it with SMC's kernel, every proposal scored and
offered to the same buffer. So a pair whose amortised samples fit poorly (a
series unlike the training's simulations, a model the estimator rarely
proposes for it) is corrected by simulations on the pair itself, at a cost of
``rounds * per_pair`` simulations per pair and model.

The samples enter with equal weights (``log r = 0``): their importance weights
against the prior would need the estimator's density of every sample; the
weights steer only which population member a proposal moves, and the hybrid
reads the buffers' scores alone.

Budget of a model with Q samples (:meth:`Refinement.budget
<torchcf.calibration.Refinement.budget>`): its particle indices ``0 .. Q - 1``
are the samples, round ``t``'s proposals follow.

What it changed (:func:`refinement_result`, a run summary's
``amortised.refinement``): per model the share of the hybrid and the median
per-pair best score before (:func:`scores_before`, taken once every model's
samples are scored; a run's checkpoint keeps it) and after.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

from ..abc.hybrid import select
from ..abc.smc import parameter_buffer
from ..abc.topn import TopN
from ..runs.summary import RefinedModel, RefinementResult
from .methods import Refinement, SelectionRule


def median_best(buffer: TopN) -> float | None:
    """The median over the pairs of a buffer's best score (pairs without one
    left out; the lower of the two central values); None if no pair has one."""
    best = buffer.score[:, 0]  # (N,)
    finite = best[torch.isfinite(best)]
    return float(finite.median()) if finite.numel() else None


def _shares(
    names: Sequence[str], buffers: Mapping[str, TopN], selection: SelectionRule
) -> dict[str, float]:
    """The hybrid's shares of the buffers (``log r`` columns dropped)."""
    plain = [parameter_buffer(buffers[name]) for name in names]
    chosen = select(
        plain,
        list(names),
        selection.top_n,
        mode=selection.mode,
        global_size=selection.global_size,
    )
    return chosen.shares()


def scores_before(
    names: Sequence[str], buffers: Mapping[str, TopN], selection: SelectionRule
) -> dict[str, dict[str, float | None]]:
    """Per model, its share of the hybrid and its median best score on the
    amortised samples alone."""
    shares = _shares(names, buffers, selection)
    return {
        name: {"share": shares[name], "median_best": median_best(buffers[name])}
        for name in names
    }


def refinement_result(
    refine: Refinement,
    before: Mapping[str, Mapping[str, float | None]],
    buffers: Mapping[str, TopN],
    selection: SelectionRule,
    n_pairs: int,
) -> RefinementResult:
    """What the refinement changed, from the record before it and the buffers
    after it (the models in ``before``'s order)."""
    names = list(before)
    after = _shares(names, buffers, selection)
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


__all__ = ["median_best", "refinement_result", "scores_before"]
