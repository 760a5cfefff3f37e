"""The attribution's local stage: sequential local search, and a shared effect's
one value.

After its small ABC run an arm refines its per-pair best by sequential local
search (:func:`local_search`: perturbed copies of the members, the kernel of
sequential ABC), so that arms are compared near their best fits rather than at
the luck of prior draws. A shared (road) effect has one value for all pairs,
searched jointly over the pairs (:func:`shared_value`).

Particles stay :class:`~torchcf.abc.particles.Particles` throughout; a perturbed
copy inherits its parent's pair and particle index.

Shapes: S members, C copies, M values, N pairs, K parameters
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..abc.particles import Particles, best_per_pair
from ..abc.rejection import Rollout
from ..config import DiagnoseConfig
from ..models.effects import parse_effect
from .candidates import compose_theta, fit_scores, variant_of

#: Standard deviations of the local search's perturbations, as fractions of each
#: parameter's prior width (copy c uses entry c % 3).
LOCAL_SCALES = (0.1, 0.03, 0.01)
#: Search rounds, and values per round, for the one value of a shared (road)
#: effect.
SHARED_ROUNDS = 3
SHARED_VALUES = 64
#: Relative fit score counted for a pair whose candidates are all invalid.
INVALID_RATIO = 10.0


def jitter(
    theta: Tensor, bounds: Tensor, copies: int, generator: torch.Generator
) -> Tensor:
    """``copies`` perturbations of every member ``theta`` (S, K): (S, C, K).

    Copy c moves each parameter by a normal step whose standard deviation is
    ``LOCAL_SCALES[c % 3]`` times the parameter's prior width, clipped to the prior
    box ``bounds`` (K, 2): a coarse-to-fine mix around the member, as the kernel of
    sequential ABC. A zero-width row (a fixed parameter) stays fixed.
    """
    s, d = theta.shape
    width = bounds[:, 1] - bounds[:, 0]
    scale = torch.tensor(LOCAL_SCALES, dtype=torch.float64)[
        torch.arange(copies) % len(LOCAL_SCALES)
    ]
    noise = torch.randn(s, copies, d, generator=generator, dtype=torch.float64)
    moved = theta[:, None, :] + noise * scale[None, :, None] * width
    return torch.maximum(torch.minimum(moved, bounds[:, 1]), bounds[:, 0])


def uniform(bounds: Tensor, shape: tuple[int, ...], generator: torch.Generator):
    """Uniform draws (*shape, K) float64 in the box ``bounds`` (K, 2)."""
    u = torch.rand(*shape, bounds.shape[0], generator=generator, dtype=torch.float64)
    return bounds[:, 0] + u * (bounds[:, 1] - bounds[:, 0])


def perturbed(
    members: Particles,
    bounds: Tensor,
    copies: int,
    rollout: Rollout,
    generator: torch.Generator,
) -> Particles:
    """``copies`` scored perturbations of every member (:func:`jitter`), member
    by member; each inherits its member's pair and particle index."""
    moved = jitter(members.theta, bounds, copies, generator)  # (S, C, K)
    theta = moved.reshape(-1, moved.shape[-1])
    pair = members.pair.repeat_interleave(copies)
    score = fit_scores(rollout, members.model, theta, pair)
    return Particles(
        members.model, theta, pair, score, members.index.repeat_interleave(copies)
    )


def local_search(
    start: list[Particles],
    bounds: dict[str, Tensor],
    rollout: Rollout,
    settings: DiagnoseConfig,
    generator: torch.Generator,
) -> list[Particles]:
    """Sequential local search of one arm: ``rounds`` times, every pair's
    ``population`` best members (over the arm's models) get ``local_copies``
    perturbed copies each (:func:`perturbed`), scored on the rollout's pairs (the
    fit windows).

    Every arm spends the same budget per pair and round, so arms differ by their
    models only.

    Returns:
        the arm's final population (per pair its ``population`` best) as sets.
    """
    members = best_per_pair(start, settings.population)
    for _ in range(settings.rounds):
        copies = [
            perturbed(m, bounds[m.model], settings.local_copies, rollout, generator)
            for m in members
        ]
        members = best_per_pair(members + copies, settings.population)
    return members


def _effect_prior(effect: str) -> Tensor:
    """The effect's default prior box (K_E, 2) float64."""
    spec = parse_effect(effect)
    return torch.tensor(
        [[p.lower, p.upper] for p in spec.param_specs], dtype=torch.float64
    )


