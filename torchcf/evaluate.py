"""Test-split evaluation of a trained run: ``python -m torchcf.evaluate RUN_DIR``.

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

Writes a report folder (default ``RUN_DIR/report``): ``table.md`` (the paper's
Appendix Tables 4-6), ``shares.png`` (Fig. 3a-c), ``pairwise.png`` (Fig. 3d-f),
``error_evolution.png`` (Fig. 4: position error of the best 5 % of the hybrid's
particles against all of them on one test pair) and ``radar.png`` (Figs. 5-6); the
figures and metrics are also logged to the run's TensorBoard folder; and last
``RUN_DIR/metrics.json``, so that a run directory with ``metrics.json`` holds a
complete evaluation (the layout: :mod:`torchcf.rundir`). :mod:`torchcf.pipeline`
calls :func:`evaluate_run` after training.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from .cli import DefaultsHelpFormatter, run_main
from .config import TrainConfig
from .data import PairSet, load_split
from .errors import TorchcfError
from .evaluation.entropic import limit_threads
from .evaluation.metrics import evaluate_cost_sets
from .evaluation.plots import (
    error_evolution_figure,
    figure_to_array,
    pairwise_figure,
    radar_figure,
    save_image,
    shares_figure,
)
from .evaluation.report import metrics_table, plausibility_table
from .files import atomic_write_text, ensure_directory, writing
from .posterior import Posterior
from .rundir import RunDir
from .sim import simulate
from .tblog import RunLogger


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
    model: str,
    theta: Tensor,
    test: PairSet,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    weights: Sequence[float] = (0.5, 0.3, 0.2),
) -> dict[str, np.ndarray]:
    """Score, e_p, e_v, e_a of every particle on every test pair: (P, n_test) each.

    Runs on one torch thread when ``P * n_test`` is small (:func:`limit_threads`):
    every step of the rollout is a handful of ops on ``P * n_test`` numbers, too
    few for threads to pay, and on a loaded machine each parallel op waits for a
    descheduled thread (the smoke run's 12 sets: 1.2 s on one thread, 14-30 s on
    two under load 4).
    """
    with limit_threads(theta.shape[0] * test.n_pairs):
        out = simulate(
            model, theta.to(dtype), test, dtype=dtype, device=device, weights=weights
        )
    return {
        key: getattr(out, key).double().cpu().numpy()
        for key in ("score", "e_p", "e_v", "e_a")
    }


def _hybrid_costs(
    name: str,
    theta: Tensor,
    rows: np.ndarray,
    costs: dict[str, dict[str, np.ndarray]],
    test: PairSet,
    kwargs: dict[str, Any],
) -> dict[str, np.ndarray]:
    """The (h, n_test) cost matrices of a model's hybrid particles ``theta``:
    the single model's rows where :func:`hybrid_rows_in_single` found them (the
    same particle on the same pairs, no second rollout), a rollout for the rest."""
    found = rows >= 0
    if found.all():
        return {key: value[rows] for key, value in costs[name].items()}
    fresh = cost_matrices(name, theta[torch.from_numpy(~found)], test, **kwargs)
    out = {key: np.empty((len(rows), test.n_pairs)) for key in fresh}
    for key, value in out.items():
        value[~found] = fresh[key]
        if found.any():
            value[found] = costs[name][key][rows[found]]
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
        mininterval=0.1 if sys.stderr.isatty() else 30.0,
        disable=not progress,
    )


def evaluate_posterior(
    posterior: Posterior,
    test: PairSet,
    cfg: TrainConfig,
    *,
    progress: bool = True,
) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, np.ndarray]]]:
    """Metrics of the hybrid and of every single model on ``test``.

    Two stages, each with a progress bar: simulating every set's particles on
    every test pair (the bar counts particles), then the metrics of all sets,
    their Sinkhorn solved together (:func:`simulated_metrics`).

    Args:
        posterior: the learned set.
        test: the test pairs.
        cfg: the run's config (dtype, device, score weights, ``eval``).
        progress: show the progress bars (stderr).

    Returns:
        metrics: ``{"hybrid" | model: evaluate_costs(...)}``;
        costs: the cost matrices of each entry (hybrid rows in model order).

    Raises:
        EvaluationError: the hybrid particle set is empty.
    """
    dtype = getattr(torch, cfg.dtype)
    kwargs = {"dtype": dtype, "device": cfg.device, "weights": cfg.abc.weights}
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
    with _bar(total, "evaluate: simulate", "particle", progress) as bar:
        for name in posterior.models:
            bar.set_postfix_str(name, refresh=False)
            if len(singles[name]):
                costs[name] = cost_matrices(name, singles[name], test, **kwargs)
                bar.update(len(singles[name]))
            if len(hybrid[name]):
                hybrid_parts.append(
                    _hybrid_costs(name, hybrid[name], rows[name], costs, test, kwargs)
                )
                bar.update(len(missing[name]))
    costs["hybrid"] = _stack(hybrid_parts)
    return simulated_metrics(costs, cfg, progress=progress), costs


def simulated_metrics(
    costs: dict[str, dict[str, np.ndarray]],
    cfg: TrainConfig,
    *,
    progress: bool = True,
) -> dict[str, dict[str, Any]]:
    """:func:`~torchcf.evaluation.metrics.evaluate_costs` of every set, with
    ``cfg.eval``'s beta, Sinkhorn regularisation and iteration cap; all sets'
    Sinkhorn problems are solved in one batched call (they share ``reg``).

    One particle invalid on every test pair makes WS and beta-WS (beta > 0)
    infinite (its mandatory mass has nowhere to go), which is reported as such,
    next to both over the other particles (``ws_valid``, ``beta_ws_valid``) and
    their count (``particles_never_valid``).

    Args:
        costs: per set, its (P_s, n_test) ``score, e_p, e_v, e_a``.
        cfg: the run's config.
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
            beta=cfg.eval.beta,
            sinkhorn_reg=cfg.eval.sinkhorn_reg,
            sinkhorn_max_iter=cfg.eval.sinkhorn_max_iter,
            callback=advance,
        )
        bar.update(2 * len(names) - bar.n)
    return dict(zip(names, results, strict=True))


