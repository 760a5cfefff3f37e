"""Absorption: does a pool model's own parameter take up the effect?

A spacing-sensor offset is taken up by a standstill gap (``s0``, ``l``), a clock
offset between two logs by a reaction the model already has: the data then
cannot tell the effect from the parameter, and "not found" means "absorbed by
``s0``: not separable in these data". For every candidate effect the attribution
measures which parameter absorbs it, and by how much (:func:`absorbed_by`):

- a **driver** effect is fitted per pair; over the effect arm's population
  (every particle that carries the effect, on every pair) each parameter is
  centred per pair and the effect parameter's within-pair correlation with each
  of the model's own parameters taken
  (:func:`~torchcf.diagnose.arms.identifiability.within_pair_correlation`): the
  strongest partner, its correlation and the slope of the ridge (partner per
  unit of the effect);
- a **recording** or **road** effect has one value for every pair, so it has no
  within-pair spread; instead it is *profiled* (:func:`profile`): fixed at
  :data:`PROFILE_VALUES` values across its prior, each pair's particles refitted
  around their start, and the correlation and slope of each parameter of a
  pair's best particle against the fixed value taken (centred per pair, pooled),
  together with how much the fit changes along the profile (a flat profile: the
  value is not identified).

The **shift** is what the partner does in the pool's fit when the effect is
added: the median over pairs of the partner in the best particle with the
effect minus in the best particle without it (the same pool model on both
sides), next to the effect's own estimate. ``absorbed`` is ``|r| >=``
:data:`~torchcf.diagnose.arms.identifiability.RIDGE_CORRELATION`.

Shapes: N pairs, S slots, K parameters, G profile values (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Self

import torch
from torch import Tensor

from ...models import CFModel
from ...models.effects import Effect
from ...models.steady import equilibrium_spacing, time_gap
from ...system.records import Record
from .identifiability import RIDGE_CORRELATION, within_pair_correlation
from .population import Population

#: Values of a shared effect's profile (spread evenly over its prior).
PROFILE_VALUES = 7


@dataclass(frozen=True)
class Absorption(Record):
    """The strongest partner of a driver effect's parameters (:func:`absorbed_by`).

    Attributes:
        parameter: the pool model's parameter that takes the effect up.
        model: that pool model.
        effect_parameter: the effect's parameter it trades off against.
        correlation: their within-pair correlation (pooled over pairs).
        slope: the ridge's slope, partner units per effect unit (None: the
            effect does not vary).
        n_pairs: the pairs the correlation pools.
        shift: the partner's median move when the effect is added (None: no
            pair descends from one model on both sides).
        absorbed: ``|correlation| >=`` :data:`~torchcf.diagnose.
            identifiability.RIDGE_CORRELATION`.
    """

    parameter: str
    model: str
    effect_parameter: str
    correlation: float
    slope: float | None
    n_pairs: int
    shift: float | None
    absorbed: bool


@dataclass(frozen=True)
class Profile(Record):
    """A one-parameter effect's profile: its fixed values (G,) and, per value,
    the summed fit score relative to the start's (G,)."""

    values: tuple[float, ...]
    relative_fit: tuple[float, ...]


@dataclass(frozen=True)
class SteadyShift(Record):
    """How the pool's steady state moves along an effect's profile
    (:func:`steady_shift`).

    Attributes:
        speed: where it is read [m/s].
        gap_slope, gap_r: the equilibrium spacing's within-pair slope [m per
            unit of the effect] and correlation on the effect's value.
        time_gap_slope, time_gap_r: the same of the time gap [s per unit].
        n_pairs: the (pair, pool model) rows pooled.
    """

    speed: float
    gap_slope: float | None
    gap_r: float | None
    time_gap_slope: float | None
    time_gap_r: float | None
    n_pairs: int


