"""Study: model recovery: does the hybrid name the model that made the data?

For each of the eight pool models, ``--pairs`` synthetic pairs driven by it with
parameters drawn from its uniform prior (one draw per pair, a spread of the
prior; ``tools/sbc_study.py``'s :func:`prior_pairs`: ``--steps`` steps at dt
0.1, measurement noise 0.05 m on the position). All ``8 x pairs`` pairs are
calibrated together with the eight models
(``torchcf.study.pipeline.train_and_evaluate``,
paired layout, top_n = 5, ``--per-pair`` particles per pair and model); the
per-pair buffers are independent across pairs, so this is the same as eight
runs. Per pair, the share of its 5 best held by each model (the hybrid's
per-pair model probability); the confusion matrix's row ``i`` is the mean share
over the pairs made by model ``i`` (:mod:`torchcf.evaluation.sbc`).

**Held out.** Each model's stream and buffers do not depend on the other models
(rejection and SMC alike), so the hybrid of the pool without model ``h`` is the
per-pair 5 best of the other seven buffers, built from the same run
(``torchcf.abc.hybrid.rank_per_pair``, the run's tie rule): exactly what a run
without ``h`` would keep. Its rows say what the hybrid calls a controller it does
not contain.

    python tools/model_recovery.py --threads 1
    python tools/model_recovery.py --render   # the report again from recovery.json

Writes ``reports/uncertainty/recovery.{json,md}`` and ``recovery_*.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402
from sbc_study import DT, NOISE, TOP_N, calibrate, join, prior_pairs  # noqa: E402

from torchcf.abc.hybrid import rank_per_pair  # noqa: E402
from torchcf.evaluation import sbc  # noqa: E402
from torchcf.posterior.tables import pair_slots  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "uncertainty"
MODELS = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")
SEED = 50_000


def slots(posterior, models: list[str]) -> np.ndarray:
    """(N, len(models)) per pair (pair id order), the slots of its ``top_n`` best
    across ``models`` alone, from the run's buffers and its tie rule."""
    n = posterior.top_n
    order = posterior.train_pair_ids.argsort()
    score = torch.stack([posterior.buffers[m]["score"][order, :n] for m in models])
    index = torch.stack([posterior.buffers[m]["index"][order, :n] for m in models])
    source = torch.arange(len(models))[:, None, None].expand_as(score)
    pair = torch.arange(score.shape[1])[None, :, None].expand_as(score)
    member, _ = rank_per_pair(
        score.reshape(-1),
        index.reshape(-1),
        source.reshape(-1),
        pair.reshape(-1),
        n,
    )
    return member.reshape(score.shape).sum(2).T.numpy()  # (N, M)


def best_score(posterior, models: list[str]) -> np.ndarray:
    """(N,) per pair (pair id order), the best score among ``models``' buffers."""
    order = posterior.train_pair_ids.argsort()
    score = torch.stack([posterior.buffers[m]["score"][order, 0] for m in models])
    return score.amin(0).numpy()


