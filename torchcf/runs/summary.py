"""The records of a run's ``summary.json``: what training, and a re-calibration of
the diagnosis loop, leave in a run directory.

:class:`RunSummary` is a frozen record of what a training's ``summary.json``
holds, with typed sub-records (:class:`ModelResult` per model,
:class:`Pairwise`, :class:`SMCResult`, :class:`AmortisedResult`,
:class:`PlausibilitySummary` per model, :class:`Versions`);
:meth:`RunSummary.to_json` gives the file's content, key order included, and
:meth:`RunSummary.from_json` reads it back (``from_json(s.to_json()) == s``).
:class:`RecalibrationSummary` is the shorter one a re-calibration writes
(:func:`torchcf.diagnose.recalibration.write_run`). The training computes its
records in :mod:`torchcf.train.summary`; :class:`~torchcf.runs.directory.RunDir`
writes and reads them (``run.read_summary()``).

Callers read the attributes (``summary.shares``,
``summary.per_model["idm"].seconds``, ``summary.smc is None``); the JSON object
is the file's edge alone.

Units: seconds (s) for times, rounded to the millisecond where stored;
particles counted per model; scores and thresholds are the run's score
``g = w_p e_p + w_v e_v + w_a e_a`` (dimensionless: the RMSEs of position [m],
speed [m/s] and acceleration [m/s^2] times ``abc.weights``); shares in [0, 1].
"""

from __future__ import annotations

import platform
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np
import torch

from ..system.files import JSON
from ..system.records import Record, copy_json, to_json_value
from ..system.version import __version__

PAIRWISE_MEANING = "table[i][j]: share of models[i] in the hybrid of {i, j} alone"
SMC_MEANING = (
    "shares: each model's share of the per-pair top-N slots, as in "
    "rejection but from a search refined where it fits, so without the "
    "prior's Occam factor; evidence_shares: importance-sampling estimate of "
    "each model's prior mass within the hybrid's per-pair threshold, "
    "normalised per pair and averaged over pairs: what rejection's shares "
    "estimate, with the Occam factor"
)


@dataclass(frozen=True)
class ModelResult(Record):
    """One model's stream and buffer (``summary.json``'s ``per_model[model]``).

    Attributes:
        particles: particles offered to the buffer.
        invalid: invalid rollouts among them (cells, in the full layout).
        invalid_rate: ``invalid`` over the cells simulated, in [0, 1].
        implausible: particles the plausibility filter rejected.
        seconds: simulation and selection time (s, rounded to ms).
        particles_per_s: ``particles / seconds`` (unrounded seconds).
        best_score: the best score over all pairs; None if none is finite.
        threshold: mean over pairs of the N-th best score (N = ``top_n``),
            over the pairs where it is finite; None if none is.
        threshold_max: the largest per-pair N-th best score; None if infinite.
        thresholds: ``(N_pairs,)`` per-pair N-th best score (None: infinite).
        pairs_short_of_n: pairs holding fewer than N finite scores.
        stopped: rollouts (cells) early rejection stopped above their buffer's
            threshold (``abc.early_rejection``); ``invalid`` then counts the
            invalid rollouts among the others.

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.summary import ModelResult
        >>> [f.name for f in fields(ModelResult)][:6]
        ['particles', 'invalid', 'invalid_rate', 'implausible', 'seconds',
         'particles_per_s']
    """

    particles: int
    invalid: int
    invalid_rate: float
    implausible: int
    seconds: float
    particles_per_s: float
    best_score: float | None
    threshold: float | None
    threshold_max: float | None
    thresholds: tuple[float | None, ...]
    pairs_short_of_n: int
    stopped: int = 0


@dataclass(frozen=True)
class Pairwise(Record):
    """The pairwise table: ``table[i][j]`` is the share of ``models[i]`` in the
    hybrid of models ``i`` and ``j`` alone (6 decimals; 1 on the diagonal).

    Examples:
        >>> from torchcf.runs.summary import Pairwise
        >>> pairwise = Pairwise(("idm", "ovm"), ((1.0, 0.7), (0.3, 1.0)))
        >>> pairwise.to_json()["table"]
        [[1.0, 0.7], [0.3, 1.0]]
        >>> Pairwise.from_json(pairwise.to_json()) == pairwise
        True
    """

    models: tuple[str, ...]
    table: tuple[tuple[float, ...], ...]
    meaning: str = PAIRWISE_MEANING


