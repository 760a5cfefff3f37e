"""How the attribution judges an arm out of sample (``diagnose.validation``).

An arm is fitted on one part of the training data and judged on another that
its search never saw; four designs split the data:

- ``"time"``: every training pair is split in time (:func:`split_in_time`).
  The arms are fitted on the first ``fit_fraction`` of its steps (the *fit
  windows*); per pair, the arm's ``top_n`` best (the hybrid's picks of that
  pair) are scored on the rest (the *validation window*, begun from the
  observed state at the split, or earlier with ``validation_warmup``, the
  early steps unscored, so that a memory effect enters it with the recorded
  history: :class:`WarmedRollout`), and the pair's value is their median
  (:func:`~torchcf.diagnose.arms.population.pick_scores`). It asks: does the fit of
  *this* driver carry forward in time?
- ``"pairs"``: the training pairs are split in two by a seeded draw
  (:func:`split_by_pair`): the arms are fitted on the whole windows of
  ``fit_fraction`` of them (the *fit pairs*); every other pair (a *held-out
  pair*) is scored by the best of all the arm's picks, pooled over the fit
  pairs (:func:`coverage_scores`): SPEC section 6's minimum distance, on pairs
  the arm never saw. It asks what the test split asks: does the learned set
  cover drivers it has not seen? Pairs, not windows, are then the units of the
  sign-flip test; they are independent of the fit given the fit pairs, so the
  test is exact as in the time design.
- ``"refit"``: the split of ``"pairs"``, but every held-out pair is refitted
  by a short local search of its own, from the placebo's picks without the
  effect and from the effect arm's picks with it (pinned at the value the fit
  pairs gave; common random numbers: :mod:`torchcf.diagnose.arms.refit`), and the
  two refits' scores compared. It asks whether the model *class* with the
  effect fits drivers it has not seen better, where ``"pairs"`` asks whether
  the arm's few hundred particles happen to lie near them: with drivers who
  differ, as measured drivers do, that is ruled by how sparse the particles
  are, not by the effect.
- ``"crossfit"``: every training pair is held out once. The arms are fitted
  on the whole windows of every training pair; every pair is then refitted
  as in ``"refit"``, its candidates the picks of the pairs of *other groups*
  only (:func:`pair_groups`: a group is the windows of one follower in one
  run where the data's ``index.csv`` says so, else the pair alone), in one
  batched search (:class:`~torchcf.diagnose.arms.refit.Exclusion`). All N pairs
  are units of the test where ``"refit"`` has the 40 % no arm saw. What is
  not held out: the effect's pinned value (a driver effect's median over
  every pair's picks, a shared effect's one value) and the order of the
  tests are learned on all the pairs, each pair one of N; the test is then
  not exact by construction, and its false-choice rate on data without the
  effect is measured instead (``docs/loop.md``, *Power on small sets*).
- ``"auto"`` (the default): ``"crossfit"`` where the training pairs are
  enough for the test, else ``"time"`` (:func:`resolve_validation`). A
  sign-flip test over V units cannot give a p-value below ``2^-V`` (all V
  drops positive), and the test's own resolution is ``1 / (permutations +
  1)``; the units are enough when ``2^-V`` is below that resolution (V >= 15
  at the default 20 000 permutations), so that no test of the step is denied
  a level the time design could reach. A ``validation_warmup`` asks for the
  time design.

Shapes: N pairs, S slots per pair, Q particles, V held-out pairs
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch
from torch import Tensor

from ...abc.rejection import Rollout
from ...config import DiagnoseConfig
from ...data import PairSet
from ...models import CFModel
from ..setup import LoopSetup
from ..signatures.series import DiagnoseError
from .population import Population, pick_scores
from .refit import (
    Exclusion,
    Layout,
    Pin,
    RefitBudget,
    candidates,
    refit_paired,
    refit_scores,
    sourced_candidates,
)

if TYPE_CHECKING:
    import pandas as pd

#: Shortest out-of-sample window that counts for a pair [steps].
MIN_VALIDATION_STEPS = 20
#: Fewest pairs on either side of a split by pair.
MIN_PAIRS = 2


# --------------------------------------------------------- split in time
def split_in_time(pairs: PairSet, fraction: float) -> tuple[PairSet, PairSet]:
    """The first ``fraction`` of the steps and the rest, for the same pairs.

    Pairs with fewer than :data:`MIN_VALIDATION_STEPS` valid steps in the second
    part are dropped from both, so both sets hold the same pairs.

    Returns:
        ``(fit, validation)``; the validation set starts from the observed state at
        the split step.

    Raises:
        DiagnoseError: a window would be too short, or fewer than 2 pairs are
            long enough.
    """
    pairs, split = _long_enough(pairs, fraction)
    return _window(pairs, slice(0, split)), _window(pairs, slice(split, None))


def warmed_validation(
    pairs: PairSet, fraction: float, warmup: int
) -> tuple[PairSet, PairSet]:
    """The validation windows of :func:`split_in_time`, each begun ``warmup``
    steps early: ``(long, warm)``, the steps ``split - warmup ..`` to the end and
    ``split - warmup .. split - 1``, for the same pairs (:class:`WarmedRollout`
    scores the difference). ``warmup`` is cut to the fit window's length."""
    pairs, split = _long_enough(pairs, fraction)
    start = split - min(warmup, split - 1)
    return _window(pairs, slice(start, None)), _window(pairs, slice(start, split))


