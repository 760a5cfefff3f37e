"""Evaluation metrics of a learned particle set on test pairs (SPEC section 6).

Every metric reads the cost matrix ``C: (P, N)``: the score of particle ``i`` on test
pair ``j`` (P particles, N test pairs). ``C`` may be a numpy array or a torch tensor of
any float dtype; everything is computed in float64 numpy (Sinkhorn runs in float64
torch, see :mod:`torchcf.evaluation.entropic`).

- :func:`average_errors`: means of ``e_p, e_v, e_a`` over the valid cells;
- :func:`wasserstein`: exact ``min <gamma, C>`` with particle marginals ``1/P`` and
  pair marginals ``1/N`` (POT's network simplex, ``ot.emd``);
- :func:`beta_wasserstein`: particle marginals ``>= beta / P`` instead, solved
  exactly as a balanced ``(P + 1, N)`` problem (proof in its docstring);
- :func:`min_distance`: ``beta = 0``, the mean over pairs of the best particle's cost;
- :func:`sinkhorn`: the entropic approximation of WS, with its gap to the exact value
  (:func:`sinkhorn_many`: several cost matrices in one batched solve);
- :func:`evaluate_costs`: all of the above as one
  :class:`~torchcf.runs.metrics.SetMetrics` record
  (:func:`evaluate_cost_sets`: several learned sets, their Sinkhorn batched).

**Invalid cells.** An invalid rollout scores ``+inf`` (NaN is read the same way). No
cell is ever dropped: a transport plan may not use an invalid cell, and when no plan
avoids them the metric is ``+inf`` with ``feasible=False``. The solver sees invalid
cells as a finite big-M cost (:func:`_big_m`, with the argument why every plan that
uses one is worse than every plan that avoids them), and a plan that still puts mass
on one proves the restricted problem infeasible. Consequences worth knowing:

- a particle whose every cell is invalid cannot carry its mandatory mass, so WS and
  beta-WS with ``beta > 0`` are ``+inf``; minimum distance ignores it;
- a test pair whose every cell is invalid makes every metric ``+inf``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import fields
from typing import NamedTuple

import numpy as np
import ot
import torch
from torch import Tensor

from ..runs.metrics import SetMetrics
from .entropic import sinkhorn_log

#: Mass on a forbidden cell above this proves infeasibility (below it is rounding).
FORBIDDEN_MASS_TOL = 1e-12
#: Network-simplex pivots allowed before ``ot.emd`` gives up (it then raises here).
EMD_MAX_ITER = 10_000_000
#: POT's ``result_code`` for an optimal network-simplex solution.
_EMD_OPTIMAL = 1

CostMatrix = np.ndarray | Tensor


class TransportResult(NamedTuple):
    """An exact transport metric.

    Attributes:
        value: ``<plan, C>``; ``inf`` when infeasible.
        plan: (P, N) optimal plan of the original problem (total mass 1), or ``None``
            when infeasible.
        invalid_cells: number of invalid (``inf``/NaN) cells of ``C``.
        feasible: whether a plan avoiding every invalid cell exists.
        particle_mass: (P,) row sums of ``plan`` (which particles carry mass), or
            ``None`` when infeasible.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import wasserstein
        >>> result = wasserstein(C)
        >>> round(result.value, 3), result.feasible, result.invalid_cells
        (1.0, True, 0)
        >>> result.plan.round(3).tolist()  # each particle 1/2, each pair 1/3
        [[0.333, 0.167, 0.0], [0.0, 0.167, 0.333]]
    """

    value: float
    plan: np.ndarray | None
    invalid_cells: int
    feasible: bool
    particle_mass: np.ndarray | None = None


class SinkhornResult(NamedTuple):
    """Entropic transport next to the exact Wasserstein value.

    Attributes:
        value: transport cost ``<gamma_reg, C>`` of the entropic plan (not the
            entropic objective, which also holds ``-reg H(gamma)``).
        ws: exact WS of the same ``C`` (:func:`wasserstein`).
        gap: ``value - ws`` (``>= 0`` up to the marginal tolerance); NaN when
            infeasible.
        converged: whether the pair-marginal error fell below ``stop_thr``.
        n_iter: Sinkhorn iterations run (0 when infeasible).
        marginal_error: L2 error of the pair marginals of ``plan`` (tested every
            10 iterations and at the last one); NaN when infeasible.
        reg: the entropic regularisation used, in the units of ``C``.
        plan: (P, N) entropic plan, or ``None`` when infeasible.
        invalid_cells: number of invalid cells of ``C``.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import sinkhorn
        >>> result = sinkhorn(C, reg=0.05)
        >>> round(result.value, 3), round(result.ws, 3), result.converged
        (1.0, 1.0, True)
        >>> bool(abs(result.gap) < 1e-6), result.plan.shape
        (True, (2, 3))
    """

    value: float
    ws: float
    gap: float
    converged: bool
    n_iter: int
    marginal_error: float
    reg: float
    plan: np.ndarray | None
    invalid_cells: int


# ---------------------------------------------------------------------------
# input handling


def _as_matrix(x: CostMatrix, name: str) -> np.ndarray:
    """``x`` as a float64 (P, N) numpy array with every invalid cell set to ``+inf``."""
    if isinstance(x, Tensor):
        x = x.detach().cpu().to(torch.float64).numpy()
    array = np.array(x, dtype=np.float64)  # a copy: the caller's array is never touched
    if array.ndim != 2:
        raise ValueError(f"{name} must be 2-D (P, N), got shape {array.shape}")
    if array.size == 0:
        raise ValueError(f"{name} must be non-empty, got shape {array.shape}")
    if np.any(array == -np.inf):
        # -inf is no invalid rollout: it would make every metric -inf, so it is a bug
        raise ValueError(f"{name} holds -inf; invalid cells must be +inf or NaN")
    array[np.isnan(array)] = np.inf
    return array


def _check_beta(beta: float) -> float:
    beta = float(beta)
    if not 0.0 <= beta <= 1.0:  # also rejects NaN
        raise ValueError(f"beta must be in [0, 1], got {beta}")
    return beta


def _check_reg(reg: float) -> float:
    reg = float(reg)
    if not (reg > 0.0 and math.isfinite(reg)):
        raise ValueError(f"reg must be a finite number > 0, got {reg}")
    return reg


def _plan_value(plan: np.ndarray, cost: np.ndarray, valid: np.ndarray) -> float:
    """``<plan, cost>`` over the valid cells (the plan is 0 on the others)."""
    return float(np.vdot(plan, np.where(valid, cost, 0.0)))


# ---------------------------------------------------------------------------
# balanced transport with forbidden cells


def _emd(a: np.ndarray, b: np.ndarray, cost: np.ndarray, max_iter: int) -> np.ndarray:
    """Exact balanced plan of ``min <gamma, cost>`` by POT's network simplex.

    Raises instead of returning a non-optimal plan: POT only *warns* when the
    simplex stops early (``numItermax``) or reports infeasible/unbounded.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plan, log = ot.emd(a, b, cost, numItermax=max_iter, log=True)
    if log["result_code"] != _EMD_OPTIMAL:
        raise RuntimeError(
            f"ot.emd did not reach optimality (result_code {log['result_code']}: "
            f"{log['warning']}); raise max_iter (now {max_iter})"
        )
    for warning in caught:  # anything else POT had to say is unexpected here
        warnings.warn_explicit(
            warning.message, warning.category, warning.filename, warning.lineno
        )
    return np.asarray(plan, dtype=np.float64)


