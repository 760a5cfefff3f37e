"""Benchmark: the amortised method at scale, its training, inference and
refinement, against per-pair SMC.

- **training**: one estimator of the pool models (``--models``, the paper's
  eight by default) trained on ``--simulations`` simulations per epoch for at
  most ``--epochs`` epochs behind the leaders of ``--train-pairs`` synthetic
  pairs (:mod:`torchcf.amortised`); its simulations, seconds and the process's
  peak RSS (``resource.getrusage``; the peak of the whole process so far).
- **inference** on each of ``--sizes`` synthetic pairs (followers of the pool
  models in turn and of a model outside the pool, Gipps
  (:class:`torchcf.sim.synthetic.Gipps`), every ``len(models) + 1``-th pair),
  parameters near the middle of each model's prior box: the network alone
  (``--samples`` samples per pair, :func:`torchcf.amortised.infer`), with the
  flows' sampling eager and compiled (``--compile``; compiled once beforehand
  on an empty compile cache, its seconds apart), then every sample simulated
  once and scored into per-pair buffers
  (:func:`torchcf.amortised.run_amortised`; up to ``--score-max-pairs``
  pairs), then the refinement (``--refine-rounds`` rounds of
  ``--refine-per-pair`` proposals per pair and model,
  :func:`torchcf.abc.smc.refine_population`; up to ``--refine-max-pairs``):
  seconds per 1 000 pairs of each.
- **quality** on the first ``--common`` pairs: per-pair SMC of every pool model
  (``--smc-per-pair`` proposals per pair and model, :func:`torchcf.abc.run_smc`)
  against the amortised samples scored, and refined: the mean over the pairs
  of the best score (all models; the run's distance) and of the mean of the
  ``top_n`` best, and the pairs where amortised is more than 5 % worse than
  SMC, by generating model.

The targets (issue 50, on 2 cores): training <= 30 min, 10^5 pairs inferred in
<= 5 min, quality within 5 % of per-pair SMC.

    python tools/bench_amortised.py --threads 2 --keep DIR       # full size
    python tools/bench_amortised.py --sizes 100 --epochs 1 --simulations 500 \\
        --samples 20 --common 20 --smc-per-pair 300 --out /tmp/bench_amortised

``--keep DIR`` keeps the trained estimator (``DIR/amortised.pt``) and reads
it back on the next run, so that inference can be measured again without
training again.

Writes ``reports/bench/amortised.{json,md}`` (``--out``).
"""

from __future__ import annotations

import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402

from torchcf.abc.rejection import ModelProgress, Rollout, prior_stream  # noqa: E402
from torchcf.abc.smc import (  # noqa: E402
    Budget,
    SMCSettings,
    new_state,
    parameter_buffer,
    refine_population,
    run_smc,
)
from torchcf.abc.topn import TopN  # noqa: E402
from torchcf.amortised import (  # noqa: E402
    AmortisedEstimator,
    NoiseLevels,
    ParameterSpace,
    Session,
    SimulationSettings,
    TrainingProgress,
    TrainingSettings,
    TrainingSimulator,
    estimator_fingerprint,
    infer,
    load_trained,
    new_estimator,
    run_amortised,
    train_estimator,
)
from torchcf.data import PairSet  # noqa: E402
from torchcf.models import CFModel, get_model  # noqa: E402
from torchcf.sim.synthetic import Gipps, synthetic_pairs  # noqa: E402
from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
POOL = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")
TOP_N = 5
#: Pairs made per synthetic_pairs call (one leader batch, one model).
BLOCK = 1000
#: A pair's parameters: the box's middle, moved by up to this share of its
#: width either way (the whole box crashes too many followers to batch).
JITTER = 0.2
#: A pair is "worse" where its best amortised score exceeds SMC's by this.
WORSE = 0.05
SERIES = ("x_lead", "v_lead", "a_lead", "x_follow", "v_follow", "a_follow")


# ----------------------------------------------------------------- the pairs
def generators(models: list[str]) -> list[CFModel]:
    """The pool models and Gipps, the model outside the pool."""
    return [get_model(name) for name in models] + [Gipps()]


