"""OVM, GFM, FVDM and IDM: hand-derived cases on top of the contract."""

from __future__ import annotations

import math

import pytest
import torch

from tests.models.contract import CFModelContract, perception
from torchcf.models import MODELS, get_model
from torchcf.models.hdv import IDM_MIN_SPACING


def params_of(model, **values):
    theta = torch.tensor([[values[n] for n in model.param_names]], dtype=torch.float64)
    return model.unpack(theta)


class TestOVM(CFModelContract):
    def make_model(self):
        return MODELS["ovm"]

    def test_equilibrium_at_optimal_velocity(self, model):
        p = params_of(model, kappa=1.2, v1=6.0, v2=22.0, c1=0.1, c2=1.6)
        spacing, length = 30.0, 5.0
        v_eq = 6.0 + 22.0 * math.tanh(0.1 * (spacing - length) - 1.6)
        u = model.command(p, perception(spacing, v_eq, v_eq, leader_length=length))
        assert abs(float(u)) < 1e-12

    def test_relaxes_towards_optimal_velocity(self, model):
        p = params_of(model, kappa=2.0, v1=6.0, v2=22.0, c1=0.1, c2=1.6)
        u = model.command(p, perception(30.0, 0.0, 0.0))
        v_opt = 6.0 + 22.0 * math.tanh(0.1 * 25.0 - 1.6)
        assert float(u) == pytest.approx(2.0 * v_opt)

    def test_leader_length_shifts_the_gap(self, model):
        p = params_of(model, kappa=1.0, v1=6.0, v2=22.0, c1=0.1, c2=1.6)
        short = model.command(p, perception(30.0, 10.0, 10.0, leader_length=0.0))
        long = model.command(p, perception(35.0, 10.0, 10.0, leader_length=5.0))
        torch.testing.assert_close(short, long)


class TestGFM(CFModelContract):
    def make_model(self):
        return MODELS["gfm"]

    def test_brake_term_only_when_closing_in(self, model):
        p = params_of(model, K=1.0, lam=0.7, v1=5.0, v2=20.0, c1=0.1, c2=1.5)
        ovm_part = lambda v: 5.0 + 20.0 * math.tanh(0.1 * 25.0 - 1.5) - v  # noqa: E731
        # follower faster than leader (dv = -3): the term acts
        closing = model.command(p, perception(30.0, 15.0, 12.0))
        assert float(closing) == pytest.approx(ovm_part(15.0) + 0.7 * -3.0)
        # follower slower (dv = +3): no term
        opening = model.command(p, perception(30.0, 15.0, 18.0))
        assert float(opening) == pytest.approx(ovm_part(15.0))


class TestFVDM(CFModelContract):
    def make_model(self):
        return MODELS["fvdm"]

    def test_equilibrium(self, model):
        p = params_of(model, tau=0.8, lam=0.5, V1=8.0, V2=12.0, l_int=6.0, beta=2.0)
        v_eq = 8.0 + 12.0 * math.tanh((30.0 - 5.0) / 6.0 - 2.0)
        assert abs(float(model.command(p, perception(30.0, v_eq, v_eq)))) < 1e-12

    def test_speed_difference_term_is_symmetric(self, model):
        p = params_of(model, tau=1.0, lam=0.5, V1=8.0, V2=12.0, l_int=6.0, beta=2.0)
        base = model.command(p, perception(30.0, 10.0, 10.0))
        faster = model.command(p, perception(30.0, 10.0, 12.0))
        slower = model.command(p, perception(30.0, 10.0, 8.0))
        assert float(faster - base) == pytest.approx(1.0)
        assert float(slower - base) == pytest.approx(-1.0)


class TestIDM(CFModelContract):
    def make_model(self):
        return MODELS["idm"]

    P = dict(a=1.2, b=2.0, v0=30.0, T=1.5, s0=2.0, delta=4.0)

    def test_free_road_gives_maximum_acceleration(self, model):
        u = model.command(params_of(model, **self.P), perception(1e9, 0.0, 0.0))
        assert float(u) == pytest.approx(1.2, abs=1e-12)

    def test_equilibrium_spacing(self, model):
        v = 20.0
        s_star = 2.0 + v * 1.5
        s_eq = s_star / math.sqrt(1.0 - (v / 30.0) ** 4)
        u = model.command(params_of(model, **self.P), perception(s_eq, v, v))
        assert abs(float(u)) < 1e-12

    def test_spacing_has_no_leader_length(self, model):
        p = params_of(model, **self.P)
        with_length = model.command(p, perception(20.0, 10.0, 10.0, leader_length=5.0))
        without = model.command(p, perception(20.0, 10.0, 10.0, leader_length=0.0))
        torch.testing.assert_close(with_length, without)

    def test_spacing_floor_where_it_divides(self, model):
        p = params_of(model, **self.P)
        u = model.command(p, perception(0.01, 0.0, 0.0))
        expected = 1.2 * (1.0 - (2.0 / IDM_MIN_SPACING) ** 2)
        assert float(u) == pytest.approx(expected)

    def test_desired_gap_never_below_jam_distance(self, model):
        # leader much faster: v T - v dv / (2 sqrt(ab)) < 0 is clipped to 0
        p = params_of(model, **self.P)
        u = model.command(p, perception(10.0, 5.0, 30.0))
        expected = 1.2 * (1.0 - (5.0 / 30.0) ** 4 - (2.0 / 10.0) ** 2)
        assert float(u) == pytest.approx(expected)

    def test_zero_speed_is_finite(self, model):
        u = model.command(params_of(model, **self.P), perception(10.0, 0.0, 0.0))
        assert float(u) == pytest.approx(1.2 * (1.0 - 0.04))


def test_get_model_lists_valid_names():
    with pytest.raises(ValueError, match="unknown model 'foo'; valid names: ovm"):
        get_model("foo")
    assert get_model("IDM") is MODELS["idm"]
