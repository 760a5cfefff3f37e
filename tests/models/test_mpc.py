"""MPC: the condensed QP, saturation, and the exact reference on top of the contract."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.conftest import prior_draws, synthetic_pairs
from tests.models.contract import CFModelContract, command_of, perception
from tests.reference import mpc_qp
from tests.sim.test_rollout import reference as pair_reference
from torchcf import simulate
from torchcf.models import MODELS, get_model
from torchcf.models.mpc import MPC, mpc_qp_matrices


class TestMPC(CFModelContract):
    rtol = 1e-6

    def make_model(self):
        return MODELS["mpc"]

    def test_gradients(self, model):
        pytest.skip("the QP solution is piecewise smooth; no gradient through ADMM")

    def test_condensed_qp_matches_explicit_prediction(self, model):
        theta = prior_draws(model, 20, seed=4)
        hessian, linear = mpc_qp_matrices(theta[:, 0], theta[:, 1], theta[:, 2], 0.1)
        for j in range(20):
            z0 = (float(3 * j - 20), float(0.5 * j - 4))
            H, g = mpc_qp(theta[j].tolist(), z0, 0.1, 5)
            np.testing.assert_allclose(hessian[j].numpy(), H, atol=1e-10)
            np.testing.assert_allclose(
                (linear[j] @ torch.tensor(z0, dtype=torch.float64)).numpy(),
                g,
                atol=1e-10,
            )

    def test_zero_at_desired_spacing(self, model):
        theta = torch.tensor([[1.0, 0.8, 1.0, 5.0, -4.0, 4.0]], dtype=torch.float64)
        v = 15.0
        u = command_of(model, theta, perception([v * 1.0 + 5.0], v, v))
        assert abs(float(u[0])) < 1e-9

    def test_saturates_at_the_limits(self, model):
        theta = torch.tensor([[1.0, 0.8, 1.0, 5.0, -4.5, 3.5]], dtype=torch.float64)
        far = command_of(model, theta, perception([80.0], 15.0, 15.0))
        close = command_of(model, theta, perception([8.0], 15.0, 15.0))
        assert float(far[0]) == pytest.approx(3.5, abs=1e-9)
        assert float(close[0]) == pytest.approx(-4.5, abs=1e-9)

    @pytest.mark.parametrize("horizon", [1, 3, 20])
    def test_other_horizons(self, horizon):
        model = MPC(horizon=horizon)
        theta = prior_draws(model, 16, seed=8)
        obs = perception(torch.linspace(10, 60, 16), 15.0, 14.0)
        u = command_of(model, theta, obs)
        from tests.reference import mpc_command

        for j in range(16):
            expected = mpc_command(
                theta[j].tolist(), float(obs.spacing[j]), 15.0, 14.0, 0.1, horizon
            )
            assert float(u[j]) == pytest.approx(expected, abs=1e-6)

    def test_bad_horizon(self):
        with pytest.raises(ValueError, match="horizon must be >= 1"):
            MPC(horizon=0)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 2e-2)])
def test_rollout_matches_exact_reference(dtype, tol):
    pairs = synthetic_pairs(n_pairs=2, n_steps=120, seed=6)
    theta = prior_draws(MODELS["mpc"], 3, seed=2)
    out = simulate(get_model("mpc"), theta.to(dtype), pairs, return_traj=True)
    for j in range(3):
        for n in range(2):
            ref = pair_reference("mpc", theta[j], pairs, n)
            assert bool(out.valid[j, n]) == ref["valid"]
            np.testing.assert_allclose(
                out.a[:, j, n].double().numpy(), ref["a"], atol=tol
            )
            assert float(out.score[j, n]) == pytest.approx(ref["score"], abs=tol)


def test_paired_equals_full_layout():
    pairs = synthetic_pairs(n_pairs=3, n_steps=80, seed=1)
    theta = prior_draws(MODELS["mpc"], 12, seed=3)
    index = torch.randint(0, 3, (12,))
    full = simulate(get_model("mpc"), theta, pairs)
    paired = simulate(get_model("mpc"), theta, pairs, index)
    torch.testing.assert_close(
        paired.score, full.score[torch.arange(12), index], rtol=1e-8, atol=1e-8
    )


def _random_mpc_states(model, n, seed, dtype):
    """Prior particles and perceived states with a good share of active bounds."""
    theta = prior_draws(model, n, seed=seed, dtype=dtype)
    generator = torch.Generator().manual_seed(seed + 1)
    v = 5 + 25 * torch.rand(n, generator=generator, dtype=dtype)
    dv = -8 + 16 * torch.rand(n, generator=generator, dtype=dtype)
    error = -30 + 70 * torch.rand(n, generator=generator, dtype=dtype)
    spacing = error + v * theta[:, 0] + theta[:, 3]
    return theta, perception(spacing, v, v + dv, dtype=dtype)


def _osqp_first_inputs(theta, obs, horizon=5):
    """u_0 of each instance by OSQP at high accuracy on the explicit-cost QP."""
    osqp = pytest.importorskip("osqp")
    import scipy.sparse as sparse

    first, active = [], 0
    identity = sparse.identity(horizon, format="csc")
    for j in range(theta.shape[0]):
        row = theta[j].double().tolist()
        z0 = (
            float(obs.spacing[j]) - float(obs.v[j]) * row[0] - row[3],
            float(obs.v_lead[j]) - float(obs.v[j]),
        )
        H, g = mpc_qp(row, z0, 0.1, horizon)
        lower, upper = np.full(horizon, row[4]), np.full(horizon, row[5])
        solver = osqp.OSQP()
        solver.setup(
            sparse.csc_matrix(np.triu(H)),
            g,
            identity,
            lower,
            upper,
            verbose=False,
            eps_abs=1e-11,
            eps_rel=1e-11,
            max_iter=200000,
            polishing=True,
        )
        x = solver.solve(raise_error=True).x
        first.append(x[0])
        active += bool(np.any(x <= lower + 1e-9) or np.any(x >= upper - 1e-9))
    return np.array(first), active / theta.shape[0]


@pytest.mark.slow  # 10 000 OSQP solves
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-4), (torch.float32, 1e-3)])
def test_first_input_against_osqp_on_10000_instances(dtype, tol):
    model = MODELS["mpc"]
    theta, obs = _random_mpc_states(model, 10_000, seed=21, dtype=dtype)
    u0 = command_of(model, theta, obs)
    reference, active_share = _osqp_first_inputs(theta, obs)
    error = np.abs(u0.double().numpy() - reference)
    assert active_share >= 0.2, f"only {active_share:.1%} with active bounds"
    assert error.max() <= tol, (
        f"max |u0 - u0_ref| = {error.max():.2e} ({active_share:.1%} active)"
    )


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-4), (torch.float32, 1e-3)])
def test_admm_alone_meets_the_accuracy(dtype, tol):
    """With method="admm" every constrained instance goes through ADMM."""
    model = MPC(method="admm")
    theta, obs = _random_mpc_states(model, 1500, seed=5, dtype=dtype)
    u0 = command_of(model, theta, obs)
    reference, active_share = _osqp_first_inputs(theta, obs)
    assert active_share >= 0.2
    assert np.abs(u0.double().numpy() - reference).max() <= tol


def test_stages_agree():
    theta, obs = _random_mpc_states(MODELS["mpc"], 2000, seed=9, dtype=torch.float64)
    with_active_set = command_of(MODELS["mpc"], theta, obs)
    admm_only = command_of(MPC(method="admm"), theta, obs)
    torch.testing.assert_close(with_active_set, admm_only, atol=1e-5, rtol=0)


def test_warm_start_from_the_last_plan(monkeypatch):
    """Step to step the MPC hands BoxQP the last plan as its active-set guess and
    the plan shifted by one step as ADMM's start; the commands are those of a cold
    solve."""
    from torchcf.qp import BoxQP

    model = MODELS["mpc"]
    theta, obs = _random_mpc_states(model, 800, seed=31, dtype=torch.float64)
    params = model.prepare(model.unpack(theta), 0.1, (800,))
    calls = []
    solve = BoxQP.solve

    def recording(self, q, l, u, **kwargs):  # noqa: E741
        calls.append(kwargs)
        return solve(self, q, l, u, **kwargs)

    monkeypatch.setattr(BoxQP, "solve", recording)
    _, memory = model.command_with_memory(params, obs, None)
    moved = obs._replace(spacing=obs.spacing + 0.4, v_lead=obs.v_lead - 0.1)
    command, _ = model.command_with_memory(params, moved, memory)
    first, second = calls
    assert first["active_guess"] is None and first["x0"] is None
    index = second["index"]
    last = memory.inputs[:, index].T
    torch.testing.assert_close(second["active_guess"], last, rtol=0, atol=0)
    shifted = torch.cat((last[:, 1:], last[:, -1:]), dim=1)
    torch.testing.assert_close(second["x0"], shifted, rtol=0, atol=0)
    monkeypatch.undo()
    cold = model.command_with_memory(params, moved, None)[0]
    torch.testing.assert_close(command, cold, rtol=0, atol=1e-9)