def summarise(shares: np.ndarray, label: np.ndarray, models: list[str]) -> dict:
    """Confusion matrix over the pool ``models`` (columns) for the generating
    models (rows, MODELS order), the top-1 rate and the per-pair shares."""
    matrix = sbc.confusion_matrix(shares, label, len(MODELS))
    top = np.nanargmax(np.where(np.isfinite(shares), shares, -1), 1)
    column = {m: i for i, m in enumerate(models)}
    hits = [
        float(np.mean(top[label == i] == column[g])) if g in column else None
        for i, g in enumerate(MODELS)
    ]
    return {
        "pool": models,
        "confusion": matrix.tolist(),
        "top1_rate": hits,
        "pairs_without_fit": int((~np.isfinite(shares).all(1)).sum()),
    }


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    began = time.perf_counter()
    made, label, truths = [], [], {}
    for k, model in enumerate(MODELS):
        pairs, truth = prior_pairs(model, args.pairs, args.steps, seed=SEED + 1000 * k)
        made.append(pairs)
        label += [k] * args.pairs
        truths[model] = truth.tolist()
    pairs = join(made, "synthetic-recovery")
    label = np.asarray(label)
    seconds_pairs = time.perf_counter() - began
    results = {"seconds_pairs": seconds_pairs, "label": label.tolist(), "methods": {}}
    for method in args.methods:
        per_pair = args.per_pair if method == "rejection" else args.smc_per_pair
        posterior, summary, seconds = calibrate(
            pairs, list(MODELS), method, per_pair * pairs.n_pairs, args.threads
        )
        full = slots(posterior, list(MODELS))
        order = posterior.train_pair_ids.argsort().numpy()
        # the buffers' merge must give back the run's own hybrid
        assert (full == pair_slots(posterior)[order]).all()
        shares = sbc.pair_shares(full)
        block = {
            "per_pair": per_pair,
            "seconds": seconds,
            "per_model_seconds": {m: summary.per_model[m].seconds for m in MODELS},
            "shares_run": summary.shares,
            "pair_shares": shares.tolist(),
            "all": summarise(shares, label, list(MODELS)),
            "held_out": {},
        }
        best = best_score(posterior, list(MODELS))
        for k, held in enumerate(MODELS):
            pool = [m for m in MODELS if m != held]
            entry = summarise(sbc.pair_shares(slots(posterior, pool)), label, pool)
            # how much worse the best fit of held's own pairs gets without it
            ratio = best_score(posterior, pool)[label == k] / best[label == k]
            entry["best_score_ratio_median"] = float(np.median(ratio))
            entry["best_score_ratio_range"] = [float(ratio.min()), float(ratio.max())]
            block["held_out"][held] = entry
        block["best_score_median"] = {
            g: float(np.median(best[label == k])) for k, g in enumerate(MODELS)
        }
        results["methods"][method] = block
        diag = np.diag(np.asarray(block["all"]["confusion"]))
        print(f"{method}: {seconds:.0f}s diag {np.round(diag, 2)}", flush=True)
    return results


# ------------------------------------------------------------------ the report
def heatmap(ax, matrix: np.ndarray, rows, cols, title: str) -> None:
    ax.imshow(matrix, vmin=0, vmax=1, cmap="viridis")
    ax.set_xticks(range(len(cols)), cols, rotation=45, fontsize=7)
    ax.set_yticks(range(len(rows)), rows, fontsize=7)
    for i in range(matrix.shape[0]):
        for j in range(matrix.shape[1]):
            value = matrix[i, j]
            if np.isfinite(value):
                ax.text(
                    j,
                    i,
                    f"{value:.2f}",
                    ha="center",
                    va="center",
                    fontsize=6,
                    color="white" if value < 0.5 else "black",
                )
    ax.set_xlabel("pool model (share of the pair's 5 best)", fontsize=7)
    ax.set_ylabel("generating model", fontsize=7)
    ax.set_title(title, fontsize=8)


def figures(payload: dict) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    label = np.asarray(payload["results"]["label"])
    for method, block in payload["results"]["methods"].items():
        fig, ax = plt.subplots(figsize=(5.2, 4.6))
        heatmap(
            ax,
            np.asarray(block["all"]["confusion"]),
            MODELS,
            MODELS,
            f"model recovery, {method}, {block['per_pair']} per pair",
        )
        fig.tight_layout()
        name = f"recovery_confusion_{method}.png"
        fig.savefig(REPORTS / name, dpi=130)
        plt.close(fig)
        written.append(name)
        # held out: row h = what the 7-model pool calls model h's pairs
        held = np.full((len(MODELS), len(MODELS)), np.nan)
        for i, h in enumerate(MODELS):
            entry = block["held_out"][h]
            for j, m in enumerate(entry["pool"]):
                held[i, MODELS.index(m)] = entry["confusion"][i][j]
        fig, ax = plt.subplots(figsize=(5.2, 4.6))
        heatmap(
            ax,
            held,
            MODELS,
            MODELS,
            f"generating model held out of the pool ({method})",
        )
        fig.tight_layout()
        name = f"recovery_held_out_{method}.png"
        fig.savefig(REPORTS / name, dpi=130)
        plt.close(fig)
        written.append(name)
        shares = np.asarray(block["pair_shares"], dtype=float)
        fig, ax = plt.subplots(figsize=(9, 2.8))
        bottom = np.zeros(len(shares))
        colors = plt.get_cmap("tab10")
        for j, m in enumerate(MODELS):
            ax.bar(
                range(len(shares)),
                np.nan_to_num(shares[:, j]),
                bottom=bottom,
                width=1.0,
                color=colors(j),
                label=m,
            )
            bottom += np.nan_to_num(shares[:, j])
        for k in range(1, len(MODELS)):
            ax.axvline(np.searchsorted(label, k) - 0.5, color="k", lw=0.8)
        ax.set_xticks(
            [np.mean(np.nonzero(label == k)[0]) for k in range(len(MODELS))],
            [f"made by {m}" for m in MODELS],
            fontsize=7,
        )
        ax.set_ylabel("share of the pair's 5 best", fontsize=7)
        ax.set_xlim(-0.5, len(shares) - 0.5)
        ax.legend(fontsize=6, ncol=8, loc="upper center", bbox_to_anchor=(0.5, 1.18))
        fig.tight_layout()
        name = f"recovery_pairs_{method}.png"
        fig.savefig(REPORTS / name, dpi=130)
        plt.close(fig)
        written.append(name)
    return written


