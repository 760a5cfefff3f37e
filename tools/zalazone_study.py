"""A whole campaign as one study: the ZalaZONE runs, ``reports/zalazone-dynamic/``.

The 19 platoon files of the OpenACC ZalaZONE dynamic-platform campaign
(``$TORCHCF_RAW/openacc-zalazone-dynamic``, see its ``SOURCE.md``) go through
torchcf's commands, each as its own process, timed:

1. **extract**: ``python -m torchcf data extract RAW --format openacc
   --lap-frame --out pairs/zalazone-dynamic`` (the campaign folder read
   recursively, every run on the platform's lap coordinate, so the loop can
   offer the 1 % tilt as a grade round the lap; the runs that drive on the
   access roads left out; 40 s windows, split by follower);
2. **train**: ``python -m torchcf train configs/zalazone.json --no-eval`` (the
   eight models, ABC rejection, the config's budget);
3. **evaluate**: ``torchcf evaluate RUN`` (the test split);
4. **loop**: ``python -m torchcf diagnose RUN`` (at its defaults);
5. **shares**: ``python -m torchcf posterior RUN --by mode`` (the ACC distance
   setting), ``--groups make.csv`` (the car make, from
   :func:`torchcf.data.formats.openacc.read_openacc_metadata` joined on
   ``(run, follower)``) and ``--by run``, each with a bootstrap interval over
   pairs, and the setting and make again over clusters of pairs (one follower
   in one run).

(``python -m torchcf train configs/zalazone.json`` alone runs steps 2-4 in one
process; they are run apart here to time each.) Then it writes
``reports/zalazone-dynamic/README.md`` (pair counts, drop reasons, shares,
test metrics, the loop, step times, commands, machine, git revision),
``study.json``, the tables it quotes and small figures. The pairs
(``pairs/zalazone-dynamic``) and the run (``runs/zalazone-dynamic``, with logs in
``runs/zalazone-study``) stay in git-ignored folders: never commit the data.

    TORCHCF_RAW=../shared/data/raw python tools/zalazone_study.py
    python tools/zalazone_study.py --resume        # keep the steps already done
    python tools/zalazone_study.py --report-only   # the report from a finished study
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import cpu_model, git_sha  # noqa: E402

from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402

CONFIG = "configs/zalazone.json"
#: The campaign folder as the commands in the report name it.
RAW_VAR = "$TORCHCF_RAW/openacc-zalazone-dynamic"
PAIRS = "pairs/zalazone-dynamic"
RUN = "runs/zalazone-dynamic"
WORK = "runs/zalazone-study"
REPORT = "reports/zalazone-dynamic"
#: ACC distance settings as the extraction's ``mode`` column writes them.
SETTINGS = {"ACC:S": "short", "ACC:M": "medium", "ACC:L": "long"}
#: The make of a car in a file whose ``Vehicle_order`` does not list exactly
#: its cars (the names may belong to other cars).
UNVERIFIED = "names unverified"
#: Clusters of the second bootstrap: the windows of one follower in one run.
CLUSTER = "run,follower"
#: Figures copied from the run (report/ and loop/), and the largest copied.
FIGURES = {
    "report": ("shares.png", "pairwise.png", "radar.png", "error_evolution.png"),
    "loop": ("before_after.png", "effects.png", "residuals.png"),
}
MAX_FIGURE_BYTES = 400_000
#: Settings of the loop beyond its defaults: none. (Until stop 39 the study ran
#: it with population 10 and 8 local copies, 8x fewer rollouts a round, for
#: speed; at the defaults the attribution's 238 rounds on the 327 training pairs
#: now take 5 min on 2 cores, with the same conclusion.)
LOOP_SET: tuple[str, ...] = ()


# ---------------------------------------------------------------- the steps
def display(argv: list[str]) -> str:
    """A command as a user types it (``python``, paths relative to the repo)."""
    words = ["python" if a == sys.executable else a for a in argv]
    return shlex.join(words)


def run_step(
    name: str, argv: list[str], work: Path, steps: dict, *, threads: int | None
) -> dict:
    """Run ``argv`` from the repository root as a whole process, its output in
    ``work/logs/<name>.log``; record and return its wall time.

    Raises:
        SystemExit: the command failed (its log's tail is printed).
    """
    log = work / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    print(f"[{name}] {display(argv)}", flush=True)
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    with log.open("w") as handle:
        code = subprocess.run(
            argv, cwd=REPO, env=env, stdout=handle, stderr=subprocess.STDOUT
        ).returncode
    seconds = time.perf_counter() - start
    if code != 0:
        tail = log.read_text(errors="replace").replace("\r", "\n").splitlines()[-15:]
        print("\n".join(tail), file=sys.stderr)
        raise SystemExit(f"[{name}] failed with exit code {code}; log: {log}")
    record = {
        "command": display(argv),
        "seconds": seconds,
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
        "git": git_sha(),
        "finished": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    steps[name] = record
    (work / "steps.json").write_text(json.dumps(steps, indent=2) + "\n")
    print(f"[{name}] {seconds:.1f} s", flush=True)
    return record


def make_mapping(raw: Path, path: Path) -> pd.DataFrame:
    """``run, follower, group`` (the car make) for every car of the campaign,
    from the files' headers; a file whose ``Vehicle_order`` does not list
    exactly its cars gets :data:`UNVERIFIED`."""
    from torchcf.data.formats.openacc import read_openacc_metadata

    meta = read_openacc_metadata(raw)
    make = meta["name"].where(meta["names_match_count"], UNVERIFIED)
    mapping = pd.DataFrame(
        {"run": meta["run"], "follower": meta["vehicle"], "group": make}
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    mapping.to_csv(path, index=False)
    return meta


def study(args: argparse.Namespace) -> dict:
    """Run every step not done yet; return the step records."""
    raw, pairs, run, work = Path(args.raw), REPO / PAIRS, REPO / RUN, REPO / WORK
    steps_file = work / "steps.json"
    steps = (
        json.loads(steps_file.read_text())
        if args.resume and steps_file.is_file()
        else {}
    )
    if not args.resume:
        for folder in (run, work):
            if folder.exists():
                if folder == run and not (folder / "config.json").is_file():
                    raise SystemExit(f"{folder} exists and holds no run: move it")
                shutil.rmtree(folder)
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m"]
    plan = [
        (
            "extract",
            [*py, "torchcf", "data", "extract", str(raw), "--format", "openacc",
             "--lap-frame", "--out", PAIRS, "--overwrite"],
            pairs / "extract.json",
        ),
        (
            "train",
            [*py, "torchcf", "train", CONFIG, "--out", RUN, "--no-eval"],
            run / "summary.json",
        ),
        ("evaluate", [*py, "torchcf", "evaluate", RUN], run / "metrics.json"),
        (
            "loop",
            [*py, "torchcf", "diagnose", RUN,
             *(w for item in args.loop_set for w in ("--set", f"diagnose.{item}"))],
            run / "loop.json",
        ),
    ]  # fmt: skip
    for name, argv, marker in plan:
        if args.resume and name in steps and marker.is_file():
            print(f"[{name}] done before ({steps[name]['seconds']:.1f} s)")
            continue
        if name == "train" and run.exists():  # a fresh run, not a resumed one
            shutil.rmtree(run)
        run_step(name, argv, work, steps, threads=args.threads)
    make_mapping(raw, work / "make.csv")
    posterior = [*py, "torchcf", "posterior", RUN]
    boot = ["--bootstrap", str(args.bootstrap), "--csv"]
    shares = {
        "shares_setting": ["--by", "mode"],
        "shares_setting_clusters": ["--by", "mode", "--cluster", CLUSTER],
        "shares_make": ["--groups", f"{WORK}/make.csv"],
        "shares_make_clusters": ["--groups", f"{WORK}/make.csv", "--cluster", CLUSTER],
        "shares_run": ["--by", "run"],
    }
    for name, extra in shares.items():
        run_step(name, [*posterior, *extra, *boot], work, steps, threads=args.threads)
    return steps


# --------------------------------------------------------------- the report
def _read_json(path: Path) -> dict:
    return json.loads(path.read_text())


def _fmt(value: object, digits: int = 3) -> str:
    if isinstance(value, int | float):
        return "inf" if value == float("inf") else f"{value:.{digits}f}"
    return str(value)


def _table(header: list[str], rows: list[list[object]], align: str = "") -> list[str]:
    align = align or "|" + "---|" * len(header)
    return [
        "| " + " | ".join(header) + " |",
        align,
        *("| " + " | ".join(str(c) for c in row) + " |" for row in rows),
    ]


def _strip_heading(text: str) -> str:
    """A Markdown file's body without its first heading line."""
    lines = text.strip().splitlines()
    if lines and lines[0].startswith("#"):
        lines = lines[1:]
    return "\n".join(lines).strip()


def _sections(text: str, prefixes: tuple[str, ...]) -> str:
    """The ``## `` sections of ``text`` whose titles start with ``prefixes``,
    one level deeper."""
    out, keep = [], False
    for line in text.splitlines():
        if line.startswith("## "):
            keep = line[3:].startswith(prefixes)
            if keep:
                out.append("#" + line)
                continue
        if keep and not line.startswith("![") and not line.startswith("# "):
            out.append(line)
    return "\n".join(out).strip()


def pair_counts(index: pd.DataFrame, mapping: pd.DataFrame) -> dict:
    """Pairs per split, per setting and per make (with runs and followers)."""
    joined = index.merge(
        mapping.rename(columns={"group": "make"}), on=["run", "follower"], how="left"
    )
    joined["make"] = joined["make"].fillna("(none)")

    def by(column: str) -> list[dict]:
        rows = []
        for value, part in joined.groupby(column, sort=True):
            rows.append(
                {
                    column: value,
                    "pairs": len(part),
                    "train": int((part["split"] == "train").sum()),
                    "test": int((part["split"] == "test").sum()),
                    "runs": int(part["run"].nunique()),
                    "followers": int(part.groupby(["run", "follower"]).ngroups),
                }
            )
        return rows

    return {"mode": by("mode"), "make": by("make")}


def drop_reasons(record: dict, dropped: pd.DataFrame, meta: pd.DataFrame) -> dict:
    """Dropped windows and short spans, overall and per setting."""
    setting = meta.drop_duplicates("run").set_index("run")["distance_setting"].to_dict()
    dropped = dropped.assign(setting=dropped["run"].map(setting))
    per_setting = (
        dropped.groupby(["reason", "setting"]).size().unstack(fill_value=0)
        if len(dropped)
        else pd.DataFrame()
    )
    return {
        "summary": record["summary"],
        "per_setting": {
            reason: {str(k): int(v) for k, v in row.items()}
            for reason, row in per_setting.iterrows()
        },
    }


def shares_figure(csv_path: Path, out: Path, title: str, order: list[str]) -> None:
    """Grouped bars of each model's share per group with the bootstrap interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    frame = pd.read_csv(csv_path, keep_default_na=False, dtype={"group": str})
    models = list(dict.fromkeys(frame["model"]))
    groups = [g for g in order if g in set(frame["group"])]
    width = 0.8 / len(groups)
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=100)
    x = np.arange(len(models))
    for k, group in enumerate(groups):
        part = frame[frame["group"] == group].set_index("model").loc[models]
        share = pd.to_numeric(part["share"], errors="coerce").to_numpy() * 100
        low = pd.to_numeric(part["low"], errors="coerce").to_numpy() * 100
        high = pd.to_numeric(part["high"], errors="coerce").to_numpy() * 100
        n = int(part["pairs"].iloc[0])
        ax.bar(
            x + (k - (len(groups) - 1) / 2) * width,
            share,
            width,
            yerr=np.vstack([share - low, high - share]),
            capsize=2,
            label=f"{group} ({n})",
            error_kw={"linewidth": 0.8},
        )
    ax.set_xticks(x, [m.upper() for m in models])
    ax.set_ylabel("share of the hybrid's slots [%]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, ncol=2 if len(groups) > 6 else 1, title="group (pairs)")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def shares_heatmap(csv_path: Path, out: Path, title: str, order: list[str]) -> None:
    """A group x model map of the shares, each cell with its interval (groups
    of fewer than ``FEW_UNITS`` units marked with a dagger)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchcf.posterior.tables import FEW_UNITS

    frame = pd.read_csv(csv_path, keep_default_na=False, dtype={"group": str})
    for column in ("share", "low", "high"):
        frame[column] = pd.to_numeric(frame[column], errors="coerce") * 100
    models = list(dict.fromkeys(frame["model"]))
    groups = [g for g in order if g in set(frame["group"])]
    table = frame.set_index(["group", "model"])
    share = np.array([[table.at[(g, m), "share"] for m in models] for g in groups])
    fig, ax = plt.subplots(figsize=(9, 0.42 * len(groups) + 1.4), dpi=100)
    ax.imshow(share, cmap="Blues", vmin=0, vmax=100, aspect="auto")
    for i, group in enumerate(groups):
        for j, model in enumerate(models):
            row = table.loc[(group, model)]
            text = f"{row['share']:.0f}"
            if not np.isnan(row["low"]) and row["high"] > 0:
                text += f" [{row['low']:.0f}, {row['high']:.0f}]"
            colour = "white" if row["share"] > 55 else "black"
            ax.text(j, i, text, ha="center", va="center", fontsize=7, color=colour)
    labels = []
    for group in groups:
        first = table.loc[group].iloc[0]
        mark = " †" if first["units"] < FEW_UNITS else ""
        labels.append(f"{group}{mark} ({first['pairs']})")
    ax.set_xticks(range(len(models)), [m.upper() for m in models])
    ax.set_yticks(range(len(groups)), labels, fontsize=8)
    ax.xaxis.tick_top()
    ax.set_title(title, fontsize=10, pad=22)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def non_overlapping(csv_path: Path, groups: list[str]) -> list[str]:
    """``MODEL: A a% vs B b%`` for every model and two groups whose intervals do
    not overlap (groups of fewer than ``FEW_UNITS`` units left out: their
    intervals are too narrow)."""
    from torchcf.posterior.tables import FEW_UNITS

    frame = pd.read_csv(csv_path, keep_default_na=False, dtype={"group": str})
    for column in ("share", "low", "high"):
        frame[column] = pd.to_numeric(frame[column], errors="coerce")
    frame = frame[(frame["units"] >= FEW_UNITS) & frame["low"].notna()]
    out = []
    for model, part in frame.groupby("model", sort=False):
        part = part.set_index("group")
        present = [g for g in groups if g in part.index]
        for i, a in enumerate(present):
            for b in present[i + 1 :]:
                x, y = part.loc[a], part.loc[b]
                if x["high"] < y["low"] or y["high"] < x["low"]:
                    out.append(
                        f"{model.upper()}: {a} {x['share']:.0%} vs {b} {y['share']:.0%}"
                    )
    return out


def overall(csv_path: Path) -> list[dict]:
    """Every model's share over all training pairs with its interval, largest
    first."""
    frame = pd.read_csv(csv_path, keep_default_na=False, dtype={"group": str})
    rows = frame[frame["group"] == "all"]
    out = [
        {
            "model": r["model"],
            "share": float(r["share"]),
            "low": float(r["low"]),
            "high": float(r["high"]),
        }
        for _, r in rows.iterrows()
    ]
    return sorted(out, key=lambda r: -r["share"])


def largest(csv_path: Path, groups: list[str]) -> dict:
    """Per group, the model of the largest share (with its clusters)."""
    frame = pd.read_csv(csv_path, keep_default_na=False, dtype={"group": str})
    out = {}
    for group in groups:
        part = frame[frame["group"] == group]
        if len(part):
            row = part.loc[pd.to_numeric(part["share"]).idxmax()]
            out[group] = {
                "model": row["model"],
                "share": float(row["share"]),
                "units": int(row["units"]),
            }
    return out


def report(args: argparse.Namespace, steps: dict) -> Path:
    """Write ``reports/zalazone-dynamic/`` from the finished study."""
    from torchcf.data.formats.openacc import read_openacc_metadata

    raw, pairs, run, work = Path(args.raw), REPO / PAIRS, REPO / RUN, REPO / WORK
    out = REPO / REPORT
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    record = _read_json(pairs / "extract.json")
    index = pd.read_csv(pairs / "index.csv", dtype=str, keep_default_na=False)
    dropped = pd.read_csv(pairs / "dropped.csv", dtype=str, keep_default_na=False)
    meta = read_openacc_metadata(raw)
    mapping = pd.read_csv(work / "make.csv", dtype=str, keep_default_na=False)
    summary, metrics = (
        _read_json(run / "summary.json"),
        _read_json(run / "metrics.json"),
    )
    loop = _read_json(run / "loop.json")
    config = _read_json(run / "config.json")
    counts = pair_counts(index, mapping)
    drops = drop_reasons(record, dropped, meta)
    rep = run / "report"
    tables = {
        "setting": rep / "shares_by_mode",
        "setting_clusters": rep / "shares_by_mode-clusters-run-follower",
        "make": rep / "shares_by_make",
        "make_clusters": rep / "shares_by_make-clusters-run-follower",
        "run": rep / "shares_by_run",
    }
    for name, stem in tables.items():
        shutil.copyfile(stem.with_suffix(".md"), out / f"shares_by_{name}.md")
    settings = [s for s in SETTINGS if s in set(index["mode"])]
    with_pairs = {row["make"] for row in counts["make"]}
    makes = sorted(with_pairs - {UNVERIFIED, "(none)"}) + [UNVERIFIED]
    shares_figure(
        tables["setting_clusters"].with_suffix(".csv"),
        figures / "shares_by_setting.png",
        "Shares per ACC distance setting "
        "(95 % bootstrap over (run, follower) clusters)",
        ["all", *settings],
    )
    shares_heatmap(
        tables["make_clusters"].with_suffix(".csv"),
        figures / "shares_by_make.png",
        "Shares per car make, % (95 % bootstrap over (run, follower) clusters; "
        "† fewer than 5 clusters)",
        ["all", *makes],
    )
    copied = []
    for folder, names in FIGURES.items():
        for name in names:
            source = run / folder / name
            if source.is_file() and source.stat().st_size <= MAX_FIGURE_BYTES:
                target = figures / (name if folder == "report" else f"loop_{name}")
                shutil.copyfile(source, target)
                copied.append(target.name)
    table_md = (rep / "table.md").read_text()
    (out / "table.md").write_text(table_md)
    loop_md = (run / "loop.md").read_text().replace("](loop/", "](figures/loop_")
    (out / "loop.md").write_text(loop_md)
    differ = {
        "setting": non_overlapping(
            tables["setting_clusters"].with_suffix(".csv"), settings
        ),
        "setting_pairs": non_overlapping(
            tables["setting"].with_suffix(".csv"), settings
        ),
        "make": non_overlapping(
            tables["make_clusters"].with_suffix(".csv"), makes[:-1]
        ),
    }
    machine = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "git": git_sha(),
        "modified": subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=REPO,
        ).stdout.split("\n"),
    }
    machine["modified"] = [line[3:] for line in machine["modified"] if line.strip()]
    import torch

    machine["torch"] = torch.__version__
    payload = {
        "machine": machine,
        "config": config["abc"],
        "steps": steps,
        "pairs": {
            k: record["summary"][k] for k in ("pairs", "train_pairs", "test_pairs")
        },
        "counts": counts,
        "runs_without_pairs": sorted(set(meta["run"]) - set(index["run"])),
        "drops": drops,
        "shares": summary["shares"],
        "metrics_hybrid": metrics["hybrid"],
        "loop": {
            "chosen": loop["chosen"],
            "seconds": loop["seconds"],
            "pool": loop["pool"],
            "before": loop["before"],
            "after": loop["after"],
        },
        "non_overlapping": differ,
        "tilt": tilt_in_residual(run, record["notes"]),
        # the campaign folder as the extraction was given it
        "raw": shlex.split(steps["extract"]["command"])[4],
        "overall": overall(tables["setting_clusters"].with_suffix(".csv")),
        "largest": largest(tables["setting_clusters"].with_suffix(".csv"), settings),
        "loop_set": [
            w.removeprefix("diagnose.")
            for w in shlex.split(steps["loop"]["command"])
            if w.startswith("diagnose.")
        ],
    }
    (out / "study.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    text = readme(
        payload, record, summary, metrics, loop, loop_md, table_md, copied, out
    )
    (out / "README.md").write_text(text)
    return out / "README.md"


