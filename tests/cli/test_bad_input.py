"""Bad input ends a run cleanly: exit code 2, one line naming the problem, no
traceback, and nothing left behind that looks like a finished result.

One test per case of issue 8: malformed JSON; an unknown key; an unknown model or
effect; a prior whose lower bound is above its upper; a non-positive dt; a
non-positive particle count; a top_n that the pairs cannot fill; a data file that
is missing, of another shape, or holds NaN or text; an output directory that
cannot be written; a full disk while checkpointing; a resume with another config;
a corrupted checkpoint or posterior.
"""

from __future__ import annotations

import copy
import errno
import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from tests.runs import run_module, write_config, write_data
from torchcf.abc.rounds import PILOT_ROUND
from torchcf.cli import evaluate as evaluate_cli
from torchcf.cli import train as train_cli
from torchcf.posterior import Posterior

#: Files whose presence says a run (or its evaluation) finished.
FINISHED = ("posterior.pt", "summary.json", "metrics.json")


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_data(tmp_path_factory.mktemp("data") / "pairs")


@pytest.fixture(scope="module")
def finished(tmp_path_factory, data) -> tuple[Path, Path]:
    """A finished, evaluated run and its config: (config path, run directory)."""
    root = tmp_path_factory.mktemp("finished")
    config = write_config(root / "cfg.json", data)
    assert train_cli.main([str(config), "--out", str(root / "run")]) == 0
    return config, root / "run"


def one_error_line(stderr: str, *needles: str) -> str:
    """The single ``error:`` line of ``stderr``, checked to be its last line and to
    name every needle; no traceback anywhere."""
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1, stderr
    assert lines[-1] == errors[0], stderr
    for needle in needles:
        assert needle in errors[0], (needle, errors[0])
    return errors[0]


def fails_cleanly(capsys, argv: list[str], *needles: str, cli=train_cli) -> str:
    """``cli.main(argv)`` returns 2 with exactly one line on stderr."""
    assert cli.main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1, captured.err
    return one_error_line(captured.err, *needles)


def nothing_finished(out: Path) -> None:
    for name in FINISHED:
        assert not (out / name).exists(), name
    if out.is_dir():
        assert not [p.name for p in out.iterdir() if ".tmp" in p.name]


# ------------------------------------------------------------------ the config
@pytest.mark.slow  # commands in subprocesses
def test_malformed_json(tmp_path):
    config = tmp_path / "bad.json"
    config.write_text('{"data": {"path": "x"},\n  "abc": {"n_particles": 5,}}')
    out = tmp_path / "run"
    result = run_module("torchcf", "train", str(config), "--out", str(out))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1
    one_error_line(result.stderr, "bad.json", "not valid JSON", "line 2")
    assert not out.exists()


def test_unknown_key(tmp_path, capsys, data):
    config = write_config(tmp_path / "cfg.json", data, abc={"n_particle": 5})
    line = fails_cleanly(
        capsys, [str(config), "--out", str(tmp_path / "run")], "abc.n_particle"
    )
    assert "unknown key" in line and "did you mean 'n_particles'" in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("no_eval", [[], ["--no-eval"]])
def test_train_and_train_only_report_bad_input_alike(tmp_path, capsys, data, no_eval):
    """``torchcf train`` and ``torchcf train --no-eval`` (training only) share
    the options and the one policy: the same exit code and line, nothing
    written."""
    cli = train_cli
    config = write_config(tmp_path / "cfg.json", data, abc={"n_particle": 5})
    argv = [str(config), "--out", str(tmp_path / "run"), *no_eval]
    line = fails_cleanly(capsys, argv, "abc.n_particle", cli=cli)
    assert "did you mean 'n_particles'" in line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("name", "needle"),
    [("bogus", "unknown model 'bogus'"), ("idm+wobble", "unknown effect 'wobble'")],
)
def test_unknown_model_or_effect(tmp_path, capsys, data, name, needle):
    config = write_config(tmp_path / "cfg.json", data, models=["llcs", name])
    fails_cleanly(
        capsys, [str(config), "--out", str(tmp_path / "run")], "models[1]", needle
    )
    assert not (tmp_path / "run").exists()


def test_lower_bound_above_upper(tmp_path, capsys, data):
    models = [{"name": "idm", "prior": {"v0": [35, 25]}}]
    config = write_config(tmp_path / "cfg.json", data, models=models)
    fails_cleanly(
        capsys,
        [str(config), "--out", str(tmp_path / "run")],
        "models[0].prior",
        "v0: needs low < high, got [35.0, 25.0]",
    )


@pytest.mark.parametrize("dt", [-0.1, 0])
def test_non_positive_dt_in_the_config(tmp_path, capsys, data, dt):
    config = write_config(tmp_path / "cfg.json", data)
    fails_cleanly(
        capsys,
        [str(config), "--out", str(tmp_path / "run"), "--set", f"data.dt={dt}"],
        "data.dt: must be > 0",
    )