def _big_m(cost: np.ndarray, valid: np.ndarray) -> float:
    """A finite cost for forbidden cells that no optimal plan will ever pay.

    Claim: with ``c_max, c_min`` the extreme valid costs, ``R = c_max - c_min``,
    and ``k = min(rows, cols)``, any ``M > c_max + (k - 1) R`` makes every plan with
    forbidden mass ``f > 0`` strictly worse than the best plan avoiding forbidden
    cells, whenever one exists, *whatever the marginals* (so the same ``M`` serves
    beta-WS, whose marginals are not multiples of ``1 / (P N)``).

    Proof (repair by augmenting paths): take a plan ``gamma`` with forbidden mass
    ``f`` and drop that mass. What is left is a flow of value ``1 - f`` in the
    network source -> rows (capacity ``a``) -> valid cells -> columns (capacity
    ``b``) -> sink, whose max flow is 1 because a valid plan exists. So its residual
    network carries an extra flow of value ``f``, which decomposes into simple
    augmenting paths (cycles can be dropped). A simple path alternates ``k' <= k``
    forward valid cells (cost ``<= c_max`` per unit) and ``k' - 1`` backward ones
    (cost ``<= -c_min``), so augmenting adds at most ``f (c_max + (k - 1) R)``: a
    valid plan costing at most ``<gamma, C>_valid + f (c_max + (k - 1) R)``, which
    is below ``<gamma, C>_valid + f M`` for the ``M`` above.

    ``M`` is kept as small as the bound allows (``k + 1`` spans, not ``P N``)
    because the simplex potentials then carry ``M`` and its rounding.
    """
    valid_costs = cost[valid]
    c_max, c_min = float(valid_costs.max()), float(valid_costs.min())
    span = max(c_max - c_min, abs(c_max), abs(c_min)) or 1.0  # > 0 and >= R
    k = min(cost.shape)
    return c_max + (k + 1) * span