def findings(res: dict) -> list[str]:
    """Per method: the diagonal, the largest confusions, and each held-out
    model's main stand-in."""
    out = []
    for method, block in res["methods"].items():
        matrix = np.asarray(block["all"]["confusion"])
        off = [
            (matrix[i, j], g, m)
            for i, g in enumerate(MODELS)
            for j, m in enumerate(MODELS)
            if i != j and matrix[i, j] >= 0.03
        ]
        off.sort(reverse=True)
        worst = int(np.argmin(np.diag(matrix)))
        out.append(
            f"- **{method}** ({block['per_pair']} per pair): the generating model "
            f"keeps {np.mean(np.diag(matrix)):.2f} of its pairs' slots on average "
            f"(lowest {MODELS[worst]} {matrix[worst, worst]:.2f}); confusions of 3 % "
            "or more: "
            + (", ".join(f"{g} -> {m} {v:.2f}" for v, g, m in off) or "none")
            + "."
        )
        stand = []
        for i, h in enumerate(MODELS):
            entry = block["held_out"][h]
            row = np.asarray(entry["confusion"][i])
            top = np.argsort(row)[::-1][:2]
            stand.append(
                f"{h} -> "
                + " + ".join(f"{entry['pool'][j]} {row[j]:.2f}" for j in top)
                + f" (best score x{entry['best_score_ratio_median']:.2f})"
            )
        out.append(f"- **{method}, held out**: " + "; ".join(stand) + ".")
    return out


def _row(cells) -> str:
    return "| " + " | ".join(cells) + " |"