def test_non_positive_dt_in_the_data(tmp_path, capsys):
    folder = write_data(tmp_path / "pairs", n_pairs=6, n_steps=40)
    (folder / "meta.json").write_text(json.dumps({"dt": 0}))
    config = write_config(tmp_path / "cfg.json", folder)
    fails_cleanly(
        capsys, [str(config), "--out", str(tmp_path / "run")], "dt must be", "> 0"
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("n", [0, -5])
def test_non_positive_particle_count(tmp_path, capsys, data, n):
    config = write_config(tmp_path / "cfg.json", data)
    fails_cleanly(
        capsys,
        [str(config), "--set", f"abc.n_particles={n}", "--out", str(tmp_path / "r")],
        f"abc.n_particles: must be > 0, got {n}",
    )


@pytest.mark.parametrize(
    ("abc", "needles"),
    [
        # 8 pairs, 3 folds: 5 training pairs; 10 particles are 2 per pair.
        ({"n_particles": 10}, ("abc.top_n: 3", "5 training pairs", ">= 15")),
        (
            {"n_particles": 100, "sensitivity_n": [3, 30]},
            ("abc.sensitivity_n: 30", ">= 150"),
        ),
        ({"n_particles": 2, "layout": "full"}, ("abc.top_n: 3", "full layout")),
    ],
)
def test_top_n_larger_than_a_pair_receives(tmp_path, capsys, data, abc, needles):
    config = write_config(tmp_path / "cfg.json", data, abc=abc)
    out = tmp_path / "run"
    fails_cleanly(capsys, [str(config), "--out", str(out)], *needles)
    assert not out.exists()


# -------------------------------------------------------------------- the data
def _broken_data(tmp_path: Path, problem: str) -> Path:
    folder = write_data(tmp_path / "pairs", n_pairs=6, n_steps=40)
    speed = folder / "Leading Speed.csv"
    lines = speed.read_text().splitlines()
    if problem == "missing":
        speed.unlink()
    elif problem == "shape":
        speed.write_text("\n".join(lines[:-1]) + "\n")
    else:
        cells = lines[2].split(",")
        cells[1] = {"nan": "nan", "text": "fast"}[problem]
        lines[2] = ",".join(cells)
        speed.write_text("\n".join(lines) + "\n")
    return folder


@pytest.mark.parametrize(
    ("problem", "needles"),
    [
        ("missing", ("missing file 'Leading Speed.csv'",)),
        ("shape", ("'Leading Speed.csv' has 39 rows x 6 columns", "40 rows")),
        ("nan", ("NaN", "row 3, column 2 of 'Leading Speed.csv'")),
        ("text", ("not a number: 'fast'", "row 3, column 2 of 'Leading Speed.csv'")),
    ],
)
def test_bad_data_file(tmp_path, capsys, problem, needles):
    config = write_config(tmp_path / "cfg.json", _broken_data(tmp_path, problem))
    out = tmp_path / "run"
    fails_cleanly(capsys, [str(config), "--out", str(out)], *needles)
    assert not out.exists()


# ------------------------------------------------------------ the output folder
def test_output_directory_under_a_file(tmp_path, capsys, data):
    config = write_config(tmp_path / "cfg.json", data)
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    fails_cleanly(
        capsys,
        [str(config), "--out", str(blocker / "run")],
        "cannot create the output directory",
        "Not a directory",
    )
    fails_cleanly(
        capsys,
        [str(config), "--out", str(blocker)],
        f"output directory {blocker} exists and is not a directory",
    )
    assert blocker.read_text() == "not a folder"


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() == 0,
    reason="permissions do not bind root",
)
def test_output_directory_without_permission(tmp_path, capsys, data):
    config = write_config(tmp_path / "cfg.json", data)
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        fails_cleanly(
            capsys,
            [str(config), "--out", str(locked / "run")],
            "cannot create the output directory",
            "Permission denied",
        )
    finally:
        locked.chmod(0o700)


