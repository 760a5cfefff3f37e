"""The search of an arm: local search with common random numbers, and nested starts.

**Local search** (:func:`local_search`): ``rounds`` times, every slot of a
:class:`~torchcf.diagnose.arms.population.Population` gets ``copies`` perturbed
copies (a normal step of ``LOCAL_SCALES[c % 3]`` times each parameter's prior
width for copy c, clipped to the prior box: the kernel of sequential ABC), scored
on the rollout's pairs, and every pair keeps its ``S`` best of members and copies
(elitist: a pair's best never gets worse).

**Early rejection.** A copy can enter its pair's population only by scoring at
most the population's worst kept score (where the population is full), so its
rollout stops once its score so far, a lower bound of its final score, exceeds
that :func:`admission_ceiling` (the early rejection of SPEC section 2,
:attr:`torchcf.sim.rollout.Execution.ceiling`). A stopped copy scores ``+inf``
and is dropped at the merge, where its final score would have dropped it too:
the search's populations are those of copies run to the end.

**Common random numbers.** A round draws its steps for *slots*, not for
particles: one (N, S, C, K_c) normal tensor from a generator seeded by the
search's key and the round (:class:`Noise`), where column k is the k-th parameter
of the slot's *current* model (the model the comparison starts from). A variant
``m+E`` in a slot reads its base parameters from the same columns as ``m`` would
(by name) and its effect's parameters from a second tensor with a seed of the
effect's own. Two arms searched from one start with one key (the base alone,
and the base with an effect) therefore take the same steps wherever they hold
the same particle: with the effect at its neutral value the augmented search
*is* the base search, and what differs between the arms is the effect, not the
luck of the search.

**Nested starts** (:func:`lift`): a slot's particle of model ``m`` becomes the
variant ``m+E`` with E's parameters at given values (the neutral ones,
:attr:`~torchcf.models.effects.Effect.neutral`: the same rollout), its own
parameters unchanged.

**A shared effect's one value** (:func:`shared_value`): a recording effect
(sensor offset, clock offset) or a road profile has one value for all pairs,
searched jointly over the pairs.

Shapes: N pairs, S slots, C copies, K parameters (K_c: noise columns of the
current models, K_E: an effect's), M candidate values, Q particles
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ...abc.rejection import Rollout
from ...config import DiagnoseConfig
from ...models import CFModel, UnknownModelError, augment
from ...models.effects import Effect
from .population import Population, merge, rescore, score_on

#: Standard deviations of the local search's steps, as fractions of each
#: parameter's prior width (copy c uses entry c % 3).
LOCAL_SCALES = (0.1, 0.03, 0.01)
#: Search rounds, and values per round, for the one value of a shared effect.
SHARED_ROUNDS = 3
SHARED_VALUES = 48
#: Relative fit score counted for a pair whose candidates are all invalid.
INVALID_RATIO = 10.0
#: A search has converged when a round lowers the pairs' summed best score by
#: less than this share (:func:`converge`).
CONVERGED = 0.002


def derive_seed(*labels: object) -> int:
    """A 63-bit seed that is a pure function of ``labels`` (stable across runs and
    machines): every random draw of the loop has its own, so an arm's result
    does not depend on which arms ran before it (or were read from a
    checkpoint). An effect stands for its token (the same seed as its name), a
    model for its name."""
    digest = hashlib.sha256(repr(_as_text(labels)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def _as_text(label: object) -> object:
    """``label`` with every effect in it (nested in tuples and lists) replaced
    by its token, and every model by its name."""
    if isinstance(label, Effect):
        return label.token
    if isinstance(label, CFModel):
        return label.name
    if isinstance(label, tuple | list):
        return type(label)(_as_text(item) for item in label)
    return label


def generator(*labels: object) -> torch.Generator:
    """A CPU generator seeded by :func:`derive_seed` of ``labels``."""
    return torch.Generator().manual_seed(derive_seed(*labels))


# ------------------------------------------------------------------ variants
def variant_of(model: CFModel, effect: Effect) -> CFModel | None:
    """``model`` wrapped by ``effect`` (the registry's one instance of the
    variant); None where the effect cannot wrap it (``lag`` on HL, which has its
    own actuation lag)."""
    try:
        return augment(model, effect)
    except UnknownModelError:
        return None


def model_bounds(
    model: CFModel, priors: dict[str, Tensor], shared: dict[str, Tensor] | None = None
) -> Tensor:
    """Prior box (K, 2) float64 of a model or variant: the run's prior box of its
    pool model (``priors``: pool model -> (K_m, 2)), each effect's own prior, and
    every shared effect named in ``shared`` (effect name -> its one value
    (K_E,)) pinned at its value (a zero-width row: the search never moves it)."""
    bounds = model.prior_bounds(torch.float64)
    base = model.pool_model.name
    if base in priors:
        bounds[: priors[base].shape[0]] = priors[base]
    for effect in model.effects:
        if shared and effect.name in shared:
            columns = [model.param_names.index(p.name) for p in effect.param_specs]
            value = shared[effect.name].to(torch.float64)
            bounds[columns] = value[:, None].expand(-1, 2)
    return bounds


# ------------------------------------------------------------------ the noise
@dataclass(frozen=True)
class Noise:
    """The random numbers of one search: a key, and the current models whose
    parameters take the common columns.

    Attributes:
        key: labels seeding the search (the same key: the same steps).
        current: per current model, its parameter names (columns 0..K_m-1).
        effect: the effect whose parameters take their own columns, or None.
    """

    key: tuple
    current: dict[CFModel, tuple[str, ...]]
    effect: Effect | None = None

    @property
    def width(self) -> int:
        """K_c: the common columns (the widest current model)."""
        return max([len(names) for names in self.current.values()], default=0)

    def steps(self, round_: int, shape: tuple[int, int, int]) -> Tensor:
        """(N, S, C, K_c + K_E) standard normal steps of round ``round_``."""
        common = torch.randn(
            *shape, self.width, generator=generator(*self.key, round_),
            dtype=torch.float64,
        )  # fmt: skip
        if self.effect is None:
            return common
        k_e = len(self.effect.param_specs)
        own = torch.randn(
            *shape, k_e, generator=generator(*self.key, round_, self.effect),
            dtype=torch.float64,
        )  # fmt: skip
        return torch.cat((common, own), dim=-1)

    def columns(self, model: CFModel, parent: CFModel) -> Tensor:
        """(K,) int64: the step column of each parameter of ``model`` whose slot
        descends from the current model ``parent`` (by name; the effect's own
        parameters after the common columns)."""
        names = self.current[parent]
        own = [p.name for p in self.effect.param_specs] if self.effect else []
        out = []
        for name in model.param_names:
            if name in names:
                out.append(names.index(name))
            elif name in own:
                out.append(self.width + own.index(name))
            else:
                raise ValueError(f"{model.name}: parameter {name} has no step column")
        return torch.tensor(out, dtype=torch.int64)


def jitter(theta: Tensor, steps: Tensor, bounds: Tensor) -> Tensor:
    """Perturbed copies (Q, C, K) of ``theta`` (Q, K): copy c moves each parameter
    by ``steps`` (Q, C, K, standard normal) times ``LOCAL_SCALES[c % 3]`` times its
    prior width, clipped to the box ``bounds`` (K, 2); a zero-width row (a pinned
    value) stays fixed."""
    copies = steps.shape[1]
    width = bounds[:, 1] - bounds[:, 0]  # (K,)
    scale = torch.tensor(LOCAL_SCALES, dtype=torch.float64)[
        torch.arange(copies) % len(LOCAL_SCALES)
    ]  # (C,)
    moved = theta[:, None, :] + steps * scale[None, :, None] * width
    return torch.maximum(torch.minimum(moved, bounds[:, 1]), bounds[:, 0])


def admission_ceiling(population: Population) -> Tensor:
    """(N,) float64: per pair, the score above which a new particle cannot enter
    the population at a :func:`~torchcf.diagnose.arms.population.merge` of its size:
    its worst kept score where it holds ``S`` distinct particles, ``+inf`` where
    it has room (an empty slot, or a repeat the merge would drop)."""
    n, size = population.score.shape
    if size == 0:
        return torch.full((n,), math.inf, dtype=torch.float64)
    worst = merge([population], size).score[:, -1]
    return torch.where(torch.isfinite(worst), worst, math.inf)


def search_round(
    population: Population,
    rollout: Rollout,
    bounds: dict[CFModel, Tensor],
    steps: Tensor,
    columns: Callable[[CFModel], Tensor],
) -> Population:
    """The scored copies of every filled slot (N, S C): slot (j, s), copy c reads
    ``steps[j, s, c]`` (N, S, C, K_c + K_E) at its model's ``columns``.

    A copy sure to score above its pair's :func:`admission_ceiling` is stopped
    early and scores ``+inf``: merged with ``population`` at its size, the
    copies give the population they would give run to the end."""
    n, size = population.score.shape
    ceiling = admission_ceiling(population)
    copies = steps.shape[2]
    width = population.theta.shape[2]
    model = torch.full((n, size, copies), -1, dtype=torch.int64)
    theta = torch.full((n, size, copies, width), math.nan, dtype=torch.float64)
    score = torch.full((n, size, copies), math.inf, dtype=torch.float64)
    index = population.index[..., None].expand(-1, -1, copies).clone()
    for m, slot_model in enumerate(population.models):
        pair, slot = population.model_slots(slot_model)
        if pair.numel() == 0:
            continue
        k = slot_model.n_params
        own = steps[pair, slot][..., columns(slot_model)]  # (Q, C, K)
        moved = jitter(population.theta[pair, slot, :k], own, bounds[slot_model])
        model[pair, slot] = m
        theta[pair, slot, :, :k] = moved
        flat_pair = pair.repeat_interleave(copies)
        score[pair, slot] = score_on(
            rollout, slot_model, moved.reshape(-1, k), flat_pair, ceiling[flat_pair]
        ).reshape(-1, copies)
    return Population(
        population.models,
        model.reshape(n, -1),
        theta.reshape(n, size * copies, width),
        score.reshape(n, -1),
        index.reshape(n, -1),
    )


def local_search(
    population: Population,
    rollout: Rollout,
    bounds: dict[CFModel, Tensor],
    noise: Noise,
    parents: dict[CFModel, CFModel],
    *,
    rounds: int,
    copies: int,
    progress: Callable[[], None] | None = None,
) -> Population:
    """``rounds`` rounds of elitist local search with common random numbers
    (module docstring).

    Args:
        population: the start (its size is kept).
        bounds: prior box (K, 2) of every model that may appear.
        noise: the search's random numbers.
        parents: per model of the population, the current model its slot
            descends from (itself for a current model).
        progress: called after every round.

    Returns:
        the population after the last round.
    """
    shape = (population.n_pairs, population.size, copies)
    cache: dict[CFModel, Tensor] = {}

    def columns(model: CFModel) -> Tensor:
        if model not in cache:
            cache[model] = noise.columns(model, parents[model])
        return cache[model]

    for r in range(rounds):
        copies_ = search_round(
            population, rollout, bounds, noise.steps(r, shape), columns
        )
        population = merge([population, copies_], population.size)
        if progress is not None:
            progress()
    return population


@dataclass(frozen=True)
class Limits:
    """How long a converging search may run.

    Attributes:
        copies: perturbed copies of every member a round.
        max_rounds: rounds at most.
    """

    copies: int
    max_rounds: int

    @classmethod
    def of(cls, settings: DiagnoseConfig) -> Limits:
        """The ``diagnose`` section's: ``local_copies``, ``max_rounds``."""
        return cls(settings.local_copies, settings.max_rounds)


