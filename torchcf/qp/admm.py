"""ADMM in the OSQP form, per instance, over a batch-last working set.

OSQP's Algorithm 1 (Stellato, Banjac, Goulart, Bemporad & Boyd 2020, "OSQP: an
operator splitting solver for quadratic programs"): sigma regularisation,
over-relaxation alpha, per-instance termination on OSQP's primal and dual
residuals, OSQP's adaptive rho and its primal and dual infeasibility certificates.
Unlike OSQP there is no Ruiz scaling, and the KKT system is reduced to
``P + sigma I + A' diag(rho) A`` and inverted explicitly per instance: for the small
``n`` the solver serves (the MPC horizon, 5 to 20) one batched matrix-vector product
is the whole linear solve.

Finished instances are frozen by writing them out at the check where they finish;
the working set is compacted once a fifth of it has finished. That keeps their
converged value, as ``torch.where(running[:, None], new, old)`` would, and also
stops paying for their iterations, which ``torch.where`` (it evaluates both
branches) would not.

Relative tolerances are raised by ``ROUNDOFF_ULPS`` machine epsilons: in float32
the residuals of badly scaled instances (``|q| ~ 500``) bottom out near 1e-5
relative, and ADMM would otherwise run to max_iter on round-off. An instance whose
residuals stall for ``_STALL_CHECKS`` checks is accepted at ``_STALL_ULPS``
epsilons. Both floors are negligible in float64.

Shapes: ``n`` variables, ``m`` constraint rows, ``B`` instances of a call, ``b``
those of the working set still iterating. Imports :mod:`~torchcf.qp.kernels` and
:mod:`~torchcf.qp.problem` only.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .kernels import inf_norm, mv, put_instances_, spd_inverse, take_instances
from .problem import (
    INF_THRESHOLD,
    ROUNDOFF_ULPS,
    ProblemData,
    QPSettings,
    QPStatus,
)

_RHO_MIN, _RHO_MAX = 1e-6, 1e6
#: rho of an equality row over rho of an inequality row (OSQP's RHO_EQ_OVER_RHO_INEQ).
_RHO_EQ_OVER_INEQ = 1e3
#: Rows with ``u - l`` below this are equalities for the choice of rho (OSQP's RHO_TOL).
_RHO_TOL = 1e-4
#: Compact the ADMM working set once this fraction of it has finished.
_COMPACT_FRACTION = 0.2
#: Round-off floor of an instance whose residuals have stalled for this many checks.
_STALL_ULPS = 1000
_STALL_CHECKS = 5


class Iterate(NamedTuple):
    """An ADMM iterate, batch-last."""

    x: Tensor  # (n, B)
    z: Tensor  # (m, B)
    y: Tensor  # (m, B)


class ADMMOutcome(NamedTuple):
    """ADMM's result for every instance of a call (batch-last, ``B`` instances)."""

    x: Tensor  # (n, B) solution, or the dual infeasibility certificate
    z: Tensor  # (m, B)
    y: Tensor  # (m, B) multipliers, or the primal infeasibility certificate
    n_iter: Tensor  # (B,) int64
    status: Tensor  # (B,) int64 QPStatus
    prim_res: Tensor  # (B,) residuals at the last check
    dual_res: Tensor  # (B,)


# --------------------------------------------------------------------------------------
# rho and the KKT inverse.


def rho_vector(rho: Tensor, data: ProblemData) -> Tensor:
    """Per-row rho (m, B) from the per-instance ``rho: (B,)`` (OSQP's rho_vec):
    ``rho`` on inequality rows, ``_RHO_EQ_OVER_INEQ rho`` on equality rows,
    ``_RHO_MIN`` on rows without bounds."""
    equality = (data.u - data.l) < _RHO_TOL
    loose = (data.l < -INF_THRESHOLD) & (data.u > INF_THRESHOLD)
    rho_vec = rho[None, :].expand_as(data.l)
    rho_vec = torch.where(equality, _RHO_EQ_OVER_INEQ * rho_vec, rho_vec)
    return torch.where(loose, torch.full_like(rho_vec, _RHO_MIN), rho_vec)