def _long_enough(pairs: PairSet, fraction: float) -> tuple[PairSet, int]:
    """The pairs with a validation window of at least
    :data:`MIN_VALIDATION_STEPS` valid steps, and the split step."""
    split = int(round(fraction * pairs.n_steps))
    if split < MIN_VALIDATION_STEPS or pairs.n_steps - split < MIN_VALIDATION_STEPS:
        raise DiagnoseError(
            f"diagnose.fit_fraction={fraction}: {pairs.n_steps} steps leave a fit "
            f"or validation window under {MIN_VALIDATION_STEPS} steps"
        )
    keep = pairs.mask[split:].sum(0) >= MIN_VALIDATION_STEPS
    if int(keep.sum()) < 2:
        raise DiagnoseError(
            "fewer than 2 training pairs are long enough for out-of-sample "
            "validation; lower diagnose.fit_fraction"
        )
    return pairs.subset(keep), split


def _window(pairs: PairSet, rows: slice) -> PairSet:
    """The steps ``rows`` of every pair (a validation window starts from the
    observed state at its first step)."""
    return pairs.steps(rows.start, rows.stop)


@dataclass(frozen=True)
class WarmedRollout(Rollout):
    """Scores on validation windows begun early, the early steps unscored.

    The rollout runs on the long windows (``pairs``: the warm-up, then the
    validation window) and on their warm-ups alone (``warm``); being causal and
    deterministic, the latter repeats the long rollout's first steps exactly. The
    validation window's RMSE per channel c is then
    ``sqrt((n_long e_c,long^2 - n_warm e_c,warm^2) / (n_long - n_warm))`` and its
    score ``sum_c w_c e_c`` (SPEC section 4's score over the window's steps), so
    a memory effect (delay, lag, sync) enters the window with the history the
    recorded leader gave it instead of a steady past. Invalid (``+inf``) when the
    long rollout is.
    """

    warm: PairSet | None = None

    def score(self, model, theta, pair, *, chunk=None, compiled=False, ceiling=None):
        # no early rejection: the window's score is a difference of two rollouts'
        if pair is None or self.warm is None:
            raise ValueError("a warmed validation scores paired particles only")
        run = {"chunk": chunk, "compiled": compiled}
        long = self.rollouts(model, theta, pair, **run)
        early = dataclasses.replace(self, pairs=self.warm).rollouts(
            model, theta, pair, **run
        )
        n_long = self.pairs.mask.sum(0).to(torch.float64)[pair]  # (P,)
        n_warm = self.warm.mask.sum(0).to(torch.float64)[pair]
        score = torch.zeros_like(n_long)
        for weight, channel in zip(self.weights, ("e_p", "e_v", "e_a"), strict=True):
            e_long = getattr(long, channel).double().cpu()
            e_warm = getattr(early, channel).double().cpu()
            sse = n_long * e_long**2 - n_warm * e_warm**2
            score += weight * torch.sqrt(sse.clamp(min=0) / (n_long - n_warm))
        valid = long.valid.cpu()
        return torch.where(valid, score, math.inf), valid


