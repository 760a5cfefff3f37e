"""Time-to-quality baseline: pyABC's ABCSMC on one CAR MODEL II pair (issue 16).

pyABC calibrates IDM on ONE leader-follower pair of CAR MODEL II's training split,
one core, the model being the per-particle NumPy peer (``tools/peer_numpy.py``),
and the trace of its best score against wall time is written to JSON, so that
torchcf's time to reach the same score can be set against it.

pyABC is not a dependency of torchcf: this script runs in its OWN virtualenv,
without torch (neither pyABC nor the peer needs it; torchcf is not imported):

    python3 -m venv /work/pyabc-venv
    /work/pyabc-venv/bin/pip install "pyabc==0.13.*" numpy pandas
    # resolved here: pyabc 0.13.0, numpy 2.4.6, pandas 3.1.1, scipy 1.17.1,
    # SQLAlchemy 2.1.9 on CPython 3.11.7 (no torch is pulled in)
    TORCHCF_DATA=/work/shared/data/abc-paper/data \
        /work/pyabc-venv/bin/python tools/pyabc_baseline.py --max-seconds 240

The set-up, replicated from ``torchcf/data/registry.py`` and ``reader.py`` without
importing them:

* **Data**: ``$TORCHCF_DATA/AV/CAR MODEL II`` (or ``--data-root``; a root holding
  ``data/AV/...`` works too), six header-less CSVs per folder (rows = 0.1 s steps,
  columns = pairs, SI units, leader length 5 m). The training split is
  ``Trajectory/``; each of its columns is matched to the full-set column it equals
  exactly (its *pair id*; identical full-set columns are handed out in order), and
  later exact copies inside the split are dropped, as ``torchcf.load_pairs(
  "car-model-2", split="train")`` does. ``--pair-position`` (default 0) picks the
  pair at that position of the de-duplicated training split (position 0 is pair id
  45); ``--pair-id`` picks a full-set column directly.
* **Model**: IDM, parameters (a, b, v0, T, s0, delta) in torchcf's order with the
  uniform priors of ``torchcf/models/hdv.py``; one simulation = one call of
  ``peer_numpy.simulate_one`` (a Python loop over the 576 steps), which returns the
  score ``0.5 e_p + 0.3 e_v + 0.2 e_a`` (RMSE of position, speed, acceleration),
  ``inf`` for an invalid rollout.
* **ABC**: ``pyabc.ABCSMC`` with ``--population`` particles, the model returning
  ``{"score": s}`` and the distance ``|s - 0|`` (the score itself), priors
  ``pyabc.RV("uniform", low, high - low)``, pyABC's defaults otherwise (adaptive
  ``MedianEpsilon``, ``MultivariateNormalTransition`` kernel, uniform acceptor,
  calibration sample of one population from the prior for the first epsilon),
  ``SingleCoreSampler``, a SQLite database in a temporary folder,
  ``--max-generations`` populations.
* **Stop**: ``--max-seconds`` of wall time since the clock started (just before
  ``ABCSMC`` is built). pyABC's own ``max_walltime`` is only checked between
  generations, so the model wrapper also stops the run hard at the deadline: the
  generation then in progress is recorded as incomplete.

Recorded: per generation (``-1`` is pyABC's calibration sample), the seconds since
the start at which its population was stored, the total simulations so far
(calibration included; counted by the wrapper and cross-checked against pyABC's
history), epsilon, the acceptance rate, the best (smallest) score over the accepted
particles of all generations so far, and the best score over EVERY simulated
particle so far (the wrapper's running minimum, the fairest "best seen"); plus
each improvement of that running minimum with its time, and the seconds spent
inside the model (the rest is pyABC's overhead). Before the run (off the clock),
``--time-peer`` prior draws time one peer simulation.

Writes ``--out`` (default ``reports/bench/pyabc_carII_idm.json``).
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import timedelta
from pathlib import Path

import numpy as np
import pandas as pd

TOOLS = Path(__file__).resolve().parent
REPO = TOOLS.parent
sys.path.insert(0, str(TOOLS))
from peer_numpy import simulate_one  # noqa: E402  (NumPy only, no torch)

from torchcf.system.console import OneLineParser, count, natural, positive  # noqa: E402

#: torchcf/data/registry.py: DATASETS["car-model-2"].
FOLDER = "AV/CAR MODEL II"
DT = 0.1  # [s]
LEADER_LENGTH = 5.0  # [m]
#: torchcf/data/reader.py: FILES, in PairSet.SERIES order.
FILES = {
    "x_lead": "Leading Position.csv",
    "v_lead": "Leading Speed.csv",
    "a_lead": "Leading Acc.csv",
    "x_follow": "Following Position.csv",
    "v_follow": "Following Speed.csv",
    "a_follow": "Following Acc.csv",
}
#: torchcf/models/hdv.py: IDM.param_specs, (name, lower, upper) in its order.
IDM_PRIOR = (
    ("a", 0.5, 2.0),
    ("b", 1.0, 4.0),
    ("v0", 20.0, 40.0),
    ("T", 0.8, 2.5),
    ("s0", 0.5, 3.0),
    ("delta", 2.0, 5.0),
)
WEIGHTS = (0.5, 0.3, 0.2)

log = logging.getLogger("pyabc_baseline")


# ------------------------------------------------------------------------ data
def data_dir(root: Path) -> Path:
    """The CAR MODEL II folder under ``root`` (or ``root/data``)."""
    for base in (root, root / "data"):
        if (base / FOLDER).is_dir():
            return base / FOLDER
    raise SystemExit(f"no '{FOLDER}' under '{root}' (set TORCHCF_DATA or --data-root)")


def read_folder(folder: Path) -> dict[str, np.ndarray]:
    """The six (T, N) float64 series of one folder, read as torchcf's reader does
    (its fast path; ragged columns, which CAR MODEL II does not have, are refused)."""
    series = {}
    for field, name in FILES.items():
        values = pd.read_csv(
            folder / name,
            header=None,
            dtype=np.float64,
            encoding="utf-8-sig",
            keep_default_na=False,
            na_values=[""],
            skip_blank_lines=False,
        ).to_numpy()
        if values.size == 0 or not np.isfinite(values).all():
            raise SystemExit(f"'{folder / name}': empty or non-finite cells")
        series[field] = values  # units "m": factor 1
    shapes = {v.shape for v in series.values()}
    if len(shapes) != 1:
        raise SystemExit(f"'{folder}': the six files differ in shape {shapes}")
    return series


def column_keys(series: dict[str, np.ndarray]) -> list[bytes]:
    """One key per column; equal keys <=> all six series exactly equal."""
    values = np.stack([series[f] for f in FILES]) + 0.0  # (6, T, N); -0.0 -> 0.0
    return [c.tobytes() for c in values.transpose(2, 0, 1).copy()]


def train_pair_ids(base: Path) -> tuple[list[int], dict[str, np.ndarray]]:
    """Pair ids (full-set columns) of the de-duplicated training split, in order,
    and the full set's series."""
    full = read_folder(base)
    train = read_folder(base / "Trajectory")
    pool: dict[bytes, list[int]] = {}
    for j, key in enumerate(column_keys(full)):
        pool.setdefault(key, []).append(j)
    used: set[int] = set()
    ids, seen = [], set()
    for col, key in enumerate(column_keys(train)):
        candidates = pool.get(key)
        if not candidates:
            raise SystemExit(f"Trajectory/ column {col + 1} equals no full-set column")
        free = [j for j in candidates if j not in used]
        pick = free[0] if free else candidates[0]
        used.add(pick)
        if key not in seen:  # drop_duplicates=True keeps the first copy
            ids.append(pick)
            seen.add(key)
    return ids, full


