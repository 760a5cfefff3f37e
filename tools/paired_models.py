"""Paired comparison of a run's models on its test pairs.

Per test pair, each model's minimum distance: the lowest score of its own
``top_n`` best per training pair on that pair (SPEC section 6's minimum
distance, one model at a time). For each comparison ``A:B`` (B usually A with
an effect): the mean over test pairs of ``log(min_B / min_A)`` (negative: B
covers the new pairs better), the pairs B covers better, and the one-sided
sign-flip p-value of "B is no better than A" (the test pairs are independent
of the training, so the test is exact). Pairs where either model has no valid
particle are left out and counted.

    python tools/paired_models.py RUN --compare idm:idm+lag gfm:gfm+delay \\
        --out reports/zalazone-dynamic/effects_on_test

Writes ``OUT.md`` and ``OUT.json``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.config import load_split  # noqa: E402
from torchcf.diagnose.significance import sign_flip_test  # noqa: E402
from torchcf.evaluation.evaluate import cost_matrices  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402


def minimum_distances(run: Path) -> tuple[dict[str, np.ndarray], int]:
    """Per model of the run, (n_test,) the best of its N best per training pair
    on every test pair (``+inf``: none valid); and the number of test pairs."""
    cfg = RunDir(run).read_config()
    _, test = load_split(cfg.data)
    posterior = torch.load(run / "posterior.pt", weights_only=False)
    top_n = posterior["top_n"]
    best = {}
    for model, buffer in posterior["buffers"].items():
        theta = buffer["theta"][:, :top_n].reshape(-1, buffer["theta"].shape[-1])
        score = buffer["score"][:, :top_n].reshape(-1)
        theta = theta[torch.isfinite(score)]
        cost = cost_matrices(
            get_model(model), theta, test, dtype=getattr(torch, cfg.dtype),
            weights=tuple(cfg.abc.weights),
        )["score"]  # fmt: skip
        best[model] = np.where(np.isfinite(cost), cost, np.inf).min(axis=0)
    return best, test.n_pairs


def compare(best: dict[str, np.ndarray], a: str, b: str, permutations: int) -> dict:
    """The paired comparison of ``b`` against ``a`` (module docstring)."""
    usable = np.isfinite(best[a]) & np.isfinite(best[b])
    ratio = np.log(best[b][usable] / best[a][usable])
    _, p_value = sign_flip_test(-ratio, permutations)
    return {
        "a": a,
        "b": b,
        "min_a": float(best[a][usable].mean()),
        "min_b": float(best[b][usable].mean()),
        "mean_log_ratio": float(ratio.mean()),
        "change": math.expm1(float(ratio.mean())),
        "better": int((ratio < 0).sum()),
        "pairs": int(usable.sum()),
        "left_out": int((~usable).sum()),
        "p_value": p_value,
    }


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# Models with and without an effect, on the test pairs",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"git {meta['git']}. Run `{payload['run']}`, {payload['n_test']} test "
        "pairs. Per test pair, each model's minimum distance (the best of its own "
        "N best per training pair); B against A: the geometric mean change of "
        "the per-pair minimum distance, the pairs B covers better, and the "
        "one-sided sign-flip p-value (B no better than A).",
        "",
        *(
            [f"The run was trained by `{payload['trained_by']}`.", ""]
            if payload.get("trained_by")
            else []
        ),
        "| A | B | min distance A | min distance B | change per pair | B better | p |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in payload["comparisons"]:
        lines.append(
            f"| {r['a']} | {r['b']} | {r['min_a']:.3f} | {r['min_b']:.3f} | "
            f"{r['change']:+.1%} | {r['better']} of {r['pairs']} | "
            f"{r['p_value']:.2g} |"
        )
    return "\n".join(lines) + "\n"


def _comparison(text: str) -> tuple[str, str]:
    """``A:B``, two variants of the run to compare."""
    a, _, b = text.partition(":")
    if not a or not b:
        raise argparse.ArgumentTypeError(f"expected A:B, got {text[:40]!r}")
    return a, b


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument(
        "--compare", nargs="+", required=True, metavar="A:B", type=_comparison
    )
    parser.add_argument("--permutations", type=count, default=20_000)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--trained-by",
        default=None,
        help="the command that trained RUN, for the report",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    pairs = args.compare
    best, n_test = minimum_distances(args.run)
    missing = sorted({m for pair in pairs for m in pair} - set(best))
    if missing:
        parser.error(f"not models of the run: {', '.join(missing)}")
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "run": str(args.run),
        "trained_by": args.trained_by,
        "n_test": n_test,
        "comparisons": [compare(best, a, b, args.permutations) for a, b in pairs],
    }
    write_report(args.out, payload, markdown(payload))
    print(markdown(payload))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
