"""The diagnosis loop where drivers differ: hit rates and power.

Measured drivers differ from one another; a regression case that copies one
driver to every pair makes the loop's job easy (the pooled particles cover new
drivers). Here every pair has its own driver (``torchcf.sim.synthetic.
heterogeneous_pairs``): a two-model mixture, each driver's parameters drawn
uniformly over the model's prior and kept where it follows plausibly, pairs of
ragged length (60-100 % of 50 s), position noise 0.1 m (speed 0.1 m/s,
acceleration 0.1 m/s^2), 50 training and 20 test pairs. One effect is planted
in every driver (a behavioural effect) or in the whole data set (a recording
effect), or none (the controls). The pool (IDM, GFM, LLCTG, HL; 40 000
particles per model, rejection) is calibrated without it and the loop runs at
its defaults.

**Cases** (``cases``, the default): every case over ``--seeds`` seeds (5), the
whole loop (re-calibration and test split included). Reports the hit rate (the
planted effect chosen) and the false-choice rate (anything chosen in a
control, or an effect other than the planted one), per case, in
``reports/loop_heterogeneous.{json,md}``.

**Power** (``power``): for each planted effect, sizes from large to small over
``--seeds`` seeds at ``--pairs`` training pairs (50 and 200), the loop's first
step only (the attribution with ``max_effects`` 1: was the planted effect
chosen first?), until a size is chosen in fewer than 80 % of the seeds; the
smallest size chosen in at least 80 % is the effect's detectable size at that
number of pairs (``reports/loop_power.{json,md}``).

**Detectable** (``detectable``): the loop's own power estimate
(:mod:`torchcf.diagnose.selection.power`, what each tested effect would have had to
measure to be chosen) on the controls' data at each ``--pairs``, the first step
over ``--seeds`` seeds, beside the planted cases' hit rates
(``reports/loop_detectable.{json,md}``): one run per control and seed where
the ``power`` mode needs one per effect, size and seed.

    python tools/loop_heterogeneous.py                      # the cases
    python tools/loop_heterogeneous.py power --pairs 50 200
    python tools/loop_heterogeneous.py detectable --pairs 200 --seeds 2
    python tools/loop_heterogeneous.py report               # markdown from JSON
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402
from loop_cases import config as loop_cases_config  # noqa: E402

from torchcf.data import PairSet  # noqa: E402
from torchcf.diagnose.selection.attribution import choose  # noqa: E402
from torchcf.diagnose.significance import (  # noqa: E402
    LEVEL_SCHEMES,
    fallback_levels,
    level_weights,
)
from torchcf.models.effects import parse_effect  # noqa: E402
from torchcf.sim.synthetic import (  # noqa: E402
    DriverMixture,
    Scene,
    heterogeneous_pairs,
)
from torchcf.study.pipeline import close_loop, train_and_evaluate  # noqa: E402
from torchcf.system.console import OneLineParser, count, natural, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
#: The pool calibrated on every case (two of them drive the data; LLCTG and HL
#: do not drive the human cases, GFM and HL not the ACC ones).
POOL = ("idm", "gfm", "llctg", "hl")
N_PARTICLES = 40_000
NOISE = 0.1
LENGTHS = (0.6, 1.0)
N_STEPS = 500
#: The road section of a planted grade [m]: knots every 200 m, leaders starting
#: anywhere in its first 300 m (the pairs share the road).
GRADE_SECTION = (0.0, 1600.0)
GRADE_KNOTS = 9
GRADE_START = (0.0, 300.0)


@dataclass(frozen=True)
class Case:
    """A heterogeneous case.

    Attributes:
        mixture: the models that drive the pairs (equal shares).
        effect: the planted effect (its token; "" for a control).
        size: its size: a one-parameter effect's value, a grade's amplitude.
        parameter: the parameter recovered (None: a profile or nothing).
    """

    mixture: tuple[str, ...]
    effect: str
    size: float
    parameter: str | None

    @property
    def expected(self) -> list[str]:
        return [parse_effect(self.effect).name] if self.effect else []

    def plant(self, size: float, seed: int) -> list[float]:
        """The planted values at ``size``: the value itself, or a grade's
        knots, +-size in a seeded order of signs."""
        if not self.effect.startswith("grade"):
            return [size] if self.effect else []
        g = torch.Generator().manual_seed(seed)
        signs = torch.where(torch.rand(GRADE_KNOTS, generator=g) < 0.5, -1.0, 1.0)
        return (size * signs.double()).tolist()


HUMAN = ("idm", "gfm")
ACC = ("llctg", "idm")
GRADE = (
    f"grade(start={GRADE_SECTION[0]:g},end={GRADE_SECTION[1]:g},knots={GRADE_KNOTS})"
)
#: The cases: a reaction delay of every (human) driver, an actuation lag of
#: every (ACC) follower, a spacing sensor 3 m short of the truth (every leader
#: recorded 3 m ahead: undone by d_offset -3 m), the leader's log 0.8 s ahead
#: of the follower's (undone by t_sync 0.8 s), a +-4 % rolling grade every
#: 200 m, and a control of each mixture.
CASES = {
    "delay": Case(HUMAN, "delay", 0.8, "t_delay"),
    "lag": Case(ACC, "lag", 0.8, "t_lag"),
    "offset": Case(ACC, "offset", -3.0, "d_offset"),
    "sync": Case(HUMAN, "sync", 0.8, "t_sync"),
    "grade": Case(HUMAN, GRADE, 0.04, None),
    "control (human)": Case(HUMAN, "", 0.0, None),
    "control (ACC)": Case(ACC, "", 0.0, None),
}
#: Sizes of the power study, largest first, per planted effect.
POWER_SIZES = {
    "delay": (0.8, 0.4, 0.2, 0.1),
    "lag": (0.8, 0.4, 0.2, 0.1),
    "offset": (-3.0, -1.5, -0.75, -0.375),
    "sync": (0.8, 0.4, 0.2, 0.1),
    "grade": (0.04, 0.02, 0.01, 0.005),
}


def case_pairs(
    case: Case, size: float, seed: int, n_train: int = 50, n_test: int = 20
) -> tuple[PairSet, PairSet]:
    """The case's training and test pairs at ``size`` (seeded)."""
    grade = case.effect.startswith("grade")
    mixture = DriverMixture(case.mixture, case.effect, case.plant(size, seed))
    recorded = {
        "noise": NOISE,
        "lengths": LENGTHS,
        "scene": Scene(start=GRADE_START if grade else (0.0, 0.0)),
    }
    train, _ = heterogeneous_pairs(
        mixture, n_train, N_STEPS, seed=1000 * seed + 1, **recorded
    )
    test, _ = heterogeneous_pairs(
        mixture, n_test, N_STEPS, seed=1000 * seed + 2, **recorded
    )
    # a planted grade puts the pairs on one road; the others have a frame each
    train, test = (dataclasses.replace(p, road_frame=grade) for p in (train, test))
    return train, test