def validation_rollout(setup: LoopSetup, train_pairs: PairSet) -> Rollout | None:
    """The validation windows' :class:`WarmedRollout` when
    ``diagnose.validation_warmup`` asks for one, else None."""
    settings = setup.settings
    steps = int(round(settings.validation_warmup / train_pairs.dt))
    if steps < 1:
        return None
    long, warm = warmed_validation(train_pairs, settings.fit_fraction, steps)
    plain = setup.rollout(long)
    return WarmedRollout(**vars(plain), warm=warm)


# ---------------------------------------------------------- split by pair
def split_by_pair(
    pairs: PairSet, fraction: float, seed: int
) -> tuple[PairSet, PairSet]:
    """``fraction`` of the pairs (a seeded draw, kept in their order) and the
    rest: ``(fit, held_out)``, whole windows both.

    Raises:
        DiagnoseError: fewer than :data:`MIN_PAIRS` pairs on a side.
    """
    fit, held = pair_split(pairs.n_pairs, fraction, seed)
    return pairs.subset(fit), pairs.subset(held)


def pair_split(n_pairs: int, fraction: float, seed: int) -> tuple[Tensor, Tensor]:
    """The positions (ascending, int64) of the fit pairs and of the held-out
    pairs of :func:`split_by_pair`.

    Raises:
        DiagnoseError: fewer than :data:`MIN_PAIRS` pairs on a side.
    """
    n_fit = n_pairs - held_out_count(n_pairs, fraction)
    if min(n_fit, n_pairs - n_fit) < MIN_PAIRS:
        raise DiagnoseError(
            f"diagnose.validation='pairs' with fit_fraction={fraction} leaves fewer "
            f"than {MIN_PAIRS} of the {n_pairs} training pairs on a side; "
            "use diagnose.validation='time'"
        )
    draw = torch.randperm(n_pairs, generator=torch.Generator().manual_seed(seed))
    return torch.sort(draw[:n_fit]).values, torch.sort(draw[n_fit:]).values


def fit_part(
    setup: LoopSetup, seed: int, n_steps: int, series: dict[str, list[np.ndarray]]
) -> dict[str, list[np.ndarray]]:
    """The part of per-pair series (one array per training pair, in order) that
    the arms are fitted on: every pair's fit window, or the fit pairs whole; what
    is decided from it (a road profile's knot spacing) never sees the data the
    arms are judged on."""
    settings = setup.settings
    n_pairs = len(next(iter(series.values()), []))
    kind = resolve_validation(settings, n_pairs)
    if kind == "crossfit":
        return {key: list(arrays) for key, arrays in series.items()}
    if held_out(kind):
        fit, _ = pair_split(n_pairs, settings.fit_fraction, seed)
        kept = fit.tolist()
        return {key: [arrays[i] for i in kept] for key, arrays in series.items()}
    steps = int(round(settings.fit_fraction * n_steps))
    return {key: [a[:steps] for a in arrays] for key, arrays in series.items()}


def coverage_scores(population: Population, n: int, rollout: Rollout) -> Tensor:
    """(V,) float64: per held-out pair of ``rollout``, the lowest score of the
    population's ``n`` best per pair, pooled over its pairs (every pick on
    every held-out pair: the rollout's full layout, ``Q * V`` rollouts);
    ``+inf`` where none is valid.

    This is SPEC section 6's minimum distance per test pair, with the picks as
    the learned set and the held-out pairs as the test pairs."""
    picks = population.best(n)
    every_pair = dataclasses.replace(rollout, paired=False)
    best = torch.full((rollout.pairs.n_pairs,), math.inf, dtype=torch.float64)
    for model in picks.models:
        pair, slot = picks.model_slots(model)
        if pair.numel() == 0:
            continue
        theta = picks.theta[pair, slot, : model.n_params]  # (Q, K)
        score, _ = every_pair.score(model, theta, None)  # (Q, V)
        best = torch.minimum(best, score.cpu().min(0).values)
    return best