@dataclass(frozen=True)
class ProfileAbsorption(Record):
    """The strongest partner of a one-parameter effect along its profile
    (:func:`profile_absorption`).

    Attributes:
        parameter, model, effect_parameter, correlation, slope, absorbed: as
            :class:`Absorption`'s (the correlation of a pair's best particle's
            parameter with the fixed value, centred per pair).
        shift: the partner's median move from the neutral value to the
            effect's estimate along the profile.
        n_pairs: the pairs whose best particle descends from ``model`` at
            every value.
        profile: the values and the fit along them.
        steady: the pool's steady state along them (None: not read, or no
            equilibrium).
    """

    parameter: str
    model: str
    effect_parameter: str
    correlation: float
    slope: float
    shift: float
    n_pairs: int
    absorbed: bool
    profile: Profile
    steady: SteadyShift | None

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of its JSON object (:meth:`to_json`'s)."""
        steady = raw["steady"]
        return cls(
            **{k: v for k, v in raw.items() if k not in ("profile", "steady")},
            profile=Profile.from_json(raw["profile"]),
            steady=None if steady is None else SteadyShift.from_json(steady),
        )


#: What absorbs an effect: a driver effect's partner, or a shared one's along
#: its profile.
Absorbed = Absorption | ProfileAbsorption


def absorbed_from_json(raw: Mapping[str, Any]) -> Absorbed:
    """The absorption of its JSON object (a profile's holds ``profile``)."""
    if "profile" in raw:
        return ProfileAbsorption.from_json(raw)
    return Absorption.from_json(raw)


def _effect_columns(model: CFModel, effect: Effect) -> list[int]:
    names = [p.name for p in effect.param_specs]
    return [model.param_names.index(n) for n in names]


def _base_names(model: CFModel, effect: Effect) -> list[str]:
    own = {p.name for p in effect.param_specs}
    return [n for n in model.param_names if n not in own]


def _shift(
    final: Population,
    base: Population,
    lifted_from: dict[CFModel, CFModel],
    partner: str,
) -> float | None:
    """Median over pairs of ``partner`` in the best slot with the effect minus in
    the best slot of the base population, where both descend from one model."""
    shifts = []
    for j in range(final.n_pairs):
        if not (bool(final.filled[j, 0]) and bool(base.filled[j, 0])):
            continue
        model = final.models[int(final.model[j, 0])]
        start = base.models[int(base.model[j, 0])]
        if lifted_from.get(model) is not start:
            continue
        after = model.param_names
        before = start.param_names
        if partner not in after or partner not in before:
            continue
        shifts.append(
            float(final.theta[j, 0, after.index(partner)])
            - float(base.theta[j, 0, before.index(partner)])
        )
    if not shifts:
        return None
    return float(torch.tensor(shifts).median())


def absorbed_by(
    effect: Effect,
    final: Population,
    base: Population,
    lifted_from: dict[CFModel, CFModel],
) -> Absorption | None:
    """The strongest partner of a driver effect's parameters (module docstring).

    Args:
        final: the effect arm's population (fit windows).
        base: the arm it is compared with (the pool searched alone).
        lifted_from: per variant carrying the effect, its pool model.

    Returns:
        the partner, or None where no pair holds enough particles with the
        effect.
    """
    best: tuple[str, str, str, float, float | None, int] | None = None
    for variant, parent in lifted_from.items():
        pair, slot = final.model_slots(variant)
        if pair.numel() == 0:
            continue
        k = variant.n_params
        held = (final.model == final.models.index(variant)) & final.filled
        score = torch.where(held, final.score, math.inf)
        # other models' slots weigh 0: zeros, not their NaN padding
        theta = torch.where(held[..., None], final.theta[..., :k], 0.0)
        correlation, n_pairs = within_pair_correlation(theta, score)
        if n_pairs == 0:
            continue
        names = variant.param_names
        for column in _effect_columns(variant, effect):
            for partner in _base_names(variant, effect):
                r = float(correlation[column, names.index(partner)])
                if not math.isfinite(r):
                    continue
                if best is None or abs(r) > abs(best[3]):
                    slope = _ridge_slope(
                        theta[..., column], theta[..., names.index(partner)], score
                    )
                    best = (partner, parent, names[column], r, slope, n_pairs)
    if best is None:
        return None
    partner, parent, effect_parameter, r, slope, n_pairs = best
    return Absorption(
        parameter=partner,
        model=parent.name,
        effect_parameter=effect_parameter,
        correlation=r,
        slope=slope,
        n_pairs=n_pairs,
        shift=_shift(final, base, lifted_from, partner),
        absorbed=abs(r) >= RIDGE_CORRELATION,
    )


def _ridge_slope(effect: Tensor, partner: Tensor, score: Tensor) -> float | None:
    """Pooled within-pair least-squares slope of ``partner`` on ``effect`` (N, S)
    over the finite-score slots (partner units per effect unit)."""
    weight = torch.isfinite(score).double()
    count = weight.sum(1, keepdim=True).clamp(min=1)
    centred_e = (effect - (effect * weight).sum(1, keepdim=True) / count) * weight
    centred_p = (partner - (partner * weight).sum(1, keepdim=True) / count) * weight
    variance = float((centred_e * centred_e).sum())
    if variance <= 0:
        return None
    return float((centred_e * centred_p).sum()) / variance


def profile_values(effect: Effect, points: int = PROFILE_VALUES) -> Tensor:
    """(G, K_E) the values an effect is profiled at: ``points`` evenly over its
    prior (every parameter together)."""
    box = torch.tensor(
        [[p.lower, p.upper] for p in effect.param_specs],
        dtype=torch.float64,
    )
    u = torch.linspace(0.0, 1.0, points, dtype=torch.float64)[:, None]
    return box[:, 0] + u * (box[:, 1] - box[:, 0])


def profile_absorption(
    effect: Effect,
    values: Tensor,
    fits: list[Population],
    lifted_from: dict[CFModel, CFModel],
    start: Population,
    estimate: Tensor | None,
    steady: Steady | None = None,
) -> ProfileAbsorption | None:
    """The strongest partner of a one-parameter effect along its profile.

    Args:
        values: (G, K_E) the fixed values (:func:`profile_values`).
        fits: per value, the population refitted with the effect fixed there.
        lifted_from: per variant, its pool model.
        start: the population the profile started from (the pool's fit).
        estimate: the effect's value found by the attribution (the shift is read
            at the profile value nearest to it), or None.
        steady: where to read the pool's steady state along the profile
            (:func:`steady_shift`), or None.

    Returns:
        the partner along the profile, or None where no pair's best particle
        carries the effect at every value.
    """
    g = values.shape[0]
    reference = start.score[:, 0]
    objective = []
    for fit in fits:
        ratio = fit.score[:, 0] / reference
        usable = torch.isfinite(ratio) & torch.isfinite(reference) & (reference > 0)
        objective.append(float(ratio[usable].mean()) if usable.any() else math.nan)
    models = {
        lifted_from.get(fit.models[int(m)])
        for fit in fits
        for m in fit.model[:, 0]
        if m >= 0
    }
    best: tuple[str, str, float, float, float, int] | None = None
    along: list[tuple[CFModel, Tensor]] = []  # per pool model, its best particles
    for parent in sorted((m for m in models if m), key=lambda m: m.name):
        names = parent.param_names
        # (N, G, K): each pair's best particle per value, where it descends
        # from this pool model at every value
        rows = torch.full((start.n_pairs, g, len(names)), math.nan, dtype=torch.float64)
        for i, fit in enumerate(fits):
            for j in range(fit.n_pairs):
                if not bool(fit.filled[j, 0]):
                    continue
                model = fit.models[int(fit.model[j, 0])]
                if lifted_from.get(model) is not parent:
                    continue
                variant = model.param_names
                rows[j, i] = torch.stack(
                    [fit.theta[j, 0, variant.index(n)] for n in names]
                )
        complete = torch.isfinite(rows).all(dim=(1, 2))
        if int(complete.sum()) < 2:
            continue
        rows = rows[complete]
        along.append((parent, rows))
        x = values[:, 0][None, :].expand(rows.shape[0], -1)  # (N', G)
        xc = x - x.mean(1, keepdim=True)
        for k, name in enumerate(names):
            y = rows[..., k]
            yc = y - y.mean(1, keepdim=True)
            denominator = float(torch.sqrt((xc * xc).sum() * (yc * yc).sum()))
            if denominator <= 0:
                continue
            r = float((xc * yc).sum()) / denominator
            if best is None or abs(r) > abs(best[2]):
                slope = float((xc * yc).sum() / (xc * xc).sum())
                at = (
                    0
                    if estimate is None
                    else int(torch.argmin((values[:, 0] - float(estimate[0])).abs()))
                )
                neutral = int(torch.argmin((values[:, 0] - effect.neutral[0]).abs()))
                shift = float((y[:, at] - y[:, neutral]).median())
                best = (name, parent, r, slope, shift, int(complete.sum()))
    if best is None:
        return None
    name, parent, r, slope, shift, n_pairs = best
    return ProfileAbsorption(
        parameter=name,
        model=parent.name,
        effect_parameter=effect.param_specs[0].name,
        correlation=r,
        slope=slope,
        shift=shift,
        n_pairs=n_pairs,
        absorbed=abs(r) >= RIDGE_CORRELATION,
        profile=Profile(tuple(values[:, 0].tolist()), tuple(objective)),
        steady=steady_shift(values[:, 0], along, steady)
        if steady is not None
        else None,
    )


@dataclass(frozen=True)
class Steady:
    """Where the pool's steady state is read: a speed [m/s] (the data's median
    follower speed), the sampling interval [s] and the leader's length [m]."""

    speed: float
    dt: float
    leader_length: float


def steady_shift(
    values: Tensor, along: list[tuple[CFModel, Tensor]], steady: Steady
) -> SteadyShift | None:
    """How the pool's own behaviour moves as an effect is fixed along its
    profile: each pair's best particle's equilibrium spacing at
    ``steady.speed`` and its time gap there (:mod:`torchcf.models.steady`),
    regressed within pairs on the effect's value (pooled over the pool's
    models).

    The reading a user needs when an effect is absorbed: a spacing-sensor
    offset ``d`` is a standstill gap ``-d`` in equilibrium, a leader log ``t``
    ahead a time gap ``+t``; the slopes say how much of it the pool's fit takes
    up (``gap_slope`` -1 m per m of offset: all of it).

    Args:
        values: (G,) the effect's fixed values.
        along: per pool model, each pair's best particle at every value (N',
            G, K), pairs where that model held the best at every value.

    Returns:
        the slopes and correlations, or None where no pair has an equilibrium
        at that speed at every value.
    """
    xs, gaps, time_gaps = [], [], []
    for model, rows in along:
        flat = rows.reshape(-1, rows.shape[-1])
        run = {"leader_length": steady.leader_length, "dt": steady.dt}
        gap = equilibrium_spacing(model, flat, steady.speed, **run)
        gap = gap.reshape(rows.shape[:2])  # (N', G)
        tg = time_gap(model, flat, steady.speed, **run).reshape(rows.shape[:2])
        keep = torch.isfinite(gap).all(1) & torch.isfinite(tg).all(1)
        if not bool(keep.any()):
            continue
        xs.append(values[None, :].expand(int(keep.sum()), -1))
        gaps.append(gap[keep])
        time_gaps.append(tg[keep])
    if not xs:
        return None
    x = torch.cat(xs)
    gap_slope, gap_r = _pooled_slope(x, torch.cat(gaps))
    tg_slope, tg_r = _pooled_slope(x, torch.cat(time_gaps))
    return SteadyShift(
        speed=steady.speed,
        gap_slope=gap_slope,
        gap_r=gap_r,
        time_gap_slope=tg_slope,
        time_gap_r=tg_r,
        n_pairs=int(x.shape[0]),
    )


def _pooled_slope(x: Tensor, y: Tensor) -> tuple[float | None, float | None]:
    """Within-row least-squares slope of ``y`` on ``x`` (N', G), pooled, and the
    pooled correlation."""
    xc = x - x.mean(1, keepdim=True)
    yc = y - y.mean(1, keepdim=True)
    sxx, syy = float((xc * xc).sum()), float((yc * yc).sum())
    if sxx <= 0:
        return None, None
    sxy = float((xc * yc).sum())
    r = sxy / math.sqrt(sxx * syy) if syy > 0 else 0.0
    return sxy / sxx, r


__all__ = [
    "PROFILE_VALUES",
    "Absorbed",
    "Absorption",
    "Profile",
    "ProfileAbsorption",
    "Steady",
    "SteadyShift",
    "absorbed_by",
    "absorbed_from_json",
    "profile_absorption",
    "profile_values",
    "steady_shift",
]
