"""Prediction of drivers a run never saw, scored as the field scores calibrations.

For each case a run is trained (the eight models, ``--particles`` per model:
by default the paper's 1e6 on NGSIM I-80, 2e5 on the whole couples, whose
rollouts are 20 times longer),
then ``torchcf.predict.predict`` predicts its test pairs: the population model
(one vector per model, searched from the kept particles), the hybrid's median
and bands over ``--draws`` draws, and each driver's own posterior after
``--history`` seconds. Beside them, the published method on the same pairs: a
pooled calibration of IDM by differential evolution over its prior box
(scipy, mean spacing RMSE over the training pairs, as Punzo et al. and the
studies after them calibrate), and, where a study published figures on the same
site, those figures (other couples: context, not a like-for-like).

Cases (``$TORCHCF_DATA`` for the paper's data, ``$TORCHCF_RAW`` for the raw
OpenACC campaigns):

- **NGSIM I-80** (the paper's split: 105 / 45 windows of 35 s, feet converted);
- **ZalaZONE, whole couples** (``openacc-zalazone-dynamic``, ``data extract
  --window whole``, split by run, 30 % test);
- **Casale, whole couples** (``openacc-casale`` likewise).

    python tools/bench_predict.py
    python tools/bench_predict.py --cases "NGSIM I-80" --particles 200000
    python tools/bench_predict.py --design   # the conditioning designs, NGSIM I-80

``--design``: on NGSIM I-80's run, every way of conditioning on a history
(rejection keeping 20 / 100 / 300 of the hybrid's particles, with and without
a per-pair search; shrinkage toward the history around each of the three best
pooled vectors at each strength; ``auto``, the design best on the training
pairs as if new) at 5, 10 and 20 s of history, against the population model
restarted at the same step.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import differential_evolution

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import bench_meta, provenance, write_report  # noqa: E402
from loop_cases import EIGHT  # noqa: E402

from torchcf.config import validate_config  # noqa: E402
from torchcf.data import PairSet, load_pairs  # noqa: E402
from torchcf.models import get_model  # noqa: E402
from torchcf.predict import PredictSettings, TrainedRun, predict  # noqa: E402
from torchcf.predict.population import pooled_objective  # noqa: E402
from torchcf.study.pipeline import train_and_evaluate  # noqa: E402
from torchcf.system.console import OneLineParser, count, positive, run_main  # noqa: E402

REPORTS = Path(__file__).resolve().parents[1] / "reports"
CASES = ("NGSIM I-80", "ZalaZONE, whole couples", "Casale, whole couples")
#: Particles per model of each case's run (``--particles`` overrides).
PARTICLES = {"NGSIM I-80": 1_000_000}
WHOLE_PARTICLES = 200_000
#: Published pooled calibrations on NGSIM I-80 (whole couples, other than the
#: paper's windows): mean spacing RMSE [m] per model, as the issue quotes them.
PUBLISHED = {"NGSIM I-80": "Gipps, IDM pooled by differential evolution: 3.17-3.18 m "
             "(IDM 3.18-3.69 m) on 20 whole test couples of 50-160 s"}  # fmt: skip


def case_pairs(name: str, cache: Path) -> tuple[PairSet, PairSet]:
    """The case's training and test pairs."""
    if name == "NGSIM I-80":
        return load_pairs("ngsim-i80", split="train"), load_pairs(
            "ngsim-i80", split="test"
        )
    raw = Path(os.environ.get("TORCHCF_RAW", "../shared/data/raw"))
    source = {"ZalaZONE": "openacc-zalazone-dynamic", "Casale": "openacc-casale"}[
        name.split(",")[0]
    ]
    out = cache / f"{source}-whole"
    if not (out / "extract.json").exists():
        subprocess.run(
            [sys.executable, "-m", "torchcf", "data", "extract", str(raw / source),
             "--format", "openacc", "--window", "whole", "--split-by", "run",
             "--test-fraction", "0.3", "--out", str(out), "--overwrite"],
            check=True, capture_output=True,
        )  # fmt: skip
    return load_pairs(out, split="train"), load_pairs(out, split="test")


def config(particles: int) -> object:
    return validate_config(
        {
            "data": {"path": "bench"},  # unused: the pairs are passed
            "models": list(EIGHT),
            "abc": {"n_particles": particles, "top_n": 5, "sensitivity_n": [5]},
            "compile": "off",
        }
    )


