"""The SMC hybrids beside the rejection ones: ``reports/smc/README.md``.

Reads the SMC runs (``python -m torchcf train configs/<ds>.json --set
abc.method=smc --out runs/smc/<ds>``) and the rejection runs' metrics kept in
``reports/`` (the paper's studies, same config but the method), and writes one
table per data set: the test metrics of the hybrid and of every model alone
(WS, 0.15-WS, minimum distance), the shares, and SMC's evidence shares. Copies the
SMC runs' ``summary.json`` and ``metrics.json`` beside the report.

    python tools/smc_report.py runs/smc --out reports/smc
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

from torchcf.system.console import OneLineParser, run_main

#: data set -> the folder in reports/ that holds its rejection run (authors' split)
REJECTION = {
    "carII": "reports/carII",
    "carI": "reports/carI",
    "ngsim": "reports/ngsim/authors-split",
}
METRICS = (("ws", "WS"), ("beta_ws", "0.15-WS"), ("min", "min distance"))


def _number(value) -> float:
    return float(value) if value is not None else math.nan


def _fmt(value) -> str:
    number = _number(value)
    return "inf" if math.isinf(number) else f"{number:.3f}"


def table(name: str, rejection: dict, smc: dict, summaries: dict) -> list[str]:
    entries = ["hybrid"] + [m for m in summaries["smc"]["models"] if m in smc]
    lines = [
        f"## {name} ({smc['n_test']} test pairs)",
        "",
        "| set | "
        + " | ".join(f"{label} rejection / SMC" for _, label in METRICS)
        + " | share rejection / SMC / SMC evidence |",
        "|---|" + "---|" * (len(METRICS) + 1),
    ]
    evidence = summaries["smc"]["smc"]["evidence_shares"]
    for entry in entries:
        cells = [
            f"{_fmt(rejection.get(entry, {}).get(k))} / {_fmt(smc[entry].get(k))}"
            for k, _ in METRICS
        ]
        if entry == "hybrid":
            share = ""
        else:
            share = (
                f"{summaries['rejection']['shares'].get(entry, 0):.1%} / "
                f"{summaries['smc']['shares'][entry]:.1%} / {evidence[entry]:.1%}"
            )
        lines.append(f"| {entry} | " + " | ".join(cells) + f" | {share} |")
    never = smc["hybrid"].get("particles_never_valid")
    if never:
        lines += [
            "",
            f"SMC hybrid: {never} particle(s) invalid on every test pair, so WS and "
            "0.15-WS are infinite (SPEC); the minimum distance compares.",
        ]
    return lines + [""]


def _smc_settings(runs: Path) -> str:
    """The SMC settings the runs used (from the first run's config.json)."""
    for name in REJECTION:
        config = runs / name / "config.json"
        if config.exists():
            smc = json.loads(config.read_text())["abc"]["smc"]
            return (
                f"population {smc['population']}, {smc['rounds']} rounds, "
                f"{smc['prior_fraction']:.0%} prior draws, quantile {smc['quantile']}"
                ", the population's elite kept"
            )
    return "unknown"


def main() -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, help="folder with one SMC run per data set")
    parser.add_argument("--out", type=Path, default=Path("reports/smc"))
    args = parser.parse_args()
    found = [n for n in REJECTION if (args.runs / n / "metrics.json").is_file()]
    if not found:
        parser.error(
            f"{args.runs} holds no evaluated SMC run ({', '.join(REJECTION)}/"
            "metrics.json)"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    settings = _smc_settings(args.runs)
    lines = [
        "# SMC hybrids beside the rejection ones (test split)",
        "",
        "Same configs as the paper's studies (`configs/<ds>.json`: 8 models x 1e6 "
        "particles, paired, N = 5, float32, seed 0, the authors' split), with "
        "`--set abc.method=smc --set compile=off` (SMC at its defaults: "
        f"{settings}). Rejection: the runs "
        "in `reports/carII`, `reports/carI`, `reports/ngsim/authors-split`. Each "
        "cell: rejection / SMC; lower is better.",
        "",
        "Shares: rejection's and SMC's are the same slot count (the per-pair top-N "
        "across models); SMC's evidence shares estimate each model's prior mass "
        "within the SMC hybrid's per-pair threshold (docs/training.md, 'Sequential "
        "refinement').",
        "",
    ]
    for name, folder in REJECTION.items():
        run = args.runs / name
        if not (run / "metrics.json").exists():
            continue
        smc = json.loads((run / "metrics.json").read_text())
        rejection = json.loads((Path(folder) / "metrics.json").read_text())
        summaries = {
            "smc": json.loads((run / "summary.json").read_text()),
            "rejection": json.loads((Path(folder) / "summary.json").read_text()),
        }
        lines += table(name, rejection, smc, summaries)
        for file in ("summary.json", "metrics.json"):
            shutil.copy(run / file, args.out / f"{name}_{file}")
    (args.out / "README.md").write_text("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
