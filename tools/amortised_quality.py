"""Study: how good the amortised posteriors are, on synthetic pairs and on the
paper's data sets, against rejection and SMC.

**Synthetic** (``--parts synthetic``): for each of the eight models,
``--pairs`` held-out pairs whose followers it drives with per-pair prior
draws (``tools/sbc_study.py``'s :func:`prior_pairs`: ``--steps`` steps, 0.05 m
position noise). One amortised run of the whole pool on them (its estimator
trained on simulations behind their leaders, never on the pairs themselves),
and one with the refinement (``--refine-rounds``), which reuses the first
run's estimator (``abc.amortised.estimator``: trained once, the same samples
refined; its seconds are the refinement's alone):

- (a) SBC and coverage per model (:mod:`torchcf.evaluation.sbc`): the rank of
  each pair's true parameters among ``--draws`` draws of its true model's flow
  (the amortised posterior itself), and among the run's 5 best scored samples
  of that model per pair, without and with the refinement (as
  ``tools/sbc_study.py`` reads a run: coverage of the central 50 % and 90 %
  intervals, the width factor that would calibrate them);
- (b) the 8 x 8 model-recovery matrix: rows the generating model, columns the
  estimator's most probable model (share of the row's pairs), and the
  hybrid's per-pair shares after scoring, without and with the refinement
  (``tools/model_recovery.py``'s reading).

**Data sets** (``--parts datasets``): each config of ``--datasets`` (the
paper's three, data under ``$TORCHCF_DATA``) trained and evaluated on its test
split four ways: rejection at ``--rejection`` particles per model, SMC at
``--smc``, amortised, amortised with the refinement (reusing the amortised
run's estimator, as above). Per method the hybrid's
test WS, 0.15-WS and minimum distance with their bootstrap intervals (the
evaluation's ``metrics.json``), the models' test WS, and where amortised is
worse than SMC: the models whose test WS is more than 5 % above SMC's and the
test pairs whose hybrid minimum distance is (``hybrid_min_by_pair``).

Runs go to ``--work`` (default a temporary folder); a finished run there is
read back, not trained again, so a long study can be resumed.

    python tools/amortised_quality.py --threads 2 --work /scratch/quality  # full
    python tools/amortised_quality.py --pairs 4 --steps 200 --draws 50 \\
        --samples 20 --simulations 500 --epochs 1 --refine-rounds 1 \\
        --refine-per-pair 10 --datasets configs/carII.json --rejection 20000 \\
        --smc 20000 --smc-population 10 --smc-rounds 2 \\
        --out /tmp/amortised_quality                                 # smoke

Writes ``reports/amortised/quality.{json,md}`` (``--out``).
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402
from model_recovery import slots, summarise  # noqa: E402
from sbc_study import LEVELS, MODELS, accepted_draws, join, prior_pairs, sbc_of  # noqa: E402

from torchcf.amortised import AmortisedEstimator, pair_features  # noqa: E402
from torchcf.amortised.space import latent_to_unit  # noqa: E402
from torchcf.calibration.estimator_samples import trained_estimator  # noqa: E402
from torchcf.calibration.of_config import method_of  # noqa: E402
from torchcf.config import TrainConfig, load_config, validate_config  # noqa: E402
from torchcf.data import PairSet  # noqa: E402
from torchcf.evaluation import sbc  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.posterior import Posterior  # noqa: E402
from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.runs.metrics import SetEvaluation  # noqa: E402
from torchcf.runs.summary import RunSummary  # noqa: E402
from torchcf.study.pipeline import train_and_evaluate  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
PAPER = ("configs/carI.json", "configs/carII.json", "configs/ngsim.json")
METHODS = ("rejection", "smc", "amortised", "refined")
#: The hybrid's test metrics compared, and their labels.
METRICS = (("ws", "WS"), ("beta_ws", "0.15-WS"), ("min", "min distance"))
#: Amortised is "worse" where its value exceeds SMC's by this share.
WORSE = 0.05
SEED = 50


# ----------------------------------------------------------------- the runs
def amortised_settings(args, refined: bool, estimator: Path | None) -> dict:
    """``abc.amortised`` of the study's amortised runs; ``estimator``: the
    amortised run whose trained estimator a refined run reuses."""
    return {
        "estimator": None if estimator is None else str(estimator),
        "samples_per_pair": args.samples,
        "window_steps": args.window,
        "simulations_per_epoch": args.simulations,
        "max_epochs": args.epochs,
        "validation_simulations": args.validation,
        "refine": {
            "rounds": args.refine_rounds if refined else 0,
            "per_pair": args.refine_per_pair,
        },
    }


def method_abc(args, method: str, amortised_run: Path) -> dict:
    """The ``abc`` settings of one of :data:`METHODS`; the refined run reuses
    the estimator of the amortised run in ``amortised_run`` (trained once,
    refined samples drawn from the same posterior)."""
    if method == "rejection":
        return {"method": "rejection", "n_particles": args.rejection}
    if method == "smc":
        smc = {"population": args.smc_population, "rounds": args.smc_rounds}
        return {"method": "smc", "n_particles": args.smc, "smc": smc}
    return {
        "method": "amortised",
        "amortised": amortised_settings(
            args,
            refined=method == "refined",
            estimator=amortised_run if method == "refined" else None,
        ),
    }


def trained(
    cfg: TrainConfig,
    out: Path,
    pairs: tuple[PairSet, PairSet] | None,
    evaluate: bool,
) -> tuple[Posterior, RunSummary]:
    """The run of ``cfg`` in ``out``, trained (and evaluated) unless it is
    there already; its posterior and summary."""
    run = RunDir(out)
    done = run.is_trained() and (run.is_evaluated() or not evaluate)
    if not done:
        train_and_evaluate(
            cfg, out, pairs=pairs, evaluate=evaluate, resume=run.holds_run()
        )
    return Posterior.load(run.posterior_pt), run.read_summary()


# ----------------------------------------------------------------- synthetic
def model_draws(
    estimator: AmortisedEstimator, pairs: PairSet, model: int, n: int, seed: int
) -> torch.Tensor:
    """(N, n, K_m) draws of the flow of ``model`` for each pair: the amortised
    posterior of the parameters given the model."""
    features, lengths = pair_features(pairs)
    k = estimator.space.n_params[model]
    g = torch.Generator().manual_seed(seed)
    normal = torch.randn(pairs.n_pairs, n, k, generator=g)
    with torch.no_grad():
        embedding = estimator.embed(features, lengths)  # (N, E)
        context = embedding.repeat_interleave(n, 0)  # (N n, E)
        flow = estimator.flows[model](context)
        latent = flow.transform.inv(normal.reshape(-1, k))
        theta = estimator.space.to_theta(model, latent_to_unit(latent))
    return theta.reshape(pairs.n_pairs, n, k).to(torch.float64)


def synthetic(args, work: Path) -> dict:
    """SBC, coverage and model recovery on held-out synthetic pairs."""
    made, truths, label = [], {}, []
    for k, model in enumerate(MODELS):
        pairs, truth = prior_pairs(model, args.pairs, args.steps, seed=SEED + 1000 * k)
        made.append(pairs)
        truths[model] = truth
        label += [k] * args.pairs
    pairs = join(made, "synthetic-amortised")
    label = np.asarray(label)
    held = (pairs, pairs.subset(torch.arange(1)))
    posteriors, summaries = {}, {}
    for method in ("amortised", "refined"):
        raw = {
            "data": {"path": "synthetic prior draws (tools/amortised_quality.py)"},
            "models": list(MODELS),
            "abc": {"top_n": 5, "sensitivity_n": [5], "seed": SEED}
            | method_abc(args, method, work / "synthetic" / "amortised"),
            "compile": "off",
            "threads": args.threads,
        }
        cfg = validate_config(raw)
        out = work / "synthetic" / method
        posteriors[method], summaries[method] = trained(cfg, out, held, False)
        if method == "amortised":
            priors = {spec.model: spec.bounds() for spec in cfg.models}
            checkpoint = RunDir(out).amortised_checkpoint
            estimator = trained_estimator(method_of(cfg), priors, checkpoint)
    probabilities = estimator.model_probabilities(*pair_features(pairs))  # (N, M)
    top = probabilities.argmax(1).numpy()
    recovery = {
        "estimator_top_model": sbc.confusion_matrix(
            np.eye(len(MODELS))[top], label, len(MODELS)
        ).tolist()
    }
    for method, posterior in posteriors.items():
        shares = sbc.pair_shares(slots(posterior, list(MODELS)))
        recovery[f"hybrid_{method}"] = summarise(shares, label, list(MODELS))
    calibration = {}
    for k, model in enumerate(MODELS):
        rows = torch.as_tensor(np.nonzero(label == k)[0])
        bounds = get_model(model).prior_bounds(torch.float64)
        draws = model_draws(estimator, pairs.subset(rows), k, args.draws, SEED + k)
        entry = {"flow": _calibration(truths[model], draws, bounds, k)}
        for method, posterior in posteriors.items():
            accepted = accepted_draws(posterior, model, pairs.n_pairs)[rows]
            entry[f"top5_{method}"] = _calibration(truths[model], accepted, bounds, k)
        calibration[model] = entry
    return {
        "pairs_per_model": args.pairs,
        "calibration": calibration,
        "recovery": recovery,
        "refinement": _json_or_none(summaries["refined"].amortised.refinement),
        "training": {
            key: getattr(summaries["amortised"].amortised, key)
            for key in ("epochs", "simulations", "seconds", "validation_accuracy")
        },
    }


def _calibration(
    truth: torch.Tensor, draws: torch.Tensor, bounds: torch.Tensor, seed: int
) -> dict | None:
    """SBC and coverage of draws (``tools/sbc_study.py``'s, without the
    per-pair ranks); None where no pair has all its draws (a model the run
    kept too few samples of on every pair)."""
    if not bool(torch.isfinite(draws).all(2).all(1).any()):
        return None
    entry = sbc_of(truth, draws, bounds, seed=seed)
    return {k: v for k, v in entry.items() if k not in ("ranks", "histogram")}


# ----------------------------------------------------------------- data sets
def datasets(args, work: Path) -> dict:
    """The paper's data sets, four methods each, on their test splits."""
    out = {}
    for path in args.datasets:
        base = load_config(path)
        name = Path(path).stem
        block: dict = {"methods": {}}
        mins = {}
        for method in METHODS:
            raw = base.model_dump(mode="json")
            raw["abc"] = raw["abc"] | method_abc(
                args, method, work / name / "amortised"
            )
            raw["threads"] = args.threads
            cfg = validate_config(raw)
            run_dir = work / name / method
            _, summary = trained(cfg, run_dir, None, True)
            evaluation = RunDir(run_dir).read_metrics()
            hybrid = evaluation.hybrid
            block["methods"][method] = {
                # WS is infinite where a particle is invalid on every test
                # pair: its value over the valid particles is kept beside it
                "hybrid": {key: _with_interval(hybrid, key) for key, _ in METRICS},
                # a model the hybrid keeps no particle of has no test WS
                "model_ws": {
                    m: evaluation.sets[m].metrics.ws if m in evaluation.sets else None
                    for m in summary.models
                },
                "shares": summary.shares,
                "seconds": _seconds(summary),
                "amortised": _json_or_none(summary.amortised),
            }
            mins[method] = np.asarray(
                [np.inf if v is None else v for v in evaluation.hybrid_min_by_pair]
            )
            block["test_pair_ids"] = list(evaluation.test_pair_ids)
        block["worse_than_smc"] = {
            method: worse(block, mins, method) for method in ("amortised", "refined")
        }
        out[name] = block
    return out