# ------------------------------------------------------------------- the model
class Deadline(BaseException):
    """Raised by the model past ``--max-seconds``; escapes pyABC's sampler."""


class TracedModel:
    """The peer simulation as a pyABC model, counting and timing every call and
    keeping the running minimum of the score (with its time and parameters)."""

    def __init__(self, pair: dict[str, np.ndarray], start: float, deadline: float):
        self.pair = pair
        self.start = start
        self.deadline = deadline
        self.n_sim = 0
        self.model_seconds = 0.0
        self.best = math.inf
        self.best_at = None  # (seconds, n_sim)
        self.best_params = None
        self.improvements: list[dict] = []

    def __call__(self, par) -> dict:
        t0 = time.perf_counter()
        if t0 > self.deadline:
            raise Deadline
        p = np.array([float(par[name]) for name, _, _ in IDM_PRIOR])
        pair = self.pair
        score = simulate_one(
            "idm",
            p,
            pair["x_lead"],
            pair["v_lead"],
            pair["x_follow"],
            pair["v_follow"],
            pair["a_follow"],
            DT,
            LEADER_LENGTH,
            WEIGHTS,
        )
        t1 = time.perf_counter()
        self.n_sim += 1
        self.model_seconds += t1 - t0
        if score < self.best:
            self.best = score
            self.best_at = (t1 - self.start, self.n_sim)
            self.best_params = p.tolist()
            self.improvements.append(
                {"seconds": t1 - self.start, "simulations": self.n_sim, "score": score}
            )
        return {"score": score}


