"""The loop's validation designs side by side on measured data.

50 training and 20 test pairs of the ZalaZONE OpenACC campaign (the draw of
``tools/bench_loop.py``), with the leader's log planted ``--shift`` seconds
ahead of the follower's (0: as measured), trained once with 2e5 particles per
model (eight models); then ``python -m torchcf diagnose`` once per design of
``diagnose.validation`` (``refit``, ``pairs``, ``time``), everything else at
its defaults. Per design: what was chosen, the first step's tests in their
order and the loop's wall time.

    TORCHCF_RAW=../shared/data/raw python tools/loop_designs.py --work DIR

``--work`` keeps the trained run and each design's ``loop.json`` (a design
whose loop is there already is read back, not run again). Writes
``reports/loop_designs.{json,md}``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_loop import clear_loop, config, measured_data  # noqa: E402
from bench_sim import bench_meta, provenance, write_report  # noqa: E402

from torchcf.system.console import OneLineParser, count, finite, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
DESIGNS = ("refit", "pairs", "time")


def run_design(run: Path, design: str, out: Path, threads: int) -> dict:
    """The loop on ``run`` with ``diagnose.validation = design``; its loop.json
    and loop.md copied to ``out`` with the wall time."""
    if (out / "loop.json").exists():
        seconds = json.loads((out / "seconds.json").read_text())
        return {**json.loads((out / "loop.json").read_text()), **seconds}
    clear_loop(run)
    began = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "torchcf", "diagnose", str(run), "--threads",
         str(threads), "--set", f'diagnose.validation="{design}"'],
        check=True, capture_output=True,
    )  # fmt: skip
    seconds = {"seconds": time.perf_counter() - began}
    out.mkdir(parents=True, exist_ok=True)
    for name in ("loop.json", "loop.md"):
        shutil.copy(run / name, out / name)
    (out / "seconds.json").write_text(json.dumps(seconds))
    return {**json.loads((run / "loop.json").read_text()), **seconds}


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The loop's validation designs on measured data",
        "",
        provenance(meta) + f". 50 training / 20 test pairs of the "
        "ZalaZONE campaign (the draw of `tools/bench_loop.py`), the leader's log "
        f"planted {payload['shift']:g} s ahead; eight models at 2e5 particles; "
        "the loop at its defaults but `diagnose.validation`.",
        "",
        "| design | chosen | first step's tests (gain, p at level), in order "
        "| loop [s] |",
        "|---|---|---|---|",
    ]
    for row in payload["designs"]:
        tests = "; ".join(
            f"{t['name']} {t['gain']:+.1%} (p {t['p_value']:.2g} at {t['level']:.2g})"
            for t in row["first_step"][:5]
        )
        lines.append(
            f"| {row['design']} | {', '.join(row['chosen']) or 'none'} | {tests} | "
            f"{row['seconds']:.0f}{' *' if row.get('note') else ''} |"
        )
    if any(row.get("note") for row in payload["designs"]):
        lines += ["", "\\* timed beside another job on the same 2 cores."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", required=True)
    parser.add_argument("--shift", type=finite, default=0.8)
    parser.add_argument("--designs", nargs="+", default=list(DESIGNS))
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--out", default=str(REPORTS / "loop_designs"))
    args = parser.parse_args(argv)
    raw = Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    data = measured_data(raw, work, "data", 50, 20, args.shift)
    run = work / "run"
    if not (run / "posterior.pt").exists():
        cfg = config(data, 200_000, args.threads, work / "cfg.json")
        subprocess.run(
            [sys.executable, "-m", "torchcf", "train", str(cfg), "--out", str(run)],
            check=True, capture_output=True,
        )  # fmt: skip
    rows = []
    for design in args.designs:
        result = run_design(run, design, work / design, args.threads)
        rows.append(
            {
                "design": design,
                "chosen": result["chosen"],
                "seconds": result["seconds"],
                "note": result.get("note"),
                "first_step": [
                    {k: t[k] for k in ("name", "gain", "p_value", "level")}
                    for t in result["steps"][0]
                ],
            }
        )
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "shift": args.shift,
        "designs": rows,
    }
    write_report(Path(args.out), payload, markdown(payload))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