def _solve_restricted(
    a: np.ndarray, b: np.ndarray, cost: np.ndarray, max_iter: int
) -> np.ndarray | None:
    """Exact plan of the balanced problem that avoids the ``inf`` cells of ``cost``.

    Args:
        a: (P',) row masses (P' = P, or P + 1 with beta-WS's free row); b: (N,)
            column masses (same total).
        cost: (P', N) costs, ``inf`` = forbidden.
        max_iter: network-simplex pivots allowed.

    Returns:
        (P', N) optimal plan, or ``None`` when no plan avoids the forbidden cells.
    """
    valid = np.isfinite(cost)
    if valid.all():
        return _emd(a, b, cost, max_iter)
    # Cheap exact certificates first: a row or column with mass but no valid cell.
    if np.any(~valid.any(axis=1) & (a > 0)) or np.any(~valid.any(axis=0) & (b > 0)):
        return None
    plan = _emd(a, b, np.where(valid, cost, _big_m(cost, valid)), max_iter)
    # By _big_m an optimal plan has no forbidden mass when a valid plan exists; the
    # simplex returns a vertex, so mass there is exact zero unless infeasible. (For
    # WS a vertex carries multiples of 1 / (P N) >= 1e-12 for P N <= 1e12; a beta-WS
    # Hall deficit below FORBIDDEN_MASS_TOL would be read as rounding.)
    if plan[~valid].max(initial=0.0) > FORBIDDEN_MASS_TOL:
        return None
    plan[~valid] = 0.0
    return plan


# ---------------------------------------------------------------------------
# public metrics


def average_errors(e_p: CostMatrix, e_v: CostMatrix, e_a: CostMatrix) -> dict:
    """Means of the RMSE matrices over the valid cells (SPEC section 6).

    A cell is valid when all three errors are finite; the invalid ones are counted,
    never dropped silently.

    Args:
        e_p: (P, N) position RMSE [m]; e_v: (P, N) speed RMSE [m/s];
        e_a: (P, N) acceleration RMSE [m/s^2].

    Returns:
        ``{"e_p", "e_v", "e_a"}`` means (float, NaN when no cell is valid) and
        ``{"valid_cells", "invalid_cells"}`` (int).

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import average_errors
        >>> C[0, 0] = np.inf  # an invalid rollout: excluded, and counted
        >>> means = average_errors(C, C / 10, C / 100)  # e_p [m], e_v [m/s], e_a
        >>> round(means["e_p"], 3), means["valid_cells"], means["invalid_cells"]
        (1.7, 5, 1)
    """
    errors = _stack_errors(e_p, e_v, e_a)  # (3, P, N)
    return _masked_means(errors, np.isfinite(errors).all(axis=0))


def _stack_errors(e_p: CostMatrix, e_v: CostMatrix, e_a: CostMatrix) -> np.ndarray:
    arrays = [
        _as_matrix(x, name) for x, name in ((e_p, "e_p"), (e_v, "e_v"), (e_a, "e_a"))
    ]
    if len({x.shape for x in arrays}) != 1:
        shapes = [x.shape for x in arrays]
        raise ValueError(f"e_p, e_v, e_a must have the same shape, got {shapes}")
    return np.stack(arrays)  # (3, P, N)