# ------------------------------------------------------------- the design
def held_out_count(n_pairs: int, fraction: float) -> int:
    """V, the training pairs :func:`split_by_pair` holds out."""
    return n_pairs - int(round(fraction * n_pairs))


def resolve_validation(settings: DiagnoseConfig, n_pairs: int) -> str:
    """``diagnose.validation``, with ``"auto"`` resolved (module docstring):
    ``"crossfit"`` when the training pairs reach the sign-flip test's
    resolution (``2^-N <= 1 / (permutations + 1)``) and no warm-up asks for
    windows in time, else ``"time"``."""
    if settings.validation != "auto":
        return settings.validation
    if settings.validation_warmup > 0:
        return "time"
    enough = math.ceil(math.log2(settings.permutations + 1))
    return "crossfit" if n_pairs >= enough else "time"


def held_out(kind: str) -> bool:
    """Whether a design judges on held-out pairs (``"pairs"``, ``"refit"``,
    ``"crossfit"``)."""
    return kind in ("pairs", "refit", "crossfit")


def refits(kind: str) -> bool:
    """Whether a design refits its units with and without the effect
    (``"refit"``, ``"crossfit"``)."""
    return kind in ("refit", "crossfit")


def pair_groups(pairs: PairSet, index: pd.DataFrame | None) -> Tensor:
    """(N,) int64 each pair's cross-fitting group (0..G-1, in order of first
    appearance): the pairs that share a follower in one run (``index.csv``'s
    ``run`` and ``follower`` of the pair's row ``pair_ids``) form one group, so
    that no window of a driver is refitted from the picks of another window of
    the same driver in the same run; without an index (or one that does not
    cover the pairs) each pair is its own group."""
    n = pairs.n_pairs
    ids = list(pairs.pair_ids)
    if index is None or not {"run", "follower"} <= set(index.columns):
        return torch.arange(n)
    if len(index) <= max(ids, default=-1):
        return torch.arange(n)
    keys = [(index["run"].iat[i], index["follower"].iat[i]) for i in ids]
    labels: dict[tuple, int] = {}
    return torch.tensor([labels.setdefault(k, len(labels)) for k in keys])