def tilt_in_residual(run_dir: Path, notes: list[str], seed: int = 0) -> dict:
    """How much of the platform's measured tilt reaches the one-step residual.

    On the lap frame a car at lap coordinate ``s`` climbs ``slope sin(s / R)``
    (the extraction's plane fitted to the altitudes, ``docs/data.md``), so a
    follower that did nothing about the grade would leave ``z(s) = -g slope
    sin(s / R)`` [m/s^2] in the command residual of the run's best particle
    (:func:`torchcf.diagnose.signatures.road.one_step_residual`). The share reaching it
    is
    the slope of that residual on ``z`` within pairs (each pair's mean
    removed), pooled over the training pairs with the loop's pair weights: 1
    = the grade is missed whole, 0 = the controller (or the fitted model)
    takes it up. The interval is a percentile bootstrap over pairs (2 000
    resamples). A free phase (``sin`` and ``cos`` regressors) checks that what
    is found lies where the altitudes put the grade.
    """
    import re

    import numpy as np

    from torchcf.config import load_split
    from torchcf.diagnose.signatures.road import (
        finite_samples,
        one_step_residual,
        pair_weights,
    )
    from torchcf.diagnose.signatures.series import best_particles
    from torchcf.models.effects import GRAVITY
    from torchcf.runs.directory import RunDir

    (slope_note,) = [n for n in notes if "lie on a plane of slope" in n]
    slope = float(re.search(r"slope ([0-9.]+) %", slope_note).group(1)) / 100
    cfg, posterior, _ = RunDir(run_dir).load_run()
    train, _ = load_split(cfg.data)
    series = finite_samples(one_step_residual(best_particles(posterior, train), train))
    radius = train.road_period / (2 * np.pi)
    weights = pair_weights(series["acceleration"])

    def centred(values: np.ndarray) -> np.ndarray:
        return values - values.mean() if values.size else values

    r = [centred(a) for a in series["acceleration"]]
    sin = [centred(-GRAVITY * slope * np.sin(x / radius)) for x in series["x"]]
    cos = [centred(-GRAVITY * slope * np.cos(x / radius)) for x in series["x"]]
    # per pair: the normal equations' terms of r ~ k_s z_sin + k_c z_cos
    terms = (
        np.array(
            [
                [s @ s, s @ c, c @ c, s @ y, c @ y]
                for s, c, y in zip(sin, cos, r, strict=True)
            ]
        )
        * weights[:, None]
    )

    def share(rows: np.ndarray) -> tuple[float, float, float]:
        ss, sc, cc, sy, cy = rows.sum(axis=0)
        alone = sy / ss
        k_sin, k_cos = np.linalg.solve([[ss, sc], [sc, cc]], [sy, cy])
        return float(alone), float(k_sin), float(k_cos)

    k, k_sin, k_cos = share(terms)
    rng = np.random.default_rng(seed)
    draws = np.array(
        [share(terms[rng.integers(0, len(terms), len(terms))])[0] for _ in range(2000)]
    )
    return {
        "slope": slope,
        "radius": float(radius),
        "pairs": int(len(terms)),
        "samples": int(sum(a.size for a in r)),
        "share": k,
        "low": float(np.percentile(draws, 2.5)),
        "high": float(np.percentile(draws, 97.5)),
        "free_phase_amplitude": float(np.hypot(k_sin, k_cos)),
        "free_phase_deg": float(np.degrees(np.arctan2(k_cos, k_sin))),
    }