def _masked_means(errors: np.ndarray, valid: np.ndarray) -> dict:
    n_valid = int(valid.sum())
    means = (
        np.where(valid, errors, 0.0).sum(axis=(1, 2)) / n_valid
        if n_valid
        else np.full(3, np.nan)
    )
    return {
        "e_p": float(means[0]),
        "e_v": float(means[1]),
        "e_a": float(means[2]),
        "valid_cells": n_valid,
        "invalid_cells": int(valid.size - n_valid),
    }


def wasserstein(
    C: CostMatrix,
    *,
    max_iter: int = EMD_MAX_ITER,
    pair_mass: np.ndarray | None = None,
) -> TransportResult:
    """Exact Wasserstein distance between the particle set and the test pairs.

    ``WS = min_gamma sum_ij gamma_ij C_ij`` s.t. ``sum_j gamma_ij = 1/P``,
    ``sum_i gamma_ij = 1/N``, ``gamma >= 0``, and ``gamma_ij = 0`` on invalid cells.
    Solved by POT's network simplex (``ot.emd``) in float64.

    Args:
        C: (P, N) cost matrix; ``inf``/NaN = invalid cell.
        max_iter: network-simplex pivots allowed; reaching it raises RuntimeError.
        pair_mass: (N,) pair marginals instead of ``1/N`` (:func:`_pair_mass`).

    Returns:
        :class:`TransportResult`; ``value = inf, feasible = False`` when no plan
        avoids the invalid cells (e.g. a particle whose every cell is invalid).

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import wasserstein
        >>> round(wasserstein(C).value, 3)
        1.0
        >>> C[:, 0] = np.inf  # a pair no particle follows validly: infeasible
        >>> wasserstein(C).value, wasserstein(C).feasible
        (inf, False)
    """
    cost = _as_matrix(C, "C")
    n_particles, n_test = cost.shape
    valid = np.isfinite(cost)
    invalid = int(valid.size - valid.sum())
    a = np.full(n_particles, 1.0 / n_particles)
    b, used = _pair_mass(pair_mass, n_test)
    plan = _solve_restricted(a, b[used], cost[:, used], max_iter)
    if plan is None:
        return TransportResult(math.inf, None, invalid, False, None)
    plan = _widen(plan, used)
    return TransportResult(
        _plan_value(plan, cost, valid), plan, invalid, True, plan.sum(axis=1)
    )