@pytest.mark.slow  # a training on a full disk
def test_full_disk_while_checkpointing(tmp_path, capsys, monkeypatch, data, finished):
    """The second checkpoint write fails half-way with ENOSPC: the first survives
    intact, no temporary file is left, and --resume later finishes the run."""
    config = write_config(tmp_path / "cfg.json", data, abc={"checkpoint_every": 1e-9})
    out = tmp_path / "run"
    real_save = torch.save
    saved = []

    def save(obj, handle, *args, **kwargs):
        if saved:
            handle.write(b"PK\x03\x04 half a checkpoint")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        saved.append(copy.deepcopy(obj))  # the buffers change after the save
        return real_save(obj, handle, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
    assert train_cli.main([str(config), "--out", str(out), "--no-eval"]) == 2
    err = capsys.readouterr().err
    one_error_line(err, f"cannot write {out / 'checkpoint.pt'}", "No space left")
    nothing_finished(out)
    kept = torch.load(out / "checkpoint.pt", weights_only=True)
    assert kept["progress"] == saved[0]["progress"]
    # the first round only: early rejection's pilot, 1/16 of a 500-particle chunk
    assert kept["progress"]["idm"]["next"] == 500 // PILOT_ROUND
    for name, buffer in saved[0]["buffers"].items():
        for key, value in buffer.items():
            assert torch.equal(kept["buffers"][name][key], value)

    monkeypatch.setattr(torch, "save", real_save)  # space again
    resume = [str(config), "--out", str(out), "--resume", "--no-eval"]
    assert train_cli.main(resume) == 0
    reference = Posterior.load(finished[1] / "posterior.pt")
    resumed = Posterior.load(out / "posterior.pt")
    for name in reference.models:
        for key in ("score", "index", "theta"):
            assert torch.equal(reference.buffers[name][key], resumed.buffers[name][key])


# ------------------------------------------------------------------ resume
def test_resume_with_a_different_config(tmp_path, capsys, finished):
    config, run = finished
    out = tmp_path / "run"
    shutil.copytree(run, out)
    fails_cleanly(
        capsys,
        [str(config), "--out", str(out), "--resume", "--set", "abc.seed=9"],
        "was run with a different config",
    )
    assert Posterior.load(out / "posterior.pt").shares  # left as it was


@pytest.mark.parametrize("damage", ["truncated", "garbage", "malformed"])
def test_corrupted_checkpoint(tmp_path, capsys, finished, damage):
    config, run = finished
    out = tmp_path / "run"
    out.mkdir()
    shutil.copy(run / "config.json", out / "config.json")
    checkpoint = out / "checkpoint.pt"
    blob = (run / "checkpoint.pt").read_bytes()
    if damage == "truncated":
        checkpoint.write_bytes(blob[: len(blob) // 2])
    elif damage == "garbage":
        checkpoint.write_text("this is not a checkpoint")
    else:
        raw = torch.load(run / "checkpoint.pt", weights_only=True)
        raw["progress"] = {"idm": {"next": 10, "bogus": 1}}
        torch.save(raw, checkpoint)
    line = fails_cleanly(
        capsys, [str(config), "--out", str(out), "--resume"], str(checkpoint)
    )
    assert ("corrupted" in line) and "another --out" in line
    nothing_finished(out)


# ------------------------------------------------------------------- evaluate
@pytest.mark.parametrize("damage", ["truncated", "garbage", "not a posterior"])
def test_corrupted_posterior(tmp_path, capsys, finished, damage):
    _, run = finished
    out = tmp_path / "run"
    shutil.copytree(run, out)
    (out / "metrics.json").unlink()
    posterior = out / "posterior.pt"
    blob = posterior.read_bytes()
    if damage == "truncated":
        posterior.write_bytes(blob[: len(blob) // 3])
    elif damage == "garbage":
        posterior.write_bytes(os.urandom(256))
    else:
        torch.save({"format": "something else"}, posterior)
    fails_cleanly(capsys, [str(out)], "posterior.pt", cli=evaluate_cli)
    assert not (out / "metrics.json").exists()


def test_corrupted_summary(tmp_path, capsys, finished):
    _, run = finished
    out = tmp_path / "run"
    shutil.copytree(run, out)
    (out / "metrics.json").unlink()
    (out / "summary.json").write_text('{"dataset": "x", "pairw')
    fails_cleanly(capsys, [str(out)], "summary.json is corrupted", cli=evaluate_cli)
    assert not (out / "metrics.json").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_asked_for_without_cuda(tmp_path, capsys, data):
    config = write_config(tmp_path / "cfg.json", data, device="cuda")
    out = tmp_path / "run"
    fails_cleanly(
        capsys, [str(config), "--out", str(out)], "device", "CUDA is not available"
    )
    assert not out.exists()


def test_crossval_with_more_folds_than_pairs_leaves_no_folder(tmp_path, capsys, data):
    from torchcf.cli import crossval as crossval_cli

    config = write_config(tmp_path / "cfg.json", data)
    out = tmp_path / "cv"
    assert crossval_cli.main([str(config), "--folds", "50", "--out", str(out)]) == 2
    one_error_line(capsys.readouterr().err, "fold")
    assert not out.exists()


def test_no_empty_folder_left_keeps_what_holds_a_file(tmp_path):
    from torchcf.system.files import no_empty_folder_left

    out = tmp_path / "out"
    with pytest.raises(RuntimeError), no_empty_folder_left(out):
        (out / "a" / "b").mkdir(parents=True)
        raise RuntimeError("refused")
    assert not out.exists()
    with pytest.raises(RuntimeError), no_empty_folder_left(out):
        (out / "fold0").mkdir(parents=True)
        (out / "empty").mkdir()
        (out / "fold0" / "checkpoint.pt").write_text("x")
        raise RuntimeError("failed after a checkpoint")
    assert (out / "fold0" / "checkpoint.pt").exists() and not (out / "empty").exists()
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(RuntimeError), no_empty_folder_left(existing):
        raise RuntimeError("refused")
    assert existing.is_dir()  # the user's folder is not ours to remove