@dataclass(frozen=True)
class Converging:
    """Where a converging search stands after a round (what resumes it).

    Attributes:
        population: the population after ``rounds`` rounds.
        rounds: rounds done.
        calm: rounds in a row, up to the last, that lowered the pairs' summed
            best score by less than :data:`CONVERGED`.
    """

    population: Population
    rounds: int
    calm: int


def converge(
    population: Population,
    rollout: Rollout,
    bounds: dict[CFModel, Tensor],
    noise: Noise,
    parents: dict[CFModel, CFModel],
    limits: Limits,
    *,
    resume: Converging | None = None,
    after_round: Callable[[Converging], None] | None = None,
) -> tuple[Population, int]:
    """Local search until it converges: rounds of :func:`local_search` until two
    rounds in a row lower the pairs' summed best score by less than
    :data:`CONVERGED` (relative), or ``limits.max_rounds`` rounds.

    A comparison starts from a converged model: an arm that starts short of its
    optimum gains from any change of its search (a redundant parameter moves
    it faster), which would pass for the effect.

    Args:
        limits: ``copies`` copies of every member a round, at most
            ``max_rounds`` rounds.
        resume: continue from this state (a round's random numbers are those
            of its number, so the result is the uninterrupted search's).
        after_round: called with the state after every round (a progress bar,
            a checkpoint).

    Returns:
        the population and the rounds it took.
    """
    copies, max_rounds = limits.copies, limits.max_rounds
    shape = (population.n_pairs, population.size, copies)
    calm, rounds = 0, 0
    if resume is not None:
        population, rounds, calm = resume.population, resume.rounds, resume.calm
    cache: dict[CFModel, Tensor] = {}

    def columns(model: CFModel) -> Tensor:
        if model not in cache:
            cache[model] = noise.columns(model, parents[model])
        return cache[model]

    while rounds < max_rounds and calm < 2:
        before = _summed_best(population)
        copies_ = search_round(
            population, rollout, bounds, noise.steps(rounds, shape), columns
        )
        population = merge([population, copies_], population.size)
        after = _summed_best(population)
        rounds += 1
        calm = calm + 1 if before - after < CONVERGED * before else 0
        if after_round is not None:
            after_round(Converging(population, rounds, calm))
    return population, rounds


