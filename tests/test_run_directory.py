"""The run directory (torchcf.runs.directory) and its files
(torchcf.system.files): every file round-trips, a damaged one is a RunFileError
naming it, and a full disk — a real, small file system where the machine lets
us mount one — keeps the previous file intact and ends a command with one line
and exit code 2."""

from __future__ import annotations

import errno
import json
import math
import os
import re
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from tests.runs import evaluation, run_module, run_summary, write_config, write_data
from torchcf.config import (
    ConfigError,
    TrainConfig,
    config_hash,
    load_config,
    resolved_json,
)
from torchcf.models import get_model
from torchcf.posterior import ModelParticles, Posterior
from torchcf.runs.directory import RunDir
from torchcf.runs.summary import Pairwise, RecalibrationSummary
from torchcf.system.errors import TorchcfError
from torchcf.system.files import (
    RunFileError,
    atomic_torch_save,
    atomic_write_text,
    from_json_safe,
    json_safe,
    read_json_object,
    read_torch,
    write_json,
)

#: Size of the small file system of the full-disk tests.
TMPFS_SIZE = "600k"


# ----------------------------------------------------------------- helpers
def small_posterior(dataset: str = "synthetic") -> Posterior:
    """Two models, a few particles each, on 4 training pairs."""
    hybrid, buffers = {}, {}
    for k, (name, count) in enumerate({"idm": 3, "llcs": 2}.items()):
        model = get_model(name)
        generator = torch.Generator().manual_seed(k)
        theta = torch.rand(count, model.n_params, generator=generator).double()
        hybrid[name] = ModelParticles(
            model.param_names,
            theta,
            torch.arange(count, dtype=torch.float64),
            torch.zeros(count, dtype=torch.long),
            torch.arange(count),
        )
        buffers[name] = {
            "param_names": list(model.param_names),
            "score": torch.zeros(4, 2, dtype=torch.float64),
            "index": torch.zeros(4, 2, dtype=torch.long),
            "theta": torch.zeros(4, 2, model.n_params, dtype=torch.float64),
        }
    return Posterior(
        dataset=dataset,
        selection="per_pair",
        top_n=2,
        models=("idm", "llcs"),
        shares={"idm": 0.6, "llcs": 0.4},
        train_pair_ids=torch.arange(4),
        hybrid=hybrid,
        buffers=buffers,
    )


SUMMARY = run_summary(("idm", "llcs"))
METRICS = evaluation()


def trained_summary(cfg: TrainConfig):
    """:data:`SUMMARY` as the training of ``cfg`` would record it (its hash)."""
    return replace(SUMMARY, config_hash=config_hash(cfg))


def small_config(folder: Path) -> TrainConfig:
    data = write_data(folder / "pairs", n_pairs=6, n_steps=40)
    return load_config(write_config(folder / "cfg.json", data))


def finished_run(folder: Path, cfg: TrainConfig) -> RunDir:
    """A trained, not evaluated run written through RunDir (no training)."""
    run = RunDir(folder).prepare()
    run.write_config(cfg)
    run.save_checkpoint({"format": "test", "step": torch.arange(5)})
    run.save_posterior(small_posterior())
    run.write_summary(trained_summary(cfg))
    return run


@pytest.fixture(scope="module")
def cfg(tmp_path_factory) -> TrainConfig:
    return small_config(tmp_path_factory.mktemp("cfg"))


def no_temporary_files(folder: Path) -> None:
    assert not [p.name for p in folder.rglob("*") if ".tmp" in p.name]


