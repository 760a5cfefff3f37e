"""Benchmark: batched box-QP solver and the MPC rollout.

1. Microseconds per QP for MPC QPs drawn from the prior (``BoxQP`` at
   ``--batch`` instances, horizons 5 and 20, cold and warm-started from the
   previous solution of a moving state as the MPC does it, float32 and float64)
   against OSQP solving the same problems one at a time with its warm start, in
   the same run.
2. MPC rollout particle-steps per second on CAR MODEL II's training split
   (paired layout, float32).

    python tools/bench_qp.py                 # B = 1e5, 1e6 MPC particles
    python tools/bench_qp.py --batch 2e4 --mpc-particles 1e5

Writes ``reports/bench_qp.json`` and ``reports/bench_qp.md``.
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torchcf
from torchcf.models.mpc import MPC, mpc_qp_matrices
from torchcf.qp import BoxQP, QPStatus
from torchcf.system.process import tune_malloc

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import cpu_model, git_sha, write_report  # noqa: E402
from peer_numpy import quiet_stdout  # noqa: E402

from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"


def mpc_problems(n: int, horizon: int, n_steps: int, seed: int, dtype):
    """``n`` MPC particles from the prior and ``n_steps`` consecutive states each.

    The state ``z_0 = [spacing error, speed difference]`` drifts like a follower's
    in traffic (spacing error in about [-30, 40] m, dv in [-8, 8] m/s), so each
    step's QP is close to the previous one, as in a rollout.

    Returns:
        H (n, K, K), G (n, K, 2), amin (n,), amax (n,), z0 (n_steps, n, 2).
    """
    generator = torch.Generator().manual_seed(seed)
    bounds = MPC(horizon).prior_bounds(dtype)
    theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * torch.rand(
        n, 6, generator=generator, dtype=dtype
    )
    H, G = mpc_qp_matrices(theta[:, 0], theta[:, 1], theta[:, 2], 0.1, horizon)
    start = torch.stack(
        (
            -30 + 70 * torch.rand(n, generator=generator, dtype=dtype),
            -8 + 16 * torch.rand(n, generator=generator, dtype=dtype),
        ),
        dim=1,
    )
    drift = 0.3 * torch.randn(n_steps, n, 2, generator=generator, dtype=dtype)
    z0 = start[None] + drift.cumsum(0)
    return H, G, theta[:, 4], theta[:, 5], z0


def time_boxqp(H, G, amin, amax, z0, warm: bool, repeats: int):
    """Median seconds per step of BoxQP over the steps, and stats."""
    solver = BoxQP(H)
    n, horizon = H.shape[0], H.shape[1]
    lower = amin[:, None].expand(n, horizon)
    upper = amax[:, None].expand(n, horizon)
    times, active, admm, iterations = [], [], [], []
    for _ in range(repeats):
        previous = None
        for step in range(z0.shape[0]):
            q = torch.einsum("ckj,cj->ck", G, z0[step])
            x0 = guess = None
            if warm and previous is not None:
                # As the MPC does: the rest of the last plan, shifted by one step,
                # starts ADMM; the last plan itself guesses the active set.
                x0 = torch.cat((previous.x[:, 1:], previous.x[:, -1:]), dim=1)
                guess = previous.x
            start = time.perf_counter()
            result = solver.solve(q, lower, upper, x0=x0, active_guess=guess)
            elapsed = time.perf_counter() - start
            if step > 0 or not warm:  # a warm run's first step is cold
                times.append(elapsed)
                free = solver.unconstrained(q)
                outside = ((free < lower) | (free > upper)).any(1)
                active.append(float(outside.float().mean()))
                needed = result.n_iter > 0
                admm.append(float(needed.float().mean()))
                if bool(needed.any()):
                    iterations.append(float(result.n_iter[needed].float().mean()))
            assert bool((result.status == int(QPStatus.SOLVED)).all())
            previous = result
    return (
        statistics.median(times),
        float(np.mean(active)),
        float(np.mean(admm)),
        float(np.mean(iterations)) if iterations else 0.0,
    )


def time_osqp(H, G, amin, amax, z0, n_problems: int):
    """Seconds per QP of OSQP: one solver per particle, warm-started step to step."""
    per_qp = []
    with quiet_stdout():  # OSQP 1.x prints polishing notes even with verbose=False
        for j in range(n_problems):
            per_qp.append(_osqp_sequence(H[j], G[j], amin[j], amax[j], z0[:, j]))
    return statistics.median(per_qp)


def _osqp_sequence(H, G, amin, amax, z0) -> float:
    """Seconds per QP of one OSQP solver over one particle's states (setup excluded)."""
    import osqp
    import scipy.sparse as sparse

    horizon = H.shape[1]
    P = sparse.csc_matrix(np.triu(H.double().numpy()))
    A = sparse.identity(horizon, format="csc")
    lower = np.full(horizon, float(amin))
    upper = np.full(horizon, float(amax))
    solver = osqp.OSQP()
    solver.setup(
        P,
        (G.double() @ z0[0].double()).numpy(),
        A,
        lower,
        upper,
        verbose=False,
        eps_abs=1e-5,
        eps_rel=1e-5,
        warm_starting=True,
        polishing=True,
    )
    solver.solve(raise_error=False)
    start = time.perf_counter()
    for step in range(1, z0.shape[0]):
        solver.update(q=(G.double() @ z0[step].double()).numpy())
        solver.solve(raise_error=False)
    return (time.perf_counter() - start) / (z0.shape[0] - 1)


