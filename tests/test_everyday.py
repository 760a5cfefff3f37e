"""The everyday path: the stumbles of a first run, and runs that cannot be mixed up.

Each test is one thing a new or careless user ran into: a typo in a model
name, a data path over a named data set, the same data notes printed over and
over, a finished run resumed, two trainings into one directory, a config edited
after training.
"""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from tests.conftest import synthetic_pairs
from tests.runs import REPO, run_module, write_config, write_data
from torchcf.cli.data import main as data_main
from torchcf.cli.train import main as train_main
from torchcf.config import ConfigError, TrainConfig, load_config
from torchcf.config.overrides import apply_overrides
from torchcf.data import registry
from torchcf.data.registry import notes_deferred
from torchcf.evaluation.evaluate import evaluate_run
from torchcf.models import get_model, parse_effect
from torchcf.runs.directory import LOCK_NAME, RunDir
from torchcf.study.pipeline import run_study
from torchcf.system.errors import did_you_mean
from torchcf.system.files import RunFileError
from torchcf.traffic.scenarios import pair_leader


# ------------------------------------------------------------------- names
def test_a_mistyped_model_or_effect_gets_a_suggestion():
    with pytest.raises(KeyError, match=r"'idn' \(did you mean 'idm'\?\)"):
        get_model("idn")
    with pytest.raises(ValueError, match=r"'dely' \(did you mean 'delay'\?\)"):
        parse_effect("dely")
    with pytest.raises(ValueError, match=r"did you mean 'delay'"):
        get_model("idm+dleay")
    assert did_you_mean("zzzzzz", ["idm", "hl"]) == ""


def test_config_names_the_suggestion_in_one_line():
    raw = {"data": {"name": "car-model-2"}, "models": ["hll"]}
    with pytest.raises(ConfigError, match=r"models\[0\].*did you mean 'hl'"):
        _validate(raw)


def _validate(raw):
    from torchcf.config import validate_config

    return validate_config(raw)


def _public_calls_with_a_name():
    """Each public function that takes a model, called with the name instead."""
    from torchcf import HybridSampler, simulate
    from torchcf.abc.particles import Particles
    from torchcf.evaluation.evaluate import cost_matrices
    from torchcf.sim.synthetic import synthetic_pairs as drive
    from torchcf.traffic.battery import check_plausibility, collides

    theta = get_model("idm").prior_bounds(torch.float64).mean(1)  # (K,)
    pairs = synthetic_pairs(n_pairs=2, n_steps=50)
    one_pair = torch.zeros(1, dtype=torch.int64)  # (1,) pair and particle index
    return {
        "simulate": lambda: simulate("idm", theta[None], pairs),
        "synthetic_pairs": lambda: drive("idm", theta, 2, 50),
        "check_plausibility": lambda: check_plausibility("idm", theta[None]),
        "collides": lambda: collides("idm", theta[None]),
        "HybridSampler": lambda: HybridSampler(["idm"], [theta[None]], dt=0.1),
        "cost_matrices": lambda: cost_matrices("idm", theta[None], pairs),
        "Particles": lambda: Particles(
            "idm", theta[None], one_pair, torch.zeros(1, dtype=torch.float64), one_pair
        ),
    }


@pytest.mark.parametrize(
    "caller",
    [
        "simulate",
        "synthetic_pairs",
        "check_plausibility",
        "collides",
        "HybridSampler",
        "cost_matrices",
        "Particles",
    ],
)
def test_a_model_name_where_the_object_goes_says_what_to_pass(caller):
    """A name is parsed where it enters (a config, the command line):
    :func:`torchcf.get_model`; past that, a function given the name says so
    in one line instead of parsing it again."""
    expected = (
        f"{caller} takes a model object, e.g. torchcf.get_model('idm'), "
        "not the name 'idm'"
    )
    with pytest.raises(TypeError) as raised:
        _public_calls_with_a_name()[caller]()
    assert str(raised.value) == expected


# ---------------------------------------------------------------- overrides
def test_a_data_path_override_replaces_a_named_data_set(tmp_path):
    raw = {"data": {"name": "car-model-2", "split": "dataset"}, "models": ["idm"]}
    out = apply_overrides(raw, [f"data.path={tmp_path}"])
    assert out["data"] == {"path": str(tmp_path), "split": "dataset"}
    back = apply_overrides(out, ["data.name=car-model-1"])
    assert back["data"] == {"name": "car-model-1", "split": "dataset"}
    assert raw["data"]["name"] == "car-model-2"  # the input is not modified


