"""Batched QP solver: OSQP-form ADMM against exact and OSQP references.

The MPC QPs (SPEC section 3) are checked in bulk against an exact active-set
enumeration (K = 5: all 3^5 choices of free / lower / upper per input, each one's KKT
conditions checked), which is itself checked against OSQP at tight tolerances; K = 20
and general constraint matrices are checked against OSQP directly.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import pytest
import torch
from torch import Tensor

from torchcf.qp import BoxQP, QPResult, QPSettings, QPStatus, solve_qp_batch

DT = 0.1  # [s]
#: SPEC section 3 priors (uniform) of the MPC parameters that shape the QP.
PRIOR = {
    "tau": (0.6, 1.4),
    "R": (0.3, 1.7),
    "alpha": (0.3, 1.7),
    "amin": (-5.0, -3.0),
    "amax": (3.0, 5.0),
}
DTYPES = (torch.float32, torch.float64)
#: |u0 - u0_ref| allowed by SPEC section 3 [m/s^2].
U0_TOL = {torch.float32: 1e-3, torch.float64: 1e-4}


def mpc_qp_matrices(
    tau: Tensor, R: Tensor, alpha: Tensor, dt: float, horizon: int = 5
) -> tuple[Tensor, Tensor]:
    """Hessian and linear-term map of the condensed MPC QP (copy of the model's).

    ``z_{k+1} = A z_k + B u_k``, ``A = [[1, dt], [0, 1]]``,
    ``B = [-tau dt - dt - dt^2/2, -dt]``; the cost
    ``sum_{k=1..K} z_k' Q z_k + R sum_{k=0..K-1} u_k^2`` is
    ``1/2 U' H U + (G z0)' U + const``.

    Args:
        tau, R, alpha: (B,) time gap [s], input weight, speed-error weight.
        dt: step [s].
        horizon: K.

    Returns:
        H: (B, K, K) symmetric positive definite; G: (B, K, 2).
    """
    batch = tau.shape[0]
    dtype, device = tau.dtype, tau.device
    b1 = -tau * dt - dt - 0.5 * dt * dt  # (B,)
    b2 = torch.full_like(tau, -dt)  # (B,)
    gamma = torch.zeros(batch, 2 * horizon, horizon, dtype=dtype, device=device)
    phi = torch.zeros(2 * horizon, 2, dtype=dtype, device=device)
    for k in range(1, horizon + 1):
        phi[2 * (k - 1)] = torch.tensor([1.0, k * dt], dtype=dtype)
        phi[2 * (k - 1) + 1] = torch.tensor([0.0, 1.0], dtype=dtype)
        for j in range(k):
            power = k - 1 - j  # A^power B = [b1 + power dt b2, b2]
            gamma[:, 2 * (k - 1), j] = b1 + power * dt * b2
            gamma[:, 2 * (k - 1) + 1, j] = b2
    weights = torch.stack((torch.ones_like(alpha), alpha), dim=1)  # (B, 2)
    qbar = weights.repeat(1, horizon)  # (B, 2K) diagonal of Qbar
    weighted = gamma * qbar[:, :, None]  # (B, 2K, K) = Qbar Gamma
    eye = torch.eye(horizon, dtype=dtype, device=device)
    hessian = 2.0 * (gamma.transpose(1, 2) @ weighted + R[:, None, None] * eye)
    linear = 2.0 * weighted.transpose(1, 2) @ phi  # (B, K, 2)
    return hessian, linear


class MPCBatch(NamedTuple):
    """A batch of MPC QPs ``min 1/2 U'HU + q'U s.t. lower <= U <= upper`` (float64)."""

    H: Tensor  # (B, K, K)
    G: Tensor  # (B, K, 2)
    z0: Tensor  # (B, 2) [spacing error m, dv m/s]
    tau: Tensor  # (B,)
    lower: Tensor  # (B, K)
    upper: Tensor  # (B, K)

    @property
    def q(self) -> Tensor:
        return (self.G @ self.z0[:, :, None])[:, :, 0]  # (B, K)

    def take(self, idx: Tensor) -> MPCBatch:
        return MPCBatch(*(t[idx] for t in self))


def mpc_batch(n: int, horizon: int, seed: int) -> MPCBatch:
    """``n`` MPC QPs with parameters from the SPEC prior.

    ``z0 = [s - v tau - l, dv]`` is a two-part mixture: half from realistic
    car-following ranges (spacing error in [-30, 40] m, dv in [-8, 8] m/s; about 85 %
    of these saturate an input), half near equilibrium ([-5, 5] m, [-1.5, 1.5] m/s;
    mostly interior). About half of the QPs then have active bounds, so both the
    exact fast path and ADMM are exercised. (The standstill distance l only enters
    through the spacing error, which is drawn directly.)
    """
    generator = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float, size: int = n) -> Tensor:
        unit = torch.rand(size, generator=generator, dtype=torch.float64)
        return low + (high - low) * unit

    p = {name: uniform(*bounds) for name, bounds in PRIOR.items()}
    H, G = mpc_qp_matrices(p["tau"], p["R"], p["alpha"], DT, horizon)
    near = torch.arange(n) % 2 == 1
    spacing_error = torch.where(near, uniform(-5.0, 5.0), uniform(-30.0, 40.0))
    dv = torch.where(near, uniform(-1.5, 1.5), uniform(-8.0, 8.0))
    z0 = torch.stack((spacing_error, dv), dim=1)
    lower = p["amin"][:, None].expand(n, horizon).contiguous()
    upper = p["amax"][:, None].expand(n, horizon).contiguous()
    return MPCBatch(H, G, z0, p["tau"], lower, upper)


def exact_box_qp(H: Tensor, q: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    """Exact minimiser of strictly convex box QPs by active-set enumeration (float64).

    For each of the ``3^n`` patterns (free / at lower / at upper per variable) solve
    the reduced system and keep the pattern whose point is feasible with multipliers
    of the right sign: the KKT conditions, which have one solution. Patterns with
    few active bounds come first and each is tried only on the unsolved instances.

    Returns:
        (B, n).
    """
    batch, n = q.shape
    solution = torch.full((batch, n), torch.nan, dtype=torch.float64)
    found = torch.zeros(batch, dtype=torch.bool)
    tol = 1e-9
    patterns = sorted(itertools.product((0, 1, 2), repeat=n), key=np.count_nonzero)
    for pattern in patterns:
        idx = (~found).nonzero().squeeze(1)
        if not idx.numel():
            break
        at = torch.tensor(pattern)[None, :].expand(idx.numel(), n)  # (b, n)
        at_lower, at_upper = at == 1, at == 2
        active = at_lower | at_upper
        free = (~active).double()
        h, g, lo, hi = H[idx], q[idx], lower[idx], upper[idx]
        fixed = torch.where(at_lower, lo, hi) * active
        system = h * free[:, :, None] * free[:, None, :]
        system = system + torch.diag_embed(active.double())
        rhs = fixed + free * (-g - (h @ fixed[:, :, None])[:, :, 0])
        x = torch.linalg.solve(system, rhs)
        y = -((h @ x[:, :, None])[:, :, 0] + g) * active  # multipliers
        kkt = (
            ((x >= lo - tol) & (x <= hi + tol)).all(1)
            & ((y <= tol) | ~at_lower).all(1)
            & ((y >= -tol) | ~at_upper).all(1)
        )
        solution[idx[kkt]] = x[kkt]
        found[idx[kkt]] = True
    assert bool(found.all()), "enumeration found no KKT point"
    return solution


def osqp_reference(
    P: Tensor, q: Tensor, A: Tensor, lower: Tensor, upper: Tensor
) -> np.ndarray:
    """OSQP at eps 1e-10 with polishing, one instance at a time (float64)."""
    osqp = pytest.importorskip("osqp")
    sparse = pytest.importorskip("scipy.sparse")
    solutions = []
    for i in range(q.shape[0]):
        solver = osqp.OSQP()
        solver.setup(
            sparse.triu(sparse.csc_matrix(P[i].double().numpy()), format="csc"),
            q[i].double().numpy(),
            sparse.csc_matrix(A[i].double().numpy()),
            lower[i].double().numpy(),
            upper[i].double().numpy(),
            eps_abs=1e-10,
            eps_rel=1e-10,
            polishing=True,
            max_iter=1_000_000,
            verbose=False,
        )
        result = solver.solve(raise_error=False)
        assert result.info.status == "solved", result.info.status
        solutions.append(result.x)
    return np.stack(solutions)


def eye_batch(batch: int, n: int, dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.eye(n, dtype=dtype).expand(batch, n, n).contiguous()


def has_active_bounds(mpc: MPCBatch) -> Tensor:
    """(B,) True where the unconstrained minimiser violates a bound."""
    free = -torch.linalg.solve(mpc.H, mpc.q)
    return ~((free >= mpc.lower) & (free <= mpc.upper)).all(1)


def random_feasible_qps(
    batch: int, n: int, m: int, seed: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """General QPs with one-sided, two-sided and equality rows around a feasible x.

    A quarter of the instances have a rank-2 (singular) ``P``.
    """
    generator = torch.Generator().manual_seed(seed)

    def normal(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=generator, dtype=torch.float64)

    factor = normal(batch, n, n)
    P = factor @ factor.transpose(1, 2) / n
    low_rank = factor[: batch // 4, :, :2]
    P[: batch // 4] = low_rank @ low_rank.transpose(1, 2)
    q = 3.0 * normal(batch, n)
    A = normal(batch, m, n)
    ax = (A @ normal(batch, n)[:, :, None])[:, :, 0]  # (B, m) A x_feasible
    gap = torch.rand(batch, m, 2, generator=generator, dtype=torch.float64)
    lower, upper = ax - 2.0 * gap[..., 0], ax + 2.0 * gap[..., 1]
    lower[:, :2] = -torch.inf
    upper[:, 2:4] = torch.inf
    equality = torch.arange(batch) % 3 == 0
    lower[equality, 4] = upper[equality, 4] = ax[equality, 4]
    return P, q, A, lower, upper


# --------------------------------------------------------------------------------------
# MPC QPs against exact references.


@pytest.fixture(scope="module")
def mpc5() -> tuple[MPCBatch, Tensor]:
    """10 000 K = 5 MPC QPs and their exact solutions."""
    mpc = mpc_batch(10_000, horizon=5, seed=11)
    return mpc, exact_box_qp(mpc.H, mpc.q, mpc.lower, mpc.upper)


@pytest.mark.parametrize("method", ["auto", "admm"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_mpc_k5_matches_exact_solution(mpc5, dtype, method):
    mpc, exact = mpc5
    result = BoxQP(mpc.H.to(dtype)).solve(
        mpc.q.to(dtype), mpc.lower.to(dtype), mpc.upper.to(dtype), method=method
    )
    active = has_active_bounds(mpc)
    err = (result.x[:, 0].double() - exact[:, 0]).abs()
    report = (
        f"{dtype} {method}: max |u0 err| {err.max():.2e} over {len(err)} QPs, "
        f"{int(active.sum())} ({float(active.double().mean()):.0%}) with active "
        f"bounds, {int(result.polished.sum())} polished, "
        f"{int((result.n_iter > 0).sum())} through ADMM "
        f"(mean {result.n_iter.double().mean():.1f} iterations)"
    )
    assert float(active.double().mean()) >= 0.2, report
    assert bool((result.status == QPStatus.SOLVED).all()), report
    assert float(err.max()) <= U0_TOL[dtype], report
    if method == "auto":
        assert bool((result.n_iter[~active] == 0).all()), "fast path missed: " + report
    assert result.x.dtype == dtype


def test_enumeration_agrees_with_osqp(mpc5):
    mpc, exact = mpc5
    idx = torch.arange(500)
    sub = mpc.take(idx)
    reference = osqp_reference(sub.H, sub.q, eye_batch(500, 5), sub.lower, sub.upper)
    assert float(has_active_bounds(sub).double().mean()) >= 0.2
    np.testing.assert_allclose(exact[idx].numpy(), reference, rtol=0, atol=1e-7)


@pytest.fixture(scope="module")
def mpc20() -> tuple[MPCBatch, np.ndarray]:
    mpc = mpc_batch(500, horizon=20, seed=12)
    eye = eye_batch(500, 20)
    return mpc, osqp_reference(mpc.H, mpc.q, eye, mpc.lower, mpc.upper)


@pytest.mark.parametrize("method", ["auto", "admm"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_mpc_k20_matches_osqp(mpc20, dtype, method):
    mpc, reference = mpc20
    result = BoxQP(mpc.H.to(dtype)).solve(
        mpc.q.to(dtype), mpc.lower.to(dtype), mpc.upper.to(dtype), method=method
    )
    active = has_active_bounds(mpc)
    err = (result.x[:, 0].double() - torch.from_numpy(reference[:, 0])).abs()
    report = (
        f"{dtype} {method}: max |u0 err| {err.max():.2e} over {len(err)} QPs, "
        f"{int(active.sum())} ({float(active.double().mean()):.0%}) with active bounds"
    )
    assert float(active.double().mean()) >= 0.2, report
    assert bool((result.status == QPStatus.SOLVED).all()), report
    assert float(err.max()) <= U0_TOL[dtype], report


# --------------------------------------------------------------------------------------
# Batch invariance, fast path, warm start, index.


def assert_same_result(batched: QPResult, alone: QPResult, atol: float) -> None:
    torch.testing.assert_close(batched.x, alone.x, rtol=0, atol=atol)
    torch.testing.assert_close(batched.y, alone.y, rtol=0, atol=atol)
    assert torch.equal(batched.status, alone.status)
    assert torch.equal(batched.n_iter, alone.n_iter)


@pytest.mark.parametrize("method", ["auto", "admm"])
def test_box_qp_batched_equals_one_by_one(method):
    mpc = mpc_batch(32, horizon=5, seed=3)
    batched = BoxQP(mpc.H).solve(mpc.q, mpc.lower, mpc.upper, method=method)
    assert 0 < int(has_active_bounds(mpc).sum()) < 32  # both kinds are covered
    for i in range(32):
        one = slice(i, i + 1)
        alone = BoxQP(mpc.H[one]).solve(
            mpc.q[one], mpc.lower[one], mpc.upper[one], method=method
        )
        assert_same_result(QPResult(*(t[one] for t in batched)), alone, atol=1e-12)


def test_general_batched_equals_one_by_one():
    P, q, A, lower, upper = random_feasible_qps(24, n=6, m=10, seed=4)
    batched = solve_qp_batch(P, q, A, lower, upper)
    assert bool((batched.status == QPStatus.SOLVED).all())
    for i in range(24):
        one = slice(i, i + 1)
        alone = solve_qp_batch(P[one], q[one], A[one], lower[one], upper[one])
        assert_same_result(QPResult(*(t[one] for t in batched)), alone, atol=1e-12)


def test_fast_path_and_active_set_stage_agree_with_admm():
    mpc = mpc_batch(400, horizon=5, seed=5)
    lower, upper = mpc.lower.clone(), mpc.upper.clone()
    lower[:50], upper[:50] = -torch.inf, torch.inf  # unconstrained
    lower[50:100, 2:] = -torch.inf  # one-sided rows
    solver = BoxQP(mpc.H)
    auto = solver.solve(mpc.q, lower, upper)
    admm = solver.solve(mpc.q, lower, upper, method="admm")
    general = solve_qp_batch(mpc.H, mpc.q, eye_batch(400, 5), lower, upper)
    fast = auto.n_iter == 0
    assert bool(fast.all())  # every instance: fast path or exact active set
    assert int((auto.polished).sum()) > 100  # ... and many of them the latter
    assert bool((admm.n_iter > 0).all())
    for result in (auto, admm, general):
        assert bool((result.status == QPStatus.SOLVED).all())
    torch.testing.assert_close(auto.x, admm.x, rtol=0, atol=1e-9)
    torch.testing.assert_close(auto.y, admm.y, rtol=0, atol=1e-8)
    # BoxQP's ADMM is solve_qp_batch's with A = I, to round-off.
    torch.testing.assert_close(admm.x, general.x, rtol=0, atol=1e-12)
    assert torch.equal(admm.n_iter, general.n_iter)
    unconstrained = -torch.linalg.solve(mpc.H, mpc.q)
    torch.testing.assert_close(solver.unconstrained(mpc.q), unconstrained)
    torch.testing.assert_close(auto.x[:50], unconstrained[:50])


def next_mpc_step(mpc: MPCBatch, u0: Tensor, seed: int) -> MPCBatch:
    """The QPs of the next time step: the state moved by u0, a random leader."""
    generator = torch.Generator().manual_seed(seed)
    a_lead = 0.3 * torch.randn(u0.shape, generator=generator, dtype=u0.dtype)
    b1 = -mpc.tau * DT - DT - 0.5 * DT**2
    spacing_error = mpc.z0[:, 0] + DT * mpc.z0[:, 1] + b1 * u0
    dv = mpc.z0[:, 1] - DT * u0 + DT * a_lead
    return mpc._replace(z0=torch.stack((spacing_error, dv), dim=1))


def shift(plan: Tensor) -> Tensor:
    """Receding horizon: drop the applied input, repeat the last one."""
    return torch.cat((plan[:, 1:], plan[:, -1:]), dim=1)


def test_warm_start_lowers_admm_iterations():
    mpc = mpc_batch(2000, horizon=5, seed=6)
    solver = BoxQP(mpc.H)
    first = solver.solve(mpc.q, mpc.lower, mpc.upper)
    nxt = next_mpc_step(mpc, first.x[:, 0], seed=7)
    exact = solver.solve(nxt.q, nxt.lower, nxt.upper)  # the exact solution
    # From the solution of a perturbed problem: the previous step's.
    cold = solver.solve(nxt.q, nxt.lower, nxt.upper, method="admm")
    warm = solver.solve(
        nxt.q, nxt.lower, nxt.upper, x0=first.x, y0=first.y, method="admm"
    )
    cold_mean = float(cold.n_iter.double().mean())
    warm_mean = float(warm.n_iter.double().mean())
    assert warm_mean < 0.85 * cold_mean, (warm_mean, cold_mean)
    # From the shifted previous plan, as the MPC does.
    shifted = solver.solve(
        nxt.q, nxt.lower, nxt.upper, x0=shift(first.x), y0=shift(first.y), method="admm"
    )
    assert float(shifted.n_iter.double().mean()) < cold_mean
    for result in (cold, warm, shifted):
        assert bool((result.status == QPStatus.SOLVED).all())
        torch.testing.assert_close(result.x, exact.x, rtol=0, atol=1e-9)


def test_shifted_plan_warm_start_helps_the_active_set_stage():
    """K = 20: from the previous plan the active set is found at once."""
    mpc = mpc_batch(1000, horizon=20, seed=18)
    solver = BoxQP(mpc.H)
    first = solver.solve(mpc.q, mpc.lower, mpc.upper)
    nxt = next_mpc_step(mpc, first.x[:, 0], seed=19)
    cold = solver.solve(nxt.q, nxt.lower, nxt.upper)
    warm = solver.solve(nxt.q, nxt.lower, nxt.upper, x0=shift(first.x))
    assert int((warm.n_iter > 0).sum()) < int((cold.n_iter > 0).sum())
    assert bool((warm.status == QPStatus.SOLVED).all())
    torch.testing.assert_close(warm.x, cold.x, rtol=0, atol=1e-9)


def _leading_work(monkeypatch) -> dict[str, int]:
    """Count the instances the leading-block stage re-solves after its first pass
    (new solves and rank-one boundary steps)."""
    # The active-set stage looks the two up in its own module: patched there.
    import torchcf.qp.active_set as active_set

    work = {"first": 0, "later": 0}
    solve, step = active_set.leading_solve, active_set.boundary_step

    def counted_solve(data, lower, upper):
        work["later" if work["first"] else "first"] += lower.shape[1]
        return solve(data, lower, upper)

    def counted_step(data, solution, j, lower, upper):
        work["later"] += j.numel()
        return step(data, solution, j, lower, upper)

    monkeypatch.setattr(active_set, "leading_solve", counted_solve)
    monkeypatch.setattr(active_set, "boundary_step", counted_step)
    return work


@pytest.mark.parametrize("dtype", DTYPES)
def test_active_guess_gives_the_same_solution(dtype):
    """Any guess of the active set, right or wrong, gives the same solution."""
    mpc = mpc_batch(1500, horizon=20, seed=22)
    mpc = MPCBatch(*(t.to(dtype) for t in mpc))
    solver = BoxQP(mpc.H)
    first = solver.solve(mpc.q, mpc.lower, mpc.upper)
    nxt = next_mpc_step(mpc, first.x[:, 0], seed=23)
    reference = solver.solve(nxt.q, nxt.lower, nxt.upper)
    generator = torch.Generator().manual_seed(24)
    noise = torch.randn(first.x.shape, generator=generator, dtype=dtype)
    guesses = {
        "previous plan": first.x,
        "shifted plan": shift(first.x),
        "all at the lower bound": nxt.lower,
        "all at the upper bound": nxt.upper,
        "alternating": torch.where(
            torch.arange(20) % 2 == 0, nxt.lower, nxt.upper
        ),  # never a leading block
        "random": 5 * noise,
        "none active": torch.zeros_like(first.x),
    }
    tol = 1e-9 if dtype == torch.float64 else 2e-3
    for name, guess in guesses.items():
        result = solver.solve(
            nxt.q, nxt.lower, nxt.upper, x0=shift(first.x), active_guess=guess
        )
        assert bool((result.status == QPStatus.SOLVED).all()), name
        if name in ("previous plan", "shifted plan"):
            assert bool((result.n_iter == 0).all()), name  # no ADMM needed
        torch.testing.assert_close(result.x, reference.x, rtol=0, atol=tol, msg=name)
    with pytest.raises(ValueError, match="active_guess"):
        solver.solve(nxt.q, nxt.lower, nxt.upper, active_guess=first.x[:, :3])


def test_unshifted_plan_is_the_better_active_set_guess(monkeypatch):
    """K = 20, states drifting as in tools/bench_qp.py (saturation persists): the
    last plan's own active set needs fewer re-solves than the shifted plan's, and
    a cold start more still. (In a closed loop, where the applied input moves the
    state as the plan predicted, the shifted plan can be the better guess; the
    solution is the same either way.)"""
    mpc = mpc_batch(2000, horizon=20, seed=25)
    generator = torch.Generator().manual_seed(26)
    solver = BoxQP(mpc.H)
    plan = solver.solve(mpc.q, mpc.lower, mpc.upper).x
    work = {}
    for _ in range(3):
        drift = 0.3 * torch.randn(
            mpc.z0.shape, generator=generator, dtype=torch.float64
        )
        mpc = mpc._replace(z0=mpc.z0 + drift)
        guesses = {"unshifted": plan, "shifted": shift(plan), "cold": None}
        results = {}
        for name, guess in guesses.items():
            counted = _leading_work(monkeypatch)
            x0 = None if guess is None else shift(plan)
            results[name] = solver.solve(
                mpc.q, mpc.lower, mpc.upper, x0=x0, active_guess=guess
            )
            work[name] = work.get(name, 0) + counted["later"]
            monkeypatch.undo()
        for result in results.values():
            torch.testing.assert_close(result.x, results["cold"].x, rtol=0, atol=1e-9)
        plan = results["unshifted"].x
    assert work["unshifted"] < 0.7 * work["shifted"], work
    assert work["shifted"] < work["cold"], work


def test_warm_start_from_perturbed_solution_lowers_iterations():
    P, q, A, lower, upper = random_feasible_qps(64, n=6, m=10, seed=8)
    generator = torch.Generator().manual_seed(9)
    perturbed = q + 0.01 * torch.randn(q.shape, generator=generator, dtype=q.dtype)
    previous = solve_qp_batch(P, perturbed, A, lower, upper)
    cold = solve_qp_batch(P, q, A, lower, upper)
    warm = solve_qp_batch(P, q, A, lower, upper, x0=previous.x, y0=previous.y)
    assert float(warm.n_iter.double().mean()) < 0.8 * float(cold.n_iter.double().mean())
    torch.testing.assert_close(warm.x, cold.x, rtol=0, atol=1e-8)


def test_index_solves_the_gathered_sub_batch():
    mpc = mpc_batch(50, horizon=5, seed=10)
    idx = torch.tensor([3, 7, 8, 20, 21, 33, 41, 49])
    sub = mpc.take(idx)
    via_index = BoxQP(mpc.H).solve(sub.q, sub.lower, sub.upper, index=idx)
    gathered = BoxQP(sub.H).solve(sub.q, sub.lower, sub.upper)
    assert_same_result(via_index, gathered, atol=1e-12)
    torch.testing.assert_close(
        BoxQP(mpc.H).unconstrained(sub.q, index=idx), BoxQP(sub.H).unconstrained(sub.q)
    )


# --------------------------------------------------------------------------------------
# General constraints, infeasibility, status.


def test_general_qps_match_osqp():
    P, q, A, lower, upper = random_feasible_qps(60, n=6, m=10, seed=13)
    result = solve_qp_batch(P, q, A, lower, upper)
    reference = osqp_reference(P, q, A, lower, upper)
    assert bool((result.status == QPStatus.SOLVED).all())
    np.testing.assert_allclose(result.x.numpy(), reference, rtol=0, atol=1e-4)
    # z is A x projected onto the bounds.
    ax = (A @ result.x[:, :, None])[:, :, 0]
    torch.testing.assert_close(result.z, torch.clamp(ax, lower, upper))


def test_primal_infeasible():
    """x1 + x2 >= 3 and x1 + x2 <= 1."""
    P = torch.eye(2, dtype=torch.float64)[None]
    A = torch.tensor([[[1.0, 1.0], [1.0, 1.0]]], dtype=torch.float64)
    lower = torch.tensor([[3.0, -torch.inf]], dtype=torch.float64)
    upper = torch.tensor([[torch.inf, 1.0]], dtype=torch.float64)
    q = torch.tensor([[1.0, -1.0]], dtype=torch.float64)
    result = solve_qp_batch(P, q, A, lower, upper)
    assert int(result.status[0]) == QPStatus.PRIMAL_INFEASIBLE
    certificate = result.y[0]  # A'y = 0 and u'y+ + l'y- < 0
    assert float((A[0].T @ certificate).abs().max()) < 1e-6
    assert (
        float(certificate[1].clamp(min=0) * 1.0 + certificate[0].clamp(max=0) * 3.0) < 0
    )


def test_dual_infeasible():
    """P = 0, q = (-1, 0) and nothing bounds x1: the objective is unbounded below."""
    P = torch.zeros(1, 2, 2, dtype=torch.float64)
    q = torch.tensor([[-1.0, 0.0]], dtype=torch.float64)
    A = torch.tensor([[[0.0, 1.0]]], dtype=torch.float64)
    lower = torch.tensor([[-1.0]], dtype=torch.float64)
    upper = torch.tensor([[1.0]], dtype=torch.float64)
    result = solve_qp_batch(P, q, A, lower, upper)
    assert int(result.status[0]) == QPStatus.DUAL_INFEASIBLE
    torch.testing.assert_close(result.x[0], torch.tensor([1.0, 0.0], dtype=P.dtype))


def mixed_batch() -> tuple[Tensor, ...]:
    """Easy, hard (ill-conditioned), primal and dual infeasible QPs, n = m = 2."""
    inf = torch.inf
    P = torch.tensor(
        [
            [[1.0, 0.0], [0.0, 1.0]],  # easy
            [[1e4, 0.0], [0.0, 1e-2]],  # hard: condition number 1e6
            [[1.0, 0.0], [0.0, 1.0]],  # primal infeasible
            [[0.0, 0.0], [0.0, 0.0]],  # dual infeasible
        ],
        dtype=torch.float64,
    )
    q = torch.tensor(
        [[0.1, -0.2], [1.0, -1.0], [1.0, -1.0], [-1.0, 0.0]], dtype=torch.float64
    )
    A = torch.tensor(
        [
            [[1.0, 0.0], [0.0, 1.0]],
            [[1.0, 1.0], [1.0, -1.0]],
            [[1.0, 1.0], [1.0, 1.0]],
            [[0.0, 1.0], [0.0, 1.0]],
        ],
        dtype=torch.float64,
    )
    lower = torch.tensor(
        [[-1.0, -1.0], [-inf, -50.0], [3.0, -inf], [-1.0, -inf]], dtype=torch.float64
    )
    upper = torch.tensor(
        [[1.0, 1.0], [1.0, 50.0], [inf, 1.0], [1.0, 2.0]], dtype=torch.float64
    )
    return P, q, A, lower, upper


def test_mixed_batch_reports_status_and_iterations_per_instance():
    P, q, A, lower, upper = mixed_batch()
    result = solve_qp_batch(P, q, A, lower, upper)
    expected = [
        QPStatus.SOLVED,
        QPStatus.SOLVED,
        QPStatus.PRIMAL_INFEASIBLE,
        QPStatus.DUAL_INFEASIBLE,
    ]
    assert result.status.tolist() == [int(s) for s in expected]
    assert int(result.n_iter[0]) < int(result.n_iter[1])  # easy before hard
    for i in range(4):
        one = slice(i, i + 1)
        alone = solve_qp_batch(P[one], q[one], A[one], lower[one], upper[one])
        assert torch.equal(alone.status, result.status[one])
        assert torch.equal(alone.n_iter, result.n_iter[one])
    # The solved ones are right.
    reference = osqp_reference(P[:2], q[:2], A[:2], lower[:2], upper[:2])
    np.testing.assert_allclose(result.x[:2].numpy(), reference, rtol=0, atol=1e-6)
    # Cut the iterations: the hard instance stops at MAX_ITER, the others do not.
    limit = int(result.n_iter[0])
    short = solve_qp_batch(P, q, A, lower, upper, settings=QPSettings(max_iter=limit))
    assert int(short.status[0]) == QPStatus.SOLVED
    assert int(short.status[1]) == QPStatus.MAX_ITER
    assert int(short.n_iter[1]) == limit
    torch.testing.assert_close(short.x[0], result.x[0])


def test_equality_constrained_qp_matches_kkt_solve():
    generator = torch.Generator().manual_seed(14)
    batch, n, m = 16, 6, 3
    factor = torch.randn(batch, n, n, generator=generator, dtype=torch.float64)
    P = factor @ factor.transpose(1, 2) / n + 0.1 * torch.eye(n, dtype=torch.float64)
    q = torch.randn(batch, n, generator=generator, dtype=torch.float64)
    A = torch.randn(batch, m, n, generator=generator, dtype=torch.float64)
    b = torch.randn(batch, m, generator=generator, dtype=torch.float64)
    kkt = torch.cat(
        (
            torch.cat((P, A.transpose(1, 2)), dim=2),
            torch.cat((A, torch.zeros(batch, m, m, dtype=torch.float64)), dim=2),
        ),
        dim=1,
    )
    solution = torch.linalg.solve(kkt, torch.cat((-q, b), dim=1))
    result = solve_qp_batch(P, q, A, b, b)
    assert bool((result.status == QPStatus.SOLVED).all())
    torch.testing.assert_close(result.x, solution[:, :n], rtol=0, atol=1e-8)
    torch.testing.assert_close(result.y, solution[:, n:], rtol=0, atol=1e-7)


# --------------------------------------------------------------------------------------
# Dtype, device, settings.


@pytest.mark.parametrize("dtype", DTYPES)
def test_output_dtypes(dtype):
    mpc = mpc_batch(40, horizon=5, seed=15)
    P, q, A, lower, upper = random_feasible_qps(8, n=6, m=10, seed=16)
    results = (
        BoxQP(mpc.H.to(dtype)).solve(
            mpc.q.to(dtype), mpc.lower.to(dtype), mpc.upper.to(dtype)
        ),
        solve_qp_batch(
            P.to(dtype), q.to(dtype), A.to(dtype), lower.to(dtype), upper.to(dtype)
        ),
    )
    for result in results:
        assert result.x.dtype == result.y.dtype == result.z.dtype == dtype
        assert result.n_iter.dtype == result.status.dtype == torch.int64
        assert result.polished.dtype == torch.bool
        assert bool((result.status == QPStatus.SOLVED).all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    mpc = mpc_batch(256, horizon=5, seed=17)
    cpu = BoxQP(mpc.H).solve(mpc.q, mpc.lower, mpc.upper)
    device = torch.device("cuda")
    gpu = BoxQP(mpc.H.to(device)).solve(
        mpc.q.to(device), mpc.lower.to(device), mpc.upper.to(device)
    )
    assert gpu.x.device.type == "cuda"
    torch.testing.assert_close(gpu.x.cpu(), cpu.x, rtol=0, atol=1e-9)
    P, q, A, lower, upper = (t.to(device) for t in mixed_batch())
    assert solve_qp_batch(P, q, A, lower, upper).status.tolist() == [0, 0, 2, 3]


def test_settings_are_validated():
    with pytest.raises(ValueError, match="alpha"):
        QPSettings(alpha=2.5)
    with pytest.raises(ValueError):
        QPSettings(rho=0.0)
    with pytest.raises(ValueError, match="shape"):
        BoxQP(torch.eye(3)[None]).solve(
            torch.zeros(1, 2), torch.zeros(1, 2), torch.ones(1, 2)
        )
    with pytest.raises(ValueError, match="lower bound"):
        BoxQP(torch.eye(2)[None]).solve(
            torch.zeros(1, 2), torch.ones(1, 2), torch.zeros(1, 2)
        )


# --------------------------------------------------------------------------------------
# Internals of the box-QP stages: each against a dense solve of its own.


def _random_spd(batch: int, n: int, seed: int, dtype=torch.float64) -> Tensor:
    """(n, n, B) batch-last symmetric positive definite matrices."""
    generator = torch.Generator().manual_seed(seed)
    root = torch.randn(batch, n, n, generator=generator, dtype=dtype)
    spd = root @ root.transpose(1, 2) + n * torch.eye(n, dtype=dtype)
    return spd.permute(1, 2, 0).contiguous()


@pytest.mark.parametrize("batch", [3, 1500])  # LAPACK path and elementwise path
def test_cholesky_factors_and_flags_singular(batch):
    from torchcf.qp.kernels import cholesky, cholesky_solve, ul_cholesky

    n = 6
    M = _random_spd(batch, n, 0)
    M[:, :, 0] = 0.0  # instance 0 is singular: zero row and column
    L, ok = cholesky(M)
    assert not bool(ok[0]) and bool(ok[1:].all())
    dense = M.permute(2, 0, 1)[1:]
    lower = torch.tril(L.permute(2, 0, 1)[1:])
    torch.testing.assert_close(lower @ lower.transpose(1, 2), dense)
    U, ok_upper = ul_cholesky(M)
    upper = torch.triu(U.permute(2, 0, 1)[1:])
    torch.testing.assert_close(upper @ upper.transpose(1, 2), dense)
    assert bool((ok_upper == ok).all())
    rhs = torch.randn(n, batch, dtype=M.dtype)
    x = cholesky_solve(L, rhs)[:, 1:]
    torch.testing.assert_close(dense @ x.T[:, :, None], rhs[:, 1:].T[:, :, None])


@pytest.mark.parametrize("dtype", DTYPES)
def test_leading_solve_matches_the_reduced_system(dtype):
    """x_F = P_FF^{-1} (-q_F - P_FA x_A) for a leading block A of every length."""
    from torchcf.qp.leading import (
        is_leading,
        leading_data,
        leading_factor,
        leading_solve,
    )

    n, batch = 7, 64
    generator = torch.Generator().manual_seed(3)
    P = _random_spd(batch, n, 1)
    q = 10 * torch.randn(n, batch, generator=generator, dtype=torch.float64)
    lo = -torch.rand(n, batch, generator=generator, dtype=torch.float64)
    hi = torch.rand(n, batch, generator=generator, dtype=torch.float64)
    depth = torch.arange(batch) % (n + 1)  # 0 .. n fixed rows
    active = torch.arange(n)[:, None] < depth[None]
    side = torch.rand(n, batch, generator=generator) < 0.5
    lower, upper = active & side, active & ~side
    assert bool(is_leading(active).all())
    factor, ok = leading_factor(P.to(dtype))
    assert bool(ok.all())
    data = leading_data(factor, q.to(dtype), lo.to(dtype), hi.to(dtype), QPSettings())
    solution = leading_solve(data, lower, upper)
    assert torch.equal(solution.k, depth)
    tol = 1e-10 if dtype == torch.float64 else 2e-4
    for b in range(batch):
        k = int(depth[b])
        Pb, qb = P[:, :, b], q[:, b]
        fixed = torch.where(lower[:, b], lo[:, b], hi[:, b])[:k]
        expect = torch.empty(n, dtype=torch.float64)
        expect[:k] = fixed
        if k < n:
            rhs = -qb[k:] - Pb[k:, :k] @ fixed
            expect[k:] = torch.linalg.solve(Pb[k:, k:], rhs)
        torch.testing.assert_close(
            solution.x[:, b].double(), expect, atol=tol, rtol=tol
        )
        multiplier = -(Pb @ expect + qb)
        multiplier[k:] = 0
        torch.testing.assert_close(
            solution.y[:, b].double(), multiplier, atol=tol * 100, rtol=tol
        )
        sign = lower[:, b].double() - upper[:, b].double()
        torch.testing.assert_close(
            solution.signed[:, b].double(), multiplier * sign, atol=tol * 100, rtol=tol
        )
        # The stationarity residual of the free rows, looked up by k, is round-off.
        stationarity = (Pb @ solution.x[:, b].double() + qb)[k:]
        looked_up = float(data.call.tail_residual[k, b])
        assert looked_up <= 100 * torch.finfo(dtype).eps * (1 + float(qb.abs().max()))
        if k < n:
            assert float(stationarity.abs().max()) <= tol * 100 + looked_up


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("batch,bad", [(400, 4), (40, 10)])  # few gathered; all
def test_tail_residual_bounds_the_back_substitution(dtype, batch, bad):
    """The table of the free rows' residual: a bound of |U g - q| where that bound
    clears the acceptance floor, the residual itself where it does not (here the
    first ``bad`` instances, ill-conditioned)."""
    from torchcf.qp.kernels import back_substitute, tail_residuals
    from torchcf.qp.leading import leading_data, leading_factor
    from torchcf.qp.problem import roundoff_floor

    n = 9
    generator = torch.Generator().manual_seed(7)
    P = _random_spd(batch, n, 3).permute(2, 0, 1)  # (B, n, n)
    basis, _ = torch.linalg.qr(torch.randn(bad, n, n, generator=generator).double())
    spectrum = torch.logspace(-2, 2, n, dtype=torch.float64)
    P[:bad] = basis @ torch.diag_embed(spectrum.expand(bad, n)) @ basis.transpose(1, 2)
    P = P.permute(1, 2, 0).contiguous().to(dtype)
    q = (10 * torch.randn(n, batch, generator=generator).double()).to(dtype)
    factor, ok = leading_factor(P)
    assert bool(ok.all())
    lo, hi = -torch.ones(n, batch, dtype=dtype), torch.ones(n, batch, dtype=dtype)
    settings = QPSettings()
    table = leading_data(factor, q, lo, hi, settings).call.tail_residual
    g = back_substitute(factor.U, factor.inv_diag, q)
    computed = tail_residuals(factor.U, g, q)
    assert table.shape == (n + 1, batch) and bool((table[n] == 0).all())
    # The residual of the computed g, evaluated in float64, is under the table.
    residual = torch.einsum("ijb,jb->ib", factor.U.double(), g.double()) - q.double()
    tail = residual.abs().flip(0).cummax(0).values.flip(0)
    slack = 4 * torch.finfo(dtype).eps * (1 + q.double().abs().amax(0))
    assert bool((tail <= table[:n].double() + slack).all())
    # The ill-conditioned instances' bounds would not clear the floor: computed.
    floor = roundoff_floor(q.abs().amax(0), settings)
    bound_cleared = table[0] <= floor
    assert torch.equal(table[:, :bad], computed[:, :bad])
    assert bool(bound_cleared[bad:].all())  # and the rest stay acceptable


@pytest.mark.parametrize("dtype", DTYPES)
def test_boundary_step_matches_a_new_solve(dtype):
    """Fixing the next bound, or freeing the last one, of a leading block by the
    rank-one update gives the solve on the new block."""
    from torchcf.qp.leading import (
        boundary_step,
        leading_data,
        leading_factor,
        leading_solve,
    )

    n, batch = 7, 96
    generator = torch.Generator().manual_seed(4)
    P = _random_spd(batch, n, 2).to(dtype)
    q = (10 * torch.randn(n, batch, generator=generator, dtype=torch.float64)).to(dtype)
    lo = -torch.rand(n, batch, generator=generator, dtype=torch.float64).to(dtype)
    hi = torch.rand(n, batch, generator=generator, dtype=torch.float64).to(dtype)
    k = torch.arange(batch) % (n + 1)  # 0 .. n fixed rows
    grow = (torch.arange(batch) % 2 == 0) & (k < n) | (k == 0)  # else shrink
    j = torch.where(grow, k, k - 1)
    side = torch.rand(n, batch, generator=generator) < 0.5
    rows = torch.arange(n)[:, None]
    before, after = rows < k[None], rows < torch.where(grow, k + 1, k - 1)[None]
    factor, ok = leading_factor(P)
    assert bool(ok.all())
    data = leading_data(factor, q, lo, hi, QPSettings())
    start = leading_solve(data, before & side, before & ~side)
    stepped = boundary_step(data, start, j, after & side, after & ~side)
    direct = leading_solve(data, after & side, after & ~side)
    tol = 1e-10 if dtype == torch.float64 else 1e-3
    torch.testing.assert_close(stepped.x, direct.x, atol=tol, rtol=tol)
    torch.testing.assert_close(stepped.y, direct.y, atol=tol * 10, rtol=tol)
    torch.testing.assert_close(stepped.signed, direct.signed, atol=tol * 10, rtol=tol)
    assert torch.equal(stepped.k, direct.k)
    fixed = torch.where(side, lo, hi)
    assert torch.equal(stepped.x[after], fixed[after])  # exactly on the bounds
    # ... so the guess is recovered from x and k, as the compacted passes do.
    from torchcf.qp.leading import leading_guess

    for solution, block in ((start, before), (stepped, after), (direct, after)):
        lower, upper = leading_guess(data, solution.x, solution.k)
        assert torch.equal(lower, block & side) and torch.equal(upper, block & ~side)


def test_is_leading():
    from torchcf.qp.leading import is_leading

    columns = [[1, 1, 0], [0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1], [1, 0, 1]]
    active = torch.tensor(columns, dtype=torch.bool).T  # (n = 3, B = 6)
    assert is_leading(active).tolist() == [True, True, True, False, True, False]


def test_guesses_that_are_not_a_leading_block_are_still_solved():
    """Random box QPs (not MPC): active bounds anywhere; results match OSQP."""
    n, batch = 8, 300
    P = _random_spd(batch, n, 5).permute(2, 0, 1)
    generator = torch.Generator().manual_seed(6)
    q = 20 * torch.randn(batch, n, generator=generator, dtype=torch.float64)
    lower = torch.full((batch, n), -1.0, dtype=torch.float64)
    upper = torch.full((batch, n), 1.0, dtype=torch.float64)
    result = BoxQP(P).solve(q, lower, upper)
    active = (result.x <= lower + 1e-9) | (result.x >= upper - 1e-9)
    from torchcf.qp.leading import is_leading

    assert not bool(is_leading(active.T).all())  # the case under test occurs
    assert bool((result.status == int(QPStatus.SOLVED)).all())
    import osqp
    import scipy.sparse as sparse

    for b in range(0, batch, 10):
        solver = osqp.OSQP()
        solver.setup(
            sparse.csc_matrix(np.triu(P[b].numpy())),
            q[b].numpy(),
            sparse.identity(n, format="csc"),
            lower[b].numpy(),
            upper[b].numpy(),
            verbose=False,
            eps_abs=1e-10,
            eps_rel=1e-10,
            max_iter=100000,
            polishing=True,
        )
        reference = solver.solve(raise_error=False).x
        np.testing.assert_allclose(result.x[b].numpy(), reference, atol=1e-6)


def test_tune_malloc_is_idempotent():
    from torchcf.system.process import tune_malloc

    first = tune_malloc()
    assert tune_malloc() is first