def _summed_best(population: Population) -> float:
    best = population.score[:, 0]
    return float(best[torch.isfinite(best)].sum())


# --------------------------------------------------------------- nested starts
def lift(
    population: Population,
    effect: Effect,
    values: Tensor,
    rollout: Rollout | None = None,
) -> tuple[Population, dict[CFModel, CFModel]]:
    """Every slot whose model the effect can wrap, as the variant ``m+effect`` with
    the effect's parameters at ``values`` ((K_E,), or (N, S, K_E) per slot);
    slots of a model it cannot wrap stay as they are.

    Args:
        rollout: re-score the lifted slots there (None: keep their scores, right
            only at exactly neutral values).

    Returns:
        the lifted population (slot order unchanged) and, per variant, the model
        it was lifted from.
    """
    names = [p.name for p in effect.param_specs]
    n, size = population.score.shape
    values = values.to(torch.float64).expand(n, size, len(names))
    models = list(population.models)
    lifted_from: dict[CFModel, CFModel] = {}
    new_index = population.model.clone()
    widths = [m.n_params for m in population.models]
    for m, model in enumerate(population.models):
        variant = variant_of(model, effect)
        if variant is None or not bool((population.model == m).any()):
            continue
        if variant in population.models:
            raise ValueError(
                f"{model.name}: {variant.name} is in the population already"
            )
        lifted_from[variant] = model
        if variant not in models:
            models.append(variant)
        new_index[population.model == m] = models.index(variant)
        widths.append(variant.n_params)
    width = max(widths)
    theta = torch.full((n, size, width), math.nan, dtype=torch.float64)
    for m, model in enumerate(models):
        held = new_index == m
        if not bool(held.any()):
            continue
        target = model.param_names
        if model in lifted_from:
            source = lifted_from[model].param_names
            old = population.theta[held]
            columns = [
                old[:, source.index(p)]
                if p in source
                else values[held][:, names.index(p)]
                for p in target
            ]
            theta[held, : len(target)] = torch.stack(columns, dim=1)
        else:
            theta[held, : len(target)] = population.theta[held, : len(target)]
    lifted = Population(
        tuple(models), new_index, theta, population.score.clone(), population.index
    )
    if rollout is not None:
        lifted = rescore(lifted, rollout)
    return lifted, lifted_from


