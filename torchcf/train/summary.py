"""The run's results and its summary (``summary.json``), as typed records.

After the streams, the hybrid is selected from the buffers (:func:`read_results`:
the :class:`~torchcf.posterior.Posterior` and the :class:`RunSummary`).
:class:`RunSummary` is a frozen record of what ``summary.json`` holds, with
typed sub-records (:class:`ModelResult` per model, :class:`Pairwise`,
:class:`SMCResult`, :class:`Versions`); :meth:`RunSummary.to_json` gives the
file's content, key order included, and :meth:`RunSummary.from_json` reads it
back (``from_json(s.to_json()) == s``).

Callers read the attributes (``summary.shares``,
``summary.per_model["idm"].seconds``, ``summary.smc is None``); the JSON object
is the file's edge alone (``summary.to_json() == run.read_summary()``).

Units: seconds (s) for times, rounded to the millisecond where stored;
particles counted per model; scores and thresholds are the run's score
``g = w_p e_p + w_v e_v + w_a e_a`` (dimensionless: the RMSEs of position [m],
speed [m/s] and acceleration [m/s^2] times ``abc.weights``); shares in [0, 1].
"""

from __future__ import annotations

import math
import platform
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np
import torch

from .. import __version__
from ..abc.configured import smc_settings
from ..abc.hybrid import Selection, hybrid_posterior, pairwise_table, select
from ..abc.rejection import ModelProgress
from ..abc.smc import (
    evidence_shares,
    parameter_buffer,
    prior_mass,
    proposals_per_pair,
    smc_budget,
)
from ..abc.topn import TopN
from ..config import TrainConfig, config_hash
from ..config.schema import DataConfig
from ..data import PairSet
from ..posterior import Posterior
from ..system.files import JSON
from ..system.records import Record, copy_json, to_json_value
from ..traffic.battery import PlausibilitySummary
from .checkpoint import RunState
from .engine import weighted_buffers

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
    hybrid of models ``i`` and ``j`` alone (6 decimals; 1 on the diagonal)."""

    models: tuple[str, ...]
    table: tuple[tuple[float, ...], ...]
    meaning: str = PAIRWISE_MEANING


@dataclass(frozen=True)
class Versions(Record):
    """The versions the run was made with."""

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
    (:class:`torchcf.abc.smc.Budget`): particles per model."""

    prior_draws: int
    proposals_per_pair_and_round: int
    rounds: int
    proposals: int
    unspent: int


@dataclass(frozen=True)
class SMCResult(Record):
    """The refinement's settings (``abc.smc``, as :class:`~torchcf.abc.smc.
    SMCSettings` fields), budget and evidence shares (model -> share in [0, 1],
    with the prior's Occam factor: :func:`torchcf.abc.smc.evidence_shares`)."""

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
    (:mod:`torchcf.train.refinement`).

    Attributes:
        share_before, share_after: the model's share of the hybrid on the
            amortised samples alone, and after the refinement.
        median_best_before, median_best_after: the median over the training
            pairs of the pair's best score of the model (the run's distance;
            None where no pair has one).
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
    "amortised"``, :mod:`torchcf.train.amortised`).

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
            (:meth:`torchcf.traffic.Plausibility.summary`); with
            ``plausibility.report`` only.
        dt: the data's time step [s]; leader_length: its leader length [m]
            (the training pairs'; None in summaries written before they were
            recorded).
        extra: keys of the file this release does not know, kept in order after
            the known ones (none in the summaries it writes).
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


# --------------------------------------------------------------------------------------
# Building the summary


def dataset_label(data: DataConfig) -> str:
    """The data set's name, folder, or raw source ("SOURCE (FORMAT)")."""
    if data.raw is not None:
        return f"{data.raw.source} ({data.raw.format})"
    return data.name if data.name is not None else str(data.path)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def model_result(
    buffer: TopN, progress: ModelProgress, top_n: int, cells: int
) -> ModelResult:
    """One model's record, from its buffer (``(N, B)`` scores) and progress;
    ``cells``: cells per particle (1 paired, the pairs in the full layout)."""
    nth = buffer.first(top_n)[0][:, -1]  # (N,) N-th best score per pair
    finite = nth[torch.isfinite(nth)]
    return ModelResult(
        particles=progress.next,
        invalid=progress.invalid,
        invalid_rate=progress.invalid / max(progress.next * cells, 1),
        implausible=progress.implausible,
        seconds=round(progress.seconds, 3),
        particles_per_s=progress.next / max(progress.seconds, 1e-9),
        best_score=_finite_or_none(float(buffer.score[:, 0].min())),
        threshold=_finite_or_none(float(finite.mean())) if finite.numel() else None,
        threshold_max=_finite_or_none(float(nth.max())),
        thresholds=tuple(_finite_or_none(float(v)) for v in nth),
        pairs_short_of_n=int((~torch.isfinite(nth)).sum()),
        stopped=progress.stopped,
    )


@dataclass(frozen=True, eq=False)
class SelectionResults:
    """What the hybrid's selection read from the run's buffers
    (:func:`read_results`).

    Attributes:
        posterior: the hybrid.
        table: ``(M, M)`` the pairwise table (:func:`torchcf.abc.hybrid.
            pairwise_table`).
        sensitivity: N -> the shares of the top-N of that N.
        smc: the refinement's record (``abc.method = "smc"``), else None.
    """

    posterior: Posterior
    table: torch.Tensor
    sensitivity: Mapping[int, dict[str, float]]
    smc: SMCResult | None = None


