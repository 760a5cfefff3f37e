"""Exact solves on a guessed active set, and OSQP's polish of the ADMM solution.

Given a guess of the active bounds, the QP reduces to an equality-constrained one
solved exactly (:func:`_polish_box` for ``A = I``, :func:`_polish_general`
otherwise). The point is accepted per instance only where it satisfies the KKT
conditions (:func:`_kkt_accept`); a rejected instance gets primal-dual active-set
corrections (:func:`active_set_solves`). The polish after ADMM
(:func:`_polish`) guesses the active set from the ADMM iterate and accepts a point
that beats ADMM's own residuals: nearly always exact, at worst as accurate as ADMM.
:class:`~torchcf.qp.boxqp.BoxQP` also calls :func:`active_set_solves` on the
instances its leading-block stage leaves.

Shapes: ``n`` variables, ``m`` rows, ``B`` instances. Imports
:mod:`~torchcf.qp.kernels`, :mod:`~torchcf.qp.problem` and :mod:`~torchcf.qp.admm`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from .admm import ADMMOutcome, Iterate, admm_iterations
from .kernels import cholesky, cholesky_solve, inf_norm, mv, take_instances
from .problem import ROUNDOFF_ULPS, ProblemData, QPSettings, QPStatus

#: Regularisation and iterative-refinement steps of the polish (OSQP's defaults).
_POLISH_DELTA = 1e-6
_POLISH_REFINE = 3
#: Polish attempts per instance (the first from ADMM's active set, then corrections).
_POLISH_PASSES = 4


def _admm_active_bounds(
    data: ProblemData, z: Tensor, y: Tensor
) -> tuple[Tensor, Tensor]:
    """OSQP's guess of the active bounds from the ADMM iterate ``z, y: (m, B)``:
    lower, upper, (m, B) bool each.

    A row is at its lower bound if ``z - l < -y``, at its upper bound if ``u - z < y``;
    an equality row (``l == u``) is always active, on whichever side ``y`` says.
    """
    lower = (z - data.l) < -y
    upper = ~lower & ((data.u - z) < y)
    equality = data.l == data.u
    return lower | (equality & ~upper), upper


# --------------------------------------------------------------------------------------
# Exact solves on a guessed active set.


def _polish_box(
    data: ProblemData, lower: Tensor, upper: Tensor, definite: Tensor | None = None
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
    L, _ = cholesky(regular, False)
    rhs = fixed + free * (-data.q - mv(data.P, fixed))
    x = cholesky_solve(L, rhs)
    if definite is None or not bool(definite.all()):
        for _ in range(_POLISH_REFINE):
            residual = rhs - mv(regular, x) + delta * x  # of the exact system
            x = x + cholesky_solve(L, residual)
    px = mv(data.P, x)
    y = -(px + data.q) * active
    return x, y, px


def _polish_general(
    data: ProblemData, lower: Tensor, upper: Tensor
) -> tuple[Tensor, Tensor]:
    """Exact solve of the reduced KKT system of the guessed active set (general A).

    ``[[P + delta I, A_a'], [A_a, -delta I]] [x; y_a] = [-q; b_a]`` (OSQP's polish),
    written at size ``n + m`` with the inactive rows reduced to ``-y_i = 0`` so the
    batch is one LU; iterative refinement against ``delta = 0`` removes the
    regularisation.

    Args:
        lower, upper: (m, B) bool, the rows fixed at each bound.

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


def _exact_solve(
    data: ProblemData, lower: Tensor, upper: Tensor, definite: Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    """``x: (n, B), y: (m, B), P x: (n, B)`` on the guessed active set
    ``lower | upper: (m, B)``, for a box or a general ``A``."""
    if data.A is None:
        return _polish_box(data, lower, upper, definite)
    x, y = _polish_general(data, lower, upper)
    return x, y, mv(data.P, x)


# --------------------------------------------------------------------------------------
# Acceptance, and active-set corrections of what is not accepted.


def _kkt_accept(
    data: ProblemData,
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
    the KKT conditions hold. The floor of a residual whose quantities are of size
    ``s`` is ``min(100 eps (1 + s), eps_abs + eps_rel' s)`` (see
    :func:`~torchcf.qp.problem.roundoff_floor`).

    Args:
        data: the problems (only ``q, l, u`` are read); x: (n, B);
        y, ax = A x, z = clamp(ax, l, u): (m, B); px, aty: (n, B) ``P x``, ``A'y``;
        lower, upper: (m, B) bool, the guessed active bounds.
        prim_ref, dual_ref: optional (B,) residuals to beat.

    Returns:
        accept: (B,) bool; wrong_sign: (m, B) bool, active bounds whose multiplier
        has the wrong sign.
    """
    ulp = torch.finfo(data.q.dtype).eps
    eps_rel = settings.eps_rel + ROUNDOFF_ULPS * ulp
    # Bool-mask where() and bool reductions over rows are slow on CPU; everything
    # below is float arithmetic, comparisons and float reductions.
    prim_res = inf_norm(ax - z)
    dual_res = inf_norm(px + data.q + aty)
    # Round-off floor: a hundred ulps of the quantities the residuals difference,
    # capped at the termination tolerance.
    x_norm, y_norm = inf_norm(x), inf_norm(y)
    prim_scale = torch.maximum(inf_norm(ax), inf_norm(z))
    dual_scale = torch.maximum(inf_norm(px), inf_norm(data.q))
    dual_scale = torch.maximum(dual_scale, inf_norm(aty))
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


class AcceptedSolutions(NamedTuple):
    """Accepted exact solutions: ``rows`` of the batch and their iterate."""

    rows: Tensor  # (b,) int64
    x: Tensor  # (n, b)
    z: Tensor  # (m, b)
    y: Tensor  # (m, b)


def active_set_solves(
    data: ProblemData,
    lower: Tensor,
    upper: Tensor,
    settings: QPSettings,
    passes: int,
    prim_ref: Tensor | None = None,
    dual_ref: Tensor | None = None,
    definite: Tensor | None = None,
) -> AcceptedSolutions:
    """Exact solves on a guessed active set, accepted per instance if optimal.

    A solution is accepted if its primal and dual residuals (OSQP's) are below
    ``prim_ref`` / ``dual_ref`` or a round-off floor, and every active multiplier
    has the sign of its bound up to that floor (a wrong sign means the guessed active
    set was wrong): then it satisfies the KKT conditions (:func:`_kkt_accept`). A
    rejected instance gets up to ``passes - 1`` more tries, each after one
    primal-dual active-set step (Hintermueller, Ito & Kunisch 2002): bounds with a
    wrong-signed multiplier are freed and bounds the solution violates are fixed.

    Args:
        data: the problems.
        lower, upper: (m, B) bool, the guessed active bounds.
        settings: for the tolerances that cap the round-off floor.
        passes: solves per instance at most.
        prim_ref, dual_ref: optional (B,) residuals to beat (default: the floor).
        definite: optional (B,) bool, P positive definite (box problems only).
    """
    rows = torch.arange(data.q.shape[-1], device=data.q.device)
    accepted: list[AcceptedSolutions] = []
    for attempt in range(passes):
        x, y, px = _exact_solve(data, lower, upper, definite)
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
                AcceptedSolutions(
                    rows[take],
                    take_instances(x, take),
                    take_instances(z, take),
                    take_instances(y, take),
                )
            )
        retry = (~accept).nonzero().squeeze(1)
        if not retry.numel() or attempt == passes - 1:
            break
        # The active-set step, on the rejected instances only.
        lower = (lower & ~wrong_sign) | (ax < data.l)
        upper = ((upper & ~wrong_sign) | (ax > data.u)) & ~lower
        rows, data = rows[retry], data.take(retry)
        lower, upper = take_instances(lower, retry), take_instances(upper, retry)
        if prim_ref is not None and dual_ref is not None:
            prim_ref, dual_ref = prim_ref[retry], dual_ref[retry]
        if definite is not None:
            definite = definite[retry]
    if not accepted:
        empty = data.q[:, :0]
        return AcceptedSolutions(rows[:0], empty, data.l[:, :0], data.l[:, :0])
    return AcceptedSolutions(
        *(torch.cat(parts, -1) for parts in zip(*accepted, strict=True))
    )


# --------------------------------------------------------------------------------------
# The polish after ADMM.


def _polish(
    data: ProblemData,
    outcome: ADMMOutcome,
    settings: QPSettings,
    definite: Tensor | None = None,
) -> tuple[ADMMOutcome, Tensor]:
    """OSQP's polish of the SOLVED instances; the ADMM point stays where it fails.

    The active set is guessed from the ADMM iterate (:func:`_admm_active_bounds`)
    and :func:`active_set_solves` must beat the ADMM point's residuals. ADMM's
    guess usually misses only weakly active bounds (multipliers near its
    tolerance), which one active-set step repairs.

    Returns:
        the outcome with accepted points replaced, and polished: (B,) bool.
    """
    polished = torch.zeros_like(outcome.n_iter, dtype=torch.bool)
    rows = (outcome.status == QPStatus.SOLVED).nonzero().squeeze(1)
    if not rows.numel():
        return outcome, polished
    sub = data.take(rows)
    lower, upper = _admm_active_bounds(
        sub, take_instances(outcome.z, rows), take_instances(outcome.y, rows)
    )
    refined = active_set_solves(
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


def admm_then_polish(
    data: ProblemData,
    start: Iterate,
    rho: Tensor,
    inverse: Tensor,
    settings: QPSettings,
    definite: Tensor | None = None,
) -> tuple[ADMMOutcome, Tensor]:
    """ADMM from ``start`` (:func:`~torchcf.qp.admm.admm_iterations`), then the
    polish if the settings ask for it.

    Returns:
        the outcome; polished: (B,) bool.
    """
    outcome = admm_iterations(data, start, rho, inverse, settings)
    if settings.polish:
        return _polish(data, outcome, settings, definite)
    return outcome, torch.zeros_like(outcome.n_iter, dtype=torch.bool)
