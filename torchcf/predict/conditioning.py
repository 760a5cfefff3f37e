"""How a history conditions a driver's prediction, chosen on the training pairs.

Two designs (:mod:`torchcf.predict.history`):

- **rejection**: the hybrid's particles that reproduce the history best, their
  median predicting the rest (the hybrid as the prior over drivers);
- **shrinkage** of strength ``lambda`` around a model's pooled vector: that
  vector moved toward the history, as far as the history's fit is worth
  against ``lambda`` times the squared move in prior widths (a Gaussian prior
  around the pooled vector: its mode).

Which predicts new drivers best depends on how much a few seconds of driving
say about a driver, which depends on the data. So ``conditioning = "auto"``
judges every design (rejection, and shrinkage at each of :data:`STRENGTHS`
around each of the :data:`CENTERS` pooled vectors of the lowest training
objective) on the run's own training pairs as if they were new: each training
pair's history conditions, its rest is predicted and scored, and a pair's own
hybrid particles
are not its candidates (they were fitted on its rest); at most
:data:`JUDGED_PAIRS` training pairs, a seeded choice. The design of the lowest
mean spacing RMSE on the training pairs' rests predicts the test pairs. (The
population vector at the shrinkage's center was searched on every training
pair, the judged one included: one pair in the pooled mean.)

Shapes: N pairs (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..data import PairSet
from ..models import get_model
from .history import (
    DriverPosterior,
    driver_posterior,
    predict_rest,
    predictable,
    shrunk_fit,
)
from .population import PooledFit
from .scores import SpacingRMSE, summarize_rmse
from .trained import TrainedRun

#: The shrinkage strengths ``conditioning = "auto"`` judges.
STRENGTHS = (1.0, 3.0, 10.0, 30.0)
#: Pooled vectors judged as the shrinkage's center (the best by training
#: objective).
CENTERS = 3
#: Training pairs the designs are judged on at most (a seeded choice).
JUDGED_PAIRS = 64
#: The settings of ``conditioning``.
CONDITIONINGS = ("auto", "rejection", "shrinkage")


@dataclass(frozen=True)
class Design:
    """One way of conditioning on a history (module docstring).

    Attributes:
        kind: ``"rejection"`` or ``"shrinkage"``.
        strength: the shrinkage's ``lambda`` (None for rejection).
        center: the shrinkage's pooled vector (None for rejection).
    """

    kind: str
    strength: float | None = None
    center: PooledFit | None = None

    @property
    def label(self) -> str:
        if self.center is None:
            return self.kind
        return f"shrinkage {self.strength:g} around {self.center.model}"

    def posterior(
        self,
        run: TrainedRun,
        pairs: PairSet,
        history: float,
        *,
        keep: int,
        refine: int,
        seed: int,
        own_excluded: bool = False,
    ) -> DriverPosterior:
        """Every pair's own posterior from its history by this design."""
        if self.kind == "rejection":
            return driver_posterior(
                run,
                pairs,
                history,
                keep=keep,
                rounds=refine,
                seed=seed,
                own_excluded=own_excluded,
            )
        model = get_model(self.center.model)
        return shrunk_fit(
            model,
            self.center.theta()[0],
            run.priors[model.name],
            pairs,
            history,
            float(self.strength),
            seed=seed,
        )


def designs(conditioning: str, fits: list[PooledFit]) -> list[Design]:
    """The designs a ``conditioning`` setting judges, the shrinkage's around
    the :data:`CENTERS` best of the models' pooled vectors ``fits``."""
    if conditioning not in CONDITIONINGS:
        raise ValueError(
            f"conditioning must be one of {CONDITIONINGS}, got {conditioning!r}"
        )
    centers = sorted(fits, key=lambda f: (f.collided, f.objective))[:CENTERS]
    shrink = [Design("shrinkage", s, c) for c in centers for s in STRENGTHS]
    if conditioning == "rejection":
        return [Design("rejection")]
    if conditioning == "shrinkage":
        return shrink
    return [Design("rejection"), *shrink]


def judged(
    run: TrainedRun,
    candidates: list[Design],
    history: float,
    *,
    keep: int,
    refine: int,
    seed: int,
) -> tuple[Design, dict[str, float | None]]:
    """The design of the lowest mean rest spacing RMSE on the training pairs
    as if new (module docstring), and every design's (None: no training pair
    long enough; the first design is then taken)."""
    train = run.train
    usable = torch.nonzero(predictable(train, history)).squeeze(1)
    if len(candidates) == 1 or not len(usable):
        return candidates[0], {d.label: None for d in candidates}
    if len(usable) > JUDGED_PAIRS:  # a seeded choice: the same for every design
        draw = torch.randperm(
            len(usable), generator=torch.Generator().manual_seed(seed)
        )
        usable = torch.sort(usable[draw[:JUDGED_PAIRS]]).values
    some = train.subset(usable.tolist())
    found = {}
    for design in candidates:
        posterior = design.posterior(
            run, some, history, keep=keep, refine=refine, seed=seed,
            own_excluded=True,
        )  # fmt: skip
        found[design.label] = rest_scores(posterior, some)[0].mean
    best = min(
        candidates,
        key=lambda d: float("inf") if found[d.label] is None else found[d.label],
    )
    return best, found


def rest_scores(
    posterior: DriverPosterior, pairs: PairSet
) -> tuple[SpacingRMSE, torch.Tensor, torch.Tensor, object]:
    """The posterior's prediction of the pairs' rests: ``(summary, (T_rest, N)
    median spacing [m], (N,) collided particles, per-pair RMSE)``."""
    rest, median, collided = predict_rest(posterior, pairs)
    gap = rest.x_lead.double().cpu() - rest.x_follow.double().cpu() - rest.leader_length
    summary, per_pair = summarize_rmse(gap - median, rest.mask.cpu())
    return summary, median, collided, per_pair


__all__ = ["CONDITIONINGS", "STRENGTHS", "Design", "designs", "judged", "rest_scores"]
