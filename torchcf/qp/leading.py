"""Box QPs whose active bounds are a leading block: exact solves without
refactorising.

For a box QP (``A = I``) with the active bounds ``A = {0 .. k-1}`` and the free
block ``F = {k .. n-1}``, the solution solves ``P_FF x_F = -q_F - P_FA x_A``. With
the "UL" factor ``P = U U'`` (:func:`~torchcf.qp.kernels.ul_cholesky`, computed
once per ``P``) that system is one forward substitution through ``U'``
(:func:`leading_solve`: ``n^2 / 2`` multiply-adds for ``x``, ``k^2 / 2`` for the
multipliers, no new factorisation), and a step that fixes or frees the bound at the
end of the block is a rank-one update from a second per-``P`` factor
(:func:`boundary_step`). A point is accepted only where the KKT conditions hold to
round-off (:func:`leading_accept`), so the answers are exact.

On the MPC QPs the guessed active sets are nearly always leading blocks: the first
inputs of the plan saturate. :mod:`torchcf.qp.active_set` iterates these solves.

The data come at three lifetimes, one tuple each: :class:`_LeadingFactor` per
``P`` (over the ``B`` instances of a :class:`~torchcf.qp.boxqp.BoxQP`),
:class:`_LeadingCall` per call (``c`` instances), and :class:`LeadingWorkingSet`
per active-set pass (``b`` instances). Solutions are :class:`LeadingSolution`.

Imports :mod:`~torchcf.qp.kernels` and :mod:`~torchcf.qp.problem` only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .kernels import (
    back_substitute,
    inf_norm,
    is_small_subset,
    put_instances_,
    swap_layout,
    sweep_slices,
    tail_residuals,
    take_instances,
    ul_cholesky,
)
from .problem import INFTY, QPSettings, roundoff_floor

# --------------------------------------------------------------------------------------
# Per-P factors.


class _LeadingFactor(NamedTuple):
    """Per-``P`` factors of the leading-block solves (:func:`leading_factor`),
    over the ``B`` instances of the factorised batch."""

    U: Tensor  # (n, n, B) upper triangular, P = U U', zero below the diagonal
    diag: Tensor  # (n, B) diag(U)
    inv_diag: Tensor  # (n, B) 1 / diag(U)
    # (B * n, 2 n): row b n + j is column j of instance b's D = U'^{-1} diag(U)
    # (unit lower triangular), then column j of its U. Batch-first, so that one
    # instance's column is one contiguous gather (see :func:`boundary_step`).
    columns: Tensor
    # (n + 1, B): max_{i >= k} ||U[i, :]||_1 in row k, 0 in row n; bounds the back
    # substitution's residual (see :func:`leading_data`).
    tail_row_norm: Tensor

    def take(self, index: Tensor) -> _LeadingFactor:
        """The factors of the instances ``index`` (int64 (b,)) alone."""
        n, width = self.diag.shape[0], self.columns.shape[1]
        batch = self.diag.shape[1]
        columns = self.columns.reshape(batch, n, width).index_select(0, index)
        return _LeadingFactor(
            U=self.U.index_select(-1, index),
            diag=self.diag.index_select(-1, index),
            inv_diag=self.inv_diag.index_select(-1, index),
            columns=columns.reshape(-1, width),
            tail_row_norm=self.tail_row_norm.index_select(-1, index),
        )


def leading_factor(P: Tensor) -> tuple[_LeadingFactor, Tensor]:
    """The factors of :func:`leading_solve` and :func:`boundary_step` for
    symmetric ``P: (n, n, B)``.

    ``D = U'^{-1} diag(U)``: column ``j`` is how the trailing block ``x_{j+1..}``
    moves, re-optimised, per unit move of ``x_j`` with ``x_{..j-1}`` fixed (row
    ``j`` is 1). It turns fixing or freeing one bound at the end of a leading
    block into a rank-one update. Computed by one forward substitution through
    ``U'`` for all ``n`` columns at once (``n^3 / 6`` multiply-adds per instance).

    Returns:
        the factors; ok: (B,) bool as in :func:`~torchcf.qp.kernels.cholesky`.
    """
    U, ok = ul_cholesky(P)
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


def _gathered_upper_factor(factor: _LeadingFactor, cols: Tensor) -> Tensor:
    """(n, n, b) ``U`` of the instances ``cols: (b,)``, from its batch-first copy in
    ``factor.columns`` (``[b, j, 1, i] = U[i, j, b]``): for a few instances."""
    n = factor.diag.shape[0]
    picked = factor.columns.view(-1, n, 2, n).index_select(0, cols)  # (b, n, 2, n)
    return picked[:, :, 1, :].permute(2, 1, 0).contiguous()


def _step_columns(factor: _LeadingFactor, j: Tensor, cols: Tensor) -> Tensor:
    """Columns ``j_b`` of ``D`` and of ``U`` of the instances ``cols_b``, for
    ``j, cols: (b,)``: (2, n, b)."""
    n = factor.diag.shape[0]
    picked = factor.columns.index_select(0, cols * n + j)  # (b, 2 n)
    return picked.T.reshape(2, n, -1)


# --------------------------------------------------------------------------------------
# Per-call data and the working sets of the active-set passes.


class _LeadingCall(NamedTuple):
    """What the leading-block solves know of one call's ``c`` problems
    (:func:`leading_data`); no active set changes it."""

    factor: _LeadingFactor  # over the factors' batch
    cols: Tensor | None  # (c,) int64 the problems' instances of it; None: the same
    U: Tensor  # (n, n, c) the problems' U (the factor's own where cols is None)
    diag: Tensor  # (n, c)
    inv_diag: Tensor  # (n, c)
    g: Tensor  # (n, c) U^{-1} q
    tail_residual: Tensor  # (n + 1, c) max_{i >= k} |U g - q|_i in row k; 0 in row n
    # (c, n) each: l and u as the caller gave them (batch-first, possibly
    # broadcast): a working set's rows of them are a cheap gather. None: use l, u.
    given_bounds: tuple[Tensor, Tensor] | None


class LeadingWorkingSet(NamedTuple):
    """A working set of ``b`` of a call's box QPs (A = I), batch-last: the vectors
    every pass reads. The rest stays in ``call``, gathered only for a new solve."""

    call: _LeadingCall
    rows: Tensor | None  # (b,) int64 positions in the call; None: all, in order
    l: Tensor  # (n, b)  # noqa: E741
    u: Tensor  # (n, b)
    q_norm: Tensor  # (b,) ||q||_inf
    inequality: Tensor | None  # (n, b) float, 0 on rows with l == u; None: no such row

    def take(self, idx: Tensor) -> LeadingWorkingSet:
        """Instances ``idx: (b',)`` of the working set."""
        rows = idx if self.rows is None else self.rows[idx]
        inequality = (
            None if self.inequality is None else take_instances(self.inequality, idx)
        )
        if self.call.given_bounds is None:
            l, u = take_instances(self.l, idx), take_instances(self.u, idx)  # noqa: E741
        else:  # from the batch-first bounds as given: contiguous rows
            l, u = (  # noqa: E741
                swap_layout(t.index_select(0, rows).to(self.l.dtype)).clamp_(
                    -INFTY, INFTY
                )
                for t in self.call.given_bounds
            )
        return LeadingWorkingSet(self.call, rows, l, u, self.q_norm[idx], inequality)

    def solve_data(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``U: (n, n, b), diag, inv_diag, g: (n, b)`` of the working set (gathered
        unless it is the whole call)."""
        call, rows = self.call, self.rows
        if rows is None:
            return call.U, call.diag, call.inv_diag, call.g
        if is_small_subset(rows, call.U.shape[-1]):
            U = _gathered_upper_factor(call.factor, self.factor_cols())
        else:
            U = take_instances(call.U, rows)
        return (
            U,
            take_instances(call.diag, rows),
            take_instances(call.inv_diag, rows),
            take_instances(call.g, rows),
        )

    def factor_cols(self) -> Tensor:
        """(b,) int64 the working set's instances of ``call.factor``."""
        cols, rows = self.call.cols, self.rows
        if rows is None:
            rows = torch.arange(self.l.shape[-1], device=self.l.device)
        return rows if cols is None else cols[rows]

    def tail_residual(self, k: Tensor) -> Tensor:
        """(b,) the back substitution's residual, max over the rows from
        ``k: (b,)``."""
        table = self.call.tail_residual  # (n + 1, c)
        rows = self.rows
        if rows is None:
            return table.gather(0, k[None])[0]
        return table.reshape(-1)[k * table.shape[-1] + rows]


def _tail_residual_table(
    factor: _LeadingFactor,
    cols: Tensor | None,
    U: Tensor,
    g: Tensor,
    q: Tensor,
    q_norm: Tensor,
    settings: QPSettings,
) -> Tensor:
    """(n + 1, c) ``_LeadingCall.tail_residual``: in row ``k`` a bound of
    ``max_{i >= k} |U g - q|_i`` where that bound is below the acceptance floor,
    the residual itself elsewhere.

    Substitution is backward stable, ``|U g - q| <= gamma_{n+1} |U| |g|``
    componentwise with ``gamma_m = m u / (1 - m u)``, ``u`` the unit round-off
    (Higham 2002, "Accuracy and Stability of Numerical Algorithms", Theorem 8.5;
    ``n + 1`` for the product with the reciprocal pivot), and
    ``(|U| |g|)_i <= ||U[i, :]||_1 ||g||_inf``, with the row norms cached per ``P``
    (``factor.tail_row_norm``). Where the bound is not that small (an
    ill-conditioned ``U``, a tight tolerance) the residual is computed, one more
    substitution's worth of work, on those instances only.

    Args:
        factor, cols: as in :func:`leading_data`.
        U: (n, n, c) the problems' factor; g: (n, c) ``U^{-1} q``; q: (n, c).
        q_norm: (c,) ``||q||_inf``.
    """
    n = q.shape[0]
    # gamma_{n+2}: one more rounding than the substitution's, for the bound's own.
    unit_roundoff = torch.finfo(q.dtype).eps / 2
    gamma = (n + 2) * unit_roundoff / (1 - (n + 2) * unit_roundoff)
    tail_row_norm = factor.tail_row_norm
    if cols is not None:
        tail_row_norm = take_instances(tail_row_norm, cols)
    tail_residual = tail_row_norm * (gamma * inf_norm(g))  # (n + 1, c) bounds
    # The dual floor's scale is at least ||q||: where the bound clears the floor at
    # that scale it clears it in any pass.
    loose = (tail_residual[0] > roundoff_floor(q_norm, settings)).nonzero()[:, 0]
    if loose.numel():
        if is_small_subset(loose, q.shape[-1]):
            sub_cols = loose if cols is None else cols[loose]
            sub = (
                _gathered_upper_factor(factor, sub_cols),
                take_instances(g, loose),
                take_instances(q, loose),
            )
            put_instances_(tail_residual, loose, tail_residuals(*sub))
        else:
            tail_residual = tail_residuals(U, g, q)
    return tail_residual


def leading_data(
    factor: _LeadingFactor,
    q: Tensor,
    l: Tensor,  # noqa: E741
    u: Tensor,
    settings: QPSettings,
    cols: Tensor | None = None,
    equality: bool = True,
    given_bounds: tuple[Tensor, Tensor] | None = None,
) -> LeadingWorkingSet:
    """The problems as the leading-block stage's working set, with the per-call
    quantities that no active set changes.

    ``g = U^{-1} q`` serves every active-set pass, and so does the residual of that
    back substitution: with the leading block ``A`` fixed, the stationarity residual
    ``P x + q`` on the free rows ``F = {k, ..}`` is ``(U g - q)_F`` (see
    :func:`leading_solve`), so its max over ``F`` is a lookup in ``tail_residual``
    (:func:`_tail_residual_table`).

    Args:
        factor: from :func:`leading_factor`.
        q, l, u: (n, c) the problems.
        settings: for the acceptance floor.
        cols: optional (c,) instances of ``factor`` that the problems belong to.
        equality: False if no row has ``l == u`` (saves looking).
        given_bounds: optional (c, n) each, ``l`` and ``u`` as the caller gave them
            (batch-first), for gathering working sets.
    """
    diag, inv_diag = factor.diag, factor.inv_diag
    U = factor.U
    if cols is not None:
        diag, inv_diag = take_instances(diag, cols), take_instances(inv_diag, cols)
        few = is_small_subset(cols, factor.diag.shape[-1])
        U = _gathered_upper_factor(factor, cols) if few else take_instances(U, cols)
    g = back_substitute(U, inv_diag, q)
    q_norm = inf_norm(q)
    tail_residual = _tail_residual_table(factor, cols, U, g, q, q_norm, settings)
    inequality = None
    if equality and bool((l == u).any()):
        inequality = (l != u).to(q.dtype)
    call = _LeadingCall(factor, cols, U, diag, inv_diag, g, tail_residual, given_bounds)
    return LeadingWorkingSet(call, None, l, u, q_norm, inequality)


# --------------------------------------------------------------------------------------
# Solutions on a leading block.


def is_leading(active: Tensor) -> Tensor:
    """(n, B) bool -> (B,) bool: the True rows are ``0 .. k-1`` for some ``k``."""
    return ~(active[1:] & ~active[:-1]).any(0)


class LeadingSolution(NamedTuple):
    """An exact solution of ``b`` box QPs on a guessed leading active set."""

    x: Tensor  # (n, b)
    y: Tensor  # (n, b) multipliers -(P x + q) on the fixed rows, 0 elsewhere
    # (n, b) y times +1 / -1 on rows fixed at the lower / upper bound, 0 on free and
    # equality rows (see signed_multipliers): > 0 where the sign is wrong.
    signed: Tensor
    k: Tensor  # (b,) int64 fixed rows


def leading_guess(
    data: LeadingWorkingSet, x: Tensor, k: Tensor
) -> tuple[Tensor, Tensor]:
    """The guess a leading-block solution ``x: (n, b)`` with ``k: (b,)`` fixed rows
    was computed on: rows ``< k``, each at the bound it sits on. Exact: the solves
    and the boundary steps leave a fixed row at its bound to the bit, and a row
    with ``l == u`` counts as at its lower bound, as when the guess was made.

    Returns:
        lower, upper: (n, b) bool.
    """
    fixed = torch.arange(x.shape[0], device=x.device)[:, None] < k[None]
    lower = fixed & (x == data.l)
    return lower, fixed & ~lower


def signed_multipliers(data: LeadingWorkingSet, y: Tensor, sign: Tensor) -> Tensor:
    """``y`` times ``sign`` (+1 / -1 on the rows fixed at their lower / upper
    bound, 0 on the free rows; overwritten), 0 on equality rows (whose multiplier
    may have either sign): ``LeadingSolution.signed``, (n, b)."""
    if data.inequality is not None:
        sign.mul_(data.inequality)
    return sign.mul_(y)


def leading_solve(
    data: LeadingWorkingSet, lower: Tensor, upper: Tensor
) -> LeadingSolution:
    """Exact solution with the leading block ``A = {0 .. k-1}`` fixed at its bounds.

    With ``F`` the trailing free block and ``P = U U'`` (:func:`ul_cholesky`),
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
    operation on ``(rows, b)`` per column and batch slice (:func:`sweep_slices`).

    Args:
        data: the problems (:func:`leading_data`); lower, upper: (n, b) bool, the
            fixed bounds, a leading block in every instance (:func:`is_leading`).
    """
    U, diag, inv_diag, g = data.solve_data()
    n = g.shape[0]
    # Masks as 0/1 floats: arithmetic on them is cheaper on CPU than torch.where
    # with a bool condition.
    at_lower, at_upper = lower.to(U.dtype), upper.to(U.dtype)
    active = at_lower + at_upper  # (n, b) 1 on the fixed rows
    x = torch.addcmul(data.l * at_lower, data.u, at_upper)  # (n, b) x_A, 0 on F
    solve = torch.addcmul(inv_diag, active, inv_diag, value=-1)  # 0 on A
    # Forward substitution: r_j = -g_j - sum_{i<j} U[i, j] x_i, then x_j = r_j /
    # U[j, j] on F (x_j stays at its bound on A). r_j is final once column j is read.
    r = g.neg()
    for part in sweep_slices(r):  # batch slices: see _SWEEP_BYTES
        x_, r_, U_, solve_ = x[:, part], r[:, part], U[..., part], solve[:, part]
        for j in range(n):
            x_[j].addcmul_(r_[j], solve_[j])
            if j < n - 1:
                r_[j + 1 :].addcmul_(U_[j, j + 1 :], x_[j], value=-1)
    k = active.sum(0).long()  # (b,)
    depth = int(k.max()) if k.numel() else 0
    y = torch.zeros_like(x)
    if depth:
        # -s_A = r_A - diag_A x_A (r_j holds -g_j - (U' x)_j + U[j, j] x_j), 0 on F.
        minus_s = torch.addcmul(r[:depth], diag[:depth], x[:depth], value=-1)
        minus_s.mul_(active[:depth])
        for part in sweep_slices(y):
            y_, U_, m_ = y[:, part], U[..., part], minus_s[:, part]
            for j in range(depth):  # y_A = U_AA (-s_A); rows of F stay 0
                y_[: j + 1].addcmul_(U_[: j + 1, j], m_[j])
    signed = signed_multipliers(data, y, at_lower.sub_(at_upper))
    return LeadingSolution(x, y, signed, k)


def boundary_step(
    data: LeadingWorkingSet,
    solution: LeadingSolution,
    j: Tensor,
    lower: Tensor,
    upper: Tensor,
) -> LeadingSolution:
    """The exact solution after fixing or freeing one bound at the end of the block.

    With ``A = {0 .. k-1}`` fixed, fixing ``x_k`` at its bound, or freeing
    ``x_{k-1}``, moves ``x_j`` (``j = k`` or ``k - 1``) by some ``delta`` and the
    trailing free block with it, re-optimised: ``x' = x + delta D[:, j]``
    (:func:`leading_factor`). Since ``U' D[:, j] = U[j, j] e_j``, the gradient
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
    d, column = _step_columns(factor, j, cols)
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
    return LeadingSolution(x, y, signed_multipliers(data, y, sign), k)


def leading_accept(
    data: LeadingWorkingSet, solution: LeadingSolution, settings: QPSettings
) -> Tensor:
    """(b,) bool: is the leading-block solution optimal, to round-off?

    The same test as :func:`~torchcf.qp.polish._kkt_accept` (OSQP's residuals
    against a round-off floor, and the signs of the active multipliers), computed
    from what the leading-block solves know: ``y_A = -(P x + q)_A`` holds by
    construction, the residual on ``F`` is looked up in ``tail_residual``, and the
    fixed rows sit exactly on their bounds, so the primal residual is the bound
    violation of the free rows. The dual scale omits ``||P x||`` (about
    ``||q|| + ||y||``), which only tightens the floor.
    """
    x, signed = solution.x, solution.signed
    prim_res = torch.maximum((x - data.u).amax(0), (data.l - x).amax(0)).clamp_min_(0)
    # Where x is in the box (prim_res == 0: then x is finite, NaN propagates) the
    # primal test holds whatever its floor; ||x|| is needed only elsewhere.
    prim_ok = prim_res == 0
    outside = (~prim_ok).nonzero()[:, 0]
    if outside.numel():
        x_norm = inf_norm(take_instances(x, outside))
        prim_ok[outside] = (
            prim_res[outside] <= roundoff_floor(x_norm, settings)
        ) & torch.isfinite(x_norm)
    dual_res = data.tail_residual(solution.k)  # max over F
    # signed y: <= 0 on a correctly signed active row, 0 on F; |signed| = |y| on
    # inequality rows.
    sign_error = signed.amax(0)
    y_norm = torch.maximum(sign_error, signed.amin(0).neg_())
    if data.inequality is not None:
        y_norm = inf_norm(solution.y)
    dual_floor = roundoff_floor(torch.maximum(data.q_norm, y_norm), settings)
    return (
        prim_ok
        & (dual_res <= dual_floor)
        & (sign_error <= dual_floor)
        & torch.isfinite(y_norm)  # amax propagates NaN
    )
