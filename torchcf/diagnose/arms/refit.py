"""Held-out pairs refitted: the model class judged on drivers no arm saw.

``diagnose.validation = "refit"`` (:mod:`torchcf.diagnose.arms.validation`). The
arms are fitted on the *fit pairs*; each *held-out pair* is then refitted by a
short local search of its own, once without the effect and once with it, and
the two refits' scores on that pair are compared:

- **each side from its own arm**: the *candidates* of the side without the
  effect are the placebo arm's picks (each fit pair's ``top_n`` best), those
  of the side with it the effect arm's picks (:func:`candidates`); at most
  :data:`REFIT_CANDIDATES` of each, so that the cost stays linear in the
  pairs. Every candidate is scored on every held-out pair, and a pair starts
  from its ``slots`` best. The two arms had equal search budgets on the fit
  pairs, so neither side starts better placed but by the effect;
- **the effect pinned**: the side with the effect lifts every candidate to
  ``m+E`` with E at one value learned on the fit pairs (a driver effect's
  estimate, the median over the arm's picks that carry it; a shared effect's
  one value: :func:`lifted`) and never moves it; the refit moves the model's
  own parameters only, as the side without it does. Both sides have the same
  free parameters on the held-out pair, and E's value was not chosen on it
  (an arm's picks with their own values of E would let the held-out pair
  choose among them: a fit of E on the pair itself);
- **common random numbers**: both refits draw their steps from one key by
  slot (:class:`~torchcf.diagnose.arms.search.Noise`).

**Cross-fitting** (``diagnose.validation = "crossfit"``): the arms are
fitted on every training pair, and every pair is then refitted as a held-out
pair, its candidates the picks of the *other* groups only (a group: the pairs
of one driver or run, else the pair alone; :class:`Exclusion`), so every
training pair is judged once, by candidates that never saw its data, in one
batched search.

What the comparison asks: fitted to a driver it has not seen, does the model
with E (at the value the other drivers gave) fit that driver better than the
model without it? The pooled picks' coverage of new drivers (``"pairs"``) asks
instead whether the arm's few hundred particles happen to lie near them, which
with drivers who differ is ruled by how sparse the particles are in six
dimensions, not by the effect.

Shapes: N fit pairs, V held-out pairs, S slots, Q candidates, K parameters
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ...abc.particles import Particles
from ...abc.rejection import Rollout
from ...models import CFModel
from ...models.effects import Effect
from .population import Population, merge, rescore
from .search import (
    Limits,
    Noise,
    converge,
    generator,
    lift,
    local_search,
    model_bounds,
    variant_of,
)

#: Candidates a held-out pair's refit starts from, at most (the placebo's and
#: the effect arm's picks pooled; subsampled by fit pair beyond it), so that
#: scoring them on every held-out pair costs the same per pair whatever the
#: number of fit pairs.
REFIT_CANDIDATES = 600


@dataclass(frozen=True)
class RefitBudget:
    """The local search of a held-out pair's refit.

    Attributes:
        slots: S, the particles each held-out pair keeps and searches from.
        copies: perturbed copies of each per round.
        rounds: rounds of the search (at most, with ``until_calm``).
        until_calm: stop once the search has converged
            (:func:`~torchcf.diagnose.arms.search.converge`'s rule: two rounds in a
            row lower the pairs' summed best score by less than
            :data:`~torchcf.diagnose.arms.search.CONVERGED`).
    """

    slots: int
    copies: int
    rounds: int
    until_calm: bool = False


@dataclass(frozen=True)
class Pin:
    """An effect held at one value on the held-out pairs.

    Attributes:
        effect: the effect.
        value: (K_E,) float64 its parameters, in the effect's order.
        free: the refit starts the effect at ``value`` and searches it per
            pair within its prior (``diagnose.refit_effect = "free"``, a
            driver effect), where pinned it never moves.
    """

    effect: Effect
    value: Tensor
    free: bool = False


@dataclass(frozen=True)
class Exclusion:
    """Which candidates a held-out pair may start from (cross-fitting).

    Attributes:
        sources: per entry of the candidates' mapping, in its order, (Q_m, G)
            bool: the groups whose picks hold each candidate.
        groups: (V,) int64 each held-out pair's group (0..G-1).

    A candidate is allowed for a pair where some group other than the pair's
    own holds it: a particle kept by another driver on that driver's data.
    """

    sources: tuple[Tensor, ...]
    groups: Tensor

    def allowed(self, entry: int) -> Tensor:
        """(Q_m, V) bool: candidate q of entry ``entry`` may start pair j."""
        sources = self.sources[entry]  # (Q, G)
        own = sources[:, self.groups]  # (Q, V): held by the pair's own group
        return sources.sum(1, keepdim=True) > own.to(torch.int64)


@dataclass(frozen=True)
class Layout:
    """Where a refit's pairs start and are scored.

    Attributes:
        exclusion: which candidates each pair may start from (cross-fitting;
            None: all).
        scored_on: where the refitted pairs are scored: the same pairs' later
            steps, when the refit's rollout holds their first (each pair's
            best particle on its first steps, scored out of sample in time);
            None: where it searched.
    """

    exclusion: Exclusion | None = None
    scored_on: Rollout | None = None


def candidates(
    population: Population,
    n: int,
    current: Mapping[CFModel, CFModel],
    seed: int,
    cap: int = REFIT_CANDIDATES,
) -> dict[CFModel, Tensor]:
    """An arm's picks, each as its current model.

    Args:
        population: the arm (the placebo, or an effect arm).
        n: picks per fit pair (``abc.top_n``).
        current: per model of the population, the current model it descends
            from (itself for a current model; ``m`` for ``m+E``).
        seed: draws which fit pairs give candidates when there are more than
            ``cap`` of them (the same fit pairs for every arm).
        cap: candidates at most.

    Returns:
        per current model, (Q_m, K_m) float64 parameters: the effect's own
        dropped, exact repeats removed.
    """
    thetas, _ = _picked(population, n, current, seed, cap)
    return {
        model: torch.unique(torch.cat(parts), dim=0) for model, parts in thetas.items()
    }


def _picked(
    population: Population,
    n: int,
    current: Mapping[CFModel, CFModel],
    seed: int,
    cap: int,
) -> tuple[dict[CFModel, list[Tensor]], dict[CFModel, list[Tensor]]]:
    """The picks :func:`candidates` offers, per current model: their
    parameters (pieces of (Q, K_m), the effect's own dropped) and the pair
    (pieces of (Q,)) each comes from, before repeats are merged."""
    n_pairs = population.n_pairs
    per_pair = max(1, min(n, cap // max(1, n_pairs)))
    keep = torch.arange(n_pairs)
    if n_pairs * per_pair > cap:
        order = torch.randperm(n_pairs, generator=generator(seed, "refit-candidates"))
        keep = torch.sort(order[:cap]).values
    thetas: dict[CFModel, list[Tensor]] = {}
    pairs: dict[CFModel, list[Tensor]] = {}
    picks = population.best(per_pair)
    for model in picks.models:
        pair, slot = picks.model_slots(model)
        chosen = torch.isin(pair, keep)
        if not bool(chosen.any()):
            continue
        parent = current.get(model, model)
        own = model.param_names
        columns = [own.index(p) for p in parent.param_names]
        thetas.setdefault(parent, []).append(
            picks.theta[pair[chosen], slot[chosen]][:, columns]
        )
        pairs.setdefault(parent, []).append(pair[chosen])
    return thetas, pairs


def sourced_candidates(
    population: Population,
    n: int,
    current: Mapping[CFModel, CFModel],
    seed: int,
    groups: Tensor,
    cap: int = REFIT_CANDIDATES,
) -> tuple[dict[CFModel, Tensor], tuple[Tensor, ...]]:
    """:func:`candidates` with, per candidate, the groups whose picks hold it.

    Args:
        groups: (N,) int64 each pair's group of ``population`` (0..G-1).

    Returns:
        per current model its candidates (Q_m, K_m), exact repeats merged, and
        per entry (in the mapping's order) the (Q_m, G) bool sources of
        :class:`Exclusion`.
    """
    n_groups = int(groups.max()) + 1 if groups.numel() else 0
    thetas, pairs = _picked(population, n, current, seed, cap)
    out, sources = {}, []
    for model, parts in thetas.items():
        unique, inverse = torch.unique(torch.cat(parts), dim=0, return_inverse=True)
        held = torch.zeros(unique.shape[0], n_groups, dtype=torch.bool)
        held[inverse, groups[torch.cat(pairs[model])]] = True
        out[model] = unique
        sources.append(held)
    return out, tuple(sources)


def lifted(candidates: Mapping[CFModel, Tensor], pin: Pin) -> dict[CFModel, Tensor]:
    """Every candidate as ``m+E`` with E at ``pin.value`` (K_E,); a model the
    effect cannot wrap (``lag`` on HL) stays as it is."""
    names = [p.name for p in pin.effect.param_specs]
    out = {}
    for model, theta in candidates.items():
        variant = variant_of(model, pin.effect)
        if variant is None:
            out[model] = theta
            continue
        own = model.param_names
        columns = [
            pin.value[names.index(p)].expand(theta.shape[0]).to(torch.float64)
            if p in names
            else theta[:, own.index(p)]
            for p in variant.param_names
        ]
        out[variant] = torch.stack(columns, dim=1)
    return out


def start(
    candidates: Mapping[CFModel, Tensor],
    rollout: Rollout,
    slots: int,
    exclusion: Exclusion | None = None,
) -> Population:
    """Per held-out pair of ``rollout``, its ``slots`` best candidates (every
    candidate scored on every pair: the rollout's full layout), among those
    ``exclusion`` allows it (None: all)."""
    every = dataclasses.replace(rollout, paired=False)
    n_held = rollout.pairs.n_pairs
    sets, index = [], 0
    for entry, (model, theta) in enumerate(candidates.items()):
        if theta.shape[0] == 0:
            continue
        score, _ = every.score(model, theta, None)  # (Q, V)
        if exclusion is not None:
            score = torch.where(exclusion.allowed(entry), score.cpu(), math.inf)
        q = theta.shape[0]
        sets.append(
            Particles(
                model,
                theta.repeat_interleave(n_held, dim=0),
                torch.arange(n_held).repeat(q),
                score.cpu().double().reshape(-1),
                (index + torch.arange(q)).repeat_interleave(n_held),
            )
        )
        index += q
    return Population.from_particles(sets, n_held, slots)


def refit_paired(
    population: Population,
    rollout: Rollout,
    budget: RefitBudget,
    priors: Mapping[str, Tensor],
    shared: Mapping[str, Tensor],
    key: tuple,
    pin: Pin | None = None,
) -> Tensor:
    """(N,) float64 each pair's best score after a refit on ``rollout``'s pairs
    (the same pairs as ``population``'s, in order: a pair's validation window),
    from its own ``budget.slots`` best particles (current models), with the
    effect ``pin`` held at its value (None: without); ``+inf`` where none is
    valid. The twin of :func:`refit_scores` for windows in time."""
    members = population.best(budget.slots)
    current = {m: m.param_names for m in members.models}
    parents = {m: m for m in members.models}
    if pin is not None:
        members, lifted_from = lift(members, pin.effect, pin.value)
        parents |= lifted_from
    members = merge([rescore(members, rollout)], budget.slots)
    searched = _searched(
        members, rollout, budget, priors, shared, key, pin, current, parents
    )
    return _best_scores(searched)


def refit_scores(
    candidates: Mapping[CFModel, Tensor],
    rollout: Rollout,
    budget: RefitBudget,
    priors: Mapping[str, Tensor],
    shared: Mapping[str, Tensor],
    key: tuple,
    pin: Pin | None = None,
    layout: Layout = Layout(),
) -> Tensor:
    """(V,) float64 each held-out pair's best score after its refit (``+inf``:
    no valid particle).

    Args:
        candidates: the current models' candidates (:func:`candidates`).
        rollout: simulates on the held-out pairs.
        priors: the run's prior box (K, 2) per pool model.
        shared: per chosen shared effect, its one value (pinned on both sides).
        key: the refit's random numbers (the same for both sides).
        pin: the effect and its value (None: the side without it).
        layout: which candidates each pair may start from and where it is
            scored (:class:`Layout`; the default: all, where it searched).
    """
    current = {m: m.param_names for m in candidates}
    members = candidates if pin is None else lifted(candidates, pin)
    parents = {m: m for m in candidates}
    if pin is not None:
        parents |= {variant_of(m, pin.effect) or m: m for m in candidates}
    population = start(members, rollout, budget.slots, layout.exclusion)
    searched = _searched(
        population, rollout, budget, priors, shared, key, pin, current, parents
    )
    return _best_scores(searched, layout.scored_on)


def _best_scores(population: Population, scored_on: Rollout | None = None) -> Tensor:
    """(V,) each pair's best score (``+inf``: no valid particle), or that best
    particle's score on ``scored_on`` (the same pairs, other steps)."""
    if scored_on is not None:
        population = rescore(population.best(1), scored_on)
    return torch.where(population.filled[:, 0], population.score[:, 0], math.inf)


def _searched(
    population: Population,
    rollout: Rollout,
    budget: RefitBudget,
    priors: Mapping[str, Tensor],
    shared: Mapping[str, Tensor],
    key: tuple,
    pin: Pin | None,
    current: dict[CFModel, tuple[str, ...]],
    parents: dict[CFModel, CFModel],
) -> Tensor:
    """``population`` after ``budget.rounds`` rounds of local search (or
    fewer, converged: ``budget.until_calm``) within the priors, the chosen
    shared effects and ``pin`` held at their values (a free pin: searched
    within its prior from its value).

    A round's random numbers are those of its number whichever rule stops the
    search, so a converged refit is the fixed one cut short. Each side of a
    comparison stops on its own: a side still gaining from more rounds is not
    compared in mid-descent with one that has settled."""
    pinned = dict(shared)
    if pin is not None and not pin.free:
        pinned[pin.effect.name] = pin.value
    bounds = {m: model_bounds(m, dict(priors), pinned) for m in population.models}
    noise = Noise(key, current, pin.effect if pin is not None else None)
    if budget.rounds > 0 and budget.until_calm:
        limits = Limits(budget.copies, budget.rounds)
        population, _ = converge(population, rollout, bounds, noise, parents, limits)
    elif budget.rounds > 0:
        population = local_search(
            population,
            rollout,
            bounds,
            noise,
            parents,
            rounds=budget.rounds,
            copies=budget.copies,
        )
    return population


__all__ = [
    "Exclusion",
    "Layout",
    "REFIT_CANDIDATES",
    "Pin",
    "RefitBudget",
    "candidates",
    "lifted",
    "refit_paired",
    "refit_scores",
    "sourced_candidates",
    "start",
]