def uniform_rows(data: ProblemData) -> Tensor:
    """(B,) True where every row is a plain inequality (rho_vec is rho everywhere)."""
    equality = (data.u - data.l) < _RHO_TOL
    loose = (data.l < -INF_THRESHOLD) & (data.u > INF_THRESHOLD)
    return ~(equality | loose).any(0)


def kkt_inverse(data: ProblemData, rho_vec: Tensor, sigma: float) -> Tensor:
    """``(P + sigma I + A' diag(rho_vec) A)^{-1}``: (n, n, B); ``rho_vec: (m, B)``."""
    if data.A is None:
        M = data.P.clone()
        torch.diagonal(M, 0, 0, 1).add_(rho_vec.T + sigma)  # (B, n) view
    else:
        weighted = data.A * rho_vec[:, None, :]  # (m, n, B)
        M = data.P + torch.einsum("ian,icn->acn", data.A, weighted)
        torch.diagonal(M, 0, 0, 1).add_(sigma)
    return spd_inverse(M)[0]


# --------------------------------------------------------------------------------------
# Starting iterates.


def osqp_starting_iterate(
    data: ProblemData, x0: Tensor | None, y0: Tensor | None, n: int, m: int
) -> Iterate:
    """OSQP's starting iterate (batch-last) from the batch-first warm start
    ``x0: (B, n)``, ``y0: (B, m)``: ``x0`` or 0, ``y0`` or 0, ``z = proj(A x)``."""
    batch = data.q.shape[-1]
    like = data.q
    # A plain clone() of the transposed input would keep its (1, n) strides and slow
    # every later elementwise operation; the copy must be contiguous batch-last.
    dense = torch.contiguous_format
    x = like.new_zeros(n, batch) if x0 is None else x0.T.to(like.dtype)
    y = like.new_zeros(m, batch) if y0 is None else y0.T.to(like.dtype)
    x, y = x.clone(memory_format=dense), y.clone(memory_format=dense)
    z = torch.clamp(data.Ax(x), data.l, data.u)
    return Iterate(x, z, y)


def dual_feasible_start(data: ProblemData, point: Tensor, usable: Tensor) -> Iterate:
    """ADMM start (A = I): ``point`` clipped to the box, and the multipliers
    ``y = -(Px + q)`` on the rows at a bound, which make it dual feasible.

    Costs one matrix-vector product and saves ADMM about a fifth of its iterations
    on the MPC QP against a start from zeros.

    Args:
        data: the problems.
        point: (n, B) the point to clip (``-P^{-1} q`` or the warm start).
        usable: (B,) bool, False where ``point`` is garbage (singular ``P``): zeros.
    """
    x = torch.clamp(point, data.l, data.u)
    x = torch.where(usable[None], x, torch.zeros_like(x))
    at_bound = (x <= data.l) | (x >= data.u)
    y = torch.where(at_bound, -(mv(data.P, x) + data.q), torch.zeros_like(x))
    return Iterate(x, x.clone(), y)


# --------------------------------------------------------------------------------------
# One iteration, and the termination tests.


