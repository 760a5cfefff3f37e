"""The diagnosis loop on data with undeclared effects: tables of development cases.

**Synthetic cases** (regression tests of the loop): each generates training (24)
and test (12) pairs of 500 steps from a pool model with effects torchcf is not
told about (``torchcf.sim.synthetic``, position noise 0.05 m), calibrates the pool
(IDM and LLCTG, 40 000 particles per model, rejection), runs the whole loop
(``torchcf.study.pipeline.close_loop`` at its defaults) and records what was chosen,
the recovered parameters (median over the re-calibrated hybrid's particles that
carry the effect) and the test-split WS and minimum distance before (the run's
particles searched as after, without the effects) and after. The case "delay,
Gipps outside the pool" is driven by :class:`torchcf.sim.synthetic.Gipps`, a
follower no pool model is. Writes ``reports/loop_cases.{json,md}``.

**Measured cases** (``--group measured``; the development cases on real data):
the driving is measured, only the plant is known.

- ZalaZONE (``$TORCHCF_RAW/openacc-zalazone-dynamic``: commercial ACC cars in
  platoons, extracted with ``python -m torchcf data extract``'s defaults, 50
  training and 20 test pairs drawn with a fixed seed), calibrated with the
  eight models at 2e5 particles each: as measured (nothing planted), with
  every leader position +3 m (a spacing-sensor offset: ``offset`` -3 m), with
  the leader's log 0.5 s ahead of the follower's (a clock offset: ``sync``
  0.5 s), and with a road grade planted on the first 1200 m of every run (the
  pairs that stay there: every follower's measured trajectory plus the
  closed-loop response of an ACC-like IDM to a +-3 % profile changing every
  100 m, the pairs declared on one road);
- CAR MODEL II's pairs (``$TORCHCF_DATA``; 44 training, 17 test; pool GFM, IDM,
  HL at 40 000 particles): nothing planted, +3 m on every leader position, the
  leader's log 0.5 s ahead.

A planted recording effect counts as right when it is chosen and recovered
(offset within 1 m, clock offset within 0.3 s) or reported as absorbed by a
named parameter (``absorbed_by``).
A planted grade that is not chosen gets one more arm: the planted profile's own
(its knots), searched from the planted values (``truth_seeded``). If that arm is
not significant either, the miss is reported as not detectable in the data (it
still counts as a miss).

    python tools/loop_cases.py                        # the synthetic cases
    python tools/loop_cases.py --group measured       # needs TORCHCF_RAW, _DATA
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, write_report  # noqa: E402

from torchcf.config import DiagnoseConfig, validate_config  # noqa: E402
from torchcf.data import PairSet, load_pairs  # noqa: E402
from torchcf.diagnose.loop import active_models  # noqa: E402
from torchcf.diagnose.selection.attribution import RoadStart, attribute_effects  # noqa: E402
from torchcf.diagnose.setup import LoopSetup  # noqa: E402
from torchcf.diagnose.signatures.road import profile_agreement  # noqa: E402
from torchcf.models import AugmentedModel, get_model, parse_effect  # noqa: E402
from torchcf.models.effects import RoadProfile  # noqa: E402
from torchcf.runs.directory import RunDir  # noqa: E402
from torchcf.sim.rollout import simulate  # noqa: E402
from torchcf.sim.synthetic import Gipps, synthetic_pairs  # noqa: E402
from torchcf.study.pipeline import close_loop, train_and_evaluate  # noqa: E402
from torchcf.system.console import OneLineParser, count, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
LLCTG = [1.0, 0.6, 0.8, 5.0]
#: a cautious IDM (long time gap, firm braking): with a 2 s delay the default
#: one crashes in the leaders' braking events
IDM_CAUTIOUS = [1.5, 4.0, 30.0, 2.5, 3.0, 4.0]
GIPPS = [1.5, 2.5, 3.0, 30.0, 0.8, 7.0]
#: Gipps (outside the pool) with a 1.2 s perception delay
GIPPS_DELAYED = AugmentedModel(Gipps(), [parse_effect("delay")])

#: sources of measured cases (the rest are synthetic)
MEASURED_SOURCES = ("car-model-2", "zalazone")
#: the eight models, for the measured ZalaZONE cases
EIGHT = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs", "hl", "mpc")

#: case -> (generating model, parameters, expected effects, {parameter: truth})
CASES = {
    "delay": ("idm+delay", IDM + [0.8], ["delay"], {"t_delay": 0.8}),
    "long delay": ("idm+delay", IDM_CAUTIOUS + [2.0], ["delay"], {"t_delay": 2.0}),
    "delay, Gipps outside the pool": (
        GIPPS_DELAYED,
        GIPPS + [1.2],
        ["delay"],
        {"t_delay": 1.2},
    ),
    "lag": ("llctg+lag", LLCTG + [1.0], ["lag"], {"t_lag": 1.0}),
    "offset": ("idm+offset", IDM + [-5.0], ["offset"], {"d_offset": -5.0}),
    "grade": (
        "llctg+grade(start=0,end=1200)",
        LLCTG + [0.05, -0.04, 0.05],
        ["grade"],
        {},
    ),
    "bend": (
        "idm+bend(start=0,end=1200)",
        IDM + [25.0, 12.0, 25.0],
        ["bend"],
        {},
    ),
    "action points": ("idm+action", IDM + [0.6, 0.1], ["action"], {}),
    "action points, 48 pairs": ("idm+action", IDM + [0.6, 0.1], ["action"], {}),
    "offset + delay": (
        "idm+offset+delay",
        IDM + [-4.0, 0.8],
        ["offset", "delay"],
        {"d_offset": -4.0, "t_delay": 0.8},
    ),
    "control (IDM)": ("idm", IDM, [], {}),
    "planted offset (CAR II)": ("car-model-2", [3.0], ["offset"], {}),
    "planted leader shift (CAR II)": ("car-model-2", [0.5], ["sync"], {}),
    "control (LLCTG)": ("llctg", LLCTG, [], {}),
    "control (CAR II, nothing planted)": ("car-model-2", [0.0], [], {}),
    "ZalaZONE ACC, as measured": ("zalazone", [0.0], [], {}),
    "ZalaZONE, leader positions +3 m": ("zalazone", [3.0], ["offset"], {}),
    "ZalaZONE, leader log 0.5 s ahead": ("zalazone", [0.5], ["sync"], {}),
    "ZalaZONE, grade planted": ("zalazone", [0.03], ["grade"], {}),
}
#: Planted recording effects: the parameter and its value that undo the plant,
#: and the tolerance of a recovery.
RECOVER = {
    "leader positions +3 m": ("d_offset", -3.0, 1.0),
    "planted offset": ("d_offset", -3.0, 1.0),
    "log 0.5 s ahead": ("t_sync", 0.5, 0.3),
    "leader shift": ("t_sync", 0.5, 0.3),
}
MEASURED = [name for name, case in CASES.items() if case[0] in MEASURED_SOURCES]


#: training pairs where a case does not use the default 24 (the guard's power)
TRAIN_PAIRS = {"action points, 48 pairs": 48}


def config(n_particles: int = 40_000, models=("idm", "llctg"), diagnose=None):
    """The cases' config; ``diagnose``: settings of the loop beside its
    defaults (``--diagnose KEY=JSON``)."""
    return validate_config(
        {
            "data": {"path": "synthetic"},
            "models": list(models),
            "abc": {"n_particles": n_particles, "sensitivity_n": [5]},
            "compile": "off",
            "diagnose": {"n_particles": n_particles, **(diagnose or {})},
        }
    )


def planted(pairs: PairSet, case: str, amount: float) -> PairSet:
    """Real pairs with a measurement effect planted: leader positions shifted by
    ``amount`` [m], or the leader's log advanced by ``amount`` [s] (the last
    steps, which have no leader record then, are cut)."""
    if amount == 0:
        return pairs
    if "offset" in case:
        return dataclasses.replace(pairs, x_lead=pairs.x_lead + amount)
    k = int(round(amount / pairs.dt))
    fields = {
        name: torch.cat((series[k:], series[-1:].expand(k, -1)))
        for name, series in pairs.series().items()
        if name.endswith("_lead")
    }
    valid = pairs.mask.sum(0) - k  # (N,) steps left per pair
    mask = torch.arange(pairs.n_steps)[:, None] < valid[None, :]
    return dataclasses.replace(pairs, **fields, mask=mask)


def plant_grade(pairs: PairSet, grade: float, seed: int) -> PairSet:
    """Measured pairs with a road grade planted: every follower's trajectory plus
    the closed-loop response of an ACC-like IDM to a profile of +-``grade``
    (``road_profile``), the pairs declared on one road.

    ``x' = x + (x_IDM+grade - x_IDM)`` (and so for speed and acceleration): the
    measured driving, moved by what the grade does to a controller that follows
    the same leader."""
    token, values = road_profile(pairs, grade, seed)
    theta = torch.tensor([ACC_IDM] * pairs.n_pairs, dtype=torch.float64)
    with_grade = torch.cat((theta, values.expand(pairs.n_pairs, -1)), dim=1)
    index = torch.arange(pairs.n_pairs)
    plain = simulate(
        get_model("idm"), theta, pairs, index, dtype=torch.float64, return_traj=True
    )
    graded = simulate(
        get_model(f"idm+{token}"),
        with_grade,
        pairs,
        index,
        dtype=torch.float64,
        return_traj=True,
    )
    fields = {
        "x_follow": pairs.x_follow + (graded.x - plain.x).to(pairs.x_follow.dtype),
        "v_follow": pairs.v_follow + (graded.v - plain.v).to(pairs.v_follow.dtype),
        "a_follow": pairs.a_follow + (graded.a - plain.a).to(pairs.a_follow.dtype),
    }
    moved = dataclasses.replace(pairs, **fields, road_frame=True)
    gap = moved.x_lead - moved.x_follow - moved.leader_length
    keep = ((gap > 0) | ~moved.mask).all(0) & (moved.v_follow >= 0).all(0)
    return moved.subset(keep.nonzero().squeeze(1))


#: An ACC-like IDM (a, b, v0, T, s0, delta) whose response to the grade is planted.
ACC_IDM = [1.5, 2.0, 40.0, 1.4, 3.0, 4.0]


#: The road section of the planted grade [m] (its first metres of every run),
#: and the distance between its knots [m]: a test track's short hills.
GRADE_SECTION = 1200.0
GRADE_KNOTS = 100.0


def road_profile(pairs: PairSet, grade: float, seed: int) -> tuple[str, Tensor]:
    """The planted grade: knots every ``GRADE_KNOTS`` over the road section,
    values +-``grade`` in a random order of signs (seeded)."""
    start, end = 0.0, GRADE_SECTION
    knots = int(end / GRADE_KNOTS) + 1
    generator = torch.Generator().manual_seed(seed)
    signs = torch.where(torch.rand(knots, generator=generator) < 0.5, -1.0, 1.0)
    return f"grade(start={start:g},end={end:g},knots={knots})", grade * signs.double()


def zalazone(
    raw: Path, cache: Path, within: float | None = None
) -> tuple[PairSet, PairSet]:
    """50 training and 20 test pairs of the ZalaZONE campaign (seeded draw);
    with ``within``, of the pairs whose followers stay within the first
    ``within`` metres of their run's road (one section, driven by many)."""
    source = cache / "zalazone"
    if not (source / "extract.json").exists():
        subprocess.run(
            [sys.executable, "-m", "torchcf", "data", "extract",
             str(raw / "openacc-zalazone-dynamic"), "--format", "openacc",
             "--out", str(source), "--overwrite"],
            check=True, capture_output=True,
        )  # fmt: skip
    generator = torch.Generator().manual_seed(0)
    out = []
    for split, n in (("train", 50), ("test", 20)):
        pairs = load_pairs(source, split=split)
        if within is not None:
            x = torch.where(pairs.mask, pairs.x_follow, -math.inf)
            pairs = pairs.subset((x.max(0).values < within).nonzero().squeeze(1))
        draw = torch.randperm(pairs.n_pairs, generator=generator)[:n]
        out.append(pairs.subset(draw))
    return out[0], out[1]


