"""Study: parameter calibration of the ABC posterior (simulation-based calibration).

For each pool model, ``--pairs`` synthetic pairs whose followers are driven by
the model with parameters drawn from its uniform prior (one draw per pair;
:func:`prior_pairs`: ``--steps`` steps at dt 0.1, measurement noise 0.05 m on the
position as in ``tools/bench_scale.py``). The model alone is calibrated on them
(``torchcf.study.pipeline.train_and_evaluate``, paired layout, ``abc.top_n`` = 5,
``--per-pair`` prior draws per pair for rejection, ``--smc-per-pair`` proposals
per pair for SMC), and per pair the rank of the true parameter among the pair's
5 accepted particles (the run's posterior) is counted
(:mod:`torchcf.evaluation.sbc`). Under an exact posterior the rank is uniform
on 0..5 and the central ``q`` interval covers the truth a fraction ``q`` of the
time; ABC's tolerance (the 5 best of a finite budget) makes the accepted set
wider than the posterior: coverage above ``q``.

A truth whose follower crashes behind its leader is drawn again (same leader):
the truth is then a draw from the prior restricted to non-crashing followers,
which is what the data (no crash) tell the posterior too, so SBC stays valid.

    python tools/sbc_study.py --threads 1
    python tools/sbc_study.py --render   # sbc.md and figures again from sbc.json

Writes ``reports/uncertainty/sbc.{json,md}`` and ``sbc_ranks_<method>.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.data import PairSet  # noqa: E402
from torchcf.evaluation import sbc  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.sim.synthetic import synthetic_pairs  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "uncertainty"
MODELS = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")
DT = 0.1
NOISE = 0.05
LEVELS = (0.5, 0.9)
TOP_N = 5


# ----------------------------------------------------------------- the pairs
def prior_pairs(
    model_name: str, n_pairs: int, n_steps: int, seed: int, tries: int = 50
) -> tuple[PairSet, torch.Tensor]:
    """``n_pairs`` pairs driven by ``model_name`` with per-pair prior draws.

    Pair ``i`` has its own leader (seed ``seed + 7919 i``); its parameter is
    drawn from the uniform prior until the follower does not crash.

    Returns:
        the pairs and the true parameters (N, K) float64.
    """
    model = get_model(model_name)
    bounds = model.prior_bounds(torch.float64)  # (K, 2)
    g = torch.Generator().manual_seed(seed)
    made, truths = [], []
    for i in range(n_pairs):
        for _ in range(tries):
            unit = torch.rand(model.n_params, generator=g, dtype=torch.float64)
            theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * unit
            try:
                pair = synthetic_pairs(
                    model, theta, 1, n_steps, DT, seed=seed + 7919 * i, noise=NOISE
                )
            except ValueError:
                continue
            made.append(pair)
            truths.append(theta)
            break
        else:
            raise RuntimeError(f"{model_name}: pair {i} crashes {tries} times")
    return join(made), torch.stack(truths)


def join(sets: list[PairSet], name: str = "synthetic-prior") -> PairSet:
    """One PairSet of the pairs of ``sets`` (same steps and dt), in order."""
    series = {
        key: torch.cat([getattr(p, key) for p in sets], dim=1)
        for key in ("x_lead", "v_lead", "a_lead", "x_follow", "v_follow", "a_follow")
    }
    return PairSet.from_arrays(series, dt=DT, name=name)


def calibrate(
    pairs: PairSet,
    models: list[str],
    method: str,
    n_particles: int,
    threads: int,
    seed: int = 0,
    compile_mode: str = "auto",
    keep: int = TOP_N,
):
    """Train ``models`` on ``pairs`` in this process; returns (posterior, summary,
    seconds). The test split is the first pair (no evaluation is run); the
    buffers keep the ``keep`` best per pair (``>= TOP_N``)."""
    from torchcf.config import validate_config
    from torchcf.posterior import Posterior
    from torchcf.study.pipeline import train_and_evaluate

    raw = {
        "data": {"path": "synthetic prior draws (tools/sbc_study.py)"},
        "models": models,
        "abc": {
            "method": method,
            "layout": "paired",
            "n_particles": n_particles,
            "top_n": TOP_N,
            "sensitivity_n": sorted({TOP_N, keep}),
            "seed": seed,
        },
        "compile": compile_mode,
        "threads": threads,
    }
    cfg = validate_config(raw)
    with tempfile.TemporaryDirectory(prefix="torchcf-sbc-") as folder:
        out = Path(folder) / "run"
        start = time.perf_counter()
        summary = train_and_evaluate(
            cfg, out, pairs=(pairs, pairs.subset(torch.arange(1))), evaluate=False
        ).summary
        seconds = time.perf_counter() - start
        posterior = Posterior.load(out / "posterior.pt")
    return posterior, summary, seconds


def accepted_draws(posterior, model: str, n_pairs: int, n: int = TOP_N) -> torch.Tensor:
    """(N, n, K) the model's ``n`` best particles per pair (its buffer's; NaN
    where a slot is empty: no valid particle)."""
    buffer = posterior.buffers[model]
    k = len(get_model(model).param_names)  # SMC buffers may carry a weight column
    theta = buffer["theta"][:, :n, :k].to(torch.float64).clone()  # (N, n, K)
    score = buffer["score"][:, :n]
    theta[~torch.isfinite(score)] = float("nan")
    order = posterior.train_pair_ids.argsort()
    assert theta.shape[0] == n_pairs
    return theta[order]


def sbc_of(truth: torch.Tensor, draws: torch.Tensor, bounds: torch.Tensor, seed: int):
    """Ranks, coverage, widths of one model and method (pairs with L fits only)."""
    n_draws = draws.shape[1]
    full = torch.isfinite(draws).all(2).all(1)  # (N,)
    truth, draws = truth[full], draws[full]
    g = torch.Generator().manual_seed(seed)
    ranks = sbc.sbc_ranks(truth, draws, generator=g)
    pit = sbc.rank_pit(ranks, n_draws, generator=g)
    coverage = sbc.central_coverage(pit, LEVELS)  # (levels, K)
    prior_width = bounds[:, 1] - bounds[:, 0]
    widths = {
        str(q): (sbc.interval_width(draws, q) / prior_width).median(0).values.tolist()
        for q in LEVELS
    }
    spread = (draws.amax(1) - draws.amin(1)) / prior_width  # (N, K)
    factor = {
        str(q): {
            "mean": sbc.width_factor(float(coverage[i].mean()), q, n_draws),
            "per_param": [sbc.width_factor(float(c), q, n_draws) for c in coverage[i]],
        }
        for i, q in enumerate(LEVELS)
    }
    return {
        "width_factor": factor,
        "pairs_used": int(full.sum()),
        "pairs_without_all_fits": int((~full).sum()),
        "ranks": ranks.T.tolist(),
        "histogram": sbc.rank_histogram(ranks, n_draws).T.tolist(),
        "pvalue": sbc.uniformity_pvalue(ranks, n_draws).tolist(),
        "coverage": {str(q): coverage[i].tolist() for i, q in enumerate(LEVELS)},
        "range_coverage": ((draws.amin(1) <= truth) & (truth <= draws.amax(1)))
        .to(torch.float64)
        .mean(0)
        .tolist(),
        "width_rel_prior": widths,
        "range_rel_prior": spread.median(0).values.tolist(),
    }


# ----------------------------------------------------------------- the study
def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    results: dict = {"methods": {}}
    for method in args.methods:
        per_pair = args.per_pair if method == "rejection" else args.smc_per_pair
        results["methods"][method] = {"per_pair": per_pair, "models": {}}
    for k, model in enumerate(args.models):
        began = time.perf_counter()
        pairs, truth = prior_pairs(model, args.pairs, args.steps, seed=1000 * (k + 1))
        made = time.perf_counter() - began
        bounds = get_model(model).prior_bounds(torch.float64)
        for method in args.methods:
            block = results["methods"][method]
            posterior, summary, seconds = calibrate(
                pairs,
                [model],
                method,
                block["per_pair"] * args.pairs,
                args.threads,
                keep=max(TOP_N, args.wide_n),
            )
            draws = accepted_draws(posterior, model, args.pairs)
            entry = sbc_of(truth, draws, bounds, seed=k)
            if args.wide_n > TOP_N:
                wide = accepted_draws(posterior, model, args.pairs, args.wide_n)
                entry["wide"] = sbc_of(truth, wide, bounds, seed=k)
            entry.update(
                params=list(get_model(model).param_names),
                seconds=seconds,
                seconds_pairs=made,
                invalid_rate=summary.per_model[model].invalid_rate,
            )
            block["models"][model] = entry
            cov = entry["coverage"]
            print(
                f"{model:6s} {method:9s} {seconds:6.1f}s  cov50 "
                f"{np.mean(cov['0.5']):.2f} cov90 {np.mean(cov['0.9']):.2f}",
                flush=True,
            )
    return results


# ------------------------------------------------------------------ the report
def figure(results: dict, method: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    models = results["methods"][method]["models"]
    names = list(models)
    k_max = max(len(models[m]["params"]) for m in names)
    fig, axes = plt.subplots(
        len(names), k_max, figsize=(1.7 * k_max, 1.35 * len(names)), squeeze=False
    )
    for row, model in enumerate(names):
        entry = models[model]
        expected = entry["pairs_used"] / (TOP_N + 1)
        for col in range(k_max):
            ax = axes[row, col]
            if col >= len(entry["params"]):
                ax.axis("off")
                continue
            counts = entry["histogram"][col]
            ax.bar(range(TOP_N + 1), counts, color="tab:blue", width=0.85)
            band = 1.96 * np.sqrt(expected * (1 - 1 / (TOP_N + 1)))
            ax.axhspan(expected - band, expected + band, color="0.85", zorder=0)
            ax.axhline(expected, color="0.4", lw=0.8)
            ax.set_xticks(range(TOP_N + 1))
            ax.tick_params(labelsize=6)
            ax.set_title(
                f"{model} {entry['params'][col]}\np={entry['pvalue'][col]:.2g}",
                fontsize=7,
            )
    fig.suptitle(
        f"SBC rank of the truth among the {TOP_N} accepted particles ({method})",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def findings(res: dict) -> list[str]:
    """One line per method: the models whose accepted particles are wider than
    the posterior, calibrated, or narrower, judged on the mean 50 % coverage
    over the model's parameters against 0.5 +- 2 binomial standard errors
    (parameters taken as independent)."""
    out = []
    for method, block in res["methods"].items():
        groups: dict[str, list[str]] = {"wider": [], "calibrated": [], "narrower": []}
        for model, e in block["models"].items():
            c50 = float(np.mean(e["coverage"]["0.5"]))
            se = np.sqrt(0.25 / (e["pairs_used"] * len(e["params"])))
            key = (
                "wider"
                if c50 > 0.5 + 2 * se
                else "narrower"
                if c50 < 0.5 - 2 * se
                else "calibrated"
            )
            factor = _factor(e["width_factor"]["0.5"]["mean"])
            low, high = (
                _factor(sbc.width_factor(min(max(c, 1e-6), 1 - 1e-6), 0.5, TOP_N))
                for c in (c50 - 2 * se, c50 + 2 * se)
            )
            groups[key].append(
                f"{model} ({c50:.2f}/{np.mean(e['coverage']['0.9']):.2f}, "
                f"x{factor} [{low}, {high}])"
            )
        out.append(
            f"- **{method}** ({block['per_pair']} per pair), coverage 50 %/90 %, "
            "the width factor and its range at the 50 % coverage +- 2 standard "
            "errors: too wide: "
            + (", ".join(groups["wider"]) or "none")
            + "; within 2 standard errors of nominal: "
            + (", ".join(groups["calibrated"]) or "none")
            + "; too narrow: "
            + (", ".join(groups["narrower"]) or "none")
            + "."
        )
    return out


def _factor(value: float) -> str:
    if value == float("inf"):
        return "> max"
    return f"{value:.2f}"


def markdown(payload: dict) -> str:
    meta, res = payload["meta"], payload["results"]
    lines = [
        "# Parameter calibration of the ABC posterior (SBC)",
        "",
        f"`{meta['command']}`",
        "",
        f"- torch {meta['torch']}, threads {meta['threads']}, cpu {meta['cpu']}, "
        f"git {meta['git']}, total wall {payload['wall_seconds']:.0f} s",
        f"- pairs per model: {payload['pairs']} synthetic, {payload['steps']} steps "
        f"at dt {DT} s, noise {NOISE} m on the position (speed and acceleration "
        "scaled as in `torchcf.sim.synthetic`), one prior draw per pair",
        f"- each model calibrated alone on its own pairs, paired layout, "
        f"top_n = {TOP_N}; per-pair budgets: "
        + ", ".join(f"{m} {b['per_pair']} per pair" for m, b in res["methods"].items())
        + " (the paper's rejection budget, 1e6 particles on CAR MODEL II's 45 "
        "training pairs, is about 22 000 per pair)",
        "",
        "Observed coverage of the truth by the central 50 % and 90 % intervals of "
        "each pair's 5 accepted particles (randomised rank PIT, so exact at any "
        "level), mean over the model's parameters and the range over them; "
        "`range` is the coverage of [min, max] of the 5 (nominal 4/6 = 0.667 under "
        "an exact posterior); `x wider`: how many times wider than the exact "
        "posterior the accepted particles are, read from the mean 50 % coverage "
        "under a Gaussian model (truth N(0, 1) around the posterior, the 5 draws "
        "N(0, x^2): `torchcf.evaluation.sbc.width_factor`; 1 = calibrated, < 1 "
        "too narrow; `> max`: beyond what 5 draws can show, at most 0.78); "
        "`w50/w90`: median width of the 5 particles' central "
        "50 %/90 % interval relative to the prior's width (mean over parameters); "
        "`p<0.01`: parameters whose rank histogram fails a chi-square test of "
        "uniformity at 1 %.",
        "",
    ]
    lines += ["## Findings (computed)", "", *findings(res), ""]
    for method, block in res["methods"].items():
        lines += [
            f"## {method} ({block['per_pair']} per pair)",
            "",
            "| model | pairs | cov 50 % (range) | cov 90 % (range) | [min,max] cov "
            "| x wider (50 %) | w50 / prior | w90 / prior | p<0.01 | seconds |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for model, e in block["models"].items():
            c50, c90 = np.array(e["coverage"]["0.5"]), np.array(e["coverage"]["0.9"])
            bad = [
                p for p, pv in zip(e["params"], e["pvalue"], strict=True) if pv < 0.01
            ]
            lines.append(
                f"| {model} | {e['pairs_used']} | {c50.mean():.2f} "
                f"({c50.min():.2f}-{c50.max():.2f}) | {c90.mean():.2f} "
                f"({c90.min():.2f}-{c90.max():.2f}) | "
                f"{np.mean(e['range_coverage']):.2f} | "
                f"{_factor(e['width_factor']['0.5']['mean'])} | "
                f"{np.mean(e['width_rel_prior']['0.5']):.2f} | "
                f"{np.mean(e['width_rel_prior']['0.9']):.2f} | "
                f"{', '.join(bad) or '-'} | {e['seconds']:.0f} |"
            )
        lines += [
            "",
            f"Per parameter ({method}): coverage 50 % / 90 %, x the width factor "
            "read from the 50 % coverage, w the 5's central 90 % width relative to "
            "the prior, p the chi-square p-value.",
            "",
        ]
        for model, e in block["models"].items():
            cells = [
                f"{p} {c5:.2f}/{c9:.2f} x{_factor(x)} w{w:.2f} p{pv:.2g}"
                for p, c5, c9, x, w, pv in zip(
                    e["params"],
                    e["coverage"]["0.5"],
                    e["coverage"]["0.9"],
                    e["width_factor"]["0.5"]["per_param"],
                    e["width_rel_prior"]["0.9"],
                    e["pvalue"],
                    strict=True,
                )
            ]
            lines.append(f"- **{model}**: " + "; ".join(cells))
        wide_n = payload.get("wide_n", TOP_N)
        if wide_n > TOP_N:
            lines += [
                "",
                f"The same with the {wide_n} best particles per pair (the buffers' "
                f"{wide_n}; nominal [min,max] coverage "
                f"{(wide_n - 1) / (wide_n + 1):.3f}):",
                "",
                "| model | cov 50 % | cov 90 % | [min,max] cov | x wider (50 %) "
                "| w50 / prior | w90 / prior | p<0.01 |",
                "|---|---|---|---|---|---|---|---|",
            ]
            for model, e in block["models"].items():
                w = e["wide"]
                bad = [
                    p
                    for p, pv in zip(e["params"], w["pvalue"], strict=True)
                    if pv < 0.01
                ]
                lines.append(
                    f"| {model} | {np.mean(w['coverage']['0.5']):.2f} | "
                    f"{np.mean(w['coverage']['0.9']):.2f} | "
                    f"{np.mean(w['range_coverage']):.2f} | "
                    f"{_factor(w['width_factor']['0.5']['mean'])} | "
                    f"{np.mean(w['width_rel_prior']['0.5']):.2f} | "
                    f"{np.mean(w['width_rel_prior']['0.9']):.2f} | "
                    f"{', '.join(bad) or '-'} |"
                )
        lines += ["", f"![ranks {method}](sbc_ranks_{method}.png)", ""]
    lines += [
        "## How to read the figures",
        "",
        "`sbc_ranks_<method>.png`: one panel per model (row) and parameter, the "
        f"histogram over pairs of the truth's rank among the pair's {TOP_N} accepted "
        f"particles (0: all {TOP_N} above the truth, {TOP_N}: all below). The line is "
        "the count expected under an exact posterior (pairs / 6), the grey band its "
        "95 % binomial range. Flat: calibrated. A hump in the middle: the accepted "
        "particles are wider than the posterior (ABC's tolerance; the truth is "
        "inside them too often). A U: too narrow (over-confident), the truth falls "
        "outside. A slope: biased (the accepted particles sit above or below the "
        "truth). A parameter the data do not identify has a posterior near its "
        "prior and a flat histogram whatever the tolerance: read it together with "
        "its width relative to the prior (close to the prior's own 0.5 / 0.9 = "
        "nothing learned).",
        "",
    ]
    return "\n".join(lines)


def render(payload: dict) -> None:
    REPORTS.mkdir(parents=True, exist_ok=True)
    for method in payload["results"]["methods"]:
        figure(payload["results"], method, REPORTS / f"sbc_ranks_{method}.png")
    write_report(REPORTS / "sbc", payload, markdown(payload))


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS))
    parser.add_argument("--methods", nargs="+", default=["rejection", "smc"])
    parser.add_argument("--pairs", type=count, default=60)
    parser.add_argument("--steps", type=count, default=300)
    parser.add_argument("--per-pair", type=count, default=20000)
    parser.add_argument("--smc-per-pair", type=count, default=1000)
    parser.add_argument(
        "--wide-n", type=count, default=20, help="also rank among this many best"
    )
    parser.add_argument("--threads", type=count, default=1)
    parser.add_argument("--render", action="store_true")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    global REPORTS
    if args.out is not None:
        REPORTS = args.out
    if args.render:
        render(json.loads((REPORTS / "sbc.json").read_text()))
        return 0
    began = time.perf_counter()
    results = run(args)
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "pairs": args.pairs,
        "steps": args.steps,
        "top_n": TOP_N,
        "wide_n": args.wide_n,
        "levels": list(LEVELS),
        "wall_seconds": time.perf_counter() - began,
        "results": results,
    }
    render(payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
