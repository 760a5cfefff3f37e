"""Closing the loop (torchcf.diagnose) on data with undeclared effects.

Synthetic pairs are generated here from a model plus effects the engine is not
told about (torchcf.sim.synthetic); the pool (IDM, LLCTG) is calibrated without
them, and the loop must choose them, recover their parameters and lower the
test WS and minimum distance by >= 15 % against the pool searched the same way.
Control sets without an effect must give "none".

Covered: a 0.8 s perception delay on IDM, a 1 s actuation lag on LLCTG, a -5 m
spacing-sensor offset on IDM, a road grade (+5 % / -4 % / +5 % over 1200 m)
under LLCTG, a 1.2 s delay on a Gipps follower (outside the pool), a -4 m
offset with a 0.8 s delay together, and two controls (IDM, LLCTG).
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from torchcf.abc.particles import Particles, best_per_pair
from torchcf.abc.rejection import prior_stream
from torchcf.cli.diagnose import main
from torchcf.config import ConfigError, resolved_json, validate_config
from torchcf.diagnose import (
    DiagnoseError,
    Population,
    best_particles,
    residual_series,
    resolve_effect,
    reusable,
    split_in_time,
)
from torchcf.diagnose.arms.candidates import (
    prior_particles,
)
from torchcf.diagnose.arms.search import Noise, model_bounds
from torchcf.diagnose.setup import LoopSetup
from torchcf.diagnose.signatures.road import profile_agreement
from torchcf.models import AugmentedModel, get_model, parse_effect, split_name
from torchcf.posterior import Posterior
from torchcf.sim.synthetic import Gipps, Scene, synthetic_pairs
from torchcf.study.pipeline import close_loop, train_and_evaluate
from torchcf.train import train

IDM_TRUTH = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
LLCTG_TRUTH = [1.0, 0.6, 0.8, 5.0]
GIPPS_TRUTH = [1.5, 2.5, 3.0, 30.0, 0.8, 7.0]

#: case -> (generating model, true parameters, the effects to choose,
#: {added parameter: (truth, tolerance)})
CASES = {
    "delay": ("idm+delay", IDM_TRUTH + [0.8], ["delay"], {"t_delay": (0.8, 0.2)}),
    "lag": ("llctg+lag", LLCTG_TRUTH + [1.0], ["lag"], {"t_lag": (1.0, 0.25)}),
    # A recording effect, one value for every pair; IDM's time gap takes part
    # of it up (the loop says so: absorbed_by), so the value is checked as the
    # issue asks: within 1 m, or reported absorbed by a named parameter.
    "offset": (
        "idm+offset",
        IDM_TRUTH + [-5.0],
        ["offset"],
        {"d_offset": (-5.0, 1.0)},
    ),
    # The profile's knots differ from those the loop fits (it spans the pairs'
    # road section): the profiles are compared where the followers drove.
    "grade": (
        "llctg+grade(start=0,end=1200)",
        LLCTG_TRUTH + [0.05, -0.04, 0.05],
        ["grade"],
        {},
    ),
    # No pool model is Gipps: the pool's IDM + delay stands in for Gipps' own
    # relaxation over tau as well, so the delay comes out short (0.7 s in
    # reports/loop_cases.md) and is not checked; the choice and the gain are.
    "delay, Gipps": (
        AugmentedModel(Gipps(), [parse_effect("delay")]),
        GIPPS_TRUTH + [1.2],
        ["delay"],
        {},
    ),
    "offset + delay": (
        "idm+offset+delay",
        IDM_TRUTH + [-4.0, 0.8],
        ["offset", "delay"],
        {"d_offset": (-4.0, 1.0), "t_delay": (0.8, 0.2)},
    ),
    "control": ("idm", IDM_TRUTH, [], {}),
    "control, LLCTG": ("llctg", LLCTG_TRUTH, [], {}),
}
FOUND = [case for case, (_, _, expected, _) in CASES.items() if expected]
#: Effects a case may choose beside the expected ones. Gipps is not in the
#: pool: with every training pair a unit of the test (cross-fitting), the
#: pool's IDM + delay also takes asymmetric gains (Gipps brakes and speeds up
#: by different laws), which fit the same class of drivers better; the time
#: design, half as powerful on 24 pairs, chose the delay alone.
ALSO = {"delay, Gipps": ("asymmetry",)}
#: Per model (training) and per variant (attribution): ~1700 per pair in the paired
#: layout, enough to resolve the effects above.
N_PARTICLES = 40_000
#: The candidates of these tests: every case's effect and its nearest rivals (a
#: clock offset for a delay, a lag for both, a sensor offset, a road grade, and
#: an effect of two parameters); tools/loop_cases.py tries them all.
EFFECTS = ["sync", "offset", "delay", "lag", "asymmetry", "grade"]
#: A lighter search than the defaults (the defaults: reports/loop_cases.md).
SEARCH = {"population": 12, "local_copies": 24, "rounds": 6, "max_rounds": 20}


def _config(n_particles=N_PARTICLES, **diagnose):
    return validate_config(
        {
            "data": {"path": "synthetic"},  # unused: the tests pass the pairs
            "models": ["idm", "llctg"],
            "abc": {"n_particles": n_particles, "sensitivity_n": [5]},
            "compile": "off",
            "diagnose": {"n_particles": n_particles // 2, **diagnose},
        }
    )


def _loop_config(detectable=True):
    return _config(effects=EFFECTS, detectable=detectable, **SEARCH)


def _pairs(model, theta):
    train_pairs = synthetic_pairs(get_model(model), theta, 24, 500, seed=1, noise=0.05)
    test_pairs = synthetic_pairs(get_model(model), theta, 12, 500, seed=2, noise=0.05)
    return train_pairs, test_pairs


@pytest.fixture(scope="module")
def loops(tmp_path_factory):
    """Run the whole loop once per case (shared by the assertions below)."""
    results = {}

    def run(case):
        if case not in results:
            model, theta, expected, _ = CASES[case]
            pairs = _pairs(model, theta)
            out = tmp_path_factory.mktemp(case.replace(" ", "")) / "run"
            # the sizes the data could have shown: asked of the controls (the
            # last step of the others is a control of the same kind)
            config = _loop_config(detectable=not expected)
            train_and_evaluate(config, out, pairs=pairs)
            results[case] = (out, close_loop(out, pairs=pairs, progress=False))
        return results[case]

    return run


@pytest.mark.slow  # a whole loop per case: 40-90 s each on 2 cores
@pytest.mark.parametrize("case", FOUND)
def test_the_undeclared_effects_are_found_and_help(loops, case):
    out, result = loops(case)
    _, _, expected, truths = CASES[case]
    first = result.selection.steps[0]
    chosen = next(r for r in first if r.chosen)
    assert chosen.name in expected and chosen.significant
    assert chosen.p_value <= chosen.level or chosen.family_p_value <= chosen.level
    assert chosen.active
    names = [e.name for e in result.chosen]
    assert sorted(n for n in names if n not in ALSO.get(case, ())) == sorted(expected)
    # the model class with the effects fits the test drivers better, refitted
    on_test = result.class_on_test
    assert on_test.change < 0 and on_test.p_value <= 0.05, on_test
    # against the reference (the run with as many more draws, without the
    # effects): the effects' share of the improvement; and against the run
    # itself. Trained by the run's sampler (the default re-calibration) the
    # variants keep the prior draws' spread: the minimum distance falls by
    # 40-65 % here (tools/loop_cases.py: reports/loop_cases_train.md), WS by
    # 10-35 % (the Gipps follower, outside the pool, the least).
    recalibrated = result.recalibrated
    after = result.after.metrics
    for before in (recalibrated.before_same_search.metrics, result.before.metrics):
        assert before.ws > 0
        assert after.ws <= 0.93 * before.ws
        assert after.min <= 0.85 * before.min
    paired_on_test = recalibrated.test_pairs
    for paired in (paired_on_test.run, paired_on_test.reference):  # significantly
        assert paired.change < 0 and paired.p_value <= 0.05
    medians = {
        name: stats.median
        for summary in recalibrated.posterior.values()
        for name, stats in summary.params.items()
        if stats.n
    }
    for name, (truth, tolerance) in truths.items():
        if name == "d_offset":  # recovered, or absorbed by a named parameter
            row = next(r for r in first if r.token == "offset")
            found = row.absorbed_by
            assert abs(medians[name] - truth) <= tolerance or found.absorbed, (
                medians[name],
                found,
            )
            continue
        assert abs(medians[name] - truth) <= tolerance, (name, medians[name])
    if case == "grade":
        model, theta, _, _ = CASES[case]
        train_pairs, _ = _pairs(model, theta)
        truth = dict(zip(get_model(model).param_names, theta, strict=True))
        where = train_pairs.x_follow[train_pairs.mask][::10]
        (chosen,) = result.chosen
        token = split_name(model)[1]
        assert profile_agreement(token, truth, chosen.token, medians, where) >= 0.8
    on_disk = json.loads((out / "loop.json").read_text())
    assert on_disk["chosen"] == result.to_json()["chosen"]
    for key in (
        "signatures",
        "effects_ranked",
        "absorption",
        "chosen",
        "posterior",
        "before",
        "before_same_search",
        "after",
    ):
        assert key in on_disk
    text = (out / "loop.md").read_text()
    assert "WS change" in text and "From the residual to the effects" in text
    # the calibrated models' response behind a standard perturbation, before
    # and after, beside the data's on the recorded pairs
    assert "behind a standard perturbation" in text
    for times in (result.response_before, recalibrated.response_after):
        assert times.perturbation_pairs > 0 and 0 < times.perturbation < 8
    if "offset" in case:  # a recording effect: its behavioural twin named
        assert "the data's fault or the drivers' habit?" in text
        assert "To separate them" in text
    assert (out / "loop" / "after" / "metrics.json").exists()
    assert (out / "loop" / "reference" / "metrics.json").exists()
    for figure in ("effects", "before_after", "residuals"):
        assert (out / "loop" / f"{figure}.png").stat().st_size > 0


@pytest.mark.slow  # a second loop on the delay case's run
def test_held_out_pairs_find_the_delay_and_carry_it_to_the_test_split(loops, tmp_path):
    """validation='pairs' (10 of the 24 pairs held out, whole windows): the
    delay is chosen by its minimum distance on pairs no arm saw, and it carries
    to the test split."""
    trained, _ = loops("delay")
    out = tmp_path / "run"
    shutil.copytree(trained, out, ignore=shutil.ignore_patterns("loop*"))
    pairs = _pairs(*CASES["delay"][:2])
    result = close_loop(
        out, ['diagnose.validation="pairs"'], pairs=pairs, progress=False
    )
    validation = result.selection.validation
    assert (validation.kind, validation.units) == ("pairs", 10)
    assert validation.fit_pairs == 14
    assert [e.name for e in result.chosen] == ["delay"]
    reference = result.recalibrated.before_same_search
    assert result.after.metrics.min <= 0.85 * reference.metrics.min
    assert "held-out pairs" in (out / "loop.md").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("case", ["control", "control, LLCTG"])
def test_control_set_yields_no_effect(loops, case):
    out, result = loops(case)
    assert result.chosen == [] and result.recalibrated is None
    assert result.after == result.before
    text = (out / "loop.md").read_text()
    assert "No effect chosen" in text
    # what these data could have shown, per effect with a one-number size
    assert "What these data could have shown" in text
    last = result.selection.steps[-1]
    sized = [r for r in last if r.name in ("delay", "lag", "sync")]
    assert sized and all(r.detectable for r in sized)
    delay = next(r for r in sized if r.name == "delay").detectable
    assert delay.if_first["above"] is not None  # 24 pairs can show a delay


@pytest.mark.slow  # needs the control case's loop
def test_cli_and_bad_input(loops, tmp_path, capsys):
    out, _ = loops("control")
    capsys.readouterr()  # the loop's own progress bars, when this test runs alone
    assert main([str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err
    assert main([str(out), "--set", "abc.n_particles=5"]) == 2
    assert "diagnose" in capsys.readouterr().err
    assert main([str(out), "--set", 'diagnose.effects=["wobble"]']) == 2
    assert "wobble" in capsys.readouterr().err


# ------------------------------------------------------------------ the pieces
def test_residuals_vanish_for_the_true_particle():
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 3, 200, seed=5)
    best = {get_model("idm"): (torch.tensor([IDM_TRUTH] * 3), torch.arange(3))}
    series = residual_series(best, pairs)
    for channel in ("spacing", "speed", "acceleration"):
        assert len(series[channel]) == 3
        # Rounding differences only (the data went through the same rollout).
        assert max(np.abs(e).max() for e in series[channel]) < 1e-5


def test_best_particles_picks_the_lowest_score_per_pair(tmp_path):
    pairs = _pairs("idm", IDM_TRUTH)
    train(_config(5000), tmp_path / "run", pairs=pairs)
    posterior = Posterior.load(tmp_path / "run" / "posterior.pt")
    best = best_particles(posterior, pairs[0])
    covered = torch.cat([position for _, position in best.values()])
    assert sorted(covered.tolist()) == list(range(pairs[0].n_pairs))
    for model, (theta, position) in best.items():
        particles = posterior.hybrid[model.name]
        for row, j in zip(theta, position.tolist(), strict=True):
            pid = pairs[0].pair_ids[j]
            lowest = min(
                float(p.score[p.pair_ids == pid].min())
                for p in posterior.hybrid.values()
                if bool((p.pair_ids == pid).any())
            )
            here = particles.score[(particles.theta == row).all(1)]
            assert math.isclose(float(here.min()), lowest)


def test_an_earlier_recalibration_is_read_back_only_when_it_is_this_one(tmp_path):
    """A loop run again reads back its own evaluated re-calibration but removes
    one left by an earlier loop that chose another effect or value, or nothing,
    or one cut short before its evaluation."""
    this, other = _config(), _config(n_particles=N_PARTICLES // 2)
    after = tmp_path / "loop" / "after"

    def earlier(cfg, evaluated=True):
        after.mkdir(parents=True, exist_ok=True)
        (after / "config.json").write_text(json.dumps(resolved_json(cfg)))
        if evaluated:
            (after / "metrics.json").write_text('{"hybrid": {}}')
        return after

    assert reusable(after, this) is False
    assert reusable(earlier(this), this) is True
    assert after.exists()
    assert reusable(earlier(other), this) is False
    assert not after.exists()
    assert reusable(earlier(this, evaluated=False), this) is False
    assert not after.exists()
    (earlier(this) / "config.json").write_text("{not json")
    assert reusable(after, this) is False
    assert not after.exists()
    assert reusable(earlier(this), None) is False
    assert not after.exists()


def test_split_in_time_keeps_pairs_aligned():
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 4, 300, seed=3)
    fit, validation = split_in_time(pairs, 0.6)
    assert fit.n_steps == 180 and validation.n_steps == 120
    assert torch.equal(validation.x_lead[0], pairs.x_lead[180])
    with pytest.raises(DiagnoseError, match="fit_fraction"):
        split_in_time(pairs, 0.99)


def test_bare_grade_spans_the_road_section():
    road = Scene(start=(100.0, 200.0))
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 2, 100, seed=3, scene=road)
    token = resolve_effect("grade", pairs).token
    x = pairs.x_follow
    assert token == (
        f"grade(start={math.floor(float(x.min()))},end={math.ceil(float(x.max()))})"
    )
    assert resolve_effect("grade(knots=2)", pairs).token.startswith("grade(")
    assert resolve_effect("delay", pairs).token == "delay"


# ------------------------------------------------------------- attribution parts
def _candidates(name, theta, pair, score):
    """Hand-built particles; index 0 for all, so that ties go by set position."""
    score = torch.as_tensor(score, dtype=torch.float64)
    return Particles(
        get_model(name),
        torch.as_tensor(theta, dtype=torch.float64),
        torch.as_tensor(pair, dtype=torch.int64),
        score,
        torch.zeros(score.numel(), dtype=torch.int64),
    )


def _per_pair(sets, n_pairs):
    """``(model, theta[0], score)`` per pair, best first: the sets' order (the
    order in which their models first appear, pair by pair) breaks score ties."""
    picks = [[] for _ in range(n_pairs)]
    for s in sets:
        rows = zip(s.theta, s.pair.tolist(), s.score.tolist(), strict=True)
        for theta, j, score in rows:
            picks[j].append((s.model.name, float(theta[0]), score))
    return [sorted(p, key=lambda pick: pick[2]) for p in picks]


def test_select_takes_the_best_per_pair_over_sets():
    a = _candidates("idm", [[1.0], [2.0], [3.0], [4.0]], [0, 0, 1, 1], [0.5, 0.2, 9, 1])
    b = _candidates("llctg", [[5.0], [6.0], [7.0]], [0, 1, 1], [0.2, math.inf, 0.1])
    picks = _per_pair(best_per_pair([a, b], 2), 3)
    assert picks == [
        [("idm", 2.0, 0.2), ("llctg", 5.0, 0.2)],  # a tie goes to the earlier set
        [("llctg", 7.0, 0.1), ("idm", 4.0, 1.0)],  # inf is never picked
        [],
    ]


def test_jitter_stays_in_the_prior_and_keeps_fixed_parameters():
    from torchcf.diagnose.arms.search import LOCAL_SCALES, jitter

    theta = torch.tensor([[0.5, 2.0, 1.0], [0.0, 3.0, 1.0]], dtype=torch.float64)
    bounds = torch.tensor([[0.0, 1.0], [0.0, 10.0], [1.0, 1.0]], dtype=torch.float64)
    steps = torch.randn(2, 3000, 3, generator=torch.Generator().manual_seed(0))
    moved = jitter(theta, steps.double(), bounds)
    assert moved.shape == (2, 3000, 3)
    assert bool((moved >= bounds[:, 0]).all() and (moved <= bounds[:, 1]).all())
    assert bool((moved[..., 2] == 1.0).all())  # zero width: fixed
    for c, scale in enumerate(LOCAL_SCALES):  # copy c uses scale c % 3
        step = moved[0, c :: len(LOCAL_SCALES), 1] - 2.0
        assert abs(float(step.std()) / (10 * scale) - 1) < 0.1


def test_local_search_spends_its_budget_and_never_loses_a_fit(monkeypatch):
    import torchcf.diagnose.arms.search as search

    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 4, 150, seed=9)
    cfg = _config(population=3, local_copies=5, rounds=2)
    rollout = LoopSetup.of(cfg).rollout(pairs)
    models = [get_model(m) for m in ("idm", "llctg")]
    bounds = {m: model_bounds(m, {}) for m in models}
    seed = LoopSetup.of(cfg).seed
    streams = [prior_stream(m, bounds[m], seed, rollout) for m in models]
    sets = [prior_particles(stream, rollout, (200,), 3)[0] for stream in streams]
    start = Population.from_particles(sets, 4, 3)
    simulated = []
    scores = search.score_on

    def counted(rollout, model, theta, pair, ceiling=None):
        simulated.append(theta.shape[0])
        return scores(rollout, model, theta, pair, ceiling)

    monkeypatch.setattr(search, "score_on", counted)
    current = {m: get_model(m).param_names for m in start.models}
    members = search.local_search(
        start, rollout, bounds, Noise((1,), current), {m: m for m in start.models},
        rounds=2, copies=5,
    )  # fmt: skip
    assert sum(simulated) == 2 * 4 * 3 * 5  # rounds x pairs x population x copies
    assert bool((members.score[:, 0] <= start.score[:, 0]).all())
    assert members.score.shape == (4, 3)


def test_diagnose_seed_replaces_the_runs_seed_in_the_attribution():
    """diagnose.seed (None = abc.seed) draws another prior sample: a check that
    the loop's answer is not the luck of one stream."""
    pairs = synthetic_pairs(get_model("idm"), IDM_TRUTH, 3, 100, seed=9)
    bounds = model_bounds(get_model("idm"), {})

    def drawn(**diagnose):
        cfg = _config(**diagnose)
        rollout = LoopSetup.of(cfg).rollout(pairs)
        stream = prior_stream(get_model("idm"), bounds, LoopSetup.of(cfg).seed, rollout)
        (particles,) = prior_particles(stream, rollout, (50,), 2)
        return particles

    default, same, other = drawn(), drawn(seed=0), drawn(seed=1)
    assert torch.equal(default.theta, same.theta)  # abc.seed is 0
    assert not torch.equal(default.theta, other.theta)
    with pytest.raises(ConfigError, match="seed"):
        _config(seed=-1)