def case_pairs(
    name: str, cache: Path | None = None
) -> tuple[PairSet, PairSet, tuple[str, ...]]:
    """The case's (train, test) pairs and its pool."""
    model, theta, _, _ = CASES[name]
    if model in ("car-model-2",):
        train, test = (load_pairs(model, split=s) for s in ("train", "test"))
        train, test = (planted(p, name, theta[0]) for p in (train, test))
        return train, test, ("gfm", "idm", "hl")
    if model == "zalazone":
        raw = Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
        within = GRADE_SECTION if "grade" in name else None
        train, test = zalazone(raw, cache or Path(tempfile.gettempdir()), within)
        if "grade" in name:
            train, test = (plant_grade(p, theta[0], seed=0) for p in (train, test))
        else:
            kind = "offset" if "positions" in name else "shift"
            train, test = (planted(p, kind, theta[0]) for p in (train, test))
        return train, test, EIGHT
    n_train = TRAIN_PAIRS.get(name, 24)
    train = synthetic_pairs(get_model(model), theta, n_train, 500, seed=1, noise=0.05)
    test = synthetic_pairs(get_model(model), theta, 12, 500, seed=2, noise=0.05)
    return train, test, ("idm", "llctg")


def run_case(name: str, cache: Path, diagnose: dict | None = None) -> dict:
    model, theta, expected, truth = CASES[name]
    train, test, pool = case_pairs(name, cache)
    particles = 200_000 if model == "zalazone" else 40_000
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        cfg = config(particles, models=pool, diagnose=diagnose)
        train_and_evaluate(cfg, out, pairs=(train, test))
        trained = time.perf_counter()
        result = close_loop(out, pairs=(train, test), progress=False)
        looped = time.perf_counter() - trained
        chosen = [effect.name for effect in result.chosen]
        loop = result.to_json()  # the record this table keeps
        oracle = None
        if model == "zalazone" and "grade" in name and "grade" not in chosen:
            oracle = truth_seeded_arm(out, train, theta[0])
    recovered = {
        param: stats["median"]
        for summary in loop["posterior"].values()
        for param, stats in summary["params"].items()
        if stats.get("n")
    }
    rows = {row["name"]: row for row in loop["steps"][0]} if loop["steps"] else {}
    best = max(loop["steps"][0], key=lambda r: r["gain"]) if rows else {}
    recovery = recovery_of(name, rows, recovered)
    right = sorted(chosen) == sorted(expected)
    if recovery is not None and not right and not chosen:
        right = recovery["absorbed"]  # reported as absorbed by a named parameter
    return {
        "case": name,
        "model": model if isinstance(model, str) else model.name,
        "expected": expected,
        "chosen": chosen,
        "right": right,
        "truth": truth,
        "recovered": {k: recovered.get(k) for k in truth},
        "recovery": recovery,
        "profile_correlation": profile_correlation(
            model, theta, loop["chosen"], recovered, train
        ),
        "best_first_step": {
            "effect": best.get("effect"),
            "gain": best.get("gain"),
            "p_value": best.get("p_value"),
            "level": best.get("level"),
            "order": best.get("order"),
        },
        "found_signatures": [
            m["signature"] for m in (loop["signatures"] or [[]])[0] if m["found"]
        ],
        "n_effects": len(loop["effects_ranked"]),
        "n_train": train.n_pairs,
        "n_test": test.n_pairs,
        "ws": [loop["before"].get("ws"), loop["after"].get("ws")],
        "min": [loop["before"].get("min"), loop["after"].get("min")],
        "same_search": [
            (loop["before_same_search"] or loop["before"]).get(key)
            for key in ("ws", "min")
        ],
        "identifiability": loop["identifiability"],
        "truth_seeded": oracle,
        "loop_seconds": looped,
        "seconds": time.perf_counter() - began,
    }


