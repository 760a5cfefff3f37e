"""Metrics against scipy's HiGHS solving the original LPs of SPEC section 6."""

from __future__ import annotations

import math

import numpy as np
import ot
import pytest
import scipy.sparse as sp
import torch
from scipy.optimize import linprog

from torchcf.evaluation.entropic import (
    OMEGA_MAX,
    SINGLE_THREAD_CELLS,
    limit_threads,
    sinkhorn_log,
)
from torchcf.evaluation.metrics import (
    average_errors,
    beta_wasserstein,
    evaluate_cost_sets,
    evaluate_costs,
    min_distance,
    sinkhorn,
    sinkhorn_many,
    wasserstein,
)

TOL = 1e-9
BETAS = [0.0, 0.05, 0.15, 0.5, 0.9, 1.0]
SHAPES = [(1, 5), (6, 1), (4, 9), (9, 4), (7, 7), (12, 30), (25, 8)]


def lp_reference(cost: np.ndarray, beta: float | None = None) -> float:
    """The original LP by HiGHS: ``inf`` when infeasible.

    Variables ``gamma: (P, N)`` flattened row-major, ``0`` on non-finite cells.
    Rows: pair marginals ``= 1/N``; particle marginals ``= 1/P`` (``beta is None``,
    WS) or ``>= beta/P``; total mass ``= 1`` (redundant, as in the paper's LP).
    """
    n, m = cost.shape
    valid = np.isfinite(cost).ravel()
    c = np.where(valid, cost.ravel(), 0.0)
    rows_of = sp.kron(sp.eye(n), np.ones((1, m)))  # (P, P N): particle sums
    cols_of = sp.kron(np.ones((1, n)), sp.eye(m))  # (N, P N): pair sums
    total = sp.csr_matrix(np.ones((1, n * m)))
    a_eq = [cols_of, total]
    b_eq = [np.full(m, 1.0 / m), [1.0]]
    a_ub = b_ub = None
    if beta is None:
        a_eq.append(rows_of)
        b_eq.append(np.full(n, 1.0 / n))
    else:
        a_ub, b_ub = -rows_of, np.full(n, -beta / n)
    bounds = [(0, None) if v else (0, 0) for v in valid]
    res = linprog(
        c,
        A_ub=a_ub,
        b_ub=b_ub,
        A_eq=sp.vstack(a_eq).tocsr(),
        b_eq=np.concatenate(b_eq),
        bounds=bounds,
        method="highs",
    )
    if res.status == 2:
        return math.inf
    assert res.status == 0, res.message
    return float(res.fun)


