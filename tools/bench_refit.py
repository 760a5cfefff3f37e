"""Benchmark: a held-out pair's refit (validation "refit"), its cost and depth
by design.

The loop judges an effect arm by refitting every held-out pair twice, without
the effect and with it pinned (:mod:`torchcf.diagnose.arms.refit`). Its budget is
``slots`` particles per pair, ``copies`` perturbed copies of each per round and
``rounds`` rounds: a round costs held-out pairs x slots x copies rollouts. This
times both sides of one comparison, on the loop's own held-out rollout, for:

- **6 rounds, 20 slots**: the refit with ``abc.top_n`` slots and six rounds;
- **24 rounds, 20 slots**: the same, four times as deep;
- **calm, 5 slots** (the default): ``diagnose.refit_slots`` 5, until two
  rounds in a row gain less than 0.2 %, at most 24 rounds.

The data: 50 training pairs (30-50 s, 0.1 m position noise) whose followers
are IDM and GFM drivers each with their own parameters drawn over the priors,
all perceiving their leader 0.8 s late (``torchcf.sim.synthetic.
heterogeneous_pairs``); the loop's split gives 20 held-out pairs. The
candidates are 300 prior draws of each model (a refit's start from an arm's
picks, without the arm's search). Reports each design's median time over
``--repeats`` and, as the depth it reaches, the held-out pairs' summed best
score without and with the delay pinned at 0.8 s and the gain between them.

    python tools/bench_refit.py [--repeats 3] [--threads 1]

Writes ``reports/bench/refit.{json,md}``.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402

from torchcf.config import validate_config  # noqa: E402
from torchcf.diagnose.arms.refit import Pin, RefitBudget, refit_scores  # noqa: E402
from torchcf.diagnose.arms.validation import design  # noqa: E402
from torchcf.diagnose.setup import LoopSetup  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.models.effects import parse_effect  # noqa: E402
from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
POOL = ("idm", "gfm")
#: (label, budget): the designs compared (copies: ``local_copies / 2``).
DESIGNS = (
    ("6 rounds, 20 slots", RefitBudget(slots=20, copies=16, rounds=6)),
    ("24 rounds, 20 slots", RefitBudget(slots=20, copies=16, rounds=24)),
    ("calm, 5 slots", RefitBudget(slots=5, copies=16, rounds=24, until_calm=True)),
)
CANDIDATES = 300


def held_out_rollout():
    """The loop's held-out rollout on 50 heterogeneous delayed pairs."""
    late = DriverMixture(list(POOL), "delay", [0.8])
    pairs, _ = heterogeneous_pairs(late, 50, 500, seed=0, noise=0.1, lengths=(0.6, 1.0))
    cfg = validate_config(
        {"data": {"path": "synthetic"}, "models": list(POOL), "compile": "off"}
    )
    _, validation = design(LoopSetup.of(cfg), pairs, seed=0)
    priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
    return validation.rollout, priors


def candidates() -> dict:
    """``CANDIDATES`` prior draws of each pool model, (Q, K) float64."""
    g = torch.Generator().manual_seed(1)
    out = {}
    for name in POOL:
        model = get_model(name)
        box = model.prior_bounds(torch.float64)
        u = torch.rand(CANDIDATES, model.n_params, generator=g, dtype=torch.float64)
        out[model] = box[:, 0] + u * (box[:, 1] - box[:, 0])
    return out


def measure(repeats: int) -> list[dict]:
    rollout, priors = held_out_rollout()
    members = candidates()
    pin = Pin(parse_effect("delay"), torch.tensor([0.8], dtype=torch.float64))
    rows = []
    for label, budget in DESIGNS:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            without = refit_scores(members, rollout, budget, priors, {}, ("b", 0))
            with_pin = refit_scores(members, rollout, budget, priors, {}, ("b", 0), pin)
            times.append(time.perf_counter() - start)
        before, after = float(without.sum()), float(with_pin.sum())
        rows.append(
            {
                "design": label,
                "slots": budget.slots,
                "copies": budget.copies,
                "rounds": budget.rounds,
                "until_calm": budget.until_calm,
                "seconds": statistics.median(times),
                "seconds_all": times,
                "held_out_pairs": int(without.shape[0]),
                "summed_without": before,
                "summed_with": after,
                "gain": (before - after) / before,
            }
        )
        print(f"{label}: {rows[-1]['seconds']:.1f} s, gain {rows[-1]['gain']:+.1%}")
    return rows


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# A held-out pair's refit: cost and depth by design",
        "",
        provenance(meta) + ". Both sides of one comparison (without "
        "the effect, and with the delay pinned at 0.8 s) on the loop's 20 held-out "
        "pairs of 50 heterogeneous IDM/GFM drivers 0.8 s late, from 300 prior "
        "draws per model; median of the repeats (`tools/bench_refit.py`).",
        "",
        "| design | slots x copies | rounds | time [s] (median) | summed best "
        "without | with delay 0.8 s | gain |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in payload["rows"]:
        rounds = f"<= {r['rounds']}, until calm" if r["until_calm"] else r["rounds"]
        lines.append(
            f"| {r['design']} | {r['slots']} x {r['copies']} | {rounds} | "
            f"{r['seconds']:.1f} | {r['summed_without']:.3f} | "
            f"{r['summed_with']:.3f} | {r['gain']:+.1%} |"
        )
    first = payload["rows"][0]["seconds"]
    lines += [
        "",
        "Time relative to the first design: "
        + ", ".join(
            f"{r['design']} {r['seconds'] / first:.2f}x" for r in payload["rows"]
        )
        + ".",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument("--threads", type=count, default=1)
    parser.add_argument("--out", type=Path, default=REPORTS / "bench" / "refit")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "rows": measure(args.repeats),
    }
    write_report(args.out, payload, markdown(payload))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
