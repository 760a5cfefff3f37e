"""LLCTG, LLCS and HL: hand-derived cases on top of the contract."""

from __future__ import annotations

import pytest
import torch

from tests.models.contract import CFModelContract, perception
from tests.models.test_hdv import params_of
from tests.reference import integrate_lag_fine
from torchcf.models import MODELS, FollowerState


class TestLLCTG(CFModelContract):
    def make_model(self):
        return MODELS["llctg"]

    def test_zero_at_desired_spacing(self, model):
        p = params_of(model, tau=1.0, ks=0.8, kv=1.1, l=4.0)
        v = 17.0
        assert float(model.command(p, perception(v * 1.0 + 4.0, v, v))) == 0.0

    def test_gains(self, model):
        p = params_of(model, tau=1.0, ks=0.8, kv=1.1, l=4.0)
        u = model.command(p, perception(30.0, 20.0, 18.0))
        assert float(u) == pytest.approx(0.8 * (30.0 - 20.0 - 4.0) + 1.1 * -2.0)


class TestLLCS(CFModelContract):
    def make_model(self):
        return MODELS["llcs"]

    def test_zero_at_desired_spacing_any_speed(self, model):
        p = params_of(model, s0=12.0, ks=0.5, kv=0.9)
        for v in (0.0, 10.0, 30.0):
            assert float(model.command(p, perception(12.0, v, v))) == 0.0


class TestHL(CFModelContract):
    def make_model(self):
        return MODELS["hl"]

    P = dict(tau=1.0, TT=0.3, ks=0.6, kv=1.0, ka=-0.5, l=5.0)

    def test_acceleration_feedback(self, model):
        p = params_of(model, **self.P)
        u = model.command(p, perception(25.0, 20.0, 20.0, a=0.8))
        assert float(u) == pytest.approx(-0.5 * 0.8)

    @pytest.mark.parametrize("lag", [0.1, 0.3, 0.5])
    @pytest.mark.parametrize("dt", [0.1, 0.04])
    def test_exact_lag_step_matches_fine_integration(self, model, lag, dt):
        p = params_of(model, **(self.P | {"TT": lag}))
        f64 = torch.float64
        state = FollowerState(
            *(torch.tensor([value], dtype=f64) for value in (3.0, 12.0, -0.7))
        )
        u = torch.tensor([1.3], dtype=f64)
        moved = model.advance(p, state, u, dt)
        x1, v1, a1 = integrate_lag_fine(1.3, -0.7, 12.0, 3.0, lag, dt)
        assert float(moved.x) == pytest.approx(x1, abs=1e-10)
        assert float(moved.v) == pytest.approx(v1, abs=1e-10)
        assert float(moved.a) == pytest.approx(a1, abs=1e-10)

    def test_realised_acceleration_is_recorded_state(self, model):
        assert model.acceleration_is_state
        assert not MODELS["llctg"].acceleration_is_state
