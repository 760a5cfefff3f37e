"""One effect's test at one step of the forward selection: a row of ``loop.md``'s
table and of ``loop.json``'s ``steps``.

:func:`~torchcf.diagnose.attribution.effect_row` measures it (gains, the
sign-flip test, the estimate, what absorbed it); the selection's procedure then
gives it its verdict (its place in the order, its level, significant, chosen:
:func:`~torchcf.diagnose.attribution.attribute_effects`), and on a step that
chooses nothing the power analysis the sizes the data could have shown
(:func:`~torchcf.diagnose.power.detectable_sizes`).

Gains are relative drops of the summed score (a fraction; positive: the effect
fits better), scores are the weighted RMSE of SPEC section 4 (dimensionless),
an estimate is in the effect parameters' own units.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ..models.effects import Effect, Scope, parse_effect
from ..system.files import JSON

#: ``detectable`` of a row whose sizes were not asked for (a step that chose):
#: written as no key at all, where ``None`` is an effect without a size.
NOT_SIZED: Any = "not sized"


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
        shared: a shared effect's ``{"value", "prior", "interval"}``, else None.
        active: the estimate lies away from the neutral value
            (:func:`~torchcf.diagnose.attribution.active`).
        absorbed_by: the model parameter that trades off against the effect
            (:mod:`torchcf.diagnose.absorption`), or None.
        order, pointed_by, level, significant, chosen: the verdict.
        detectable: the smallest sizes these data could have shown
            (:func:`~torchcf.diagnose.power.detectable_sizes`; None: the effect
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
    shared: dict[str, Any] | None = None
    active: bool = False
    absorbed_by: dict[str, Any] | None = None
    order: int = 0
    pointed_by: list[str] = dataclasses.field(default_factory=list)
    level: float = 0.0
    significant: bool = False
    chosen: bool = False
    detectable: dict[str, Any] | None = NOT_SIZED

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
            out[field.name] = value
        return out

    @classmethod
    def from_json(cls, raw: JSON) -> EffectTest:
        """A row read back from :meth:`to_json`'s dict (the effect parsed from
        its token: where a row re-enters from a file)."""
        names = [f.name for f in dataclasses.fields(cls)[1:]]
        values = {name: raw[name] for name in names if name in raw}
        return cls(effect=parse_effect(raw["effect"]), **values)


__all__ = ["NOT_SIZED", "EffectTest"]