def _horizons(text: str) -> list[int]:
    """``"5,20"``: the horizons K, whole numbers >= 1."""
    return [count(k) for k in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=count, default=1e5)
    parser.add_argument("--steps", type=count, default=20)
    parser.add_argument("--osqp-problems", type=count, default=200)
    parser.add_argument("--mpc-particles", type=count, default=1e6)
    parser.add_argument(
        "--horizons", default="5,20", type=_horizons, help="comma-separated K"
    )
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--repeats", type=count, default=1)
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=REPORTS / "bench_qp")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    tune_malloc()
    batch = int(args.batch)

    rows = []
    for horizon in args.horizons:
        for dtype in (torch.float32, torch.float64):
            H, G, amin, amax, z0 = mpc_problems(batch, horizon, args.steps, 0, dtype)
            osqp_s = time_osqp(H, G, amin, amax, z0, args.osqp_problems)
            for warm in (False, True):
                step_s, active, admm, iters = time_boxqp(
                    H, G, amin, amax, z0, warm, args.repeats
                )
                row = {
                    "horizon": horizon,
                    "dtype": str(dtype).replace("torch.", ""),
                    "warm": warm,
                    "batch": batch,
                    "us_per_qp": 1e6 * step_s / batch,
                    "osqp_us_per_qp": 1e6 * osqp_s,
                    "speedup_vs_osqp": osqp_s / (step_s / batch),
                    "active_share": active,
                    "admm_share": admm,
                    "mean_admm_iterations": iters,
                }
                rows.append(row)
                print(json.dumps(row), flush=True)

    pairs = torchcf.load_pairs(
        "car-model-2",
        split="train",
        data_root=args.data_root,
        cleaning=torchcf.data.Cleaning(drop_duplicates=False),
    )
    n_mpc = int(args.mpc_particles)
    generator = torch.Generator().manual_seed(1)
    bounds = MPC().prior_bounds(torch.float32)
    theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * torch.rand(
        n_mpc, 6, generator=generator
    )
    index = torch.randint(0, pairs.n_pairs, (n_mpc,), generator=generator)
    start = time.perf_counter()
    out = torchcf.simulate(torchcf.get_model("mpc"), theta, pairs, index)
    mpc_s = time.perf_counter() - start
    rollout = {
        "particles": n_mpc,
        "steps": pairs.n_steps,
        "seconds": mpc_s,
        "particle_steps_per_s": n_mpc * pairs.n_steps / mpc_s,
        "invalid_fraction": float((~out.valid).float().mean()),
    }
    print(json.dumps(rollout), flush=True)

    meta = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": cpu_model(),
        "git": git_sha(),
        "osqp": __import__("osqp").__version__,
    }
    lines = [
        "# Batched box-QP solver and MPC rollout",
        "",
        f"`python tools/bench_qp.py --batch {args.batch:.0e} --steps {args.steps} "
        f"--osqp-problems {args.osqp_problems} --mpc-particles "
        f"{args.mpc_particles:.0e} --horizons "
        f"{','.join(map(str, args.horizons))} --threads "
        f"{args.threads} --repeats {args.repeats}`",
        "",
        *(f"- {key}: {value}" for key, value in meta.items()),
        "",
        f"MPC QPs from the prior, {args.steps} consecutive states per particle; "
        "torchcf "
        f"solves B = {batch} at once (median seconds per step / B); OSQP solves "
        f"{args.osqp_problems} particles' sequences one QP at a time with its warm "
        "start (eps 1e-5, polishing; setup excluded). torchcf's warm start is the "
        "MPC's: the last plan guesses the active set, and shifted by one step it "
        "starts ADMM.",
        "",
        "| K | dtype | warm start | us per QP | OSQP us per QP | speed-up | "
        "active bounds | needing ADMM | mean ADMM iterations |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['horizon']} | {r['dtype']} | {'yes' if r['warm'] else 'no'} | "
            f"{r['us_per_qp']:.3f} | {r['osqp_us_per_qp']:.1f} | "
            f"{r['speedup_vs_osqp']:.0f}x | {r['active_share']:.1%} | "
            f"{r['admm_share']:.2%} | "
            f"{r['mean_admm_iterations']:.1f} |"
        )
    lines += [
        "",
        "## MPC rollout",
        "",
        f"{n_mpc:.0e} MPC particles (K = 5), paired layout on CAR MODEL II training "
        f"({pairs.n_pairs} pairs x {pairs.n_steps} steps), float32: "
        f"{mpc_s:.1f} s, {rollout['particle_steps_per_s']:.3g} particle-steps/s.",
        "",
    ]
    payload = {"meta": meta, "qp": rows, "mpc_rollout": rollout}
    write_report(args.out, payload, "\n".join(lines))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
