"""Predict pairs from a trained run: :func:`predict`.

Three predictions of every pair (any length: whole couples), each answering
its own question:

- **the population model** (:mod:`torchcf.predict.population`): one vector per
  model for every driver, as published pooled calibrations give; the model of
  the lowest training objective predicts;
- **the hybrid's median and bands** (:mod:`torchcf.predict.bands`): the run's
  distribution over drivers, for a driver it never saw;
- **conditioned on a history** (:mod:`torchcf.predict.history`): the driver's
  own posterior from the first ``history`` seconds of its pair, predicting the
  rest; beside it the population model restarted at the same step from the
  recorded state, so that the two differ by the parameters only.

Every prediction starts from the pair's recorded follower state and follows its
recorded leader (SPEC section 2), and is scored as the field scores
calibrations (:mod:`torchcf.predict.scores`).

Shapes: T steps, N pairs, D draws (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..data import PairSet
from ..models import get_model
from ..system.records import Record
from .bands import Bands, predictive_bands
from .conditioning import CONDITIONINGS, designs, judged, rest_scores
from .history import history_steps, predictable
from .population import OBJECTIVES, PooledFit, pooled_fits, population_model
from .rollouts import Particles, follow, steps_between
from .scores import SpacingRMSE, coverage, displacement, summarize_rmse
from .trained import PredictError, TrainedRun

#: The most posterior draws per pair (memory: T x N x D trajectories).
MAX_DRAWS = 10_000


@dataclass(frozen=True)
class PredictSettings:
    """How :func:`predict` predicts.

    Attributes:
        draws: posterior draws per pair for the median and the bands.
        history: seconds of each pair that condition the driver's own
            posterior (None: no conditioned prediction).
        keep: particles of a driver's own posterior.
        refine: rounds of the per-pair search after the rejection (0: none;
            :mod:`torchcf.predict.history`).
        conditioning: how a history conditions: ``"auto"`` (the design best
            on the training pairs as if new), ``"rejection"`` or
            ``"shrinkage"`` (:mod:`torchcf.predict.conditioning`).
        objective: the population model's pooled objective, ``"spacing"``
            (mean spacing RMSE) or ``"score"`` (SPEC section 4's).
        seed: seeds every draw and search.

    Examples:
        >>> from torchcf.predict import PredictError, PredictSettings
        >>> settings = PredictSettings(draws=50, history=None)  # no history
        >>> settings.draws, settings.objective
        (50, 'spacing')
        >>> PredictSettings(conditioning="oracle")
        Traceback (most recent call last):
            ...
        torchcf.predict.trained.PredictError: conditioning must be one of auto, ...
    """

    draws: int = 200
    history: float | None = 10.0
    keep: int = 100
    refine: int = 0
    conditioning: str = "auto"
    objective: str = "spacing"
    seed: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.draws <= MAX_DRAWS:
            raise PredictError(f"draws must be 1-{MAX_DRAWS}, got {self.draws}")
        if self.history is not None and not 0 < self.history < 1e5:
            raise PredictError(f"history must be > 0 s, got {self.history}")
        if not 1 <= self.keep <= 1000:
            raise PredictError(f"keep must be 1-1000, got {self.keep}")
        if self.conditioning not in CONDITIONINGS:
            raise PredictError(
                f"conditioning must be one of {', '.join(CONDITIONINGS)}, got "
                f"{self.conditioning!r}"
            )
        if not 0 <= self.refine <= 100:
            raise PredictError(f"refine must be 0-100 rounds, got {self.refine}")
        if self.objective not in OBJECTIVES:
            raise PredictError(
                f"objective must be one of {', '.join(OBJECTIVES)}, got "
                f"{self.objective!r}"
            )


@dataclass(frozen=True)
class PopulationResult(Record):
    """The population model on the pairs.

    Attributes:
        chosen: the model whose pooled vector predicts (the lowest training
            objective).
        fits: every model's pooled vector.
        spacing_rmse: the chosen model's on the pairs, whole.
        by_model: every model's pooled vector's on the pairs, whole.

    Examples:
        What the record holds (:func:`predict`'s example makes one):

        >>> import dataclasses
        >>> [field.name for field in dataclasses.fields(PopulationResult)]
        ['chosen', 'fits', 'spacing_rmse', 'by_model']
    """

    chosen: str
    fits: list[PooledFit]
    spacing_rmse: SpacingRMSE
    by_model: dict[str, SpacingRMSE]


@dataclass(frozen=True)
class BandsResult(Record):
    """The hybrid's predictive median and bands on the pairs.

    Attributes:
        draws: per pair.
        median: the spacing RMSE of the per-step median.
        per_draw: the mean over pairs and draws of a draw's spacing RMSE (a
            draw is one driver of the hybrid, not a prediction of this one).
        min_ade, min_fde: the least ADE / FDE over a pair's draws [m], mean
            over pairs.
        coverage_50, coverage_90: the share of recorded steps within the 50 %
            and 90 % bands.
        collisions: the share of draws that collided.

    Examples:
        What the record holds (:func:`predict`'s example makes one):

        >>> import dataclasses
        >>> [field.name for field in dataclasses.fields(BandsResult)]
        ['draws', 'median', 'per_draw', 'min_ade', 'min_fde', 'coverage_50',
         'coverage_90', 'collisions']
    """

    draws: int
    median: SpacingRMSE
    per_draw: float | None
    min_ade: float | None
    min_fde: float | None
    coverage_50: float
    coverage_90: float
    collisions: float


@dataclass(frozen=True)
class HistoryResult(Record):
    """The driver's own posterior from a history, on the rest of its pair.

    Attributes:
        history: seconds of history.
        design: how the history conditions (``"rejection"`` or ``"shrinkage
            LAMBDA"``: :mod:`torchcf.predict.conditioning`).
        source: the rejection's candidates (``"hybrid"``, or ``"hybrid +
            amortised"`` for a run with an estimator), or the shrinkage's
            center.
        judged_on_train: per design judged, its mean rest spacing RMSE [m] on
            the training pairs as if new (None: not judged).
        pairs: pairs predicted; too_short: pairs with less than
            :data:`~torchcf.predict.history.MIN_REST` seconds after the history.
        conditioned: the spacing RMSE on the rest of the posterior's median.
        population: the population model's, restarted at the same step.
        change: ``conditioned.mean / population.mean - 1``.
        collisions: the share of a posterior's particles that collided on the
            rest.

    Examples:
        What the record holds (:func:`predict`'s example makes one):

        >>> import dataclasses
        >>> [field.name for field in dataclasses.fields(HistoryResult)]
        ['history', 'design', 'source', 'judged_on_train', 'pairs', 'too_short',
         'conditioned', 'population', 'change', 'collisions']
    """

    history: float
    design: str
    source: str
    judged_on_train: dict[str, float | None]
    pairs: int
    too_short: int
    conditioned: SpacingRMSE
    population: SpacingRMSE
    change: float | None
    collisions: float


@dataclass(frozen=True)
class PredictionSummary(Record):
    """What :func:`predict` found (``predict.json``).

    Examples:
        What the record holds (:func:`predict`'s example makes one):

        >>> import dataclasses
        >>> [field.name for field in dataclasses.fields(PredictionSummary)]
        ['run', 'data', 'pairs', 'seconds_of_data', 'dt', 'leader_length',
         'settings', 'population', 'bands', 'history', 'seconds']
    """

    run: str
    data: str
    pairs: int
    seconds_of_data: float
    dt: float
    leader_length: float
    settings: dict
    population: PopulationResult
    bands: BandsResult
    history: HistoryResult | None
    seconds: float


@dataclass(frozen=True, eq=False)
class Prediction:
    """:func:`predict`'s result: the summary and the per-step series.

    Attributes:
        summary: the scores (:class:`PredictionSummary`).
        pairs: the pairs predicted.
        population: ``(T, N)`` the population model's spacing [m].
        bands: the hybrid's median and bands.
        conditioned: ``(T, N)`` the conditioned median spacing [m], NaN up to
            the history's end and for pairs not predicted; None without a
            history.
        per_pair: per pair (in pair order), its scores.

    Examples:
        What the record holds (:func:`predict`'s example makes one):

        >>> import dataclasses
        >>> [field.name for field in dataclasses.fields(Prediction)]
        ['summary', 'pairs', 'population', 'bands', 'conditioned', 'per_pair']
    """

    summary: PredictionSummary
    pairs: PairSet
    population: Tensor
    bands: Bands
    conditioned: Tensor | None
    per_pair: dict[str, np.ndarray] = field(default_factory=dict)


def predict(
    run: TrainedRun,
    pairs: PairSet,
    settings: PredictSettings = PredictSettings(),
    *,
    data: str = "",
    progress: Callable[[str], None] | None = None,
) -> Prediction:
    """Predict every pair of ``pairs`` from the trained ``run`` (module
    docstring); ``progress`` hears each stage as it begins (one line each).

    Raises:
        PredictError: the pairs' time step or leader length is not the run's.

    Examples:
        >>> from pathlib import Path
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.config import TrainConfig
        >>> from torchcf.posterior import ModelParticles, Posterior
        >>> from torchcf.predict import PredictSettings, TrainedRun, predict
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm, truth = get_model("idm"), [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> pairs = synthetic_pairs(idm, truth, n_pairs=6, n_steps=200)  # 20 s each
        >>> train, test = pairs.subset([0, 1, 2, 3]), pairs.subset([4, 5])
        >>> low, high = idm.prior_bounds().unbind(1)
        >>> g = torch.Generator().manual_seed(0)
        >>> theta = low + (high - low) * torch.rand(8, 6, generator=g).double()
        >>> theta[0] = torch.tensor(truth)  # the hybrid holds the true driver
        >>> hybrid = {"idm": ModelParticles(
        ...     idm.param_names, theta, torch.zeros(8).double(),
        ...     pair_ids=torch.arange(8) % 4, particle_index=torch.arange(8),
        ... )}
        >>> posterior = Posterior(
        ...     "demo", "per_pair", 2, ("idm",), {"idm": 1.0}, torch.arange(4),
        ...     hybrid, buffers={},
        ... )
        >>> config = TrainConfig(data={"path": "demo"}, models=["idm"])
        >>> priors = {"idm": idm.prior_bounds()}
        >>> run = TrainedRun(Path("demo"), config, posterior, train, priors)
        >>> found = predict(run, test, PredictSettings(draws=10, history=None))
        >>> found.summary.population.chosen, found.bands.median.shape  # (T, N)
        ('idm', torch.Size([200, 2]))
        >>> found.conditioned is None
        True
    """
    run.check(pairs)
    began = time.perf_counter()
    pairs = pairs.to(dtype=torch.float64)
    observed_gap = _gap(pairs, pairs.x_follow.double().cpu())
    mask = pairs.mask.cpu()
    say = progress or (lambda _: None)
    say(
        f"the population model: {len(run.models)} models' pooled vectors on "
        f"{run.train.n_pairs} training pairs"
    )
    fits, by_model, (population_x, population_rmse) = _population(run, pairs, settings)
    chosen = population_model(fits)
    say(
        f"the hybrid's median and bands: {settings.draws} draws on each of "
        f"{pairs.n_pairs} pairs"
    )
    bands = predictive_bands(run, pairs, settings.draws, settings.seed)
    bands_result, draw_scores = _bands_result(bands, observed_gap, mask)
    history, conditioned, conditioned_rmse = None, None, None
    if settings.history is not None:
        say(
            f"after {settings.history:g} s of history: the designs judged on the "
            "training pairs, then each pair's own prediction"
        )
        history, conditioned, conditioned_rmse = _conditioned(
            run, pairs, fits, chosen, settings
        )
    per_pair = {
        "pair_id": np.array(pairs.pair_ids),
        "seconds": (pairs.lengths.cpu().numpy() - 1) * pairs.dt,
        "population_rmse": population_rmse,
        "median_rmse": draw_scores["median_rmse"],
        "min_ade": draw_scores["min_ade"],
        "min_fde": draw_scores["min_fde"],
        "collided_draws": bands.collided.numpy(),
    }
    if conditioned_rmse is not None:
        per_pair["conditioned_rmse"] = conditioned_rmse
    summary = PredictionSummary(
        run=str(run.path),
        data=data or pairs.name,
        pairs=pairs.n_pairs,
        seconds_of_data=float((pairs.lengths.cpu() - 1).sum()) * pairs.dt,
        dt=pairs.dt,
        leader_length=pairs.leader_length,
        settings={
            "draws": settings.draws,
            "history": settings.history,
            "keep": settings.keep,
            "refine": settings.refine,
            "conditioning": settings.conditioning,
            "objective": settings.objective,
            "seed": settings.seed,
        },
        population=PopulationResult(
            chosen=chosen.model,
            fits=fits,
            spacing_rmse=by_model[chosen.model],
            by_model=by_model,
        ),
        bands=bands_result,
        history=history,
        seconds=time.perf_counter() - began,
    )
    return Prediction(
        summary=summary,
        pairs=pairs,
        population=_gap(pairs, population_x),
        bands=bands,
        conditioned=conditioned,
        per_pair=per_pair,
    )


def _population(
    run: TrainedRun, pairs: PairSet, settings: PredictSettings
) -> tuple[list[PooledFit], dict[str, SpacingRMSE], tuple[Tensor, np.ndarray]]:
    """Every model's pooled vector, its spacing RMSE on ``pairs``, and the
    population model's ``(T, N)`` follower positions [m] with its ``(N,)``
    per-pair RMSE."""
    fits = pooled_fits(
        run.models,
        {m.name: run.kept(m) for m in run.models},
        run.priors,
        run.train,
        objective=settings.objective,
        seed=settings.seed,
    )
    observed = pairs.x_follow.double().cpu()
    by_model, paths = {}, {}
    for fit in fits:
        x = _one_vector(fit, pairs)
        by_model[fit.model], rmse = summarize_rmse(x - observed, pairs.mask.cpu())
        paths[fit.model] = (x, rmse)
    return fits, by_model, paths[population_model(fits).model]


def _gap(pairs: PairSet, x_follow: Tensor) -> Tensor:
    """``(T, N)`` the bumper-to-bumper gap [m] of followers at ``x_follow``
    (T, N) behind the pairs' leaders."""
    return pairs.x_lead.double().cpu() - x_follow - pairs.leader_length


def _one_vector(fit: PooledFit, pairs: PairSet) -> Tensor:
    """``(T, N)`` the follower's position [m] under one vector on every pair."""
    model = get_model(fit.model)
    theta = fit.theta().expand(pairs.n_pairs, -1)
    particles = Particles(
        (model,),
        torch.zeros(pairs.n_pairs, dtype=torch.int64),
        theta.clone(),
        torch.arange(pairs.n_pairs),
    )
    return follow(particles, pairs).x


def _bands_result(
    bands: Bands, observed_gap: Tensor, mask: Tensor
) -> tuple[BandsResult, dict[str, np.ndarray]]:
    median, median_rmse = summarize_rmse(observed_gap - bands.median, mask)
    q05, q25, _, q75, q95 = bands.quantiles
    ade, fde = displacement(bands.draw_error, mask)  # (N, D)
    per_draw = np.sqrt(
        np.where(mask.numpy()[:, :, None], bands.draw_error.numpy() ** 2, 0.0).sum(0)
        / np.maximum(mask.numpy().sum(0), 1)[:, None]
    )  # (N, D)
    finite = np.isfinite(per_draw)
    with warnings.catch_warnings():  # a pair whose every draw collided: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        min_ade = np.nanmin(np.where(np.isfinite(ade), ade, np.nan), axis=1)
        min_fde = np.nanmin(np.where(np.isfinite(fde), fde, np.nan), axis=1)
    result = BandsResult(
        draws=bands.draws,
        median=median,
        per_draw=float(per_draw[finite].mean()) if finite.any() else None,
        min_ade=_mean(min_ade),
        min_fde=_mean(min_fde),
        coverage_50=coverage(observed_gap, q25, q75, mask),
        coverage_90=coverage(observed_gap, q05, q95, mask),
        collisions=float(bands.collided.sum())
        / max(bands.collided.numel() * bands.draws, 1),
    )
    return result, {"median_rmse": median_rmse, "min_ade": min_ade, "min_fde": min_fde}


def _conditioned(
    run: TrainedRun,
    pairs: PairSet,
    fits: list[PooledFit],
    chosen: PooledFit,
    settings: PredictSettings,
) -> tuple[HistoryResult, Tensor, np.ndarray]:
    """The conditioned prediction of every pair long enough (its design judged
    on the training pairs: :mod:`torchcf.predict.conditioning`), and the
    population model restarted at the same step."""
    history = float(settings.history)
    usable = torch.nonzero(predictable(pairs, history)).squeeze(1)
    k = history_steps(pairs, history)
    conditioned = torch.full(
        (pairs.n_steps, pairs.n_pairs), float("nan"), dtype=torch.float64
    )
    rmse = np.full(pairs.n_pairs, np.nan)
    options = dict(keep=settings.keep, refine=settings.refine, seed=settings.seed)
    design, judged_on_train = judged(
        run, designs(settings.conditioning, fits), history, **options
    )
    source = "hybrid" if run.estimator is None else "hybrid + amortised"
    if design.center is not None:
        source = f"the pooled {design.center.model}"
    if not len(usable):
        empty = SpacingRMSE(None, None, None, 0, 0)
        result = HistoryResult(
            history, design.label, source, judged_on_train, 0, pairs.n_pairs,
            empty, empty, None, 0.0,
        )  # fmt: skip
        return result, conditioned, rmse
    some = pairs.subset(usable.tolist())
    posterior = design.posterior(run, some, history, **options)
    found, median, collided, found_rmse = rest_scores(posterior, some)
    rest = steps_between(some, k)
    population_x = _one_vector(chosen, rest)
    population, _ = summarize_rmse(
        population_x - rest.x_follow.double().cpu(), rest.mask.cpu()
    )
    conditioned[k : k + median.shape[0], usable] = median
    rmse[usable.numpy()] = found_rmse
    change = (
        found.mean / population.mean - 1
        if found.mean is not None and population.mean
        else None
    )
    result = HistoryResult(
        history=history,
        design=design.label,
        source=source,
        judged_on_train=judged_on_train,
        pairs=len(usable),
        too_short=pairs.n_pairs - len(usable),
        conditioned=found,
        population=population,
        change=change,
        collisions=float(collided.sum())
        / max(collided.numel() * posterior.score.shape[1], 1),
    )
    return result, conditioned, rmse


def _mean(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


__all__ = [
    "MAX_DRAWS",
    "BandsResult",
    "HistoryResult",
    "PopulationResult",
    "PredictSettings",
    "Prediction",
    "PredictionSummary",
    "predict",
]