@dataclass(frozen=True)
class Versions(Record):
    """The versions the run was made with.

    Examples:
        >>> import torch
        >>> from torchcf.runs.summary import Versions
        >>> versions = Versions.current()
        >>> list(versions.to_json()), versions.torch == torch.__version__
        (['torchcf', 'torch', 'numpy', 'python'], True)
    """

    torchcf: str
    torch: str
    numpy: str
    python: str

    @classmethod
    def current(cls) -> Versions:
        """This process's versions."""
        return cls(
            torchcf=__version__,
            torch=torch.__version__,
            numpy=np.__version__,
            python=platform.python_version(),
        )


@dataclass(frozen=True)
class SMCBudgetResult(Record):
    """How each model's ``n_particles`` were spent by the refinement
    (:class:`torchcf.abc.smc.Budget`): particles per model.

    Examples:
        >>> from torchcf.runs.summary import SMCBudgetResult
        >>> budget = SMCBudgetResult(150, 15, 3, 450, 0)  # 600 particles, 10 pairs
        >>> budget.prior_draws + budget.proposals + budget.unspent
        600
        >>> SMCBudgetResult.from_json(budget.to_json()) == budget
        True
    """

    prior_draws: int
    proposals_per_pair_and_round: int
    rounds: int
    proposals: int
    unspent: int


@dataclass(frozen=True)
class SMCResult(Record):
    """The refinement's settings (``abc.smc``, as :class:`~torchcf.abc.smc.
    SMCSettings` fields), budget and evidence shares (model -> share in [0, 1],
    with the prior's Occam factor: :func:`torchcf.abc.smc.evidence_shares`).

    Examples:
        >>> from torchcf.runs.summary import SMCBudgetResult, SMCResult
        >>> budget = SMCBudgetResult(150, 15, 3, 450, 0)
        >>> smc = SMCResult({"rounds": 3}, budget, {"idm": 0.8, "ovm": 0.2})
        >>> list(smc.to_json()), SMCResult.from_json(smc.to_json()) == smc
        (['settings', 'budget', 'evidence_shares', 'meaning'], True)
    """

    settings: JSON
    budget: SMCBudgetResult
    evidence_shares: dict[str, float]
    meaning: str = SMC_MEANING

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> SMCResult:
        """The record of ``summary.json``'s ``smc`` object."""
        if set(raw) - {f.name for f in fields(cls)}:
            raise ValueError(f"SMCResult: unknown key(s) in {list(raw)}")
        return cls(
            settings=copy_json(raw["settings"]),
            budget=SMCBudgetResult.from_json(raw["budget"]),
            evidence_shares=dict(raw["evidence_shares"]),
            meaning=raw["meaning"],
        )


@dataclass(frozen=True)
class RefinedModel(Record):
    """What the refinement changed for one model
    (:mod:`torchcf.calibration.refinement`).

    Attributes:
        share_before, share_after: the model's share of the hybrid on the
            amortised samples alone, and after the refinement.
        median_best_before, median_best_after: the median over the training
            pairs of the pair's best score of the model (the run's distance;
            None where no pair has one).

    Examples:
        >>> from torchcf.runs.summary import RefinedModel
        >>> RefinedModel(0.4, 0.55, 1.2, 0.9).to_json()
        {'share_before': 0.4, 'share_after': 0.55, 'median_best_before': 1.2,
         'median_best_after': 0.9}
    """

    share_before: float
    share_after: float
    median_best_before: float | None
    median_best_after: float | None


@dataclass(frozen=True)
class RefinementResult(Record):
    """The refinement of an amortised run (``abc.amortised.refine``).

    Attributes:
        rounds: SMC rounds after the amortised samples.
        per_pair: proposals per training pair, model and round.
        population: particles per pair carried from round to round.
        quantile: the threshold schedule's quantile.
        simulations: the refinement's simulations, all models and pairs.
        simulations_per_pair: of them, per training pair (all models).
        per_model: model -> :class:`RefinedModel`.

    Examples:
        >>> from torchcf.runs.summary import RefinedModel, RefinementResult
        >>> idm = RefinedModel(0.4, 0.55, 1.2, 0.9)
        >>> result = RefinementResult(2, 50, 20, 0.5, 2000, 200, {"idm": idm})
        >>> RefinementResult.from_json(result.to_json()) == result
        True
    """

    rounds: int
    per_pair: int
    population: int
    quantile: float
    simulations: int
    simulations_per_pair: int
    per_model: dict[str, RefinedModel]

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> RefinementResult:
        """The record of ``summary.json``'s ``amortised.refinement`` object."""
        plain = super().from_json({**raw, "per_model": {}})
        return replace(
            plain,
            per_model={
                name: RefinedModel.from_json(record)
                for name, record in raw["per_model"].items()
            },
        )


