"""The contract every car-following model satisfies (subclass and set make_model)."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import prior_draws
from tests.reference import command as reference_command
from torchcf.models import MODELS, CFModel, FollowerState, Perception


def perception(spacing, v, v_lead, a=0.0, leader_length=5.0, dtype=torch.float64):
    as_t = lambda value: torch.as_tensor(value, dtype=dtype)  # noqa: E731
    return Perception(as_t(spacing), as_t(v), as_t(v_lead), as_t(a), leader_length)


def command_of(model: CFModel, theta, obs: Perception, state_ndim: int = 1, dt=0.1):
    """``model.command`` after unpacking and preparing ``theta`` as the rollout does."""
    shape = torch.broadcast_shapes(
        *(torch.as_tensor(f).shape for f in obs[:4]),
        (theta.shape[0],) + (1,) * (state_ndim - 1),
    )
    params = model.prepare(model.unpack(theta, state_ndim=state_ndim), dt, shape)
    return model.command(params, obs)


class CFModelContract:
    """Shapes, dtype, finiteness over the prior, batch invariance, reference values."""

    #: tolerance against the scalar reference (MPC's iterative solver: 1e-4)
    rtol = 1e-12

    def make_model(self) -> CFModel:
        raise NotImplementedError

    @pytest.fixture
    def model(self) -> CFModel:
        return self.make_model()

    def test_registered_under_its_name(self, model):
        assert MODELS[model.name] is model
        assert model.name == model.name.lower()

    def test_param_specs_are_consistent(self, model):
        assert model.param_names == tuple(model.Params._fields)
        bounds = model.prior_bounds()
        assert bounds.shape == (model.n_params, 2)
        assert bool((bounds[:, 0] <= bounds[:, 1]).all())
        assert all(spec.unit for spec in model.param_specs)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("state_ndim", [1, 2])
    def test_shape_dtype_and_finite_over_prior(self, model, dtype, state_ndim):
        n_particles, n_pairs = 64, 3
        theta = prior_draws(model, n_particles, dtype=dtype)
        shape = (n_particles,) if state_ndim == 1 else (n_particles, n_pairs)
        params = model.prepare(model.unpack(theta, state_ndim=state_ndim), 0.1, shape)
        generator = torch.Generator().manual_seed(1)
        spacing = 5.5 + 60 * torch.rand(shape, generator=generator, dtype=dtype)
        v = 30 * torch.rand(shape, generator=generator, dtype=dtype)
        v_lead = 30 * torch.rand(shape, generator=generator, dtype=dtype)
        a = torch.randn(shape, generator=generator, dtype=dtype)
        obs = Perception(spacing, v, v_lead, a, 5.0)
        u = model.command(params, obs)
        assert u.shape == shape and u.dtype == dtype
        assert bool(torch.isfinite(u).all())
        moved = model.advance(params, FollowerState(torch.zeros_like(v), v, a), u, 0.1)
        assert all(m.shape == shape and m.dtype == dtype for m in moved)

    def test_batch_equals_loop(self, model):
        theta = prior_draws(model, 16)
        obs = perception(
            torch.linspace(6, 60, 16), torch.linspace(0, 25, 16), 12.0, 0.3
        )
        batched = command_of(model, theta, obs)
        for j in range(16):
            single_obs = Perception(
                *(f[j] if torch.is_tensor(f) and f.ndim else f for f in obs)
            )
            single = command_of(model, theta[j : j + 1], single_obs)
            torch.testing.assert_close(batched[j], single[0], rtol=0, atol=0)

    def test_full_layout_broadcasts_particles_over_pairs(self, model):
        theta = prior_draws(model, 8)
        spacing = torch.tensor([[10.0, 30.0, 50.0]], dtype=torch.float64)  # (1, N)
        obs = perception(spacing, 15.0, 14.0, 0.2)
        full = command_of(model, theta, obs, state_ndim=2)  # (P, N)
        assert full.shape == (8, 3)
        for n in range(3):
            paired = command_of(
                model, theta, perception(spacing[0, n], 15.0, 14.0, 0.2)
            )
            torch.testing.assert_close(full[:, n], paired)

    def test_matches_independent_reference(self, model):
        """The command equals the scalar reference of tests/reference.py."""
        theta = prior_draws(model, 32, seed=3)
        generator = torch.Generator().manual_seed(2)
        spacing = 0.05 + 70 * torch.rand(32, generator=generator, dtype=torch.float64)
        v = 35 * torch.rand(32, generator=generator, dtype=torch.float64)
        v_lead = 35 * torch.rand(32, generator=generator, dtype=torch.float64)
        a = 2 * torch.randn(32, generator=generator, dtype=torch.float64)
        u = command_of(model, theta, Perception(spacing, v, v_lead, a, 5.0))
        for j in range(32):
            expected = reference_command(
                model.name,
                theta[j].tolist(),
                float(spacing[j]),
                float(v[j]),
                float(v_lead[j]),
                float(a[j]),
                5.0,
                dt=0.1,
            )
            assert math.isclose(
                float(u[j]), expected, rel_tol=self.rtol, abs_tol=self.rtol
            )

    def test_gradients(self, model):
        theta = prior_draws(model, 4).requires_grad_(True)
        obs = perception([12.0, 25.0, 40.0, 33.0], 14.0, 13.0, 0.1)
        torch.autograd.gradcheck(lambda th: command_of(model, th, obs), (theta,))