# ------------------------------------------------------------ a shared value
def shared_value(
    effect: Effect,
    population: Population,
    rollout: Rollout,
    bounds: dict[CFModel, Tensor],
    prior: Tensor,
    key: tuple,
    start: Sequence[Tensor] = (),
) -> tuple[Tensor, Tensor, list[tuple[Tensor, Tensor]]]:
    """The one value (K_E,) of a shared effect's parameters for all pairs.

    ``SHARED_ROUNDS`` rounds of ``SHARED_VALUES`` candidate values: the first spread
    over the effect's ``prior`` (K_E, 2) by a Latin hypercube, with the ``start``
    candidates among them; each later round uniform in a box around the best so
    far with half the width. Value c is tried with every particle of the
    population, each moved by its own step of scale ``LOCAL_SCALES[c % 3]`` (the
    model's own parameters may have absorbed part of the effect: a value is
    judged with them free to move; a start candidate with the finest steps). A
    value's objective is the sum over pairs of its best score relative to the
    pair's best particle, so every pair weighs alike. (The neutral value is not
    a candidate: the effect arm holds the base arm, which is the effect at its
    neutral value.)

    Args:
        bounds: prior box of every model of the population.
        start: first candidates (K_E,) (a grade from the residual regression, a
            speed limit from the speed envelope:
            :mod:`torchcf.diagnose.signatures.road`).

    Returns:
        the value (K_E,), the box (K_E, 2) of the last round's resolution around
        it, and every candidate tried with its per-pair best score:
        ``[(values (M, K_E), per-pair best (N, M) score)]`` per round.
    """
    reference = population.score[:, 0]
    usable = torch.isfinite(reference) & (reference > 0)
    best, best_objective = None, math.inf
    half = (prior[:, 1] - prior[:, 0]) / 2
    finest = min(range(len(LOCAL_SCALES)), key=LOCAL_SCALES.__getitem__)
    tried = []
    for r in range(SHARED_ROUNDS):
        g = generator(*key, "shared", effect, r)
        if best is None:
            strata = torch.argsort(
                torch.rand(prior.shape[0], SHARED_VALUES, generator=g), dim=-1
            )
            u = strata + torch.rand(strata.shape, generator=g, dtype=torch.float64)
            u = (u / SHARED_VALUES).T  # (M, K_E)
            values = prior[:, 0] + u * (prior[:, 1] - prior[:, 0])
            for i, candidate in enumerate(start):
                # the slots whose steps are finest: finest, finest + 3, ...
                values[finest + len(LOCAL_SCALES) * i] = candidate.to(values.dtype)
        else:
            box = _around(best, half, prior)
            u = torch.rand(
                SHARED_VALUES, prior.shape[0], generator=g, dtype=torch.float64
            )
            values = box[:, 0] + u * (box[:, 1] - box[:, 0])
        per_pair = _value_scores(effect, values, population, rollout, bounds, key, r)
        tried.append((values, per_pair))
        ratio = per_pair[usable] / reference[usable, None]
        ratio = torch.where(torch.isfinite(ratio), ratio, INVALID_RATIO)
        objective = ratio.sum(0)  # (M,)
        k = int(torch.argmin(objective))
        if float(objective[k]) < best_objective:
            best, best_objective = values[k], float(objective[k])
        half = half / 2
    return best, _around(best, half, prior), tried