def summarize(
    cfg: TrainConfig,
    train: PairSet,
    test: PairSet | None,
    state: RunState,
    selected: SelectionResults,
    wall: float,
    processes: int = 1,
) -> RunSummary:
    """The run's summary.

    Args:
        cfg: the run's config.
        train: the training pairs.
        test: the test pairs (None: the data have no test split, ``n_test``
            is 0).
        state: the run state after the streams (buffers and progress).
        selected: the hybrid, the pairwise table, the shares at other N and
            the refinement's record.
        wall: this process's wall time so far (s).
        processes: the run's processes.
    """
    posterior, table = selected.posterior, selected.table
    names = list(posterior.models)
    cells = 1 if cfg.abc.layout == "paired" else train.n_pairs
    return RunSummary(
        dataset=dataset_label(cfg.data),
        layout=cfg.abc.layout,
        selection=cfg.abc.selection,
        top_n=cfg.abc.top_n,
        n_particles=cfg.abc.n_particles,
        n_train=train.n_pairs,
        n_test=0 if test is None else test.n_pairs,
        train_pair_ids=tuple(int(i) for i in train.pair_ids),
        test_pair_ids=() if test is None else tuple(int(i) for i in test.pair_ids),
        models=tuple(names),
        shares=dict(posterior.shares),
        hybrid_size=sum(len(p) for p in posterior.hybrid.values()),
        pairwise=Pairwise(
            models=tuple(names),
            table=tuple(tuple(round(float(v), 6) for v in row) for row in table),
        ),
        sensitivity=dict(selected.sensitivity),
        per_model={
            name: model_result(
                state.buffers[name], state.progress[name], cfg.abc.top_n, cells
            )
            for name in names
        },
        seconds_total=round(sum(p.seconds for p in state.progress.values()), 3),
        seconds_wall_this_process=round(wall, 3),
        processes=processes,
        config_hash=config_hash(cfg),
        versions=Versions.current(),
        method=cfg.abc.method,
        smc=selected.smc,
        dt=train.dt,
        leader_length=train.leader_length,
    )


def smc_result(
    cfg: TrainConfig, pairs: PairSet, state: RunState, selection: Selection
) -> SMCResult:
    """The refinement's settings, budget and the shares with the prior's Occam
    factor (:func:`torchcf.abc.smc.evidence_shares`)."""
    names = [spec.name for spec in cfg.models]
    settings = smc_settings(cfg)
    budget = smc_budget(cfg.abc.n_particles, pairs.n_pairs, settings)
    n = cfg.abc.top_n
    scores = torch.stack([state.buffers[m].first(n)[0] for m in names])  # (M, N, n)
    member = torch.where(selection.member, scores, -math.inf)
    tau = member.amax(dim=(0, 2))  # (N,) the hybrid's worst member per pair
    masses = []
    for spec in cfg.models:
        proposals = proposals_per_pair(
            spec.model, spec.bounds(torch.float64), cfg.abc.seed, budget
        )
        masses.append(prior_mass(state.buffers[spec.name], proposals, tau))
    return SMCResult(
        settings=dict(settings.__dict__),
        budget=SMCBudgetResult(
            prior_draws=budget.prior,
            proposals_per_pair_and_round=budget.per_pair,
            rounds=budget.rounds,
            proposals=budget.total,
            unspent=cfg.abc.n_particles - budget.total,
        ),
        evidence_shares=evidence_shares(names, masses),
    )


def read_results(
    cfg: TrainConfig,
    train_pairs: PairSet,
    test_pairs: PairSet | None,
    state: RunState,
    wall: float,
    processes: int = 1,
) -> tuple[Posterior, RunSummary]:
    """The hybrid (posterior) and the summary, read from the buffers.

    Args:
        cfg: the run's config.
        train_pairs: the run's training pairs.
        test_pairs: its test pairs (None: no test split).
        state: the run state after the streams.
        wall: this process's wall time so far (s).
        processes: the run's processes.
    """
    names = [spec.name for spec in cfg.models]
    buffers = [state.buffers[name] for name in names]
    if weighted_buffers(cfg) is not None:  # the hybrid reads the parameters alone
        buffers = [parameter_buffer(b) for b in buffers]
    kwargs = {"mode": cfg.abc.selection, "global_size": cfg.abc.global_size}
    selection = select(buffers, names, cfg.abc.top_n, **kwargs)
    table = pairwise_table(buffers, names, cfg.abc.top_n, **kwargs)
    sensitivity = {
        n: select(buffers, names, n, **kwargs).shares()
        for n in sorted(set(cfg.abc.sensitivity_n))
    }
    posterior = hybrid_posterior(
        buffers,
        [spec.model for spec in cfg.models],
        selection,
        cfg.abc.top_n,
        torch.as_tensor(train_pairs.pair_ids, dtype=torch.int64),
        dataset=dataset_label(cfg.data),
        mode=cfg.abc.selection,
    )
    smc = None
    if cfg.abc.method == "smc":
        smc = smc_result(cfg, train_pairs, state, selection)
    selected = SelectionResults(posterior, table, sensitivity, smc)
    summary = summarize(cfg, train_pairs, test_pairs, state, selected, wall, processes)
    return posterior, summary


__all__ = [
    "AmortisedResult",
    "ModelResult",
    "Pairwise",
    "RefinedModel",
    "RefinementResult",
    "RunSummary",
    "SMCBudgetResult",
    "SMCResult",
    "SelectionResults",
    "Versions",
    "dataset_label",
    "model_result",
    "read_results",
    "smc_result",
    "summarize",
]
