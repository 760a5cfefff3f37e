"""What the loop found and what it changed: :class:`LoopResult`, the value of
:func:`~torchcf.diagnose.loop.finish_loop` (and of
:func:`torchcf.study.pipeline.close_loop`), written as ``RUN_DIR/loop.json``
(:meth:`LoopResult.to_json`, format :data:`FORMAT`).

Metrics are the evaluation's test-split metrics of a hybrid (``metrics.json``'s
``hybrid`` entry: Wasserstein-type distances, minimum distance [m]...); shares
are fractions of the hybrid's particles per model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import DiagnoseConfig
from ..models.effects import Effect
from ..system.files import JSON
from .attribution import EffectSelection
from .road import RoadOffer

#: ``loop.json``'s format.
FORMAT = "torchcf.loop/2"


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
            by test pair (:func:`~torchcf.diagnose.significance.paired_change`;
            None where a run's metrics have no per-pair distances).
        posterior: per chosen effect's token, its parameters over the hybrid's
            particles (:func:`~torchcf.diagnose.loop.effect_posterior`).
        identifiability: per chosen effect's token, its strongest partners
            (:func:`~torchcf.diagnose.identifiability.effect_identifiability`).
        residuals_after: the residual tests of the re-calibrated hybrid.
    """

    after_run: Path
    reference_run: Path
    after: JSON
    shares: dict[str, float]
    before_same_search: JSON
    test_pairs: dict[str, Any]
    posterior: dict[str, Any]
    identifiability: dict[str, Any]
    residuals_after: list[dict[str, Any]]


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
    """

    run: Path
    dataset: str | None
    pool: list[str]
    road: RoadOffer
    selection: EffectSelection
    unexplained: list[dict[str, Any]]
    settings: DiagnoseConfig
    search: dict[str, Any]
    before: JSON
    shares_before: dict[str, float]
    residuals_before: list[dict[str, Any]]
    recalibrated: Recalibrated | None
    seconds: float

    @property
    def chosen(self) -> list[Effect]:
        """The chosen effects, in the order chosen."""
        return self.selection.chosen

    @property
    def after(self) -> JSON:
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
            "signatures": selection.signatures,
            "effects_ranked": [row.to_json() for row in first],
            "steps": [[row.to_json() for row in rows] for rows in selection.steps],
            "absorption": {row.token: row.absorbed_by for row in first},
            "unexplained": self.unexplained,
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
            "recalibration": self.settings.recalibration,
            "search": self.search,
            "before": self.before,
            "residuals_before": self.residuals_before,
            "after": self.after,
        }
        done = self.recalibrated
        out |= {
            "after_run": None if done is None else str(done.after_run),
            "shares_after": self.shares_after,
            "before_same_search": None if done is None else done.before_same_search,
            "test_pairs": None if done is None else done.test_pairs,
            "reference_run": None if done is None else str(done.reference_run),
            "posterior": {} if done is None else done.posterior,
            "identifiability": {} if done is None else done.identifiability,
            "residuals_after": self.residuals_before
            if done is None
            else done.residuals_after,
            "seconds": self.seconds,
        }
        return out


__all__ = ["FORMAT", "LoopResult", "Recalibrated"]
