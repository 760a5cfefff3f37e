"""The re-calibration by the run's own sampler (torchcf.diagnose.recalibration): the
reference is the run with N more draws per pool model, after the run beside
the pool's variants trained as the run trains a model."""

from __future__ import annotations

import pytest
import torch

import torchcf.diagnose.recalibration as recalibration_module
from torchcf.config import validate_config
from torchcf.diagnose.arms.search import model_bounds
from torchcf.diagnose.recalibration import (
    FinalModel,
    buffers_in_order,
    retrain,
    searched_box,
    wrapped,
)
from torchcf.models import get_model
from torchcf.posterior import Posterior
from torchcf.sim.synthetic import synthetic_pairs
from torchcf.traffic.configured import plausibility_screen
from torchcf.train import train

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]
N = 3000


def _config(models=("idm", "llctg"), n_particles=N, method="rejection", **top):
    abc = {"n_particles": n_particles, "sensitivity_n": [5], "method": method}
    if method == "smc":
        abc["smc"] = {"population": 20, "rounds": 3}
    return validate_config(
        {
            "data": {"path": "synthetic"},
            "models": list(models),
            "abc": abc,
            "compile": "off",
            **top,
        }
    )


@pytest.fixture(scope="module")
def pairs():
    return synthetic_pairs(
        get_model("idm+delay"), IDM + [0.8], 6, 200, seed=6, noise=0.05
    )


def _models(*names):
    """The model objects of ``names`` (what the loop passes)."""
    return [get_model(name) for name in names]


def _trained(tmp_path, name, cfg, pairs):
    train(cfg, tmp_path / name, pairs=(pairs, pairs))
    return Posterior.load(tmp_path / name / "posterior.pt")


def _assert_same(buffer, expected):
    for key in ("score", "index", "theta"):
        assert torch.equal(buffer[key], expected[key].to(buffer[key].dtype)), key


@pytest.mark.parametrize("method", ["rejection", "smc"])
def test_after_is_the_run_beside_variants_trained_the_runs_way(tmp_path, pairs, method):
    cfg = _config(method=method)
    run = _trained(tmp_path, "run", cfg, pairs)
    reference, after = retrain(  # llctg: a pool model no variant wraps
        cfg,
        run,
        FinalModel(_models("idm", "llctg", "idm+delay")),
        _models("idm", "llctg"),
        pairs,
    )
    alone = _trained(tmp_path, "variant", _config(["idm+delay"], method=method), pairs)
    _assert_same(after["idm+delay"], alone.buffers["idm+delay"])
    for name in ("idm", "llctg"):  # the run's buffers, untouched
        _assert_same(after[name], run.buffers[name])
    _assert_same(reference["llctg"], run.buffers["llctg"])  # no draws spent
    # the reference holds the run: per pair, no slot is worse than the run's
    assert bool((reference["idm"]["score"] <= run.buffers["idm"]["score"]).all())
    assert bool((reference["idm"]["score"] < run.buffers["idm"]["score"]).any())


def test_the_plausibility_filter_screens_the_variants_as_it_screened_the_run(
    tmp_path, pairs
):
    screened = {"plausibility": {"filter": True}}
    cfg = _config(["idm"], **screened)
    run = _trained(tmp_path, "run", cfg, pairs)
    screen = plausibility_screen(cfg.plausibility, pairs)
    args = (cfg, run, FinalModel(_models("idm", "idm+delay")), _models("idm"), pairs)
    _, after = retrain(*args, screen=screen)
    alone = _trained(tmp_path, "variant", _config(["idm+delay"], **screened), pairs)
    _assert_same(after["idm+delay"], alone.buffers["idm+delay"])


def test_the_reference_of_rejection_is_the_run_with_twice_the_draws(tmp_path, pairs):
    cfg = _config()
    run = _trained(tmp_path, "run", cfg, pairs)
    models = _models("idm", "llctg", "idm+delay")
    reference, _ = retrain(cfg, run, FinalModel(models), _models("idm"), pairs)
    double = _trained(tmp_path, "double", _config(["idm"], 2 * N), pairs)
    _assert_same(reference["idm"], double.buffers["idm"])