def beta_wasserstein(
    C: CostMatrix,
    beta: float = 0.15,
    *,
    max_iter: int = EMD_MAX_ITER,
    pair_mass: np.ndarray | None = None,
) -> TransportResult:
    """beta-Wasserstein distance: every particle carries at least ``beta / P``.

    The original LP (SPEC section 6):
    ``min_gamma <gamma, C>`` s.t. ``sum_i gamma_ij = 1/N`` (pairs),
    ``sum_j gamma_ij >= beta/P`` (particles), ``gamma >= 0``, ``gamma = 0`` on
    invalid cells. ``beta = 1`` is WS, ``beta = 0`` the minimum distance.

    **Exact reduction to a balanced problem.** Let ``c_j = min_{valid i} C_ij`` be
    the cost of pair ``j``'s best particle. The balanced ``(P + 1, N)`` problem has
    rows ``i < P`` of mass ``beta/P`` with costs ``C_ij`` and one *free* row of mass
    ``1 - beta`` with costs ``c_j``; its optimum equals the original one:

    - (original >= reduced) Take a feasible ``gamma`` with row sums
      ``r_i = beta/P + s_i``, ``s_i >= 0``, ``sum_i s_i = 1 - beta``. Split each row
      proportionally, ``gamma = gamma^m + gamma^f`` with
      ``gamma^f_ij = gamma_ij s_i / r_i``: ``gamma^m`` has row sums ``beta/P`` and
      ``gamma^f`` total mass ``1 - beta``. Collapsing ``gamma^f`` onto the free row,
      ``f_j = sum_i gamma^f_ij``, gives a reduced plan ``(gamma^m, f)`` whose cost
      ``<gamma^m, C> + sum_j f_j c_j <= <gamma, C>`` since ``c_j <= C_ij`` on valid
      cells.
    - (original <= reduced) Lifting a reduced plan by moving ``f_j`` onto the cell
      ``(argmin_i C_ij, j)`` gives a feasible original plan (rows ``>= beta/P``,
      columns ``1/N``, valid cells only) with the same cost.

    So one network simplex on ``(P + 1) x N`` solves it, and the lifted plan is
    optimal for the original LP. ``beta = 1`` drops the free row (plain WS);
    ``beta = 0`` needs no particle rows: the free row alone gives
    ``mean_j c_j``. An all-invalid particle makes ``beta > 0`` infeasible (its
    mandatory mass has nowhere to go); an all-invalid pair makes every beta
    infeasible.

    Args:
        C: (P, N) cost matrix; ``inf``/NaN = invalid cell.
        beta: minimum share of the mass on each particle, times ``P``; in [0, 1].
        max_iter: network-simplex pivots allowed; reaching it raises RuntimeError.
        pair_mass: (N,) pair marginals instead of ``1/N`` (:func:`_pair_mass`).

    Returns:
        :class:`TransportResult` whose ``plan`` is the lifted (P, N) plan and
        ``particle_mass`` its row sums: ``beta/P`` plus the free mass of the pairs
        for which the particle is the (lowest-index) best.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import beta_wasserstein
        >>> [round(beta_wasserstein(C, beta).value, 3) for beta in (0.0, 0.5, 1.0)]
        [0.833, 0.833, 1.0]
        >>> beta_wasserstein(C, 0.5).particle_mass.round(3).tolist()  # each >= 0.25
        [0.333, 0.667]
    """
    beta = _check_beta(beta)
    if beta == 1.0:
        return wasserstein(C, max_iter=max_iter, pair_mass=pair_mass)
    cost = _as_matrix(C, "C")
    n_particles, n_test = cost.shape
    valid = np.isfinite(cost)
    invalid = int(valid.size - valid.sum())
    b, used = _pair_mass(pair_mass, n_test)
    best = np.argmin(cost, axis=0)  # (N,) lowest index among ties; inf only if no valid
    best_cost = cost[best, np.arange(n_test)]  # (N,)
    if not np.isfinite(best_cost[used]).all():
        return TransportResult(math.inf, None, invalid, False, None)

    if beta == 0.0:
        reduced = b[None, :]  # the free row alone (1, N)
    else:
        a = np.append(np.full(n_particles, beta / n_particles), 1.0 - beta)  # (P+1,)
        free_cost = np.vstack([cost, best_cost[None, :]])  # (P + 1, N)
        reduced = _solve_restricted(a, b[used], free_cost[:, used], max_iter)
        if reduced is None:
            return TransportResult(math.inf, None, invalid, False, None)
        reduced = _widen(reduced, used)
    # Lift: the free row's mass goes to each pair's best particle.
    plan = np.zeros((n_particles, n_test))
    plan[: reduced.shape[0] - 1] = reduced[:-1]
    np.add.at(plan, (best, np.arange(n_test)), reduced[-1])
    return TransportResult(
        _plan_value(plan, cost, valid), plan, invalid, True, plan.sum(axis=1)
    )


def _pair_mass(
    pair_mass: np.ndarray | None, n_test: int
) -> tuple[np.ndarray, np.ndarray]:
    """The pair marginals ``b`` (N,) and which pairs carry mass ``used`` (N,) bool.

    ``None`` gives the uniform ``1/N`` of SPEC section 6. Other marginals serve
    the bootstrap over pairs (:mod:`torchcf.evaluation.bootstrap`): a resample
    that draws pair ``j`` ``k_j`` times is the cost matrix with column ``j``
    repeated ``k_j`` times, each at mass ``1/N``; merging identical columns
    (their masses add) changes no optimum, so it is ``pair_mass = k / N`` here,
    and a pair never drawn carries no mass (its column, invalid cells included,
    is left out of the solve).
    """
    if pair_mass is None:
        return np.full(n_test, 1.0 / n_test), np.ones(n_test, dtype=bool)
    b = np.asarray(pair_mass, dtype=np.float64)
    if b.shape != (n_test,) or np.any(~(b >= 0)) or not math.isclose(b.sum(), 1.0):
        raise ValueError(
            f"pair_mass must be ({n_test},) non-negative and sum to 1, got {b}"
        )
    return b, b > 0