def _admm_step(
    data: ProblemData,
    s: Iterate,
    rho_vec: Tensor,
    inverse: Tensor,
    settings: QPSettings,
) -> Iterate:
    """One iteration of OSQP's Algorithm 1 with the reduced x-update.

    ``(P + sigma I + A' R A) x~ = sigma x - q + A'(R z - y)`` with ``R = diag(rho)``
    is the KKT system of the algorithm with ``nu`` eliminated; ``z~ = A x~``. Then
    ``x+ = x + alpha (x~ - x)``, ``z+ = proj_[l, u](z_r + y / rho)`` with the
    relaxed ``z_r = z + alpha (z~ - z)``, and ``y+ = y + rho (z_r - z+)``.
    """
    alpha = settings.alpha
    rhs = data.Aty(rho_vec * s.z - s.y)
    rhs = rhs.add_(s.x, alpha=settings.sigma).sub_(data.q)
    x_tilde = mv(inverse, rhs)
    z_tilde = data.Ax(x_tilde)
    x = torch.lerp(s.x, x_tilde, alpha)
    relaxed = torch.lerp(s.z, z_tilde, alpha)
    shifted = torch.addcdiv(relaxed, s.y, rho_vec)  # (m, B) relaxed + y / rho
    z = torch.clamp(shifted, data.l, data.u)
    # y + rho (relaxed - z) written as rho (shifted - z): one operation fewer.
    y = (shifted - z).mul_(rho_vec)
    return Iterate(x, z, y)


def _primal_certificate(
    data: ProblemData, dy: Tensor, eps: float
) -> tuple[Tensor, Tensor]:
    """OSQP's primal infeasibility test on the step ``dy: (m, B)`` of ``y``.

    ``dy`` is first projected onto the polar of the recession cone of ``[l, u]`` (a
    row without upper bound cannot certify with a positive entry); then
    ``u'max(dy, 0) + l'min(dy, 0) < -eps ||dy||`` and ``||A'dy|| < eps ||dy||``.

    Returns:
        infeasible: (B,) bool; certificate: (m, B) the projected ``dy``.
    """
    no_upper = data.u > INF_THRESHOLD
    no_lower = data.l < -INF_THRESHOLD
    dy = torch.where(no_upper, dy.clamp(max=0), dy)
    dy = torch.where(no_lower, dy.clamp(min=0), dy)
    norm = inf_norm(dy)
    # After the projection an infinite bound only meets zero entries; the where
    # keeps +-1e30 * 0 out of the sum all the same.
    upper = torch.where(no_upper, torch.zeros_like(dy), data.u * dy.clamp(min=0))
    lower = torch.where(no_lower, torch.zeros_like(dy), data.l * dy.clamp(max=0))
    support = (upper + lower).sum(0)
    infeasible = (
        (norm > torch.finfo(dy.dtype).tiny)
        & (support < -eps * norm)
        & (inf_norm(data.Aty(dy)) < eps * norm)
    )
    return infeasible, dy


def _dual_certificate(data: ProblemData, dx: Tensor, eps: float) -> Tensor:
    """OSQP's dual infeasibility (unboundedness) test on the step ``dx: (n, B)`` of
    ``x``.

    ``||P dx|| < eps ||dx||``, ``q'dx < -eps ||dx||`` and ``A dx`` in the recession
    cone of ``[l, u]`` up to ``eps ||dx||``.

    Returns:
        (B,) bool.
    """
    norm = inf_norm(dx)
    tol = eps * norm
    a_dx = data.Ax(dx)
    in_cone = (
        ((data.u > INF_THRESHOLD) | (a_dx <= tol))
        & ((data.l < -INF_THRESHOLD) | (a_dx >= -tol))
    ).all(0)
    return (
        (norm > torch.finfo(dx.dtype).tiny)
        & ((data.q * dx).sum(0) < -tol)
        & (inf_norm(mv(data.P, dx)) < tol)
        & in_cone
    )


class _Residuals(NamedTuple):
    """OSQP's residuals at a check and the scales of their relative tolerances."""

    prim: Tensor  # (b,) ||A x - z||_inf
    dual: Tensor  # (b,) ||P x + q + A'y||_inf
    prim_scale: Tensor  # (b,) max(||A x||, ||z||)
    dual_scale: Tensor  # (b,) max(||P x||, ||A'y||, ||q||)

    def take(self, idx: Tensor) -> _Residuals:
        return _Residuals(*(t[idx] for t in self))