def _with_interval(entry: SetEvaluation, key: str) -> list[float | None]:
    """A set's metric ``key``: its value, its bootstrap interval's bounds and
    its value over the particles valid on some test pair (None: not
    computed)."""
    metrics = entry.metrics
    interval = None
    if entry.uncertainty is not None:
        interval = entry.uncertainty.intervals.get(key)
    return [
        getattr(metrics, key),
        None if interval is None else interval.low,
        None if interval is None else interval.high,
        getattr(metrics, f"{key}_valid", None),
    ]


def _json_or_none(record) -> dict | None:
    """A record's JSON object; None stays None."""
    return None if record is None else record.to_json()


def _seconds(summary: RunSummary) -> float:
    """A training run's seconds: its models' streams (``seconds_total``) and,
    where it trained one, its estimator's training."""
    amortised = summary.amortised
    trained = amortised.seconds if amortised and not amortised.reused else 0.0
    return summary.seconds_total + trained


def worse(block: dict, mins: dict, method: str) -> dict:
    """Where ``method`` is worse than SMC: models by test WS, test pairs by
    the hybrid's minimum distance."""
    smc, mine = block["methods"]["smc"], block["methods"][method]
    both = [
        m
        for m in smc["model_ws"]
        if smc["model_ws"][m] is not None and mine["model_ws"].get(m) is not None
    ]
    models = {
        m: mine["model_ws"][m] / smc["model_ws"][m]
        for m in both
        if mine["model_ws"][m] > (1 + WORSE) * smc["model_ws"][m]
    }
    absent = [m for m in smc["model_ws"] if mine["model_ws"].get(m) is None]
    ratio = mins[method] / mins["smc"]
    ids = block["test_pair_ids"]
    bad = np.nonzero(ratio > 1 + WORSE)[0]
    order = bad[np.argsort(-ratio[bad])]
    return {
        "models_ws_ratio": models,
        "models_without_particles": absent,
        "pairs_worse": int(bad.size),
        "pairs": len(ratio),
        "worst_pairs": [
            {"pair_id": int(ids[j]), "ratio": float(ratio[j])} for j in order[:10]
        ],
    }