def random_cost(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.gamma(2.0, 2.0, size=shape)  # score-like: positive, skewed


def degenerate_costs() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    base = rng.random((5, 8))
    return {
        "all_equal": np.full((6, 9), 2.5),
        "zeros": np.zeros((4, 7)),
        "some_zeros": np.where(rng.random((8, 5)) < 0.5, 0.0, rng.random((8, 5))),
        "dup_rows": np.vstack([base, base, base[:2]]),
        "dup_cols": np.hstack([base, base, base[:, :3]]),
        "int_ties": rng.integers(0, 3, size=(9, 12)).astype(float),
        "int_ties_tall": rng.integers(0, 2, size=(15, 4)).astype(float),
    }


def check_plan(result, cost: np.ndarray, beta: float) -> None:
    """The plan is feasible for the original LP and its value is <plan, C>."""
    n, m = cost.shape
    plan = result.plan
    assert plan.shape == (n, m)
    assert plan.min() >= 0.0
    np.testing.assert_allclose(plan.sum(axis=0), 1.0 / m, atol=1e-13)
    np.testing.assert_allclose(result.particle_mass, plan.sum(axis=1), atol=1e-15)
    if beta == 1.0:
        np.testing.assert_allclose(plan.sum(axis=1), 1.0 / n, atol=1e-13)
    else:
        assert np.all(plan.sum(axis=1) >= beta / n - 1e-13)
    finite = np.isfinite(cost)
    assert np.all(plan[~finite] == 0.0)
    value = float(np.sum(plan[finite] * cost[finite]))
    assert abs(value - result.value) <= 1e-12 * max(1.0, abs(value))


# ---------------------------------------------------------------------------
# exact values against HiGHS


@pytest.mark.parametrize("shape", SHAPES)
def test_wasserstein_matches_linprog(shape):
    for seed in range(2):
        cost = random_cost(shape, seed)
        result = wasserstein(cost)
        assert result.feasible and result.invalid_cells == 0
        assert abs(result.value - lp_reference(cost)) <= TOL
        check_plan(result, cost, 1.0)


@pytest.mark.parametrize("beta", BETAS)
@pytest.mark.parametrize("shape", SHAPES)
def test_beta_wasserstein_matches_linprog(shape, beta):
    cost = random_cost(shape, seed=10 * SHAPES.index(shape) + BETAS.index(beta))
    result = beta_wasserstein(cost, beta)
    assert result.feasible
    assert abs(result.value - lp_reference(cost, beta)) <= TOL
    check_plan(result, cost, beta)


@pytest.mark.parametrize("shape", SHAPES)
def test_min_distance_matches_linprog(shape):
    cost = random_cost(shape, seed=3)
    assert abs(min_distance(cost) - lp_reference(cost, 0.0)) <= TOL
    assert abs(min_distance(cost) - cost.min(axis=0).mean()) <= 1e-15


@pytest.mark.parametrize("name", list(degenerate_costs()))
def test_degenerate_costs_match_linprog(name):
    cost = degenerate_costs()[name]
    ws = wasserstein(cost)
    assert abs(ws.value - lp_reference(cost)) <= TOL
    check_plan(ws, cost, 1.0)
    for beta in BETAS:
        result = beta_wasserstein(cost, beta)
        assert abs(result.value - lp_reference(cost, beta)) <= TOL, beta
        check_plan(result, cost, beta)
    assert abs(min_distance(cost) - lp_reference(cost, 0.0)) <= TOL


@pytest.mark.parametrize("shape", [(1, 5), (6, 1), (9, 4), (12, 30)])
def test_beta_endpoints(shape):
    cost = random_cost(shape, seed=11)
    assert beta_wasserstein(cost, 1.0).value == wasserstein(cost).value
    assert beta_wasserstein(cost, 0.0).value == pytest.approx(
        min_distance(cost), abs=1e-15
    )
    # beta-WS is nondecreasing in beta (the feasible set shrinks)
    values = [beta_wasserstein(cost, beta).value for beta in BETAS]
    assert all(b >= a - 1e-12 for a, b in zip(values, values[1:], strict=False))


def test_beta_particle_mass_marks_best_particles():
    cost = np.array([[0.0, 5.0, 5.0], [5.0, 5.0, 5.0], [5.0, 0.0, 0.0]])
    result = beta_wasserstein(cost, 0.3)  # mandatory 0.1 each, free 0.7
    # particle 1 only carries its mandatory mass; the free mass goes to 0 and 2
    assert result.particle_mass[1] == pytest.approx(0.1, abs=1e-15)
    assert result.particle_mass.sum() == pytest.approx(1.0, abs=1e-15)
    assert result.value == pytest.approx(lp_reference(cost, 0.3), abs=TOL)


def test_torch_input_matches_numpy():
    cost = random_cost((10, 6), seed=5)
    for tensor in (torch.from_numpy(cost), torch.from_numpy(cost).float()):
        reference = tensor.double().numpy()
        assert wasserstein(tensor).value == wasserstein(reference).value
        assert beta_wasserstein(tensor, 0.15).value == (
            beta_wasserstein(reference, 0.15).value
        )
        assert min_distance(tensor) == min_distance(reference)


def test_emd_iteration_limit_raises():
    cost = random_cost((40, 40), seed=0)
    with pytest.raises(RuntimeError, match="max_iter"):
        wasserstein(cost, max_iter=3)


# ---------------------------------------------------------------------------
# Sinkhorn


@pytest.mark.parametrize("shape", [(12, 30), (25, 8)])
def test_sinkhorn_gap_shrinks_with_reg(shape):
    cost = random_cost(shape, seed=2)
    scale = cost.max() - cost.min()
    ws = wasserstein(cost).value
    gaps = []
    for rel in (1.0, 0.1, 0.01):
        result = sinkhorn(cost, rel * scale)
        assert result.converged, (rel, result.marginal_error)
        assert result.ws == ws
        assert result.gap == pytest.approx(result.value - ws, abs=1e-15)
        assert result.gap >= -1e-9
        np.testing.assert_allclose(result.plan.sum(axis=1), 1 / shape[0], atol=1e-12)
        gaps.append(result.gap)
    # <gamma_reg, C> is nondecreasing in reg, so the gap shrinks with it
    assert gaps[0] > gaps[1] > gaps[2] >= -1e-9
    assert gaps[2] < 0.05 * scale


def test_sinkhorn_unconverged_is_reported():
    cost = random_cost((20, 20), seed=4)
    result = sinkhorn(cost, 1e-3 * cost.max(), max_iter=20)
    assert not result.converged
    assert result.n_iter == 20


# ---------------------------------------------------------------------------
# our Sinkhorn against POT's (the independent reference)


def pot_sinkhorn(cost: np.ndarray, reg: float, max_iter: int = 100_000):
    """POT's log-domain Sinkhorn on the same problem: (value, plan, iterations,
    last marginal error); forbidden cells (``inf``) get zero kernel there too."""
    n, m = cost.shape
    a = torch.full((n,), 1.0 / n, dtype=torch.float64)
    b = torch.full((m,), 1.0 / m, dtype=torch.float64)
    plan, log = ot.sinkhorn(
        a, b, torch.from_numpy(cost), reg, method="sinkhorn_log",
        numItermax=max_iter, stopThr=1e-9, log=True, warn=False,
    )  # fmt: skip
    plan = plan.numpy()
    value = float(np.sum(plan * np.where(np.isfinite(cost), cost, 0.0)))
    return value, plan, int(log["niter"]) + 1, float(log["err"][-1])


def squared_distances(n: int, m: int, seed: int) -> np.ndarray:
    """``(x_i - y_j)^2`` of sorted points in [0, 1]: near-ties everywhere, the
    classic case where plain Sinkhorn needs thousands of iterations."""
    rng = np.random.default_rng(seed)
    x, y = np.sort(rng.random(n)), np.sort(rng.random(m))
    return (x[:, None] - y[None, :]) ** 2


def sinkhorn_cases() -> dict[str, tuple[np.ndarray, float]]:
    """name -> (cost, reg): random and structured, with forbidden cells."""
    return {
        "random 12x30": (random_cost((12, 30), seed=2), 0.5),
        "random 220x17": (random_cost((220, 17), seed=3), 0.05),
        "squared distances 60x40": (squared_distances(60, 40, seed=0), 1e-3),
        "integer ties 9x12": (degenerate_costs()["int_ties"], 0.05),
        "forbidden 15x20": (feasible_invalid_cost((15, 20), seed=15)[0], 0.2),
        "forbidden 40x8": (feasible_invalid_cost((40, 8), 40, fraction=0.5)[0], 0.1),
    }  # fmt: skip


SINKHORN_CASES = [
    "random 12x30", "random 220x17", "squared distances 60x40",
    "integer ties 9x12", "forbidden 15x20", "forbidden 40x8",
]  # fmt: skip


@pytest.mark.parametrize("name", SINKHORN_CASES)
def test_sinkhorn_matches_pot(name):
    cost, reg = sinkhorn_cases()[name]
    value, plan, _, pot_error = pot_sinkhorn(cost, reg)
    assert pot_error < 1e-9  # the reference converged
    result = sinkhorn(cost, reg)
    assert result.converged and result.marginal_error < 1e-9
    assert result.value == pytest.approx(value, rel=1e-7)
    np.testing.assert_allclose(result.plan, plan, rtol=0, atol=1e-8)
    # rows exact (the last update), pair marginals within the reported error
    n, m = cost.shape
    np.testing.assert_allclose(result.plan.sum(axis=1), 1 / n, rtol=0, atol=1e-14)
    column_error = np.linalg.norm(result.plan.sum(axis=0) - 1 / m)
    assert column_error == pytest.approx(result.marginal_error, rel=1e-6, abs=1e-15)
    assert np.all(result.plan[~np.isfinite(cost)] == 0.0)
    assert result.ws == wasserstein(cost).value and result.gap >= -1e-9


@pytest.mark.parametrize("name", SINKHORN_CASES)
def test_plain_iterations_are_pots(name):
    """Without over-relaxation our iterates are POT's: same iteration count."""
    cost, reg = sinkhorn_cases()[name]
    value, _, n_iter, _ = pot_sinkhorn(cost, reg)
    (plain,) = sinkhorn_log([cost], reg, max_iter=100_000, overrelax=False)
    assert plain.n_iter == n_iter and plain.omega == 1.0
    assert plain.value == pytest.approx(value, rel=1e-12)


def test_overrelaxation_cuts_iterations():
    cost, reg = sinkhorn_cases()["squared distances 60x40"]
    (plain,) = sinkhorn_log([cost], reg, max_iter=100_000, overrelax=False)
    (fast,) = sinkhorn_log([cost], reg, max_iter=100_000)
    assert plain.converged and fast.converged
    assert fast.n_iter < plain.n_iter / 3 and 1.0 < fast.omega <= OMEGA_MAX
    assert fast.value == pytest.approx(plain.value, rel=1e-7)


def test_sinkhorn_batched_equals_one_at_a_time():
    cases = [cost for cost, _ in sinkhorn_cases().values()]
    infeasible = random_cost((5, 6), seed=9)
    infeasible[2] = np.inf  # WS infeasible: never solved, reported as such
    matrices = [*cases, infeasible, torch.from_numpy(cases[0]).float()]
    calls = []
    batched = sinkhorn_many(
        matrices, 0.1, max_iter=5000, callback=lambda i, n: calls.append((i, n))
    )
    assert len(batched) == len(matrices)
    for matrix, together in zip(matrices, batched, strict=True):
        alone = sinkhorn(matrix, 0.1, max_iter=5000)
        assert together.n_iter == alone.n_iter
        assert together.converged == alone.converged
        assert together.ws == alone.ws
        if alone.plan is None:
            assert together.plan is None and together.value == math.inf
            assert together.n_iter == 0 and math.isnan(together.marginal_error)
            continue
        assert together.value == pytest.approx(alone.value, rel=1e-13)
        np.testing.assert_allclose(together.plan, alone.plan, rtol=0, atol=1e-15)
        assert together.marginal_error == pytest.approx(alone.marginal_error, rel=1e-6)
    # progress: iterations increase, every matrix (the infeasible one too) ends done
    assert [i for i, _ in calls] == sorted(i for i, _ in calls)
    assert calls[0][1] >= 1 and calls[-1] == (max(r.n_iter for r in batched), 8)


def test_sinkhorn_iteration_cap_is_respected_and_reported():
    hard = squared_distances(50, 30, seed=1)
    easy = 1e-5 * random_cost((10, 4), seed=5)  # reg ~ its cost range: fast
    max_iter = 37  # not a multiple of the test interval: the last one is tested too
    _, _, _, pot_error = pot_sinkhorn(hard, 1e-4, max_iter=max_iter)
    assert pot_error > 1e-9  # POT does not converge within the cap either
    capped = sinkhorn(hard, 1e-4, max_iter=max_iter)
    assert not capped.converged and capped.n_iter == max_iter
    column_error = np.linalg.norm(capped.plan.sum(axis=0) - 1 / hard.shape[1])
    assert capped.marginal_error == pytest.approx(column_error, rel=1e-9)
    assert capped.marginal_error > 1e-9 and np.isfinite(capped.value)
    # in one batch the capped problem does not hold the other back
    together, quick = sinkhorn_many([hard, easy], 1e-4, max_iter=max_iter)
    assert not together.converged and together.n_iter == max_iter
    assert together.value == pytest.approx(capped.value, rel=1e-13)
    assert quick.converged and quick.n_iter < max_iter


def test_entropic_solver_rejects_rows_without_a_cell():
    cost = np.ones((3, 4))
    cost[1] = np.inf
    with pytest.raises(ValueError, match="no finite cell"):
        sinkhorn_log([cost], 0.1)
    with pytest.raises(ValueError, match="reg"):
        sinkhorn_log([np.ones((2, 2))], 0.0)
    assert sinkhorn_log([], 0.1) == []


def test_limit_threads_restores_the_setting():
    before = torch.get_num_threads()
    with limit_threads(10):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with limit_threads(SINGLE_THREAD_CELLS):
        assert torch.get_num_threads() == before


# ---------------------------------------------------------------------------
# invalid cells


def feasible_invalid_cost(shape, seed, fraction=0.3):
    """Random costs with ``fraction`` invalid cells, off a feasible support.

    The north-west-corner plan of the uniform marginals is feasible, so cells it
    uses stay valid and a plan avoiding the invalid ones always exists.
    """
    n, m = shape
    cost = random_cost(shape, seed)
    keep = np.zeros(shape, dtype=bool)
    row_left, col_left = np.full(n, float(m)), np.full(m, float(n))  # scaled by n m
    i = j = 0
    while i < n and j < m:
        keep[i, j] = True
        moved = min(row_left[i], col_left[j])
        row_left[i] -= moved
        col_left[j] -= moved
        if row_left[i] == 0:
            i += 1
        if col_left[j] == 0:
            j += 1
    rng = np.random.default_rng(seed + 100)
    drop = (rng.random(shape) < fraction) & ~keep
    cost[drop] = np.inf
    return cost, int(drop.sum())


@pytest.mark.parametrize("shape", [(4, 9), (9, 4), (8, 8), (15, 20)])
def test_invalid_cells_match_bounded_linprog(shape):
    cost, n_invalid = feasible_invalid_cost(shape, seed=shape[0])
    assert n_invalid > 0
    ws = wasserstein(cost)
    assert ws.feasible and ws.invalid_cells == n_invalid
    assert abs(ws.value - lp_reference(cost)) <= TOL
    check_plan(ws, cost, 1.0)
    for beta in BETAS:
        result = beta_wasserstein(cost, beta)
        assert result.invalid_cells == n_invalid
        assert abs(result.value - lp_reference(cost, beta)) <= TOL
        check_plan(result, cost, beta)
    assert abs(min_distance(cost) - lp_reference(cost, 0.0)) <= TOL
    # NaN marks an invalid cell exactly as inf does
    with_nan = np.where(np.isinf(cost), np.nan, cost)
    assert wasserstein(with_nan).value == ws.value
    # invalid cells get a zero kernel; reg relative to the valid cost range (a
    # sparse support slows Sinkhorn down, so reg stays moderate here)
    entropic = sinkhorn(cost, 0.1 * np.ptp(cost[np.isfinite(cost)]))
    assert entropic.converged and np.all(entropic.plan[np.isinf(cost)] == 0.0)
    assert entropic.gap >= -1e-9


def test_hall_violation_depends_on_beta():
    # particles 0 and 1 may only serve pair 0, which holds 1/3 of the mass
    inf = math.inf
    cost = np.array([[1.0, inf, inf], [2.0, inf, inf], [1.0, 3.0, 2.0]])
    assert not wasserstein(cost).feasible
    assert lp_reference(cost) == math.inf
    for beta in BETAS:
        result = beta_wasserstein(cost, beta)
        expected = lp_reference(cost, beta)
        feasible = 2 * beta / 3 <= 1 / 3  # mandatory mass of 0 and 1 fits in pair 0
        assert result.feasible == feasible == math.isfinite(expected), beta
        if feasible:
            assert abs(result.value - expected) <= TOL
            check_plan(result, cost, beta)
        else:
            assert result.value == math.inf and result.plan is None


def test_all_invalid_row_and_column():
    cost = random_cost((5, 6), seed=9)
    cost[2] = np.inf  # a particle whose every rollout failed
    ws = wasserstein(cost)
    assert not ws.feasible and ws.value == math.inf and ws.invalid_cells == 6
    assert beta_wasserstein(cost, 0.15).value == math.inf
    assert lp_reference(cost, 0.15) == math.inf
    # without mandatory mass the failed particle is simply never used
    assert beta_wasserstein(cost, 0.0).feasible
    assert abs(min_distance(cost) - lp_reference(cost, 0.0)) <= TOL
    cost = random_cost((5, 6), seed=9)
    cost[:, 4] = np.nan  # a test pair no particle can follow
    assert min_distance(cost) == math.inf
    for beta in BETAS:
        assert not beta_wasserstein(cost, beta).feasible
    result = sinkhorn(cost, 0.05)
    assert result.value == math.inf and math.isnan(result.gap)
    assert not result.converged


def test_average_errors_counts_invalid_cells():
    rng = np.random.default_rng(0)
    e_p, e_v, e_a = (rng.random((4, 5)) for _ in range(3))
    e_p[0, 0] = np.inf
    e_v[1, 2] = np.nan
    e_a[1, 2] = np.inf
    out = average_errors(e_p, e_v, e_a)
    valid = np.ones((4, 5), dtype=bool)
    valid[0, 0] = valid[1, 2] = False
    assert out["valid_cells"] == 18 and out["invalid_cells"] == 2
    for key, x in (("e_p", e_p), ("e_v", e_v), ("e_a", e_a)):
        assert out[key] == pytest.approx(x[valid].mean(), rel=1e-15)
    none_valid = average_errors(np.full((2, 2), np.inf), e_v[:2, :2], e_a[:2, :2])
    assert none_valid["valid_cells"] == 0 and math.isnan(none_valid["e_p"])


def test_evaluate_costs_keys_and_consistency():
    rng = np.random.default_rng(1)
    e_p, e_v, e_a = (rng.gamma(2.0, 1.0, (9, 6)) for _ in range(3))
    score = 0.5 * e_p + 0.3 * e_v + 0.2 * e_a
    score[3, 1] = np.inf  # invalid through the score only
    e_a[5, 2] = np.nan  # invalid through an error only
    out = evaluate_costs(score, e_p, e_v, e_a)
    assert set(out.to_json()) == {
        "e_p", "e_v", "e_a", "min", "beta_ws", "ws", "sinkhorn", "sinkhorn_gap",
        "sinkhorn_iterations", "sinkhorn_converged", "sinkhorn_marginal_error",
        "valid_cells", "invalid_cells", "n_particles", "n_test", "ws_valid",
        "beta_ws_valid", "particles_never_valid",
    }  # fmt: skip
    assert out.invalid_cells == 2 and out.valid_cells == 52
    assert (out.n_particles, out.n_test) == (9, 6)
    masked = score.copy()
    masked[5, 2] = np.inf
    assert out.ws == wasserstein(masked).value
    assert out.beta_ws == beta_wasserstein(masked, 0.15).value
    assert out.min == min_distance(masked)
    assert out.sinkhorn_gap == pytest.approx(out.sinkhorn - out.ws, abs=0)
    assert out.min <= out.beta_ws <= out.ws <= out.sinkhorn
    assert (out.ws_valid, out.beta_ws_valid) == (out.ws, out.beta_ws)
    assert out.particles_never_valid == 0
    assert out.sinkhorn_converged and out.sinkhorn_iterations > 0
    assert out.sinkhorn_marginal_error < 1e-9
    for key, value in out.to_json().items():
        expected = int if key in ("valid_cells", "invalid_cells") else None
        expected = int if key == "particles_never_valid" else expected
        expected = int if key.startswith("n_") else expected
        expected = int if key == "sinkhorn_iterations" else expected
        expected = bool if key == "sinkhorn_converged" else expected
        assert type(value) is (expected or float), key


def test_evaluate_cost_sets_equals_evaluate_costs_per_set():
    rng = np.random.default_rng(3)
    sets = []
    for n_particles in (9, 14, 5):
        e_p, e_v, e_a = (rng.gamma(2.0, 1.0, (n_particles, 6)) for _ in range(3))
        sets.append((0.5 * e_p + 0.3 * e_v + 0.2 * e_a, e_p, e_v, e_a))
    sets[2][0][1] = np.inf  # a particle invalid everywhere: WS infeasible
    steps = []
    together = evaluate_cost_sets(
        sets, sinkhorn_max_iter=500, callback=lambda *step: steps.append(step)
    )
    for one, out in zip(sets, together, strict=True):
        alone = evaluate_costs(*one, sinkhorn_max_iter=500)
        assert list(out.to_json()) == list(alone.to_json())
        for key, value in alone.to_json().items():
            assert getattr(out, key) == pytest.approx(value, rel=1e-13, nan_ok=True), (
                key
            )
    assert together[2].sinkhorn_iterations == 0
    assert not together[2].sinkhorn_converged
    assert steps[:3] == [("exact", 1, 3), ("exact", 2, 3), ("exact", 3, 3)]
    assert steps[-1][0] == "sinkhorn" and steps[-1][2] == 3


def test_ws_over_the_particles_valid_somewhere():
    """A particle invalid on every test pair makes SPEC's WS infinite; the
    report's second WS drops it (and only it) and counts it."""
    rng = np.random.default_rng(2)
    e_p, e_v, e_a = (rng.gamma(2.0, 1.0, (7, 5)) for _ in range(3))
    score = 0.5 * e_p + 0.3 * e_v + 0.2 * e_a
    score[4] = np.inf  # every rollout of particle 4 failed
    score[1, 3] = np.inf  # particle 1 failed on one pair only: kept
    out = evaluate_costs(score, e_p, e_v, e_a)
    assert out.ws == math.inf and out.beta_ws == math.inf
    kept = np.delete(score, 4, axis=0)
    assert out.ws_valid == pytest.approx(lp_reference(kept, 1.0), abs=TOL)
    assert out.beta_ws_valid == pytest.approx(lp_reference(kept, 0.15), abs=TOL)
    assert out.particles_never_valid == 1
    assert out.min == min_distance(score)  # unchanged: it never needed row 4
    # every particle invalid: nothing left to measure
    none = evaluate_costs(np.full((2, 3), np.inf), *(np.ones((2, 3)),) * 3)
    assert none.ws_valid == math.inf and none.particles_never_valid == 2


# ---------------------------------------------------------------------------
# input validation


@pytest.mark.parametrize(
    ("cost", "match"),
    [
        (np.ones(4), "2-D"),
        (np.ones((2, 2, 2)), "2-D"),
        (np.ones((0, 3)), "non-empty"),
        (np.array([[1.0, -np.inf]]), "-inf"),
    ],
)
def test_bad_cost_matrix(cost, match):
    for call in (wasserstein, min_distance, lambda c: beta_wasserstein(c, 0.1)):
        with pytest.raises(ValueError, match=match):
            call(cost)
    with pytest.raises(ValueError, match=match):
        sinkhorn(cost, 0.1)


@pytest.mark.parametrize("beta", [-0.1, 1.1, math.nan])
def test_bad_beta(beta):
    with pytest.raises(ValueError, match="beta"):
        beta_wasserstein(np.ones((2, 2)), beta)


@pytest.mark.parametrize("reg", [0.0, -1.0, math.inf, math.nan])
def test_bad_reg(reg):
    with pytest.raises(ValueError, match="reg"):
        sinkhorn(np.ones((2, 2)), reg)


def test_mismatched_shapes():
    with pytest.raises(ValueError, match="same shape"):
        average_errors(np.ones((2, 3)), np.ones((2, 3)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="same shape"):
        evaluate_costs(np.ones((2, 2)), *(np.ones((2, 3)),) * 3)