@dataclass(frozen=True)
class AmortisedResult(Record):
    """The amortised estimator's training and sampling (``abc.method =
    "amortised"``, :mod:`torchcf.calibration.estimator_samples`).

    Attributes:
        samples_per_pair: samples drawn per training pair, over all models.
        noise: the measurement noise added to the simulated followers:
            position [m], speed [m/s], acceleration [m/s^2].
        epochs: training epochs run.
        finished: why the training ended: ``"epochs"`` (its budget),
            ``"patience"`` (early stopping) or ``"seconds"`` (its time limit).
        simulations: simulations drawn, validation set included.
        invalid: of them, invalid rollouts (discarded).
        seconds: training time, every session of it (s, ms).
        validation_loss: the lowest validation loss, the weights kept (the
            negative log density in the flows' unbounded space).
        validation_accuracy: the share of validation simulations whose most
            probable model is the true one, with those weights.
        refinement: what the refinement changed (``abc.amortised.refine``);
            None (absent in the file) without one.
        reused: where the estimator was read from
            (``abc.amortised.estimator``), its training figures above being
            that earlier run's; None (absent in the file): trained by this run.

    Examples:
        >>> from torchcf.runs.summary import AmortisedResult
        >>> result = AmortisedResult(200, (0.05, 0.02, 0.1), 12, "patience", 84_000, 3,
        ...                          41.2, -3.1, 0.91)
        >>> "refinement" in result.to_json(), result.to_json()["noise"]
        (False, [0.05, 0.02, 0.1])
        >>> AmortisedResult.from_json(result.to_json()) == result
        True
    """

    samples_per_pair: int
    noise: tuple[float, float, float]
    epochs: int
    finished: str
    simulations: int
    invalid: int
    seconds: float
    validation_loss: float
    validation_accuracy: float
    refinement: RefinementResult | None = None
    reused: str | None = None

    def to_json(self) -> JSON:
        """The JSON object: the fields in order, ``refinement`` and ``reused``
        only when set."""
        raw = super().to_json()
        for optional in ("refinement", "reused"):
            if getattr(self, optional) is None:
                del raw[optional]
        return raw

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> AmortisedResult:
        """The record of ``summary.json``'s ``amortised`` object."""
        refinement = raw.get("refinement")
        plain = super().from_json({k: v for k, v in raw.items() if k != "refinement"})
        if refinement is None:
            return plain
        return replace(plain, refinement=RefinementResult.from_json(refinement))

    def with_refinement(self, refinement: RefinementResult) -> AmortisedResult:
        """This record with the refinement's."""
        return replace(self, refinement=refinement)


@dataclass(frozen=True)
class PlausibilitySettings(Record):
    """The battery's settings a summary records (``settings``; those of
    :class:`torchcf.traffic.battery.Battery`): cruise speed
    [m/s], the braking leader's decelerations [m/s^2], the collision spacing
    [m] and the platoon's vehicles.

    Examples:
        >>> from torchcf.runs.summary import PlausibilitySettings
        >>> PlausibilitySettings(25.0, (4.0, 6.0, 8.0), 0.0, 8).to_json()
        {'speed': 25.0, 'decelerations': [4.0, 6.0, 8.0], 'collision_spacing': 0.0,
         'platoon_size': 8}
    """

    speed: float
    decelerations: tuple[float, ...]
    collision_spacing: float
    platoon_size: int


@dataclass(frozen=True)
class PlausibilitySummary(Record):
    """A model's particles through the battery, as shares over them
    (:meth:`torchcf.traffic.battery.Plausibility.summary`; ``summary.json``'s
    ``plausibility[model]``).

    Attributes:
        n_particles: the particles P.
        collided: share that collided in some scenario (``string`` excluded).
        per_scenario: scenario name -> share that collided there.
        string_unstable: share whose platoon amplifies a disturbance.
        string_untested: share without a string-stability ratio.
        no_equilibrium: share without an equilibrium at some speed of the grid.
        not_started: share that did not pull away from standstill.
        min_ttc_median: median least time to collision [s] over the particles
            that closed in (None: none did).
        string_ratio_median: median string-stability ratio (None: none).
        settings: the battery's settings.

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.summary import PlausibilitySummary
        >>> [f.name for f in fields(PlausibilitySummary)][:4]
        ['n_particles', 'collided', 'per_scenario', 'string_unstable']
    """

    n_particles: int
    collided: float
    per_scenario: dict[str, float]
    string_unstable: float
    string_untested: float
    no_equilibrium: float
    not_started: float
    min_ttc_median: float | None
    string_ratio_median: float | None
    settings: PlausibilitySettings

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> PlausibilitySummary:
        """The record of a ``plausibility[model]`` object.

        Raises:
            KeyError: a key is missing.
            ValueError: an unknown key.
        """
        settings = PlausibilitySettings.from_json(raw["settings"])
        read = super().from_json({**raw, "per_scenario": dict(raw["per_scenario"])})
        return replace(read, settings=settings)


