"""Benchmark: the evaluation metrics against scipy's HiGHS on the same cost matrix.

For every size (particles x test pairs) one random score-like matrix
(``gamma(2, 1.5)``, so scores of about 0.1-15) is drawn, and in the same run

- ours: :func:`torchcf.metrics.wasserstein`, ``beta_wasserstein(beta)``,
  ``min_distance`` and ``sinkhorn(reg)``, median of ``--repeats`` timed runs after
  one warm-up;
- linprog: ``scipy.optimize.linprog(method="highs")`` on the *original* LPs of SPEC
  section 6 (gamma (P x N) variables; pair marginals, total mass, particle
  marginals ``= 1/P`` or ``>= beta/P``), median of ``--repeats`` runs, or one run
  under ``--linprog-limit`` seconds for sizes above ``--single-run-cells`` cells
  (5000 x 1000 is a 5e6-variable LP), reported as ``> limit`` when cut off.

Sinkhorn is compared with the WS LP (its |difference| is the entropic gap).

    python tools/bench_metrics.py                         # 225x18 525x45 5000x1000
    python tools/bench_metrics.py --sizes 225x18 --out /tmp/bm

Writes ``reports/bench_metrics.json`` and ``reports/bench_metrics.md``.
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import ot
import scipy
import scipy.sparse as sp
import torch
from scipy.optimize import linprog

import torchcf
from torchcf.evaluation.metrics import (
    beta_wasserstein,
    min_distance,
    sinkhorn,
    wasserstein,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import cpu_model, git_sha, write_report  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
DEFAULT_SIZES = ["225x18", "525x45", "5000x1000"]


def parse_size(text: str) -> tuple[int, int]:
    try:
        n_particles, n_test = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be PxN, got {text!r}") from None
    return n_particles, n_test


def setup(n_particles: int, n_test: int, seed: int = 0) -> np.ndarray:
    """A (P, N) score-like cost matrix: positive, right-skewed, no ties."""
    return np.random.default_rng(seed).gamma(2.0, 1.5, size=(n_particles, n_test))


def solve_lp(cost: np.ndarray, beta: float | None, time_limit: float) -> dict:
    """The original LP by HiGHS: WS (``beta is None``) or beta-WS.

    Returns:
        ``{"value", "seconds", "status", "message"}``; ``value`` is None unless
        HiGHS proved optimality (status 1 = time or iteration limit).
    """
    n, m = cost.shape
    start = time.perf_counter()
    # The matrix build is part of what a user of linprog pays, so it is timed.
    rows_of = sp.kron(sp.eye(n, format="csr"), np.ones((1, m)), format="csr")
    cols_of = sp.kron(np.ones((1, n)), sp.eye(m, format="csr"), format="csr")
    a_eq = [cols_of, sp.csr_matrix(np.ones((1, n * m)))]
    b_eq = [np.full(m, 1.0 / m), [1.0]]
    a_ub = b_ub = None
    if beta is None:
        a_eq.append(rows_of)
        b_eq.append(np.full(n, 1.0 / n))
    else:
        a_ub, b_ub = -rows_of, np.full(n, -beta / n)
    res = linprog(
        cost.ravel(),
        A_ub=a_ub,
        b_ub=b_ub,
        A_eq=sp.vstack(a_eq, format="csr"),
        b_eq=np.concatenate(b_eq),
        bounds=(0, None),
        method="highs",
        options={"time_limit": float(time_limit)},
    )
    return {
        "value": float(res.fun) if res.status == 0 else None,
        "seconds": time.perf_counter() - start,
        "status": int(res.status),
        "message": str(res.message),
    }


def time_ours(fn, repeats: int):
    """Median seconds of ``repeats`` runs after one warm-up, and the last output."""
    out = fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times, out


def time_lp(cost, beta, repeats: int, time_limit: float) -> dict:
    runs = [solve_lp(cost, beta, time_limit) for _ in range(repeats)]
    best = runs[-1]
    return {
        **best,
        "seconds": statistics.median(r["seconds"] for r in runs),
        "runs_s": [r["seconds"] for r in runs],
        "hit_limit": any(r["status"] == 1 for r in runs),
    }


def bench_size(n_particles, n_test, args) -> list[dict]:
    cost = setup(n_particles, n_test, args.seed)
    single = n_particles * n_test > args.single_run_cells
    lp_repeats = 1 if single else args.repeats
    ours_repeats = min(args.repeats, 3) if single else args.repeats
    lps = {}
    for key, beta in (("ws", None), ("beta_ws", args.beta), ("min", 0.0)):
        lps[key] = time_lp(cost, beta, lp_repeats, args.linprog_limit)
        print(
            f"{n_particles}x{n_test} linprog {key}: {lps[key]['seconds']:.3g} s "
            f"(status {lps[key]['status']})",
            flush=True,
        )
    ours = {
        "ws": lambda: wasserstein(cost),
        "beta_ws": lambda: beta_wasserstein(cost, args.beta),
        "min": lambda: min_distance(cost),
        "sinkhorn": lambda: sinkhorn(cost, args.reg),
    }
    rows = []
    for metric, fn in ours.items():
        seconds, runs, out = time_ours(fn, ours_repeats)
        value = out if isinstance(out, float) else out.value
        lp = lps["ws" if metric == "sinkhorn" else metric]
        row = {
            "n_particles": n_particles,
            "n_test": n_test,
            "metric": metric,
            "ours_s": seconds,
            "ours_runs_s": runs,
            "ours_value": value,
            "linprog_s": lp["seconds"],
            "linprog_runs_s": lp["runs_s"],
            "linprog_value": lp["value"],
            "linprog_status": lp["status"],
            "linprog_hit_limit": lp["hit_limit"],
            "linprog_reference": "ws" if metric == "sinkhorn" else metric,
            "speedup": lp["seconds"] / seconds if not lp["hit_limit"] else None,
            "abs_diff": abs(value - lp["value"]) if lp["value"] is not None else None,
        }
        if metric == "sinkhorn":
            row.update(
                sinkhorn_converged=out.converged,
                sinkhorn_iters=out.n_iter,
                sinkhorn_gap=out.gap,
            )
        rows.append(row)
        print(
            f"{n_particles}x{n_test} ours {metric}: {seconds:.3g} s, "
            f"value {value:.12g}",
            flush=True,
        )
    return rows


def fmt_seconds(seconds: float) -> str:
    return f"{seconds:.3g}"


def markdown(rows, meta, command, args) -> str:
    lines = [
        "# Evaluation metrics vs scipy linprog (HiGHS)",
        "",
        f"`{command}`",
        "",
        *(f"- {key}: {value}" for key, value in meta.items()),
        "",
        "| size (P x N) | metric | ours [s] | linprog [s] | speed-up "
        "| abs. difference |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        size = f"{r['n_particles']} x {r['n_test']}"
        lp = (
            f"> {args.linprog_limit:g}"
            if r["linprog_hit_limit"]
            else fmt_seconds(r["linprog_s"])
        )
        speedup = (
            f"> {args.linprog_limit / r['ours_s']:.3g}x"
            if r["linprog_hit_limit"]
            else f"{r['speedup']:.3g}x"
        )
        diff = "n/a" if r["abs_diff"] is None else f"{r['abs_diff']:.2e}"
        metric = r["metric"]
        if metric == "sinkhorn":
            metric += f" (reg {args.reg:g}, vs WS LP)"
        elif metric == "beta_ws":
            metric += f" (beta {args.beta:g})"
        lines.append(
            f"| {size} | {metric} | {fmt_seconds(r['ours_s'])} | {lp} | {speedup} "
            f"| {diff} |"
        )
    lines += [
        "",
        "ours: `torchcf.metrics` (WS and beta-WS by POT's network simplex, beta-WS "
        "reduced to a balanced (P + 1) x N problem; minimum distance in closed form; "
        "Sinkhorn log-domain through POT on float64 torch tensors). linprog: "
        "`scipy.optimize.linprog(method='highs')` on the original LPs, matrix "
        "build included. Times are medians of the runs listed in the JSON; sizes "
        f"above {args.single_run_cells:.0e} cells run linprog once under a "
        f"{args.linprog_limit:g} s limit. The Sinkhorn difference is its gap to "
        "the exact WS, not an error; the Sinkhorn time includes "
        "that exact WS solve (`sinkhorn()` returns both).",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", nargs="+", type=parse_size, default=DEFAULT_SIZES, help="PxN"
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--beta", type=float, default=0.15)
    parser.add_argument("--reg", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--linprog-limit",
        type=float,
        default=600.0,
        help="HiGHS time limit per LP [s]",
    )
    parser.add_argument(
        "--single-run-cells",
        type=float,
        default=1e6,
        help="above this many cells linprog runs once (ours at most 3 times)",
    )
    parser.add_argument("--out", type=Path, default=REPORTS / "bench_metrics")
    args = parser.parse_args(argv)
    sizes = [parse_size(s) if isinstance(s, str) else s for s in args.sizes]
    command = "python tools/bench_metrics.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )

    # Sinkhorn runs on torch tensors: pin its threads like the other benchmarks.
    torch.set_num_threads(args.threads)
    rows = []
    for n_particles, n_test in sizes:
        rows += bench_size(n_particles, n_test, args)

    meta = {
        "torch": torch.__version__,
        "pot": ot.__version__,
        "scipy": scipy.__version__,
        "numpy": np.__version__,
        "torchcf": torchcf.__version__,
        "python": sys.version.split()[0],
        "threads": torch.get_num_threads(),
        "cpu": cpu_model(),
        "git": git_sha(),
        "repeats": args.repeats,
        "costs": f"gamma(2, 1.5) per cell, seed {args.seed}",
    }
    write_report(
        args.out,
        {"meta": meta, "command": command, "rows": rows},
        markdown(rows, meta, command, args),
    )
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