class _Verdict(NamedTuple):
    """What a check concludes per instance (the three flags are exclusive)."""

    solved: Tensor  # (b,) bool, within tolerance (or stalled at the looser floor)
    prim_inf: Tensor  # (b,) bool, primal infeasible
    dual_inf: Tensor  # (b,) bool, dual infeasible
    prim_cert: Tensor  # (m, b) the projected step of y (see _primal_certificate)
    dual_cert: Tensor  # (n, b) the step of x


class _Progress(NamedTuple):
    """Per-instance record of the best normalised residual, for the stall test."""

    best: Tensor  # (b,) max(prim / prim_tol, dual / dual_tol), best so far
    since_best: Tensor  # (b,) checks since it last improved by 10 %

    def take(self, idx: Tensor) -> _Progress:
        return _Progress(self.best[idx], self.since_best[idx])


def _check(
    data: ProblemData,
    iterate: Iterate,
    previous: Iterate,
    progress: _Progress,
    eps_rel: tuple[float, float],
    settings: QPSettings,
) -> tuple[_Residuals, _Verdict, _Progress]:
    """OSQP's termination and infeasibility tests at ``iterate`` (``previous`` is
    the iterate one step before it).

    Solved where ``prim <= eps_abs + eps_rel prim_scale`` and
    ``dual <= eps_abs + eps_rel dual_scale``, or, after ``_STALL_CHECKS`` checks
    without a 10 % gain, the same at the looser stalled ``eps_rel``.

    Args:
        eps_rel: the relative tolerance raised to the round-off floor, and raised to
            the stalled floor.
    """
    eps_rel_floor, eps_rel_stalled = eps_rel
    ax, px, aty = data.Ax(iterate.x), mv(data.P, iterate.x), data.Aty(iterate.y)
    prim_res = inf_norm(ax - iterate.z)
    dual_res = inf_norm(px + data.q + aty)
    prim_scale = torch.maximum(inf_norm(ax), inf_norm(iterate.z))
    dual_scale = torch.maximum(
        torch.maximum(inf_norm(px), inf_norm(aty)), inf_norm(data.q)
    )
    prim_tol = settings.eps_abs + eps_rel_floor * prim_scale
    dual_tol = settings.eps_abs + eps_rel_floor * dual_scale
    prim_ok, dual_ok = prim_res <= prim_tol, dual_res <= dual_tol
    normalised = torch.maximum(prim_res / prim_tol, dual_res / dual_tol)
    improved = normalised < 0.9 * progress.best
    best = torch.where(improved, normalised, progress.best)
    since_best = torch.where(improved, 0, progress.since_best + 1)
    stalled = (
        (since_best >= _STALL_CHECKS)
        & (prim_res <= settings.eps_abs + eps_rel_stalled * prim_scale)
        & (dual_res <= settings.eps_abs + eps_rel_stalled * dual_scale)
    )
    solved = (prim_ok & dual_ok) | stalled
    prim_inf, prim_cert = _primal_certificate(
        data, iterate.y - previous.y, settings.eps_prim_inf
    )
    prim_inf &= ~prim_ok & ~solved  # OSQP tests it only while not converged
    dual_cert = iterate.x - previous.x
    dual_inf = _dual_certificate(data, dual_cert, settings.eps_dual_inf)
    dual_inf &= ~dual_ok & ~solved & ~prim_inf
    return (
        _Residuals(prim_res, dual_res, prim_scale, dual_scale),
        _Verdict(solved, prim_inf, dual_inf, prim_cert, dual_cert),
        _Progress(best, since_best),
    )


# --------------------------------------------------------------------------------------
# The ADMM loop and its stages.


