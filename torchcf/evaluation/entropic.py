"""Entropic optimal transport: a batched, log-domain Sinkhorn in float64 torch.

One problem ``b`` is a cost matrix ``C_b: (P_b, N_b)`` (P particles, N test pairs)
with uniform marginals ``a = 1/P_b``, ``b = 1/N_b`` and forbidden cells ``+inf``.
The entropic plan at regularisation ``reg`` (``eps`` below)

    gamma = argmin_{gamma 1 = a, gamma^T 1 = b} <gamma, C> - eps H(gamma)

is ``gamma_ij = exp(u_i + v_j - C_ij / eps)`` for the scaled dual potentials
``u: (P,)``, ``v: (N,)`` that solve the marginal equations; a forbidden cell has
zero kernel ``exp(-inf) = 0``, so it carries no mass. Sinkhorn solves them by
alternate exact updates, in the log domain so that small ``eps`` never
under/overflows (``LSE`` = log-sum-exp):

    v_j <- log b_j - LSE_i(u_i - C_ij / eps)        (columns exact)
    u_i <- log a_i - LSE_j(v_j - C_ij / eps)        (rows exact)

which is what POT's ``ot.sinkhorn(..., method="sinkhorn_log")`` iterates, from the
same start ``u = v = 0``. Three things bound the time it takes:

- **Over-relaxation.** Plain Sinkhorn converges linearly with a rate ``theta``
  that tends to 1 as ``eps`` shrinks against the cost range (the smoke run's IDM
  set: 3271 iterations). Each update is instead extrapolated,
  ``x <- x + omega (x_exact - x)``, with ``omega = 2 / (1 + sqrt(1 - theta))``,
  Young's optimal SOR parameter for a Gauss-Seidel rate ``theta`` (Thibault et al.
  2021, *Overrelaxed Sinkhorn-Knopp*, Algorithms 14:143; Lehmann et al. 2022,
  Optim. Lett. 16:2209), whose rate ``omega - 1 ~ 1 - 2 sqrt(1 - theta)`` needs
  about the square root of the iterations. ``theta`` is read off the marginal
  error of the first plain iterations, per problem; an error that grows between
  two checks halves ``omega - 1`` (a safeguard: SOR's global convergence is only
  proven for a range of ``omega`` that depends on the unknown kernel).
- **Checks every k iterations.** The stopping test (the pair-marginal error of
  the plan after an exact row update, as POT's) costs a full ``exp`` of the
  matrix, so it runs every ``check_every`` iterations, and always at the last.
- **Batching.** Problems of different shapes are padded to one ``(B, P, N)``
  tensor with forbidden cells and zero-mass rows/columns, so one iteration is a
  handful of torch calls whatever ``B``; a problem leaves the batch when it
  converges (its result is then exactly that of a solve on its own, up to
  rounding), and the padding shrinks with the batch.

Epsilon-scaling (``eps`` halved from the cost range down to the target, the
potentials warm-started) is not used: on the smoke run's cost matrices it saved
no iterations in all, single matrices both gaining and losing (the last
stage's linear rate dominates; the figures: ``reports/performance.md``,
"Sinkhorn").

**Threads.** A Sinkhorn step on the evaluation's matrices (a few 10^4 cells) is
far too small for torch's intra-op threads to pay, and on a loaded machine every
parallel region waits for a descheduled thread, so small batches run on one
thread (:func:`limit_threads`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

#: Below this many cells per torch call one thread is faster than several.
SINGLE_THREAD_CELLS = 1 << 18
#: Plain iterations before ``omega`` is estimated from the error decay.
OVERRELAX_WARMUP = 30
#: Upper bound of the over-relaxation parameter (SOR diverges at 2).
OMEGA_MAX = 1.9


class EntropicPlan(NamedTuple):
    """The entropic plan of one problem.

    Attributes:
        plan: (P, N) ``gamma``, rows summing to ``1/P`` and columns to ``1/N``
            within ``marginal_error``; zero on forbidden cells.
        value: the transport cost ``<gamma, C>`` over the allowed cells.
        converged: whether ``marginal_error < stop_thr``.
        n_iter: Sinkhorn iterations (one row and one column update each).
        marginal_error: L2 norm of ``gamma^T 1 - b`` at the last iteration.
        omega: the over-relaxation parameter in use at the end (1 = plain).

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.entropic import sinkhorn_log
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N) costs
        >>> (found,) = sinkhorn_log([C], reg=0.05)
        >>> round(found.value, 3), found.converged, bool(found.omega >= 1.0)
        (1.0, True, True)
        >>> found.plan.sum(axis=0).round(3).tolist()  # each pair's mass, 1/N
        [0.333, 0.333, 0.333]
    """

    plan: np.ndarray
    value: float
    converged: bool
    n_iter: int
    marginal_error: float
    omega: float


@contextmanager
def limit_threads(cells: int) -> Iterator[None]:
    """Run torch on one thread while the work is below :data:`SINGLE_THREAD_CELLS`
    elements per call (restores the caller's setting afterwards).

    Examples:
        >>> import torch
        >>> from torchcf.evaluation.entropic import limit_threads
        >>> before = torch.get_num_threads()
        >>> with limit_threads(cells=100):  # a small problem: one thread
        ...     inside = torch.get_num_threads()
        >>> inside, torch.get_num_threads() == before
        (1, True)
    """
    before = torch.get_num_threads()
    if cells >= SINGLE_THREAD_CELLS or before == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def sor_omega(theta: float) -> float:
    """Young's optimal SOR parameter for a Gauss-Seidel contraction ``theta``:
    ``omega = 2 / (1 + sqrt(1 - theta))``, capped at :data:`OMEGA_MAX`.

    Examples:
        >>> from torchcf.evaluation.entropic import sor_omega
        >>> sor_omega(0.0), round(sor_omega(0.75), 3), sor_omega(1.0)  # 1.0: plain
        (1.0, 1.333, 1.0)
    """
    if not 0.0 <= theta < 1.0:
        return 1.0
    return min(2.0 / (1.0 + math.sqrt(1.0 - theta)), OMEGA_MAX)


def _check_problem(cost: np.ndarray, index: int) -> np.ndarray:
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or cost.size == 0:
        raise ValueError(f"cost {index} must be a non-empty (P, N) matrix")
    if np.isnan(cost).any() or (cost == -np.inf).any():
        raise ValueError(f"cost {index} holds NaN or -inf; forbidden cells are +inf")
    allowed = np.isfinite(cost)
    if not (allowed.any(axis=1).all() and allowed.any(axis=0).all()):
        # such a row or column has no plan at all (its potential would be inf)
        raise ValueError(f"cost {index} has a row or column with no finite cell")
    return cost


class _Batch:
    """The padded problems still running: ``B`` problems, ``P x N`` padded.

    ``C: (B, P, N)`` (``+inf`` on forbidden and padded cells), ``K = -C / eps``,
    ``log_a: (B, P)``, ``log_b, b: (B, N)`` (0 on padding), the row/column masks,
    the potentials ``u: (B, P)``, ``v: (B, N)`` (0 on padding, which the ``-inf``
    kernel keeps out of every sum), and ``index: (B,)`` into the caller's list.
    """

    def __init__(self, costs: list[np.ndarray], reg: float) -> None:
        n_rows = [c.shape[0] for c in costs]
        n_cols = [c.shape[1] for c in costs]
        shape = (len(costs), max(n_rows), max(n_cols))
        cost = torch.full(shape, math.inf, dtype=torch.float64)
        for k, c in enumerate(costs):
            cost[k, : c.shape[0], : c.shape[1]] = torch.from_numpy(c)
        self.cost = cost
        self.log_kernel = -cost / reg
        rows = torch.as_tensor(n_rows, dtype=torch.float64)[:, None]
        cols = torch.as_tensor(n_cols, dtype=torch.float64)[:, None]
        self.rows = torch.arange(shape[1]) < rows  # (B, P)
        self.cols = torch.arange(shape[2]) < cols  # (B, N)
        self.log_a = torch.where(self.rows, -rows.log(), 0.0)
        self.log_b = torch.where(self.cols, -cols.log(), 0.0)
        self.b = torch.where(self.cols, 1.0 / cols, 0.0)
        self.u = torch.zeros(shape[:2], dtype=torch.float64)
        self.v = torch.zeros(shape[0], shape[2], dtype=torch.float64)
        self.index = np.arange(shape[0])
        self.padded = not (self.rows.all() and self.cols.all())

    def column_update(self) -> Tensor:
        """Exact ``v`` for the current ``u``: (B, N)."""
        lse = torch.logsumexp(self.log_kernel + self.u[:, :, None], dim=1)
        v = self.log_b - lse
        return v.masked_fill_(~self.cols, 0.0) if self.padded else v

    def row_update(self) -> Tensor:
        """Exact ``u`` for the current ``v``: (B, P)."""
        lse = torch.logsumexp(self.log_kernel + self.v[:, None, :], dim=2)
        u = self.log_a - lse
        return u.masked_fill_(~self.rows, 0.0) if self.padded else u

    def log_plan(self, u: Tensor) -> Tensor:
        """``log gamma = u_i + v_j - C_ij / eps``: (B, P, N)."""
        return self.log_kernel + u[:, :, None] + self.v[:, None, :]

    def keep(self, mask: np.ndarray) -> None:
        """Drop the problems where ``mask`` is False; trim the padding."""
        keep = torch.from_numpy(mask)
        rows, cols = self.rows[keep], self.cols[keep]
        n_rows = int(rows.sum(dim=1).max()) if mask.any() else 0
        n_cols = int(cols.sum(dim=1).max()) if mask.any() else 0
        self.cost = self.cost[keep, :n_rows, :n_cols]
        self.log_kernel = self.log_kernel[keep, :n_rows, :n_cols]
        self.rows, self.cols = rows[:, :n_rows], cols[:, :n_cols]
        self.log_a, self.u = self.log_a[keep, :n_rows], self.u[keep, :n_rows]
        self.log_b, self.b = self.log_b[keep, :n_cols], self.b[keep, :n_cols]
        self.v = self.v[keep, :n_cols]
        self.index = self.index[mask]
        self.padded = not (self.rows.all() and self.cols.all())


class _Relaxation:
    """Per-problem over-relaxation ``omega`` (module docstring), tuned at checks.

    ``theta`` is the error's contraction per iteration between two checks,
    ``(err_t / err_{t-k})^(1/k)``, measured once past :data:`OVERRELAX_WARMUP`
    plain iterations; a growing error halves ``omega - 1`` from then on.
    """

    def __init__(self, n: int, enabled: bool) -> None:
        self.enabled = enabled
        self.omega = np.ones(n)
        self.tuned = np.zeros(n, dtype=bool)
        self.error = np.full(n, np.nan)
        self.iteration = 0
        self._weight: Tensor | None = None  # omega as (B, 1), None when all 1

    def update(self, error: np.ndarray, iteration: int) -> None:
        if self.enabled and not np.isnan(self.error).all():
            steps = iteration - self.iteration
            with np.errstate(divide="ignore", invalid="ignore"):  # stop_thr = 0
                ratio = error / self.error
            grew = self.tuned & (ratio > 1.0)
            self.omega[grew] = 1.0 + (self.omega[grew] - 1.0) / 2.0
            if iteration > OVERRELAX_WARMUP:
                fresh = ~self.tuned & (ratio < 1.0)
                for k in np.flatnonzero(fresh):
                    self.omega[k] = sor_omega(float(ratio[k]) ** (1.0 / steps))
                self.tuned |= fresh
        self.error, self.iteration = error, iteration
        self._set_weight()

    def keep(self, mask: np.ndarray) -> None:
        self.omega, self.tuned = self.omega[mask], self.tuned[mask]
        self.error = self.error[mask]
        self._set_weight()

    def _set_weight(self) -> None:
        plain = (self.omega == 1.0).all()
        self._weight = None if plain else torch.from_numpy(self.omega)[:, None]

    def step(self, old: Tensor, exact: Tensor) -> Tensor:
        """``old + omega (exact - old)`` per problem (``exact`` when all are 1)."""
        if self._weight is None:
            return exact
        return torch.lerp(old, exact, self._weight)


def sinkhorn_log(
    costs: Sequence[np.ndarray],
    reg: float,
    *,
    max_iter: int = 10_000,
    stop_thr: float = 1e-9,
    check_every: int = 10,
    overrelax: bool = True,
    callback: Callable[[int, int], None] | None = None,
) -> list[EntropicPlan]:
    """Entropic plans of several cost matrices at once (module docstring).

    Args:
        costs: B matrices ``(P_b, N_b)`` float64, ``+inf`` = forbidden; every row
            and column needs an allowed cell. Shapes may differ.
        reg: entropic regularisation ``eps > 0``, in the units of the costs.
        max_iter: iterations allowed per problem; a problem that reaches it is
            returned with ``converged=False`` and ``n_iter = max_iter``.
        stop_thr: stop a problem once the L2 error of its pair marginals
            ``||gamma^T 1 - b||_2`` is below this (POT's ``stopThr``).
        check_every: iterations between two stopping tests (the first test
            follows the first iteration, as in POT).
        overrelax: extrapolate the updates (``False``: plain Sinkhorn, the same
            iterates and iteration count as POT's ``sinkhorn_log``).
        callback: called at every test with ``(iterations, problems done)``.

    Returns:
        one :class:`EntropicPlan` per cost matrix, in order.

    Examples:
        >>> import numpy as np
        >>> from torchcf.evaluation.entropic import sinkhorn_log
        >>> C = np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]])  # (P, N) costs
        >>> plans = sinkhorn_log([C, C[:, :2]], reg=0.05)  # two shapes, one call
        >>> [p.plan.shape for p in plans], [round(p.value, 3) for p in plans]
        ([(2, 3), (2, 2)], [1.0, 1.0])
        >>> C[0, 0] = np.inf  # a forbidden cell: no mass on it
        >>> float(sinkhorn_log([C], reg=0.05)[0].plan[0, 0])
        0.0
    """
    if not (reg > 0.0 and math.isfinite(reg)):
        raise ValueError(f"reg must be a finite number > 0, got {reg}")
    if max_iter < 1 or check_every < 1:
        raise ValueError("max_iter and check_every must be >= 1")
    problems = [_check_problem(c, k) for k, c in enumerate(costs)]
    results: dict[int, EntropicPlan] = {}
    if not problems:
        return []
    batch = _Batch(problems, reg)
    relax = _Relaxation(len(problems), overrelax)
    iteration = 0
    with limit_threads(batch.cost.numel()), torch.no_grad():
        while batch.index.size:
            iteration += 1
            batch.v = relax.step(batch.v, batch.column_update())
            u_exact = batch.row_update()
            test = (iteration - 1) % check_every == 0 or iteration == max_iter
            # the stopping test reads the exact update: rows exact, as in POT
            log_plan = batch.log_plan(u_exact) if test else None
            batch.u = relax.step(batch.u, u_exact)
            if log_plan is not None:
                results.update(
                    _test(batch, log_plan, iteration, max_iter, stop_thr, relax)
                )
                if callback is not None:
                    callback(iteration, len(results))
    return [results[k] for k in range(len(problems))]


def _test(
    batch: _Batch,
    log_plan: Tensor,
    iteration: int,
    max_iter: int,
    stop_thr: float,
    relax: _Relaxation,
) -> dict[int, EntropicPlan]:
    """The stopping test on ``log_plan: (B, P, N)``: finish the problems that
    converged (or ran out of iterations), drop them from the batch, and tune
    ``omega`` of the others. Returns ``{caller's index: result}``."""
    plan = log_plan.exp_()
    error = torch.linalg.vector_norm(plan.sum(dim=1) - batch.b, dim=1).numpy()
    converged = error < stop_thr
    # a non-finite error cannot get better: stop it as not converged
    finish = converged | ~np.isfinite(error) | (iteration >= max_iter)
    results = {}
    for k in np.flatnonzero(finish):
        n_rows, n_cols = int(batch.rows[k].sum()), int(batch.cols[k].sum())
        gamma = plan[k, :n_rows, :n_cols]
        cost = batch.cost[k, :n_rows, :n_cols]
        results[int(batch.index[k])] = EntropicPlan(
            plan=gamma.numpy().copy(),
            # forbidden cells carry exactly 0 (exp(-inf)); 0 * inf would be NaN
            value=float((gamma * cost.nan_to_num(posinf=0.0)).sum()),
            converged=bool(converged[k]),
            n_iter=iteration,
            marginal_error=float(error[k]),
            omega=float(relax.omega[k]),
        )
    if finish.any():
        batch.keep(~finish)
        relax.keep(~finish)
    relax.update(error[~finish], iteration)
    return results


__all__ = [
    "EntropicPlan",
    "OMEGA_MAX",
    "SINGLE_THREAD_CELLS",
    "limit_threads",
    "sinkhorn_log",
    "sor_omega",
]