def distance(x: dict, x_0: dict) -> float:
    """The score itself: the simulated score against the observed 0."""
    return abs(x["score"] - x_0["score"])


# --------------------------------------------------------------- the benchmark
def time_peer(pair: dict[str, np.ndarray], n: int, seed: int) -> dict:
    """Median (and spread) wall time of one peer simulation over ``n`` prior draws."""
    rng = np.random.default_rng(seed)
    lo = np.array([b[1] for b in IDM_PRIOR])
    hi = np.array([b[2] for b in IDM_PRIOR])
    times, n_inf = [], 0
    for _ in range(n):
        p = lo + (hi - lo) * rng.random(len(IDM_PRIOR))
        t0 = time.perf_counter()
        score = simulate_one(
            "idm", p, pair["x_lead"], pair["v_lead"], pair["x_follow"],
            pair["v_follow"], pair["a_follow"], DT, LEADER_LENGTH, WEIGHTS,
        )  # fmt: skip
        times.append(time.perf_counter() - t0)
        n_inf += not math.isfinite(score)
    q = np.quantile(times, [0.1, 0.9])
    return {
        "particles": n,
        "median_s": statistics.median(times),
        "mean_s": statistics.fmean(times),
        "p10_s": float(q[0]),
        "p90_s": float(q[1]),
        "steps": len(pair["x_lead"]),
        "invalid_fraction": n_inf / n,
    }


def environment(argv: list[str]) -> dict:
    import pyabc
    import scipy
    import sqlalchemy

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        rev = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=10, check=False,
        ).stdout.strip() or None  # fmt: skip
    except OSError:
        rev = None
    return {
        "command": shlex.join([Path(sys.executable).as_posix(), *sys.argv[:1], *argv]),
        "python": platform.python_version(),
        "pyabc": pyabc.__version__,
        "numpy": np.__version__,
        "pandas": pd.__version__,
        "scipy": scipy.__version__,
        "sqlalchemy": sqlalchemy.__version__,
        "torch_installed": _has_module("torch"),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else None,
        "platform": platform.platform(),
        "git_revision": rev,
    }