def recovery_of(name: str, rows: dict, recovered: dict) -> dict | None:
    """A planted recording effect: its estimate (chosen: the re-calibrated
    posterior's median; else the first step's), whether it is within the
    tolerance, and what absorbs it."""
    key = next((k for k in RECOVER if k in name), None)
    if key is None:
        return None
    param, value, tolerance = RECOVER[key]
    effect = "offset" if param == "d_offset" else "sync"
    row = rows.get(effect, {})
    estimate = recovered.get(param, (row.get("estimate") or {}).get(param))
    absorbed = row.get("absorbed_by") or {}
    return {
        "parameter": param,
        "plant": value,
        "estimate": estimate,
        "within": estimate is not None and abs(estimate - value) <= tolerance,
        "tolerance": tolerance,
        "absorbed": bool(absorbed.get("absorbed")),
        "absorbed_by": absorbed or None,
    }


def truth_seeded_arm(run_dir: Path, train: PairSet, grade: float) -> dict:
    """Whether the planted grade can be found in these data at all: the
    attribution's arm of the planted profile itself (its knots), its search
    started from the planted values, alone (level alpha). A missed plant whose
    truth-seeded arm is not significant either is not detectable in the data:
    the pool's misfit of the measured driving hides it, whatever the loop's
    trace and knot spacing."""
    cfg, posterior, _ = RunDir(run_dir).load_run()
    token, values = road_profile(train, grade, seed=0)
    profile = parse_effect(token)
    selection = attribute_effects(
        LoopSetup.of(cfg),
        active_models(cfg, posterior),
        [profile],
        train,
        road=RoadStart({profile: values}, profile),
        progress=False,
    )
    row = selection.steps[0][0]
    return {
        "effect": token,
        "fit_gain": row.fit_gain,
        "gain": row.gain,
        "p_value": row.p_value,
        "level": row.level,
        "significant": bool(row.significant),
    }


