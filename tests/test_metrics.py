"""Metrics against scipy's HiGHS solving the original LPs of SPEC section 6."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.optimize import linprog

from torchcf.evaluation.metrics import (
    average_errors,
    beta_wasserstein,
    evaluate_costs,
    min_distance,
    sinkhorn,
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
    assert set(out) == {
        "e_p", "e_v", "e_a", "min", "beta_ws", "ws", "sinkhorn", "sinkhorn_gap",
        "valid_cells", "invalid_cells", "n_particles", "n_test", "ws_valid",
        "beta_ws_valid", "particles_never_valid",
    }  # fmt: skip
    assert out["invalid_cells"] == 2 and out["valid_cells"] == 52
    assert (out["n_particles"], out["n_test"]) == (9, 6)
    masked = score.copy()
    masked[5, 2] = np.inf
    assert out["ws"] == wasserstein(masked).value
    assert out["beta_ws"] == beta_wasserstein(masked, 0.15).value
    assert out["min"] == min_distance(masked)
    assert out["sinkhorn_gap"] == pytest.approx(out["sinkhorn"] - out["ws"], abs=0)
    assert out["min"] <= out["beta_ws"] <= out["ws"] <= out["sinkhorn"]
    assert (out["ws_valid"], out["beta_ws_valid"]) == (out["ws"], out["beta_ws"])
    assert out["particles_never_valid"] == 0
    for key, value in out.items():
        expected = int if key in ("valid_cells", "invalid_cells") else None
        expected = int if key == "particles_never_valid" else expected
        expected = int if key.startswith("n_") else expected
        assert type(value) is (expected or float), key


def test_ws_over_the_particles_valid_somewhere():
    """A particle invalid on every test pair makes SPEC's WS infinite; the
    report's second WS drops it (and only it) and counts it."""
    rng = np.random.default_rng(2)
    e_p, e_v, e_a = (rng.gamma(2.0, 1.0, (7, 5)) for _ in range(3))
    score = 0.5 * e_p + 0.3 * e_v + 0.2 * e_a
    score[4] = np.inf  # every rollout of particle 4 failed
    score[1, 3] = np.inf  # particle 1 failed on one pair only: kept
    out = evaluate_costs(score, e_p, e_v, e_a)
    assert out["ws"] == math.inf and out["beta_ws"] == math.inf
    kept = np.delete(score, 4, axis=0)
    assert out["ws_valid"] == pytest.approx(lp_reference(kept, 1.0), abs=TOL)
    assert out["beta_ws_valid"] == pytest.approx(lp_reference(kept, 0.15), abs=TOL)
    assert out["particles_never_valid"] == 1
    assert out["min"] == min_distance(score)  # unchanged: it never needed row 4
    # every particle invalid: nothing left to measure
    none = evaluate_costs(np.full((2, 3), np.inf), *(np.ones((2, 3)),) * 3)
    assert none["ws_valid"] == math.inf and none["particles_never_valid"] == 2


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