def test_setting_inside_a_source_or_to_null_drops_nothing():
    raw = {"data": {"name": "car-model-2"}}
    assert apply_overrides(raw, ["data.path=null"])["data"] == {
        "name": "car-model-2",
        "path": None,
    }
    nested = apply_overrides(raw, ["data.raw.source=x"])["data"]
    assert nested["name"] == "car-model-2" and nested["raw"] == {"source": "x"}


def test_the_exclusive_sources_message_says_how_to_override(tmp_path):
    config = tmp_path / "c.json"
    config.write_text(json.dumps({"data": {"name": "car-model-2"}, "models": ["idm"]}))
    cfg = load_config(config, [f"data.path={tmp_path}"])
    assert cfg.data.path is not None and cfg.data.name is None
    with pytest.raises(ConfigError, match="--set data.path=DIR alone replaces"):
        _validate({"data": {"name": "car-model-2", "path": "x"}, "models": ["idm"]})


# --------------------------------------------------------------- the budget
@pytest.mark.parametrize("value", [1e13, 10**20, 1e20])
def test_particle_counts_beyond_reason_are_refused_with_why(value):
    raw = {"data": {"name": "car-model-2"}, "models": ["idm"]}
    raw["abc"] = {"n_particles": value}
    with pytest.raises(ConfigError, match=r"abc.n_particles: at most 1e\+12.*12 days"):
        _validate(raw)
    raw["abc"] = {"n_particles": 10**12}
    assert _validate(raw).abc.n_particles == 10**12


# -------------------------------------------------------------------- notes
@pytest.fixture
def fresh_notes(monkeypatch):
    monkeypatch.setattr(registry, "_ANNOUNCED", set())


def test_a_data_note_is_logged_once_per_process(fresh_notes, caplog):
    """One line per load, each note once per data set, in its short form."""
    warn = logging.WARNING
    with caplog.at_level(logging.INFO, logger="torchcf.data"):
        registry._announce("set", [(warn, "a quirk; dropped from train")])
        registry._announce("set", [(warn, "a quirk; dropped from test")])
        registry._announce("set", [(warn, "a quirk"), (warn, "another")])
        registry._announce("other", [(warn, "a quirk")])
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3
    assert messages[0].startswith("set: 1 data note, handled as documented")
    assert messages[0].endswith(": a quirk")
    assert messages[1].endswith(": another")
    assert messages[2].startswith("other: 1 data note")
    assert "docs/data.md" in messages[2]


def test_deferred_notes_follow_the_block_or_go_with_its_error(fresh_notes, caplog):
    warn = logging.WARNING
    with caplog.at_level(logging.INFO, logger="torchcf.data"):
        with pytest.raises(ConfigError), notes_deferred():
            registry._announce("set", [(warn, "first")])
            raise ConfigError("abc.top_n: too many")
        assert caplog.records == []
        with notes_deferred():
            registry._announce("set", [(warn, "second")])
            assert caplog.records == []
        (message,) = [r.getMessage() for r in caplog.records]
        assert message.startswith("set: 1 data note") and message.endswith(": second")


def test_the_paper_data_notes_are_not_repeated(fresh_notes, data_root, caplog):
    with caplog.at_level(logging.INFO, logger="torchcf.data"):
        registry.load_pairs("car-model-2", split="train")
        first = len(caplog.records)
        registry.load_pairs("car-model-2", split="test")
        registry.load_pairs("car-model-2", split="train")
    texts = [r.getMessage().split(": ", 1)[1] for r in caplog.records]
    assert first >= 1 and len(texts) == len(set(texts))


