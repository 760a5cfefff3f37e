"""Benchmark: the evaluation metrics against scipy's HiGHS on the same cost matrix.

For every size (particles x test pairs) one random score-like matrix
(``gamma(2, 1.5)``, so scores of about 0.1-15) is drawn, and in the same run

- ours: :func:`torchcf.evaluation.metrics.wasserstein`, ``beta_wasserstein(beta)``,
  ``min_distance`` and ``sinkhorn(reg)``, median of ``--repeats`` timed runs after
  one warm-up;
- linprog: ``scipy.optimize.linprog(method="highs")`` on the *original* LPs of SPEC
  section 6 (gamma (P x N) variables; pair marginals, total mass, particle
  marginals ``= 1/P`` or ``>= beta/P``), median of ``--repeats`` runs, or one run
  under ``--linprog-limit`` seconds for sizes above ``--single-run-cells`` cells
  (5000 x 1000 is a 5e6-variable LP), reported as ``> limit`` when cut off.

Sinkhorn is compared with the WS LP (its |difference| is the entropic gap).

A second section times the entropic solve alone, POT's
``ot.sinkhorn(method="sinkhorn_log")`` (one matrix at a time, at ``--threads`` and
at one thread) against ours (:func:`torchcf.evaluation.entropic.sinkhorn_log`,
over-relaxed, all matrices of a case in one batched call, and one at a time), on
the same matrices with the same ``reg`` and ``stopThr = 1e-9``: the random
matrices above, a structured one (``(x_i - y_j)^2`` of sorted points, ``--sqdist``
at ``--sqdist-reg``: plain Sinkhorn needs thousands of iterations there) and, with
``--run RUN_DIR``, the learned sets' cost matrices of a trained run (invalid cells
forbidden, the run's ``eval.sinkhorn_reg``). Medians of up to ``--repeats`` runs;
a solver whose runs pass ``--sinkhorn-budget`` seconds stops repeating.

    python tools/bench_metrics.py                         # 225x18 525x45 5000x1000
    python tools/bench_metrics.py --sizes 225x18 --out /tmp/bm
    python tools/bench_metrics.py --run runs/smoke --sinkhorn-only

Writes ``reports/bench_metrics.json`` and ``reports/bench_metrics.md``; with
``--sinkhorn-only`` the LP table is not rerun but kept from the existing JSON.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import ot
import scipy
import scipy.sparse as sp
import torch
from scipy.optimize import linprog

import torchcf
from torchcf.evaluation.entropic import sinkhorn_log
from torchcf.evaluation.metrics import (
    beta_wasserstein,
    min_distance,
    sinkhorn,
    wasserstein,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import cpu_model, git_sha, write_report  # noqa: E402

from torchcf.system.console import (  # noqa: E402
    OneLineParser,
    count,
    natural,
    open_fraction,
    positive,
    run_main,
)

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


# ---------------------------------------------------------------------------
# the entropic solve alone: POT against ours

#: Iterations allowed to both solvers: high enough never to bind here.
SINKHORN_MAX_ITER = 100_000
SINKHORN_STOP = 1e-9


def pot_solve(cost: np.ndarray, reg: float) -> dict:
    """POT's log-domain Sinkhorn: transport cost, iterations, marginal error."""
    n, m = cost.shape
    a = torch.full((n,), 1.0 / n, dtype=torch.float64)
    b = torch.full((m,), 1.0 / m, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        plan, log = ot.sinkhorn(
            a, b, torch.from_numpy(cost), reg, method="sinkhorn_log",
            numItermax=SINKHORN_MAX_ITER, stopThr=SINKHORN_STOP, log=True,
            warn=False,
        )  # fmt: skip
    error = float(log["err"][-1])
    return {
        "value": float((plan.numpy() * np.where(np.isfinite(cost), cost, 0.0)).sum()),
        "n_iter": int(log["niter"]) + 1,
        "converged": error < SINKHORN_STOP,
    }


def ours_solve(costs: list[np.ndarray], reg: float) -> list[dict]:
    plans = sinkhorn_log(costs, reg, max_iter=SINKHORN_MAX_ITER, stop_thr=SINKHORN_STOP)
    return [
        {"value": p.value, "n_iter": p.n_iter, "converged": p.converged} for p in plans
    ]


def time_budgeted(fn, repeats: int, budget: float, threads: int):
    """Median seconds of up to ``repeats`` runs of ``fn`` on ``threads`` torch
    threads, stopping early once the runs took ``budget`` seconds; the runs and
    the last output."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        times, out = [], None
        while len(times) < repeats and sum(times) <= budget:
            start = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - start)
    finally:
        torch.set_num_threads(before)
    return statistics.median(times), times, out


def squared_distances(n: int, m: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x, y = np.sort(rng.random(n)), np.sort(rng.random(m))
    return (x[:, None] - y[None, :]) ** 2


def run_costs(run_dir: Path) -> tuple[dict[str, np.ndarray], float]:
    """The learned sets' score matrices of a trained run on its test pairs
    (invalid rollouts at ``inf``, as the metrics see them), and its reg."""
    from torchcf.config import load_split
    from torchcf.evaluation.evaluate import EvaluationSettings, evaluate_posterior
    from torchcf.runs.directory import RunDir

    cfg, posterior, _ = RunDir(run_dir).load_run()
    test = load_split(cfg.data)[1]
    _, costs = evaluate_posterior(
        posterior, test, EvaluationSettings.of(cfg), progress=False
    )
    out = {}
    for name, c in costs.items():
        errors = np.stack([c["e_p"], c["e_v"], c["e_a"]])
        valid = np.isfinite(c["score"]) & np.isfinite(errors).all(axis=0)
        out[name] = np.where(valid, c["score"], np.inf)
    return out, cfg.eval.sinkhorn_reg


def sinkhorn_cases(args) -> list[tuple[str, list[str], list[np.ndarray], float]]:
    """(case, matrix names, matrices, reg): a trained run's sets (``--run``),
    the random matrices of the LP table, the structured one."""
    cases = []
    if args.run is not None:
        costs, reg = run_costs(args.run)
        cases.append(
            (f"learned sets of {args.run}", list(costs), list(costs.values()), reg)
        )
    for n_particles, n_test in args.sizes:
        name = f"random {n_particles}x{n_test}"
        cases.append((name, [name], [setup(n_particles, n_test, args.seed)], args.reg))
    n, m = args.sqdist
    name = f"squared distances {n}x{m}"
    cases.append((name, [name], [squared_distances(n, m, args.seed)], args.sqdist_reg))
    return cases


def bench_sinkhorn(args) -> list[dict]:
    return [bench_sinkhorn_case(*case, args) for case in sinkhorn_cases(args)]


def bench_sinkhorn_case(case, names, costs, reg, args) -> dict:
    """One case: POT one matrix at a time (``--threads``, then 1 thread), ours
    batched (and, for several matrices, one at a time), on the same matrices."""

    def pot():
        return [pot_solve(c, reg) for c in costs]

    def ours():
        return ours_solve(costs, reg)

    def ours_one_by_one():
        return [ours_solve([c], reg)[0] for c in costs]

    solvers = {"pot": (pot, args.threads), "pot_1thread": (pot, 1)}
    solvers["ours"] = (ours, args.threads)
    if len(costs) > 1:
        solvers["ours_one_by_one"] = (ours_one_by_one, args.threads)
    row = {"case": case, "names": names, "reg": reg, "n_matrices": len(costs)}
    row["shapes"] = [list(c.shape) for c in costs]
    outs = {}
    for key, (fn, threads) in solvers.items():
        seconds, runs, outs[key] = time_budgeted(
            fn, args.repeats, args.sinkhorn_budget, threads
        )
        row[f"{key}_s"], row[f"{key}_runs_s"] = seconds, runs
        print(f"sinkhorn {case}: {key} {seconds:.3g} s ({len(runs)} runs)", flush=True)
    pot_out, ours_out = outs["pot"], outs["ours"]
    row["pot_iters"] = [r["n_iter"] for r in pot_out]
    row["ours_iters"] = [r["n_iter"] for r in ours_out]
    row["all_converged"] = all(r["converged"] for r in pot_out + ours_out)
    row["max_rel_diff"] = max(
        abs(o["value"] - p["value"]) / abs(p["value"])
        for o, p in zip(ours_out, pot_out, strict=True)
    )
    row["speedup"] = row["pot_s"] / row["ours_s"]
    row["speedup_1thread"] = row["pot_1thread_s"] / row["ours_s"]
    return row


def _iterations(counts: list[int]) -> str:
    return str(counts[0]) if len(counts) == 1 else f"{sum(counts)} (max {max(counts)})"


def _heading(title: str, command: str, meta: dict) -> list[str]:
    """A report section's first lines: its title, the command, the run's meta."""
    return [
        title,
        "",
        f"`{command}`",
        "",
        *(f"- {k}: {v}" for k, v in meta.items()),
        "",
    ]


def sinkhorn_markdown(rows, meta, command, args) -> str:
    lines = [
        *_heading("## Sinkhorn: POT vs ours (the entropic solve alone)", command, meta),
        f"| case | reg | POT [s] ({args.threads} threads) | POT [s] (1 thread) "
        "| ours [s] | ours one at a time [s] | iterations POT | iterations ours "
        "| max rel. diff. | all converged |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        one = fmt_seconds(r["ours_one_by_one_s"]) if "ours_one_by_one_s" in r else "="
        lines.append(
            f"| {r['case']} | {r['reg']:g} | {fmt_seconds(r['pot_s'])} "
            f"| {fmt_seconds(r['pot_1thread_s'])} | {fmt_seconds(r['ours_s'])} "
            f"| {one} | {_iterations(r['pot_iters'])} | {_iterations(r['ours_iters'])} "
            f"| {r['max_rel_diff']:.1e} | {'yes' if r['all_converged'] else 'no'} |"
        )
    for r in rows:
        if r["n_matrices"] > 1:
            per = ", ".join(
                f"{n} {p}/{o}"
                for n, p, o in zip(
                    r["names"], r["pot_iters"], r["ours_iters"], strict=True
                )
            )
            lines += ["", f"Iterations POT/ours per matrix ({r['case']}): {per}."]
    lines += [
        "",
        "Both stop at a pair-marginal L2 error below 1e-9 (tested every 10 "
        "iterations) from the same start. POT runs one matrix at a time; ours "
        "solves a case's matrices in one "
        "batched call (`ours`) and one at a time. Ours picks one torch thread "
        "below 2^18 cells per call (on a loaded machine every parallel op waits "
        "for a descheduled thread) and otherwise runs on the given threads; the "
        "POT columns show both settings. Iterations: a case's total over its "
        "matrices (max: the longest, which bounds the batched solve). Times are "
        "medians of the runs listed in the JSON. Max rel. diff.: "
        "|ours - POT| / POT of the transport cost <gamma, C>.",
        "",
    ]
    return "\n".join(lines)


def fmt_seconds(seconds: float) -> str:
    return f"{seconds:.3g}"


def load_average() -> str:
    """The 1-minute load average when the benchmark ended (a loaded machine
    slows multi-threaded torch most)."""
    try:
        return Path("/proc/loadavg").read_text().split()[0]
    except OSError:
        return "unknown"


def markdown(rows, meta, command, args) -> str:
    lines = [
        *_heading("# Evaluation metrics vs scipy linprog (HiGHS)", command, meta),
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
        "ours: `torchcf.evaluation.metrics` at the commit above (WS and beta-WS by "
        "POT's network simplex, beta-WS reduced to a balanced (P + 1) x N problem; "
        "minimum distance in closed form; Sinkhorn log-domain in float64 torch: "
        "POT's `ot.sinkhorn` up to commit 7bb6e03, then our over-relaxed batched "
        "solver, see the next section). linprog: "
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
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes", nargs="+", type=parse_size, default=DEFAULT_SIZES, help="PxN"
    )
    parser.add_argument("--repeats", type=count, default=5)
    parser.add_argument("--beta", type=open_fraction, default=0.15)
    parser.add_argument("--reg", type=positive, default=0.05)
    parser.add_argument("--seed", type=natural, default=0)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument(
        "--linprog-limit",
        type=positive,
        default=600.0,
        help="HiGHS time limit per LP [s]",
    )
    parser.add_argument(
        "--single-run-cells",
        type=count,
        default=1e6,
        help="above this many cells linprog runs once (ours at most 3 times)",
    )
    parser.add_argument("--out", type=Path, default=REPORTS / "bench_metrics")
    parser.add_argument(
        "--run", type=Path, default=None, help="a trained run: its sets' Sinkhorn"
    )
    parser.add_argument(
        "--sqdist", type=parse_size, default=(500, 300), help="structured case PxN"
    )
    parser.add_argument("--sqdist-reg", type=positive, default=1e-3)
    parser.add_argument(
        "--sinkhorn-budget",
        type=positive,
        default=30.0,
        help="a Sinkhorn solver stops repeating once its runs took this long [s]",
    )
    parser.add_argument(
        "--sinkhorn-only",
        action="store_true",
        help="skip the LP table (kept from the existing --out JSON)",
    )
    args = parser.parse_args(argv)
    args.sizes = [parse_size(s) if isinstance(s, str) else s for s in args.sizes]
    command = "python tools/bench_metrics.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )

    # Sinkhorn runs on torch tensors: pin its threads like the other benchmarks.
    torch.set_num_threads(args.threads)
    sinkhorn_rows = bench_sinkhorn(args)
    if args.sinkhorn_only:
        previous = json.loads(args.out.with_suffix(".json").read_text())
        lp = {key: previous[key] for key in ("meta", "command", "rows")}
        # the kept table is rendered with the options it was measured with
        lp_args = parser.parse_args(shlex.split(lp["command"])[2:])
    else:
        rows = []
        for n_particles, n_test in args.sizes:
            rows += bench_size(n_particles, n_test, args)
        lp = {"meta": None, "command": command, "rows": rows}
        lp_args = args

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
    if lp["meta"] is None:
        lp["meta"] = meta
    sinkhorn_meta = {**meta, "load": load_average()}
    payload = {
        **lp,
        "sinkhorn": {"meta": sinkhorn_meta, "command": command, "rows": sinkhorn_rows},
    }
    write_report(
        args.out,
        payload,
        markdown(lp["rows"], lp["meta"], lp["command"], lp_args)
        + "\n"
        + sinkhorn_markdown(sinkhorn_rows, sinkhorn_meta, command, args),
    )
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