def _widen(plan: np.ndarray, used: np.ndarray) -> np.ndarray:
    """A plan over the ``used`` pairs as one over all (zero on the others)."""
    if used.all():
        return plan
    out = np.zeros((plan.shape[0], len(used)))
    out[:, used] = plan
    return out


def min_distance(C: CostMatrix) -> float:
    """Minimum distance: the mean over test pairs of the best particle's cost.

    ``MD = (1/N) sum_j min_{valid i} C_ij`` (beta-WS with ``beta = 0``).

    Args:
        C: (P, N) cost matrix; ``inf``/NaN = invalid cell.

    Returns:
        The mean; ``inf`` when some pair has no valid cell.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import min_distance
        >>> round(min_distance(C), 3)  # (1 + 1 + 0.5) / 3
        0.833
    """
    cost = _as_matrix(C, "C")
    return float(cost.min(axis=0).mean())


def sinkhorn(
    C: CostMatrix,
    reg: float,
    *,
    max_iter: int = 100_000,
    stop_thr: float = 1e-9,
) -> SinkhornResult:
    """Entropic (Sinkhorn) approximation of WS, with its gap to the exact value.

    ``gamma_reg = argmin <gamma, C> - reg H(gamma)`` over the same uniform marginals
    as :func:`wasserstein` (``1/P`` per particle, ``1/N`` per test pair), by the
    log-domain Sinkhorn of :func:`torchcf.evaluation.entropic.sinkhorn_log`
    (over-relaxed; it stays finite for small ``reg``). Reported: the transport
    cost ``<gamma_reg, C>``, which decreases to WS as ``reg -> 0``; on a converged
    problem it is POT's ``ot.sinkhorn(..., method="sinkhorn_log")`` value up to the
    marginal tolerance (the tests hold it to that).

    ``reg`` is in the units of ``C`` (score units) and is used as given, never
    rescaled by the cost range: the gap depends on ``reg / (range of C)``.
    Invalid cells get zero kernel (``exp(-inf) = 0``), i.e. they are forbidden as in
    WS; when WS is infeasible Sinkhorn is not run (value ``inf``, gap NaN).

    Args:
        C: (P, N) cost matrix; ``inf``/NaN = invalid cell.
        reg: entropic regularisation, > 0, in the units of ``C``.
        max_iter: Sinkhorn iterations allowed.
        stop_thr: stop when the L2 error of the pair marginals is below this.

    Returns:
        :class:`SinkhornResult`; ``converged=False`` when ``max_iter`` ran out
        (the value is still the last iterate's transport cost).

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import sinkhorn
        >>> result = sinkhorn(C, reg=0.05)  # reg in the units of C
        >>> round(result.value, 3), result.converged
        (1.0, True)
    """
    return sinkhorn_many([C], reg, max_iter=max_iter, stop_thr=stop_thr)[0]


def sinkhorn_many(
    costs: Sequence[CostMatrix],
    reg: float,
    *,
    max_iter: int = 100_000,
    stop_thr: float = 1e-9,
    callback: Callable[[int, int], None] | None = None,
) -> list[SinkhornResult]:
    """:func:`sinkhorn` of several cost matrices (any shapes), solved in one
    batched call; each result equals that of :func:`sinkhorn` on its own matrix
    (up to rounding), iterations included.

    Args:
        costs: (P_b, N_b) cost matrices; ``inf``/NaN = invalid cell.
        reg: the entropic regularisation, as :func:`sinkhorn`.
        max_iter: the iteration cap, as :func:`sinkhorn`.
        stop_thr: the marginal error that stops, as :func:`sinkhorn`.
        callback: ``(iterations, matrices done)`` at every stopping test (for a
            progress bar); an infeasible matrix (never solved) counts as done.

    Returns:
        one :class:`SinkhornResult` per matrix, in order.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import sinkhorn_many
        >>> results = sinkhorn_many([C, C[:, :2]], reg=0.05)  # any shapes
        >>> [round(r.value, 3) for r in results], [r.converged for r in results]
        ([1.0, 1.0], [True, True])
    """
    reg = _check_reg(reg)
    matrices = [_as_matrix(c, "C") for c in costs]
    exact = [wasserstein(cost) for cost in matrices]
    feasible = [k for k, ws in enumerate(exact) if ws.feasible]
    skipped = len(matrices) - len(feasible)
    plans = sinkhorn_log(
        [matrices[k] for k in feasible], reg,
        max_iter=max_iter, stop_thr=stop_thr,
        callback=None if callback is None else lambda i, n: callback(i, skipped + n),
    )  # fmt: skip
    solved = dict(zip(feasible, plans, strict=True))
    results = []
    for k, ws in enumerate(exact):
        if k not in solved:  # WS infeasible: Sinkhorn is not run
            results.append(
                SinkhornResult(
                    value=math.inf,
                    ws=math.inf,
                    gap=math.nan,
                    converged=False,
                    n_iter=0,
                    marginal_error=math.nan,
                    reg=reg,
                    plan=None,
                    invalid_cells=ws.invalid_cells,
                )
            )
            continue
        entropic = solved[k]
        results.append(
            SinkhornResult(
                value=entropic.value,
                ws=ws.value,
                gap=entropic.value - ws.value,
                converged=entropic.converged,
                n_iter=entropic.n_iter,
                marginal_error=entropic.marginal_error,
                reg=reg,
                plan=entropic.plan,
                invalid_cells=ws.invalid_cells,
            )
        )
    return results


