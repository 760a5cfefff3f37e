"""A simulation demo: each model's prior particles on CAR MODEL II training pairs.

    python -m torchcf.demo [--particles 200000] [--dataset NAME] [--data-root DIR]

Draws particles uniformly from each model's default prior, simulates each on one
randomly chosen training pair (the paper's down-sampled layout), and prints per
model the best and median score, the invalid fraction and the throughput. This is
the engine underneath ABC; ``python -m torchcf.train`` builds on it.
"""

from __future__ import annotations

import argparse
import time

import torch

from . import MODELS, load_pairs, simulate
from .cli import DefaultsHelpFormatter, run_main
from .runtime import tune_malloc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        formatter_class=DefaultsHelpFormatter,
        prog="python -m torchcf.demo",
        description=__doc__.splitlines()[0],
    )
    parser.add_argument("--particles", type=int, default=200_000)
    parser.add_argument("--dataset", default="car-model-2")
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    if args.particles <= 0:
        parser.error(f"--particles must be positive, got {args.particles}")
    if args.threads:
        torch.set_num_threads(args.threads)
    tune_malloc()
    return run_main(lambda: _demo(args))


def _demo(args: argparse.Namespace) -> int:
    """Simulate and print the table (module docstring)."""
    pairs = load_pairs(args.dataset, split="train", data_root=args.data_root)
    print(
        f"{pairs.name} train: {pairs.n_pairs} pairs x {pairs.n_steps} steps "
        f"(dt {pairs.dt} s); {args.particles} particles per model, paired layout"
    )
    print(f"{'model':6s} {'best':>8s} {'median':>8s} {'invalid':>8s} {'steps/s':>10s}")
    generator = torch.Generator().manual_seed(args.seed)
    for name, model in MODELS.items():
        bounds = model.prior_bounds(torch.float32)
        unit = torch.rand(args.particles, model.n_params, generator=generator)
        theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * unit
        pair_index = torch.randint(
            0, pairs.n_pairs, (args.particles,), generator=generator
        )
        start = time.perf_counter()
        out = simulate(name, theta, pairs, pair_index)
        elapsed = time.perf_counter() - start
        valid_scores = out.score[out.valid]
        best = float(valid_scores.min()) if valid_scores.numel() else float("inf")
        median = float(valid_scores.median()) if valid_scores.numel() else float("inf")
        print(
            f"{name:6s} {best:8.3f} {median:8.3f} "
            f"{float((~out.valid).float().mean()):8.3%} "
            f"{args.particles * pairs.n_steps / elapsed:10.3g}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