def tilt_lines(tilt: dict) -> list[str]:
    """The README's paragraph on the tilt in the residual."""
    from torchcf.models.effects import GRAVITY

    full = GRAVITY * tilt["slope"]
    return [
        "## The platform's tilt in the residual",
        "",
        f"On the lap frame every car climbs `{100 * tilt['slope']:.2f} % x "
        f"sin(s / {tilt['radius']:.1f} m)` at lap coordinate `s` (the plane "
        "fitted to the altitudes); a follower that did nothing about it would "
        f"leave up to {full:.3f} m/s^2 in the command residual of its best "
        f"particle. Regressed on that grade within each of the "
        f"{tilt['pairs']} training pairs ({tilt['samples']:,} steps, the loop's "
        "pair weights), the residual carries a share "
        f"**{tilt['share']:.2f}** [{tilt['low']:.2f}, {tilt['high']:.2f}] "
        "(95 % bootstrap over pairs) of it: 1 would be the grade missed whole, 0 "
        "taken up by the ACC (or absorbed by the fitted models). With a free "
        f"phase the residual's lap wave has {tilt['free_phase_amplitude']:.2f} of "
        f"the amplitude, {tilt['free_phase_deg']:+.0f} deg from where the "
        "altitudes put the grade. (`tilt_in_residual` in "
        "`tools/zalazone_study.py`.)",
        "",
    ]


