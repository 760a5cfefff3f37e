"""Benchmark: time to quality, rejection against SMC (and against pyABC).

Two parts, each writing ``reports/bench/<name>.{json,md}``:

``datasets``: for every config (the paper's three studies), training runs with
``abc.method = "rejection"`` and ``"smc"`` at several budgets (particles per
model), on the same training pairs, timed in this process
(:func:`torchcf.train.train`, no evaluation). Quality is the hybrid's per-pair
N-th best score (the worst particle it keeps on a pair), averaged over the pairs;
lower is better. The time to quality of SMC is the wall time of its smallest
budget whose quality is at least rejection's at its largest budget (the paper's
1e6), and the speed-up the ratio of the two wall times.

    python tools/bench_smc.py datasets --threads 2
    python tools/bench_smc.py datasets --configs configs/carII.json \\
        --rejection 100000 1000000 --smc 50000 100000 200000

``models``: per model, on every data set, the engine alone
(:func:`torchcf.abc.run_smc`, :func:`torchcf.abc.run_rejection`, no run
directory): rejection at ``--rejection`` (1e6) against SMC at ``--budget`` (5e4,
20x fewer simulations) for each kernel design of :data:`DESIGNS` (the one kept
first), quality each model's own (the mean over pairs of its N-th best score).
The kept design also at ``--seeds``.

    python tools/bench_smc.py models --threads 2

``pyabc``: one pair and one model, against the trace that
``tools/pyabc_baseline.py`` wrote (pyABC's ABCSMC in its own environment, on the
same pair): the engine (:func:`torchcf.abc.run_smc`, :func:`torchcf.abc.
run_rejection`, no run directory) at growing budgets until its best score on the
pair reaches pyABC's best, timed from the first draw to the result.

    python tools/bench_smc.py pyabc --trace reports/bench/pyabc_carII_idm.json

Both use ``compile = "off"`` unless ``--compile`` says otherwise, so that the two
methods run the same kernels (rejection's long runs would otherwise compile and
SMC's short ones not).
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402

import torchcf.abc.smc as smc_module  # noqa: E402
from torchcf.abc.kernel import SMCKernel  # noqa: E402
from torchcf.abc.rejection import (  # noqa: E402
    ModelProgress,
    Rollout,
    prior_stream,
    run_rejection,
)
from torchcf.abc.rounds import Chunk  # noqa: E402
from torchcf.abc.smc import SMCSettings, new_state, run_smc  # noqa: E402
from torchcf.abc.topn import TopN  # noqa: E402
from torchcf.config import (
    load_config,  # noqa: E402
    load_split,  # noqa: E402
)
from torchcf.data import load_pairs  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.posterior import Posterior  # noqa: E402
from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402
from torchcf.system.process import tune_malloc  # noqa: E402
from torchcf.train import train  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"
CONFIGS = ("configs/carII.json", "configs/carI.json", "configs/ngsim.json")


# ------------------------------------------------------------------ data sets
def hybrid_thresholds(posterior: Posterior) -> list[float]:
    """Per training pair, the worst score the hybrid keeps (its N-th best)."""
    worst: dict[int, float] = {int(p): -math.inf for p in posterior.train_pair_ids}
    for particles in posterior.hybrid.values():
        for pair, score in zip(
            particles.pair_ids.tolist(), particles.score.tolist(), strict=True
        ):
            worst[int(pair)] = max(worst[int(pair)], score)
    return [worst[int(p)] for p in posterior.train_pair_ids]


def one_run(cfg, pairs, method: str, budget: int, overrides: dict) -> dict:
    """A training run of ``cfg`` with ``method`` at ``budget`` particles per model."""
    abc = cfg.abc.model_copy(update={"method": method, "n_particles": budget})
    run_cfg = cfg.model_copy(update={"abc": abc, **overrides})
    with tempfile.TemporaryDirectory() as folder:
        began = time.perf_counter()
        summary = train(run_cfg, Path(folder) / "run", pairs=pairs)
        seconds = time.perf_counter() - began
        posterior = Posterior.load(Path(folder) / "run" / "posterior.pt")
    per_pair = hybrid_thresholds(posterior)
    finite = [v for v in per_pair if math.isfinite(v)]
    return {
        "method": method,
        "budget": budget,
        "seconds": seconds,
        "quality": sum(finite) / len(finite) if finite else math.inf,
        "per_pair": per_pair,
        "shares": summary.shares,
        "per_model_seconds": {m: r.seconds for m, r in summary.per_model.items()},
        "evidence_shares": None if summary.smc is None else summary.smc.evidence_shares,
        "model_thresholds": {m: summary.per_model[m].threshold for m in summary.shares},
    }


def time_to_quality(runs: list[dict]) -> dict:
    """SMC's smallest budget at least as good as rejection's largest, and the
    ratio of their wall times."""
    rejection = max((r for r in runs if r["method"] == "rejection"), key=_budget)
    for run in sorted((r for r in runs if r["method"] == "smc"), key=_budget):
        if run["quality"] <= rejection["quality"]:
            better = sum(
                s <= r
                for s, r in zip(run["per_pair"], rejection["per_pair"], strict=True)
            )
            return {
                "rejection_budget": rejection["budget"],
                "rejection_seconds": rejection["seconds"],
                "smc_budget": run["budget"],
                "smc_seconds": run["seconds"],
                "speed_up": rejection["seconds"] / run["seconds"],
                "budget_ratio": rejection["budget"] / run["budget"],
                "pairs_at_least_as_good": f"{better}/{len(run['per_pair'])}",
            }
    return {"rejection_budget": rejection["budget"], "reached": False}


def _budget(run: dict) -> int:
    return run["budget"]


def datasets(args) -> int:
    overrides = {"threads": args.threads, "compile": args.compile}
    results = {}
    for config in args.configs:
        cfg = load_config(config)
        pairs = load_split(cfg.data)
        runs = []
        plan = [("rejection", b) for b in args.rejection] + [
            ("smc", b) for b in args.smc
        ]
        for method, budget in plan:
            run = one_run(cfg, pairs, method, budget, overrides)
            print(
                f"{cfg.data.name} {method:9s} {budget:>8d}: {run['seconds']:7.1f} s, "
                f"quality {run['quality']:.4f}",
                file=sys.stderr,
            )
            runs.append(run)
        results[cfg.data.name] = {
            "n_train": pairs[0].n_pairs,
            "models": [m.name for m in cfg.models],
            "smc": cfg.abc.smc.model_dump(),
            "runs": runs,
            "time_to_quality": time_to_quality(runs),
        }
    payload = {"meta": bench_meta(sys.argv, args.threads), "results": results}
    write_report(REPORTS / args.name, payload, datasets_markdown(payload, args))
    return 0


def datasets_markdown(payload: dict, args) -> str:
    meta = payload["meta"]
    lines = [
        "# Time to quality: rejection against SMC",
        "",
        provenance(meta) + f", compile {args.compile}.",
        "",
        "Quality: the hybrid's per-pair N-th best score (the worst particle it keeps "
        "on a training pair), mean over the pairs; lower is better. Budget: "
        "particles per model (SMC: proposals in all rounds). Seconds: the whole "
        "training run (8 models, selection, outputs), wall time.",
        "",
    ]
    for name, result in payload["results"].items():
        ttq = result["time_to_quality"]
        lines += [
            f"## {name} ({result['n_train']} training pairs)",
            "",
            "| method | budget | seconds | slowest models (s) | quality | shares "
            "| evidence shares (SMC) |",
            "|---|---|---|---|---|---|---|",
        ]
        for run in result["runs"]:
            shares = ", ".join(f"{m} {v:.0%}" for m, v in run["shares"].items() if v)
            evidence = run["evidence_shares"] or {}
            ev = ", ".join(f"{m} {v:.0%}" for m, v in evidence.items() if v >= 0.005)
            slowest = sorted(run["per_model_seconds"].items(), key=lambda kv: -kv[1])
            slow = ", ".join(f"{m} {v:.1f}" for m, v in slowest[:3])
            lines.append(
                f"| {run['method']} | {run['budget']:,} | {run['seconds']:.1f} | "
                f"{slow} | {run['quality']:.4f} | {shares} | {ev} |"
            )
        lines.append("")
        if ttq.get("reached", True):
            lines.append(
                f"SMC reaches rejection's {ttq['rejection_budget']:,}-particle quality "
                f"with {ttq['smc_budget']:,} particles per model: "
                f"{ttq['smc_seconds']:.1f} s against {ttq['rejection_seconds']:.1f} s, "
                f"**{ttq['speed_up']:.1f}x sooner** "
                f"({ttq['budget_ratio']:.0f}x fewer simulations; "
                f"{ttq['pairs_at_least_as_good']} pairs at least as good)."
            )
        else:
            lines.append(
                f"No SMC budget tried reaches rejection's "
                f"{ttq['rejection_budget']:,}-particle quality."
            )
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------- per model
#: The designs compared by ``models``: name -> (settings, the kernel's space:
#: ``"logit"`` the engine's, ``"box"`` :class:`BoxKernel`), the kept one first.
DESIGNS = {
    "logit (kept)": (SMCSettings(), "logit"),
    "box (before)": (SMCSettings(), "box"),
    "box, scale 1": (SMCSettings(kernel_scale=1.0), "box"),
    "box, 20 rounds": (SMCSettings(rounds=20), "box"),
    "box, prior 10 %": (SMCSettings(prior_fraction=0.1), "box"),
    "logit, scale 1": (SMCSettings(kernel_scale=1.0), "logit"),
    "logit, prior 15 %": (SMCSettings(prior_fraction=0.15), "logit"),
    "logit, quantile 0.3": (SMCSettings(quantile=0.3), "logit"),
    "logit, population 30": (SMCSettings(population=30), "logit"),
    "logit, 8 rounds": (SMCSettings(rounds=8), "logit"),
    "logit, 16 rounds": (SMCSettings(rounds=16), "logit"),
}


def model_quality(buffer: TopN, n: int) -> float:
    """Mean over the pairs of the buffer's ``n``-th best score (finite ones)."""
    nth = buffer.score[:, n - 1]
    return float(nth[torch.isfinite(nth)].mean())


