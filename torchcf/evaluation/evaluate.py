"""Test-split evaluation of a trained run: ``torchcf evaluate RUN_DIR``.

SPEC section 6. Every particle of a learned set is simulated on every test pair
(full layout), giving the cost matrix ``C`` (particles x test pairs) of scores and
the matching ``e_p, e_v, e_a``; :func:`torchcf.evaluation.metrics.evaluate_cost_sets`
turns them into the average errors, the minimum distance, the beta-WS, the WS and
Sinkhorn (every set's Sinkhorn in one batched solve, capped at
``eval.sinkhorn_max_iter`` iterations; ``metrics.json`` records per set its
``sinkhorn_iterations``, ``sinkhorn_converged`` and ``sinkhorn_marginal_error``).
Simulating the sets, their metrics and the report's figures each show a progress
bar on stderr (``progress=False``: none).

Learned sets evaluated: ``"hybrid"`` (``Theta_hybrid`` of ``posterior.pt``) and every
single model, represented by its own N best particles per training pair (the model
learned alone, as in the paper's comparison).

Uncertainty (:mod:`torchcf.evaluation.uncertainty`, its docstring lists the
keys): the same rollouts also give each set's predictive coverage of the
observed spacing and speed (:mod:`torchcf.evaluation.coverage`; the
trajectories are reduced model by model, never all kept), and the cost matrices
a percentile bootstrap over test pairs of the minimum distance, 0.15-WS and WS,
with the paired differences hybrid minus each model
(:mod:`torchcf.evaluation.bootstrap`; ``eval.bootstrap``,
``eval.bootstrap_transport``, ``eval.level``, ``eval.seed``), next to the
hybrid's shares with their interval over training pairs.

Writes a report folder (default ``RUN_DIR/report``): ``table.md`` (the paper's
Appendix Tables 4-6, then the intervals, the differences, the shares and the
coverage), ``calibration.png`` (nominal against observed coverage),
``shares.png`` (Fig. 3a-c), ``pairwise.png`` (Fig. 3d-f),
``error_evolution.png`` (Fig. 4: position error of the best 5 % of the hybrid's
particles against all of them on one test pair) and ``radar.png`` (Figs. 5-6); the
figures and metrics are also logged to the run's TensorBoard folder; and last
``RUN_DIR/metrics.json``, so that a run directory with ``metrics.json`` holds a
complete evaluation (the layout: :mod:`torchcf.runs.directory`).
:mod:`torchcf.study.pipeline` calls :func:`evaluate_run` after training.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter
from typing import TypedDict

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..config import TrainConfig, load_split
from ..data import PairSet
from ..models import CFModel, get_model, require_model
from ..posterior import Posterior
from ..runs.directory import RunDir
from ..runs.metrics import Evaluation, SetEvaluation, SetMetrics
from ..runs.summary import RunSummary
from ..runs.tensorboard import RunLogger
from ..sim.rollout import Execution, simulate
from ..system.console import bar_interval
from ..system.errors import TorchcfError
from ..system.files import atomic_write_text, ensure_directory, writing
from .coverage import (
    PredictiveCDF,
    add_draws,
    observed,
    predicted,
    scored_steps,
)
from .entropic import limit_threads
from .metrics import evaluate_cost_sets
from .plots import (
    calibration_figure,
    error_evolution_figure,
    figure_to_array,
    pairwise_figure,
    radar_figure,
    save_image,
    shares_figure,
)
from .report import (
    METRIC_NOTES,
    coverage_table,
    differences_table,
    intervals_table,
    metrics_table,
    plausibility_table,
    shares_interval_table,
)
from .uncertainty import tensorboard_scalars, uncertainty

#: Bytes of trajectories one rollout may hold for the predictive coverage
#: (:func:`cost_matrices` slices the particles to stay below).
TRAJECTORY_BYTES = 2**28


class RolloutOptions(TypedDict):
    """The run's rollout settings :func:`cost_matrices` takes as keywords."""

    dtype: torch.dtype
    device: torch.device | str
    weights: Sequence[float]