def make_pairs(
    models: list[CFModel], n_pairs: int, n_steps: int, seed: int
) -> tuple[PairSet, torch.Tensor]:
    """``n_pairs`` pairs, pair ``i`` driven by ``models[i % len(models)]``.

    Returns:
        The pairs and (N,) int64 the generating model's position.
    """
    g = torch.Generator().manual_seed(seed)
    series: dict[str, list[torch.Tensor]] = {}
    label = torch.arange(n_pairs) % len(models)
    order = []
    for m, model in enumerate(models):
        rows = (label == m).nonzero().squeeze(1)
        for start in range(0, rows.numel(), BLOCK):
            block = rows[start : start + BLOCK]
            made = _block(model, block.numel(), n_steps, g, seed + 31 * m + start)
            for key in (
                "x_lead",
                "v_lead",
                "a_lead",
                "x_follow",
                "v_follow",
                "a_follow",
            ):
                series.setdefault(key, []).append(getattr(made, key))
            order.append(block)
    position = torch.cat(order).argsort()  # back to pair order
    joined = {key: torch.cat(parts, 1)[:, position] for key, parts in series.items()}
    return PairSet.from_arrays(joined, dt=0.1, name="bench-amortised"), label


def _block(
    model: CFModel, n: int, n_steps: int, g: torch.Generator, seed: int
) -> PairSet:
    """``n`` pairs of ``model``, parameters jittered around the box's middle
    (less jitter where a follower crashes)."""
    box = model.prior_bounds(torch.float64)  # (K, 2)
    middle, width = box.mean(1), box[:, 1] - box[:, 0]
    jitter = JITTER
    for _ in range(6):
        unit = torch.rand(n, box.shape[0], generator=g, dtype=torch.float64)
        theta = middle + (2 * unit - 1) * jitter * width  # (n, K)
        try:
            return synthetic_pairs(model, theta, n, n_steps, seed=seed, noise=0.05)
        except ValueError:  # a follower crashed: closer to the middle
            jitter /= 2
    return synthetic_pairs(model, middle, n, n_steps, seed=seed, noise=0.05)