def evaluate_costs(
    score: CostMatrix,
    e_p: CostMatrix,
    e_v: CostMatrix,
    e_a: CostMatrix,
    beta: float = 0.15,
    sinkhorn_reg: float = 0.05,
    sinkhorn_max_iter: int = 10_000,
) -> SetMetrics:
    """Every SPEC section 6 metric of one learned set on one test split.

    A cell is invalid when its score or any of its errors is not finite (an invalid
    rollout); the same cells are excluded from the averages and forbidden in the
    transport metrics, so the counts agree.

    Args:
        score: (P, N) scores ``g``; e_p, e_v, e_a: (P, N) RMSEs [m, m/s, m/s^2].
        beta: beta of beta-WS, in [0, 1].
        sinkhorn_reg: Sinkhorn regularisation in score units (> 0).
        sinkhorn_max_iter: Sinkhorn iteration cap (config ``eval.sinkhorn_max_iter``).

    Returns:
        :class:`SetMetrics`: ``e_p, e_v, e_a, min, beta_ws, ws, sinkhorn,
        sinkhorn_gap`` (float; ``inf`` when infeasible, NaN for an undefined
        mean or gap); ``valid_cells, invalid_cells, n_particles, n_test`` (int);
        the Sinkhorn solve's ``sinkhorn_iterations`` (int, 0 when WS is
        infeasible), ``sinkhorn_converged`` (bool) and
        ``sinkhorn_marginal_error`` (float, the L2 error of its pair marginals);
        and, because one particle invalid on every test pair makes SPEC's WS and
        beta-WS infinite whatever the rest of the set does, the same two over
        the particles valid on some test pair, ``ws_valid`` and
        ``beta_ws_valid`` (equal to ``ws`` and ``beta_ws`` when no particle is
        dropped; ``inf`` still where a test pair has no valid particle), with
        ``particles_never_valid`` (int) the number dropped.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import evaluate_costs
        >>> metrics = evaluate_costs(C, e_p=C, e_v=C / 10, e_a=C / 100)
        >>> round(metrics.ws, 3), round(metrics.beta_ws, 3), round(metrics.min, 3)
        (1.0, 0.833, 0.833)
        >>> metrics.n_particles, metrics.n_test, metrics.invalid_cells
        (2, 3, 0)
    """
    return evaluate_cost_sets(
        [(score, e_p, e_v, e_a)],
        beta=beta,
        sinkhorn_reg=sinkhorn_reg,
        sinkhorn_max_iter=sinkhorn_max_iter,
    )[0]