# ----------------------------------------------------------- command lines
def test_train_prints_the_schema_where_its_help_points(capsys):
    assert train_main(["--schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert "abc" in schema["properties"]
    with pytest.raises(SystemExit) as exit_:
        train_main([])
    assert exit_.value.code == 2
    assert "give a CONFIG file (or --schema)" in capsys.readouterr().err


def test_help_shows_the_defaults(capsys):
    with pytest.raises(SystemExit):
        data_main(["extract", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "pair length [s]; 'auto'" in text and "(default: 40.0)" in text
    assert "'whole': every couple one pair of its own length" in text
    assert "share of pairs for test, whole groups; 0: no test split" in text
    assert "(default: 0.3) --seed" in text
    assert "the raw format (default" not in text  # required: no default to show


def test_pair_leader_takes_one_pair_as_an_int():
    pairs = synthetic_pairs(n_pairs=3, n_steps=50)
    x_lead, v_lead, start = pair_leader(pairs, 1)
    assert x_lead.shape == (50, 1) and start.v.shape == (1,)
    torch.testing.assert_close(x_lead[:, 0], pairs.x_lead[:, 1])
    assert torch.equal(pair_leader(pairs, [1])[0], x_lead)


# ------------------------------------------------------------------ locking
_HOLD = textwrap.dedent(
    """
    import sys, time
    from torchcf.runs.directory import RunDir
    with RunDir(sys.argv[1]).locked():
        print("held", flush=True)
        time.sleep(60)
    """
)


def test_a_run_directory_is_held_by_one_process(tmp_path):
    run = tmp_path / "run"
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(
            RunFileError, match=rf"in use by another .*pid {holder.pid}"
        ):
            with RunDir(run).locked():
                pass
    finally:
        holder.kill()
        holder.wait()
    with RunDir(run).locked(), RunDir(run).locked():  # free again; re-entrant
        assert (run / LOCK_NAME).read_text().strip().isdigit()


def test_a_lock_that_creates_the_directory_leaves_nothing_on_failure(tmp_path):
    run = tmp_path / "new"
    with pytest.raises(ValueError), RunDir(run).locked():
        raise ValueError("the data failed")
    assert not run.exists()


# ---------------------------------------------------- runs and their files
def _config() -> TrainConfig:
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": ["idm", "llctg"],
            "abc": {"n_particles": 600, "chunk_size": 300, "top_n": 2},
            "compile": "off",
            "plausibility": {"report": False},
        }
    )


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    pairs = (synthetic_pairs(n_pairs=4, n_steps=120, seed=1),) * 2
    run_study(_config(), out, pairs=pairs)
    return RunDir(out), pairs


def _stamps(run: RunDir) -> dict[str, int]:
    files = [*run.tb_dir.iterdir(), run.metrics_json, run.summary_json]
    return {p.name: p.stat().st_mtime_ns for p in files}


def test_a_finished_run_resumed_does_nothing(study):
    run, pairs = study
    before = _stamps(run)
    result = run_study(_config(), run.path, resume=True, pairs=pairs)
    assert result.summary == run.read_summary()
    assert _stamps(run) == before  # nothing retrained, re-evaluated or logged


def test_evaluating_again_replaces_the_evaluation_in_tensorboard(study):
    run, pairs = study
    evaluate_run(run, pairs=pairs)
    evaluate_run(run, pairs=pairs)
    streams = sorted(p.name for p in run.tb_dir.iterdir())
    assert len([s for s in streams if s.endswith(".evaluation")]) == 1
    assert len(streams) == 2  # training's and the evaluation's


def test_a_config_edited_after_training_is_refused(study, tmp_path):
    run, pairs = study
    raw = json.loads(run.config_json.read_text())
    raw["data"]["name"] = "car-model-1"
    copy = RunDir(tmp_path / "copy")
    copy.path.mkdir()
    for name in ("posterior.pt", "summary.json"):
        (copy.path / name).write_bytes((run.path / name).read_bytes())
    copy.config_json.write_text(json.dumps(raw))
    with pytest.raises(RunFileError, match="not the config .* was trained with"):
        evaluate_run(copy, pairs=pairs)
    raw["data"]["name"] = "car-model-2"
    raw["eval"]["beta"] = 0.3  # evaluation settings may change
    copy.config_json.write_text(json.dumps(raw))
    assert evaluate_run(copy, pairs=pairs).beta == 0.3


# ------------------------------------------------------------------ signals
@pytest.mark.parametrize(
    ("signum", "code", "word"),
    [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")],
)
@pytest.mark.slow  # a training in a subprocess, signalled
def test_a_signal_writes_a_checkpoint_and_says_how_to_continue(
    tmp_path, signum, code, word
):
    data = write_data(tmp_path / "pairs")
    abc = {"n_particles": 300_000, "chunk_size": 2000, "checkpoint_every": 3600}
    config = write_config(tmp_path / "cfg.json", data, abc=abc, models=["idm"])
    out = tmp_path / "run"
    command = [sys.executable, "-m", "torchcf", "train", str(config), "--out", str(out)]
    process = subprocess.Popen(
        [*command, "--no-eval"], stderr=subprocess.PIPE, text=True, cwd=REPO
    )
    while not (out / "config.json").exists() and process.poll() is None:
        time.sleep(0.05)  # the data are read: the stream starts
    time.sleep(1.0)
    process.send_signal(signum)
    stderr = process.communicate(timeout=120)[1]
    assert process.returncode == code, stderr
    assert "Traceback" not in stderr
    assert f"{word} (checkpoint written): continue with --resume" in stderr
    progress = RunDir(out).load_checkpoint()["progress"]["idm"]
    assert 0 < progress["next"] < 300_000 and not progress["done"]
    if signum == signal.SIGTERM:
        resumed = run_module(
            "torchcf", "train", str(config), "--out", str(out), "--resume", "--no-eval"
        )
        assert resumed.returncode == 0, resumed.stderr
        assert RunDir(out).is_trained()
