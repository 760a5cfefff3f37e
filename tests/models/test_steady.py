"""Steady states (torchcf.models.steady) against closed forms."""

from __future__ import annotations

import math

import torch

from torchcf.models import get_model
from torchcf.models.steady import equilibrium_spacing, time_gap

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]  # a, b, v0, T, s0, delta
LEADER = 5.0


def idm_spacing(theta: list[float], v: float) -> float:
    """IDM's equilibrium: a (1 - (v/v0)^delta - (s*/s)^2) = 0 with s* = s0 + v T
    at equal speeds, so s = s* / sqrt(1 - (v/v0)^delta) (the SPEC's IDM reads
    the front-to-front spacing itself, the leader's length not taken off)."""
    _, _, v0, t, s0, delta = theta
    return (s0 + v * t) / math.sqrt(1 - (v / v0) ** delta)


def test_idm_keeps_its_closed_form_spacing_and_time_gap():
    theta = torch.tensor([IDM, [1.0, 1.5, 35.0, 2.0, 4.0, 4.0]], dtype=torch.float64)
    for v in (5.0, 15.0, 25.0):
        got = equilibrium_spacing(get_model("idm"), theta, v, leader_length=LEADER)
        want = torch.tensor([idm_spacing(row, v) for row in theta.tolist()])
        torch.testing.assert_close(got, want.double(), atol=0, rtol=1e-6)
    # at low speed the slope of s_e is T (the (v/v0)^delta term is negligible)
    gap = time_gap(get_model("idm"), theta, 5.0, leader_length=LEADER)
    torch.testing.assert_close(gap, theta[:, 3], atol=0.01, rtol=0)


def test_an_offset_moves_the_spacing_and_a_faster_speed_has_none():
    """A spacing-sensor offset d makes the model keep the recorded spacing at
    its equilibrium: the true spacing moves by -d; above the desired speed
    there is no equilibrium (NaN)."""
    plain = equilibrium_spacing(get_model("idm"), torch.tensor([IDM]), 15.0)
    shifted = equilibrium_spacing(
        get_model("idm+offset"), torch.tensor([IDM + [-3.0]]), 15.0
    )
    torch.testing.assert_close(
        shifted - plain, torch.tensor([3.0]).double(), atol=1e-6, rtol=0
    )
    assert torch.isnan(
        equilibrium_spacing(get_model("idm"), torch.tensor([IDM]), 31.0)
    ).all()


def test_llctg_keeps_its_constant_time_gap():
    """LLCTG (tau, ks, kv, l): spacing l + v tau at any speed."""
    theta = torch.tensor([[1.0, 0.6, 0.8, 5.0]], dtype=torch.float64)
    for v in (0.5, 10.0, 30.0):
        got = equilibrium_spacing(get_model("llctg"), theta, v)
        torch.testing.assert_close(
            got, torch.tensor([5.0 + v]).double(), atol=1e-6, rtol=0
        )
    torch.testing.assert_close(
        time_gap(get_model("llctg"), theta, 0.5),
        torch.tensor([1.0]).double(),
        atol=1e-6,
        rtol=0,
    )