@pytest.mark.parametrize("method", ["rejection", "smc"])
def test_a_shared_effect_is_held_at_its_value(tmp_path, pairs, method):
    cfg = _config(["idm"], method=method)
    run = _trained(tmp_path, "run", cfg, pairs)
    final = FinalModel(
        _models("idm", "idm+offset"),
        {"offset": [-2.5]},
        {"offset": {"d_offset": (-3.0, -2.0)}},
    )
    _, after = retrain(cfg, run, final, _models("idm"), pairs)
    theta = after["idm+offset"]["theta"]
    kept = torch.isfinite(after["idm+offset"]["score"])
    assert bool(kept.any())
    assert bool((theta[..., -1][kept] == -2.5).all())
    (buffer,) = buffers_in_order(after, ["idm+offset"])
    assert buffer.theta.shape[-1] == 7


def test_the_reference_spends_draws_only_on_the_pool_models_a_variant_wraps():
    both = wrapped(_models("idm+lag", "gfm+lag"), _models("gfm", "idm", "hl"))
    assert [m.name for m in both] == ["gfm", "idm"]
    assert wrapped([], _models("idm")) == []


def test_a_shared_effect_ahead_of_a_driver_effect_is_drawn_from_its_box():
    bounds = model_bounds(
        get_model("idm+offset+delay"),
        {},
        {"offset": torch.tensor([-2.5], dtype=torch.float64)},
    )
    drawn, fixed = searched_box(
        get_model("idm+offset+delay"), bounds, {"offset": {"d_offset": (-3.0, -2.0)}}
    )
    assert fixed is None and drawn[-2].tolist() == [-3.0, -2.0]
    drawn, fixed = searched_box(get_model("idm+offset"), bounds[:-1], {})
    assert fixed.tolist() == [-2.5] and drawn.shape == (6, 2)
    with pytest.raises(ValueError, match="no box"):
        searched_box(get_model("idm+offset+delay"), bounds, {})


def test_an_interrupted_recalibration_resumes_at_its_model(
    tmp_path, pairs, monkeypatch
):
    cfg = _config(["idm"])
    run = _trained(tmp_path, "run", cfg, pairs)
    args = (cfg, run, FinalModel(_models("idm", "idm+delay")), _models("idm"), pairs)
    whole = retrain(*args)
    real, calls = recalibration_module._trained, []

    def interrupted(cfg, model, *rest):
        raise KeyboardInterrupt

    monkeypatch.setattr(recalibration_module, "_trained", interrupted)
    with pytest.raises(KeyboardInterrupt):  # after the reference, in the variant
        retrain(*args, ledger=tmp_path / "retrain.pt")

    def counted(cfg, model, *rest):
        calls.append(model.name)
        return real(cfg, model, *rest)

    monkeypatch.setattr(recalibration_module, "_trained", counted)
    done = []
    resumed = retrain(*args, ledger=tmp_path / "retrain.pt", tick=done.append)
    assert calls == ["idm+delay"]  # the reference was read back
    assert sum(done) == 2 * N  # progress counts what was read back too
    for a, b in zip(resumed, whole, strict=True):
        for name in b:
            _assert_same(a[name], b[name])


def test_an_amortised_run_is_recalibrated_by_rejection(tmp_path, pairs):
    """The variants are rejection's N prior draws; the reference merges N fresh
    draws of each wrapped pool model into the run's buffer."""
    amortised = {
        "samples_per_pair": 20,
        "window_steps": 150,
        "simulations_per_epoch": 300,
        "max_epochs": 1,
        "validation_simulations": 100,
        "batch_size": 100,
    }
    cfg = _config(["idm"], method="amortised")
    raw = cfg.model_dump(mode="json")
    raw["abc"]["amortised"] = amortised
    cfg = validate_config(raw)
    run = _trained(tmp_path, "run", cfg, pairs)
    models = _models("idm", "idm+delay")
    reference, after = retrain(cfg, run, FinalModel(models), _models("idm"), pairs)
    alone = _trained(tmp_path, "variant", _config(["idm+delay"]), pairs)
    _assert_same(after["idm+delay"], alone.buffers["idm+delay"])
    assert bool((reference["idm"]["score"] <= run.buffers["idm"]["score"]).all())