class _WorkingSet(NamedTuple):
    """The ``b`` instances ADMM still iterates, and their state."""

    active: Tensor  # (b,) int64 positions in the call's batch
    running: Tensor  # (b,) bool, False once finished (until the next compaction)
    data: ProblemData
    iterate: Iterate
    rho: Tensor  # (b,)
    rho_vec: Tensor  # (m, b) see rho_vector
    inverse: Tensor  # (n, n, b) the KKT inverse for rho_vec
    progress: _Progress

    def take(self, idx: Tensor) -> _WorkingSet:
        """Instances ``idx: (b',)`` of the working set."""
        return _WorkingSet(
            self.active[idx],
            self.running[idx],
            self.data.take(idx),
            Iterate(*(take_instances(t, idx) for t in self.iterate)),
            self.rho[idx],
            take_instances(self.rho_vec, idx),
            take_instances(self.inverse, idx),
            self.progress.take(idx),
        )


def _empty_outcome(start: Iterate, like: Tensor) -> ADMMOutcome:
    """The output buffers of ``B`` instances: the start, MAX_ITER, no iterations;
    residuals in the dtype of ``like: (n, B)``."""
    batch = like.shape[-1]
    device = like.device
    out_x, out_z, out_y = (t.clone() for t in start)
    zeros = torch.zeros(batch, dtype=like.dtype, device=device)
    return ADMMOutcome(
        out_x,
        out_z,
        out_y,
        n_iter=torch.zeros(batch, dtype=torch.int64, device=device),
        status=torch.full((batch,), int(QPStatus.MAX_ITER), device=device),
        prim_res=zeros.clone(),
        dual_res=zeros.clone(),
    )


def _iterate(
    work: _WorkingSet, steps: int, settings: QPSettings
) -> tuple[Iterate, Iterate]:
    """``steps`` iterations; returns the iterate before the last one and the last."""
    data, state = work.data, work.iterate
    for _ in range(steps - 1):
        state = _admm_step(data, state, work.rho_vec, work.inverse, settings)
    previous = state
    state = _admm_step(data, state, work.rho_vec, work.inverse, settings)
    return previous, state


def _write_finished(
    out: ADMMOutcome,
    rows: Tensor,
    work: _WorkingSet,
    residuals: _Residuals,
    verdict: _Verdict,
    done_iter: int,
) -> None:
    """Write the working set's instances ``rows: (r,)`` into ``out``, in place.

    OSQP returns the infeasibility certificates in place of the iterate; here they
    are scaled to unit inf-norm (the ADMM step itself grows like ``1 / sigma``).
    """
    state = work.iterate
    status = torch.full_like(rows, int(QPStatus.MAX_ITER))
    status[verdict.solved[rows]] = int(QPStatus.SOLVED)
    status[verdict.prim_inf[rows]] = int(QPStatus.PRIMAL_INFEASIBLE)
    status[verdict.dual_inf[rows]] = int(QPStatus.DUAL_INFEASIBLE)
    where = work.active[rows]
    dual_cert = verdict.dual_cert[:, rows] / inf_norm(verdict.dual_cert[:, rows])
    prim_cert = verdict.prim_cert[:, rows] / inf_norm(verdict.prim_cert[:, rows])
    out.x[:, where] = torch.where(verdict.dual_inf[rows], dual_cert, state.x[:, rows])
    out.y[:, where] = torch.where(verdict.prim_inf[rows], prim_cert, state.y[:, rows])
    out.z[:, where] = state.z[:, rows]
    out.status[where] = status
    out.n_iter[where] = done_iter
    out.prim_res[where] = residuals.prim[rows]
    out.dual_res[where] = residuals.dual[rows]


