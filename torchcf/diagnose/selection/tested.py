"""One effect's test at one step of the forward selection: a row of ``loop.md``'s
table and of ``loop.json``'s ``steps``.

:func:`~torchcf.diagnose.selection.attribution.effect_row` measures it (gains, the
sign-flip test, the estimate, what absorbed it); the selection's procedure then
gives it its verdict (its place in the order, its level, significant, chosen:
:func:`~torchcf.diagnose.selection.attribution.attribute_effects`), and on a step that
chooses nothing the power analysis the sizes the data could have shown
(:func:`~torchcf.diagnose.selection.power.detectable_sizes`).

Gains are relative drops of the summed score (a fraction; positive: the effect
fits better), scores are the weighted RMSE of SPEC section 4 (dimensionless),
an estimate is in the effect parameters' own units.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Self

from ...models.effects import Effect, Scope, parse_effect
from ...system.files import JSON
from ...system.records import Record, to_json_value
from ..arms.absorption import Absorbed, absorbed_from_json


@dataclass(frozen=True)
class Rung(Record):
    """One size tried: the test the data would have given it.

    Attributes:
        size: the effect's value (a grade: the amplitude) [its unit].
        gain: the relative drop of the summed score, ``sum(after - before) /
            sum(after)`` with ``after`` the refit with the effect at the size
            (what the model without the effect would score on data with it).
        p_value: the one-sided sign-flip test of the per-unit log ratios.
    """

    size: float
    gain: float
    p_value: float

    def passes(self, level: float, min_gain: float) -> bool:
        return self.p_value <= level and self.gain >= min_gain


@dataclass(frozen=True)
class Detectable(Record):
    """The smallest sizes an effect's test would have found in these data
    (:func:`detectable_sizes`), per side of the neutral value (``"below"``,
    ``"above"``; None: not even at the end of the prior).

    Attributes:
        unit: the size's unit (a grade: ``"1 (grade amplitude)"``).
        level: the level the effect was judged at (its place in the order).
        at_level: per side, the smallest size detectable at ``level``.
        first_level: the step's first level (had the residual pointed to it).
        if_first: per side, the smallest size detectable at ``first_level``.
        tried: per side, the sizes tried and their tests, smallest first.
    """

    unit: str
    level: float
    at_level: dict[str, float | None]
    first_level: float
    if_first: dict[str, float | None]
    tried: dict[str, tuple[Rung, ...]]

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of its JSON object (:meth:`to_json`'s)."""
        return cls(
            unit=raw["unit"],
            level=raw["level"],
            at_level=dict(raw["at_level"]),
            first_level=raw["first_level"],
            if_first=dict(raw["if_first"]),
            tried={
                side: tuple(Rung.from_json(rung) for rung in rungs)
                for side, rungs in raw["tried"].items()
            },
        )


#: ``detectable`` of a row whose sizes were not asked for (a step that chose):
#: written as no key at all, where ``None`` is an effect without a size.
NOT_SIZED: Any = "not sized"


@dataclass(frozen=True)
class SharedValue(Record):
    """A shared effect's one value for every pair, as its arm found it.

    Attributes:
        value: per effect parameter, its value.
        prior: per effect parameter, the ``(low, high)`` box of the search's
            last round.
        interval: per the effect's first parameter, its interval (None: not
            measured).
    """

    value: dict[str, float]
    prior: dict[str, tuple[float, float]]
    interval: dict[str, list[float]] | None

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of its JSON object (a box read back as a tuple)."""
        interval = raw["interval"]
        return cls(
            value=dict(raw["value"]),
            prior={k: tuple(box) for k, box in raw["prior"].items()},
            interval=None if interval is None else dict(interval),
        )


@dataclass
class EffectTest:
    """An effect tested against the placebo at one step.

    Attributes:
        effect: the effect (its options resolved).
        fit_gain: in-sample gain against the placebo (fit windows).
        base_fit_gain: in-sample gain against the base arm, which the effect
            arm holds (never negative).
        gain: the out-of-sample gain against the placebo (the validation).
        statistic, p_value: the sign-flip test of the per-unit log drops.
        score_before, score_after: mean validation score of the placebo and of
            the effect arm over the usable units (None: none usable).
        n_pairs: usable validation units; pairs_changed: units whose score moved.
        pinned: the effect's values held on held-out pairs (validation
            ``"refit"``), else None.
        variants: the pool models' variants carrying the effect.
        estimate: the effect's parameters (median over the arm's picks that
            carry it, or a shared effect's one value).
        per_pair: ``{"before": [...], "after": [...]}`` validation score per unit
            (None: invalid).
        shared: a shared effect's one value, else None.
        active: the estimate lies away from the neutral value
            (:func:`~torchcf.diagnose.selection.attribution.active`).
        absorbed_by: the model parameter that trades off against the effect
            (:mod:`torchcf.diagnose.arms.absorption`), or None.
        order, pointed_by, level, significant, chosen: the verdict.
        family: the tokens of the family the effect was tested in (twins
            that one signature points to, itself among them; empty: tested
            alone); family_p_value: that family's p-value (the largest
            statistic over its members), None when tested alone.
        detectable: the smallest sizes these data could have shown
            (:func:`~torchcf.diagnose.selection.power.detectable_sizes`; None: the
            effect
            has no one-number size; :data:`NOT_SIZED`: not asked).
    """

    effect: Effect
    fit_gain: float
    base_fit_gain: float
    gain: float
    statistic: float
    p_value: float
    score_before: float | None
    score_after: float | None
    n_pairs: int
    pairs_changed: int
    pinned: dict[str, float] | None
    variants: list[str]
    estimate: dict[str, float]
    per_pair: dict[str, list[float | None]]
    shared: SharedValue | None = None
    active: bool = False
    absorbed_by: Absorbed | None = None
    order: int = 0
    pointed_by: list[str] = dataclasses.field(default_factory=list)
    family: list[str] = dataclasses.field(default_factory=list)
    family_p_value: float | None = None
    level: float = 0.0
    significant: bool = False
    chosen: bool = False
    detectable: Detectable | None = NOT_SIZED

    @property
    def name(self) -> str:
        """The effect's kind (``"grade"`` for ``grade(start=0,end=900)``)."""
        return self.effect.name

    @property
    def token(self) -> str:
        """The effect with its options, as written in a model's name."""
        return self.effect.token

    @property
    def scope(self) -> Scope:
        return self.effect.scope

    def to_json(self) -> JSON:
        """The row as ``loop.json`` and the attribution's ledger keep it."""
        out: JSON = {"name": self.name, "effect": self.token}
        out["scope"] = self.scope
        for field in dataclasses.fields(self)[1:]:
            value = getattr(self, field.name)
            if field.name == "shared" and value is None:
                continue
            if field.name == "detectable" and value is NOT_SIZED:
                continue
            out[field.name] = to_json_value(value)
        return out

    @classmethod
    def from_json(cls, raw: JSON) -> EffectTest:
        """A row read back from :meth:`to_json`'s dict (the effect parsed from
        its token, the records of its parts from theirs: where a row re-enters
        from a file)."""
        names = [f.name for f in dataclasses.fields(cls)[1:]]
        values = {name: raw[name] for name in names if name in raw}
        parts = {
            "shared": SharedValue.from_json,
            "absorbed_by": absorbed_from_json,
            "detectable": Detectable.from_json,
        }
        for name, read in parts.items():
            if values.get(name) is not None:
                values[name] = read(values[name])
        return cls(effect=parse_effect(raw["effect"]), **values)


__all__ = ["NOT_SIZED", "EffectTest", "SharedValue"]