def _has_module(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = OneLineParser(description=__doc__.splitlines()[0])
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--pair-position",
        type=natural,
        default=0,
        help="position in the de-duplicated training split (default 0)",
    )
    which.add_argument(
        "--pair-id",
        type=natural,
        default=None,
        help="full-set column (0-based pair id) instead",
    )
    parser.add_argument("--population", type=count, default=1000)
    parser.add_argument("--max-generations", type=count, default=8)
    parser.add_argument("--max-seconds", type=positive, default=600.0)
    parser.add_argument("--seed", type=natural, default=0, help="numpy's global seed")
    parser.add_argument(
        "--time-peer",
        type=natural,
        default=300,
        help="prior draws timed before the run (0: skip)",
    )
    parser.add_argument("--data-root", default=os.environ.get("TORCHCF_DATA"))
    parser.add_argument(
        "--out", type=Path, default=REPO / "reports" / "bench" / "pyabc_carII_idm.json"
    )
    parser.add_argument("--verbose", action="store_true", help="pyABC's INFO log")
    args = parser.parse_args(argv)  # fmt: skip
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    if not args.data_root:
        raise SystemExit("set TORCHCF_DATA or pass --data-root")

    base = data_dir(Path(args.data_root).expanduser())
    ids, full = train_pair_ids(base)
    if args.pair_id is None:
        pair_id = ids[args.pair_position]
    else:
        pair_id = args.pair_id
        if not 0 <= pair_id < full["x_lead"].shape[1]:
            raise SystemExit(f"--pair-id {pair_id} out of range")
    position = ids.index(pair_id) if pair_id in ids else None
    pair = {f: np.ascontiguousarray(v[:, pair_id]) for f, v in full.items()}
    log.info("pair id %d (training position %s), %d steps", pair_id, position,
             len(pair["x_lead"]))  # fmt: skip

    peer = time_peer(pair, args.time_peer, args.seed) if args.time_peer else None
    if peer:
        log.info("peer: median %.3f ms per simulation (%d draws, %.0f%% invalid)",
                 1e3 * peer["median_s"], peer["particles"],
                 100 * peer["invalid_fraction"])  # fmt: skip

    t_import = time.perf_counter()
    import pyabc

    import_s = time.perf_counter() - t_import
    # pyABC's import gives its "ABC" logger an INFO handler of its own.
    abc_log = logging.getLogger("ABC")
    abc_log.setLevel(logging.INFO if args.verbose else logging.WARNING)
    abc_log.propagate = False
    np.random.seed(args.seed)  # noqa: NPY002  (pyABC draws from the global state)

    trace: list[dict] = []
    best_accepted = math.inf
    stopped = "max_generations"
    with tempfile.TemporaryDirectory(prefix="pyabc_baseline_") as tmp:
        db = "sqlite:///" + os.path.join(tmp, "abc.db")
        start = time.perf_counter()  # the clock: everything pyABC does from here
        model = TracedModel(pair, start, start + args.max_seconds)
        prior = pyabc.Distribution(
            **{n: pyabc.RV("uniform", lo, hi - lo) for n, lo, hi in IDM_PRIOR}
        )
        abc = pyabc.ABCSMC(
            model,
            prior,
            distance,
            population_size=args.population,
            sampler=pyabc.sampler.SingleCoreSampler(),
        )
        history = abc.new(db, {"score": 0.0})

        def row(t, eps, n_gen, accepted_min, complete=True):
            nonlocal best_accepted
            if accepted_min is not None:
                best_accepted = min(best_accepted, accepted_min)
            entry = {
                "generation": t,
                "complete": complete,
                "seconds": time.perf_counter() - start,
                "simulations": model.n_sim,
                "generation_simulations": n_gen,
                "epsilon": _finite(eps),
                "acceptance_rate": (args.population / n_gen)
                if complete and n_gen
                else None,
                "best_accepted": _finite(best_accepted),
                "best_simulated": _finite(model.best),
                "model_seconds": model.model_seconds,
            }
            trace.append(entry)
            log.info(
                "gen %3s %s %7.1f s  sims %7d  eps %-10.5g  best acc %-9.5g sim %-9.5g",
                t, " " if complete else "*", entry["seconds"], model.n_sim,
                eps, best_accepted, model.best,
            )  # fmt: skip

        calibration = history.update_after_calibration
        append = history.append_population

        def on_calibration(nr_samples, end_time, wall_time):
            # The calibration population is accepted wholesale; its scores are
            # not "accepted" ones (epsilon is infinite), so best_accepted skips it.
            row(-1, math.inf, nr_samples, None)
            return calibration(nr_samples, end_time, wall_time)

        def on_population(t, current_epsilon, population, nr_simulations, *a, **kw):
            dist = population.get_weighted_distances()["distance"]
            row(t, current_epsilon, nr_simulations, float(dist.min()))
            return append(t, current_epsilon, population, nr_simulations, *a, **kw)

        history.update_after_calibration = on_calibration
        history.append_population = on_population
        try:
            abc.run(
                max_nr_populations=args.max_generations,
                max_walltime=timedelta(seconds=args.max_seconds),
            )
            if time.perf_counter() - start > args.max_seconds:
                stopped = "max_seconds (pyABC's max_walltime, between generations)"
        except Deadline:
            stopped = "max_seconds (hard stop inside a generation)"
            last = trace[-1]["generation"] if trace else -2
            done = sum(r["generation_simulations"] for r in trace)
            try:
                eps = float(abc.eps(last + 1))
            except Exception:  # noqa: BLE001  (the next epsilon may not exist yet)
                eps = math.nan
            row(last + 1, eps, model.n_sim - done, None, complete=False)
        wall = time.perf_counter() - start

        # Cross-check against pyABC's own records.
        pops = history.get_all_populations()
        check = {
            "history_total_simulations": int(history.total_nr_simulations),
            "wrapper_completed_simulations": int(
                sum(r["generation_simulations"] for r in trace if r["complete"])
            ),
            "history_epsilons": [
                _finite(e) for e in pops.loc[pops.t >= 0, "epsilon"].tolist()
            ],
            "history_min_distance": [
                _finite(float(history.get_weighted_distances(t)["distance"].min()))
                for t in pops.t[pops.t >= 0].tolist()
            ],
        }

    result = {
        "benchmark": "pyABC ABCSMC time-to-quality baseline (issue 16)",
        "environment": environment(argv),
        "pair": {
            "dataset": "car-model-2",
            "folder": str(base),
            "split": "train (Trajectory/, exact duplicates dropped)",
            "pair_id": pair_id,
            "train_position": position,
            "train_pair_ids": ids,
            "steps": len(pair["x_lead"]),
            "dt": DT,
            "leader_length": LEADER_LENGTH,
        },
        "model": {
            "name": "idm",
            "simulator": "tools/peer_numpy.py simulate_one",
            "params": [n for n, _, _ in IDM_PRIOR],
            "prior": {n: [lo, hi] for n, lo, hi in IDM_PRIOR},
            "weights": list(WEIGHTS),
        },
        "abc": {
            "population": args.population,
            "max_generations": args.max_generations,
            "max_seconds": args.max_seconds,
            "seed": args.seed,
            "epsilon": "MedianEpsilon (default)",
            "transition": "MultivariateNormalTransition (default)",
            "sampler": "SingleCoreSampler",
            "stopped": stopped,
        },
        "import_pyabc_s": import_s,
        "wall_s": wall,
        "simulations": model.n_sim,
        "model_s": model.model_seconds,
        "overhead_fraction": 1.0 - model.model_seconds / wall if wall else None,
        "peer_timing": peer,
        "trace": trace,
        "best": {
            "score": _finite(model.best),
            "seconds": model.best_at[0] if model.best_at else None,
            "simulations": model.best_at[1] if model.best_at else None,
            "params": model.best_params,
            "best_accepted": _finite(best_accepted),
        },
        "improvements": model.improvements,
        "pyabc_history_check": check,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    log.info("best %.6g at %.1f s (%d simulations); wrote %s", model.best,
             result["best"]["seconds"] or math.nan, result["best"]["simulations"] or 0,
             args.out)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
