"""What the loop found and what it changed: :class:`LoopResult`, the value of
:func:`~torchcf.diagnose.loop.finish_loop` (and of
:func:`torchcf.study.pipeline.close_loop`), written as ``RUN_DIR/loop.json``
(:meth:`LoopResult.to_json`, format :data:`FORMAT`).

Its parts that ``loop.json`` writes are records (:class:`~torchcf.system.
records.Record`: their ``to_json`` is the file's object, key order included):
:class:`ParamSpread` and :class:`EffectPosterior` (a chosen effect over the
hybrid), :class:`ChangeOnTest` (test pair by test pair), :class:`Unexplained`
(a signature no chosen effect explains) and :class:`SearchBudget`.

Metrics are the evaluation's test-split metrics of a hybrid (``metrics.json``'s
``hybrid`` entry: Wasserstein-type distances, minimum distance [m]...); shares
are fractions of the hybrid's particles per model.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

from ...config import DiagnoseConfig
from ...models.effects import Effect
from ...runs.metrics import SetEvaluation
from ...system.files import JSON
from ...system.records import Record, to_json_value
from ..arms.identifiability import Identifiability
from ..selection.attribution import EffectSelection
from ..selection.on_test import ClassOnTest
from ..signatures.response import ResponseTimes
from ..signatures.road import RoadOffer
from ..signatures.series import ResidualRow
from ..significance import PairedChange

#: ``loop.json``'s format.
FORMAT = "torchcf.loop/2"


@dataclass(frozen=True)
class ParamSpread(Record):
    """One effect parameter over the hybrid's particles that carry it, in its
    own unit (the file holds ``n`` alone where none does).

    Attributes:
        n: the particles; median, q05, q95, mean: of their values (None: no
            particle).
    """

    n: int
    median: float | None = None
    q05: float | None = None
    q95: float | None = None
    mean: float | None = None

    def to_json(self) -> JSON:
        """The object: ``{"n": 0}`` without particles, else every field."""
        return {"n": 0} if self.n == 0 else super().to_json()


@dataclass(frozen=True)
class EffectPosterior(Record):
    """A chosen effect over the re-calibrated hybrid
    (:func:`~torchcf.diagnose.loop.effect_posterior`).

    Attributes:
        share: the hybrid's share of the models that carry it.
        params: per effect parameter, its spread over their particles.
    """

    share: float
    params: dict[str, ParamSpread]

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of its JSON object."""
        return cls(
            share=raw["share"],
            params={k: ParamSpread.from_json(v) for k, v in raw["params"].items()},
        )