def pooled_de(train: PairSet, test: PairSet, seed: int = 0) -> dict:
    """IDM pooled by differential evolution on ``train`` (mean spacing RMSE),
    and its per-pair spacing RMSE on ``test``."""
    model = get_model("idm")
    prior = model.prior_bounds(torch.float64)

    def objective(theta: np.ndarray) -> np.ndarray:  # (K, S): a generation at once
        collided, mean = pooled_objective(model, torch.from_numpy(theta.T), train)
        penalty = torch.full_like(mean, 1e3)
        return torch.where(collided > 0, penalty + collided, mean).numpy()

    began = time.perf_counter()
    found = differential_evolution(
        objective, prior.numpy(), vectorized=True, updating="deferred",
        maxiter=100, popsize=15, seed=seed, polish=False, tol=1e-6,
    )  # fmt: skip
    collided, _ = pooled_objective(model, torch.from_numpy(found.x[None]), train)
    from torchcf.sim.rollout import simulate

    out = simulate(model, torch.from_numpy(found.x[None]).expand(test.n_pairs, -1),
                   test, torch.arange(test.n_pairs), dtype=torch.float64)  # fmt: skip
    rmse = out.e_p.numpy()
    ok = np.isfinite(rmse)
    return {
        "params": dict(zip(model.param_names, found.x.tolist(), strict=True)),
        "train_objective": float(found.fun),
        "train_collided": int(collided[0]),
        "test_mean": float(rmse[ok].mean()) if ok.any() else None,
        "test_median": float(np.median(rmse[ok])) if ok.any() else None,
        "test_collided": int((~ok).sum()),
        "vectors": int((found.nit + 1) * 15 * model.n_params),
        "seconds": time.perf_counter() - began,
    }


def run_case(name: str, cache: Path, args) -> dict:
    train, test = case_pairs(name, cache)
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        particles = args.particles or PARTICLES.get(name, WHOLE_PARTICLES)
        train_and_evaluate(config(particles), out, pairs=(train, test))
        trained = time.perf_counter() - began
        run = TrainedRun.load(out, train=train)
        settings = PredictSettings(draws=args.draws, history=args.history, seed=0)
        found = predict(run, test, settings, data=name)
    summary = found.summary.to_json()
    lengths = (test.lengths.numpy() - 1) * test.dt
    return {
        "case": name,
        "particles": particles,
        "n_train": train.n_pairs,
        "n_test": test.n_pairs,
        "test_seconds": [
            float(lengths.min()),
            float(np.median(lengths)),
            float(lengths.max()),
        ],
        "train_seconds": trained,
        "prediction": summary,
        "de_idm": pooled_de(train, test),
        "published": PUBLISHED.get(name),
    }


def design_grid(args) -> dict:
    """The conditioning designs on NGSIM I-80's test pairs (module docstring)."""
    from torchcf.predict.conditioning import Design, designs, judged, rest_scores
    from torchcf.predict.history import predictable
    from torchcf.predict.population import pooled_fits, population_model
    from torchcf.predict.predict import _one_vector
    from torchcf.predict.rollouts import steps_between
    from torchcf.predict.scores import summarize_rmse

    train, test = case_pairs("NGSIM I-80", args.cache)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "run"
        particles = args.particles or PARTICLES["NGSIM I-80"]
        train_and_evaluate(config(particles), out, pairs=(train, test))
        run = TrainedRun.load(out, train=train)
    models = run.models
    fits = pooled_fits(models, {m.name: run.kept(m) for m in models}, run.priors, train)
    chosen = population_model(fits)
    grid = [
        (Design("rejection"), 20, 0),
        (Design("rejection"), 100, 0),
        (Design("rejection"), 300, 0),
        (Design("rejection"), 20, 8),
        (Design("rejection"), 100, 8),
        *[(d, 100, 0) for d in designs("shrinkage", fits)],
    ]
    for history in (5.0, 10.0, 20.0):
        usable = torch.nonzero(predictable(test, history)).squeeze(1)
        some = test.subset(usable.tolist())
        k = int(round(history / test.dt))
        rest = steps_between(some, k)
        population, _ = summarize_rmse(
            _one_vector(chosen, rest) - rest.x_follow.double(), rest.mask
        )
        auto, on_train = judged(
            run, designs("auto", fits), history, keep=100, refine=0, seed=0
        )
        for design, keep, refine in grid:
            plain = refine == 0 and keep == 100
            posterior = design.posterior(
                run, some, history, keep=keep, refine=refine, seed=0
            )
            found = rest_scores(posterior, some)[0]
            rows.append({
                "history": history,
                "design": design.label,
                "keep": keep if design.kind == "rejection" else None,
                "refine": refine,
                "test_mean": found.mean,
                "population_mean": population.mean,
                "change": found.mean / population.mean - 1,
                "judged_on_train": on_train.get(design.label) if plain else None,
                "auto": plain and design.label == auto.label,
            })  # fmt: skip
            print(f"{history:g} s {design.label} keep {keep} refine {refine}: "
                  f"{rows[-1]['change']:+.1%}", file=sys.stderr)  # fmt: skip
    return {"chosen": chosen.model, "rows": rows}