def config(diagnose: dict | None = None):
    """The cases' config (:func:`loop_cases.config` with this pool)."""
    return loop_cases_config(N_PARTICLES, POOL, diagnose)


def run_case(
    name: str, seed: int, size: float | None = None, *, n_train: int = 50,
    first_step: bool = False, diagnose: dict | None = None,
) -> dict:  # fmt: skip
    """One case at one seed: calibrate, close the loop, what it chose."""
    case = CASES[name]
    size = case.size if size is None else size
    train, test = case_pairs(case, size, seed, n_train)
    settings = dict(diagnose or {})
    if first_step:
        settings["max_effects"] = 1
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        train_and_evaluate(config(settings), out, pairs=(train, test))
        trained = time.perf_counter()
        result = close_loop(out, pairs=(train, test), progress=False)
    chosen = [effect.name for effect in result.chosen]
    loop = result.to_json()  # the record this table keeps
    first = loop["steps"][0] if loop["steps"] else []
    planted = next((r for r in first if r["name"] in case.expected), None)
    return {
        "case": name,
        "seed": seed,
        "size": size,
        "n_train": train.n_pairs,
        "expected": case.expected,
        "chosen": chosen,
        "hit": bool(case.expected) and chosen[:1] == case.expected,
        "false": bool(chosen) and chosen[:1] != case.expected,
        "estimate": _estimate(loop, case),
        "planted_test": _test_of(planted),
        "first_step": [_test_of(r) for r in first],
        "validation": loop.get("validation"),
        "ws": [loop["before"].get("ws"), loop["after"].get("ws")],
        "min": [loop["before"].get("min"), loop["after"].get("min")],
        "same_search": [
            (loop["before_same_search"] or loop["before"]).get(k) for k in ("ws", "min")
        ],
        "class_on_test": _class_change(loop.get("class_on_test")),
        "response_times": {
            side: None
            if times is None
            else {k: times.get(k) for k in ("data", "model", "perturbation")}
            for side, times in (loop.get("response_times") or {}).items()
        },
        "loop_seconds": time.perf_counter() - trained,
        "seconds": time.perf_counter() - began,
    }