def _value_scores(
    effect: Effect,
    values: Tensor,
    members: Population,
    rollout: Rollout,
    bounds: dict[CFModel, Tensor],
    key: tuple,
    round_: int,
) -> Tensor:
    """(N, M) the best score on each pair of each value (K_E,) in ``values``
    (M, K_E), tried with every member moved by its own step of scale
    ``LOCAL_SCALES[c % 3]`` for value c (:func:`jitter`)."""
    m = values.shape[0]
    n = members.n_pairs
    per_pair = torch.full((n, m), math.inf, dtype=torch.float64)
    g = generator(*key, "shared-steps", effect, round_)
    for model in members.models:
        variant = variant_of(model, effect)
        pair, slot = members.model_slots(model)
        if variant is None or pair.numel() == 0:
            continue
        k = model.n_params
        theta = members.theta[pair, slot, :k]  # (Q, K)
        steps = torch.randn(theta.shape[0], m, k, generator=g, dtype=torch.float64)
        moved = jitter(theta, steps, bounds[model])  # (Q, M, K)
        composed = _compose(
            model, variant, moved, values[None].expand(len(pair), -1, -1)
        )
        score = score_on(
            rollout, variant, composed.reshape(-1, composed.shape[-1]),
            pair.repeat_interleave(m),
        ).reshape(-1, m)  # fmt: skip
        per_pair = per_pair.scatter_reduce(
            0, pair[:, None].expand(-1, m), score, "amin"
        )
    return per_pair


def _compose(
    model: CFModel, variant: CFModel, theta: Tensor, effect_values: Tensor
) -> Tensor:
    """Parameters (..., K_variant) of ``variant`` = ``model`` plus one effect, placed
    by name, from ``theta`` (..., K_model) and ``effect_values`` (..., K_E)."""
    have = model.param_names
    added = [n for n in variant.param_names if n not in have]
    columns = [
        theta[..., have.index(n)] if n in have else effect_values[..., added.index(n)]
        for n in variant.param_names
    ]
    return torch.stack(columns, dim=-1)


def _around(value: Tensor, half: Tensor, prior: Tensor) -> Tensor:
    """The box (K, 2) ``value +- half`` within ``prior``."""
    low, high = prior[:, 0], prior[:, 1]
    return torch.stack(
        (torch.maximum(value - half, low), torch.minimum(value + half, high)), 1
    )


def effect_prior(effect: Effect) -> Tensor:
    """The effect's default prior box (K_E, 2) float64."""
    return torch.tensor(
        [[p.lower, p.upper] for p in effect.param_specs], dtype=torch.float64
    )


__all__ = [
    "CONVERGED",
    "Converging",
    "Limits",
    "INVALID_RATIO",
    "LOCAL_SCALES",
    "SHARED_ROUNDS",
    "SHARED_VALUES",
    "Noise",
    "admission_ceiling",
    "converge",
    "derive_seed",
    "effect_prior",
    "generator",
    "jitter",
    "lift",
    "local_search",
    "model_bounds",
    "search_round",
    "shared_value",
    "variant_of",
]
