"""The trainer's typed results and its checkpoint module: RunSummary's JSON round
trip (``summary.json`` written by a run reads back, key order included), the
attribute reads callers rely on, and the refusal of a corrupted or
mismatched checkpoint."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from tests.conftest import synthetic_pairs
from torchcf.abc.rejection import ModelProgress
from torchcf.abc.topn import TopN
from torchcf.calibration.state import StateError, build_buffers
from torchcf.config import TrainConfig, config_hash
from torchcf.models import get_model
from torchcf.runs.directory import RunDir
from torchcf.runs.summary import (
    ModelResult,
    Pairwise,
    PlausibilitySettings,
    PlausibilitySummary,
    RunSummary,
    SMCBudgetResult,
    SMCResult,
    Versions,
)
from torchcf.study.pipeline import StudyResult, train_and_evaluate
from torchcf.train import RunError, RunState, open_run
from torchcf.train.checkpoint import CHECKPOINT_FORMAT, resume_note

MODELS = ["idm", "hl"]
MODEL_OBJECTS = [get_model(name) for name in MODELS]


def _config(**abc) -> TrainConfig:
    settings = {"n_particles": 800, "top_n": 3, "sensitivity_n": [3, 5], "seed": 1}
    settings.update(abc)
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": MODELS,
            "abc": settings,
            "compile": "off",
        }
    )


def _model_result(thresholds=(1.5, None)) -> ModelResult:
    return ModelResult(
        particles=800,
        invalid=3,
        invalid_rate=3 / 800,
        implausible=0,
        seconds=0.125,
        particles_per_s=6400.0,
        best_score=0.5,
        threshold=1.5,
        threshold_max=None,
        thresholds=tuple(thresholds),
        pairs_short_of_n=sum(v is None for v in thresholds),
    )


def _summary(**changes) -> RunSummary:
    summary = RunSummary(
        dataset="synthetic",
        layout="paired",
        selection="per_pair",
        top_n=3,
        n_particles=800,
        n_train=2,
        n_test=2,
        train_pair_ids=(0, 1),
        test_pair_ids=(2, 3),
        models=tuple(MODELS),
        shares={"idm": 0.75, "hl": 0.25},
        hybrid_size=6,
        pairwise=Pairwise(models=tuple(MODELS), table=((1.0, 0.75), (0.25, 1.0))),
        sensitivity={3: {"idm": 0.75, "hl": 0.25}, 5: {"idm": 0.5, "hl": 0.5}},
        per_model={"idm": _model_result(), "hl": _model_result((2.0, 3.0))},
        seconds_total=0.25,
        seconds_wall_this_process=1.5,
        processes=1,
        config_hash="0123456789abcdef",
        versions=Versions.current(),
        method="rejection",
    )
    return replace(summary, **changes)


def _plausibility() -> PlausibilitySummary:
    return PlausibilitySummary(
        n_particles=6,
        collided=0.0,
        per_scenario={"brake_4": 0.0},
        string_unstable=0.5,
        string_untested=0.0,
        no_equilibrium=0.0,
        not_started=0.0,
        min_ttc_median=None,
        string_ratio_median=1.25,
        settings=PlausibilitySettings(
            speed=20.0, decelerations=(4.0,), collision_spacing=0.0, platoon_size=8
        ),
    )


# ------------------------------------------------------------------ RunSummary


def test_a_summary_round_trips_through_json_with_every_optional_part():
    smc = SMCResult(
        settings={"population": 50, "rounds": 12, "space": "logit"},
        budget=SMCBudgetResult(
            prior_draws=200,
            proposals_per_pair_and_round=10,
            rounds=12,
            proposals=440,
            unspent=360,
        ),
        evidence_shares={"idm": 0.6, "hl": 0.4},
    )
    plausibility = {"idm": _plausibility()}
    for summary in (
        _summary(),
        _summary(method="smc", smc=smc),
        _summary(plausibility=plausibility),
        _summary(method=None, extra={"note": [1, 2]}),
    ):
        raw = summary.to_json()
        back = RunSummary.from_json(json.loads(json.dumps(raw)))
        assert back == summary
        assert back.to_json() == raw and list(back.to_json()) == list(raw)
        # the typed parts compare as records too, not only as JSON
        assert back.per_model == summary.per_model and back.smc == summary.smc
        assert back.pairwise == summary.pairwise
        assert back.sensitivity == summary.sensitivity


def test_the_json_keys_and_their_order_are_summary_json_s():
    raw = _summary(plausibility={"idm": _plausibility()}).to_json()
    assert list(raw) == [
        "dataset",
        "layout",
        "selection",
        "top_n",
        "n_particles",
        "n_train",
        "n_test",
        "train_pair_ids",
        "test_pair_ids",
        "models",
        "shares",
        "hybrid_size",
        "pairwise",
        "sensitivity",
        "per_model",
        "seconds_total",
        "seconds_wall_this_process",
        "processes",
        "config_hash",
        "versions",
        "method",
        "plausibility",
    ]
    assert raw["sensitivity"] == {"3": raw["shares"], "5": {"idm": 0.5, "hl": 0.5}}
    assert raw["pairwise"]["table"] == [[1.0, 0.75], [0.25, 1.0]]
    assert raw["per_model"]["idm"]["thresholds"] == [1.5, None]
    assert "smc" not in raw  # absent, as a rejection run's summary.json has it


def test_a_summary_reads_through_its_attributes():
    """Callers read the record's attributes; its JSON object is the file's
    content alone, a fresh copy each time (no mapping behaviour)."""
    summary = _summary()
    raw = summary.to_json()
    assert summary.shares == {"idm": 0.75, "hl": 0.25}
    assert summary.per_model["hl"].seconds == 0.125
    assert "smc" not in raw and "per_model" in raw
    assert summary.smc is None and summary.top_n == 3
    assert list(summary.to_json()) == list(raw) and summary.to_json() == raw
    assert RunSummary.from_json(raw) == summary
    with pytest.raises(KeyError):
        raw["smc"]
    with pytest.raises(TypeError):
        summary["shares"]  # no mapping: the attributes are the way in
    assert summary != raw
    # the JSON is a copy: the record does not change through it
    copy = summary.to_json()
    copy["shares"]["idm"] = 0.0
    copy["per_model"]["hl"]["thresholds"].append(9.0)
    assert summary.to_json() == raw


def test_what_is_not_a_summary_is_refused():
    raw = _summary().to_json()
    for broken in (
        {k: v for k, v in raw.items() if k != "per_model"},
        {**raw, "per_model": {"idm": {**raw["per_model"]["idm"], "x": 1}}},
        {**raw, "pairwise": {"models": MODELS}},
        {**raw, "sensitivity": {"three": {}}},
    ):
        with pytest.raises(ValueError, match="not a run summary"):
            RunSummary.from_json(broken)


# ------------------------------------------------------------------ a run


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("results") / "run"
    pairs = synthetic_pairs(n_pairs=4, n_steps=120, seed=2)
    result = train_and_evaluate(_config(), out, pairs=(pairs, pairs), evaluate=False)
    return out, result


def test_the_summary_json_of_a_run_reads_back(trained):
    out, result = trained
    assert isinstance(result, StudyResult) and not result.evaluated
    summary = result.summary
    assert isinstance(summary, RunSummary)
    text = (out / "summary.json").read_text()
    on_disk = json.loads(text)
    assert json.dumps(summary.to_json(), indent=2) + "\n" == text  # order included
    back = RunDir(out).read_summary()
    assert back == summary and back.per_model == summary.per_model
    assert isinstance(back.per_model["idm"], ModelResult)
    assert back.per_model["idm"].particles == 800
    # the study result's summary is the file's content
    assert result.summary.to_json() == on_disk
    assert on_disk["shares"] == summary.shares
    assert on_disk["per_model"]["hl"]["seconds"] == summary.per_model["hl"].seconds


def test_a_finished_run_resumed_returns_its_summary(trained):
    out, result = trained
    pairs = synthetic_pairs(n_pairs=4, n_steps=120, seed=2)
    again = train_and_evaluate(
        _config(), out, resume=True, pairs=(pairs, pairs), evaluate=False
    )
    assert again.summary == result.summary
    assert isinstance(again.summary, RunSummary)


# ------------------------------------------------------------------ checkpoint


def _checkpointed(tmp_path, cfg: TrainConfig, n_pairs: int = 3) -> RunDir:
    """A run directory holding a valid checkpoint of ``cfg`` (fresh buffers)."""
    run = RunDir(tmp_path / "run")
    run.path.mkdir()
    state = RunState(config_hash(cfg))
    build_buffers(MODEL_OBJECTS, n_pairs, cfg.abc.buffer_size, None, state.calibration)
    state.calibration.progress["idm"] = ModelProgress(next=100, invalid=2, seconds=0.5)
    state.calibration.buffers["idm"].score[0, 0] = 0.25
    run.save_checkpoint(state.as_checkpoint())
    return run


def test_a_checkpoint_resumes_to_its_state(tmp_path):
    cfg = _config()
    run = _checkpointed(tmp_path, cfg)
    assert run.load_checkpoint()["format"] == CHECKPOINT_FORMAT
    state = open_run(config_hash(cfg), run.path, resume=True).calibration
    assert state.progress["idm"] == ModelProgress(next=100, invalid=2, seconds=0.5)
    build_buffers(MODEL_OBJECTS, 3, cfg.abc.buffer_size, None, state)
    assert float(state.buffers["idm"].score[0, 0]) == 0.25
    assert isinstance(state.buffers["hl"], TopN)


def test_resume_says_what_it_reuses():
    state = RunState("h")
    state.calibration.progress["idm"] = ModelProgress(next=1000, done=True)
    state.calibration.progress["gfm"] = ModelProgress(next=340)
    note = resume_note(state, ["idm", "gfm", "hl", "mpc"], 1000)
    assert note == (
        "resuming from checkpoint.pt: idm finished; gfm at 340 of 1,000; hl, mpc to run"
    )
    assert resume_note(RunState("h"), ["idm"], 10).endswith(
        "no model finished; idm to run"
    )
    # an amortised run: a model's particles are its samples, not n_particles
    assert resume_note(state, ["idm", "gfm"], None) == (
        "resuming from checkpoint.pt: idm finished; gfm at 340"
    )


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda raw: {**raw, "format": "torchcf.checkpoint/0"}, "not a torchcf"),
        (lambda raw: {**raw, "config_hash": "ffff"}, "different config"),
        (lambda raw: {k: v for k, v in raw.items() if k != "progress"}, "corrupted"),
        (
            lambda raw: {**raw, "progress": {"idm": {"next": -1}}},
            "corrupted",
        ),
        (
            lambda raw: {**raw, "progress": {"idm": {"particles": 3}}},
            "corrupted",
        ),
        (
            lambda raw: {**raw, "buffers": {"idm": {"score": torch.zeros(3, 2)}}},
            "corrupted",
        ),
    ],
)
def test_a_corrupted_or_foreign_checkpoint_is_refused(tmp_path, damage, message):
    cfg = _config()
    run = _checkpointed(tmp_path, cfg)
    run.save_checkpoint(damage(run.load_checkpoint()))
    with pytest.raises(RunError, match=message):
        open_run(config_hash(cfg), run.path, resume=True)


def test_a_checkpoint_of_other_buffers_is_refused_when_loaded(tmp_path):
    """Its format and config match, but its buffers are not this run's (other
    pairs): refused when the buffers are built, naming the model."""
    cfg = _config()
    run = _checkpointed(tmp_path, cfg, n_pairs=3)
    state = open_run(config_hash(cfg), run.path, resume=True).calibration
    with pytest.raises(StateError, match="idm"):
        build_buffers(MODEL_OBJECTS, 4, cfg.abc.buffer_size, None, state)


def test_no_checkpoint_and_an_unreadable_one_are_refused(tmp_path):
    cfg = _config()
    run = RunDir(tmp_path / "run")
    run.path.mkdir()
    with pytest.raises(RunError, match="no checkpoint.pt"):
        open_run(config_hash(cfg), run.path, resume=True)
    run.checkpoint.write_bytes(b"not a pickle")
    with pytest.raises(RunError, match="start again with another --out"):
        open_run(config_hash(cfg), run.path, resume=True)