def _class_change(found: dict | None) -> dict | None:
    """The model class on the test pairs (``loop.json``'s), without its
    per-pair lists."""
    if found is None:
        return None
    return {k: v for k, v in found.items() if k != "per_pair"}


def _test_of(row: dict | None) -> dict | None:
    if row is None:
        return None
    keep = ("name", "order", "gain", "fit_gain", "p_value", "level", "significant",
            "active", "estimate", "pointed_by", "detectable")  # fmt: skip
    out = {k: row.get(k) for k in keep}
    out["interval"] = (row.get("shared") or {}).get("interval")
    return out


def _estimate(result: dict, case: Case) -> float | None:
    """The planted parameter's estimate: the re-calibrated posterior's median
    where the effect was chosen, else its first-step estimate."""
    if case.parameter is None:
        return None
    for summary in (result.get("posterior") or {}).values():
        stats = summary["params"].get(case.parameter)
        if stats and stats.get("n"):
            return stats["median"]
    for row in result["steps"][0] if result["steps"] else []:
        if case.parameter in (row.get("estimate") or {}):
            return row["estimate"][case.parameter]
    return None


def cases_markdown(payload: dict) -> str:
    meta = payload["meta"]
    rows = payload["runs"]
    lines = [
        "# The loop where drivers differ: hit rates",
        "",
        provenance(meta) + ". Every pair its own driver (a "
        "two-model mixture, parameters drawn over the priors, kept where they "
        "follow plausibly), 50 training / 20 test pairs of 30-50 s, noise 0.1 m; "
        "pool IDM, GFM, LLCTG, HL at 40 000 particles; the loop at its defaults "
        "(`tools/loop_heterogeneous.py`). *Hit*: the planted effect chosen "
        "first; *false*: anything else chosen first.",
        "",
        "| case | mixture | planted | hits | false choices | estimate (median "
        "over seeds) | its test (median gain, p) | loop [s] (median) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, case in CASES.items():
        runs = [r for r in rows if r["case"] == name]
        if not runs:
            continue
        hits = sum(r["hit"] for r in runs)
        false = sum(r["false"] for r in runs)
        estimates = [r["estimate"] for r in runs if r["estimate"] is not None]
        tests = [r["planted_test"] for r in runs if r["planted_test"]]
        planted = (
            f"{case.effect.split('(')[0]} {case.size:g}" if case.effect else "none"
        )
        lines.append(
            f"| {name} | {' + '.join(case.mixture)} | {planted} | "
            + (f"{hits}/{len(runs)}" if case.expected else "—")
            + f" | {false}/{len(runs)} | "
            + (f"{_median(estimates):.3g}" if estimates else "—")
            + " | "
            + (
                f"{_median([t['gain'] for t in tests]):+.1%}, "
                f"{_median([t['p_value'] for t in tests]):.2g}"
                if tests
                else "—"
            )
            + f" | {_median([r['loop_seconds'] for r in runs]):.0f} |"
        )
    controls = [r for r in rows if not r["expected"]]
    behaviour = [r for r in rows if r["expected"] and r["case"] in ("delay", "lag")]
    lines += [
        "",
        f"Controls: {sum(r['false'] for r in controls)} false choices in "
        f"{len(controls)} runs. Behavioural effects (delay, lag): "
        f"{sum(r['hit'] for r in behaviour)} hits in {len(behaviour)} runs.",
        *levels_markdown(rows),
        *detectable_markdown(rows),
        "",
        "Per run (chosen, in order):",
        "",
    ]
    for r in rows:
        lines.append(
            f"- {r['case']}, seed {r['seed']}: {', '.join(r['chosen']) or 'none'}"
            f" ({r['validation']}; min distance {_fmt(r['min'][0])} -> "
            f"{_fmt(r['min'][1])}, searched as after {_fmt(r['same_search'][1])}"
            + _class_text(r.get("class_on_test"))
            + ")"
        )
    return "\n".join(lines) + "\n"


def _class_text(found: dict | None) -> str:
    if not found:
        return ""
    return (
        f"; the class on the test pairs {found['change']:+.1%}, better on "
        f"{found['better']} of {found['pairs']}, p {found['p_value']:.2g}"
    )


def detectable_markdown(
    rows: list[dict], planted: list[dict] | None = None
) -> list[str]:
    """What the controls could have shown: the loop's own detectable sizes
    (:mod:`torchcf.diagnose.selection.power`, computed where nothing is chosen) on each
    control's data, median over seeds, beside the planted case of the same
    mixture and its hit rate (from ``planted``, default ``rows``): the
    estimate's check against planted effects."""
    planted_rows = rows if planted is None else planted
    lines = []
    for control in ("control (human)", "control (ACC)"):
        runs = [r for r in rows if r["case"] == control]
        if not any(t and t.get("detectable") for r in runs for t in r["first_step"]):
            continue  # run with diagnose.detectable off: nothing to show
        mixture = CASES[control].mixture
        lines += [
            "",
            f"What {control} could have shown at {runs[0]['n_train']} training "
            f"pairs: the loop's detectable sizes on "
            f"its data (step 1, {len(runs)} seeds; median over seeds, at the "
            "effect's level / if tested first; '>' where the largest size "
            "tried was not chosen), beside the planted case of this mixture:",
            "",
            "| effect | side | detectable at its level | if tested first | "
            "planted case | hits |",
            "|---|---|---|---|---|---|",
        ]
        names = sorted({t["name"] for r in runs for t in r["first_step"] if t})
        for name in names:
            found = [
                t["detectable"] for r in runs for t in r["first_step"]
                if t and t["name"] == name and t.get("detectable")
            ]  # fmt: skip
            for side in ("above", "below"):
                sizes = [d for d in found if side in (d.get("at_level") or {})]
                if not sizes:
                    continue
                case = next(
                    (c for n, c in CASES.items()
                     if c.mixture == mixture and c.effect
                     and parse_effect(c.effect).name == name
                     and (c.size >= 0) == (side == "above")),
                    None,
                )  # fmt: skip
                planted = next(
                    (n for n, c in CASES.items() if c is case), None
                )  # fmt: skip
                hits = [r["hit"] for r in planted_rows if r["case"] == planted]
                largest = max(
                    abs(t["size"]) for d in sizes for t in d["tried"].get(side, [])
                )  # fmt: skip
                lines.append(
                    f"| {name} | {'+' if side == 'above' else '-'} | "
                    f"{_detectable(sizes, 'at_level', side, largest)} | "
                    f"{_detectable(sizes, 'if_first', side, largest)} | "
                    + (f"{case.size:g}" if case else "—")
                    + " | "
                    + (f"{sum(hits)}/{len(hits)}" if hits else "—")
                    + " |"
                )
    return lines


def _detectable(found: list[dict], key: str, side: str, largest: float) -> str:
    """The median over seeds of one side's detectable size (absolute; a seed
    where none was chosen counts as above every size tried)."""
    values = [
        abs(d[key][side]) if (d.get(key) or {}).get(side) is not None else math.inf
        for d in found
    ]
    median = sorted(values)[(len(values) - 1) // 2]  # the lower median
    unit = found[0]["unit"]
    return f"> {largest:.3g} {unit}" if median == math.inf else f"{median:.3g} {unit}"


def first_choice(run: dict, scheme: str, min_gain: float = 0.05) -> str | None:
    """What the run's first step would have chosen with its level shared by
    ``scheme`` (``diagnose.levels``): the same tests (gains, p-values, order),
    judged again by the fallback procedure and the step's choice (the runs
    were judged by halving)."""
    rows = [dict(r) for r in run["first_step"]]
    if not rows:
        return None
    step_level = rows[0]["level"] / level_weights([False] * len(rows))[0]
    weights = level_weights([bool(r["pointed_by"]) for r in rows], scheme)
    _, significant = fallback_levels(
        [r["p_value"] for r in rows],
        [r["gain"] >= min_gain and r["active"] for r in rows],
        step_level,
        weights,
    )
    judged = [
        SimpleNamespace(
            name=row["name"],
            gain=row["gain"],
            significant=yes,
            scope=parse_effect(row["name"]).scope,
        )
        for row, yes in zip(rows, significant, strict=True)
    ]
    best = choose(judged, min_gain)  # reads a row's name, gain, significance, scope
    return None if best is None else best.name


def levels_markdown(rows: list[dict]) -> list[str]:
    """Hits and false choices of the first step under each way of sharing its
    level (``diagnose.levels``), from the same tests."""
    lines = [
        "",
        "The first step's choice with its level shared otherwise "
        "(`diagnose.levels`; the same tests judged again):",
        "",
        "| levels | hits | false choices |",
        "|---|---|---|",
    ]
    planted = sum(bool(r["expected"]) for r in rows)
    for scheme in LEVEL_SCHEMES:
        choices = [(r, first_choice(r, scheme)) for r in rows]
        hits = sum(bool(r["expected"]) and c == r["expected"][0] for r, c in choices)
        false = sum(c is not None and c not in r["expected"] for r, c in choices)
        lines.append(f"| {scheme} | {hits}/{planted} | {false}/{len(rows)} |")
    return lines


def power_markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The loop's power where drivers differ",
        "",
        provenance(meta) + ". The cases of "
        "`reports/loop_heterogeneous.md` at smaller sizes, the loop's first step "
        "(was the planted effect chosen first?), sizes from large to small until "
        "fewer than 80 % of the seeds choose it. At more pairs the sizes begin "
        "below the smallest chosen at fewer pairs, which is carried (not run "
        "again: more pairs only add power).",
        "",
        "| effect | pairs | size: chosen / seeds | smallest size chosen in >= 80 % |",
        "|---|---|---|---|",
    ]
    for entry in payload["power"]:
        sizes = ", ".join(
            f"{s['size']:g}: {s['hits']}/{s['seeds']}" for s in entry["sizes"]
        )
        if entry.get("from") is not None:
            sizes = f"{entry['from']:g}: carried from fewer pairs, {sizes}"
        smallest = _smallest_text(entry)
        if not _finished(entry, payload.get("seeds", 5)):
            smallest += " (unfinished: its last size needs more seeds)"
        lines.append(f"| {entry['effect']} | {entry['pairs']} | {sizes} | {smallest} |")
    return "\n".join(lines) + "\n"


def _finished(entry: dict, seeds: int) -> bool:
    """Whether an effect's sizes at its number of pairs are all decided: its
    last size has every seed or too many misses for 80 %, and it is either
    below 80 % or the smallest size of the study."""
    if not entry["sizes"]:
        return False
    last = entry["sizes"][-1]
    misses = last["seeds"] - last["hits"]
    decided = last["seeds"] == seeds or misses > seeds - _needed(seeds)
    smallest = abs(last["size"]) == min(abs(s) for s in POWER_SIZES[entry["effect"]])
    return decided and (last["hits"] < _needed(seeds) or smallest)


def _smallest_text(entry: dict) -> str:
    """The power table's last column: the smallest size chosen in 80 % of the
    seeds, or, where none is (yet), the largest size tried and its hits."""
    if entry["smallest"] is not None:
        return f"{entry['smallest']:g}"
    if not entry["sizes"]:
        return "none tried"
    first = entry["sizes"][0]
    return f"none (largest tried, {first['size']:g}: {first['hits']}/{first['seeds']})"


def power(
    effects: list[str],
    pairs: list[int],
    seeds: int,
    diagnose: dict,
    done: dict[tuple, dict],
    save,
) -> list[dict]:
    """Per effect and number of pairs, the sizes tried and the smallest chosen
    in at least 80 % of the seeds (``done``: runs read back, by (effect,
    pairs, size, seed); ``save`` is called after every run)."""
    out = []
    chosen_at_fewer: dict[str, float] = {}  # effect -> smallest chosen so far
    for n_train in sorted(pairs):
        for effect in effects:
            start = chosen_at_fewer.get(effect)
            entry = {"effect": effect, "pairs": n_train, "sizes": [], "smallest": None,
                     "from": start}  # fmt: skip
            out.append(entry)
            for size in POWER_SIZES[effect]:
                if start is not None and abs(size) >= abs(start):
                    continue  # chosen at fewer pairs: more pairs only add power
                runs = []
                tried = {"size": size, "hits": 0, "seeds": 0, "runs": runs}
                entry["sizes"].append(tried)
                for seed in range(seeds):
                    row = done.get((effect, n_train, size, seed)) or run_case(
                        effect, seed, size, n_train=n_train, first_step=True,
                        diagnose=diagnose,
                    )  # fmt: skip
                    runs.append(row)
                    tried["hits"] = sum(r["hit"] for r in runs)
                    tried["seeds"] = len(runs)
                    if tried["hits"] >= _needed(seeds):  # more seeds only add hits
                        entry["smallest"] = size
                    save(out)
                    misses = sum(not r["hit"] for r in runs)
                    if misses > seeds - _needed(seeds):
                        break  # 80 % out of reach
                hits = tried["hits"]
                print(
                    f"power {effect} {n_train} pairs, size {size:g}: "
                    f"{hits}/{len(runs)}",
                    file=sys.stderr,
                )
                if hits < _needed(seeds):
                    break
            if entry["smallest"] is None and start is not None:
                entry["smallest"] = start  # carried from fewer pairs
            if entry["smallest"] is not None:
                chosen_at_fewer[effect] = entry["smallest"]
            save(out)
    return out


def detectable(
    pairs: list[int], seeds: int, diagnose: dict, done: dict[tuple, dict], save
) -> list[dict]:
    """The loop's own power estimate (:mod:`torchcf.diagnose.selection.power`) on the
    controls' data at each number of training pairs: every control over
    ``seeds`` seeds (and every seed ``done`` holds), the first step only
    (``done``: runs read back, by (case, pairs, seed), the cases' controls
    among them: their first step is the same; ``save`` is called after every
    run)."""
    rows = []
    for n_train in pairs:
        known = {seed for (_, n, seed) in done if n == n_train}
        for seed in sorted(known | set(range(seeds))):
            for name in ("control (human)", "control (ACC)"):
                row = done.get((name, n_train, seed)) or run_case(
                    name, seed, n_train=n_train, first_step=True, diagnose=diagnose
                )
                print(
                    f"detectable: {name}, {n_train} pairs, seed {seed}, "
                    f"loop {row['loop_seconds']:.0f} s",
                    file=sys.stderr,
                )
                rows.append(row)
                save(rows)
    return rows


def detectable_report(payload: dict, planted: list[dict]) -> str:
    """The markdown of ``detectable``: per number of pairs, each control's
    table (:func:`detectable_markdown`), the planted cases' hits beside."""
    meta = payload["meta"]
    lines = [
        "# What the loop could show where drivers differ: its own power estimate",
        "",
        provenance(meta) + ". The controls of "
        "`tools/loop_heterogeneous.py` (nothing planted) at each number of "
        "training pairs (20 test pairs), the loop's first step: the sizes "
        "each tested effect would have had to have to be chosen "
        "(`torchcf.diagnose.selection.power`). Hits: the planted cases of "
        "`reports/loop_heterogeneous.md` (50 pairs).",
    ]
    for n_train in sorted({r["n_train"] for r in payload["runs"]}):
        runs = [r for r in payload["runs"] if r["n_train"] == n_train]
        seconds = _median([r["loop_seconds"] for r in runs])
        lines += [
            "",
            f"## {n_train} training pairs (loop {seconds:.0f} s, median)",
            *detectable_markdown(runs, planted if n_train == 50 else []),
        ]
    return "\n".join(lines) + "\n"


def _needed(seeds: int) -> int:
    """Hits out of ``seeds`` for 80 %."""
    return -(-4 * seeds // 5)


def _median(values: list[float]) -> float:
    return float(torch.tensor(values, dtype=torch.float64).quantile(0.5))


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "what", nargs="?", choices=("cases", "power", "detectable", "report"),
        default="cases",
        help="detectable: the loop's own power estimate on the controls at each "
        "--pairs; report: write a cases' or power report's markdown again from "
        "its JSON (--name)",
    )  # fmt: skip
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--effects", nargs="+", default=list(POWER_SIZES))
    parser.add_argument("--pairs", nargs="+", type=count, default=[50, 200])
    parser.add_argument("--seeds", type=count, default=5)
    parser.add_argument(
        "--from-seed", type=natural, default=0,
        help="cases: start at this seed (a design tried on the seeds it missed)",
    )  # fmt: skip
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument(
        "--workers", type=natural, default=0,
        help="diagnose.workers (the results are the same for any; not a setting "
        "of the report)",
    )  # fmt: skip
    parser.add_argument("--name", default=None)
    parser.add_argument(
        "--resume", action="store_true",
        help="keep the runs of the report written before (same settings)",
    )  # fmt: skip
    parser.add_argument(
        "--also-from", nargs="+", default=[], metavar="NAME",
        help="with --resume: keep the runs of these reports too (same settings)",
    )  # fmt: skip
    parser.add_argument(
        "--diagnose", action="append", default=[], metavar="KEY=JSON",
        help="a loop setting beside the defaults, e.g. validation='\"time\"'",
    )  # fmt: skip
    args = parser.parse_args(argv)
    diagnose = {}
    for item in args.diagnose:
        key, _, value = item.partition("=")
        diagnose[key] = json.loads(value)
    torch.set_num_threads(args.threads)
    payload = {"meta": bench_meta(sys.argv, args.threads), "diagnose": diagnose}
    diagnose = {**diagnose, "workers": args.workers}
    default = {"power": "loop_power", "detectable": "loop_detectable"}.get(
        args.what, "loop_heterogeneous"
    )
    out = REPORTS / (args.name or default)
    if args.what == "report":
        written = json.loads(out.with_suffix(".json").read_text())
        text = power_markdown if "power" in written else cases_markdown
        write_report(out, written, text(written))
        return 0
    earlier = _earlier(out, payload["diagnose"]) if args.resume else {}
    if args.what == "detectable":
        cases = REPORTS / "loop_heterogeneous.json"
        planted = json.loads(cases.read_text())["runs"] if cases.exists() else []
        controls = [r for r in planted if not r["expected"]]  # the same step 1
        done = {
            (r["case"], r["n_train"], r["seed"]): r
            for r in [*controls, *earlier.get("runs", [])]
        }

        def save_rows(rows: list[dict]) -> None:
            payload["runs"] = rows
            write_report(out, payload, detectable_report(payload, planted))

        detectable(args.pairs, args.seeds, diagnose, done, save_rows)
        return 0
    if args.what == "power":
        reports = [earlier] + [
            _earlier(REPORTS / name, payload["diagnose"]) for name in args.also_from
        ]
        done = {
            (e["effect"], e["pairs"], s["size"], r["seed"]): r
            for report in (reports if args.resume else [])
            for e in report.get("power", [])
            for s in e["sizes"]
            for r in s["runs"]
        }

        payload["seeds"] = args.seeds

        def save(entries: list[dict]) -> None:
            payload["power"] = entries
            write_report(out, payload, power_markdown(payload))

        power(args.effects, args.pairs, args.seeds, diagnose, done, save)
        return 0
    done = {(r["case"], r["seed"]): r for r in earlier.get("runs", [])}
    seeds = range(args.from_seed, args.seeds)
    grid = {(name, seed) for seed in seeds for name in args.cases}
    runs = [r for key, r in done.items() if key not in grid]  # other cases kept
    for seed in seeds:
        for name in args.cases:
            row = done.get((name, seed)) or run_case(name, seed, diagnose=diagnose)
            print(
                f"{name}, seed {seed}: chosen {row['chosen']} "
                f"(expected {row['expected']}), loop {row['loop_seconds']:.0f} s",
                file=sys.stderr,
            )
            runs.append(row)
            payload["runs"] = runs
            write_report(out, payload, cases_markdown(payload))  # after every run
    return 0


def _earlier(out: Path, diagnose: dict) -> dict:
    """The report written before with the same loop settings (to resume), or
    nothing."""
    path = out.with_suffix(".json")
    if not path.exists():
        return {}
    earlier = json.loads(path.read_text())
    return earlier if earlier.get("diagnose") == diagnose else {}


if __name__ == "__main__":
    raise SystemExit(run_main(main))