@dataclass(frozen=True)
class ChangeOnTest(Record):
    """After against the run and against the reference, test pair by test pair
    (:func:`~torchcf.diagnose.significance.paired_change`; None where the two
    do not share a usable test pair)."""

    run: PairedChange | None
    reference: PairedChange | None

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of its JSON object."""
        return cls(
            *(
                None if raw[k] is None else PairedChange.from_json(raw[k])
                for k in ("run", "reference")
            )
        )


@dataclass(frozen=True)
class Unexplained(Record):
    """A signature still in the final model's residual that no chosen effect
    explains (:func:`~torchcf.diagnose.loop.unexplained`).

    Attributes:
        signature, mean, unit, p_value: the signature's test
            (:class:`~torchcf.diagnose.signatures.families.SignatureRow`).
        tested_not_chosen: effects it points to that were tested, not chosen.
        family: the model family it suggests.
    """

    signature: str
    mean: float
    unit: str
    p_value: float
    tested_not_chosen: tuple[str, ...]
    family: str


@dataclass(frozen=True)
class SearchBudget(Record):
    """The loop's search budgets as run (``diagnose.*``, with the run's).

    Attributes:
        population: slots per pair (at least the run's ``top_n``).
        local_copies, rounds, refit_rounds, validation_warmup: ``diagnose.*``.
        n_particles: ``diagnose.n_particles``; run_particles: the run's
            ``abc.n_particles``.
        n_train: training pairs.
        refit_slots, refit_stop: ``diagnose.*`` (None and "rounds" in a
            record written before them: ``abc.top_n`` slots, every round run).
    """

    population: int
    local_copies: int
    rounds: int
    refit_rounds: int
    validation_warmup: float
    n_particles: int
    run_particles: int
    n_train: int
    refit_slots: int | None = None
    refit_stop: str = "rounds"


@dataclass(frozen=True)
class Recalibrated:
    """The re-calibration with the chosen effects, beside the run's particles
    searched the same way without them.

    Attributes:
        after_run: ``RUN_DIR/loop/after``; reference_run: ``RUN_DIR/loop/reference``.
        after: the re-calibration's test metrics (the hybrid's); shares: its
            hybrid's shares.
        before_same_search: the reference's test metrics (the hybrid's).
        test_pairs: after against the run and against the reference, test pair
            by test pair.
        posterior: per chosen effect's token, its parameters over the hybrid's
            particles (:func:`~torchcf.diagnose.loop.effect_posterior`).
        identifiability: per chosen effect's token, its strongest partners
            (:func:`~torchcf.diagnose.arms.identifiability.effect_identifiability`).
        residuals_after: the residual tests of the re-calibrated hybrid.
        response_after: the re-calibrated hybrid's response times.
    """

    after_run: Path
    reference_run: Path
    after: SetEvaluation
    shares: dict[str, float]
    before_same_search: SetEvaluation
    test_pairs: ChangeOnTest
    posterior: dict[str, EffectPosterior]
    identifiability: Identifiability
    residuals_after: list[ResidualRow]
    response_after: ResponseTimes | None = None


@dataclass(frozen=True)
class LoopResult:
    """The loop's result.

    Attributes:
        run: the diagnosed run's directory.
        dataset: the data set's name (from its ``metrics.json``).
        pool: the pool models that got the effects.
        road: how road effects were offered.
        selection: the forward selection (its steps, chosen effects, final
            models).
        unexplained: signatures still in the final model's residual
            (:func:`~torchcf.diagnose.loop.unexplained`).
        settings: the ``diagnose`` section the loop ran with.
        search: the search's budgets as run (``population``, ``local_copies``,
            ``rounds``, ..., ``n_train``).
        before: the run's test metrics; shares_before: its hybrid's shares.
        residuals_before: the residual tests of the run.
        recalibrated: the re-calibration, or None when nothing was chosen.
        seconds: the loop's wall-clock time [s].
        response_before: the data's and the run's response times
            (:func:`~torchcf.diagnose.signatures.response.response_times`).
        class_on_test: the model class with and without the chosen effects,
            every test pair refitted (:func:`~torchcf.diagnose.selection.on_test.
            class_on_test`; None: nothing chosen).
    """

    run: Path
    dataset: str
    pool: list[str]
    road: RoadOffer
    selection: EffectSelection
    unexplained: list[Unexplained]
    settings: DiagnoseConfig
    search: SearchBudget
    before: SetEvaluation
    shares_before: dict[str, float]
    residuals_before: list[ResidualRow]
    recalibrated: Recalibrated | None
    seconds: float
    response_before: ResponseTimes | None = None
    class_on_test: ClassOnTest | None = None

    @property
    def chosen(self) -> list[Effect]:
        """The chosen effects, in the order chosen."""
        return self.selection.chosen

    @property
    def after(self) -> SetEvaluation:
        """The test metrics after: the re-calibration's, or the run's when
        nothing was chosen."""
        return self.before if self.recalibrated is None else self.recalibrated.after

    @property
    def shares_after(self) -> dict[str, float]:
        """The hybrid's shares after (the run's when nothing was chosen)."""
        if self.recalibrated is None:
            return self.shares_before
        return self.recalibrated.shares

    def to_json(self) -> JSON:
        """``loop.json``'s content."""
        selection = self.selection
        first = selection.steps[0] if selection.steps else []
        out: JSON = {
            "format": FORMAT,
            "run": str(self.run),
            "dataset": self.dataset,
            "pool": self.pool,
            "road": self.road.to_json(),
            "signatures": to_json_value(selection.signatures),
            "effects_ranked": [row.to_json() for row in first],
            "steps": [[row.to_json() for row in rows] for rows in selection.steps],
            "absorption": {row.token: to_json_value(row.absorbed_by) for row in first},
            "unexplained": to_json_value(self.unexplained),
            "chosen": [effect.token for effect in self.chosen],
            "shared": selection.shared,
            "models_after": [m.name for m in selection.models],
            "steps_at_most": selection.steps_at_most,
            "levels": selection.levels,
            "alpha": self.settings.alpha,
            "fit_fraction": self.settings.fit_fraction,
            "validation": selection.validation.kind,
            "validation_asked": self.settings.validation,
            "validation_units": selection.validation.units,
            "fit_pairs": selection.validation.fit_pairs,
            "min_gain": self.settings.min_gain,
            "recalibration": "train",  # the one engine (earlier: or "search")
            "search": self.search.to_json(),
            "before": self.before.to_json(),
            "residuals_before": to_json_value(self.residuals_before),
            "after": self.after.to_json(),
        }
        done = self.recalibrated
        out |= {
            "after_run": None if done is None else str(done.after_run),
            "shares_after": self.shares_after,
            "before_same_search": None
            if done is None
            else done.before_same_search.to_json(),
            "test_pairs": None if done is None else done.test_pairs.to_json(),
            "reference_run": None if done is None else str(done.reference_run),
            "posterior": {} if done is None else to_json_value(done.posterior),
            "identifiability": {}
            if done is None
            else to_json_value(done.identifiability),
            "residuals_after": to_json_value(
                self.residuals_before if done is None else done.residuals_after
            ),
            "class_on_test": to_json_value(self.class_on_test),
            "response_times": {
                "before": to_json_value(self.response_before),
                "after": to_json_value(
                    self.response_before if done is None else done.response_after
                ),
            },
            "seconds": self.seconds,
        }
        return out


__all__ = [
    "FORMAT",
    "ChangeOnTest",
    "EffectPosterior",
    "LoopResult",
    "ParamSpread",
    "Recalibrated",
    "SearchBudget",
    "Unexplained",
]