@dataclass(frozen=True)
class EvaluationSettings:
    """How a learned set is evaluated: its rollouts and its metrics.

    Attributes:
        dtype: the rollouts' precision.
        device: where they run.
        weights: score weights of (position, speed, acceleration).
        beta: the beta of beta-WS.
        sinkhorn_reg: the entropic regularisation of the Sinkhorn solve.
        sinkhorn_max_iter: its iteration cap.

    Examples:
        >>> EvaluationSettings(beta=0.15).rollout["dtype"]
        torch.float32
    """

    dtype: torch.dtype = torch.float32
    device: str = "cpu"
    weights: tuple[float, float, float] = (0.5, 0.3, 0.2)
    beta: float = 0.15
    sinkhorn_reg: float = 0.05
    sinkhorn_max_iter: int = 10_000

    @classmethod
    def of(cls, cfg: TrainConfig) -> EvaluationSettings:
        """The settings of a run config (``dtype``, ``device``,
        ``abc.weights``, ``eval``)."""
        return cls(
            dtype=getattr(torch, cfg.dtype),
            device=cfg.device,
            weights=tuple(cfg.abc.weights),
            beta=cfg.eval.beta,
            sinkhorn_reg=cfg.eval.sinkhorn_reg,
            sinkhorn_max_iter=cfg.eval.sinkhorn_max_iter,
        )

    @property
    def rollout(self) -> RolloutOptions:
        """The keywords :func:`cost_matrices` takes."""
        return RolloutOptions(
            dtype=self.dtype, device=self.device, weights=self.weights
        )


class EvaluationError(TorchcfError, RuntimeError):
    """A run directory that cannot be evaluated (one-line message)."""


def single_model_particles(posterior: Posterior, name: str) -> Tensor:
    """A model learned alone: its N best particles on every training pair.

    Returns:
        (n, K) float64, the finite-score entries of the first N buffer slots.
    """
    buffer = posterior.buffers[name]
    n = posterior.top_n
    score = buffer["score"][:, :n].reshape(-1)
    theta = buffer["theta"][:, :n].reshape(-1, buffer["theta"].shape[-1])
    return theta[torch.isfinite(score)]


def hybrid_rows_in_single(posterior: Posterior, name: str) -> np.ndarray:
    """Where each of the model's hybrid particles sits among its single-model
    particles (:func:`single_model_particles`), or -1.

    A particle kept by the hybrid for a training pair is among its own model's N
    best on that pair (per-pair selection), so its cost rows on the test pairs are
    already simulated there; a global selection can keep one that is not (-1).
    Particles are matched by (training pair, stream index), which names one
    particle of one model.

    Returns:
        (h,) int64, row in the single model's (n, ...) arrays, or -1.
    """
    buffer = posterior.buffers[name]
    n = posterior.top_n
    pair_ids = posterior.train_pair_ids.tolist()
    score = buffer["score"][:, :n]
    index = buffer["index"][:, :n]
    finite = torch.isfinite(score)
    keys = [
        (pair_ids[row], int(index[row, slot]))
        for row, slot in finite.nonzero().tolist()
    ]  # row-major, the order of single_model_particles
    row_of = {key: i for i, key in enumerate(keys)}
    hybrid = posterior.hybrid[name]
    return np.array(
        [
            row_of.get((int(pair), int(j)), -1)
            for pair, j in zip(
                hybrid.pair_ids.tolist(), hybrid.particle_index.tolist(), strict=True
            )
        ],
        dtype=np.int64,
    )