# ----------------------------------------------------------------- the report
def markdown(payload: dict) -> str:
    meta, res, args = payload["meta"], payload["results"], payload["settings"]
    lines = ["# The amortised posteriors: calibration, recovery, test metrics", ""]
    lines += [
        f"{provenance(meta)}. Amortised: {args['samples']} samples per pair, the "
        f"estimator trained on {args['simulations']:,} simulations per epoch for "
        f"at most {args['epochs']} epochs; refined: {args['refine_rounds']} rounds "
        f"of {args['refine_per_pair']} proposals per pair and model, from the "
        "amortised run's estimator. Data sets: rejection at "
        f"{args['rejection']:,} particles per model, SMC at {args['smc']:,} "
        f"(population {args['smc_population']}, {args['smc_rounds']} rounds).",
        "",
    ]
    if "synthetic" in res:
        syn = res["synthetic"]
        lines += [
            f"## Synthetic pairs ({syn['pairs_per_model']} per model)",
            "",
            "Coverage of the central 50 % / 90 % intervals (mean over the "
            "parameters; calibrated: 0.50 / 0.90), then SBC: the parameters "
            "whose ranks of the truth are not uniform (chi-square p < 0.01) of "
            "the model's; for the flow's draws of the true model (the amortised "
            "posterior itself) and the run's 5 best scored samples per pair "
            "(the ABC posterior the run keeps).",
            "",
            "| model | flow | top 5 amortised | top 5 refined |",
            "|---|---|---|---|",
        ]
        for model, entry in syn["calibration"].items():
            cells = []
            for key in ("flow", "top5_amortised", "top5_refined"):
                if entry[key] is None:
                    cells.append("- (no pair with 5 fits)")
                    continue
                cov = entry[key]["coverage"]
                pvalues = np.asarray(entry[key]["pvalue"])
                cells.append(
                    " / ".join(f"{np.mean(cov[str(q)]):.2f}" for q in LEVELS)
                    + f"; SBC {int((pvalues < 0.01).sum())} of {pvalues.size}"
                    + f" ({entry[key]['pairs_used']} pairs)"
                )
            lines.append(f"| {model} | {' | '.join(cells)} |")
        lines += ["", "Model recovery: the diagonal (share of a model's pairs).", ""]
        lines += ["| model | estimator's top model | hybrid amortised "
                  "| hybrid refined |", "|---|---:|---:|---:|"]  # fmt: skip
        rec = syn["recovery"]
        for k, model in enumerate(MODELS):
            cells = [
                rec["estimator_top_model"][k][k],
                rec["hybrid_amortised"]["confusion"][k][k],
                rec["hybrid_refined"]["confusion"][k][k],
            ]
            lines.append(f"| {model} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")
    for name, block in res.get("datasets", {}).items():
        lines += [
            "",
            f"## {name}: the hybrid on the test split",
            "",
            "Value [bootstrap interval over test pairs]; seconds: the run's "
            "models' streams and the amortised run's estimator training (the "
            "refined run reuses that estimator: its seconds are the scoring and "
            "the refinement), on a machine shared with other work, so a rough "
            "guide, not a timing.",
            "",
            "| method | " + " | ".join(label for _, label in METRICS) + " | seconds |",
            "|---|" + "---|" * len(METRICS) + "---:|",
        ]
        for method, entry in block["methods"].items():
            cells = [_interval(entry["hybrid"][key]) for key, _ in METRICS]
            seconds = entry.get("seconds")
            cells.append("-" if seconds is None else f"{seconds:.0f}")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        for method, w in block["worse_than_smc"].items():
            models = ", ".join(f"{m} x{r:.2f}" for m, r in w["models_ws_ratio"].items())
            absent = ", ".join(w.get("models_without_particles", []))
            lines.append(
                f"\n{method}: models with test WS > 5 % above SMC's: "
                f"{models or 'none'}"
                + (f" (no particle in the hybrid: {absent})" if absent else "")
                + "; test pairs whose hybrid minimum distance is "
                f"> 5 % above SMC's: {w['pairs_worse']} of {w['pairs']}."
            )
    return "\n".join(lines) + "\n"


