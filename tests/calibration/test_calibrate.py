"""``torchcf.calibrate``: objects in, a typed record out, the same buffers as
the command line's training run."""

from __future__ import annotations

import pytest
import torch

from tests.conftest import synthetic_pairs
from torchcf import SMC, Calibration, Rejection, calibrate, get_model
from torchcf.abc import Rollout, SMCSettings
from torchcf.calibration import (
    CalibrationError,
    CalibrationState,
    SelectionRule,
    Tracker,
)
from torchcf.config import TrainConfig
from torchcf.posterior import Posterior
from torchcf.train import train

MODELS = ["idm", "hl"]


def _config(**abc) -> TrainConfig:
    settings = {"n_particles": 3000, "top_n": 3, "sensitivity_n": [3, 5], "seed": 2}
    settings.update(abc)
    return TrainConfig.model_validate(
        {
            "data": {"name": "car-model-2"},
            "models": MODELS,
            "abc": settings,
            "compile": "off",
        }
    )


@pytest.fixture(scope="module")
def pairs():
    return synthetic_pairs(n_pairs=6, n_steps=120, seed=3)


def _same_buffers(a: Posterior, b: Posterior) -> None:
    assert list(a.buffers) == list(b.buffers)
    for name in a.buffers:
        for key in ("score", "index", "theta"):
            torch.testing.assert_close(
                a.buffers[name][key], b.buffers[name][key], rtol=0, atol=0
            )


@pytest.mark.parametrize("method", ["rejection", "smc"])
def test_a_notebook_gets_the_command_lines_buffers(pairs, tmp_path, method):
    """calibrate() on a PairSet with objects equals train() of the config that
    says the same (its posterior.pt), bit for bit."""
    smc = {"population": 10, "rounds": 3}
    cfg = _config(method=method, smc=smc) if method == "smc" else _config()
    train(cfg, tmp_path / "run", pairs=(pairs, pairs))
    run = Posterior.load(tmp_path / "run" / "posterior.pt")
    sampler = (
        SMC(3000, SMCSettings(population=10, rounds=3))
        if method == "smc"
        else Rejection(3000)
    )
    result = calibrate(
        Rollout(pairs, compile="off", early_rejection=True),
        [get_model(name) for name in MODELS],
        sampler,
        selection=SelectionRule(top_n=3, sensitivity_n=(3, 5)),
        seed=2,
    )
    assert isinstance(result, Calibration)
    _same_buffers(result.posterior, run)
    assert result.shares == pytest.approx(run.shares, abs=0)
    assert set(result.sensitivity) == {3, 5}
    assert result.pairwise.shape == (2, 2)
    assert (result.smc is not None) == (method == "smc")
    assert result.per_model["idm"].particles == (
        3000 if method == "rejection" else result.smc.budget.proposals
    )


def test_the_defaults_and_a_prior_box_of_ones_own(pairs):
    """A plain PairSet, the default rejection sampler with its budget given,
    and a narrowed box: every accepted particle inside the box."""
    idm = get_model("idm")
    box = idm.prior_bounds(torch.float64)
    box[0] = torch.tensor([1.0, 1.2], dtype=torch.float64)  # v0 narrowed
    result = calibrate(
        pairs, {idm: box}, Rejection(600), selection=SelectionRule(3, (3,))
    )
    theta = result.posterior.hybrid["idm"].theta
    assert result.models == ["idm"] and result.shares == {"idm": 1.0}
    assert bool(((theta[:, 0] >= 1.0) & (theta[:, 0] <= 1.2)).all())


def test_a_kept_state_is_not_run_again(pairs):
    """A tracker's state of finished models resumes to the same result with no
    particle simulated (the checkpoint's contract)."""
    models = [get_model(name) for name in MODELS]
    selection = SelectionRule(3, (3,))
    tracker = Tracker()
    first = calibrate(
        pairs, models, Rejection(600), selection=selection, tracker=tracker
    )
    kept = CalibrationState(
        progress=tracker.state.progress,
        saved_buffers={k: b.state_dict() for k, b in tracker.state.buffers.items()},
    )
    counted = []

    class Counting(Tracker):
        def round(self, name, progress, rollout):
            counted.append(name)

    again = calibrate(
        pairs, models, Rejection(600), selection=selection, tracker=Counting(kept)
    )
    assert counted == []
    _same_buffers(first.posterior, again.posterior)


def test_bad_requests_are_refused_in_one_line(pairs):
    idm = get_model("idm")
    with pytest.raises(CalibrationError, match="top_n: 5 particles per pair"):
        calibrate(pairs, [idm], Rejection(12), selection=SelectionRule(5, (5,)))
    with pytest.raises(ValueError, match=r"prior box of shape \(2, 2\)"):
        calibrate(pairs, {idm: torch.zeros(2, 2)}, Rejection(100))
    with pytest.raises(ValueError, match="given twice"):
        calibrate(pairs, [idm, get_model("idm")], Rejection(100))
    with pytest.raises(ValueError, match="n_particles must be an integer >= 1"):
        Rejection(0)
    with pytest.raises(ValueError, match="mode must be"):
        SelectionRule(mode="best")


@pytest.mark.parametrize("method", ["rejection", "smc"])
def test_a_boxs_last_rows_of_zero_width_are_held(pairs, method):
    """idm+delay with its delay held at 0.4 s: every kept particle carries it,
    the others drawn inside their boxes (a shared effect's one value)."""
    model = get_model("idm+delay")
    box = model.prior_bounds(torch.float64)
    box[-1] = torch.tensor([0.4, 0.4], dtype=torch.float64)
    sampler = (
        SMC(1200, SMCSettings(population=5, rounds=2))
        if method == "smc"
        else Rejection(600)
    )
    result = calibrate(pairs, {model: box}, sampler, selection=SelectionRule(3, (3,)))
    theta = result.posterior.buffers[model.name]["theta"]  # (N, B, K)
    assert theta.shape[-1] == model.n_params
    kept = result.posterior.hybrid[model.name].theta
    assert bool((kept[:, -1] == 0.4).all())
    inside = (kept[:, :-1] >= box[:-1, 0]) & (kept[:, :-1] <= box[:-1, 1])
    assert bool(inside.all())
