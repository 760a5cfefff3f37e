"""The response times of the data and of the calibrated models
(torchcf.diagnose.signatures.response)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcf.data import PairSet
from torchcf.diagnose.signatures.response import (
    Perturbation,
    braking_onsets,
    event_shifts,
    perturbation_response,
    response_times,
    speed_shift,
)
from torchcf.models import get_model

IDM = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta
DT = 0.1


def _cruising(n_pairs: int, speed: float = 20.0, spacing: float = 35.0) -> PairSet:
    """``n_pairs`` pairs of 5 s at ``speed`` [m/s], ``spacing`` [m] apart."""
    v = np.full((50, n_pairs), speed)
    x = np.cumsum(v, axis=0) * DT
    zero = np.zeros_like(v)
    return PairSet.from_arrays([x + spacing, v, zero, x, v, zero], dt=DT)


def _idm(name: str, *extra: float, **changed: float) -> tuple:
    model = get_model(name)
    values = dict(zip(model.param_names, IDM + list(extra), strict=True))
    values.update(changed)
    theta = torch.tensor([[values[k] for k in model.param_names]], dtype=torch.float64)
    return model, theta


def _response(name: str, *extra: float, **changed: float) -> float:
    model, theta = _idm(name, *extra, **changed)
    found = perturbation_response(model, theta, _cruising(1), torch.tensor([0]))
    return float(found[0])


def test_the_leader_brakes_by_a_quarter_of_its_speed_at_most_5_and_comes_back():
    shape = Perturbation(settle=10.0, rate=1.0, hold=4.0, after=6.0)
    v, start = shape.leader_speed(np.array([8.0, 30.0]), DT)
    assert start == 100
    assert v[: start + 1] == pytest.approx(np.array([[8.0, 30.0]] * (start + 1)))
    assert v.min(0) == pytest.approx([6.0, 25.0])  # drops of 2 and 5 m/s
    assert v[-1] == pytest.approx([8.0, 30.0])
    assert np.abs(np.diff(v, axis=0)).max() == pytest.approx(1.0 * DT)  # the rate
    # 10 s cruising, 2 x 5 s ramps (the larger drop), 4 s held, 6 s after
    assert v.shape[0] == int(round(30.0 / DT)) + 1


def test_the_speed_shift_reads_an_exact_shift_and_none_from_a_failed_rollout():
    t = np.arange(800) * DT
    lead = 20.0 - 3.0 * np.exp(-(((t - 50.0) / 6.0) ** 2))
    follow = np.interp(t - 1.7, t, lead)  # the leader's speed 1.7 s later
    broken = follow.copy()
    broken[700] = np.nan
    found = speed_shift(
        np.stack([follow, lead, broken], 1), np.stack([lead] * 3, 1), 300, DT
    )
    assert found[:2] == pytest.approx([1.7, 0.0])
    assert np.isnan(found[2])


def test_the_perturbation_response_grows_with_the_time_gap_and_a_perception_delay():
    gaps = [_response("idm", T=gap) for gap in (0.8, 1.2, 1.8, 2.5)]
    assert gaps == sorted(gaps) and gaps[-1] - gaps[0] > 1.0
    plain = _response("idm")
    assert 0.8 <= plain <= 2.5  # an IDM at a 1.2 s gap: a commercial ACC's range
    # A delay of 1 s adds to the response, by less than the delay itself: the
    # follower's own speed is not perceived late
    delayed = _response("idm+delay", 1.0)
    assert 0.4 <= delayed - plain <= 1.0
    assert _response("idm+lag", 1.0) > plain


def test_batched_particles_equal_one_by_one():
    model, theta = _idm("idm")
    thetas = theta.repeat(3, 1)
    thetas[:, 3] = torch.tensor([0.9, 1.4, 2.1], dtype=torch.float64)
    pairs = PairSet.from_arrays(
        [s.numpy() for s in _cruising(3, 15.0).series().values()], dt=DT
    )
    batched = perturbation_response(model, thetas, pairs, torch.tensor([2, 0, 1]))
    looped = [
        perturbation_response(model, thetas[i : i + 1], pairs, torch.tensor([p]))[0]
        for i, p in enumerate([2, 0, 1])
    ]
    assert batched == pytest.approx(looped)


def _shifted(u: np.ndarray, steps: int) -> np.ndarray:
    return np.concatenate([np.zeros(steps), u[: u.size - steps]])


def test_response_times_read_the_lags_of_data_and_model_per_model():
    rng = np.random.default_rng(0)
    n = 400
    series = {"a": [], "acceleration": [], "a_lead": [], "v": [], "dv": [], "speed": []}
    lags = [(12, 5), (14, 6), (10, 20)]  # (observed, simulated) steps per pair
    for observed, simulated in lags:
        lead = np.convolve(rng.normal(size=n), np.ones(8) / 8, mode="same")
        a_obs = _shifted(lead, observed)
        a_sim = _shifted(lead, simulated)
        series["a"].append(a_obs)
        series["acceleration"].append(a_obs - a_sim)  # observed - simulated
        series["a_lead"].append(lead)
        series["v"].append(np.full(n, 20.0))  # no braking event
        series["dv"].append(np.zeros(n))
        series["speed"].append(np.zeros(n))
    idm, theta = _idm("idm")
    gfm = get_model("gfm")
    gfm_theta = torch.tensor([[0.8, 0.6, 8.0, 12.0, 0.13, 1.57]], dtype=torch.float64)
    best = {
        idm: (theta.repeat(2, 1), torch.tensor([0, 1])),
        gfm: (gfm_theta, torch.tensor([2])),
    }
    found = response_times(best, series, _cruising(3))
    assert found.data_quartiles == pytest.approx((1.1, 1.3))
    assert found.pairs == 3
    assert found.data == pytest.approx(1.2)  # median of 1.2, 1.4, 1.0 s
    assert found.model == pytest.approx(0.6)  # median of 0.5, 0.6, 2.0 s
    assert found.by_model == pytest.approx({"idm": 0.55, "gfm": 2.0})
    assert found.per_model == {"idm": 2, "gfm": 1}
    # the perturbation response: per model, the same particle on equal pairs
    assert found.perturbation_pairs == 3
    assert found.perturbation_by_model["idm"] == pytest.approx(_response("idm"))
    assert set(found.perturbation_by_model) == {"idm", "gfm"}
    assert found.events == 0 and found.event_data is None


def _braking_leader(onset_s: float, length_s: float = 40.0) -> np.ndarray:
    """A leader at 20 m/s that brakes at 1 m/s^2 to 16 m/s at ``onset_s``."""
    t = np.arange(int(round(length_s / DT))) * DT
    return 20.0 - np.clip(t - onset_s, 0.0, 4.0)


def test_braking_onsets_need_a_steady_leader_a_drop_and_room_after():
    lead = _braking_leader(12.0)
    (onset,) = braking_onsets(lead, DT, earliest=80, room=150)
    assert 121 <= onset <= 123  # 0.2 m/s below the steady 20 m/s
    assert braking_onsets(lead, DT, earliest=80, room=300) == []  # no room
    noisy = lead + np.sin(np.arange(lead.size))  # spread 0.7 m/s
    assert braking_onsets(noisy, DT, earliest=80, room=150) == []  # not steady
    gentle = 20.0 - np.clip(np.arange(lead.size) * DT - 12.0, 0.0, 4.0) / 4
    assert braking_onsets(gentle, DT, earliest=80, room=150) == []  # 1 m/s


def test_event_shifts_read_the_observed_and_the_simulated_followers():
    lead = _braking_leader(12.0)
    t = np.arange(lead.size) * DT
    observed = np.interp(t - 2.3, t, lead)
    simulated = np.interp(t - 1.1, t, lead)
    series = {"v": [observed], "dv": [lead - observed], "speed": [observed - simulated]}
    (found,) = event_shifts(series, DT)
    assert found == pytest.approx((2.3, 1.1))