def in_short(payload: dict, metrics: dict, loop: dict) -> list[str]:
    """The study's findings in a few lines, from its numbers."""
    top = payload["overall"][:3]
    shares = ", ".join(
        f"{r['model'].upper()} {r['share']:.0%} [{r['low']:.0%}, {r['high']:.0%}]"
        for r in top
    )
    singles = {
        m: v["ws"] for m, v in metrics.items() if isinstance(v, dict) and "ws" in v
    }
    singles.pop("hybrid", None)
    best = min(singles, key=singles.get)
    differ = payload["non_overlapping"]["setting"]
    total = sum(step["seconds"] for step in payload["steps"].values())
    largest = "; ".join(
        f"{g} {r['model'].upper()} {r['share']:.0%} ({r['units']} clusters)"
        for g, r in payload["largest"].items()
    )
    found = [s for s in loop["signatures"][0] if s["found"]]
    return [
        "## In short",
        "",
        f"- **Shares** (all {payload['pairs']['train_pairs']} training pairs, 95 % "
        f"interval over (run, follower) clusters): {shares}.",
        f"- **Per setting**, intervals that do not overlap (clusters): "
        f"{'; '.join(differ) or 'none'}. The largest share per setting: "
        f"{largest}.",
        f"- **Test split** ({metrics['n_test']} pairs): hybrid WS "
        f"{metrics['hybrid']['ws']:.3f}, 0.15-WS {metrics['hybrid']['beta_ws']:.3f}, "
        f"minimum distance {metrics['hybrid']['min']:.3f}; best single model "
        f"{best.upper()} WS {singles[best]:.3f}.",
        f"- **Loop**: chosen {', '.join(loop['chosen']) or 'none'}; "
        f"{len(found)} of {len(loop['signatures'][0])} residual signatures found "
        f"({', '.join(s['signature'] for s in found)}); the effects they point to "
        + (
            "were tested and none gains out of sample at its level."
            if not loop["chosen"]
            else "were tested (see below)."
        ),
        f"- **Time**: {total / 60:.0f} min for the whole study (loop "
        f"{payload['steps']['loop']['seconds'] / 60:.0f} min).",
        "",
    ]


