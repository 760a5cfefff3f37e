"""The longest silence of each everyday command: how long a user waits with no
output at all.

Runs each command as a user would (from the repository root, output to a
terminal-like unbuffered pipe, stdout and stderr merged) and timestamps every
piece of output it writes, progress bars' redraws included (tqdm redraws a bar
in place with ``\\r``: each redraw counts as output). A command's *silence* is
the longest stretch between two writes (the start and the end count as
writes); the report gives it with what came just before and after, and the
command's whole time.

    TORCHCF_DATA=../shared/data/abc-paper/data python tools/silences.py
    python tools/silences.py --only smoke "sumo export"

The commands (``--only`` picks some): the README's main job (the CAR MODEL II
study), the quick start's smoke run, ``sumo export`` and ``sumo verify`` of the
main job's run. Results in ``reports/bench/silences.{json,md}``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.system.console import OneLineParser, positive, run_main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REPORTS = ROOT / "reports" / "bench"


def commands(work: Path) -> dict[str, list[str]]:
    """The everyday commands, by name, writing under ``work``."""
    python = sys.executable
    main_run = str(work / "carII")
    return {
        "main job": [python, "-m", "torchcf", "train", "configs/carII.json",
                     "--out", main_run],
        "smoke": [python, "-m", "torchcf", "train", "configs/smoke.json",
                  "--out", str(work / "smoke")],
        "sumo export": [python, "-m", "torchcf", "sumo", "export", main_run,
                        "--out", str(work / "export")],
        "sumo verify": [python, "-m", "torchcf", "sumo", "verify", main_run,
                        "--out", str(work / "verify")],
    }  # fmt: skip


#: A command's output: ``(seconds since its start, text written)`` per piece.
Writes = list[tuple[float, str]]


def timed_writes(argv: list[str], timeout: float) -> tuple[Writes, int]:
    """Run ``argv``; every piece of output as ``(seconds since start, text)``,
    and the exit code."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    began = time.perf_counter()
    process = subprocess.Popen(
        argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    writes = []
    assert process.stdout is not None
    fd = process.stdout.fileno()
    while True:
        piece = os.read(fd, 65536)
        now = time.perf_counter() - began
        if not piece:
            break
        writes.append((now, piece.decode("utf-8", "replace")))
        if now > timeout:
            process.kill()
            break
    code = process.wait()
    writes.append((time.perf_counter() - began, ""))  # the end
    return writes, code


def longest_silence(writes: Writes) -> dict:
    """The longest gap between two writes (the start at 0 s counts as one)."""
    times = [0.0] + [t for t, _ in writes]
    texts = [""] + [text for _, text in writes]
    gaps = [(times[i + 1] - times[i], i) for i in range(len(times) - 1)]
    gap, i = max(gaps)
    return {
        "seconds": round(gap, 2),
        "from_s": round(times[i], 2),
        "before": _tail(texts[i]),
        "after": _tail(texts[i + 1], head=True),
    }


def _tail(text: str, head: bool = False) -> str:
    """The last (or first) line of a piece of output, as a user saw it."""
    lines = [line for line in text.replace("\r", "\n").split("\n") if line.strip()]
    if not lines:
        return ""
    line = lines[0] if head else lines[-1]
    return line.strip()[:160]


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The longest silence of each everyday command",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['cpu']} "
        f"({meta['cpu_count']} CPUs), git {meta['git']}. Output timestamped "
        "as it arrives (stdout and stderr merged, unbuffered; a progress bar's "
        "redraw counts as output); the silence is the longest stretch without "
        "any (`tools/silences.py`).",
        "",
        "| command | exit | whole [s] | longest silence [s] | from [s] | last output "
        "before it | first output after it |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, row in payload["commands"].items():
        s = row["silence"]
        lines.append(
            f"| {name} | {row['exit']} | {row['seconds']:.1f} | {s['seconds']:.1f} | "
            f"{s['from_s']:.1f} | `{s['before']}` | `{s['after']}` |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--only", nargs="+", default=None, metavar="NAME",
        help="some of: main job, smoke, sumo export, sumo verify",
    )  # fmt: skip
    parser.add_argument("--timeout", type=positive, default=1800.0, help="[s] each")
    parser.add_argument("--out", type=Path, default=REPORTS / "silences")
    args = parser.parse_args(argv)
    payload = {"meta": bench_meta(sys.argv, threads=os.cpu_count() or 1)}
    payload["commands"] = {}
    with tempfile.TemporaryDirectory(prefix="torchcf-silences-") as name:
        chosen = commands(Path(name))
        unknown = set(args.only or []) - set(chosen)
        if unknown:
            parser.error(f"--only: unknown {sorted(unknown)}; known: {list(chosen)}")
        for command, argv_ in chosen.items():
            if args.only and command not in args.only:
                continue
            writes, code = timed_writes(argv_, args.timeout)
            row = {
                "argv": " ".join(argv_[1:]),
                "exit": code,
                "seconds": round(writes[-1][0], 2),
                "silence": longest_silence(writes),
            }
            payload["commands"][command] = row
            print(
                f"{command}: exit {code}, {row['seconds']:.1f} s, longest silence "
                f"{row['silence']['seconds']:.1f} s",
                file=sys.stderr,
            )
    write_report(args.out, payload, markdown(payload))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
