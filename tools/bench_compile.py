"""Benchmark: what ``torch.compile`` costs a first run, and what it buys.

The cold start of a paper-scale run is mostly compilation (``reports/bench/
train_carII.md``: 206 s on an empty compile cache, 80 s on a full one). This
measures, per model and per fused block length (``torchcf.sim.rollout.BLOCK_STEPS``,
the time steps one compiled call unrolls), in a fresh process with an empty
inductor cache each:

- the first compiled call on 2^18 paired particles of CAR MODEL II's training
  pairs (compilation plus one run),
- a second call (the run alone: compiled throughput),
- the same call eager (no compilation),

and so the particles per model above which compiling pays on a cold cache:
``compile time / (1 / eager rate - 1 / compiled rate)``. The results of every
variant are compared (the score sum over valid particles): compiled results do
not depend on the block length; eager ones differ by rounding.

    python tools/bench_compile.py                     # idm, hl, llctg x 16, 8, 4, 1
    python tools/bench_compile.py --models idm --blocks 16 8
    python tools/bench_compile.py --device cuda --particles 8388608 --blocks 8 \
        --out reports/bench/compile_cuda_h100   # on a GPU: where compiling pays
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402

from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports" / "bench"
PARTICLES = 1 << 18

#: One measurement, run in a child process (an empty inductor cache each).
_CHILD = """
import json, logging, sys, time
import torch
logging.disable(logging.WARNING)
import torchcf, torchcf.sim.rollout as sim
name = sys.argv[1]
block, threads, n = (int(a) for a in sys.argv[2:5])
device = sys.argv[5]
sim.BLOCK_STEPS = block
torch.set_num_threads(threads)
pairs = torchcf.load_pairs("car-model-2", split="train")
model = torchcf.MODELS[name]
low, high = model.prior_bounds(torch.float32).unbind(1)
g = torch.Generator().manual_seed(0)
theta = low + (high - low) * torch.rand(n, model.n_params, generator=g)
index = torch.randint(0, pairs.n_pairs, (n,), generator=g)
def timed(compile):
    run = torchcf.Execution(device=device, compile=compile)
    start = time.perf_counter()
    out = torchcf.simulate(model, theta, pairs, index, execution=run)
    return time.perf_counter() - start, float(out.score[out.valid].double().sum())
first, check_first = timed(True)
second, check_second = timed(True)
eager, check_eager = timed(False)
print(json.dumps({"first": first, "run": second, "eager": eager,
                  "checks": [check_first, check_second, check_eager]}))
"""


def measure(model: str, block: int, threads: int, particles: int, device: str) -> dict:
    """One (model, block) in a fresh process with an empty inductor cache."""
    with tempfile.TemporaryDirectory(prefix="torchcf-inductor-") as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
        done = subprocess.run(
            [sys.executable, "-c", _CHILD, model, str(block), str(threads),
             str(particles), device],
            capture_output=True, text=True, env=env, check=True,
        )  # fmt: skip
    row = json.loads(done.stdout.strip().splitlines()[-1])
    compile_s = row["first"] - row["run"]
    compiled_rate, eager_rate = particles / row["run"], particles / row["eager"]
    saved_per_particle = 1 / eager_rate - 1 / compiled_rate
    return {
        "model": model,
        "block": block,
        "compile_s": compile_s,
        "compiled_particles_per_s": compiled_rate,
        "eager_particles_per_s": eager_rate,
        "break_even_particles": compile_s / saved_per_particle
        if saved_per_particle > 0
        else None,
        "compiled_check": row["checks"][0],
        "eager_relative_difference": abs(row["checks"][2] - row["checks"][0])
        / abs(row["checks"][0]),
        **row,
    }


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# Compilation: its cost on a cold cache, its gain per particle",
        "",
        provenance(meta) + f". CAR MODEL II training pairs (44 x 576 "
        f"steps), {payload['particles']} paired particles per call on "
        f"{payload['device']}, float32; each row in a "
        "fresh process with an empty inductor cache. *Compile*: first compiled "
        "call minus the second; *break-even*: particles per model above which "
        "compiling pays on a cold cache.",
        "",
        "| model | block steps | compile [s] | compiled [particles/s] | eager "
        "[particles/s] | 1e6 compiled / eager [s] | break-even [particles] | "
        "compiled result as block 16 | eager vs compiled |",
        "|---|---|---|---|---|---|---|---|",
    ]
    reference = {
        r["model"]: r["compiled_check"] for r in payload["rows"] if r["block"] == 16
    }
    for r in payload["rows"]:
        even = r["break_even_particles"]
        same = reference.get(r["model"])
        same = (
            "n/a" if same is None else ("yes" if same == r["compiled_check"] else "NO")
        )
        lines.append(
            f"| {r['model']} | {r['block']} | {r['compile_s']:.1f} | "
            f"{r['compiled_particles_per_s']:.3g} | {r['eager_particles_per_s']:.3g} | "
            f"{1e6 / r['compiled_particles_per_s']:.2g} / "
            f"{1e6 / r['eager_particles_per_s']:.2g} | "
            f"{f'{even:.3g}' if even else 'never'} | {same} | "
            f"{r['eager_relative_difference']:.1e} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["idm", "hl", "llctg"])
    parser.add_argument("--blocks", nargs="+", type=count, default=[16, 8, 4, 1])
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--particles", type=count, default=PARTICLES, help="per call")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=REPORTS / "compile")
    args = parser.parse_args(argv)
    rows = []
    for model in args.models:
        for block in args.blocks:
            rows.append(
                measure(model, block, args.threads, args.particles, args.device)
            )
            r = rows[-1]
            print(
                f"{model} block {block}: compile {r['compile_s']:.1f} s, "
                f"{r['compiled_particles_per_s']:.3g} vs eager "
                f"{r['eager_particles_per_s']:.3g} particles/s",
                flush=True,
            )
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "particles": args.particles,
        "device": args.device,
        "rows": rows,
    }
    write_report(args.out, payload, markdown(payload))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