def loop_budget(settings: list[str]) -> str:
    """The loop's settings in words."""
    if not settings:
        return "The loop at its defaults."
    given = ", ".join(f"`{x}`" for x in settings)
    return f"The loop with {given}, the rest at its defaults."


def readme(
    payload: dict,
    record: dict,
    summary: dict,
    metrics: dict,
    loop: dict,
    loop_md: str,
    table_md: str,
    figures: list[str],
    out: Path,
) -> str:
    steps, abc, machine = payload["steps"], payload["config"], payload["machine"]
    s = record["summary"]
    n_per_pair = abc["n_particles"] / s["train_pairs"]
    per_model = summary["per_model"]
    lines = [
        "# The ZalaZONE campaign as one study",
        "",
        "The 19 platoon files of the OpenACC ZalaZONE dynamic-platform campaign "
        "(`$TORCHCF_RAW/openacc-zalazone-dynamic`, JRC, October 2019; see its "
        "`SOURCE.md`) extracted in one command on the platform's lap coordinate "
        "(`--lap-frame`: one road frame round the circle, so the loop can offer "
        "the platform's tilt as a grade; runs that leave the circle for the "
        "access roads are left out), every window calibrated with the "
        "eight models, evaluated on the test split, the loop closed, and the "
        "hybrid's shares per ACC distance setting and per car make. Written by "
        "`python tools/zalazone_study.py`; every step ran as its own process and "
        f"was timed. Machine: {machine['cpu']}, {machine['cores']} cores "
        f"(shared with other work: see the load column), torch {machine['torch']}, "
        f"Python {machine['python']}, git {machine['git']}"
        + (
            f" (uncommitted changes to {', '.join(machine['modified'])} when the "
            "report was written)"
            if machine["modified"]
            else ""
        )
        + ".",
        "",
        f"**Budget**: ABC rejection (the paper's method), "
        f"{abc['n_particles']:,} particles per model from the prior, paired layout "
        f"(about {n_per_pair:.0f} per training pair and model), "
        f"N = {abc['top_n']} per pair, per-pair selection, seed {abc['seed']}. "
        + loop_budget(payload["loop_set"])
        + " 200,000 particles per model keep the whole study within minutes on "
        "two cores: 1e6 would run every model five times longer.",
        "",
        *in_short(payload, metrics, loop),
        "## Pairs",
        "",
        f"{s['pairs']} pairs of {s['window_steps'] * s['dt']:.0f} s "
        f"({s['train_pairs']} training, {s['test_pairs']} test; split by follower, "
        f"so no car of a run is on both sides) from {s['vehicles']} vehicles in "
        f"{s['runs']} runs; {s['candidate_windows']} candidate windows. "
        + (
            f"No pair from {', '.join(f'`{r}`' for r in payload['runs_without_pairs'])}"
            " (no couple lasts a window)."
            if payload["runs_without_pairs"]
            else ""
        ),
        "",
    ]
    names = {"mode": "setting", "make": "make"}
    for key, label in names.items():
        rows = [
            [
                r[key] + (f" ({SETTINGS[r[key]]})" if r[key] in SETTINGS else ""),
                r["pairs"],
                r["train"],
                r["test"],
                r["runs"],
                r["followers"],
            ]
            for r in payload["counts"][key]
        ]
        lines += _table(
            [label, "pairs", "train", "test", "runs", "followers (run, car)"], rows
        )
        lines.append("")
    lines += [
        f"`{UNVERIFIED}`: `short_setting/dynamic_part1` lists 11 makes in "
        "`Vehicle_order` for its 6 cars (`Number_of_vehicles`), so its makes are "
        "not known for sure; its pairs stay out of the make groups.",
        "",
        "### Dropped",
        "",
    ]
    drops = payload["drops"]
    per_setting = drops["per_setting"]
    settings = [k for k in ("S", "M", "L")]
    rows = []
    for reason, dropped in s["windows_dropped"].items():
        row = per_setting.get(reason, {})
        rows.append(
            [f"window: `{reason}`", dropped, *(row.get(k, 0) for k in settings)]
        )
    short = per_setting.get("short", {})
    rows.append(
        [
            f"couple span shorter than a window ({s['seconds_in_short_spans']:.0f} s)",
            s["spans_short"],
            *(short.get(k, "") for k in settings),
        ]
    )
    lines += _table(["reason", "count", "S", "M", "L"], rows)
    general = [n for n in record["notes"] if not n.startswith("run ")]
    lines += [
        "",
        f"{sum(s['windows_dropped'].values())} of {s['candidate_windows']} windows "
        "dropped (`dropped.csv` names each with its value). The extraction's "
        f"notes: {len(record['notes'])}, one per run and finding (`extract.json`); "
        "those about the whole campaign:",
        "",
        *(f"- {n}" for n in general),
        "",
        "## Shares",
        "",
        "Each training pair's N slots in the hybrid, and which model holds them, "
        "summed per group (`python -m torchcf posterior RUN --by mode`, `--groups "
        "make.csv`): a model's share of a group is its slots over the group's. Two "
        "intervals: over pairs (every 40 s window drawn on its own), and over "
        "clusters of pairs, the windows of one follower in one run drawn together "
        "(`--cluster run,follower`). The windows of one car in one run share the "
        "car, the platoon and the run's leader, so the second is the honest one; "
        "the first is narrower.",
        "",
        "### Per ACC distance setting",
        "",
        "![shares per setting](figures/shares_by_setting.png)",
        "",
        _strip_heading((out / "shares_by_setting_clusters.md").read_text()),
        "",
        _strip_heading((out / "shares_by_setting.md").read_text()),
        "",
    ]
    differ = payload["non_overlapping"]
    lines += [
        "Models whose intervals do not overlap between two settings: over "
        f"clusters {'; '.join(differ['setting']) or 'none'}; over pairs "
        f"{'; '.join(differ['setting_pairs']) or 'none'}.",
        "",
        "The settings are not an experiment's arms: S has 12 runs, L 5 and M one "
        "(`medium_setting/dynamic_part8`, 5 cars), and the cars, their order and "
        "the leader's speed profile change between runs, so a difference between "
        "settings is a difference between these runs too.",
        "",
        "### Per car make",
        "",
        "![shares per make](figures/shares_by_make.png)",
        "",
        _strip_heading((out / "shares_by_make_clusters.md").read_text()),
        "",
        _strip_heading((out / "shares_by_make.md").read_text()),
        "",
        "Makes whose intervals over clusters do not overlap (makes of at least "
        "5 clusters; no correction for the many comparisons: every two makes, "
        f"eight models): {'; '.join(differ['make']) or 'none'}.",
        "",
        "Per run: [`shares_by_run.md`](shares_by_run.md).",
        "",
        "## Test split",
        "",
        _strip_heading(table_md).replace("\n## ", "\n### "),
        "",
        "## The loop",
        "",
    ]
    chosen = ", ".join(loop["chosen"]) or "none"
    lines += [
        f"Pool (share >= 5 %): {', '.join(loop['pool'])}. **Chosen: {chosen}** "
        f"(the loop's own time: {loop['seconds']:.0f} s). The whole report: "
        "[`loop.md`](loop.md).",
        "",
        _sections(
            loop_md,
            ("From the residual", "Step", "Structure", "Test-split error"),
        ),
        "",
        *tilt_lines(payload["tilt"]),
        "## Time",
        "",
    ]
    rows = []
    for name, step in steps.items():
        inside = ""
        if name == "train":
            seconds = sum(per_model[m]["seconds"] for m in per_model)
            slowest = sorted(per_model, key=lambda m: -per_model[m]["seconds"])[:2]
            parts = [f"{m} {per_model[m]['seconds']:.0f} s" for m in slowest]
            inside = f"ABC {seconds:.0f} s ({', '.join(parts)})"
        if name == "loop":
            inside = f"loop {loop['seconds']:.0f} s"
        rows.append(
            [
                name,
                f"{step['seconds']:.1f}",
                f"{step['load_before']:.1f} / {step['load_after']:.1f}",
                inside,
            ]
        )
    total = sum(step["seconds"] for step in steps.values())
    rows.append(["**all**", f"**{total:.0f}**", "", ""])
    lines += _table(["step", "wall [s]", "load 1 min before / after", "inside"], rows)
    lines += [
        "",
        "Wall times of whole processes (start-up included) on a machine shared "
        "with other developers: the load average says how busy it was (2 cores).",
        "",
        "## Commands",
        "",
        "```bash",
        "export TORCHCF_RAW=../shared/data/raw  # the raw samples, never committed",
        *(step["command"].replace(payload["raw"], RAW_VAR) for step in steps.values()),
        "```",
        "",
        "The same in one line: `TORCHCF_RAW=../shared/data/raw python "
        "tools/zalazone_study.py`; `python -m torchcf train configs/zalazone.json` "
        "runs train, evaluation and loop in one process. `make.csv` is "
        "`read_openacc_metadata(RAW)`'s `run, vehicle, name` as `run, follower, "
        f"group` (`{UNVERIFIED}` where the names may not be the cars).",
        "",
        "## Figures",
        "",
        "- [`figures/shares_by_setting.png`](figures/shares_by_setting.png), "
        "[`figures/shares_by_make.png`](figures/shares_by_make.png): drawn by the "
        "study from the tables above",
        *(f"- [`figures/{name}`](figures/{name}): the run's" for name in figures),
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--raw",
        default=str(
            Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
            / "openacc-zalazone-dynamic"
        ),
        help="the campaign folder",
    )
    parser.add_argument("--bootstrap", type=natural, default=2000, help="resamples")
    parser.add_argument(
        "--threads", type=count, default=None, help="OMP_NUM_THREADS of the steps"
    )
    parser.add_argument(
        "--loop-set",
        action="append",
        default=list(LOOP_SET),
        metavar="KEY=VALUE",
        help="a diagnose setting for the loop (repeatable; default: none, the "
        "loop at its defaults)",
    )
    parser.add_argument(
        "--resume", action="store_true", help="skip the steps already done"
    )
    parser.add_argument(
        "--report-only", action="store_true", help="write the report only"
    )
    args = parser.parse_args(argv)
    if args.report_only:
        steps = _read_json(REPO / WORK / "steps.json")
    else:
        steps = study(args)
    print(f"wrote {report(args, steps)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