def one_error_line(result: subprocess.CompletedProcess[str], *needles: str) -> str:
    """A command that ended with exit code 2 and one ``error:`` line, no
    traceback."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# -------------------------------------------------------------- the layout
def test_layout(tmp_path):
    run = RunDir(tmp_path / "run")
    root = tmp_path / "run"
    assert run.path == root and Path(run) == root and str(run) == str(root)
    names = {
        "config_json": "config.json",
        "checkpoint": "checkpoint.pt",
        "posterior_pt": "posterior.pt",
        "summary_json": "summary.json",
        "metrics_json": "metrics.json",
        "report_dir": "report",
        "tb_dir": "tb",
        "loop_json": "loop.json",
        "loop_md": "loop.md",
        "loop_dir": "loop",
    }
    for attribute, name in names.items():
        assert getattr(run, attribute) == root / name
    assert run.recalibration_dir == root / "loop" / "after"
    assert run.fold(2) == RunDir(root / "fold2")
    assert not tmp_path.joinpath("run").exists()  # nothing touched


def test_error_classes_share_one_base():
    from torchcf.abc.distributed import GroupError
    from torchcf.data import DataError
    from torchcf.evaluation.evaluate import EvaluationError

    for kind in (RunFileError, ConfigError, DataError, GroupError, EvaluationError):
        assert issubclass(kind, TorchcfError), kind
    assert issubclass(ConfigError, ValueError) and issubclass(DataError, ValueError)
    assert issubclass(GroupError, RuntimeError)
    assert issubclass(RunFileError, ValueError)  # as the posterior's error was


# ------------------------------------------------------------- round trips
def test_every_file_round_trips(tmp_path, cfg):
    run = RunDir(tmp_path / "run").prepare()
    assert (run.holds_run(), run.is_trained(), run.is_evaluated()) == (False,) * 3
    assert not run.is_looped() and not run.has_checkpoint()

    run.write_config(cfg)
    assert run.read_config() == cfg
    assert run.read_config_json() == resolved_json(cfg)
    run.write_config(resolved_json(cfg))  # the resolved object does as well
    assert run.read_config() == cfg

    checkpoint = {"format": "x", "buffers": {"idm": torch.arange(6.0)}, "n": 3}
    run.save_checkpoint(checkpoint)
    assert run.holds_run() and run.has_checkpoint() and not run.is_trained()
    loaded = run.load_checkpoint()
    assert loaded["n"] == 3 and torch.equal(loaded["buffers"]["idm"], torch.arange(6.0))

    posterior = small_posterior()
    run.save_posterior(posterior)
    back = run.load_posterior()
    assert (back.models, back.shares, back.top_n) == (
        posterior.models,
        posterior.shares,
        posterior.top_n,
    )
    for name in posterior.models:
        assert torch.equal(back.hybrid[name].theta, posterior.hybrid[name].theta)
        theta = posterior.buffers[name]["theta"]
        assert torch.equal(back.buffers[name]["theta"], theta)

    summary = trained_summary(cfg)
    run.write_summary(summary)
    assert run.is_trained() and run.read_summary() == summary
    assert read_json_object(run.summary_json) == summary.to_json()  # the file's
    cfg_back, posterior_back, summary_back = run.load_run()
    assert cfg_back == cfg and summary_back == summary
    assert posterior_back.shares == posterior.shares
    # a re-calibration's summary (the loop's run directories) reads as its own
    recalibrated = RecalibrationSummary(
        dataset="synthetic",
        shares={"idm": 0.5, "llcs": 0.5},
        hybrid_size=4,
        pairwise=Pairwise(models=("idm", "llcs"), table=((1.0, 0.5), (0.5, 1.0))),
        recalibration="search",
    )
    run.write_summary(recalibrated)
    assert run.read_summary() == recalibrated
    assert list(read_json_object(run.summary_json)) == [
        "dataset",
        "shares",
        "hybrid_size",
        "pairwise",
        "recalibration",
    ]
    assert run.load_run()[2] == recalibrated  # no config hash to check
    # an edited config is refused against a training's summary
    run.write_summary(replace(summary, config_hash="0" * 16))
    with pytest.raises(RunFileError, match="is not the config .* was trained with"):
        run.load_run()
    run.write_summary(summary)

    run.write_metrics(METRICS)
    assert run.is_evaluated()
    raw = read_json_object(run.metrics_json)
    assert raw["hybrid"]["beta_ws"] == "inf"  # JSON has no infinity
    assert raw == json_safe(METRICS.to_json())
    assert run.read_metrics() == METRICS
    run.discard_metrics()
    assert not run.is_evaluated()
    run.discard_metrics()  # gone already: nothing to do

    run.write_loop({"format": "loop", "gain": float("nan")}, "# the loop\n")
    assert run.is_looped()
    assert run.read_loop() == {"format": "loop", "gain": "nan"}
    assert run.loop_md.read_text() == "# the loop\n"
    text = run.metrics_json.parent.joinpath("summary.json").read_text()
    assert text.endswith("}\n") and text.startswith("{\n  ")  # indented, one newline
    no_temporary_files(run.path)


def test_write_json_rejects_what_json_cannot_hold(tmp_path):
    with pytest.raises(TypeError):  # a bug, not a file problem
        write_json(tmp_path / "x.json", {"tensor": torch.zeros(2)})
    assert not (tmp_path / "x.json").exists()
    no_temporary_files(tmp_path)


# -------------------------------------------------------- damaged or missing
def _write(run: RunDir, name: str) -> Path:
    if name == "metrics.json":
        run.write_metrics(METRICS)
    elif name == "summary.json":
        run.write_summary(SUMMARY)
    elif name == "checkpoint.pt":
        run.save_checkpoint({"format": "x", "buffers": torch.zeros(1000)})
    else:
        run.save_posterior(small_posterior())
    return run.path / name


def _read(run: RunDir, name: str) -> Callable[[], object]:
    return {
        "metrics.json": run.read_metrics,
        "summary.json": run.read_summary,
        "checkpoint.pt": run.load_checkpoint,
        "posterior.pt": run.load_posterior,
    }[name]


@pytest.mark.parametrize(
    "name", ["metrics.json", "summary.json", "checkpoint.pt", "posterior.pt"]
)
def test_a_truncated_file_is_a_run_file_error_naming_it(tmp_path, name):
    run = RunDir(tmp_path / "run").prepare()
    path = _write(run, name)
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(RunFileError, match=re.escape(str(path))) as info:
        _read(run, name)()
    assert "corrupted" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("name", "needle"),
    [
        ("metrics.json", "not evaluated (no metrics.json)"),
        ("summary.json", "holds no finished run (no summary.json)"),
        ("checkpoint.pt", "no checkpoint.pt in"),
        ("posterior.pt", "holds no finished run (no posterior.pt)"),
    ],
)
def test_a_missing_file_is_a_run_file_error(tmp_path, name, needle):
    run = RunDir(tmp_path / "run")
    with pytest.raises(RunFileError, match=re.escape(needle)):
        _read(run, name)()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[1, 2]", "is corrupted: not a JSON object"),
        ('{"dataset": "x"}', "is corrupted: no 'hybrid' entry"),
        ('{"hybrid": {"ws": 1.0', "is corrupted: Expecting"),
        ("", "is corrupted: Expecting value at line 1 column 1"),
    ],
)
def test_a_metrics_file_that_is_not_one(tmp_path, text, needle):
    run = RunDir(tmp_path).prepare()
    run.metrics_json.write_text(text)
    with pytest.raises(RunFileError, match=re.escape(needle)):
        run.read_metrics()


def test_an_evaluation_of_another_release_says_what_to_do(tmp_path):
    run = RunDir(tmp_path).prepare()
    raw = json_safe(METRICS.to_json())
    del raw["seconds"]
    run.metrics_json.write_text(json.dumps(raw))
    with pytest.raises(RunFileError) as info:
        run.read_metrics()
    message = str(info.value)
    assert message.startswith(f"{run.metrics_json}: not an evaluation (KeyError")
    assert message.endswith(f"; evaluate the run again (torchcf evaluate {tmp_path})")
    assert "\n" not in message


def test_other_damage(tmp_path, cfg):
    run = RunDir(tmp_path / "run").prepare()
    run.summary_json.write_text('{"dataset": "x"}')
    with pytest.raises(RunFileError, match=r"summary.json: no 'pairwise' entry"):
        run.read_summary()
    raw = SUMMARY.to_json()
    del raw["per_model"]
    run.summary_json.write_text(json.dumps(raw))
    with pytest.raises(
        RunFileError, match=r"summary.json: not a run summary \(KeyError: 'per_model'"
    ):
        run.read_summary()
    run.summary_json.write_bytes(b"\xff\xfe{}")
    with pytest.raises(RunFileError, match=r"summary.json is corrupted: not UTF-8"):
        run.read_summary()
    torch.save([1, 2, 3], run.checkpoint)
    with pytest.raises(RunFileError, match=r"checkpoint.pt is corrupted: a list"):
        run.load_checkpoint()
    torch.save({"format": "something else"}, run.posterior_pt)
    with pytest.raises(RunFileError, match=r"posterior.pt: not a torchcf posterior"):
        run.load_posterior()
    raw = small_posterior().to_dict()
    del raw["hybrid"]["idm"]["score"]
    torch.save(raw, run.posterior_pt)
    with pytest.raises(RunFileError, match=r"malformed torchcf posterior \(KeyError"):
        run.load_posterior()
    run.posterior_pt.write_bytes(os.urandom(256))
    with pytest.raises(RunFileError, match="posterior.pt: unreadable or corrupted"):
        run.load_posterior()
    # More than tensors and plain data: refused, with the cause and not a page
    # of advice.
    torch.save({"cfg": cfg}, run.checkpoint)
    with pytest.raises(RunFileError, match="checkpoint.pt: unreadable") as info:
        run.load_checkpoint()
    assert "Unsupported global" in str(info.value) and "(1)" not in str(info.value)

    raw_cfg = resolved_json(cfg)
    raw_cfg["abc"]["n_particles"] = -1
    run.config_json.write_text(json.dumps(raw_cfg))
    with pytest.raises(ConfigError, match=r"config.json: abc.n_particles: must be > 0"):
        run.read_config()
    fresh = RunDir(tmp_path / "fresh").prepare()
    fresh.write_config(cfg)
    with pytest.raises(RunFileError, match=r"no finished run \(no posterior.pt\)"):
        fresh.load_run()
    (tmp_path / "run" / "config.json").unlink()
    with pytest.raises(RunFileError, match=r"holds no run \(no config.json\)"):
        run.read_config()


def test_readers_of_files_anywhere(tmp_path):
    with pytest.raises(RunFileError, match=r"nothing.json: no such file"):
        read_json_object(tmp_path / "nothing.json")
    with pytest.raises(RunFileError, match=r"nothing.pt: no such file"):
        read_torch(tmp_path / "nothing.pt")
    with pytest.raises(RunFileError, match="cannot read"):
        read_json_object(tmp_path)  # a directory


# ------------------------------------------------------- the output directory
def test_prepare(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(
        RunFileError,
        match=re.escape(f"output directory {blocker} exists and is not a directory"),
    ):
        RunDir(blocker).prepare()
    with pytest.raises(
        RunFileError, match=r"cannot create the output directory .*: Not a directory"
    ):
        RunDir(blocker / "run").prepare()
    assert blocker.read_text() == "not a folder"
    with pytest.raises(RunFileError, match="cannot create the output directory"):
        RunDir(blocker / "run").probe()
    run = RunDir(tmp_path / "a" / "b")
    run.probe()  # the same checks, leaving nothing behind
    assert not (tmp_path / "a").exists()
    assert run.prepare() is run
    assert run.path.is_dir() and not list(run.path.iterdir())  # the probe is gone
    run.probe()
    assert run.path.is_dir()  # an existing directory stays


def test_a_failed_write_keeps_the_previous_file(tmp_path, monkeypatch):
    """torch.save failing half-way (mocked): the previous file stays, no
    temporary file is left, the error names the file and the reason."""
    path = tmp_path / "checkpoint.pt"
    atomic_torch_save({"n": torch.arange(3)}, path)

    def save(obj, handle, *args, **kwargs):
        handle.write(b"PK\x03\x04 half")
        try:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        except OSError:
            # as torch does: the OSError becomes a RuntimeError on closing
            raise RuntimeError("[enforce fail] unexpected pos") from None

    monkeypatch.setattr(torch, "save", save)
    with pytest.raises(RunFileError, match=r"checkpoint.pt: No space left on device"):
        atomic_torch_save({"n": torch.arange(9)}, path)
    monkeypatch.undo()
    assert torch.equal(read_torch(path)["n"], torch.arange(3))
    no_temporary_files(tmp_path)


# ------------------------------------------------- a real, full file system
@pytest.fixture
def small_fs(tmp_path) -> Iterator[Path]:
    """An empty tmpfs of TMPFS_SIZE, mounted for the test (skips where mounting is
    not permitted) and always unmounted."""
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    try:
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE}", "tmpfs", str(mount)],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.SubprocessError) as error:
        pytest.skip(f"cannot mount a tmpfs here: {error}")
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        if subprocess.run(["umount", str(mount)], capture_output=True).returncode:
            subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def fill(folder: Path) -> None:
    """Fill the file system of ``folder`` to the last byte."""
    with open(folder / "filler", "wb", buffering=0) as handle:
        block = b"\0" * 4096
        while True:
            try:
                handle.write(block)
            except OSError as error:
                assert error.errno == errno.ENOSPC, error
                break
    assert os.statvfs(folder).f_bavail == 0


def test_torch_save_on_a_full_disk(small_fs):
    run = RunDir(small_fs / "run").prepare()
    before = {"format": "x", "buffers": torch.arange(1000.0)}
    run.save_checkpoint(before)
    fill(small_fs)
    big = {"format": "x", "buffers": torch.zeros(200_000)}  # 800 kB > the disk
    with pytest.raises(RunFileError) as info:
        atomic_torch_save(big, run.checkpoint)  # torch's RuntimeError underneath
    message = str(info.value)
    assert message == f"cannot write {run.checkpoint}: No space left on device"
    with pytest.raises(RunFileError, match="No space left on device"):
        run.save_checkpoint(big)
    kept = run.load_checkpoint()
    assert torch.equal(kept["buffers"], before["buffers"])
    no_temporary_files(small_fs)
    with pytest.raises(RunFileError, match="cannot write in the output directory"):
        RunDir(small_fs / "another").prepare()  # the probe finds the disk full
    with pytest.raises(RunFileError, match="cannot write in the output directory"):
        RunDir(small_fs / "a" / "b").probe()
    assert not (small_fs / "a").exists()
    with pytest.raises(RunFileError, match="No space left on device"):
        run.prepare()


def test_text_write_on_a_full_disk(small_fs):
    path = small_fs / "metrics.json"
    atomic_write_text(path, '{"before": 1}\n')
    fill(small_fs)
    with pytest.raises(RunFileError) as info:
        atomic_write_text(path, "x" * 700_000)
    assert str(info.value) == f"cannot write {path}: No space left on device"
    with pytest.raises(RunFileError, match="No space left on device"):
        RunDir(small_fs).write_metrics(evaluation(dataset="y" * 700_000))
    assert path.read_text() == '{"before": 1}\n'
    no_temporary_files(small_fs)


@pytest.mark.slow  # evaluation and crossval runs
def test_evaluate_and_crossval_on_a_full_disk(small_fs, tmp_path, cfg):
    """The commands end with one line and exit code 2, before any work."""
    run = finished_run(small_fs / "run", cfg)
    fill(small_fs)
    result = run_module("torchcf", "evaluate", str(run))
    one_error_line(result, f"output directory {run.path}", "No space left on device")
    assert not run.is_evaluated()
    no_temporary_files(small_fs)

    config = tmp_path / "cfg.json"
    config.write_text(json.dumps(resolved_json(cfg)))
    out = small_fs / "cv"
    result = run_module("torchcf", "crossval", str(config), "--out", str(out))
    one_error_line(result, "cannot", str(out), "No space left on device")
    no_temporary_files(small_fs)


# ------------------------------------------------ commands on damaged files
@pytest.mark.slow  # a training, then an evaluation
def test_evaluate_a_run_with_a_truncated_summary(tmp_path, cfg):
    run = finished_run(tmp_path / "run", cfg)
    text = run.summary_json.read_text()
    run.summary_json.write_text(text[: len(text) // 2])
    result = run_module("torchcf", "evaluate", str(run))
    one_error_line(result, str(run.summary_json), "is corrupted")
    assert not run.is_evaluated()


@pytest.mark.slow  # a cross-validation
def test_crossval_with_a_truncated_fold_metrics(tmp_path, cfg):
    config = tmp_path / "cfg.json"
    config.write_text(json.dumps(resolved_json(cfg)))
    out = RunDir(tmp_path / "cv")
    for fold in range(2):
        out.fold(fold).prepare().write_metrics(METRICS)
    damaged = out.fold(1).metrics_json
    damaged.write_text(damaged.read_text()[:20])
    result = run_module(
        "torchcf", "crossval", str(config), "--folds", "2", "--out", str(out)
    )
    one_error_line(result, str(damaged), "is corrupted")
    assert not out.is_evaluated()


@pytest.mark.slow  # trainings on a full disk
@pytest.mark.parametrize("free_kb", [0, 24])
def test_training_on_a_full_disk(small_fs, tmp_path, free_kb):
    """``torchcf train`` with ``--out`` on a small file system that is
    full (0 kB left: found by the probe, before any data is read) or fills up
    during the run (24 kB left: a checkpoint or the posterior does not fit, and
    torch.save's RuntimeError underneath is the machine's error): one line, exit
    code 2, no temporary file, and what was written before still readable."""
    config = write_config(tmp_path / "cfg.json", write_data(tmp_path / "pairs"))
    fill(small_fs)
    if free_kb:
        with open(small_fs / "filler", "r+b") as handle:
            handle.truncate(os.path.getsize(small_fs / "filler") - free_kb * 1024)
    out = small_fs / "run"
    result = run_module("torchcf", "train", str(config), "--out", str(out), "--no-eval")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if "particle" not in line]
    lines = [line for line in lines if line.strip()]  # less the progress bars
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "No space left on device" in lines[0] and str(out) in lines[0]
    no_temporary_files(small_fs)
    run = RunDir(out)
    assert not run.is_trained()
    if free_kb:
        assert "holds the data" not in result.stderr
        assert run.read_config().abc.top_n == 3  # config.json went in whole
        if run.checkpoint.exists():
            assert run.load_checkpoint()["format"] == "torchcf.checkpoint/1"
    else:
        assert not out.exists()
        assert "train" not in result.stderr.split("error:")[0]  # no data notes


def test_from_json_safe_inverts_json_safe():
    value = {"ws": math.inf, "min": -math.inf, "rows": [1.0, math.nan], "name": "hl"}
    back = from_json_safe(json.loads(json.dumps(json_safe(value))))
    assert back["ws"] == math.inf and back["min"] == -math.inf
    assert back["rows"][0] == 1.0 and math.isnan(back["rows"][1])
    assert back["name"] == "hl"