def design_markdown(payload: dict) -> str:
    lines = [
        "# Conditioning on a history: the designs",
        "",
        f"{provenance(payload['meta'])}; NGSIM I-80 (the paper's split, 105 / "
        f"45 windows of 35 s), {payload['particles']:g} particles per model; the "
        f"population model ({payload['grid']['chosen']}) restarted at the "
        "history's end beside each. Mean spacing RMSE [m] over the rest of the "
        "test pairs; *on training*: the design's score on the training pairs as "
        "if new, by which `auto` chooses (marked **auto**).",
        "",
        "| history [s] | design | kept | search rounds | own | population "
        "restarted | change | on training |",
        "|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for row in payload["grid"]["rows"]:
        label = f"**{row['design']}** (auto)" if row["auto"] else row["design"]
        lines.append(
            f"| {row['history']:g} | {label} | {row['keep'] or '-'} | "
            f"{row['refine']} | {_f(row['test_mean'])} | "
            f"{_f(row['population_mean'])} | {_pct(row['change'])} | "
            f"{_f(row['judged_on_train'])} |"
        )
    return "\n".join(lines) + "\n"


def markdown(payload: dict) -> str:
    lines = [
        "# Prediction of drivers the run never saw",
        "",
        f"{provenance(payload['meta'])}; particles per model: "
        + ", ".join(f"{c['case']} {c['particles']:g}" for c in payload["cases"])
        + f"; {payload['draws']} draws per pair, {payload['history']:g} s of "
        "history. Spacing RMSE per test pair [m], mean (median); every prediction "
        "starts from the pair's recorded state behind its recorded leader.",
        "",
        "| case | pairs (train / test), test length [s] | population model | "
        "DE-pooled IDM (published method) | the hybrid's median | one draw at a "
        "time | after the history: own posterior / population restarted "
        "(change) | bands: 50 % / 90 % coverage | min ADE / FDE [m] | draws "
        "collided | published |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for row in payload["cases"]:
        p = row["prediction"]
        pop, bands, hist, de = p["population"], p["bands"], p["history"], row["de_idm"]
        t = row["test_seconds"]
        lines.append(
            f"| {row['case']} | {row['n_train']} / {row['n_test']}, "
            f"{t[0]:.0f}-{t[2]:.0f} (median {t[1]:.0f}) | "
            f"{_m(pop['spacing_rmse'])} ({pop['chosen']}) | "
            f"{_f(de['test_mean'])} ({_f(de['test_median'])}) | "
            f"{_m(bands['median'])} | {_f(bands['per_draw'])} | "
            + (
                f"{_m(hist['conditioned'])} / {_m(hist['population'])} "
                f"({_pct(hist['change'])}, {hist['pairs']} pairs)"
                if hist
                else "-"
            )
            + f" | {bands['coverage_50']:.1%} / {bands['coverage_90']:.1%} | "
            f"{_f(bands['min_ade'])} / {_f(bands['min_fde'])} | "
            f"{bands['collisions']:.1%} | {row['published'] or '-'} |"
        )
    lines += [
        "",
        "Each model's pooled vector on the test pairs, mean (median) [m]:",
        "",
    ]
    for row in payload["cases"]:
        by = row["prediction"]["population"]["by_model"]
        lines.append(
            f"- **{row['case']}**: " + "; ".join(f"{k} {_m(v)}" for k, v in by.items())
        )
    lines += ["", "Times [s]:", ""]
    for row in payload["cases"]:
        lines.append(
            f"- **{row['case']}**: training {row['train_seconds']:.0f}, prediction "
            f"{row['prediction']['seconds']:.0f}, DE-pooled IDM "
            f"{row['de_idm']['seconds']:.0f} ({row['de_idm']['vectors']} vectors)"
        )
    return "\n".join(lines) + "\n"


def _m(rmse: dict) -> str:
    return f"{_f(rmse['mean'])} ({_f(rmse['median'])})"


def _f(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _pct(value) -> str:
    return "-" if value is None else f"{value:+.1%}"


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--particles", type=count, default=None)
    parser.add_argument("--draws", type=count, default=200)
    parser.add_argument("--history", type=positive, default=10.0)
    parser.add_argument("--threads", type=count, default=2)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()))
    parser.add_argument("--name", default=None)
    parser.add_argument(
        "--design", action="store_true", help="the conditioning designs (NGSIM I-80)"
    )
    args = parser.parse_args(argv)
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {unknown}; one of {list(CASES)}")
    torch.set_num_threads(args.threads)
    if args.design:
        payload = {
            "meta": bench_meta(sys.argv, args.threads),
            "particles": args.particles or PARTICLES["NGSIM I-80"],
            "grid": design_grid(args),
        }
        out = REPORTS / (args.name or "predict_design")
        write_report(out, payload, design_markdown(payload))
        print(f"wrote {out}.md", file=sys.stderr)
        return 0
    args.name = args.name or "predict"
    payload = {
        "meta": bench_meta(sys.argv, args.threads),
        "particles": args.particles,
        "draws": args.draws,
        "history": args.history,
        "cases": [],
    }
    for name in args.cases:
        print(f"{name} ...", file=sys.stderr, flush=True)
        payload["cases"].append(run_case(name, args.cache, args))
        write_report(REPORTS / args.name, payload, markdown(payload))
    print(f"wrote {REPORTS / args.name}.md", file=sys.stderr)
    print(json.dumps([c["case"] for c in payload["cases"]]), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