class BoxKernel(SMCKernel):
    """The engine's kernel (:class:`torchcf.abc.kernel.SMCKernel`) stepping in
    the prior box itself instead of its logit: the design before
    (``reports/smc/design.md``). ``Sigma_p = scale Cov_w(theta) +
    (KERNEL_FLOOR width)^2 I``; the uniform prior's density is one over the
    box's volume; a step can leave the box (:class:`BoxKernelRuns` counts such
    a proposal in the budget without simulating it)."""

    @staticmethod
    def _free(theta: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        return theta

    @staticmethod
    def _boxed(z: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        return z

    @staticmethod
    def _log_prior(z: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
        width = bounds[:, 1] - bounds[:, 0]
        return (-torch.log(width).sum()).expand(z.shape[0])

    @staticmethod
    def _centre_width(bounds: torch.Tensor) -> torch.Tensor:
        return bounds[:, 1] - bounds[:, 0]


def inside_box(theta: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """(Q,) bool: rows of ``theta`` (Q, K) inside the box ``bounds`` (K, 2)."""
    return ((theta >= bounds[:, 0]) & (theta <= bounds[:, 1])).all(dim=1)


class BoxKernelRuns:
    """Within it, :func:`torchcf.abc.run_smc` refines with :class:`BoxKernel`:
    the engine's kernel and round proposals (``torchcf.abc.smc.SMCKernel`` and
    ``_round_proposals``) replaced, a refinement proposal outside the box
    dropped from its chunk before it is simulated (its particle index spent),
    and counted."""

    def __init__(self) -> None:
        self.proposed = self.outside = 0

    def __enter__(self) -> BoxKernelRuns:
        self.real = smc_module.SMCKernel, smc_module._round_proposals
        kernel_class, round_proposals = self.real

        def box_round_proposals(kernel, stream, t, budget):
            propose = round_proposals(kernel, stream, t, budget)
            if kernel is None:  # round 0: the prior's draws
                return propose

            def inside_only(start: int, stop: int, batch: int | None) -> Chunk:
                chunk = propose(start, stop, batch)
                real = chunk.size
                keep = inside_box(chunk.theta[:real], kernel.bounds)
                keep = keep.nonzero().squeeze(1)
                self.proposed += real
                self.outside += real - keep.numel()
                theta, pair = chunk.theta[keep], chunk.pair[keep]
                if not keep.numel():
                    return Chunk(theta, pair, chunk.index[keep])
                pad = batch - keep.numel() if batch is not None else 0
                return Chunk(
                    torch.cat((theta, theta[:1].expand(pad, -1))),
                    torch.cat((pair, pair[:1].expand(pad))),
                    chunk.index[keep],
                    rows=chunk.rows[keep],
                )

            return inside_only

        smc_module.SMCKernel = BoxKernel
        smc_module._round_proposals = box_round_proposals
        return self

    def __exit__(self, *exc) -> None:
        smc_module.SMCKernel, smc_module._round_proposals = self.real

    @property
    def fraction(self) -> float:
        """Share of the refinement's proposals outside the box."""
        return self.outside / max(self.proposed, 1)


def engine_quality(
    method: str,
    name: str,
    pairs,
    budget: int,
    design: tuple[SMCSettings, str],
    seed: int,
    n: int,
    dtype,
) -> tuple[float, float, float]:
    """(quality, seconds, share of the refinement's proposals outside the box)
    of one model's engine run on ``pairs``; ``design``: the settings and the
    kernel's space (:data:`DESIGNS`)."""
    settings, space = design
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    rollout = Rollout(pairs, dtype=dtype, compile="off")
    stream = prior_stream(model, bounds, seed, rollout)
    began = time.perf_counter()
    outside = 0.0
    if method == "smc":
        buffer = TopN(pairs.n_pairs, n, model.n_params + 1)
        state = new_state(pairs.n_pairs, settings, model.n_params)
        progress = ModelProgress()
        if space == "box":
            with BoxKernelRuns() as tally:
                run_smc(stream, buffer, rollout, budget, settings, progress, state)
            outside = tally.fraction
        else:  # the engine's own kernel never leaves the box
            run_smc(stream, buffer, rollout, budget, settings, progress, state)
    else:
        buffer = TopN(pairs.n_pairs, n, model.n_params)
        run_rejection(stream, buffer, rollout, budget, ModelProgress())
    return model_quality(buffer, n), time.perf_counter() - began, outside


def models(args) -> int:
    results = {}
    for config in args.configs:
        cfg = load_config(config)
        pairs = load_split(cfg.data)[0]
        dtype = getattr(torch, cfg.dtype)
        n = cfg.abc.top_n
        rows = {}
        for spec in cfg.models:
            name = spec.name
            ref, ref_s, _ = engine_quality(
                "rejection", name, pairs, args.rejection, DESIGNS["logit (kept)"], 0,
                n, dtype,
            )  # fmt: skip
            row = {"rejection": ref, "rejection_seconds": ref_s, "designs": {}}
            runs = [(d, 0) for d in DESIGNS] + [
                (next(iter(DESIGNS)), s) for s in args.seeds if s != 0
            ]
            for design, seed in runs:
                quality, seconds, outside = engine_quality(
                    "smc", name, pairs, args.budget, DESIGNS[design], seed, n, dtype
                )
                key = design if seed == 0 else f"{design}, seed {seed}"
                row["designs"][key] = {
                    "quality": quality,
                    "seconds": seconds,
                    "outside": outside,
                }
                print(
                    f"{cfg.data.name} {name:5s} {key:28s} {quality:.4f} "
                    f"(rejection {ref:.4f})",
                    file=sys.stderr,
                )
            rows[name] = row
        results[cfg.data.name] = {"n_train": pairs.n_pairs, "models": rows}
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "budget": args.budget,
        "rejection_budget": args.rejection,
        "designs": {
            k: {**asdict(settings), "space": space}
            for k, (settings, space) in DESIGNS.items()
        },
        "results": results,
        "summary": design_summary(results),
    }
    write_report(REPORTS / args.name, payload, models_markdown(payload))
    return 0


def design_summary(results: dict) -> dict:
    """Per design (and seed): the (data set, model) cells where SMC's quality is
    worse than rejection's, the mean and the worst of log(SMC / rejection)."""
    cells: dict[str, list[tuple[float, str]]] = {}
    for data, result in results.items():
        for name, row in result["models"].items():
            for design, run in row["designs"].items():
                ratio = math.log(run["quality"] / row["rejection"])
                cells.setdefault(design, []).append((ratio, f"{data}/{name}"))
    return {
        design: {
            "cells": len(values),
            "worse": [cell for ratio, cell in values if ratio > 0],
            "mean_log_ratio": sum(r for r, _ in values) / len(values),
            "worst": max(values),
        }
        for design, values in cells.items()
    }


def _models(payload: dict) -> list[str]:
    """The model names of the first data set (every data set has the eight)."""
    return list(next(iter(payload["results"].values()))["models"])


def models_markdown(payload: dict) -> str:
    meta = payload["meta"]
    designs = list(payload["designs"])
    lines = [
        "# SMC per model: 20x fewer simulations against rejection",
        "",
        provenance(meta) + ", compile off, the engine alone.",
        "",
        f"Quality: each model's own mean over the training pairs of its 5th best "
        f"score; lower is better. Rejection: {payload['rejection_budget']:,} prior "
        f"particles per model; SMC: {payload['budget']:,} proposals per model, "
        "seed 0, one column per kernel design (`*`: worse than rejection).",
        "",
        "| design | cells worse than rejection | mean log(SMC / rejection) | worst |",
        "|---|---|---|---|",
    ]
    for design, row in payload["summary"].items():
        worst_ratio, worst_cell = row["worst"]
        worse = ", ".join(row["worse"]) if row["worse"] else "none"
        lines.append(
            f"| {design} | {len(row['worse'])}/{row['cells']} ({worse}) | "
            f"{row['mean_log_ratio']:+.4f} | {worst_ratio:+.4f} ({worst_cell}) |"
        )
    lines += [
        "",
        "Share of the refinement's proposals outside the prior box, counted in the "
        "budget but not simulated, with the kernel in the box (the design before; "
        "the logit kernel's are none):",
        "",
        "| data set | " + " | ".join(_models(payload)) + " |",
        "|---|" + "---|" * len(_models(payload)),
    ]
    for data, result in payload["results"].items():
        shares = [
            f"{row['designs']['box (before)']['outside']:.0%}"
            for row in result["models"].values()
        ]
        lines.append(f"| {data} | " + " | ".join(shares) + " |")
    for data, result in payload["results"].items():
        lines += [
            "",
            f"## {data} ({result['n_train']} training pairs)",
            "",
            "| model | rejection | " + " | ".join(designs) + " |",
            "|---|---|" + "---|" * len(designs),
        ]
        for name, row in result["models"].items():
            cells = []
            for design in designs:
                q = row["designs"][design]["quality"]
                cells.append(f"{q:.4f}{'*' if q > row['rejection'] else ''}")
            lines.append(
                f"| {name} | {row['rejection']:.4f} | " + " | ".join(cells) + " |"
            )
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- pyABC
def engine_best(
    method: str, name: str, pair, budget: int, settings: SMCSettings, dtype
) -> tuple[float, float]:
    """(best score, seconds) of the engine alone on one pair."""
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    rollout = Rollout(pair, dtype=dtype, compile="off")
    stream = prior_stream(model, bounds, 0, rollout)
    began = time.perf_counter()
    if method == "smc":
        buffer = TopN(1, 1, model.n_params + 1)
        state = new_state(1, settings, model.n_params)
        run_smc(stream, buffer, rollout, budget, settings, ModelProgress(), state)
    else:
        buffer = TopN(1, 1, model.n_params)
        run_rejection(stream, buffer, rollout, budget, ModelProgress())
    return float(buffer.score[0, 0]), time.perf_counter() - began


def pyabc(args) -> int:
    trace = json.loads(Path(args.trace).read_text())
    target, target_seconds = trace["best"]["score"], trace["best"]["seconds"]
    pairs = load_pairs("car-model-2", split="train")
    position = list(pairs.pair_ids).index(int(trace["pair"]["pair_id"]))
    pair = pairs.subset(torch.arange(pairs.n_pairs) == position)
    dtype = getattr(torch, args.dtype)
    series = [
        (f"smc, {r} rounds", SMCSettings(population=args.population, rounds=r))
        for r in args.rounds
    ] + [("rejection", SMCSettings())]
    warm_up = SMCSettings(population=args.population, rounds=2)
    engine_best("smc", "idm", pair, 8 * args.population, warm_up, dtype)
    rows, reached = [], {}
    for label, settings in series:
        method = label.split(",")[0]
        for budget in args.budgets:
            best, seconds = engine_best(method, "idm", pair, budget, settings, dtype)
            rows.append(
                {"method": label, "budget": budget, "best": best, "seconds": seconds}
            )
            print(f"{label:18s} {budget:>8d}: best {best:.5f} in {seconds:.3f} s")
            if best <= target and label not in reached:
                reached[label] = rows[-1]
    payload = {
        "meta": bench_meta(sys.argv, torch.get_num_threads()),
        "pyabc": {
            "trace": args.trace,
            "best": target,
            "seconds": target_seconds,
            "version": trace.get("environment", {}).get("pyabc"),
        },
        "pair": trace["pair"],
        "runs": rows,
        "reached": {
            m: {**r, "speed_up": target_seconds / r["seconds"]}
            for m, r in reached.items()
        },
    }
    write_report(REPORTS / args.name, payload, pyabc_markdown(payload, args))
    return 0


def pyabc_markdown(payload: dict, args) -> str:
    meta, ref = payload["meta"], payload["pyabc"]
    lines = [
        "# Time to pyABC's best score on one pair",
        "",
        provenance(meta) + f", {args.dtype}, compile off.",
        "",
        f"pyABC {ref['version']} (`{ref['trace']}`, `tools/pyabc_baseline.py`): best "
        f"score **{ref['best']:.5f}** after {ref['seconds']:.1f} s on CAR MODEL II "
        f"pair id {payload['pair']['pair_id']}, IDM. torchcf: the engine alone "
        "(no run directory), best score on the pair after each budget.",
        "",
        "| method | budget | best | seconds |",
        "|---|---|---|---|",
    ]
    for run in payload["runs"]:
        lines.append(
            f"| {run['method']} | {run['budget']:,} | {run['best']:.5f} | "
            f"{run['seconds']:.3f} |"
        )
    lines.append("")
    for method, run in payload["reached"].items():
        lines.append(
            f"{method}: reaches pyABC's best with {run['budget']:,} particles in "
            f"{run['seconds']:.3f} s, **{run['speed_up']:.0f}x sooner** than pyABC."
        )
    for label in dict.fromkeys(run["method"] for run in payload["runs"]):
        if label not in payload["reached"]:
            lines.append(f"{label}: does not reach pyABC's best in the budgets tried.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parts = parser.add_subparsers(dest="part", required=True)
    data = parts.add_parser("datasets", help="rejection vs SMC on the data sets")
    data.add_argument("--configs", nargs="+", default=list(CONFIGS))
    data.add_argument(
        "--rejection", nargs="+", type=count, default=[100_000, 1_000_000]
    )
    data.add_argument(
        "--smc", nargs="+", type=count, default=[25_000, 50_000, 100_000, 200_000]
    )
    data.add_argument("--threads", type=count, default=2)
    data.add_argument("--compile", default="off", choices=("off", "auto", "on"))
    data.add_argument("--name", default="smc_datasets")
    per_model = parts.add_parser("models", help="SMC designs per model")
    per_model.add_argument("--configs", nargs="+", default=list(CONFIGS))
    per_model.add_argument("--rejection", type=count, default=1_000_000)
    per_model.add_argument("--budget", type=count, default=50_000)
    per_model.add_argument("--seeds", nargs="+", type=natural, default=[0, 1, 2])
    per_model.add_argument("--threads", type=count, default=2)
    per_model.add_argument("--name", default="smc_models")
    single = parts.add_parser("pyabc", help="the engine against pyABC on one pair")
    single.add_argument("--trace", default=str(REPORTS / "pyabc_carII_idm.json"))
    single.add_argument(
        "--budgets",
        nargs="+",
        type=count,
        default=[2_000, 5_000, 10_000, 20_000, 50_000, 100_000, 200_000, 1_000_000],
    )
    single.add_argument("--population", type=count, default=SMCSettings().population)
    single.add_argument(
        "--rounds",
        nargs="+",
        type=count,
        default=[SMCSettings().rounds],
        help="SMC refinement rounds; several: one SMC series each",
    )
    single.add_argument("--dtype", default="float64", choices=("float32", "float64"))
    single.add_argument("--threads", type=count, default=1)
    single.add_argument("--name", default="smc_pyabc")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    tune_malloc()
    parts = {"datasets": datasets, "models": models, "pyabc": pyabc}
    return parts[args.part](args)


if __name__ == "__main__":
    raise SystemExit(run_main(main))