def profile_correlation(
    model, theta, chosen: list[str], recovered: dict[str, float], pairs: PairSet
) -> float | None:
    """Correlation of the chosen road profile (knots at their posterior medians)
    with the generating one at the training followers' recorded positions; None
    when the case has no road effect or none was chosen."""
    if model == "car-model-2":
        return None  # real pairs: no road profile planted
    if model == "zalazone":
        if not theta[0] or "grade" not in "".join(chosen):
            return None
        token, values = road_profile(pairs, theta[0], seed=0)
        names = get_model(f"idm+{token}").param_names[-values.numel() :]
        truth = dict(zip(names, values.tolist(), strict=True))
        fitted = next(c for c in chosen if c.startswith("grade"))
        grid = pairs.x_follow[pairs.mask][::10].double()
        return profile_agreement(token, truth, fitted, recovered, grid)
    truth_model = get_model(model)
    true_effect = next(
        (e for e in getattr(truth_model, "effects", ()) if isinstance(e, RoadProfile)),
        None,
    )
    if true_effect is None:
        return None
    token = next((c for c in chosen if parse_effect(c).name == true_effect.name), None)
    if token is None:
        return None
    # every 10th recorded follower position: the road weighted by how much of
    # the data was driven there (a profile is only learned where data are)
    grid = pairs.x_follow[pairs.mask][::10].double()
    truth = dict(zip(truth_model.param_names, theta, strict=True))
    return profile_agreement(true_effect.token, truth, token, recovered, grid)