def position_errors(
    posterior: Posterior, test: PairSet, pair: int, cfg: TrainConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fig. 4 data: simulated minus observed follower position of every hybrid
    particle on test pair ``pair``.

    Returns:
        time (T,) [s]; errors (P, T) [m], NaN past the pair's valid steps and for
        invalid rollouts; scores (P,).
    """
    one = test.subset([pair])
    dtype = getattr(torch, cfg.dtype)
    errors, scores = [], []
    for name in posterior.models:
        theta = posterior.hybrid[name].theta
        if not theta.shape[0]:
            continue
        with limit_threads(theta.shape[0]):  # one pair: see cost_matrices
            out = simulate(
                name,
                theta.to(dtype),
                one,
                dtype=dtype,
                device=cfg.device,
                return_traj=True,
                weights=cfg.abc.weights,
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
) -> dict[str, Any]:
    """Evaluate the finished run in ``run_dir``; write metrics.json and the report.

    Args:
        run_dir: a trainer output directory (:class:`~torchcf.rundir.RunDir`).
        report_dir: where the report goes (default ``run_dir/report``).
        pairs: optional ``(train, test)`` instead of loading the run's data config.
        figure_pair: the test pair (position) of the Fig. 4 figure; default the one
            whose best hybrid particle is closest to the median over pairs.
        tensorboard: also log to ``run_dir/tb``.
        progress: show progress bars on stderr (simulation, metrics, report).

    Returns:
        The metrics (also in ``run_dir/metrics.json``, written last: a run
        directory with ``metrics.json`` holds its whole report).

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
) -> dict[str, Any]:
    """:func:`evaluate_run` with the run directory held."""
    cfg, posterior, summary = run.load_run()
    report = Path(report_dir) if report_dir is not None else run.report_dir
    # The outputs' folders must take files before the data are loaded: fail fast
    # (and leave no empty report folder if the data then fail).
    run.probe()
    ensure_directory(report, "report directory", keep=False)
    test = load_split(cfg.data)[1] if pairs is None else pairs[1]
    # A stale metrics.json of an earlier evaluation must not outlive a failure of
    # this one and pass for its result.
    run.discard_metrics()
    metrics, costs = evaluate_posterior(posterior, test, cfg, progress=progress)
    entries = [*[m for m in posterior.models if m in metrics], "hybrid"]
    result = {
        "dataset": summary["dataset"],
        "n_test": test.n_pairs,
        "test_pair_ids": [int(i) for i in test.pair_ids],
        "beta": cfg.eval.beta,
        "sinkhorn_reg": cfg.eval.sinkhorn_reg,
        "sinkhorn_max_iter": cfg.eval.sinkhorn_max_iter,
        **{entry: metrics[entry] for entry in entries},
    }

    ensure_directory(report, "report directory")
    atomic_write_text(
        report / "table.md",
        f"# {summary['dataset']}: test-split evaluation\n\n"
        f"{test.n_pairs} test pairs; single models: each model's own "
        f"{posterior.top_n} best particles per training pair; hybrid: "
        f"{sum(len(p) for p in posterior.hybrid.values())} particles.\n\n"
        + metrics_table(metrics, entries)
        + "\n"
        + plausibility_table(summary.get("plausibility", {}))
        + "\nThe calibrated parameters per model: `parameters.md` (one row per "
        "particle: `parameters.csv`).\n",
    )
    if figure_pair is None:
        best = costs["hybrid"]["score"].min(axis=0)  # (n_test,)
        finite = np.where(np.isfinite(best), best, np.inf)
        figure_pair = int(
            np.argmin(np.abs(finite - np.median(best[np.isfinite(best)])))
        )
    time, errors, scores = position_errors(posterior, test, figure_pair, cfg)
    pair_id = int(test.pair_ids[figure_pair])
    figures = {
        "error_evolution": error_evolution_figure(
            time,
            errors,
            scores,
            title=f"Hybrid, test pair {pair_id}: position error",
        ),
        "radar": radar_figure({entry: metrics[entry] for entry in entries}),
    }
    # Training wrote the shares and pairwise PNGs into its report folder; another
    # folder (or a run trained before it did) gets them drawn here.
    trained = ("shares", "pairwise")
    in_run = report.resolve() == run.report_dir.resolve()
    if not (in_run and all((report / f"{n}.png").is_file() for n in trained)):
        pairwise = summary["pairwise"]
        figures["shares"] = shares_figure(posterior.shares)
        figures["pairwise"] = pairwise_figure(pairwise["models"], pairwise["table"])
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
                    {k: images[k] for k in ("error_evolution", "radar")},
                    {e: metrics[e] for e in entries},
                )
            bar.update()
    run.write_metrics(result)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        formatter_class=DefaultsHelpFormatter,
        prog="python -m torchcf.evaluate",
        description="Evaluate a trained run on its test pairs (SPEC section 6).",
    )
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--report", type=Path, default=None, help="report folder")
    parser.add_argument("--pair", type=int, default=None, help="test pair of Fig. 4")
    args = parser.parse_args(argv)

    def body() -> int:
        result = evaluate_run(
            args.run_dir, report_dir=args.report, figure_pair=args.pair
        )
        print(f"{'':8} {'e_p':>8} {'min':>8} {'0.15-WS':>8} {'WS':>8}")
        for entry, m in result.items():
            if isinstance(m, dict) and "ws" in m:
                print(
                    f"{entry:8} {m['e_p']:8.3f} {m['min']:8.3f} "
                    f"{m['beta_ws']:8.3f} {m['ws']:8.3f}"
                )
        print(f"wrote {RunDir(args.run_dir).metrics_json}")
        return 0

    return run_main(body)


if __name__ == "__main__":
    raise SystemExit(main())
