"""Batched convex QP solver: ADMM in the OSQP form.

Solves, for ``B`` independent instances of the same shape,

    min 1/2 x'Px + q'x   s.t.   l <= A x <= u,

with ``P`` symmetric positive semidefinite, by the ADMM of OSQP (Stellato, Banjac,
Goulart, Bemporad & Boyd 2020, "OSQP: an operator splitting solver for quadratic
programs", Algorithm 1): sigma regularisation, over-relaxation alpha, per-instance
termination on OSQP's primal and dual residuals, OSQP's adaptive rho, its primal and
dual infeasibility certificates and its solution polishing. Unlike OSQP there is no
Ruiz scaling, and the KKT system is reduced to ``P + sigma I + A' diag(rho) A`` and
inverted explicitly per instance: for the small ``n`` this module serves (the MPC
horizon, 5 to 20) one batched matrix-vector product is the whole linear solve.

Two entry points:

- :func:`solve_qp_batch` for a general ``A: (B, m, n)``;
- :class:`BoxQP` for ``A = I``, which factorises once per ``P`` and reuses the factors
  for every ``(q, l, u)``. Before ADMM it solves exactly on guessed active sets: from
  the caller's guess (the MPC passes its last plan) or from "no bound active", whose
  solve is the unconstrained minimiser, corrected by primal-dual active-set steps,
  and kept only where the KKT conditions hold. Where the guessed active bounds are a
  leading block ``0 .. k-1`` (on the MPC QPs nearly always: the first inputs of the
  plan saturate) the solve reuses a "UL" Cholesky factor computed per ``P``
  (``n^2 / 2`` multiply-adds for ``x``, ``k^2 / 2`` for the multipliers, no new
  factorisation), and a step that fixes or frees the bound at the end of the block
  is a rank-one update from a second per-``P`` factor; other guesses refactorise.
  On the MPC QPs these stages finish nearly every instance, so ADMM is the
  fallback.

Internally every tensor is *batch-last* (``(n, B)``, ``(n, n, B)``): a matrix-vector
product is then ``n`` fused multiply-adds over contiguous ``B``-vectors, about four
times faster on CPU than ``bmm`` with ``5 x 5`` matrices, and the explicit Cholesky
below is a loop over ``n`` of elementwise operations over the batch instead of one
LAPACK call per matrix. The public API is batch-first.

Finished instances are frozen by writing them out at the check where they finish;
the working set is compacted once a fifth of it has finished. That keeps their
converged value, as ``torch.where(running[:, None], new, old)`` would, and also stops
paying for their iterations, which ``torch.where`` (it evaluates both branches) would
not.

Numerics worth knowing:

- Relative tolerances are raised by ``_ROUNDOFF_ULPS`` machine epsilons: in float32
  the residuals of badly scaled instances (``|q| ~ 500``) bottom out near 1e-5
  relative, and ADMM would otherwise run to max_iter on round-off. An instance whose
  residuals stall for ``_STALL_CHECKS`` checks is accepted at ``_STALL_ULPS``
  epsilons. Both floors are negligible in float64.
- The active-set stages accept a point only if it satisfies the KKT conditions to
  round-off, so their answers are exact, not ADMM-accurate. The polish after ADMM
  accepts a point that beats ADMM's own residuals: nearly always exact, at worst
  as accurate as ADMM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

#: Bounds beyond +-this are infinite (OSQP's OSQP_INFTY); +-inf inputs are clamped here.
INFTY = 1e30
_RHO_MIN, _RHO_MAX = 1e-6, 1e6
#: rho of an equality row over rho of an inequality row (OSQP's RHO_EQ_OVER_RHO_INEQ).
_RHO_EQ_OVER_INEQ = 1e3
#: Rows with ``u - l`` below this are equalities for the choice of rho (OSQP's RHO_TOL).
_RHO_TOL = 1e-4
#: Regularisation and iterative-refinement steps of the polish (OSQP's defaults).
_POLISH_DELTA = 1e-6
_POLISH_REFINE = 3
#: Polish attempts per instance (the first from ADMM's active set, then corrections).
_POLISH_PASSES = 4
#: Exact active-set solves per instance in BoxQP's second stage.
_ACTIVE_SET_PASSES = 5
#: Batches up to this size multiply by one batched product (see :func:`_mv`).
_SMALL_BATCH = 64
#: Batches up to this size are factorised and solved by LAPACK, one call per matrix:
#: the elementwise loops cost a fixed ~n^2 / 2 tensor operations (about 7 ms at
#: n = 20), LAPACK a few microseconds per matrix.
_LAPACK_BATCH = 1024
#: The leading-block stage's column sweeps run over batch slices whose accumulator
#: (``(n, b)`` values, read and written once per column) fits in this many bytes: it
#: then stays in the last-level cache (float64, n = 20, B = 1e5: 24 ms for a sweep
#: of the whole batch, 17 ms in two halves; float32 fits whole).
_SWEEP_BYTES = 8 << 20
#: Compact the leading-block stage's working set once less than this share runs.
_LEADING_COMPACT = 0.5
#: Relative tolerances are raised by this many machine epsilons (see :func:`_admm`).
_ROUNDOFF_ULPS = 100
#: Compact the ADMM working set once this fraction of it has finished.
_COMPACT_FRACTION = 0.2
#: Round-off floor of an instance whose residuals have stalled for this many checks.
_STALL_ULPS = 1000
_STALL_CHECKS = 5
#: A bound whose magnitude exceeds this is treated as infinite (OSQP: INFTY * 1e-4).
_INF_THRESHOLD = INFTY * 1e-4


class QPStatus(IntEnum):
    """Per-instance outcome of a solve."""

    SOLVED = 0
    MAX_ITER = 1
    PRIMAL_INFEASIBLE = 2
    DUAL_INFEASIBLE = 3


@dataclass(frozen=True)
class QPSettings:
    """ADMM settings; the names and defaults follow OSQP's where they exist.

    Attributes:
        rho: initial ADMM step size of an inequality row (equality rows use
            ``1e3 rho``, rows without bounds ``1e-6``).
        sigma: regularisation of the x-update (keeps a singular ``P`` invertible).
        alpha: over-relaxation, in (0, 2).
        eps_abs, eps_rel: absolute and relative tolerances of the primal residual
            ``||Ax - z||_inf`` and of the dual residual ``||Px + q + A'y||_inf``.
        eps_prim_inf, eps_dual_inf: tolerances of the infeasibility certificates.
        max_iter: iteration limit per instance.
        check_every: residuals, infeasibility and rho are checked every this many
            iterations (each check costs about two iterations and a host sync).
        adaptive_rho: rescale rho per instance from the residual ratio (OSQP's rule).
        adaptive_rho_tolerance: refactorise only when the new rho differs from the
            current one by more than this factor.
        polish: refine solved instances by an exact solve on the guessed active set.
    """

    rho: float = 0.1
    sigma: float = 1e-6
    alpha: float = 1.6
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    eps_prim_inf: float = 1e-6
    eps_dual_inf: float = 1e-6
    max_iter: int = 4000
    check_every: int = 10
    adaptive_rho: bool = True
    adaptive_rho_tolerance: float = 5.0
    polish: bool = True

    def __post_init__(self) -> None:
        if not self.rho > 0 or not self.sigma > 0:
            raise ValueError("rho and sigma must be positive")
        if not 0 < self.alpha < 2:
            raise ValueError(f"alpha must be in (0, 2), got {self.alpha}")
        if self.eps_abs < 0 or self.eps_rel < 0 or self.eps_abs + self.eps_rel <= 0:
            raise ValueError("eps_abs and eps_rel must be >= 0, not both 0")
        if self.max_iter < 1 or self.check_every < 1:
            raise ValueError("max_iter and check_every must be >= 1")
        if not self.adaptive_rho_tolerance >= 1:
            raise ValueError("adaptive_rho_tolerance must be >= 1")


class QPResult(NamedTuple):
    """Solution of a batch of QPs.

    For a PRIMAL_INFEASIBLE instance ``y`` is the infeasibility certificate (the last
    ADMM step of ``y``, OSQP's ``prim_inf_cert``: ``A'y = 0``, ``u'y_+ + l'y_- < 0``);
    for a DUAL_INFEASIBLE one ``x`` is the certificate (the last step of ``x``: a
    direction of unbounded descent). Both are scaled to unit inf-norm. MAX_ITER
    instances hold the last iterate.

    Attributes:
        x: (B, n) primal solution, contiguous.
        y: (B, m) multipliers of ``l <= Ax <= u``: positive where the upper bound is
            active, negative where the lower one is (``Px + q + A'y = 0``). A
            transposed view of batch-last storage (``.contiguous()`` copies it).
        z: (B, m) ``Ax`` projected onto ``[l, u]``; a transposed view like ``y``.
        n_iter: (B,) int64 ADMM iterations (0 where BoxQP's fast path or active-set
            stage solved the instance).
        status: (B,) int64 :class:`QPStatus` values.
        polished: (B,) bool, True where the returned point is an exact solve on an
            active set (the polish after ADMM, or BoxQP's active-set stage).
    """

    x: Tensor
    y: Tensor
    z: Tensor
    n_iter: Tensor
    status: Tensor
    polished: Tensor


# --------------------------------------------------------------------------------------
# Batch-last linear algebra: matrices (r, c, B), vectors (c, B).


def _mv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` per instance: (r, c, B) x (c, B) -> (r, B)."""
    if v.shape[-1] <= _SMALL_BATCH:  # a few instances: one batched product
        return torch.einsum("rcb,cb->rb", M, v)
    out = M[:, 0] * v[0]
    for j in range(1, v.shape[0]):
        out.addcmul_(M[:, j], v[j])
    return out


def _rmv(M: Tensor, v: Tensor) -> Tensor:
    """``M' v`` per instance: (r, c, B) x (r, B) -> (c, B)."""
    out = M[0] * v[0]
    for i in range(1, v.shape[0]):
        out.addcmul_(M[i], v[i])
    return out


def _take(t: Tensor, idx: Tensor) -> Tensor:
    """Instances ``idx`` of a batch-last tensor ``(..., B) -> (..., len(idx))``.

    Gathering along the last dim of a flat ``(rows, B)`` view is several times faster
    than ``index_select(-1)`` on the ``(n, n, B)`` tensor itself.
    """
    flat = t.reshape(-1, t.shape[-1]).index_select(1, idx)
    return flat.reshape(*t.shape[:-1], idx.numel())


def _few(idx: Tensor, batch: int) -> bool:
    """Is ``idx`` few enough of ``batch`` instances to gather them from batch-first
    storage? Gathering a few columns of a batch-last ``(n, n, B)`` tensor touches a
    page per element (about 10 ms for 600 instances at n = 20, B = 1e5);
    batch-first, each instance is one contiguous block."""
    return idx.numel() * 8 <= batch


def _put_(t: Tensor, idx: Tensor, src: Tensor) -> Tensor:
    """Replace instances ``idx`` of contiguous batch-last ``t`` by ``src``, in place."""
    if idx.numel():
        t.view(-1, t.shape[-1]).index_copy_(1, idx, src.reshape(-1, idx.numel()))
    return t


def _transpose(t: Tensor) -> Tensor:
    """Contiguous ``t.T`` of a 2-D tensor: between the batch-first API and the
    batch-last working layout.

    On the CPU numpy's blocked transpose is about twice as fast as torch's strided
    copy (measured: 3 ms against 6 ms for 100000 x 20 float32, 2 threads).
    """
    if t.device.type == "cpu" and not t.requires_grad and t.dtype != torch.bfloat16:
        array = t.resolve_conj().resolve_neg().numpy()
        return torch.from_numpy(np.ascontiguousarray(array.T))
    return t.T.contiguous()


def _cholesky(M: Tensor, strict: bool = True) -> tuple[Tensor, Tensor]:
    """Lower Cholesky factor of symmetric ``M: (n, n, B)``, one column per step.

    Every inner product is a chain of in-place ``addcmul_`` over ``B``-vectors: no
    ``(n, n, B)`` temporaries, which is what makes ``n = 20`` affordable.

    Args:
        M: (n, n, B).
        strict: treat pivots below ``n eps max(diag)`` as zero (a singular ``M``);
            otherwise only non-positive pivots fail.

    Returns:
        L: (n, n, B) whose lower triangle holds the factor, ``L L' = M`` where
            ``ok`` (garbage elsewhere); the strict upper triangle is uninitialised.
        ok: (B,) bool, False where a pivot is not clearly positive (``M`` singular or
            indefinite to working precision).
    """
    n = M.shape[0]
    floor = torch.diagonal(M).amax(-1).clamp_min(0) * (n * torch.finfo(M.dtype).eps)
    if not strict:
        floor = torch.zeros_like(floor)
    if M.shape[-1] <= _LAPACK_BATCH:
        # A few matrices: LAPACK per matrix beats n^2 / 2 tiny elementwise calls.
        L, info = torch.linalg.cholesky_ex(M.permute(2, 0, 1))  # (B, n, n)
        pivots = torch.diagonal(L, 0, 1, 2).square()  # (B, n)
        ok = (info == 0) & (pivots > floor[:, None]).all(1)
        return L.permute(1, 2, 0).contiguous(), ok
    L = torch.empty_like(M)  # only the lower triangle is written and read
    ok = torch.ones(M.shape[-1], dtype=torch.bool, device=M.device)
    for j in range(n):
        col = M[j:, j].clone()  # (n - j, B)
        for k in range(j):
            col.addcmul_(L[j:, k], L[j, k], value=-1)
        good = col[0] > floor
        ok &= good
        pivot = torch.where(good, col[0], torch.ones_like(col[0])).sqrt_()  # (B,)
        L[j, j] = pivot
        L[j + 1 :, j] = col[1:] / pivot
    return L, ok


def _cholesky_solve(L: Tensor, b: Tensor) -> Tensor:
    """Solve ``L L' x = b`` for ``L: (n, n, B)`` lower triangular, ``b: (n, B)``."""
    n = b.shape[0]
    if b.shape[-1] <= _LAPACK_BATCH:
        x = torch.cholesky_solve(b.T[:, :, None], L.permute(2, 0, 1).tril())
        return x[:, :, 0].T
    w = b.clone()
    for i in range(n):  # forward: L w = b
        for k in range(i):
            w[i].addcmul_(L[i, k], w[k], value=-1)
        w[i] /= L[i, i]
    for i in reversed(range(n)):  # backward: L' x = w
        for k in range(i + 1, n):
            w[i].addcmul_(L[k, i], w[k], value=-1)
        w[i] /= L[i, i]
    return w


def _spd_inverse(M: Tensor) -> tuple[Tensor, Tensor]:
    """Explicit inverse of symmetric positive definite ``M: (n, n, B)``.

    LAPACK's potri done by hand: ``W = L^{-1}`` row by row, then ``M^{-1} = W' W``,
    both as ``addcmul_`` chains over the batch (``n^3 / 3`` of them in all); the cost
    is a few elementwise passes per matrix entry instead of one LAPACK call per
    matrix.

    Returns:
        inverse: (n, n, B); ok: (B,) bool as in :func:`_cholesky`.
    """
    n = M.shape[0]
    L, ok = _cholesky(M)
    if M.shape[-1] <= _LAPACK_BATCH:  # a few matrices: LAPACK's potri per matrix
        inverse = torch.cholesky_inverse(L.permute(2, 0, 1).tril())  # (B, n, n)
        inverse = torch.where(ok[:, None, None], inverse, 0)  # no NaN where not ok
        return inverse.permute(1, 2, 0).contiguous(), ok
    W = torch.empty_like(M)  # lower triangular; the upper triangle is never read
    for i in range(n):
        W[i, i] = L[i, i].reciprocal()
        if i:
            row = M.new_zeros(i, M.shape[-1])  # (i, B)
            for k in range(i):
                row[: k + 1].addcmul_(W[k, : k + 1], L[i, k])  # W[k, c>k] = 0
            W[i, :i] = row.mul_(-W[i, i])
    inverse = torch.empty_like(M)
    for a in range(n):
        # Column a below the diagonal: inverse[c, a] = sum_{k >= c} W[k, c] W[k, a],
        # and W[k, c] = 0 for c > k, so term k only touches rows c <= k.
        col = W[n - 1, a:] * W[n - 1, a]  # (n - a, B)
        for k in range(a, n - 1):
            col[: k - a + 1].addcmul_(W[k, a : k + 1], W[k, a])
        inverse[a:, a] = col
        inverse[a, a + 1 :] = col[1:]
    return inverse, ok


# --------------------------------------------------------------------------------------
# Problem data in the working layout.


class _Data(NamedTuple):
    """One working set of QPs, batch-last. ``A is None`` means ``A = I`` (m = n)."""

    P: Tensor  # (n, n, B)
    q: Tensor  # (n, B)
    A: Tensor | None  # (m, n, B)
    l: Tensor  # (m, B), clamped to [-INFTY, INFTY]  # noqa: E741
    u: Tensor  # (m, B)

    def take(self, idx: Tensor) -> _Data:
        return _Data(*(None if t is None else _take(t, idx) for t in self))

    def Ax(self, x: Tensor) -> Tensor:
        return x if self.A is None else _mv(self.A, x)

    def Aty(self, y: Tensor) -> Tensor:
        return y if self.A is None else _rmv(self.A, y)


def _rho_vector(rho: Tensor, data: _Data) -> Tensor:
    """Per-row rho (m, B) from the per-instance ``rho: (B,)`` (OSQP's rho_vec)."""
    equality = (data.u - data.l) < _RHO_TOL
    loose = (data.l < -_INF_THRESHOLD) & (data.u > _INF_THRESHOLD)
    rho_vec = rho[None, :].expand_as(data.l)
    rho_vec = torch.where(equality, _RHO_EQ_OVER_INEQ * rho_vec, rho_vec)
    return torch.where(loose, torch.full_like(rho_vec, _RHO_MIN), rho_vec)


def _uniform_rows(data: _Data) -> Tensor:
    """(B,) True where every row is a plain inequality (rho_vec is rho everywhere)."""
    equality = (data.u - data.l) < _RHO_TOL
    loose = (data.l < -_INF_THRESHOLD) & (data.u > _INF_THRESHOLD)
    return ~(equality | loose).any(0)


def _kkt_inverse(data: _Data, rho_vec: Tensor, sigma: float) -> Tensor:
    """``(P + sigma I + A' diag(rho_vec) A)^{-1}``: (n, n, B)."""
    if data.A is None:
        M = data.P.clone()
        torch.diagonal(M, 0, 0, 1).add_(rho_vec.T + sigma)  # (B, n) view
    else:
        weighted = data.A * rho_vec[:, None, :]  # (m, n, B)
        M = data.P + torch.einsum("ian,icn->acn", data.A, weighted)
        torch.diagonal(M, 0, 0, 1).add_(sigma)
    return _spd_inverse(M)[0]


# --------------------------------------------------------------------------------------
# ADMM.


class _State(NamedTuple):
    x: Tensor  # (n, B)
    z: Tensor  # (m, B)
    y: Tensor  # (m, B)


class _Outcome(NamedTuple):
    """ADMM result for every instance of a working set (batch-last)."""

    x: Tensor
    z: Tensor
    y: Tensor
    n_iter: Tensor  # (B,)
    status: Tensor  # (B,)
    prim_res: Tensor  # (B,) residuals at the last check
    dual_res: Tensor


def _admm_step(
    data: _Data, s: _State, rho_vec: Tensor, inverse: Tensor, settings: QPSettings
) -> _State:
    """One iteration of OSQP's Algorithm 1 with the reduced x-update.

    ``(P + sigma I + A' R A) x~ = sigma x - q + A'(R z - y)`` with ``R = diag(rho)``
    is the KKT system of the algorithm with ``nu`` eliminated; ``z~ = A x~``.
    """
    alpha = settings.alpha
    rhs = data.Aty(rho_vec * s.z - s.y)
    rhs = rhs.add_(s.x, alpha=settings.sigma).sub_(data.q)
    x_tilde = _mv(inverse, rhs)
    z_tilde = data.Ax(x_tilde)
    x = torch.lerp(s.x, x_tilde, alpha)
    relaxed = torch.lerp(s.z, z_tilde, alpha)
    shifted = torch.addcdiv(relaxed, s.y, rho_vec)  # (m, B) relaxed + y / rho
    z = torch.clamp(shifted, data.l, data.u)
    # y + rho (relaxed - z) written as rho (shifted - z): one operation fewer.
    y = (shifted - z).mul_(rho_vec)
    return _State(x, z, y)


def _inf_norm(v: Tensor) -> Tensor:
    """Max-norm over the rows: (m, B) -> (B,); NaN propagates.

    Two reductions and no ``|v|`` temporary, which on the CPU costs more than both
    (``torch.aminmax`` over dim 0 is slower still).
    """
    return torch.maximum(v.amax(0), v.amin(0).neg_())


def _primal_certificate(data: _Data, dy: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """OSQP's primal infeasibility test on the step ``dy`` of ``y``.

    ``dy`` is first projected onto the polar of the recession cone of ``[l, u]`` (a
    row without upper bound cannot certify with a positive entry); then
    ``u'max(dy, 0) + l'min(dy, 0) < -eps ||dy||`` and ``||A'dy|| < eps ||dy||``.

    Returns:
        infeasible: (B,) bool; certificate: (m, B) the projected ``dy``.
    """
    no_upper = data.u > _INF_THRESHOLD
    no_lower = data.l < -_INF_THRESHOLD
    dy = torch.where(no_upper, dy.clamp(max=0), dy)
    dy = torch.where(no_lower, dy.clamp(min=0), dy)
    norm = _inf_norm(dy)
    # After the projection an infinite bound only meets zero entries; the where
    # keeps +-1e30 * 0 out of the sum all the same.
    upper = torch.where(no_upper, torch.zeros_like(dy), data.u * dy.clamp(min=0))
    lower = torch.where(no_lower, torch.zeros_like(dy), data.l * dy.clamp(max=0))
    support = (upper + lower).sum(0)
    infeasible = (
        (norm > torch.finfo(dy.dtype).tiny)
        & (support < -eps * norm)
        & (_inf_norm(data.Aty(dy)) < eps * norm)
    )
    return infeasible, dy


def _dual_certificate(data: _Data, dx: Tensor, eps: float) -> Tensor:
    """OSQP's dual infeasibility (unboundedness) test on the step ``dx`` of ``x``.

    ``||P dx|| < eps ||dx||``, ``q'dx < -eps ||dx||`` and ``A dx`` in the recession
    cone of ``[l, u]`` up to ``eps ||dx||``.

    Returns:
        (B,) bool.
    """
    norm = _inf_norm(dx)
    tol = eps * norm
    a_dx = data.Ax(dx)
    in_cone = (
        ((data.u > _INF_THRESHOLD) | (a_dx <= tol))
        & ((data.l < -_INF_THRESHOLD) | (a_dx >= -tol))
    ).all(0)
    return (
        (norm > torch.finfo(dx.dtype).tiny)
        & ((data.q * dx).sum(0) < -tol)
        & (_inf_norm(_mv(data.P, dx)) < tol)
        & in_cone
    )


def _admm(
    data: _Data, state: _State, rho: Tensor, inverse: Tensor, settings: QPSettings
) -> _Outcome:
    """Run ADMM on every instance of ``data`` until each one terminates.

    An instance is written to the output at the check where it terminates and stops
    counting from then on (``running``); the working set is compacted to the running
    instances once enough of it has finished to pay for the gather.

    Args:
        data: the problems, batch-last.
        state: starting iterate.
        rho: (B,) starting rho per instance.
        inverse: (n, n, B) KKT inverse for ``rho`` (see :func:`_kkt_inverse`);
            owned by the call: refactorisations overwrite it in place.
        settings: solver settings.
    """
    batch = data.q.shape[-1]
    device = data.q.device
    out_x, out_z, out_y = (t.clone() for t in state)
    zeros = torch.zeros(batch, dtype=data.q.dtype, device=device)
    out = {
        "n_iter": torch.zeros(batch, dtype=torch.int64, device=device),
        "status": torch.full((batch,), int(QPStatus.MAX_ITER), device=device),
        "prim_res": zeros.clone(),
        "dual_res": zeros.clone(),
    }
    # Residuals below about a hundred ulps of the quantities they difference are
    # round-off (float32 reaches it on badly scaled instances): never ask for less.
    # An instance whose residuals stop shrinking (``_STALL_CHECKS`` checks without a
    # 10 % gain) is accepted at the looser ``_STALL_ULPS`` floor instead of running
    # to max_iter on round-off; in float64 both floors are far below any tolerance.
    ulp = torch.finfo(data.q.dtype).eps
    eps_rel = settings.eps_rel + _ROUNDOFF_ULPS * ulp
    eps_rel_stalled = settings.eps_rel + _STALL_ULPS * ulp
    best = torch.full_like(rho, math.inf)  # (B,) best normalised residual so far
    since_best = torch.zeros_like(rho)  # (B,) checks since it last improved
    active = torch.arange(batch, device=device)  # global index of the working set
    running = torch.ones(batch, dtype=torch.bool, device=device)
    rho_vec = _rho_vector(rho, data)
    done_iter = 0
    while batch and done_iter < settings.max_iter:
        steps = min(settings.check_every, settings.max_iter - done_iter)
        for _ in range(steps - 1):
            state = _admm_step(data, state, rho_vec, inverse, settings)
        previous = state
        state = _admm_step(data, state, rho_vec, inverse, settings)
        done_iter += steps

        # OSQP's residuals and tolerances, per instance.
        ax, px, aty = data.Ax(state.x), _mv(data.P, state.x), data.Aty(state.y)
        prim_res = _inf_norm(ax - state.z)
        dual_res = _inf_norm(px + data.q + aty)
        prim_scale = torch.maximum(_inf_norm(ax), _inf_norm(state.z))
        dual_scale = torch.maximum(
            torch.maximum(_inf_norm(px), _inf_norm(aty)), _inf_norm(data.q)
        )
        prim_tol = settings.eps_abs + eps_rel * prim_scale
        dual_tol = settings.eps_abs + eps_rel * dual_scale
        prim_ok, dual_ok = prim_res <= prim_tol, dual_res <= dual_tol
        normalised = torch.maximum(prim_res / prim_tol, dual_res / dual_tol)
        improved = normalised < 0.9 * best
        best = torch.where(improved, normalised, best)
        since_best = torch.where(improved, 0, since_best + 1)
        stalled = (
            (since_best >= _STALL_CHECKS)
            & (prim_res <= settings.eps_abs + eps_rel_stalled * prim_scale)
            & (dual_res <= settings.eps_abs + eps_rel_stalled * dual_scale)
        )
        solved = (prim_ok & dual_ok) | stalled
        prim_inf, prim_cert = _primal_certificate(
            data, state.y - previous.y, settings.eps_prim_inf
        )
        prim_inf &= ~prim_ok & ~solved  # OSQP tests it only while not converged
        dual_cert = state.x - previous.x
        dual_inf = _dual_certificate(data, dual_cert, settings.eps_dual_inf)
        dual_inf &= ~dual_ok & ~solved & ~prim_inf

        finished = solved | prim_inf | dual_inf
        if done_iter >= settings.max_iter:
            finished = torch.ones_like(finished)
        rows = (finished & running).nonzero().squeeze(1)
        if rows.numel():
            status = torch.full_like(rows, int(QPStatus.MAX_ITER))
            status[solved[rows]] = int(QPStatus.SOLVED)
            status[prim_inf[rows]] = int(QPStatus.PRIMAL_INFEASIBLE)
            status[dual_inf[rows]] = int(QPStatus.DUAL_INFEASIBLE)
            where = active[rows]
            # OSQP returns the infeasibility certificates in place of the iterate;
            # here scaled to unit inf-norm (the ADMM step itself grows like 1/sigma).
            dual_cert = dual_cert[:, rows] / _inf_norm(dual_cert[:, rows])
            prim_cert = prim_cert[:, rows] / _inf_norm(prim_cert[:, rows])
            out_x[:, where] = torch.where(dual_inf[rows], dual_cert, state.x[:, rows])
            out_y[:, where] = torch.where(prim_inf[rows], prim_cert, state.y[:, rows])
            out_z[:, where] = state.z[:, rows]
            out["status"][where] = status
            out["n_iter"][where] = done_iter
            out["prim_res"][where] = prim_res[rows]
            out["dual_res"][where] = dual_res[rows]
            running[rows] = False
            n_running = int(running.sum())
            if not n_running:
                break
            if n_running <= (1 - _COMPACT_FRACTION) * running.numel():
                keep = running.nonzero().squeeze(1)
                active, running = active[keep], running[keep]
                data = data.take(keep)
                state = _State(*(_take(t, keep) for t in state))
                rho, rho_vec = rho[keep], _take(rho_vec, keep)
                best, since_best = best[keep], since_best[keep]
                inverse = _take(inverse, keep)
                prim_res, dual_res = prim_res[keep], dual_res[keep]
                prim_scale, dual_scale = prim_scale[keep], dual_scale[keep]

        if settings.adaptive_rho:
            # OSQP's estimate: balance the normalised primal and dual residuals.
            ratio = (prim_res / (prim_scale + 1e-10)) / (
                dual_res / (dual_scale + 1e-10) + 1e-10
            )
            new_rho = (rho * ratio.sqrt()).clamp(_RHO_MIN, _RHO_MAX)
            tol = settings.adaptive_rho_tolerance
            change = running & ((new_rho > tol * rho) | (new_rho < rho / tol))
            change = change.nonzero().squeeze(1)
            if change.numel():
                rho = rho.index_copy(0, change, new_rho[change])
                sub = data.take(change)
                sub_rho_vec = _rho_vector(rho[change], sub)
                rho_vec = _put_(rho_vec, change, sub_rho_vec)
                _put_(inverse, change, _kkt_inverse(sub, sub_rho_vec, settings.sigma))
    return _Outcome(out_x, out_z, out_y, **out)


# --------------------------------------------------------------------------------------
# Polish.


def _active_set(data: _Data, z: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """OSQP's guess of the active bounds from the ADMM iterate: (m, B) bool each.

    A row is at its lower bound if ``z - l < -y``, at its upper bound if ``u - z < y``;
    an equality row (``l == u``) is always active, on whichever side ``y`` says.
    """
    lower = (z - data.l) < -y
    upper = ~lower & ((data.u - z) < y)
    equality = data.l == data.u
    return lower | (equality & ~upper), upper


def _polish_box(
    data: _Data, lower: Tensor, upper: Tensor, definite: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Exact solve with the active variables fixed at their bounds (A = I).

    With ``F`` the free variables: ``P_FF x_F = -q_F - P_FA x_A``. The system is
    written at full size, the active rows and columns replaced by the identity, so the
    whole batch is one Cholesky. Where ``P`` may be only semidefinite,
    ``P_FF + delta I`` is factorised and iterative refinement removes the ``delta``
    (OSQP's polish); where ``P`` is known to be definite, ``P_FF`` is factorised as
    it is and one solve is exact.

    Args:
        data: the problems (``A is None``).
        lower, upper: (n, B) bool, the variables fixed at each bound.
        definite: optional (B,) bool, True where ``P`` is positive definite.

    Returns:
        x: (n, B); y: (n, B) multipliers, ``-(Px + q)`` on active rows, 0 elsewhere;
        px: (n, B) ``P x``.
    """
    active = lower | upper
    free = (~active).to(data.P.dtype)  # (n, B)
    fixed = torch.where(lower, data.l, data.u) * active  # (n, B) x_A, 0 where free
    # [P_FF + delta, 0; 0, I]: P_FF in place, identity on the active rows/columns.
    regular = data.P * free[:, None, :]
    regular.mul_(free[None, :, :])
    delta = free * _POLISH_DELTA  # (n, B)
    if definite is not None:
        delta = delta * ~definite
    torch.diagonal(regular, 0, 0, 1).add_((active + delta).T)
    L, _ = _cholesky(regular, False)
    rhs = fixed + free * (-data.q - _mv(data.P, fixed))
    x = _cholesky_solve(L, rhs)
    if definite is None or not bool(definite.all()):
        for _ in range(_POLISH_REFINE):
            residual = rhs - _mv(regular, x) + delta * x  # of the exact system
            x = x + _cholesky_solve(L, residual)
    px = _mv(data.P, x)
    y = -(px + data.q) * active
    return x, y, px


def _polish_general(data: _Data, lower: Tensor, upper: Tensor) -> tuple[Tensor, Tensor]:
    """Exact solve of the reduced KKT system of the guessed active set (general A).

    ``[[P + delta I, A_a'], [A_a, -delta I]] [x; y_a] = [-q; b_a]`` (OSQP's polish),
    written at size ``n + m`` with the inactive rows reduced to ``-y_i = 0`` so the
    batch is one LU; iterative refinement against ``delta = 0`` removes the
    regularisation.

    Returns:
        x: (n, B); y: (m, B).
    """
    assert data.A is not None
    n = data.q.shape[0]
    active = lower | upper
    act = active.to(data.P.dtype)  # (m, B)
    A = data.A.permute(2, 0, 1) * act.T[:, :, None]  # (B, m, n), inactive rows zero
    P = data.P.permute(2, 0, 1)  # (B, n, n)
    eye_n = torch.eye(n, dtype=P.dtype, device=P.device)
    exact = torch.cat(
        (
            torch.cat((P, A.transpose(1, 2)), 2),
            torch.cat((A, torch.diag_embed(act.T - 1)), 2),
        ),
        1,
    )  # (B, n + m, n + m); inactive rows read -y_i = 0
    regular = exact.clone()
    regular[:, :n, :n] += _POLISH_DELTA * eye_n
    regular[:, n:, n:] -= torch.diag_embed(_POLISH_DELTA * act.T)
    bound = torch.where(lower, data.l, data.u) * act  # (m, B)
    rhs = torch.cat((-data.q, bound), 0).T[:, :, None]  # (B, n + m, 1)
    factors, pivots = torch.linalg.lu_factor(regular)
    sol = torch.linalg.lu_solve(factors, pivots, rhs)
    for _ in range(_POLISH_REFINE):
        sol = sol + torch.linalg.lu_solve(factors, pivots, rhs - exact @ sol)
    sol = sol[:, :, 0].T  # (n + m, B)
    return sol[:n], sol[n:]


# --------------------------------------------------------------------------------------
# Box QPs whose active bounds are a leading block: exact solves without refactorising.


def _ul_cholesky(M: Tensor) -> tuple[Tensor, Tensor]:
    """Upper triangular ``U`` with ``M = U U'`` for symmetric ``M: (n, n, B)``.

    It is the Cholesky factor of ``M`` with its rows and columns reversed, and it
    factorises every trailing block at once: row ``i`` of ``U`` is zero left of
    ``i``, so ``M[k:, k:] = U[k:, k:] U[k:, k:]'``. Fixing the first ``k`` variables
    of a box QP therefore needs no new factorisation (see :func:`_leading_solve`).

    Returns:
        U: (n, n, B), strict lower triangle uninitialised; ok: (B,) bool as in
        :func:`_cholesky`.
    """
    L, ok = _cholesky(M.flip(0, 1))
    return L.flip(0, 1), ok


class _LeadingFactor(NamedTuple):
    """Per-``P`` factors of the leading-block stage (:func:`_leading_factor`)."""

    U: Tensor  # (n, n, B) upper triangular, P = U U', zero below the diagonal
    diag: Tensor  # (n, B) diag(U)
    inv_diag: Tensor  # (n, B) 1 / diag(U)
    # (B * n, 2 n): row b n + j is column j of instance b's D = U'^{-1} diag(U)
    # (unit lower triangular), then column j of its U. Batch-first, so that one
    # instance's column is one contiguous gather (see :func:`_boundary_step`).
    columns: Tensor
    # (n + 1, B): max_{i >= k} ||U[i, :]||_1 in row k, 0 in row n; bounds the back
    # substitution's residual (see :func:`_leading_data`).
    tail_row_norm: Tensor


def _leading_factor(P: Tensor) -> tuple[_LeadingFactor, Tensor]:
    """The factors of :func:`_leading_solve` and :func:`_boundary_step` for
    symmetric ``P: (n, n, B)``.

    ``D = U'^{-1} diag(U)``: column ``j`` is how the trailing block ``x_{j+1..}``
    moves, re-optimised, per unit move of ``x_j`` with ``x_{..j-1}`` fixed (row
    ``j`` is 1). It turns fixing or freeing one bound at the end of a leading
    block into a rank-one update. Computed by one forward substitution through
    ``U'`` for all ``n`` columns at once (``n^3 / 6`` multiply-adds per instance).

    Returns:
        the factors; ok: (B,) bool as in :func:`_cholesky`.
    """
    U, ok = _ul_cholesky(P)
    n, batch = P.shape[0], P.shape[-1]
    rows = torch.arange(n, device=P.device)
    upper_triangle = (rows[:, None] <= rows[None, :])[:, :, None]  # (n, n, 1)
    U = torch.where(upper_triangle, U, 0)  # the lower triangle was uninitialised
    diag = torch.diagonal(U, 0, 0, 1).T.contiguous()  # (n, B)
    inv_diag = diag.reciprocal()
    D = torch.zeros_like(U)
    # r[i, c] = -sum_{m < i} U[m, i] D[m, c]; row m of D is r[m] / U[m, m] left of
    # the diagonal, 1 on it.
    r = torch.zeros_like(U)
    for m in range(n):
        D[m, :m] = r[m, :m] * inv_diag[m]
        D[m, m] = 1
        if m < n - 1:
            r[m + 1 :, : m + 1].addcmul_(
                U[m, m + 1 :, None], D[m, None, : m + 1], value=-1
            )
    # [b, j, s, i] = (D, U)[s][i, j, b]
    columns = torch.stack((D, U)).permute(3, 2, 0, 1).reshape(batch * n, 2 * n)
    tail_row_norm = torch.cat((U.abs().sum(1), U.new_zeros(1, batch)))  # (n + 1, B)
    for i in reversed(range(n)):
        torch.maximum(tail_row_norm[i], tail_row_norm[i + 1], out=tail_row_norm[i])
    return _LeadingFactor(U, diag, inv_diag, columns, tail_row_norm), ok


class _LeadingCall(NamedTuple):
    """What the leading-block stage knows of one call's problems, over the call's
    batch (:func:`_leading_data`); no active set changes it."""

    factor: _LeadingFactor  # over the factors' batch
    cols: Tensor | None  # (B,) int64 the problems' instances of it; None: the same
    U: Tensor  # (n, n, B) the problems' U (the factor's own where cols is None)
    diag: Tensor  # (n, B)
    inv_diag: Tensor  # (n, B)
    g: Tensor  # (n, B) U^{-1} q
    tail_residual: Tensor  # (n + 1, B) max_{i >= k} |U g - q|_i in row k; 0 in row n
    # (B, n) each: l and u as the caller gave them (batch-first, possibly
    # broadcast): a working set's rows of them are a cheap gather. None: use l, u.
    given_bounds: tuple[Tensor, Tensor] | None


class _Leading(NamedTuple):
    """A working set of a call's box QPs (A = I), batch-last: the vectors every
    pass reads. The rest stays in ``call``, gathered only for a new solve."""

    call: _LeadingCall
    rows: Tensor | None  # (b,) int64 positions in the call; None: all, in order
    l: Tensor  # (n, b)  # noqa: E741
    u: Tensor  # (n, b)
    q_norm: Tensor  # (b,) ||q||_inf
    inequality: Tensor | None  # (n, b) float, 0 on rows with l == u; None: no such row

    def take(self, idx: Tensor) -> _Leading:
        """Instances ``idx`` of the working set."""
        rows = idx if self.rows is None else self.rows[idx]
        inequality = None if self.inequality is None else _take(self.inequality, idx)
        if self.call.given_bounds is None:
            l, u = _take(self.l, idx), _take(self.u, idx)  # noqa: E741
        else:  # from the batch-first bounds as given: contiguous rows
            l, u = (  # noqa: E741
                _transpose(t.index_select(0, rows).to(self.l.dtype)).clamp_(
                    -INFTY, INFTY
                )
                for t in self.call.given_bounds
            )
        return _Leading(self.call, rows, l, u, self.q_norm[idx], inequality)

    def solve_data(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``U, diag, inv_diag, g`` of the working set (gathered unless it is the
        whole call)."""
        call, rows = self.call, self.rows
        if rows is None:
            return call.U, call.diag, call.inv_diag, call.g
        if _few(rows, call.U.shape[-1]):
            U = _upper_columns(call.factor, self.factor_cols())
        else:
            U = _take(call.U, rows)
        return (
            U,
            _take(call.diag, rows),
            _take(call.inv_diag, rows),
            _take(call.g, rows),
        )

    def factor_cols(self) -> Tensor:
        """(b,) int64 the working set's instances of ``call.factor``."""
        cols, rows = self.call.cols, self.rows
        if rows is None:
            rows = torch.arange(self.l.shape[-1], device=self.l.device)
        return rows if cols is None else cols[rows]

    def tail_residual(self, k: Tensor) -> Tensor:
        """(b,) the back substitution's residual, max over the rows from ``k``."""
        table = self.call.tail_residual  # (n + 1, B)
        rows = self.rows
        if rows is None:
            return table.gather(0, k[None])[0]
        return table.reshape(-1)[k * table.shape[-1] + rows]


def _sweep_slices(t: Tensor) -> list[slice]:
    """Even batch slices of a sweep's accumulator ``t: (n, B)`` (see
    ``_SWEEP_BYTES``); one slice, the whole batch, where it fits."""
    batch = t.shape[-1]
    per = max(1, _SWEEP_BYTES // max(1, t.shape[0] * t.element_size()))
    size = -(-batch // -(-batch // per)) if batch else 1  # ceil(batch / slices)
    return [slice(start, start + size) for start in range(0, batch, size)]


def _back_substitute(U: Tensor, inv_diag: Tensor, q: Tensor) -> Tensor:
    """``g = U^{-1} q`` for upper triangular ``U: (n, n, B)``, ``q: (n, B)``.

    Column by column, one fused ``(rows, b)`` operation per column and batch slice
    (:func:`_sweep_slices`): ``n^2 / 2`` multiply-adds. ``inv_diag``: (n, B)
    ``1 / diag(U)``.
    """
    n = q.shape[0]
    g = q.clone()
    for part in _sweep_slices(g):
        g_, U_, inv_ = g[:, part], U[..., part], inv_diag[:, part]
        for j in reversed(range(n)):
            g_[j].mul_(inv_[j])
            if j:
                g_[:j].addcmul_(U_[:j, j], g_[j], value=-1)
    return g


def _tail_residual(U: Tensor, g: Tensor, q: Tensor) -> Tensor:
    """(n + 1, B): ``max_{i >= k} |U g - q|_i`` in row ``k``, 0 in row ``n``.

    The residual is recomputed from ``U`` and ``g``, not carried over from the
    substitution, so that round-off growth in it (an ill-conditioned ``U``)
    shows.
    """
    n = q.shape[0]
    table = q.new_empty(n + 1, q.shape[-1])
    residual = torch.neg(q, out=table[:n])
    for j in range(n):
        residual[: j + 1].addcmul_(U[: j + 1, j], g[j])
    residual.abs_()
    table[n] = 0
    for i in reversed(range(n)):  # a running max from the bottom (cummax is slow)
        torch.maximum(table[i], table[i + 1], out=table[i])
    return table


def _upper_columns(factor: _LeadingFactor, cols: Tensor) -> Tensor:
    """(n, n, b) ``U`` of instances ``cols``, from its batch-first copy in
    ``factor.columns`` (``[b, j, 1, i] = U[i, j, b]``): for a few instances."""
    n = factor.diag.shape[0]
    picked = factor.columns.view(-1, n, 2, n).index_select(0, cols)  # (b, n, 2, n)
    return picked[:, :, 1, :].permute(2, 1, 0).contiguous()


def _leading_data(
    factor: _LeadingFactor,
    q: Tensor,
    l: Tensor,  # noqa: E741
    u: Tensor,
    settings: QPSettings,
    cols: Tensor | None = None,
    equality: bool = True,
    given_bounds: tuple[Tensor, Tensor] | None = None,
) -> _Leading:
    """The problems as the leading-block stage's working set, with the per-call
    quantities that no active set changes.

    ``g = U^{-1} q`` serves every active-set pass, and so does the residual of that
    back substitution: with the leading block ``A`` fixed, the stationarity residual
    ``P x + q`` on the free rows ``F = {k, ..}`` is ``(U g - q)_F`` (see
    :func:`_leading_solve`), so its max over ``F`` is a lookup in ``tail_residual``.

    The table holds a bound of the residual rather than the residual where the
    bound is already below the acceptance floor: substitution is backward stable,
    ``|U g - q| <= gamma_{n+1} |U| |g|`` componentwise with
    ``gamma_m = m u / (1 - m u)``, ``u`` the unit round-off (Higham 2002, "Accuracy
    and Stability of Numerical Algorithms", Theorem 8.5; ``n + 1`` for the product
    with the reciprocal pivot), and ``(|U| |g|)_i <= ||U[i, :]||_1 ||g||_inf``,
    with the row norms cached per ``P``. Where the bound is not that small (an
    ill-conditioned ``U``, a tight tolerance) the residual is computed, one more
    substitution's worth of work, on those instances only.

    Args:
        factor: from :func:`_leading_factor`.
        q, l, u: (n, b) the problems.
        settings: for the acceptance floor.
        cols: optional (b,) instances of ``factor`` that the problems belong to.
        equality: False if no row has ``l == u`` (saves looking).
        given_bounds: optional (b, n) each, ``l`` and ``u`` as the caller gave them
            (batch-first), for gathering working sets.
    """
    diag, inv_diag = factor.diag, factor.inv_diag
    U = factor.U
    if cols is not None:
        diag, inv_diag = _take(diag, cols), _take(inv_diag, cols)
        few = _few(cols, factor.diag.shape[-1])
        U = _upper_columns(factor, cols) if few else _take(U, cols)
    n = q.shape[0]
    g = _back_substitute(U, inv_diag, q)
    # gamma_{n+2}: one more rounding than the substitution's, for the bound's own.
    unit_roundoff = torch.finfo(q.dtype).eps / 2
    gamma = (n + 2) * unit_roundoff / (1 - (n + 2) * unit_roundoff)
    tail_row_norm = factor.tail_row_norm
    if cols is not None:
        tail_row_norm = _take(tail_row_norm, cols)
    tail_residual = tail_row_norm * (gamma * _inf_norm(g))  # (n + 1, b) bounds
    q_norm = _inf_norm(q)
    # The dual floor's scale is at least ||q||: where the bound clears the floor at
    # that scale it clears it in any pass.
    loose = (tail_residual[0] > _roundoff_floor(q_norm, settings)).nonzero()[:, 0]
    if loose.numel():
        if _few(loose, q.shape[-1]):
            sub_cols = loose if cols is None else cols[loose]
            sub = _upper_columns(factor, sub_cols), _take(g, loose), _take(q, loose)
            _put_(tail_residual, loose, _tail_residual(*sub))
        else:
            tail_residual = _tail_residual(U, g, q)
    inequality = None
    if equality and bool((l == u).any()):
        inequality = (l != u).to(q.dtype)
    call = _LeadingCall(factor, cols, U, diag, inv_diag, g, tail_residual, given_bounds)
    return _Leading(call, None, l, u, q_norm, inequality)


def _is_leading(active: Tensor) -> Tensor:
    """(n, B) bool -> (B,) bool: the True rows are ``0 .. k-1`` for some ``k``."""
    return ~(active[1:] & ~active[:-1]).any(0)


class _LeadingSolution(NamedTuple):
    """An exact solution on a guessed leading active set."""

    x: Tensor  # (n, B)
    y: Tensor  # (n, B) multipliers -(P x + q) on the fixed rows, 0 elsewhere
    signed: Tensor  # (n, B) y times +1 / -1 on rows fixed at the lower / upper bound
    k: Tensor  # (B,) int64 fixed rows


def _leading_guess(data: _Leading, x: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """The guess a leading-block solution ``x: (n, B)`` with ``k: (B,)`` fixed rows
    was computed on: rows ``< k``, each at the bound it sits on. Exact: the solves
    and the boundary steps leave a fixed row at its bound to the bit, and a row
    with ``l == u`` counts as at its lower bound, as when the guess was made.

    Returns:
        lower, upper: (n, B) bool.
    """
    fixed = torch.arange(x.shape[0], device=x.device)[:, None] < k[None]
    lower = fixed & (x == data.l)
    return lower, fixed & ~lower


def _signed(data: _Leading, y: Tensor, sign: Tensor) -> Tensor:
    """``y`` times ``sign`` (+1 / -1 on the rows fixed at their lower / upper
    bound, 0 on the free rows; overwritten), 0 on equality rows (whose multiplier
    may have either sign)."""
    if data.inequality is not None:
        sign.mul_(data.inequality)
    return sign.mul_(y)


def _leading_solve(data: _Leading, lower: Tensor, upper: Tensor) -> _LeadingSolution:
    """Exact solution with the leading block ``A = {0 .. k-1}`` fixed at its bounds.

    With ``F`` the trailing free block and ``P = U U'`` (:func:`_ul_cholesky`),
    ``P_FF = U_FF U_FF'`` and ``P_FA = U_FF U_AF'``, so the reduced system
    ``P_FF x_F = -q_F - P_FA x_A`` reads ``(U' x)_F = -g_F`` with ``g = U^{-1} q``
    (``g_F = U_FF^{-1} q_F``): one forward substitution through the lower triangular
    ``U'`` in which the fixed rows take their bound instead of being solved for.
    The multipliers need only the ``k x k`` block: with ``s = U_AA' x_A + g_A``,
    ``y_A = -(P x + q)_A = -U_AA s_A`` (expand ``P_AA``, ``P_AF`` and use
    ``q_A = U_AA g_A + U_AF g_F``), and on ``F`` the stationarity residual is the
    back substitution's, ``(P x + q)_F = (U g - q)_F``. Cost: ``n^2 / 2`` multiply-
    adds for ``x`` and ``k^2 / 2`` for ``y`` (the batch pays for its largest ``k``),
    against ``n^3 / 6`` for a new Cholesky. Each loop runs over columns, one fused
    operation on ``(rows, b)`` per column and batch slice (:func:`_sweep_slices`).

    Args:
        data: the problems (:func:`_leading_data`); lower, upper: (n, B) bool, the
            fixed bounds, a leading block in every instance (:func:`_is_leading`).
    """
    U, diag, inv_diag, g = data.solve_data()
    n = g.shape[0]
    # Masks as 0/1 floats: arithmetic on them is several times faster on CPU than
    # torch.where with a bool condition.
    at_lower, at_upper = lower.to(U.dtype), upper.to(U.dtype)
    active = at_lower + at_upper  # (n, B) 1 on the fixed rows
    x = torch.addcmul(data.l * at_lower, data.u, at_upper)  # (n, B) x_A, 0 on F
    solve = torch.addcmul(inv_diag, active, inv_diag, value=-1)  # 0 on A
    # Forward substitution: r_j = -g_j - sum_{i<j} U[i, j] x_i, then x_j = r_j /
    # U[j, j] on F (x_j stays at its bound on A). r_j is final once column j is read.
    r = g.neg()
    for part in _sweep_slices(r):  # batch slices: see _SWEEP_BYTES
        x_, r_, U_, solve_ = x[:, part], r[:, part], U[..., part], solve[:, part]
        for j in range(n):
            x_[j].addcmul_(r_[j], solve_[j])
            if j < n - 1:
                r_[j + 1 :].addcmul_(U_[j, j + 1 :], x_[j], value=-1)
    k = active.sum(0).long()  # (B,)
    depth = int(k.max()) if k.numel() else 0
    y = torch.zeros_like(x)
    if depth:
        # -s_A = r_A - diag_A x_A (r_j holds -g_j - (U' x)_j + U[j, j] x_j), 0 on F.
        minus_s = torch.addcmul(r[:depth], diag[:depth], x[:depth], value=-1)
        minus_s.mul_(active[:depth])
        for part in _sweep_slices(y):
            y_, U_, m_ = y[:, part], U[..., part], minus_s[:, part]
            for j in range(depth):  # y_A = U_AA (-s_A); rows of F stay 0
                y_[: j + 1].addcmul_(U_[: j + 1, j], m_[j])
    return _LeadingSolution(x, y, _signed(data, y, at_lower.sub_(at_upper)), k)


def _columns(factor: _LeadingFactor, j: Tensor, cols: Tensor) -> Tensor:
    """Columns ``j_b`` of ``D`` and of ``U`` of instances ``cols_b``: (2, n, b)."""
    n = factor.diag.shape[0]
    picked = factor.columns.index_select(0, cols * n + j)  # (b, 2 n)
    return picked.T.reshape(2, n, -1)


def _boundary_step(
    data: _Leading,
    solution: _LeadingSolution,
    j: Tensor,
    lower: Tensor,
    upper: Tensor,
) -> _LeadingSolution:
    """The exact solution after fixing or freeing one bound at the end of the block.

    With ``A = {0 .. k-1}`` fixed, fixing ``x_k`` at its bound, or freeing
    ``x_{k-1}``, moves ``x_j`` (``j = k`` or ``k - 1``) by some ``delta`` and the
    trailing free block with it, re-optimised: ``x' = x + delta D[:, j]``
    (:func:`_leading_factor`). Since ``U' D[:, j] = U[j, j] e_j``, the gradient
    moves by ``P D[:, j] delta = U[:, j] U[j, j] delta``: nothing on the rows after
    ``j``, so they stay stationary; a fixed ``x_j`` gets the multiplier
    ``-U[j, j]^2 delta``, and a freed one becomes stationary for
    ``delta = y_j / U[j, j]^2``. Two columns gathered per instance and a few
    vector operations, instead of a solve.

    Args:
        data: the problems; solution: on the current block, (n, b).
        j: (b,) int64 the bound that changes.
        lower, upper: (n, b) bool, the new guess: the current one with bound ``j``
            fixed or freed.
    """
    factor, cols = data.call.factor, data.factor_cols()
    # d: (n, b) 0 above row j, 1 on it; column: (n, b) U[:, j], 0 below row j.
    d, column = _columns(factor, j, cols)
    pivot = factor.diag.reshape(-1)[j * factor.diag.shape[-1] + cols]  # (b,) U[j, j]
    at = j[None]
    fixed_lower, fixed_upper = lower.gather(0, at)[0], upper.gather(0, at)[0]
    grow = fixed_lower | fixed_upper  # (b,) bound j is fixed, else freed
    bound = torch.where(fixed_lower, data.l.gather(0, at)[0], data.u.gather(0, at)[0])
    x_j, y_j = solution.x.gather(0, at)[0], solution.y.gather(0, at)[0]
    delta = torch.where(grow, bound - x_j, y_j / pivot.square())  # (b,)
    x = torch.addcmul(solution.x, d, delta)
    y = torch.addcmul(solution.y, column, delta * pivot, value=-1)
    # Row j exactly: the bound where it is fixed, a zero multiplier where freed.
    x.scatter_(0, at, torch.where(grow, bound, x.gather(0, at)[0])[None])
    y.scatter_(0, at, torch.where(grow, y.gather(0, at)[0], 0)[None])
    # (Clamped: instances that are not one bound away from the guess get garbage.)
    k = (solution.k + torch.where(grow, 1, -1)).clamp_(0, x.shape[0])
    sign = lower.to(y.dtype).sub_(upper.to(y.dtype))
    return _LeadingSolution(x, y, _signed(data, y, sign), k)


def _roundoff_floor(scale: Tensor, settings: QPSettings) -> Tensor:
    """(B,) the acceptance floor of a residual whose quantities are of size
    ``scale``: a hundred ulps of it, capped at the termination tolerance (see
    :func:`_kkt_accept`). Increasing in ``scale``."""
    ulp = torch.finfo(scale.dtype).eps
    eps_rel = settings.eps_rel + _ROUNDOFF_ULPS * ulp
    return torch.minimum(100 * ulp * (1 + scale), settings.eps_abs + eps_rel * scale)


def _leading_accept(
    data: _Leading, solution: _LeadingSolution, settings: QPSettings
) -> Tensor:
    """(B,) bool: is the leading-block solution optimal, to round-off?

    The same test as :func:`_kkt_accept` (OSQP's residuals against a round-off
    floor, and the signs of the active multipliers), computed from what the
    leading-block solves know: ``y_A = -(P x + q)_A`` holds by construction, the
    residual on ``F`` is looked up in ``tail_residual``, and the fixed rows sit
    exactly on their bounds, so the primal residual is the bound violation of the
    free rows. The dual scale omits ``||P x||`` (about ``||q|| + ||y||``), which
    only tightens the floor.
    """
    x, signed = solution.x, solution.signed
    prim_res = torch.maximum((x - data.u).amax(0), (data.l - x).amax(0)).clamp_min_(0)
    # Where x is in the box (prim_res == 0: then x is finite, NaN propagates) the
    # primal test holds whatever its floor; ||x|| is needed only elsewhere.
    prim_ok = prim_res == 0
    outside = (~prim_ok).nonzero()[:, 0]
    if outside.numel():
        x_norm = _inf_norm(_take(x, outside))
        prim_ok[outside] = (
            prim_res[outside] <= _roundoff_floor(x_norm, settings)
        ) & torch.isfinite(x_norm)
    dual_res = data.tail_residual(solution.k)  # max over F
    # signed y: <= 0 on a correctly signed active row, 0 on F; |signed| = |y| on
    # inequality rows.
    sign_error = signed.amax(0)
    y_norm = torch.maximum(sign_error, signed.amin(0).neg_())
    if data.inequality is not None:
        y_norm = _inf_norm(solution.y)
    dual_floor = _roundoff_floor(torch.maximum(data.q_norm, y_norm), settings)
    return (
        prim_ok
        & (dual_res <= dual_floor)
        & (sign_error <= dual_floor)
        & torch.isfinite(y_norm)  # amax propagates NaN
    )


def _active_set_step(
    data: _Leading, solution: _LeadingSolution, lower: Tensor, upper: Tensor
) -> tuple[Tensor, Tensor]:
    """The primal-dual active-set step (Hintermueller, Ito & Kunisch 2002): free
    the bounds with a wrong-signed multiplier, fix the bounds ``x`` violates.

    Returns:
        the new guess: lower, upper (n, B) bool.
    """
    wrong_sign = solution.signed > 0
    new_lower = (lower & ~wrong_sign) | (solution.x < data.l)
    new_upper = ((upper & ~wrong_sign) | (solution.x > data.u)) & ~new_lower
    return new_lower, new_upper


class _Unfinished(NamedTuple):
    """Instances an active-set stage hands on, with its last guess of the bounds."""

    rows: Tensor  # (b,) int64
    lower: Tensor  # (n, b) bool
    upper: Tensor  # (n, b) bool


class _LeadingOutcome(NamedTuple):
    """What :func:`_leading_active_set` solved, over the whole batch."""

    x: Tensor  # (n, B) solutions where ``solved``, garbage elsewhere
    y: Tensor  # (n, B)
    solved: Tensor  # (B,) bool
    constrained: Tensor  # (B,) bool, solved with at least one active bound
    unfinished: _Unfinished


def _leading_active_set(
    data: _Leading,
    lower: Tensor,
    upper: Tensor,
    running: Tensor,
    settings: QPSettings,
    passes: int,
) -> _LeadingOutcome:
    """Primal-dual active-set steps (Hintermueller, Ito & Kunisch 2002) on leading
    blocks, for as long as the guessed active set is one.

    On the MPC QPs it nearly always is: the bounds that bind are the first inputs of
    the plan. The first pass solves every running instance (:func:`_leading_solve`,
    masked: the finished ones' solves are wasted unless fewer than half run); the
    later ones only the instances still running, compacted: where the active-set
    step fixes or frees one bound at the end of the block (most of them: the block
    grew or shrank by one since the guess) by a rank-one update
    (:func:`_boundary_step`), otherwise by a new solve. An instance leaves for the
    general stage (:func:`_refine`) with its current guess once the guess is not a
    leading block, or after ``passes`` solves. A first guess with no active bound
    makes the first pass the unconstrained minimiser (BoxQP's fast path).

    Args:
        data: the problems (:func:`_leading_data`, positive definite ``P``).
        lower, upper: (n, B) bool, the first guess.
        running: (B,) bool, the instances to solve.
        settings: for the tolerances of the acceptance test.
        passes: solves per instance at most.
    """
    batch = data.l.shape[-1]
    rows = torch.arange(batch, device=data.l.device)
    unfinished: list[_Unfinished] = []

    def hand_on(which: Tensor, lower: Tensor, upper: Tensor) -> None:
        idx = which.nonzero().squeeze(1)
        if idx.numel():
            unfinished.append(
                _Unfinished(rows[idx], _take(lower, idx), _take(upper, idx))
            )

    # Pass 1, on the first guesses.
    leading = _is_leading(lower | upper)
    hand_on(running & ~leading, lower, upper)
    running = running & leading
    if int(running.sum()) < _LEADING_COMPACT * batch:
        keep = running.nonzero().squeeze(1)
        rows, data, running = rows[keep], data.take(keep), running[keep]
        lower, upper = _take(lower, keep), _take(upper, keep)
    solution = _leading_solve(data, lower, upper)
    accept = _leading_accept(data, solution, settings) & running
    if rows.numel() == batch:
        # The whole batch in order: its solutions are the output as they stand.
        x_out, y_out = solution.x, solution.y
        solved, constrained = accept, accept & (solution.k > 0)
    else:
        x_out = data.l.new_zeros(data.l.shape[0], batch)
        y_out = torch.zeros_like(x_out)
        solved = torch.zeros(batch, dtype=torch.bool, device=x_out.device)
        constrained = torch.zeros_like(solved)
        _put_(x_out, rows, solution.x)
        _put_(y_out, rows, solution.y)
        solved[rows] = accept
        constrained[rows] = accept & (solution.k > 0)

    for _ in range(passes - 1):
        rejected = running & ~accept
        count = int(rejected.sum())
        if not count:
            break
        whole = rows.numel() == batch and count >= _LEADING_COMPACT * batch
        if not whole:
            # Only the rejected instances from here on, compacted (their vectors;
            # the factors stay whole).
            keep = rejected.nonzero().squeeze(1)
            rows, data, rejected = rows[keep], data.take(keep), rejected[keep]
            x, y, k = _take(solution.x, keep), _take(solution.y, keep), solution.k[keep]
            # The guess and the signed multipliers follow from x and k: cheaper
            # than gathering them.
            lower, upper = _leading_guess(data, x, k)
            sign = lower.to(x.dtype).sub_(upper.to(x.dtype))
            solution = _LeadingSolution(x, y, _signed(data, y, sign), k)
        new_lower, new_upper = _active_set_step(data, solution, lower, upper)
        new_active = new_lower | new_upper
        leading = _is_leading(new_active)
        hand_on(rejected & ~leading, new_lower, new_upper)
        running = rejected & leading
        if whole:
            # Most of the batch still runs (a cold start): another masked pass.
            lower, upper = new_lower, new_upper
            solution = _leading_solve(data, lower, upper)
        else:
            changed = (new_lower != lower) | (new_upper != upper)
            grown = new_active.sum(0) - solution.k  # (b,)
            one_bound = (changed.sum(0) == 1) & (grown.abs() == 1)
            # The changed row where one_bound (clamped: garbage elsewhere).
            j = torch.where(grown > 0, solution.k, solution.k - 1)
            j = j.clamp_(0, lower.shape[0] - 1)
            lower, upper = new_lower, new_upper
            solution = _boundary_step(data, solution, j, lower, upper)
            resolve = (running & ~one_bound).nonzero().squeeze(1)
            if resolve.numel():
                sub = _leading_solve(
                    data.take(resolve), _take(lower, resolve), _take(upper, resolve)
                )
                solution = _LeadingSolution(
                    _put_(solution.x, resolve, sub.x),
                    _put_(solution.y, resolve, sub.y),
                    _put_(solution.signed, resolve, sub.signed),
                    solution.k.index_copy(0, resolve, sub.k),
                )
        accept = _leading_accept(data, solution, settings) & running
        if whole:  # only the accepted: the working set holds finished instances
            take = accept.nonzero().squeeze(1)
            where = rows[take]
            _put_(x_out, where, _take(solution.x, take))
            _put_(y_out, where, _take(solution.y, take))
            solved[where] = True
            constrained[where] = solution.k[take] > 0
        else:  # all of it: what is not accepted yet is overwritten later
            _put_(x_out, rows, solution.x)
            _put_(y_out, rows, solution.y)
            solved[rows] = accept
            constrained[rows] = accept & (solution.k > 0)
    else:
        hand_on(running & ~accept, lower, upper)
    left = (
        _Unfinished(*(torch.cat(parts, -1) for parts in zip(*unfinished, strict=True)))
        if unfinished
        else _Unfinished(rows[:0], lower[:, :0], upper[:, :0])
    )
    return _LeadingOutcome(x_out, y_out, solved, constrained, left)


class _Refined(NamedTuple):
    """Accepted exact solutions: ``rows`` of the batch and their iterate."""

    rows: Tensor  # (b,) int64
    x: Tensor  # (n, b)
    z: Tensor  # (m, b)
    y: Tensor  # (m, b)


def _kkt_accept(
    data: _Data | _Leading,
    x: Tensor,
    y: Tensor,
    ax: Tensor,
    z: Tensor,
    px: Tensor,
    aty: Tensor,
    lower: Tensor,
    upper: Tensor,
    settings: QPSettings,
    prim_ref: Tensor | None = None,
    dual_ref: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Is ``(x, y)`` optimal for the guessed active set ``lower | upper``?

    Accepted where the primal and dual residuals (OSQP's) are below ``prim_ref`` /
    ``dual_ref`` or a round-off floor, and every active multiplier has the sign of its
    bound up to that floor (a wrong sign means the guessed active set was wrong): then
    the KKT conditions hold.

    Args:
        data: the problems (only ``q, l, u`` are read); x: (n, B);
        y, ax = A x, z = clamp(ax, l, u): (m, B); px, aty: (n, B) ``P x``, ``A'y``;
        lower, upper: (m, B) bool, the guessed active bounds.

    Returns:
        accept: (B,) bool; wrong_sign: (m, B) bool, active bounds whose multiplier
        has the wrong sign.
    """
    ulp = torch.finfo(data.q.dtype).eps
    eps_rel = settings.eps_rel + _ROUNDOFF_ULPS * ulp
    # Bool-mask where() and bool reductions over rows are slow on CPU; everything
    # below is float arithmetic, comparisons and float reductions.
    prim_res = _inf_norm(ax - z)
    dual_res = _inf_norm(px + data.q + aty)
    # Round-off floor: a hundred ulps of the quantities the residuals difference,
    # capped at the termination tolerance.
    x_norm, y_norm = _inf_norm(x), _inf_norm(y)
    prim_scale = torch.maximum(_inf_norm(ax), _inf_norm(z))
    dual_scale = torch.maximum(_inf_norm(px), _inf_norm(data.q))
    dual_scale = torch.maximum(dual_scale, _inf_norm(aty))
    prim_floor = torch.minimum(
        100 * ulp * (1 + prim_scale), settings.eps_abs + eps_rel * prim_scale
    )
    dual_floor = torch.minimum(
        100 * ulp * (1 + dual_scale), settings.eps_abs + eps_rel * dual_scale
    )
    prim_bound, dual_bound = prim_floor, dual_floor
    if prim_ref is not None and dual_ref is not None:
        prim_bound = torch.maximum(prim_floor, prim_ref)
        dual_bound = torch.maximum(dual_floor, dual_ref)
    inequality = data.l != data.u  # an equality row's multiplier has either sign
    lower, upper = lower & inequality, upper & inequality
    wrong_sign = (lower & (y > 0)) | (upper & (y < 0))  # (m, B)
    sign_error = torch.maximum(
        (y * lower.to(y.dtype)).amax(0), (y * upper.to(y.dtype)).amin(0).neg_()
    )  # >= 0 wherever a row is inactive; a clean active row gives <= 0
    accept = (
        (prim_res <= prim_bound)
        & (dual_res <= dual_bound)
        & (sign_error <= dual_floor)
        & torch.isfinite(x_norm)  # amax propagates NaN
        & torch.isfinite(y_norm)
    )
    return accept, wrong_sign


def _refine(
    data: _Data,
    lower: Tensor,
    upper: Tensor,
    settings: QPSettings,
    passes: int,
    prim_ref: Tensor | None = None,
    dual_ref: Tensor | None = None,
    definite: Tensor | None = None,
) -> _Refined:
    """Exact solves on a guessed active set, accepted per instance if optimal.

    A solution is accepted if its primal and dual residuals (OSQP's) are below
    ``prim_ref`` / ``dual_ref`` or a round-off floor, and every active multiplier
    has the sign of its bound up to that floor (a wrong sign means the guessed active
    set was wrong): then it satisfies the KKT conditions. A rejected instance gets up
    to ``passes - 1`` more tries, each after one primal-dual active-set step
    (Hintermueller, Ito & Kunisch 2002): bounds with a wrong-signed multiplier are
    freed and bounds the solution violates are fixed.

    Args:
        data: the problems.
        lower, upper: (m, B) bool, the guessed active bounds.
        settings: for the tolerances that cap the round-off floor.
        passes: solves per instance at most.
        prim_ref, dual_ref: optional (B,) residuals to beat (default: the floor).
        definite: optional (B,) bool, P positive definite (box problems only).
    """
    rows = torch.arange(data.q.shape[-1], device=data.q.device)
    accepted: list[_Refined] = []
    for attempt in range(passes):
        if data.A is None:
            x, y, px = _polish_box(data, lower, upper, definite)
        else:
            x, y = _polish_general(data, lower, upper)
            px = _mv(data.P, x)
        ax = data.Ax(x)
        z = torch.clamp(ax, data.l, data.u)
        accept, wrong_sign = _kkt_accept(
            data,
            x,
            y,
            ax,
            z,
            px,
            data.Aty(y),
            lower,
            upper,
            settings,
            prim_ref,
            dual_ref,
        )
        take = accept.nonzero().squeeze(1)
        if take.numel():
            accepted.append(
                _Refined(rows[take], _take(x, take), _take(z, take), _take(y, take))
            )
        retry = (~accept).nonzero().squeeze(1)
        if not retry.numel() or attempt == passes - 1:
            break
        # The active-set step, on the rejected instances only.
        lower = (lower & ~wrong_sign) | (ax < data.l)
        upper = ((upper & ~wrong_sign) | (ax > data.u)) & ~lower
        rows, data = rows[retry], data.take(retry)
        lower, upper = _take(lower, retry), _take(upper, retry)
        if prim_ref is not None and dual_ref is not None:
            prim_ref, dual_ref = prim_ref[retry], dual_ref[retry]
        if definite is not None:
            definite = definite[retry]
    if not accepted:
        empty = data.q[:, :0]
        return _Refined(rows[:0], empty, data.l[:, :0], data.l[:, :0])
    return _Refined(*(torch.cat(parts, -1) for parts in zip(*accepted, strict=True)))


def _polish(
    data: _Data,
    outcome: _Outcome,
    settings: QPSettings,
    definite: Tensor | None = None,
) -> tuple[_Outcome, Tensor]:
    """OSQP's polish of the SOLVED instances; the ADMM point stays where it fails.

    The active set is guessed from the ADMM iterate (:func:`_active_set`) and
    :func:`_refine` must beat the ADMM point's residuals. ADMM's guess usually misses
    only weakly active bounds (multipliers near its tolerance), which one active-set
    step repairs.

    Returns:
        the outcome with accepted points replaced, and polished: (B,) bool.
    """
    polished = torch.zeros_like(outcome.n_iter, dtype=torch.bool)
    rows = (outcome.status == QPStatus.SOLVED).nonzero().squeeze(1)
    if not rows.numel():
        return outcome, polished
    sub = data.take(rows)
    lower, upper = _active_set(sub, _take(outcome.z, rows), _take(outcome.y, rows))
    refined = _refine(
        sub,
        lower,
        upper,
        settings,
        _POLISH_PASSES,
        outcome.prim_res[rows],
        outcome.dual_res[rows],
        None if definite is None else definite[rows],
    )
    take = rows[refined.rows]
    polished[take] = True
    return outcome._replace(
        x=outcome.x.index_copy(-1, take, refined.x),
        z=outcome.z.index_copy(-1, take, refined.z),
        y=outcome.y.index_copy(-1, take, refined.y),
    ), polished


def _solve(
    data: _Data,
    state: _State,
    rho: Tensor,
    inverse: Tensor,
    settings: QPSettings,
    definite: Tensor | None = None,
) -> tuple[_Outcome, Tensor]:
    """ADMM, then the polish if the settings ask for it."""
    outcome = _admm(data, state, rho, inverse, settings)
    if settings.polish:
        return _polish(data, outcome, settings, definite)
    return outcome, torch.zeros_like(outcome.n_iter, dtype=torch.bool)


def _start(data: _Data, x0: Tensor | None, y0: Tensor | None, n: int, m: int) -> _State:
    """Starting iterate (batch-last): ``x0`` or 0, ``y0`` or 0, ``z = proj(A x)``."""
    batch = data.q.shape[-1]
    like = data.q
    # A plain clone() of the transposed input would keep its (1, n) strides and slow
    # every later elementwise operation; the copy must be contiguous batch-last.
    dense = torch.contiguous_format
    x = like.new_zeros(n, batch) if x0 is None else x0.T.to(like.dtype)
    y = like.new_zeros(m, batch) if y0 is None else y0.T.to(like.dtype)
    x, y = x.clone(memory_format=dense), y.clone(memory_format=dense)
    z = torch.clamp(data.Ax(x), data.l, data.u)
    return _State(x, z, y)


def _bounds(
    l: Tensor,  # noqa: E741
    u: Tensor,
    dtype: torch.dtype,
    keep_broadcast: bool = False,
) -> tuple[Tensor, Tensor, bool]:
    """Batch-last bounds with infinities replaced by +-INFTY, and whether any row
    is an equality (``l == u``).

    With ``keep_broadcast``, a bound given as the same value on every row (an
    expanded ``(B, 1)`` tensor, as the MPC passes its input limits) stays a
    broadcast ``(n, B)`` view of one row: every operation that reads it then reads
    ``B`` values, not ``n B``. Such views must only be read.
    """

    def batch_last(t: Tensor) -> Tensor:
        t = t.T  # (n, B)
        if keep_broadcast and t.shape[0] > 1 and t.stride(0) == 0:
            return t[:1].to(dtype).clamp(-INFTY, INFTY).expand(t.shape)
        return t.to(dtype).clamp(-INFTY, INFTY).contiguous()

    lower, upper = batch_last(l), batch_last(u)
    # The gap on the stored rows only (one row of a broadcast bound).
    rows = 1 if lower.stride(0) == 0 and upper.stride(0) == 0 else lower.shape[0]
    gap = upper[:rows] - lower[:rows]
    least = float(gap.amin()) if gap.numel() else 1.0
    if least < 0:
        raise ValueError("every lower bound must be <= its upper bound")
    return lower, upper, least == 0


def _check(name: str, t: Tensor | None, shape: tuple[int, ...]) -> None:
    if t is not None and tuple(t.shape) != shape:
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {shape}")


def _result(
    x: Tensor, y: Tensor, z: Tensor, n_iter: Tensor, status: Tensor, polished: Tensor
) -> QPResult:
    """Batch-first result from batch-last iterates: ``x`` contiguous, ``y`` and
    ``z`` transposed views (a transposing copy costs about as much as a pass of
    the active-set stage, and most callers only read ``x``)."""
    return QPResult(_transpose(x), y.T, z.T, n_iter, status, polished)


def solve_qp_batch(
    P: Tensor,
    q: Tensor,
    A: Tensor,
    l: Tensor,  # noqa: E741
    u: Tensor,
    *,
    settings: QPSettings | None = None,
    x0: Tensor | None = None,
    y0: Tensor | None = None,
) -> QPResult:
    """Solve ``min 1/2 x'Px + q'x s.t. l <= Ax <= u`` for a batch of instances.

    OSQP's ADMM (Stellato et al. 2020, Algorithm 1) per instance, with per-instance
    termination, adaptive rho, infeasibility detection and polishing; see the module
    docstring. Bounds may be ``-inf`` / ``+inf``; rows with ``l == u`` are equalities.

    Args:
        P: (B, n, n) symmetric positive semidefinite.
        q: (B, n).
        A: (B, m, n).
        l, u: (B, m) bounds, ``l <= u``.
        settings: solver settings; default :class:`QPSettings()`.
        x0, y0: (B, n), (B, m) optional warm start of the primal and dual iterate.

    Returns:
        :class:`QPResult` in the dtype and on the device of ``q``.
    """
    settings = settings or QPSettings()
    batch, n = q.shape
    m = A.shape[1]
    _check("P", P, (batch, n, n))
    _check("A", A, (batch, m, n))
    _check("l", l, (batch, m))
    _check("u", u, (batch, m))
    _check("x0", x0, (batch, n))
    _check("y0", y0, (batch, m))
    dtype = q.dtype
    lower, upper, _ = _bounds(l, u, dtype)
    data = _Data(
        P=P.to(dtype).permute(1, 2, 0).contiguous(),
        q=q.T.contiguous(),
        A=A.to(dtype).permute(1, 2, 0).contiguous(),
        l=lower,
        u=upper,
    )
    rho = q.new_full((batch,), settings.rho)
    inverse = _kkt_inverse(data, _rho_vector(rho, data), settings.sigma)
    state = _start(data, x0, y0, n, m)
    outcome, polished = _solve(data, state, rho, inverse, settings)
    return _result(
        outcome.x, outcome.y, outcome.z, outcome.n_iter, outcome.status, polished
    )


class BoxQP:
    """``min 1/2 x'Px + q'x s.t. l <= x <= u`` (A = I) for many instances.

    The instances share nothing but their shape. The factorisation depends only on
    ``P`` (and rho), so it is built once here and reused by every :meth:`solve`; this
    is what the MPC uses: ``P`` depends on the particle only, ``q`` changes every
    time step. Cached per instance: ``P^{-1}`` (for the exact fast path) and
    ``(P + (sigma + rho) I)^{-1}`` (the ADMM x-update).

    Args:
        P: (B, n, n) symmetric positive semidefinite (definite for the fast path).
        settings: solver settings; default :class:`QPSettings()`.

    Attributes:
        P: (B, n, n) the Hessians as given.
        settings: the solver settings.
    """

    def __init__(self, P: Tensor, settings: QPSettings | None = None) -> None:
        if P.ndim != 3 or P.shape[1] != P.shape[2]:
            raise ValueError(f"P must be (B, n, n), got {tuple(P.shape)}")
        self.settings = settings or QPSettings()
        self.P = P  # (B, n, n) as given
        self._P = P.permute(1, 2, 0).contiguous()  # (n, n, B)
        self._p_inverse, self._definite = _spd_inverse(self._P)
        self._leading, upper_ok = _leading_factor(self._P)
        self._definite &= upper_ok
        kkt = self._P.clone()
        torch.diagonal(kkt, 0, 0, 1).add_(self.settings.sigma + self.settings.rho)
        self._kkt, _ = _spd_inverse(kkt)

    @property
    def batch_size(self) -> int:
        return self._P.shape[-1]

    @property
    def n(self) -> int:
        return self._P.shape[0]

    def unconstrained(self, q: Tensor, *, index: Tensor | None = None) -> Tensor:
        """Unconstrained minimiser ``-P^{-1} q`` from the cached inverse.

        Args:
            q: (B, n), or (len(index), n) with ``index``.
            index: optional (b,) int64 rows of the batch that ``q`` belongs to.

        Returns:
            (B, n) (NaN-free garbage where ``P`` is singular).
        """
        inverse = self._p_inverse
        if index is not None:
            inverse = _take(inverse, index)
        return -_mv(inverse, q.T.to(inverse.dtype)).T

    def _working_set(
        self,
        rest: Tensor,
        index: Tensor | None,
        q_t: Tensor,
        lower: Tensor,
        upper: Tensor,
    ) -> tuple[Tensor, _Data]:
        """The problems ``rest`` (positions in this call's batch): their rows of the
        cached factors and their batch-last data."""
        cached = rest if index is None else index[rest]
        if _few(cached, self.batch_size):  # from the batch-first P as given
            P = self.P.index_select(0, cached).to(self._P.dtype).permute(1, 2, 0)
            P = P.contiguous()
        else:
            P = _take(self._P, cached)
        data = _Data(P, q_t[:, rest], None, lower[:, rest], upper[:, rest])
        return cached, data

    def solve(
        self,
        q: Tensor,
        l: Tensor,  # noqa: E741
        u: Tensor,
        *,
        x0: Tensor | None = None,
        y0: Tensor | None = None,
        index: Tensor | None = None,
        method: Literal["auto", "admm"] = "auto",
        active_guess: Tensor | None = None,
    ) -> QPResult:
        """Solve the instances ``index`` (default: all) for the given ``q, l, u``.

        ``method="auto"`` runs three stages, each on what the previous one left:

        1. exact fast path: where ``-P^{-1} q`` lies in ``[l, u]`` it is the solution
           (SOLVED, ``n_iter = 0``, ``y = 0``, not ``polished``);
        2. active set: the bounds that ``-P^{-1} q`` violates, or with a guess (see
           below) the bounds the guess sits on, are fixed and the reduced system
           solved exactly, with up to ``_ACTIVE_SET_PASSES - 1`` primal-dual
           active-set corrections (Hintermueller, Ito & Kunisch 2002); a solution is
           kept only where it satisfies the KKT conditions to round-off (SOLVED,
           ``n_iter = 0``, ``polished`` unless no bound is active). On the MPC QPs
           this finishes almost every instance;
        3. ADMM and polish (:func:`solve_qp_batch`) on the rest, started from
           ``x0, y0``; without ``y0``, from ``x0`` (or ``-P^{-1} q``) clipped to
           the box, with the multipliers ``-(Px + q)`` on its rows at a bound.

        With a guess, stage 1 is not run on its own: stage 2 starts from the guess,
        and an instance whose guess has no active bound gets the unconstrained
        minimiser in its first pass, as stage 1 would give it.

        ``method="admm"`` runs stage 3 alone, from ``x0, y0`` or zeros as OSQP does:
        the same result as ``solve_qp_batch`` with ``A = I``.

        Args:
            q: (b, n) with ``b = B`` or ``len(index)``.
            l, u: (b, n) bounds, ``-inf`` / ``+inf`` allowed.
            x0, y0: (b, n) optional warm start of ADMM (the MPC passes its previous
                plan, shifted by one step, as ``x0`` alone); ``x0`` is also stage
                2's guess unless ``active_guess`` is given.
            index: optional (b,) int64 rows of the batch to solve; the cached factors
                are gathered.
            method: "auto" or "admm", see above.
            active_guess: optional (b, n) point whose entries at or beyond a bound
                (``<= l``, ``>= u``) are stage 2's first guess of the active set.
                The MPC passes its previous plan unshifted: saturated inputs tend
                to stay saturated (on the states of ``tools/bench_qp.py`` its
                active set is the new one about three times as often as the
                shifted plan's). Only a guess: any point gives the same solution.

        Returns:
            :class:`QPResult` with ``b`` rows.
        """
        if method not in ("auto", "admm"):
            raise ValueError(f"method must be 'auto' or 'admm', got {method!r}")
        n = self.n
        batch = self.batch_size if index is None else index.shape[0]
        for name, t in (
            ("q", q),
            ("l", l),
            ("u", u),
            ("x0", x0),
            ("y0", y0),
            ("active_guess", active_guess),
        ):
            _check(name, t, (batch, n))
        definite = self._definite if index is None else self._definite[index]
        dtype = self._P.dtype
        lower, upper, equality = _bounds(l, u, dtype, keep_broadcast=True)
        q_t = _transpose(q.to(dtype))
        n_iter = torch.zeros(batch, dtype=torch.int64, device=q.device)
        status = torch.full_like(n_iter, int(QPStatus.SOLVED))
        polished = torch.zeros(batch, dtype=torch.bool, device=q.device)

        if method == "admm":
            rest = torch.arange(batch, device=q.device)
            x = y = z = None  # stage 3 alone: its result is the output
        else:
            # Stages 1 and 2: active-set passes on the leading-block solve; the
            # first guess of a cold start is "no bound active", so its first pass
            # is the unconstrained minimiser.
            point = x0 if active_guess is None else active_guess
            if point is None:
                at_lower = torch.zeros(n, batch, dtype=torch.bool, device=q.device)
                at_upper = torch.zeros_like(at_lower)
                passes = _ACTIVE_SET_PASSES + 1
            else:
                # Compared batch-first, with l and u as given (clamping the
                # infinities changes no comparison), and the bool masks transposed:
                # cheaper than transposing the point.
                point = point.to(dtype)
                below, above = point <= l.to(dtype), point >= u.to(dtype)  # (b, n)
                at_lower = _transpose(below)
                at_upper = _transpose(above).logical_and_(~at_lower)
                passes = _ACTIVE_SET_PASSES
            leading = _leading_active_set(
                _leading_data(
                    self._leading,
                    q_t,
                    lower,
                    upper,
                    self.settings,
                    index,
                    equality,
                    given_bounds=(l, u),
                ),
                at_lower,
                at_upper,
                definite,
                self.settings,
                passes,
            )
            x, y, polished = leading.x, leading.y, leading.constrained
            z = torch.clamp(x, lower, upper)
            # The rest: guesses that stopped being a leading block, instances out
            # of passes, and singular P. Exact solves that refactorise.
            other = (~definite).nonzero().squeeze(1)
            rest = torch.cat((leading.unfinished.rows, other))
            if not rest.numel():
                return _result(x, y, z, n_iter, status, polished)
            at_lower = torch.cat((leading.unfinished.lower, at_lower[:, other]), -1)
            at_upper = torch.cat((leading.unfinished.upper, at_upper[:, other]), -1)
            cached, data = self._working_set(rest, index, q_t, lower, upper)
            refined = _refine(
                data,
                at_lower,
                at_upper,
                self.settings,
                _ACTIVE_SET_PASSES,
                definite=definite[rest],
            )
            done = rest[refined.rows]
            _put_(x, done, refined.x)
            _put_(y, done, refined.y)
            _put_(z, done, refined.z)
            polished[done] = True
            left = torch.ones(rest.numel(), dtype=torch.bool, device=q.device)
            left[refined.rows] = False
            keep = left.nonzero().squeeze(1)
            if not keep.numel():
                return _result(x, y, z, n_iter, status, polished)
            rest = rest[keep]

        # Stage 3: ADMM and polish.
        settings = self.settings
        cached, data = self._working_set(rest, index, q_t, lower, upper)
        rho = q_t.new_full((rest.numel(),), settings.rho)
        if _few(cached, self.batch_size):  # factorising a few costs less than a gather
            kkt = _kkt_inverse(data, _rho_vector(rho, data), settings.sigma)
        else:
            kkt = _take(self._kkt, cached)
            # Equality or free rows change rho_vec: refactorise those instances only.
            special = (~_uniform_rows(data)).nonzero().squeeze(1)
            if special.numel():
                sub = data.take(special)
                sub_rho = _rho_vector(rho[special], sub)
                _put_(kkt, special, _kkt_inverse(sub, sub_rho, settings.sigma))
        if method == "admm" or y0 is not None:
            state = _start(
                data,
                None if x0 is None else x0[rest],
                None if y0 is None else y0[rest],
                n,
                n,
            )
        elif x0 is None:
            if _few(cached, self.batch_size):
                L, _ = _cholesky(data.P, strict=False)
                point = _cholesky_solve(L, -data.q)  # -P^{-1} q
            else:
                point = -_mv(_take(self._p_inverse, cached), data.q)
            state = _dual_feasible_start(data, point, definite[rest])
        else:
            usable = torch.ones_like(definite[rest])
            point = _transpose(x0[rest].to(dtype))
            state = _dual_feasible_start(data, point, usable)
        outcome, sub_polished = _solve(
            data, state, rho, kkt, settings, definite=definite[rest]
        )
        if z is None:  # method="admm": every instance ran here, in order
            x, y, z = outcome.x, outcome.y, outcome.z
        else:
            _put_(x, rest, outcome.x)
            _put_(y, rest, outcome.y)
            _put_(z, rest, outcome.z)
        n_iter[rest] = outcome.n_iter
        status[rest] = outcome.status
        polished[rest] = sub_polished
        return _result(x, y, z, n_iter, status, polished)


def _dual_feasible_start(data: _Data, point: Tensor, usable: Tensor) -> _State:
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
    y = torch.where(at_bound, -(_mv(data.P, x) + data.q), torch.zeros_like(x))
    return _State(x, x.clone(), y)


__all__ = ["INFTY", "BoxQP", "QPResult", "QPSettings", "QPStatus", "solve_qp_batch"]