#: The re-calibration, as the table's header says it.
RECALIBRATION = {
    "train": "re-calibration: the pool's variants trained as the run trained its "
    "models, beside the run, against the pool given as many more draws",
    "search": "re-calibration: local search from the run's particles beside the "
    "same search without the effects",
}


def _recalibration(payload: dict) -> str:
    """How the payload's loops re-calibrated (reports written before the
    setting existed: by local search)."""
    return payload.get("recalibration", "search")


def markdown(payload: dict) -> str:
    meta = payload["meta"]
    lines = [
        "# The loop on data with undeclared effects",
        "",
        f"`{meta['command']}`; torch {meta['torch']}, {meta['threads']} threads, "
        f"git {meta['git']}. The loop at its defaults"
        + "".join(f", {k} = {v}" for k, v in payload.get("diagnose", {}).items())
        + " "
        f"({payload['cases'][0]['n_effects']} candidate effects where the pairs "
        "share a road, forward selection of nested arms against a placebo, the "
        "fallback procedure at alpha 0.05 over at most 3 steps; "
        + RECALIBRATION[_recalibration(payload)]
        + "). WS and minimum distance on the test split: the run -> after "
        "(before, searched as after, in brackets). Cases: see "
        "`tools/loop_cases.py`.",
        "",
        "| case | pairs | expected | chosen | right | recovered (truth) | "
        "best first-step test | WS | min distance | loop |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in payload["cases"]:
        recovered = ", ".join(
            f"{k} {_fmt(v)} ({row['truth'][k]:g})" for k, v in row["recovered"].items()
        )
        if row.get("profile_correlation") is not None:
            recovered += f"profile r {row['profile_correlation']:.2f} with the truth"
        if row.get("recovery"):
            recovered += _recovery_text(row["recovery"])
        if row.get("truth_seeded"):
            seeded = row["truth_seeded"]
            recovered += (
                f"the planted profile's own arm, seeded at the truth: "
                f"{seeded['gain']:+.1%} (in sample {seeded['fit_gain']:+.1%}), "
                f"p {seeded['p_value']:.2g} at level {seeded['level']:.2g}"
                + ("" if seeded["significant"] else ": not detectable in these data")
            )
        first = row["best_first_step"]
        test = (
            f"{first['effect']} {first['gain']:+.1%}, p {first['p_value']:.2g} "
            f"(tested {first['order']}., level {first['level']:.2g})"
            if first.get("effect")
            else "-"
        )
        lines.append(
            f"| {row['case']} | {row['n_train']}/{row['n_test']} | "
            f"{', '.join(row['expected']) or 'none'} | "
            f"{', '.join(row['chosen']) or 'none'} | "
            f"{'yes' if row['right'] else '**no**'} | {recovered} | {test} | "
            f"{_fmt(row['ws'][0])} -> {_fmt(row['ws'][1])} "
            f"({_fmt(row['same_search'][0])}) | "
            f"{_fmt(row['min'][0])} -> {_fmt(row['min'][1])} "
            f"({_fmt(row['same_search'][1])}) | {row['loop_seconds']:.0f} s |"
        )
    right = sum(row["right"] for row in payload["cases"])
    lines += ["", f"Right in {right} of {len(payload['cases'])} cases."]
    hidden = [
        row["case"]
        for row in payload["cases"]
        if row.get("truth_seeded") and not row["truth_seeded"]["significant"]
    ]
    if hidden:
        lines += [
            "",
            "Missed and not detectable even from the truth (the planted "
            "profile's own arm, its search started at the planted values, is not "
            f"significant): {', '.join(hidden)}.",
        ]
    return "\n".join(lines) + "\n"


def _recovery_text(recovery: dict) -> str:
    text = (
        f"{recovery['parameter']} {_fmt(recovery['estimate'])} "
        f"(undoes the plant at {recovery['plant']:g})"
    )
    found = recovery.get("absorbed_by")
    if found:
        text += (
            f"; absorbed by {found['model']}'s {found['parameter']}: r "
            f"{found['correlation']:+.2f}, slope {_fmt(found.get('slope'))}"
            if found["absorbed"]
            else f"; separable (strongest partner {found['parameter']}, r "
            f"{found['correlation']:+.2f})"
        )
    return text


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    synthetic = [name for name in CASES if name not in MEASURED]
    parser.add_argument("--group", choices=("synthetic", "measured"), default=None)
    parser.add_argument("--cases", nargs="+", default=None, choices=CASES)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--name", default=None)
    parser.add_argument(
        "--diagnose",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="a loop setting beside the defaults, e.g. validation='\"pairs\"'",
    )
    args = parser.parse_args(argv)
    diagnose = {}
    for item in args.diagnose:
        key, _, value = item.partition("=")
        diagnose[key] = json.loads(value)
    torch.set_num_threads(args.threads)
    group = args.group or "synthetic"
    cases = args.cases or (MEASURED if group == "measured" else synthetic)
    name = args.name or ("loop_cases_measured" if group == "measured" else "loop_cases")
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for case in cases:
            row = run_case(case, Path(cache), diagnose)
            print(
                f"{case}: chosen {row['chosen']} (expected {row['expected']}), "
                f"loop {row['loop_seconds']:.0f} s",
                file=sys.stderr,
            )
            rows.append(row)
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "diagnose": diagnose,
        "recalibration": diagnose.get(
            "recalibration", DiagnoseConfig.model_fields["recalibration"].default
        ),
        "cases": rows,
    }
    write_report(REPORTS / name, payload, markdown(payload))
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