@dataclass(frozen=True)
class Validation:
    """Out-of-sample scores of an arm (module docstring).

    Attributes:
        kind: ``"time"`` (validation windows of the fit pairs), ``"pairs"``
            (held-out pairs, the pooled picks' coverage) or ``"refit"``
            (held-out pairs, each refitted).
        rollout: simulates on the validation windows, or on the held-out pairs.
        budget: a validation unit's refit (the test of ``"refit"``; the
            profile of :meth:`Judge.profile` in every design).
        priors: the run's prior box (K, 2) per pool model.
        seed: the attribution's seed (the refits' random numbers).
        groups: (N,) int64 each training pair's group (``"crossfit"``: a pair
            is refitted from the picks of the other groups only).
        scored_on: with ``diagnose.refit_effect = "free"``, the judged pairs'
            later steps (``rollout`` then holds their first ``fit_fraction``):
            a refit searches a driver effect per pair on the first steps and
            is scored on the rest (:func:`free_effect_windows`); None: a
            refit is scored where it searched.
    """

    kind: Literal["time", "pairs", "refit", "crossfit"]
    rollout: Rollout
    budget: RefitBudget | None = None
    priors: dict[str, Tensor] = dataclasses.field(default_factory=dict)
    seed: int = 0
    groups: Tensor | None = None
    scored_on: Rollout | None = None

    judged: Tensor | None = None

    @property
    def n_units(self) -> int:
        """The validation units: pairs with a validation window, or held-out
        pairs."""
        return self.rollout.pairs.n_pairs

    @property
    def units(self) -> str:
        """What one value of :meth:`scores` is, for the report."""
        if self.kind == "crossfit":
            return "training pairs, each held out once"
        return "validation windows" if self.kind == "time" else "held-out pairs"

    def scores(self, population: Population, n: int) -> np.ndarray:
        """(U,) float64, one value per validation unit (a fit pair's validation
        window, or a held-out pair covered by the pooled picks); ``+inf`` where
        invalid. Not for ``"refit"``, which scores two arms together
        (:meth:`judge`)."""
        if self.kind == "time":
            return pick_scores(population, n, self.rollout).numpy()
        if self.kind == "pairs":
            return coverage_scores(population, n, self.rollout).numpy()
        raise ValueError("a refit judges an arm against the placebo: use judge()")

    def refit(
        self,
        arm: Population,
        n: int,
        current: dict[CFModel, CFModel],
        shared: dict[str, Tensor],
        pin: Pin | None = None,
        *,
        key: tuple,
        budget: RefitBudget | None = None,
        as_pinned: bool = False,
    ) -> np.ndarray:
        """(V,) float64 each held-out pair's score after its refit from the
        picks of ``arm`` (``n`` per pair, as their current models:
        :func:`~torchcf.diagnose.arms.refit.candidates`; cross-fitting: those of
        the other groups), with the effect ``pin`` held at its value (None:
        without; ``as_pinned``: held there even where ``refit_effect`` frees
        a driver effect, as the power analysis's sizes are)."""
        budget = budget or self.budget
        if budget is None:
            raise ValueError("a refit needs its budget")
        key = (self.seed, *key)
        exclusion = None
        if self.kind == "crossfit":
            groups = self.groups
            if groups is None:
                groups = torch.arange(arm.n_pairs)
            members, sources = sourced_candidates(arm, n, current, self.seed, groups)
            held = groups if self.judged is None else groups[self.judged]
            exclusion = Exclusion(sources, held)
        else:
            members = candidates(arm, n, current, self.seed)
        free = self.scored_on is not None and not as_pinned
        if pin is not None and free and not pin.effect.shared:
            pin = dataclasses.replace(pin, free=True)
        layout = Layout(exclusion, self.scored_on)
        return refit_scores(
            members, self.rollout, budget, self.priors, shared, key, pin, layout
        ).numpy()

    def judge(
        self,
        placebo: Population,
        n: int,
        step: int,
        shared: dict[str, Tensor] | None = None,
    ) -> Judge:
        """The step's judge of effect arms against its placebo arm."""
        shared = dict(shared or {})
        if refits(self.kind):
            before = self.refit(placebo, n, {}, shared, key=("refit", step))
        else:
            before = self.scores(placebo, n)
        return Judge(self, placebo, n, step, shared, before)