# ----------------------------------------------------------------- the steps
def peak_rss_mb() -> float:
    """The process's peak resident set so far [MB] (Linux: ru_maxrss in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def train(
    args, space: ParameterSpace, pairs: PairSet
) -> tuple[AmortisedEstimator, dict]:
    """The estimator trained behind ``pairs``' leaders; its cost. With
    ``--keep DIR`` the training's checkpoint is ``DIR/amortised.pt``: a
    finished one is read back (its seconds those of the run that trained it)."""
    if args.estimator is not None:
        return read_estimator(args.estimator, new_estimator(space, seed=args.seed))
    simulator = TrainingSimulator(
        space,
        pairs,
        SimulationSettings(window_steps=args.window, noise=NoiseLevels.of_pairs(pairs)),
        seed=args.seed,
    )
    settings = TrainingSettings(
        simulations_per_epoch=args.simulations,
        max_epochs=args.epochs,
        validation_simulations=args.validation,
        seed=args.seed,
    )
    estimator = new_estimator(space, seed=args.seed)
    session = Session()
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        checkpoint = args.keep / "amortised.pt"
        session = Session(checkpoint=checkpoint, resume=checkpoint.exists())
    result = train_estimator(estimator, simulator, settings, session)
    progress = result.progress
    return estimator, {
        "simulations": progress.simulations,
        "epochs": len(progress.history),
        "finished": progress.finished,
        "seconds": round(progress.seconds, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "validation_accuracy": result.validation_accuracy,
        "read_back": session.resume,
    }


def read_estimator(
    path: Path, estimator: AmortisedEstimator
) -> tuple[AmortisedEstimator, dict]:
    """A trained estimator of the same models, boxes and network read from
    ``path`` (an amortised run's ``amortised.pt``, or its directory) into
    ``estimator``; its training's record."""
    if path.is_dir():
        path = path / "amortised.pt"
    raw = load_trained(path, estimator_fingerprint(estimator))
    estimator.load_state_dict(
        raw["best"] if raw["best"] is not None else raw["estimator"]
    )
    progress = TrainingProgress.from_dict(raw["progress"])
    return estimator.eval(), {
        "simulations": progress.simulations,
        "epochs": len(progress.history),
        "finished": progress.finished,
        "seconds": round(progress.seconds, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "validation_accuracy": progress.best_accuracy,
        "read_back": True,
        "estimator": str(path),
    }


def scored(samples, pairs: PairSet, models: list[str]) -> dict[str, TopN]:
    """Every pair's samples (:func:`infer`'s) simulated once and kept in
    per-model buffers with SMC's ``log r`` column (0), ready to be refined."""
    rollout = Rollout(pairs, compile="off")
    buffers = {}
    for m, name in enumerate(models):
        model = get_model(name)
        buffer = TopN(pairs.n_pairs, 2 * TOP_N, model.n_params + 1)
        run_amortised(
            model, samples.of_model(m), buffer, rollout, ModelProgress(),
            weight_column=True,
        )  # fmt: skip
        buffers[name] = buffer
    return buffers


def sample_counts(samples, models: list[str]) -> dict[str, int]:
    """Per model, the samples that drew it (its particles before the
    refinement's)."""
    counts = torch.bincount(samples.model.reshape(-1), minlength=len(models))
    return dict(zip(models, counts.tolist(), strict=True))


def refined(
    buffers: dict[str, TopN], pairs: PairSet, args, samples_of: dict[str, int]
) -> None:
    """The buffers refined in place (``--refine-rounds`` rounds)."""
    rollout = Rollout(pairs, compile="off")
    settings = SMCSettings(population=args.refine_population, rounds=args.refine_rounds)
    for name, buffer in buffers.items():
        model = get_model(name)
        bounds = model.prior_bounds(torch.float64)
        budget = Budget(
            samples_of[name], args.refine_per_pair, args.refine_rounds, pairs.n_pairs
        )
        refine_population(
            prior_stream(model, bounds, args.seed, rollout),
            buffer,
            rollout,
            budget,
            settings,
            ModelProgress(next=samples_of[name]),
            new_state(pairs.n_pairs, settings, model.n_params),
        )


def smc_buffers(pairs: PairSet, models: list[str], args) -> dict[str, TopN]:
    """Per-pair SMC of every pool model (``--smc-per-pair`` per pair)."""
    rollout = Rollout(pairs, compile="off")
    settings = SMCSettings(population=args.smc_population, rounds=args.smc_rounds)
    out = {}
    for name in models:
        model = get_model(name)
        bounds = model.prior_bounds(torch.float64)
        buffer = TopN(pairs.n_pairs, 2 * TOP_N, model.n_params + 1)
        run_smc(
            prior_stream(model, bounds, args.seed, rollout),
            buffer,
            rollout,
            args.smc_per_pair * pairs.n_pairs,
            settings,
            ModelProgress(),
            new_state(pairs.n_pairs, settings, model.n_params),
        )
        out[name] = buffer
    return out


def quality(buffers: dict[str, TopN]) -> dict:
    """Per pair the best score over the models and the mean of the ``TOP_N``
    best (the per-pair hybrid's), and their means over the pairs."""
    scores = torch.cat(
        [parameter_buffer(b).score[:, :TOP_N] for b in buffers.values()], 1
    )  # (N, M TOP_N)
    best_n = torch.sort(scores, 1).values[:, :TOP_N]  # (N, TOP_N)
    best = best_n[:, 0]
    return {
        "best": best,
        "mean_best": float(best[torch.isfinite(best)].mean()),
        "mean_top_n": float(best_n.mean(1)[torch.isfinite(best_n.mean(1))].mean()),
        "pairs_without_fit": int((~torch.isfinite(best)).sum()),
    }


def compare(smc: dict, amortised: dict, label: torch.Tensor, names: list[str]) -> dict:
    """Amortised against SMC on common pairs: the ratio of the means, and per
    generating model the pairs more than 5 % worse."""
    ratio = amortised["best"] / smc["best"]
    worse = ratio > 1 + WORSE
    return {
        "mean_best_ratio": amortised["mean_best"] / smc["mean_best"],
        "mean_top_n_ratio": amortised["mean_top_n"] / smc["mean_top_n"],
        "pairs_worse": int(worse.sum()),
        "pairs_worse_by_model": {
            name: int(worse[label == m].sum()) for m, name in enumerate(names)
        },
        "worst_pairs": [
            {"pair": int(j), "model": names[int(label[j])], "ratio": float(ratio[j])}
            for j in torch.argsort(ratio, descending=True)[:10]
            if torch.isfinite(ratio[j])
        ],
    }


def _plain(result: dict) -> dict:
    return {k: v for k, v in result.items() if k != "best"}


# ----------------------------------------------------------------- the bench
def measure(args) -> dict:
    models = list(args.models)
    makers = generators(models)
    names = [m.name for m in makers]
    space = ParameterSpace(
        [get_model(n) for n in models],
        [get_model(n).prior_bounds(torch.float64) for n in models],
    )
    train_pairs, _ = make_pairs(makers[:-1], args.train_pairs, args.steps, seed=1)
    estimator, training = train(args, space, train_pairs)
    print(f"training: {training}", flush=True)
    modes = {"off": [False], "on": [True], "both": [False, True]}[args.compile]
    compile_seconds = None
    if True in modes:  # the flows compiled once, on an empty compile cache
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="inductor-")
        warm, _ = make_pairs(makers, 64, args.steps, seed=5)
        began = time.perf_counter()
        infer(estimator, warm, args.samples, seed=args.seed, compile=True)
        compile_seconds = time.perf_counter() - began
        print(f"compiled in {compile_seconds:.1f} s", flush=True)
    rows = []
    for size in args.sizes:
        pairs, label = make_pairs(makers, size, args.steps, seed=100 + size)
        row: dict = {"pairs": size}
        for compiled in modes:
            began = time.perf_counter()
            samples = infer(
                estimator, pairs, args.samples, seed=args.seed, compile=compiled
            )
            key = "infer_compiled_s_per_1000" if compiled else "infer_s_per_1000"
            row[key] = (time.perf_counter() - began) * 1000 / size
        top = samples.probabilities.argmax(1)
        row["top_model_rate_pool"] = float(
            (top == label)[label < len(models)].to(torch.float64).mean()
        )
        if size <= args.score_max_pairs:
            began = time.perf_counter()
            buffers = scored(samples, pairs, models)
            row["score_s_per_1000"] = (time.perf_counter() - began) * 1000 / size
            if size <= args.refine_max_pairs and args.refine_rounds:
                began = time.perf_counter()
                refined(buffers, pairs, args, sample_counts(samples, models))
                spent = time.perf_counter() - began
                row["refine_s_per_1000"] = spent * 1000 / size
        row["peak_rss_mb"] = round(peak_rss_mb(), 1)
        print(row, flush=True)
        rows.append(row)
    if not args.common:
        return {"training": training, "compile_seconds": compile_seconds, "sizes": rows}
    common, label = make_pairs(makers, args.common, args.steps, seed=7)
    began = time.perf_counter()
    smc = quality(smc_buffers(common, models, args))
    smc_seconds = time.perf_counter() - began
    samples = infer(estimator, common, args.samples, seed=args.seed)
    buffers = scored(samples, common, models)
    amortised = quality(buffers)
    comparison = {"amortised": compare(smc, amortised, label, names)}
    out = {"smc": _plain(smc), "amortised": _plain(amortised)}
    if args.refine_rounds:
        refined(buffers, common, args, sample_counts(samples, models))
        after = quality(buffers)
        out["refined"] = _plain(after)
        comparison["refined"] = compare(smc, after, label, names)
    return {
        "training": training,
        "compile_seconds": compile_seconds,
        "sizes": rows,
        "common": {
            "pairs": args.common,
            "smc_seconds_per_1000": smc_seconds * 1000 / args.common,
            **out,
            "against_smc": comparison,
        },
    }


def markdown(payload: dict) -> str:
    meta, res, args = payload["meta"], payload["results"], payload["settings"]
    t = res["training"]
    sizes = res["sizes"]
    compiled = any("infer_compiled_s_per_1000" in row for row in sizes)
    lines = [
        "# The amortised method at scale",
        "",
        f"{provenance(meta)}. Pool {', '.join(args['models'])}; Gipps outside the "
        "pool drives every (pool + 1)-th pair. Targets (issue 50, 2 cores): "
        "training <= 30 min, 10^5 pairs inferred in <= 5 min, quality within 5 % "
        "of per-pair SMC.",
        "",
        "## Training",
        "",
        f"{t['simulations']:,} simulations, {t['epochs']} epochs ({t['finished']}), "
        f"{t['seconds']:.1f} s, peak RSS {t['peak_rss_mb']:.0f} MB, validation "
        f"model accuracy {t['validation_accuracy']:.1%}"
        + (
            f" (read back from `{t.get('estimator', '--keep')}`: the seconds of "
            "the run that trained it, the peak RSS of this one)."
            if t.get("read_back")
            else "."
        ),
        "",
        "## Seconds per 1 000 pairs",
        "",
        f"{args['samples']} samples per pair; refinement {args['refine_rounds']} "
        f"rounds x {args['refine_per_pair']} proposals per pair and model. "
        "Inference: the network's forward passes and samples; scoring: every "
        "sample simulated once and kept (inference not included)."
        + (
            f" Compiled: the flows' sampling through `torch.compile` "
            f"(`compile`), compiled once beforehand in {res['compile_seconds']:.1f} "
            "s on an empty compile cache (not included)."
            if compiled
            else ""
        ),
        "",
        "| pairs | inference | inference, compiled | scoring | refinement "
        "| top model (pool pairs) | peak RSS MB |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in sizes:
        cells = [
            f"{row[key]:.2f}" if key in row else "-"
            for key in (
                "infer_s_per_1000",
                "infer_compiled_s_per_1000",
                "score_s_per_1000",
                "refine_s_per_1000",
            )
        ]
        lines.append(
            f"| {row['pairs']:,} | {' | '.join(cells)} | "
            f"{row['top_model_rate_pool']:.1%} | {row['peak_rss_mb']:.0f} |"
        )
    if "common" not in res:
        return "\n".join(lines) + "\n"
    common = res["common"]
    lines += [
        "",
        f"## Quality against per-pair SMC ({common['pairs']} common pairs)",
        "",
        f"SMC: {args['smc_per_pair']} proposals per pair and model "
        f"({common['smc_seconds_per_1000']:.1f} s per 1 000 pairs). Mean over the "
        "pairs of the best score (all models) and of the mean of the 5 best; "
        "the ratio to SMC's (1: as good, above: worse).",
        "",
        "| method | mean best | mean 5 best | ratio best | ratio 5 best "
        "| pairs > 5 % worse |",
        "|---|---:|---:|---:|---:|---:|",
        f"| SMC | {common['smc']['mean_best']:.4f} | "
        f"{common['smc']['mean_top_n']:.4f} | 1 | 1 | - |",
    ]
    for key in ("amortised", "refined"):
        if key not in common:
            continue
        c = common["against_smc"][key]
        lines.append(
            f"| {key} | {common[key]['mean_best']:.4f} | "
            f"{common[key]['mean_top_n']:.4f} | {c['mean_best_ratio']:.3f} | "
            f"{c['mean_top_n_ratio']:.3f} | {c['pairs_worse']} |"
        )
    lines += ["", "Pairs more than 5 % worse than SMC, by generating model:", ""]
    for key, c in common["against_smc"].items():
        worse = ", ".join(f"{m} {n}" for m, n in c["pairs_worse_by_model"].items())
        lines.append(f"- {key}: {worse}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(POOL))
    parser.add_argument("--sizes", nargs="+", type=count, default=[1000, 10000, 100000])
    parser.add_argument("--steps", type=count, default=300)
    parser.add_argument("--train-pairs", type=count, default=500)
    parser.add_argument("--window", type=count, default=300)
    parser.add_argument("--simulations", type=count, default=20000)
    parser.add_argument("--validation", type=count, default=4000)
    parser.add_argument("--epochs", type=count, default=40)
    parser.add_argument("--samples", type=count, default=200)
    parser.add_argument("--score-max-pairs", type=natural, default=10000)
    parser.add_argument("--refine-max-pairs", type=count, default=10000)
    parser.add_argument("--refine-rounds", type=natural, default=4)
    parser.add_argument("--refine-per-pair", type=count, default=50)
    parser.add_argument("--refine-population", type=count, default=20)
    parser.add_argument(
        "--common", type=natural, default=200,
        help="pairs of the quality comparison with per-pair SMC (0: none)",
    )  # fmt: skip
    parser.add_argument("--smc-per-pair", type=count, default=2000)
    parser.add_argument("--smc-population", type=count, default=50)
    parser.add_argument("--smc-rounds", type=count, default=12)
    parser.add_argument("--seed", type=natural, default=0)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument(
        "--compile", choices=("off", "on", "both"), default="both",
        help="inference with the flows' sampling eager, compiled or both",
    )  # fmt: skip
    parser.add_argument(
        "--estimator", type=Path, default=None,
        help="a trained estimator of the same models and network (an amortised "
        "run's amortised.pt or directory) instead of training one",
    )  # fmt: skip
    parser.add_argument(
        "--keep", type=Path, default=None,
        help="keep the trained estimator in this folder (amortised.pt), or read "
        "it back from there",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=REPORTS / "bench" / "amortised")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    settings = {
        k: str(v) if isinstance(v, Path) else v
        for k, v in vars(args).items()
        if k != "out"
    }
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "settings": settings,
        "results": measure(args),
    }
    write_report(args.out, payload, markdown(payload))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