def _best_member_scores(members: list[Particles], n_pairs: int) -> Tensor:
    """(N,) float64 best score of the members on each pair (``inf``: none)."""
    reference = torch.full((n_pairs,), math.inf, dtype=torch.float64)
    for member in members:
        reference = reference.scatter_reduce(0, member.pair, member.score, "amin")
    return reference


def _value_scores(
    effect: str,
    values: Tensor,
    members: list[Particles],
    bounds: dict[str, Tensor],
    rollout: Rollout,
    generator: torch.Generator,
) -> Tensor:
    """(N, M) best fit score on each pair of each value (K_E,) in ``values``
    (M, K_E), tried with every member's m-th coarse perturbation."""
    m = values.shape[0]
    per_pair = torch.full((rollout.pairs.n_pairs, m), math.inf, dtype=torch.float64)
    for member in members:
        variant = variant_of(member.model, effect)
        if variant is None:
            continue
        s = len(member)
        base = jitter(member.theta, bounds[member.model], m, generator)
        theta = compose_theta(
            member.model, variant, base, values[None].expand(s, m, -1)
        )
        pair = member.pair.repeat_interleave(m)
        score = fit_scores(rollout, variant, theta.reshape(s * m, -1), pair)
        index = member.pair[:, None].expand(s, m)
        per_pair = per_pair.scatter_reduce(0, index, score.reshape(s, m), "amin")
    return per_pair


def _around(value: Tensor, half: Tensor, prior: Tensor) -> Tensor:
    """The box (K, 2) ``value +- half`` within ``prior``."""
    low, high = prior[:, 0], prior[:, 1]
    return torch.stack(
        (torch.maximum(value - half, low), torch.minimum(value + half, high)), 1
    )


def shared_value(
    effect: str,
    members: list[Particles],
    bounds: dict[str, Tensor],
    rollout: Rollout,
    generator: torch.Generator,
    start: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The one value of a shared (road) effect's parameters for all pairs.

    Searched over the pool arm's final population (``members``):
    ``SHARED_ROUNDS`` rounds of ``SHARED_VALUES`` values, the first uniform over the
    effect's prior, each later one uniform in a box around the best so far with
    half the width. Value c is tried with every member's c-th coarse perturbation
    (the base parameters may have absorbed part of the effect). A value's
    objective is the sum over pairs of its best fit score relative to the pair's
    best member, so every pair weighs alike.

    Args:
        start: a first candidate (K_E,), tried in the first round with the
            members' finest perturbation (a grade profile from the residual
            regression, :func:`torchcf.diagnose.road.grade_seed`; a speed
            limit from the speed envelope, :func:`~torchcf.diagnose.road.bend_seed`).

    Returns:
        the value (K_E,) and the box (K_E, 2) of the last round's resolution
        around it (the effect's prior in the arm and the re-calibration).
    """
    prior = _effect_prior(effect)
    reference = _best_member_scores(members, rollout.pairs.n_pairs)
    usable = torch.isfinite(reference) & (reference > 0)
    best, best_objective = None, math.inf
    half = (prior[:, 1] - prior[:, 0]) / 2
    for _ in range(SHARED_ROUNDS):
        box = prior if best is None else _around(best, half, prior)
        values = uniform(box, (SHARED_VALUES,), generator)  # (M, K_E)
        if best is None and start is not None:
            # the slot whose members are jittered least (LOCAL_SCALES' finest)
            finest = min(range(len(LOCAL_SCALES)), key=LOCAL_SCALES.__getitem__)
            values[finest] = start.to(values.dtype)
        per_pair = _value_scores(effect, values, members, bounds, rollout, generator)
        ratio = per_pair[usable] / reference[usable, None]
        ratio = torch.where(torch.isfinite(ratio), ratio, INVALID_RATIO)
        objective = ratio.sum(0)  # (M,)
        k = int(torch.argmin(objective))
        if float(objective[k]) < best_objective:
            best, best_objective = values[k], float(objective[k])
        half = half / 2
    return best, _around(best, half, prior)


__all__ = [
    "INVALID_RATIO",
    "LOCAL_SCALES",
    "SHARED_ROUNDS",
    "SHARED_VALUES",
    "jitter",
    "local_search",
    "perturbed",
    "shared_value",
    "uniform",
]