@dataclass(frozen=True)
class RunSummary(Record):
    """A finished run's summary: the content of ``summary.json``.

    Attributes (in the file's order):
        dataset: the data set's label (name, folder or ``"SOURCE (FORMAT)"``).
        layout: ``abc.layout`` (``"paired"`` or ``"full"``).
        selection: ``abc.selection`` (the hybrid's selection mode).
        top_n: ``abc.top_n``, the N of the per-pair top-N.
        n_particles: ``abc.n_particles``, particles per model.
        n_train: training pairs.
        n_test: test pairs (0: the data have no test split).
        train_pair_ids: ``(n_train,)`` the training pairs' ids.
        test_pair_ids: ``(n_test,)`` the test pairs' ids.
        models: the models, in the config's order.
        shares: model -> share of the hybrid, in [0, 1].
        hybrid_size: particles in the hybrid, all models.
        pairwise: the pairwise table.
        sensitivity: N -> the shares with the top-N of that N
            (``abc.sensitivity_n``); keys are strings in the file.
        per_model: model -> its stream's and buffer's record.
        seconds_total: the models' stream time summed (s, ms).
        seconds_wall_this_process: this process's wall time (s, ms; a resumed
            run counts since its resumption).
        processes: processes of the run (``torchrun``'s world size).
        config_hash: :func:`torchcf.config.config_hash` of the run's config.
        versions: the software's versions.
        method: ``abc.method``; None (absent in the file) in older summaries.
        smc: the refinement's record; ``abc.method = "smc"`` only.
        amortised: the estimator's record; ``abc.method = "amortised"`` only.
        plausibility: model -> the battery's shares over the hybrid's particles
            (:meth:`torchcf.traffic.battery.Plausibility.summary`); with
            ``plausibility.report`` only.
        dt: the data's time step [s]; leader_length: its leader length [m]
            (the training pairs'; None in summaries written before they were
            recorded).
        extra: keys of the file this release does not know, kept in order after
            the known ones (none in the summaries it writes).

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.runs.summary import RunSummary
        >>> [f.name for f in fields(RunSummary)][:6]
        ['dataset', 'layout', 'selection', 'top_n', 'n_particles', 'n_train']
        >>> RunSummary.OPTIONAL[:3]  # written only when set
        ('method', 'smc', 'amortised')
    """

    dataset: str
    layout: str
    selection: str
    top_n: int
    n_particles: int
    n_train: int
    n_test: int
    train_pair_ids: tuple[int, ...]
    test_pair_ids: tuple[int, ...]
    models: tuple[str, ...]
    shares: dict[str, float]
    hybrid_size: int
    pairwise: Pairwise
    sensitivity: dict[int, dict[str, float]]
    per_model: dict[str, ModelResult]
    seconds_total: float
    seconds_wall_this_process: float
    processes: int
    config_hash: str
    versions: Versions
    method: str | None = None
    smc: SMCResult | None = None
    amortised: AmortisedResult | None = None
    plausibility: dict[str, PlausibilitySummary] | None = None
    dt: float | None = None
    leader_length: float | None = None
    extra: JSON = field(default_factory=dict)

    #: fields written only when set (absent from the file when None)
    OPTIONAL: ClassVar[tuple[str, ...]] = (
        "method",
        "smc",
        "amortised",
        "plausibility",
        "dt",
        "leader_length",
    )

    # ------------------------------------------------------------------ JSON

    def _json_keys(self) -> list[str]:
        """The file's keys, in order."""
        keys = [
            f.name
            for f in fields(self)
            if f.name != "extra"
            and not (f.name in self.OPTIONAL and getattr(self, f.name) is None)
        ]
        return keys + list(self.extra)

    def to_json(self) -> JSON:
        """The content of ``summary.json``, key order included (a fresh copy)."""
        return {
            key: copy_json(self.extra[key])
            if key in self.extra
            else to_json_value(getattr(self, key))
            for key in self._json_keys()
        }

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> RunSummary:
        """The summary of ``summary.json``'s content.

        Raises:
            ValueError: a key of the summary is missing or malformed.
        """
        names = {f.name for f in fields(cls)} - {"extra"}
        try:
            smc, plausibility = raw.get("smc"), raw.get("plausibility")
            amortised = raw.get("amortised")
            return cls(
                dataset=raw["dataset"],
                layout=raw["layout"],
                selection=raw["selection"],
                top_n=raw["top_n"],
                n_particles=raw["n_particles"],
                n_train=raw["n_train"],
                n_test=raw["n_test"],
                train_pair_ids=tuple(raw["train_pair_ids"]),
                test_pair_ids=tuple(raw["test_pair_ids"]),
                models=tuple(raw["models"]),
                shares=dict(raw["shares"]),
                hybrid_size=raw["hybrid_size"],
                pairwise=Pairwise.from_json(raw["pairwise"]),
                sensitivity={int(k): dict(v) for k, v in raw["sensitivity"].items()},
                per_model={
                    name: ModelResult.from_json(record)
                    for name, record in raw["per_model"].items()
                },
                seconds_total=raw["seconds_total"],
                seconds_wall_this_process=raw["seconds_wall_this_process"],
                processes=raw["processes"],
                config_hash=raw["config_hash"],
                versions=Versions.from_json(raw["versions"]),
                method=raw.get("method"),
                smc=None if smc is None else SMCResult.from_json(smc),
                amortised=None
                if amortised is None
                else AmortisedResult.from_json(amortised),
                plausibility=None
                if plausibility is None
                else {
                    name: PlausibilitySummary.from_json(record)
                    for name, record in plausibility.items()
                },
                dt=raw.get("dt"),
                leader_length=raw.get("leader_length"),
                extra={k: copy_json(v) for k, v in raw.items() if k not in names},
            )
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise ValueError(
                f"not a run summary ({type(error).__name__}: {error})"
            ) from None

    def with_plausibility(
        self, plausibility: dict[str, PlausibilitySummary]
    ) -> RunSummary:
        """This summary with the hybrid's plausibility report."""
        return replace(self, plausibility=plausibility)

    def with_amortised(self, amortised: AmortisedResult) -> RunSummary:
        """This summary with the amortised estimator's record."""
        return replace(self, amortised=amortised)