def cost_matrices(
    model: CFModel,
    theta: Tensor,
    test: PairSet,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    weights: Sequence[float] = (0.5, 0.3, 0.2),
    predictive: Sequence[tuple[PredictiveCDF, np.ndarray | None]] = (),
) -> dict[str, np.ndarray]:
    """Score, e_p, e_v, e_a of every particle on every test pair: (P, n_test) each.

    ``model`` is the model object (``torchcf.get_model(name)``); ``theta``
    ``(P, K)`` its particles.

    With ``predictive``, the same rollout's spacing and speed also feed each
    ``(cdf, weights)``: ``weights`` (P,) per particle, None: 1 each. The
    trajectories live for one rollout only; where all of them would pass
    :data:`TRAJECTORY_BYTES`, the particles are simulated in slices that stay
    below it (a rollout is particle by particle, so the costs are the same).

    Runs on one torch thread when ``P * n_test`` is small (:func:`limit_threads`):
    every step of the rollout is a handful of ops on ``P * n_test`` numbers, too
    few for threads to pay, and on a loaded machine each parallel op waits for a
    descheduled thread (on the smoke run's sets, two threads under load took
    over ten times as long as one).
    """
    model = require_model(model, "cost_matrices")
    n_particles = theta.shape[0]
    # x, v, a of the rollout, then spacing and the coverage's copies: about 6
    # (T, P, N) arrays of the run's dtype per particle
    per_particle = 6 * test.n_steps * test.n_pairs * dtype.itemsize
    step = max(1, TRAJECTORY_BYTES // per_particle) if predictive else n_particles
    parts = []
    with limit_threads(n_particles * test.n_pairs):
        for start in range(0, max(n_particles, 1), max(step, 1)):
            stop = min(start + step, n_particles)
            out = simulate(
                model,
                theta[start:stop].to(dtype),
                test,
                dtype=dtype,
                return_traj=bool(predictive),
                weights=weights,
                execution=Execution(device=device),
            )
            if predictive:
                draws = predicted(test.x_lead.to(out.x), out.x, out.v)  # (T, P, N)
                feeds = [
                    (cdf, None if w is None else np.asarray(w)[start:stop])
                    for cdf, w in predictive
                ]
                add_draws(feeds, draws, out.valid)
                del draws  # the slice's trajectories go before the next slice's
                out = out._replace(x=None, v=None, a=None)
            parts.append(
                {
                    key: getattr(out, key).double().cpu().numpy()
                    for key in ("score", "e_p", "e_v", "e_a")
                }
            )
    return parts[0] if len(parts) == 1 else _stack(parts)


def _hybrid_costs(
    model: CFModel,
    theta: Tensor,
    rows: np.ndarray,
    single: dict[str, np.ndarray] | None,
    test: PairSet,
    kwargs: RolloutOptions,
    predictive: PredictiveCDF | None = None,
) -> dict[str, np.ndarray]:
    """The (h, n_test) cost matrices of a model's hybrid particles ``theta``:
    the single model's rows (``single``, its cost matrices; None where it has
    no particle) where :func:`hybrid_rows_in_single` found them (the same
    particle on the same pairs, no second rollout), a rollout for the rest
    (whose trajectories also feed the hybrid's ``predictive`` CDF; the found
    rows fed it with the single model's rollout)."""
    found = rows >= 0
    if found.all():
        return {key: value[rows] for key, value in single.items()}
    fresh = cost_matrices(
        model,
        theta[torch.from_numpy(~found)],
        test,
        **kwargs,
        predictive=() if predictive is None else [(predictive, None)],
    )
    out = {key: np.empty((len(rows), test.n_pairs)) for key in fresh}
    for key, value in out.items():
        value[~found] = fresh[key]
        if found.any():
            value[found] = single[key][rows[found]]
    return out


def _stack(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def _bar(total: int, desc: str, unit: str, progress: bool) -> tqdm:
    """A progress bar on stderr in the trainer's style (a live bar in a terminal,
    a line every 30 s in a log file); ``progress=False``: silent."""
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        dynamic_ncols=True,
        file=sys.stderr,
        mininterval=bar_interval(),
        disable=not progress,
    )


def evaluate_posterior(
    posterior: Posterior,
    test: PairSet,
    settings: EvaluationSettings,
    *,
    progress: bool = True,
    predictive: dict[str, PredictiveCDF] | None = None,
) -> tuple[dict[str, SetMetrics], dict[str, dict[str, np.ndarray]]]:
    """Metrics of the hybrid and of every single model on ``test``.

    Two stages, each with a progress bar: simulating every set's particles on
    every test pair (the bar counts particles), then the metrics of all sets,
    their Sinkhorn solved together (:func:`simulated_metrics`).

    Args:
        posterior: the learned set.
        test: the test pairs.
        settings: the rollouts' and the metrics' settings.
        progress: show the progress bars (stderr).
        predictive: filled with each set's :class:`PredictiveCDF` at the
            observed spacing and speed (:mod:`torchcf.evaluation.coverage`),
            from the same rollouts (the hybrid: every particle once, i.e. drawn
            by its hybrid weight); None: no trajectories are kept.

    Returns:
        metrics: ``{"hybrid" | model: evaluate_costs(...)}``;
        costs: the cost matrices of each entry (hybrid rows in model order).

    Raises:
        EvaluationError: the hybrid particle set is empty.
    """
    kwargs = settings.rollout
    models = {name: get_model(name) for name in posterior.models}  # names enter
    singles = {
        name: single_model_particles(posterior, name) for name in posterior.models
    }
    hybrid = {name: posterior.hybrid[name].theta for name in posterior.models}
    if not any(len(theta) for theta in hybrid.values()):
        raise EvaluationError("the hybrid particle set is empty")
    rows = {name: hybrid_rows_in_single(posterior, name) for name in posterior.models}
    missing = {name: np.flatnonzero(rows[name] < 0) for name in posterior.models}
    total = sum(len(t) for t in singles.values()) + sum(map(len, missing.values()))
    costs: dict[str, dict[str, np.ndarray]] = {}
    hybrid_parts = []
    if predictive is not None:
        targets = observed(test.x_lead, test.x_follow, test.v_follow)
        steps = scored_steps(test.mask)
        for name in [*posterior.models, "hybrid"]:
            predictive[name] = PredictiveCDF(targets, steps)
    with _bar(total, "evaluate: simulate", "particle", progress) as bar:
        for name in posterior.models:
            bar.set_postfix_str(name, refresh=False)
            if len(singles[name]):
                feeds = []
                if predictive is not None:
                    found = rows[name][rows[name] >= 0]
                    feeds = [(predictive[name], None)]
                    if len(found):  # the hybrid's particles among these rows
                        feeds.append(
                            (
                                predictive["hybrid"],
                                np.bincount(found, minlength=len(singles[name])),
                            )
                        )
                costs[name] = cost_matrices(
                    models[name], singles[name], test, **kwargs, predictive=feeds
                )
                bar.update(len(singles[name]))
            if len(hybrid[name]):
                hybrid_parts.append(
                    _hybrid_costs(
                        models[name],
                        hybrid[name],
                        rows[name],
                        costs.get(name),
                        test,
                        kwargs,
                        None if predictive is None else predictive["hybrid"],
                    )
                )
                bar.update(len(missing[name]))
    costs["hybrid"] = _stack(hybrid_parts)
    return simulated_metrics(costs, settings, progress=progress), costs


def simulated_metrics(
    costs: dict[str, dict[str, np.ndarray]],
    settings: EvaluationSettings,
    *,
    progress: bool = True,
) -> dict[str, SetMetrics]:
    """:func:`~torchcf.evaluation.metrics.evaluate_costs` of every set, with
    ``settings``' beta, Sinkhorn regularisation and iteration cap; all sets'
    Sinkhorn problems are solved in one batched call (they share ``reg``).

    One particle invalid on every test pair makes WS and beta-WS (beta > 0)
    infinite (its mandatory mass has nowhere to go), which is reported as such,
    next to both over the other particles (``ws_valid``, ``beta_ws_valid``) and
    their count (``particles_never_valid``).

    Args:
        costs: per set, its (P_s, n_test) ``score, e_p, e_v, e_a``.
        settings: the metrics' beta and Sinkhorn settings.
        progress: a bar over the sets' exact metrics, then their Sinkhorn.

    Returns:
        ``{set: evaluate_costs(...)}`` in the order of ``costs``.
    """
    names = list(costs)
    with _bar(2 * len(names), "evaluate: metrics", "step", progress) as bar:

        def advance(stage: str, count: int, done: int) -> None:
            # "exact": sets done; "sinkhorn": iterations so far, problems done
            if stage == "exact":
                bar.update(done - bar.n)
            else:
                bar.set_postfix_str(f"sinkhorn iteration {count}", refresh=False)
                bar.update(len(names) + done - bar.n)

        results = evaluate_cost_sets(
            [tuple(costs[n][k] for k in ("score", "e_p", "e_v", "e_a")) for n in names],
            beta=settings.beta,
            sinkhorn_reg=settings.sinkhorn_reg,
            sinkhorn_max_iter=settings.sinkhorn_max_iter,
            callback=advance,
        )
        bar.update(2 * len(names) - bar.n)
    return dict(zip(names, results, strict=True))


def position_errors(
    posterior: Posterior, test: PairSet, pair: int, settings: EvaluationSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fig. 4 data: simulated minus observed follower position of every hybrid
    particle on test pair ``pair``.

    Returns:
        time (T,) [s]; errors (P, T) [m], NaN past the pair's valid steps and for
        invalid rollouts; scores (P,).
    """
    one = test.subset([pair])
    dtype = settings.dtype
    errors, scores = [], []
    for name in posterior.models:
        theta = posterior.hybrid[name].theta
        if not theta.shape[0]:
            continue
        with limit_threads(theta.shape[0]):  # one pair: see cost_matrices
            out = simulate(
                get_model(name),  # the posterior's name enters here
                theta.to(dtype),
                one,
                dtype=dtype,
                return_traj=True,
                weights=settings.weights,
                execution=Execution(device=settings.device),
            )
        x = out.x[:, :, 0].double().cpu()  # (T, P)
        err = (x - one.x_follow[:, :1]).T.numpy()  # (P, T)
        err[:, ~one.mask[:, 0].numpy()] = np.nan
        err[~out.valid[:, 0].cpu().numpy()] = np.nan
        errors.append(err)
        scores.append(out.score[:, 0].double().cpu().numpy())
    time = np.arange(one.n_steps) * one.dt
    return time, np.concatenate(errors), np.concatenate(scores)


def evaluate_run(
    run_dir: str | Path | RunDir,
    *,
    report_dir: str | Path | None = None,
    pairs: tuple[PairSet, PairSet] | None = None,
    figure_pair: int | None = None,
    tensorboard: bool = True,
    progress: bool = True,
) -> Evaluation:
    """Evaluate the finished run in ``run_dir``; write metrics.json and the report.

    Args:
        run_dir: a trainer output directory (:class:`~torchcf.runs.directory.RunDir`).
        report_dir: where the report goes (default ``run_dir/report``).
        pairs: optional ``(train, test)`` instead of loading the run's data config.
        figure_pair: the test pair (position) of the Fig. 4 figure; default the one
            whose best hybrid particle is closest to the median over pairs.
        tensorboard: also log to ``run_dir/tb``.
        progress: show progress bars on stderr (simulation, metrics, report).

    Returns:
        The evaluation (its ``to_json`` is ``run_dir/metrics.json``, written
        last: a run directory with ``metrics.json`` holds its whole report).

    Raises:
        RunFileError: an unfinished or corrupted run, or an output that cannot be
            written (a full disk, a directory without permission).
        ConfigError, DataError: the run's config is invalid, or its data cannot
            be loaded.
        EvaluationError: the hybrid particle set is empty.
    """
    run = RunDir(run_dir)
    # No training or loop writes into the run meanwhile; a missing directory
    # fails in load_run with its one line, with nothing to lock.
    with run.locked() if run.path.is_dir() else nullcontext():
        return _evaluate_held(
            run, report_dir, pairs, figure_pair, tensorboard, progress
        )


def _evaluate_held(
    run: RunDir,
    report_dir: str | Path | None,
    pairs: tuple[PairSet, PairSet] | None,
    figure_pair: int | None,
    tensorboard: bool,
    progress: bool,
) -> Evaluation:
    """:func:`evaluate_run` with the run directory held."""
    started = perf_counter()
    cfg, posterior, summary = run.load_run()
    report = Path(report_dir) if report_dir is not None else run.report_dir
    # The outputs' folders must take files before the data are loaded: fail fast
    # (and leave no empty report folder if the data then fail).
    run.probe()
    ensure_directory(report, "report directory", keep=False)
    test = load_split(cfg.data)[1] if pairs is None else pairs[1]
    if figure_pair is not None and not 0 <= figure_pair < test.n_pairs:
        raise EvaluationError(
            f"--pair {figure_pair}: the test split has {test.n_pairs} pairs "
            f"(positions 0-{test.n_pairs - 1})"
        )
    # A stale metrics.json of an earlier evaluation must not outlive a failure of
    # this one and pass for its result.
    run.discard_metrics()
    predictive: dict[str, PredictiveCDF] = {}
    settings = EvaluationSettings.of(cfg)
    metrics, costs = evaluate_posterior(
        posterior, test, settings, progress=progress, predictive=predictive
    )
    entries = [*[m for m in posterior.models if m in metrics], "hybrid"]
    seed = cfg.abc.seed if cfg.eval.seed is None else cfg.eval.seed
    honest = uncertainty(costs, metrics, predictive, posterior, cfg.eval, seed)
    sets = {
        entry: SetEvaluation(metrics[entry], honest.per_set[entry]) for entry in entries
    }
    # each set's metrics.json keys, the rows of the report's tables and figures
    rows = {entry: sets[entry].to_json() for entry in entries}
    best = costs["hybrid"]["score"].min(axis=0)  # (n_test,) the hybrid's per pair
    # a re-calibration's summary records no battery
    plausibility = (
        summary.plausibility if isinstance(summary, RunSummary) else None
    ) or {}

    ensure_directory(report, "report directory")
    atomic_write_text(
        report / "table.md",
        f"# {summary.dataset}: test-split evaluation\n\n"
        f"{test.n_pairs} test pairs; single models: each model's own "
        f"{posterior.top_n} best particles per training pair; hybrid: "
        f"{sum(len(p) for p in posterior.hybrid.values())} particles.\n\n"
        + metrics_table(rows, entries)
        + f"\n{METRIC_NOTES}\n"
        + "\n## Uncertainty\n\n"
        + intervals_table(rows, entries, honest.bootstrap)
        + "\n"
        + differences_table(honest.hybrid_minus)
        + "\n"
        + shares_interval_table(honest.shares, cfg.eval.level)
        + "\n## Predictive coverage\n\n"
        + coverage_table(rows, entries, cfg.eval.coverage_levels)
        + "\nCalibration curves: `calibration.png`.\n\n"
        + plausibility_table(plausibility)
        + "\nThe calibrated parameters per model: `parameters.md` (one row per "
        "particle: `parameters.csv`).\n",
    )
    if figure_pair is None:
        finite = np.where(np.isfinite(best), best, np.inf)
        figure_pair = int(
            np.argmin(np.abs(finite - np.median(best[np.isfinite(best)])))
        )
    time, errors, scores = position_errors(posterior, test, figure_pair, settings)
    pair_id = int(test.pair_ids[figure_pair])
    figures = {
        "error_evolution": error_evolution_figure(
            time,
            errors,
            scores,
            title=f"Hybrid, test pair {pair_id}: position error",
        ),
        "radar": radar_figure(rows),
        "calibration": calibration_figure(
            {entry: rows[entry]["coverage_curve"] for entry in entries}
        ),
    }
    # Training wrote the shares and pairwise PNGs into its report folder; another
    # folder (or a run trained before it did) gets them drawn here.
    trained = ("shares", "pairwise")
    in_run = report.resolve() == run.report_dir.resolve()
    if not (in_run and all((report / f"{n}.png").is_file() for n in trained)):
        figures["shares"] = shares_figure(posterior.shares)
        figures["pairwise"] = pairwise_figure(
            summary.pairwise.models, summary.pairwise.table
        )
    # Each figure is drawn once (the draw is most of its cost), for its PNG and
    # TensorBoard (where training already put the shares and pairwise figures).
    with _bar(
        len(figures) + tensorboard, "evaluate: report", "figure", progress
    ) as bar:
        images = {}
        for name, figure in figures.items():
            images[name] = figure_to_array(figure)
            path = report / f"{name}.png"
            with writing(path):
                save_image(images[name], path)
            bar.update()
        if tensorboard:
            with (
                writing(run.tb_dir),
                RunLogger(run.tb_dir, stream="evaluation") as logger,
            ):
                logger.evaluation(
                    {k: images[k] for k in ("error_evolution", "radar", "calibration")},
                    rows,
                )
                logger.evaluation({}, tensorboard_scalars(honest))
            bar.update()
    result = Evaluation(
        dataset=summary.dataset,
        n_test=test.n_pairs,
        test_pair_ids=tuple(int(i) for i in test.pair_ids),
        beta=cfg.eval.beta,
        sinkhorn_reg=cfg.eval.sinkhorn_reg,
        sinkhorn_max_iter=cfg.eval.sinkhorn_max_iter,
        bootstrap=honest.bootstrap,
        coverage_levels=tuple(cfg.eval.coverage_levels),
        sets=sets,
        hybrid_minus=honest.hybrid_minus,
        shares=honest.shares,
        hybrid_min_by_pair=_by_pair(best),
        # the evaluation's own wall time (loading its data included), beside the
        # training's per-model seconds in summary.json
        seconds=round(perf_counter() - started, 3),
    )
    run.write_metrics(result)
    return result


def _by_pair(best: np.ndarray) -> tuple[float | None, ...]:
    """Per test pair, the hybrid's minimum distance (the best score of its
    particles on that pair; None where none is valid), for paired comparisons
    of two runs on the same test pairs (:mod:`torchcf.diagnose.loop`)."""
    return tuple(float(v) if math.isfinite(v) else None for v in best.tolist())
