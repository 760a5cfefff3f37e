"""The run configuration (torchcf.config) and the training / test splits
(torchcf.data.splits): defaults, every constraint, overrides, hashing, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from tests.conftest import synthetic_pairs
from torchcf.cli.config import main
from torchcf.config import (
    ABCConfig,
    ConfigError,
    ModelSpec,
    TrainConfig,
    apply_overrides,
    config_hash,
    load_config,
    load_split,
    resolved_json,
    validate_config,
)
from torchcf.data import DataError, kfold_split
from torchcf.models import MODELS, get_model

BASE: dict[str, Any] = {"data": {"name": "car-model-2"}}


def make(**sections: Any) -> TrainConfig:
    """Validate BASE updated with ``sections`` (top-level keys)."""
    return validate_config({**BASE, **sections})


def error_of(raw: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as info:
        validate_config(raw)
    message = str(info.value)
    assert "\n" not in message
    return message


def write(tmp_path: Path, raw: Any, name: str = "run.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(raw), encoding="utf-8")
    return path


# -------------------------------------------------------------------- defaults
def test_defaults() -> None:
    cfg = make()
    assert [m.name for m in cfg.models] == list(MODELS)
    assert all(m.prior is None for m in cfg.models)
    assert cfg.abc == ABCConfig()
    assert cfg.abc.n_particles == 1_000_000 and cfg.abc.layout == "paired"
    assert cfg.abc.weights == (0.5, 0.3, 0.2)
    assert cfg.abc.buffer_size == 15
    assert cfg.eval.beta == 0.15 and cfg.eval.sinkhorn_reg == 0.05
    assert cfg.data.split == "dataset" and cfg.data.drop_duplicates
    assert (cfg.device, cfg.dtype, cfg.compile) == ("cpu", "float32", "auto")
    assert cfg.torch_dtype == torch.float32
    assert cfg.output is None and cfg.threads is None


def test_path_and_kfold_valid() -> None:
    cfg = make(data={"path": "some/folder", "split": "kfold", "folds": 5, "fold": 4})
    assert (cfg.data.path, cfg.data.folds, cfg.data.fold) == ("some/folder", 5, 4)


def test_cuda_allowed_and_canonical() -> None:
    assert make(device="cuda").device == "cuda"
    assert make(device="cuda:1").device == "cuda:1"


# ------------------------------------------------------------------ constraints
@pytest.mark.parametrize(
    ("raw", "where"),
    [
        ({"abc": {"n_particles": -5}}, "abc.n_particles: must be > 0, got -5"),
        ({"abc": {"n_particles": 0}}, "abc.n_particles: must be > 0"),
        ({"abc": {"n_particles": 1.5}}, "abc.n_particles"),
        ({"abc": {"layout": "grid"}}, "abc.layout"),
        ({"abc": {"top_n": 0}}, "abc.top_n: must be > 0"),
        ({"abc": {"sensitivity_n": []}}, "abc.sensitivity_n: must not be empty"),
        ({"abc": {"sensitivity_n": [5, 0]}}, "abc.sensitivity_n[1]: must be > 0"),
        ({"abc": {"chunk_size": 0}}, "abc.chunk_size: must be > 0"),
        ({"abc": {"seed": -1}}, "abc.seed: must be >= 0"),
        ({"abc": {"selection": "best"}}, "abc.selection"),
        ({"abc": {"global_size": 10}}, "abc: global_size=10 only applies"),
        (
            {"abc": {"selection": "global", "global_size": 0}},
            "abc.global_size: must be > 0",
        ),
        ({"abc": {"weights": [0.5, -0.1, 0.6]}}, "abc.weights[1]: must be >= 0"),
        ({"abc": {"weights": [0, 0, 0]}}, "abc.weights: must not all be 0"),
        ({"abc": {"weights": [1, 1]}}, "abc.weights"),
        ({"abc": {"checkpoint_every": 0}}, "abc.checkpoint_every: must be > 0"),
        ({"eval": {"beta": 1.5}}, "eval.beta: must be <= 1"),
        ({"eval": {"beta": -0.1}}, "eval.beta: must be >= 0"),
        ({"eval": {"sinkhorn_reg": 0}}, "eval.sinkhorn_reg: must be > 0"),
        ({"eval": {"sinkhorn_max_iter": 0}}, "eval.sinkhorn_max_iter: must be > 0"),
        ({"device": "gpu0"}, "device: not a torch device"),
        ({"dtype": "float16"}, "dtype"),
        ({"threads": 0}, "threads: must be > 0"),
        ({"compile": "yes"}, "compile"),
        ({"output": ""}, "output"),
        ({"models": []}, "models: must not be empty"),
        ({"models": ["idm", "bogus"]}, "models[1].name: unknown model 'bogus'"),
        ({"models": ["idm", {"name": "IDM"}]}, "models: each model at most once"),
        ({"models": "idm"}, "models"),
    ],
)
def test_constraint_rejected(raw: dict[str, Any], where: str) -> None:
    assert where in error_of({**BASE, **raw})


@pytest.mark.parametrize(
    ("data", "where"),
    [
        ({}, "data: give exactly one of name"),
        ({"name": "car-model-2", "path": "x"}, "data: give exactly one of name"),
        ({"name": "car-model-3"}, "data.name: unknown dataset 'car-model-3'"),
        ({"path": "x", "root": "y"}, "data: root is only used with name"),
        ({"name": "car-model-2", "units": "km"}, "data.units"),
        ({"name": "car-model-2", "dt": 0}, "data.dt: must be > 0"),
        ({"name": "car-model-2", "leader_length": -1}, "data.leader_length"),
        ({"name": "car-model-2", "min_spacing": -1}, "data.min_spacing: must be >= 0"),
        ({"name": "car-model-2", "split": "random"}, "data.split"),
        ({"name": "car-model-2", "split": "kfold", "folds": 1}, "data.folds"),
        ({"name": "car-model-2", "split": "kfold", "fold": -1}, "data.fold"),
        ({"name": "car-model-2", "split": "kfold", "fold": 3}, "data: fold must be <"),
        ({"name": "car-model-2", "fold": 1}, "only used with split='kfold'"),
        ({"name": "car-model-2", "drop_duplicates": "maybe"}, "data.drop_duplicates"),
    ],
)
def test_data_constraint_rejected(data: dict[str, Any], where: str) -> None:
    assert where in error_of({"data": data})


def test_missing_data_and_nan() -> None:
    assert error_of({}) == "data: required"
    assert "abc.checkpoint_every" in error_of(
        {**BASE, "abc": {"checkpoint_every": float("nan")}}
    )


@pytest.mark.parametrize(
    "raw",
    [
        {**BASE, "bogus": 1},
        {"data": {"name": "car-model-2", "bogus": 1}},
        {**BASE, "abc": {"bogus": 1}},
        {**BASE, "eval": {"bogus": 1}},
        {**BASE, "models": [{"name": "idm", "bogus": 1}]},
    ],
)
def test_unknown_keys_rejected(raw: dict[str, Any]) -> None:
    assert "bogus: unknown key (known:" in error_of(raw)


def test_unknown_key_suggests() -> None:
    message = error_of({**BASE, "abc": {"n_particle": 5}})
    assert message.startswith("abc.n_particle: unknown key")
    assert "did you mean 'n_particles'?" in message


def test_several_errors_one_line() -> None:
    message = error_of(
        {
            **BASE,
            "abc": {"n_particles": -1, "top_n": 0, "seed": -1, "chunk_size": 0},
        }
    )
    assert message.count("; ") == 3 and message.endswith("and 1 more")


# ----------------------------------------------------------------------- models
def test_models_shorthand_and_objects() -> None:
    cfg = make(models=["idm", {"name": "HL"}, {"name": "mpc", "prior": {}}])
    assert [m.name for m in cfg.models] == ["idm", "hl", "mpc"]
    assert all(isinstance(m, ModelSpec) for m in cfg.models)
    assert cfg.models[2].prior is None  # {} is no override
    assert make(models=["idm"]) == make(models=[{"name": "idm"}])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_prior_override_applied(dtype: torch.dtype) -> None:
    model = get_model("idm")
    spec = ModelSpec(name="idm", prior={"v0": (20.0, 30.0), "T": (1, 2)})
    box = spec.bounds(dtype)
    default = model.prior_bounds(dtype)
    assert box.shape == (model.n_params, 2) and box.dtype == dtype
    i, j = model.param_names.index("v0"), model.param_names.index("T")
    assert box[i].tolist() == [20.0, 30.0] and box[j].tolist() == [1.0, 2.0]
    others = [k for k in range(model.n_params) if k not in (i, j)]
    assert torch.equal(box[others], default[others])
    assert torch.equal(ModelSpec(name="idm").bounds(dtype), default)


@pytest.mark.parametrize(
    ("prior", "where"),
    [
        ({"kappa": [0, 1]}, "models[0].prior: unknown parameter 'kappa' for idm"),
        ({"v0": [30, 20]}, "models[0].prior: v0: needs low < high"),
        ({"v0": [20, 20]}, "needs low < high"),
        ({"v0": [20]}, "models[0].prior.v0"),
        ({"v0": [20, float("inf")]}, "models[0].prior.v0[1]"),
    ],
)
def test_prior_override_rejected(prior: dict[str, Any], where: str) -> None:
    message = error_of({**BASE, "models": [{"name": "idm", "prior": prior}]})
    assert where in message
    if "unknown parameter" in where:
        assert f"(known: {', '.join(get_model('idm').param_names)})" in message


# -------------------------------------------------------------------- overrides
def test_overrides() -> None:
    raw = {**BASE, "models": ["ovm", "idm"], "abc": {"top_n": 3}}
    out = apply_overrides(
        raw,
        [
            "abc.n_particles=200000",
            "device=cpu",
            "abc.weights=[1,0,0]",
            "eval.beta=0.5",  # creates the "eval" object
            "models.1.name=hl",
            "models.0.prior.kappa=[0.6, 1.5]",  # shorthand "ovm" becomes an object
            "output=runs/a=b",  # only the first "=" splits
        ],
    )
    assert raw == {**BASE, "models": ["ovm", "idm"], "abc": {"top_n": 3}}
    assert out["abc"] == {"top_n": 3, "n_particles": 200000, "weights": [1, 0, 0]}
    assert out["device"] == "cpu" and out["eval"] == {"beta": 0.5}
    assert out["models"] == [
        {"name": "ovm", "prior": {"kappa": [0.6, 1.5]}},
        {"name": "hl"},
    ]
    assert out["output"] == "runs/a=b"
    cfg = validate_config(out)
    assert cfg.abc.n_particles == 200000 and cfg.abc.weights == (1.0, 0.0, 0.0)
    assert cfg.models[0].prior == {"kappa": (0.6, 1.5)}


def test_override_whole_list_and_nested_creation() -> None:
    out = apply_overrides({}, ['models=["idm","hl"]', "data.name=car-model-1"])
    assert out == {"models": ["idm", "hl"], "data": {"name": "car-model-1"}}
    assert apply_overrides({"abc": None}, ["abc.seed=3"]) == {"abc": {"seed": 3}}


@pytest.mark.parametrize(
    "item",
    ["abc.top_n", "=5", "abc..top_n=5", "abc.=5", "abc.top_n.x=1", "models.5.name=x"],
)
def test_bad_override(item: str) -> None:
    raw = {**BASE, "models": ["idm"], "abc": {"top_n": 5}}
    with pytest.raises(ConfigError, match="override"):
        apply_overrides(raw, [item])


# ------------------------------------------------------------------ load_config
def test_load_config(tmp_path: Path) -> None:
    path = write(tmp_path, {**BASE, "abc": {"n_particles": 10}}, "smoke.json")
    cfg = load_config(path, ["abc.seed=7"])
    assert cfg.output == "runs/smoke" and cfg.abc.seed == 7
    assert load_config(path, ["output=elsewhere"]).output == "elsewhere"
    # config.json as the trainer writes it loads back to the same config.
    again = load_config(write(tmp_path, resolved_json(cfg), "config.json"))
    assert again == cfg


def test_load_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{\n  "data": {"name": "car-model-2",}\n}', encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid JSON: .* line 2 column"):
        load_config(bad)
    with pytest.raises(ConfigError, match="must hold a JSON object, got list"):
        load_config(write(tmp_path, [1, 2]))
    with pytest.raises(ConfigError, match=r"abc\.top_n: must be > 0"):
        load_config(write(tmp_path, BASE), ["abc.top_n=0"])


# ------------------------------------------------------------ hash and resolved
def test_config_hash() -> None:
    cfg = make()
    digest = config_hash(cfg)
    assert len(digest) == 16 and int(digest, 16) >= 0
    assert config_hash(make()) == digest
    same = make(
        output="x",
        threads=4,
        eval={"beta": 0.5},
        abc={"checkpoint_every": 1.0},
        models=[{"name": m} for m in MODELS],
    )
    assert config_hash(same) == digest
    assert config_hash(make(abc={"seed": 1})) != digest
    assert config_hash(make(abc={"weights": [1, 0, 0]})) != digest
    assert config_hash(make(models=["idm"])) != digest
    assert config_hash(make(models=[{"name": "idm", "prior": {"v0": [20, 30]}}])) != (
        config_hash(make(models=["idm"]))
    )
    assert config_hash(make(data={"name": "car-model-1"})) != digest


def test_resolved_json() -> None:
    cfg = make(models=["idm", {"name": "hl", "prior": {"tau": [0.1, 1]}}])
    data = resolved_json(cfg)
    assert json.loads(json.dumps(data)) == data
    assert data["models"] == [
        {"name": "idm", "prior": None},
        {"name": "hl", "prior": {"tau": [0.1, 1.0]}},
    ]
    assert data["abc"]["weights"] == [0.5, 0.3, 0.2]
    assert validate_config(data) == cfg


# --------------------------------------------------------------------------- CLI
def test_main_resolves(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, BASE)
    assert main([str(path), "--set", "abc.seed=2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["config"]["abc"]["seed"] == 2 and out["config"]["output"] == "runs/run"
    assert out["hash"] == config_hash(load_config(path, ["abc.seed=2"]))


def test_main_bad_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(write(tmp_path, {"data": {"name": "nope"}}))]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: data.name: unknown dataset") and err.count("\n") == 1


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "torchcf", "config", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )


def test_cli_schema() -> None:
    result = run_cli("--schema")
    assert result.returncode == 0, result.stderr
    schema = json.loads(result.stdout)
    assert "n_particles" in result.stdout
    assert schema["properties"]["models"]["items"]["anyOf"][0]["enum"] == list(MODELS)


def test_cli_bad_config(tmp_path: Path) -> None:
    path = write(tmp_path, {**BASE, "abc": {"n_particles": -5}})
    result = run_cli(str(path))
    assert result.returncode == 2
    assert result.stderr == "error: abc.n_particles: must be > 0, got -5\n"
    assert "Traceback" not in result.stderr and result.stdout == ""


def test_main_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2 and "give a CONFIG file" in capsys.readouterr().err


# -------------------------------------------------------------------- k-fold
@pytest.mark.parametrize(("n_pairs", "folds"), [(10, 3), (7, 2), (5, 5)])
def test_kfold_partitions(n_pairs: int, folds: int) -> None:
    pairs = synthetic_pairs(n_pairs=n_pairs, n_steps=20)
    pairs = pairs.subset(list(range(n_pairs)))  # pair_ids 0..N-1 track positions
    tests = []
    for fold in range(folds):
        train, test = kfold_split(pairs, folds, fold, seed=0)
        train_ids, test_ids = list(train.pair_ids), list(test.pair_ids)
        assert train_ids == sorted(train_ids) and test_ids == sorted(test_ids)
        assert not set(train_ids) & set(test_ids)
        assert sorted(train_ids + test_ids) == list(range(n_pairs))
        assert (train.split, test.split) == ("train", "test")
        assert torch.equal(test.x_lead, pairs.x_lead[:, test_ids])
        tests.append(test_ids)
    # Test folds partition the pairs, sizes as np.array_split makes them.
    assert sorted(i for t in tests for i in t) == list(range(n_pairs))
    sizes = [len(t) for t in tests]
    assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)


def test_kfold_seeded() -> None:
    pairs = synthetic_pairs(n_pairs=12, n_steps=20)
    first = kfold_split(pairs, 3, 1, seed=5)[1].pair_ids
    assert kfold_split(pairs, 3, 1, seed=5)[1].pair_ids == first
    others = {kfold_split(pairs, 3, 1, seed=s)[1].pair_ids for s in range(6, 11)}
    assert others - {first}


@pytest.mark.parametrize(
    ("n_pairs", "folds", "fold", "match"),
    [
        (6, 1, 0, "folds must be >= 2"),
        (6, 3, 3, "fold must be in"),
        (6, 3, -1, "fold must be in"),
        (2, 3, 0, "2 pairs cannot be split into 3 folds"),
    ],
)
def test_kfold_errors(n_pairs: int, folds: int, fold: int, match: str) -> None:
    pairs = synthetic_pairs(n_pairs=n_pairs, n_steps=20)
    with pytest.raises(DataError, match=match):
        kfold_split(pairs, folds, fold, seed=0)


def test_load_split_folder_kfold(tmp_path: Path) -> None:
    # A six-CSV folder through the real reader: load_split passes dt and the
    # k-fold settings through.
    import numpy as np

    from torchcf.data.reader import FILES

    pairs = synthetic_pairs(n_pairs=6, n_steps=30)
    for field, file_name in FILES.items():
        values = getattr(pairs, field).numpy()
        np.savetxt(tmp_path / file_name, values, delimiter=",")
    data = make(
        data={
            "path": str(tmp_path),
            "dt": 0.1,
            "split": "kfold",
            "folds": 3,
            "fold": 2,
            "split_seed": 4,
        }
    ).data
    train, test = load_split(data, download=False)
    assert (train.n_pairs, test.n_pairs) == (4, 2)
    assert sorted(train.pair_ids + test.pair_ids) == list(range(6))
    assert test.pair_ids == kfold_split(pairs, 3, 2, seed=4)[1].pair_ids


def test_split_pairs_takes_plain_arguments(tmp_path: Path) -> None:
    # The data layer's split needs no configuration object: the same folder and
    # k-fold settings give the pairs load_split gives from a DataConfig.
    import numpy as np

    from torchcf.data import split_pairs
    from torchcf.data.reader import FILES

    pairs = synthetic_pairs(n_pairs=6, n_steps=30)
    for field, file_name in FILES.items():
        np.savetxt(tmp_path / file_name, getattr(pairs, field).numpy(), delimiter=",")
    train, test = split_pairs(
        str(tmp_path), "kfold", folds=3, fold=1, seed=4, dt=0.1, download=False
    )
    data = make(
        data={"path": str(tmp_path), "dt": 0.1, "split": "kfold", "folds": 3}
        | {"fold": 1, "split_seed": 4}
    ).data
    by_config = load_split(data, download=False)
    assert (train.pair_ids, test.pair_ids) == (
        by_config[0].pair_ids,
        by_config[1].pair_ids,
    )
    with pytest.raises(DataError, match="split must be 'dataset' or 'kfold'"):
        split_pairs(str(tmp_path), "random", dt=0.1, download=False)


def test_load_split_lives_in_config_only() -> None:
    """The data section's reader is the config's (no alias in torchcf.data)."""
    import torchcf.data

    assert not hasattr(torchcf.data, "load_split")


def test_load_split_real(data_root: Path) -> None:
    data = make(
        data={"name": "car-model-2", "root": str(data_root), "drop_duplicates": True}
    ).data
    train, test = load_split(data, download=False)
    assert (train.n_pairs, test.n_pairs) == (44, 17)
    assert (train.split, test.split) == ("train", "test")
    assert not set(train.pair_ids) & set(test.pair_ids)


def test_model_specs_hold_their_model_objects() -> None:
    # Parsed once when the config is read: the spec's model is the registry's one
    # instance of the canonical name; an effect option with an exponent keeps its
    # '+' (the name is not split by hand).
    from torchcf.models import get_model

    cfg = make(models=["IDM", "idm+delay", "hl+grade(end=1e+06)"])
    idm, delayed, graded = cfg.models
    assert idm.model is get_model("idm") and idm.plain
    assert delayed.model is get_model("idm+delay") and not delayed.plain
    assert not graded.plain and graded.model.effects[0].name == "grade"
    assert graded.model.param_names[-1].startswith("grade")