def test_shared_value_finds_a_constant_grade():
    """Data from LLCTG on a 4 % grade; members = the true LLCTG parameters: the
    joint search over pairs returns a grade near 4 %."""
    from torchcf.diagnose.arms.search import effect_prior, shared_value

    effect = parse_effect("grade(start=0,end=1000,knots=1)")
    model = f"llctg+{effect.token}"
    pairs = synthetic_pairs(get_model(model), LLCTG_TRUTH + [0.04], 6, 300, seed=4)
    cfg = _config(local_copies=4)
    members = Population.from_particles(
        [_candidates("llctg", [LLCTG_TRUTH] * 6, range(6), [1.0] * 6)], 6, 2
    )
    llctg = get_model("llctg")
    bounds = {llctg: model_bounds(llctg, {})}
    rollout = LoopSetup.of(cfg).rollout(pairs)
    value, box, tried = shared_value(
        effect, members, rollout, bounds, effect_prior(effect), (0,)
    )
    assert abs(float(value[0]) - 0.04) < 0.01
    assert float(box[0, 0]) <= float(value[0]) <= float(box[0, 1])
    assert float(box[0, 1] - box[0, 0]) < 0.16 / 4  # narrower than the prior
    assert len(tried) == 3 and tried[0][1].shape == (6, tried[0][0].shape[0])