@dataclass(frozen=True)
class Judge:
    """Judges the effect arms of one step against its placebo arm.

    Attributes:
        validation: the design.
        placebo: the step's placebo arm.
        n: picks per pair (``abc.top_n``).
        step: the step (its refits' random numbers).
        shared: per chosen shared effect, its value (pinned on both sides).
        before: the placebo's scores per unit (a refit's: each held-out pair
            refitted from the placebo's picks, without the effect).
    """

    validation: Validation
    placebo: Population
    n: int
    step: int
    shared: dict[str, Tensor]
    before: np.ndarray

    def __call__(
        self, arm: Population, lifted_from: dict[CFModel, CFModel], pin: Pin | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(U,) float64 each: the scores per unit without and with the effect.

        Args:
            arm: the effect arm.
            lifted_from: per variant carrying the effect, the current model it
                was lifted from.
            pin: the effect at the value the fit pairs gave it (``"refit"``;
                None for the others, which score the arm's own particles).
        """
        v = self.validation
        if not refits(v.kind):
            return self.before, v.scores(arm, self.n)
        if pin is None:
            raise ValueError("a refit needs the effect's value")
        current = dict(lifted_from)
        key = ("refit", self.step)
        after = v.refit(arm, self.n, current, self.shared, pin, key=key)
        return self.before, after

    def profile(self, pin: Pin | None) -> np.ndarray:
        """(U,) float64 every validation unit refitted from the placebo's picks,
        the effect ``pin`` held at its value (None: without it), with the step's
        random numbers: held-out pairs from the pooled picks (``"refit"``,
        ``"pairs"``), a pair's validation window from its own picks
        (``"time"``). The profile of the placebo's model class over the effect
        (:mod:`torchcf.diagnose.selection.power`)."""
        v = self.validation
        budget = v.budget or RefitBudget(self.n, 16, 6)
        key = (v.seed, "profile", self.step)
        if v.kind == "time":
            scores = refit_paired(
                self.placebo, v.rollout, budget, v.priors, self.shared, key, pin
            )
            return scores.numpy()
        return v.refit(
            self.placebo,
            self.n,
            {},
            self.shared,
            pin,
            key=("profile", self.step),
            budget=budget,
            as_pinned=True,
        )


def design(
    setup: LoopSetup,
    train_pairs: PairSet,
    seed: int,
    groups: Tensor | None = None,
) -> tuple[Rollout, Validation]:
    """The fit rollout and the :class:`Validation` of ``diagnose.validation``
    (``"auto"`` resolved by :func:`resolve_validation`); ``groups``: (N,) the
    pairs' cross-fitting groups (None: each pair its own)."""
    settings = setup.settings
    kind = resolve_validation(settings, train_pairs.n_pairs)
    budget = refit_budget(settings)
    priors = setup.priors
    if kind == "crossfit":
        if groups is None:
            groups = torch.arange(train_pairs.n_pairs)
        if int(groups.max()) + 1 < MIN_PAIRS:
            raise DiagnoseError(
                "diagnose.validation='crossfit' needs pairs of at least "
                f"{MIN_PAIRS} groups (drivers or runs); these pairs are one "
                "group: use diagnose.validation='time'"
            )
        whole = setup.rollout(train_pairs)
        if settings.refit_effect == "free":
            judged, first, later = free_effect_windows(
                train_pairs, settings.fit_fraction
            )
            return whole, Validation(
                kind,
                setup.rollout(first),
                budget,
                priors,
                seed,
                groups,
                setup.rollout(later),
                judged,
            )
        return whole, Validation(kind, whole, budget, priors, seed, groups)
    if held_out(kind):
        fit, held = split_by_pair(train_pairs, settings.fit_fraction, seed)
        if kind == "refit" and settings.refit_effect == "free":
            _, first, later = free_effect_windows(held, settings.fit_fraction)
            return setup.rollout(fit), Validation(
                kind,
                setup.rollout(first),
                budget,
                priors,
                seed,
                scored_on=setup.rollout(later),
            )
        return setup.rollout(fit), Validation(
            kind, setup.rollout(held), budget, priors, seed
        )
    fit, window = split_in_time(train_pairs, settings.fit_fraction)
    rollout = validation_rollout(setup, train_pairs) or setup.rollout(window)
    return setup.rollout(fit), Validation("time", rollout, budget, priors, seed)


def free_effect_windows(
    pairs: PairSet, fraction: float
) -> tuple[Tensor, PairSet, PairSet]:
    """The judged pairs of ``diagnose.refit_effect = "free"``: those with a
    later window of at least :data:`MIN_VALIDATION_STEPS` valid steps
    (positions (V,) int64), their first ``fraction`` of steps (where a refit
    searches a driver effect per pair) and the rest (where it is scored, from
    the observed state at the split).

    Raises:
        DiagnoseError: a window would be too short, or fewer than 2 pairs are
            long enough.
    """
    split = int(round(fraction * pairs.n_steps))
    kept, _ = _long_enough(pairs, fraction)
    keep = (pairs.mask[split:].sum(0) >= MIN_VALIDATION_STEPS).nonzero().squeeze(1)
    return keep, _window(kept, slice(0, split)), _window(kept, slice(split, None))


def refit_budget(settings: DiagnoseConfig) -> RefitBudget:
    """A held-out pair's refit: ``refit_slots`` particles, ``local_copies / 2``
    copies, ``refit_rounds`` rounds (at most, with ``refit_stop`` "calm")."""
    return RefitBudget(
        slots=settings.refit_slots,
        copies=max(1, settings.local_copies // 2),
        rounds=settings.refit_rounds,
        until_calm=settings.refit_stop == "calm",
    )


__all__ = [
    "Judge",
    "MIN_PAIRS",
    "MIN_VALIDATION_STEPS",
    "Validation",
    "WarmedRollout",
    "coverage_scores",
    "design",
    "fit_part",
    "held_out",
    "free_effect_windows",
    "held_out_count",
    "pair_groups",
    "refit_budget",
    "refits",
    "pair_split",
    "resolve_validation",
    "split_by_pair",
    "split_in_time",
    "validation_rollout",
    "warmed_validation",
]