def _adapt_rho(
    work: _WorkingSet, residuals: _Residuals, settings: QPSettings
) -> _WorkingSet:
    """OSQP's adaptive rho: balance the normalised primal and dual residuals,
    ``rho' = rho sqrt((prim / prim_scale) / (dual / dual_scale))``, and refactorise
    the running instances whose rho moves by more than ``adaptive_rho_tolerance``
    (``rho_vec`` and ``inverse`` are updated in place)."""
    rho = work.rho
    ratio = (residuals.prim / (residuals.prim_scale + 1e-10)) / (
        residuals.dual / (residuals.dual_scale + 1e-10) + 1e-10
    )
    new_rho = (rho * ratio.sqrt()).clamp(_RHO_MIN, _RHO_MAX)
    tol = settings.adaptive_rho_tolerance
    change = work.running & ((new_rho > tol * rho) | (new_rho < rho / tol))
    change = change.nonzero().squeeze(1)
    if not change.numel():
        return work
    rho = rho.index_copy(0, change, new_rho[change])
    sub = work.data.take(change)
    sub_rho_vec = rho_vector(rho[change], sub)
    rho_vec = put_instances_(work.rho_vec, change, sub_rho_vec)
    put_instances_(work.inverse, change, kkt_inverse(sub, sub_rho_vec, settings.sigma))
    return work._replace(rho=rho, rho_vec=rho_vec)


def admm_iterations(
    data: ProblemData,
    state: Iterate,
    rho: Tensor,
    inverse: Tensor,
    settings: QPSettings,
) -> ADMMOutcome:
    """Run ADMM on every instance of ``data`` until each one terminates.

    An instance is written to the output at the check where it terminates and stops
    counting from then on (``running``); the working set is compacted to the running
    instances once enough of it has finished to pay for the gather.

    Args:
        data: the problems, batch-last.
        state: starting iterate.
        rho: (B,) starting rho per instance.
        inverse: (n, n, B) KKT inverse for ``rho`` (see :func:`kkt_inverse`);
            owned by the call: refactorisations overwrite it in place.
        settings: solver settings.
    """
    batch = data.q.shape[-1]
    device = data.q.device
    out = _empty_outcome(state, data.q)
    # Residuals below about a hundred ulps of the quantities they difference are
    # round-off (float32 reaches it on badly scaled instances): never ask for less.
    # An instance whose residuals stop shrinking (``_STALL_CHECKS`` checks without a
    # 10 % gain) is accepted at the looser ``_STALL_ULPS`` floor instead of running
    # to max_iter on round-off; in float64 both floors are far below any tolerance.
    ulp = torch.finfo(data.q.dtype).eps
    eps_rel = (
        settings.eps_rel + ROUNDOFF_ULPS * ulp,
        settings.eps_rel + _STALL_ULPS * ulp,
    )
    work = _WorkingSet(
        active=torch.arange(batch, device=device),
        running=torch.ones(batch, dtype=torch.bool, device=device),
        data=data,
        iterate=state,
        rho=rho,
        rho_vec=rho_vector(rho, data),
        inverse=inverse,
        progress=_Progress(torch.full_like(rho, math.inf), torch.zeros_like(rho)),
    )
    done_iter = 0
    while batch and done_iter < settings.max_iter:
        steps = min(settings.check_every, settings.max_iter - done_iter)
        previous, iterate = _iterate(work, steps, settings)
        done_iter += steps
        residuals, verdict, progress = _check(
            work.data, iterate, previous, work.progress, eps_rel, settings
        )
        work = work._replace(iterate=iterate, progress=progress)

        finished = verdict.solved | verdict.prim_inf | verdict.dual_inf
        if done_iter >= settings.max_iter:
            finished = torch.ones_like(finished)
        rows = (finished & work.running).nonzero().squeeze(1)
        if rows.numel():
            _write_finished(out, rows, work, residuals, verdict, done_iter)
            work.running[rows] = False
            n_running = int(work.running.sum())
            if not n_running:
                break
            if n_running <= (1 - _COMPACT_FRACTION) * work.running.numel():
                keep = work.running.nonzero().squeeze(1)
                work, residuals = work.take(keep), residuals.take(keep)

        if settings.adaptive_rho:
            work = _adapt_rho(work, residuals, settings)
    return out