@dataclass(frozen=True)
class RecalibrationSummary(Record):
    """The summary of a re-calibration's run directory (the diagnosis loop's
    ``loop/after`` or ``loop/reference`` searched, not trained:
    :func:`torchcf.diagnose.recalibration.write_run`), what its evaluation reads.

    Attributes (in the file's order):
        dataset: the run's data set label (its training summary's).
        shares: model -> share of the re-calibrated hybrid, in [0, 1].
        hybrid_size: particles in the hybrid, all models.
        pairwise: the pairwise table of its buffers.
        recalibration: how the buffers were made.

    Examples:
        >>> from torchcf.runs.summary import Pairwise, RecalibrationSummary
        >>> pairwise = Pairwise(("idm",), ((1.0,),))
        >>> summary = RecalibrationSummary("demo", {"idm": 1.0}, 5, pairwise, "smc")
        >>> RecalibrationSummary.from_json(summary.to_json()) == summary
        True
    """

    dataset: str
    shares: dict[str, float]
    hybrid_size: int
    pairwise: Pairwise
    recalibration: str

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> RecalibrationSummary:
        """The summary of a re-calibration's ``summary.json``.

        Raises:
            ValueError: a key is missing, unknown or malformed.
        """
        try:
            return cls(
                dataset=raw["dataset"],
                shares=dict(raw["shares"]),
                hybrid_size=raw["hybrid_size"],
                pairwise=Pairwise.from_json(raw["pairwise"]),
                recalibration=raw["recalibration"],
            )
        except (KeyError, TypeError, ValueError, AttributeError) as error:
            raise ValueError(
                f"not a re-calibration's summary ({type(error).__name__}: {error})"
            ) from None


__all__ = [
    "PAIRWISE_MEANING",
    "SMC_MEANING",
    "AmortisedResult",
    "ModelResult",
    "Pairwise",
    "PlausibilitySettings",
    "PlausibilitySummary",
    "RecalibrationSummary",
    "RefinedModel",
    "RefinementResult",
    "RunSummary",
    "SMCBudgetResult",
    "SMCResult",
    "Versions",
]