def markdown(payload: dict) -> str:
    meta, res = payload["meta"], payload["results"]
    lines = [
        "# Model recovery: the hybrid's shares on pairs of a known model",
        "",
        f"`{meta['command']}`",
        "",
        f"- torch {meta['torch']}, threads {meta['threads']}, cpu {meta['cpu']}, "
        f"git {meta['git']}, total wall {payload['wall_seconds']:.0f} s",
        f"- {payload['pairs']} pairs per generating model ({8 * payload['pairs']} in "
        f"all), {payload['steps']} steps at dt {DT} s, noise {NOISE} m on the "
        "position, one prior draw per pair; the eight models calibrated on all "
        f"pairs together, paired layout, top_n = {TOP_N}",
        "",
        "Row: the model that made the pairs; column: the mean over those pairs of "
        "the share of the pair's 5 best particles held by each pool model (each "
        "row sums to 1). `top-1`: the fraction of the row's pairs on which the "
        "generating model holds the largest share (ties to the first model in the "
        "list).",
        "",
    ]
    lines += ["## Findings (computed)", "", *findings(res), ""]
    for method, block in res["methods"].items():
        matrix = np.asarray(block["all"]["confusion"])
        lines += [
            f"## {method} ({block['per_pair']} per pair and model, "
            f"{block['seconds']:.0f} s)",
            "",
            _row(["made by \\ share", *MODELS, "top-1"]),
            _row(["---"] * (len(MODELS) + 2)),
        ]
        for i, g in enumerate(MODELS):
            cells = [
                f"**{v:.2f}**" if i == j else f"{v:.2f}"
                for j, v in enumerate(matrix[i])
            ]
            lines.append(_row([g, *cells, f"{block['all']['top1_rate'][i]:.2f}"]))
        lines += [
            "",
            f"Mean diagonal {np.mean(np.diag(matrix)):.2f}; pairs without any fit: "
            f"{block['all']['pairs_without_fit']}.",
            "",
            f"### {method}: the generating model held out of the pool",
            "",
            "Row `h`: the pairs made by `h`, calibrated with the seven other models "
            "(the same buffers without `h`'s); `-` marks `h`'s own column.",
            "",
            _row(["held out \\ share", *MODELS, "best score x"]),
            _row(["---"] * (len(MODELS) + 2)),
        ]
        for i, h in enumerate(MODELS):
            entry = block["held_out"][h]
            cells = []
            for m in MODELS:
                if m == h:
                    cells.append("-")
                else:
                    cells.append(f"{entry['confusion'][i][entry['pool'].index(m)]:.2f}")
            low, high = entry["best_score_ratio_range"]
            cells.append(
                f"{entry['best_score_ratio_median']:.2f} ({low:.2f}-{high:.2f})"
            )
            lines.append(_row([h, *cells]))
        lines += [
            "",
            "`best score x`: on `h`'s pairs, the best score of the seven others over "
            "the best of all eight (its own, about the noise's), median over the "
            "pairs (range): how much worse the best stand-in fits.",
        ]
        for h in ("hl", "idm"):
            entry = block["held_out"][h]
            lines += [
                "",
                f"Without **{h}**, the whole matrix (all generating models) — rows "
                "whose generator is still in the pool show how much of it the "
                f"missing {h} took in the full pool:",
                "",
                _row(["made by \\ share", *entry["pool"]]),
                _row(["---"] * (len(entry["pool"]) + 1)),
            ]
            for i, g in enumerate(MODELS):
                lines.append(_row([g, *(f"{v:.2f}" for v in entry["confusion"][i])]))
        lines += [
            "",
            f"![confusion {method}](recovery_confusion_{method}.png)",
            f"![held out {method}](recovery_held_out_{method}.png)",
            f"![pairs {method}](recovery_pairs_{method}.png)",
            "",
        ]
    lines += [
        "## How to read the figures",
        "",
        "`recovery_confusion_<method>.png`: the table above as a heatmap; a "
        "perfect recovery is a bright diagonal. Off-diagonal mass in a row is what "
        "the hybrid credits to other models on that model's data: models that nest "
        "or mimic each other (e.g. LLCTG inside HL, LLCS and LLCTG; OVM inside GFM) "
        "share pairs because both fit within the noise, which is a statement about "
        "identifiability, not an error of the engine.",
        "",
        "`recovery_held_out_<method>.png`: row `h` is the pairs made by `h` "
        "calibrated without `h` (its own cell blank): which models the hybrid uses "
        "to stand in for a controller it does not contain.",
        "",
        "`recovery_pairs_<method>.png`: every pair's model probabilities (its share "
        "of its 5 best by model), one bar per pair, grouped by generating model: "
        "whether a row's mean share comes from every pair split alike or from some "
        "pairs won outright and others lost.",
        "",
    ]
    return "\n".join(lines)


def render(payload: dict) -> None:
    REPORTS.mkdir(parents=True, exist_ok=True)
    figures(payload)
    write_report(REPORTS / "recovery", payload, markdown(payload))


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=count, default=24)
    parser.add_argument("--steps", type=count, default=300)
    parser.add_argument("--methods", nargs="+", default=["rejection", "smc"])
    parser.add_argument("--per-pair", type=count, default=20000)
    parser.add_argument("--smc-per-pair", type=count, default=1000)
    parser.add_argument("--threads", type=count, default=1)
    parser.add_argument("--render", action="store_true")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    global REPORTS
    if args.out is not None:
        REPORTS = args.out
    if args.render:
        render(json.loads((REPORTS / "recovery.json").read_text()))
        return 0
    began = time.perf_counter()
    results = run(args)
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "pairs": args.pairs,
        "steps": args.steps,
        "top_n": TOP_N,
        "wall_seconds": time.perf_counter() - began,
        "results": results,
    }
    render(payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