def _interval(cell: list) -> str:
    value, low, high, valid = (list(cell) + [None])[:4]
    if value is None:
        return "-"
    if not math.isfinite(value) and valid is not None:
        return f"inf (over the particles valid somewhere: {valid:.4f})"
    if low is None or high is None:
        return f"{value:.4f}"
    return f"{value:.4f} [{low:.4f}, {high:.4f}]"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=["synthetic", "datasets"],
                        choices=["synthetic", "datasets"])  # fmt: skip
    parser.add_argument("--pairs", type=count, default=100)
    parser.add_argument("--steps", type=count, default=300)
    parser.add_argument("--draws", type=count, default=100)
    parser.add_argument("--samples", type=count, default=200)
    parser.add_argument("--window", type=count, default=None)
    parser.add_argument("--simulations", type=count, default=20000)
    parser.add_argument("--validation", type=count, default=4000)
    parser.add_argument("--epochs", type=count, default=40)
    parser.add_argument("--refine-rounds", type=count, default=4)
    parser.add_argument("--refine-per-pair", type=count, default=50)
    parser.add_argument("--datasets", nargs="+", default=list(PAPER))
    parser.add_argument("--rejection", type=count, default=1_000_000)
    parser.add_argument("--smc", type=count, default=1_000_000)
    parser.add_argument("--smc-population", type=count, default=50)
    parser.add_argument("--smc-rounds", type=count, default=12)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=REPORTS / "amortised" / "quality")
    args = parser.parse_args(argv)
    if args.window is None:  # the training windows fit the synthetic pairs
        args.window = min(300, args.steps)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="torchcf-quality-") as scratch:
        work = args.work if args.work is not None else Path(scratch)
        results = {}
        if "synthetic" in args.parts:
            results["synthetic"] = synthetic(args, work)
        if "datasets" in args.parts:
            results["datasets"] = datasets(args, work)
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "settings": settings,
        "results": results,
    }
    write_report(args.out, payload, markdown(payload))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