def evaluate_cost_sets(
    sets: Sequence[tuple[CostMatrix, CostMatrix, CostMatrix, CostMatrix]],
    beta: float = 0.15,
    sinkhorn_reg: float = 0.05,
    sinkhorn_max_iter: int = 10_000,
    *,
    callback: Callable[[str, int, int], None] | None = None,
) -> list[SetMetrics]:
    """:func:`evaluate_costs` of several learned sets (``(score, e_p, e_v, e_a)``
    each, any shapes), their Sinkhorn solved in one batched call.

    Args:
        sets: per learned set, (P_s, N) score and RMSE matrices.
        beta: the beta of beta-WS, as :func:`evaluate_costs`.
        sinkhorn_reg: as :func:`evaluate_costs`.
        sinkhorn_max_iter: as :func:`evaluate_costs`.
        callback: progress, called as ``("exact", sets done, len(sets))`` after
            each set's exact metrics and ``("sinkhorn", iterations, problems
            done)`` at every Sinkhorn stopping test.

    Returns:
        one :func:`evaluate_costs` record per set, in order.

    Examples:
        >>> import numpy as np
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N): 2 particles
        >>> from torchcf.evaluation.metrics import evaluate_cost_sets
        >>> one, other = C, C[:1]  # two learned sets: 2 and 1 particles
        >>> found = evaluate_cost_sets([(one,) * 4, (other,) * 4])
        >>> [round(m.ws, 3) for m in found], [m.n_particles for m in found]
        ([1.0, 2.0], [2, 1])
    """
    beta = _check_beta(beta)
    sinkhorn_reg = _check_reg(sinkhorn_reg)
    costs, outs = [], []
    for done, (score, e_p, e_v, e_a) in enumerate(sets, start=1):
        cost, out = _exact_metrics(score, e_p, e_v, e_a, beta)
        costs.append(cost)
        outs.append(out)
        if callback is not None:
            callback("exact", done, len(sets))
    entropic = sinkhorn_many(
        costs,
        sinkhorn_reg,
        max_iter=sinkhorn_max_iter,
        callback=None if callback is None else lambda i, n: callback("sinkhorn", i, n),
    )
    for out, result in zip(outs, entropic, strict=True):
        out.update(
            ws=result.ws,
            sinkhorn=result.value,
            sinkhorn_gap=result.gap,
            sinkhorn_iterations=result.n_iter,
            sinkhorn_converged=result.converged,
            sinkhorn_marginal_error=result.marginal_error,
        )
        if out["particles_never_valid"] == 0:
            out["ws_valid"] = out["ws"]
    keys = [f.name for f in fields(SetMetrics)]
    return [SetMetrics(**{key: out[key] for key in keys}) for out in outs]


def _exact_metrics(
    score: CostMatrix,
    e_p: CostMatrix,
    e_v: CostMatrix,
    e_a: CostMatrix,
    beta: float,
) -> tuple[np.ndarray, dict]:
    """The cost matrix with every invalid cell at ``inf``, and the metrics of
    :func:`evaluate_costs` except WS and Sinkhorn (which :func:`sinkhorn_many`
    returns together; ``ws_valid`` is set here only when particles were dropped)."""
    cost = _as_matrix(score, "score")
    errors = _stack_errors(e_p, e_v, e_a)  # (3, P, N)
    if errors.shape[1:] != cost.shape:
        raise ValueError(
            f"score {cost.shape} and errors {errors.shape[1:]} must have the same shape"
        )
    valid = np.isfinite(cost) & np.isfinite(errors).all(axis=0)  # (P, N)
    cost[~valid] = np.inf
    out = _masked_means(errors, valid)
    out.update(
        min=min_distance(cost),
        beta_ws=beta_wasserstein(cost, beta).value,
        n_particles=int(cost.shape[0]),
        n_test=int(cost.shape[1]),
    )
    somewhere = valid.any(axis=1)  # (P,) valid on some test pair
    dropped = int((~somewhere).sum())
    if dropped == 0:
        out["beta_ws_valid"] = out["beta_ws"]  # ws_valid follows with ws
    elif dropped == cost.shape[0]:
        out.update(ws_valid=math.inf, beta_ws_valid=math.inf)
    else:
        kept = cost[somewhere]
        out.update(
            ws_valid=wasserstein(kept).value,
            beta_ws_valid=beta_wasserstein(kept, beta).value,
        )
    out["particles_never_valid"] = dropped
    return cost, out


__all__ = [
    "EMD_MAX_ITER",
    "FORBIDDEN_MASS_TOL",
    "SinkhornResult",
    "TransportResult",
    "average_errors",
    "beta_wasserstein",
    "evaluate_cost_sets",
    "evaluate_costs",
    "min_distance",
    "sinkhorn",
    "sinkhorn_many",
    "wasserstein",
]
