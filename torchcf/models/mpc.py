"""Model predictive control of an automated vehicle (SPEC section 3).

State ``z_0 = [s - v tau - l, dv]`` (spacing error under a constant-time-gap policy
and speed difference). Prediction over a horizon of K steps, the leader's
acceleration assumed zero (the paper's Appendix Table 3, as printed):
``z_{k+1} = A z_k + B u_k``, ``A = [[1, dt], [0, 1]]``,
``B = [-tau dt - dt - dt^2/2, -dt]^T``. At every step the controller solves

    min  sum_{k=1..K} z_k' Q z_k + R sum_{k=0..K-1} u_k^2,   Q = diag(1, alpha)
    s.t. amin <= u_k <= amax

and applies the first input ``u_0``. Condensed, this is a box-constrained QP in the
K inputs whose Hessian depends on the particle only (:func:`mpc_qp_matrices`): it is
factorised once per particle (:meth:`MPC.prepare`) and reused at every step, and each
step warm-starts from the previous solution shifted by one step.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ..qp import BoxQP, QPSettings
from .base import CFModel, Perception, spec


def mpc_qp_matrices(
    tau: Tensor, R: Tensor, alpha: Tensor, dt: float, horizon: int = 5
) -> tuple[Tensor, Tensor]:
    """Hessian and linear-term map of the condensed MPC QP.

    With the stacked predictions ``Z = Phi z_0 + Gamma U`` the cost
    ``sum_{k=1..K} z_k' Q z_k + R sum_k u_k^2`` equals
    ``1/2 U' H U + (G z_0)' U + const`` with ``H = 2 (Gamma' Qbar Gamma + R I)``,
    ``G = 2 Gamma' Qbar Phi`` and ``Qbar = diag(Q, ..., Q)``.

    Args:
        tau: (B,) desired time gap [s].
        R: (B,) input weight.
        alpha: (B,) speed-difference weight.
        dt: step [s].
        horizon: K.

    Returns:
        H: (B, K, K) symmetric positive definite; G: (B, K, 2).
    """
    batch, dtype, device = tau.shape[0], tau.dtype, tau.device
    b_spacing = -tau * dt - dt - 0.5 * dt * dt  # (B,) first entry of B
    b_speed = -dt  # second entry of B
    gamma = torch.zeros(batch, 2 * horizon, horizon, dtype=dtype, device=device)
    phi = torch.zeros(2 * horizon, 2, dtype=dtype, device=device)
    for k in range(1, horizon + 1):
        phi[2 * k - 2, 0], phi[2 * k - 2, 1], phi[2 * k - 1, 1] = 1.0, k * dt, 1.0
        for j in range(k):
            # z_k depends on u_j through A^(k-1-j) B = [b_s + (k-1-j) dt b_v, b_v].
            gamma[:, 2 * k - 2, j] = b_spacing + (k - 1 - j) * dt * b_speed
            gamma[:, 2 * k - 1, j] = b_speed
    state_weights = torch.stack((torch.ones_like(alpha), alpha), dim=1)  # (B, 2)
    weighted = gamma * state_weights.repeat(1, horizon)[:, :, None]  # Qbar Gamma
    eye = torch.eye(horizon, dtype=dtype, device=device)
    hessian = 2.0 * (gamma.transpose(1, 2) @ weighted + R[:, None, None] * eye)
    linear = 2.0 * weighted.transpose(1, 2) @ phi  # (B, K, 2)
    return hessian, linear


# --------------------------------------------------------------------------------------
# The active-set stage between the fast path and ADMM.
class ActiveSetResult(NamedTuple):
    """Outcome of :func:`solve_box_active_set`.

    Attributes:
        x: (b, n) last iterate.
        y: (b, n) multipliers (positive at an active upper bound, negative at a lower).
        solved: (b,) bool, True where ``x`` satisfies the KKT conditions exactly
            (up to rounding): the active set was found.
        n_steps: (b,) int64 active-set steps taken.
    """

    x: Tensor
    y: Tensor
    solved: Tensor
    n_steps: Tensor


def solve_box_active_set(
    P: Tensor,
    q: Tensor,
    l: Tensor,  # noqa: E741
    u: Tensor,
    x: Tensor,
    *,
    max_steps: int = 8,
) -> ActiveSetResult:
    """Primal-dual active-set method for ``min 1/2 x'Px + q'x s.t. l <= x <= u``.

    Hintermueller, Ito & Kunisch (2002), a semismooth Newton method: with the
    multiplier ``y = -(Px + q)`` on the active set, step k guesses
    ``upper = {y + c (x - u) > 0}``, ``lower = {y + c (x - l) < 0}`` (``c = diag P``
    makes the test unit-free), fixes those variables at their bound, solves the
    reduced system exactly for the free ones and stops when the guess is
    self-consistent and the KKT conditions hold. On the small, strictly convex box
    QPs of MPC it finds the exact solution in two or three steps from the clipped
    unconstrained minimiser; instances it does not settle are left to ADMM.

    Args:
        P: (b, n, n) symmetric positive definite.
        q, l, u: (b, n).
        x: (b, n) starting point (e.g. the unconstrained minimiser, or the last
            step's solution).
        max_steps: active-set steps at most.

    Returns:
        :class:`ActiveSetResult`.
    """
    n = q.shape[1]
    eye = torch.eye(n, dtype=P.dtype, device=P.device).expand_as(P)
    scale = torch.diagonal(P, dim1=1, dim2=2)  # (b, n)
    y = torch.zeros_like(q)
    tol = 1e-10 if q.dtype == torch.float64 else 1e-5
    solved = torch.zeros(q.shape[0], dtype=torch.bool, device=q.device)
    n_steps = torch.zeros(q.shape[0], dtype=torch.int64, device=q.device)
    for _ in range(max_steps):
        at_upper = y + scale * (x - u) > 0  # (b, n)
        at_lower = (y + scale * (x - l) < 0) & ~at_upper
        active = at_upper | at_lower
        fixed = torch.where(at_upper, u, torch.where(at_lower, l, torch.zeros_like(x)))
        # Reduced system, kept n x n and symmetric positive definite: the rows and
        # columns of fixed variables become identity, their values move to the
        # right-hand side.
        free_pair = ~active[:, :, None] & ~active[:, None, :]
        reduced = torch.where(free_pair, P, eye)
        rhs = torch.where(active, fixed, -q - _bmv(P, fixed))
        factor, info = torch.linalg.cholesky_ex(reduced)
        step = torch.cholesky_solve(rhs[:, :, None], factor).squeeze(-1)
        step = torch.where(active, fixed, step)
        gradient = _bmv(P, step) + q
        x_new = torch.where(solved[:, None], x, step)
        y = torch.where(solved[:, None], y, torch.where(active, -gradient, 0.0))
        x = x_new
        n_steps += (~solved).long()
        # KKT: primal feasible, multipliers of the right sign, stationary (by
        # construction on the free set).
        slack = tol * (1.0 + x.abs())
        feasible = ((x >= l - slack) & (x <= u + slack)).all(1)
        signs = ((~at_upper | (y >= -slack)) & (~at_lower | (y <= slack))).all(1)
        solved = solved | (feasible & signs & (info == 0))
        if bool(solved.all()):
            break
    return ActiveSetResult(x=x, y=y, solved=solved, n_steps=n_steps)


def _bmv(M: Tensor, v: Tensor) -> Tensor:
    """Batch-first matrix-vector product: (b, r, c) x (b, c) -> (b, r)."""
    return (M @ v[:, :, None]).squeeze(-1)


class MPCParams(NamedTuple):
    tau: Tensor
    R: Tensor
    alpha: Tensor
    l: Tensor  # noqa: E741 - the paper's standstill distance
    amin: Tensor
    amax: Tensor


class MPCPrepared(NamedTuple):
    """An MPC chunk ready to run: flattened parameters and the factorised QPs.

    Every field is over the C = prod(state shape) simulated cells.
    """

    params: MPCParams  # fields (C,)
    solver: BoxQP  # C box QPs of size K
    linear: Tensor  # (C, K, 2): q = linear @ z_0
    free_spacing: Tensor  # (C, K): unconstrained U* = free_spacing e + free_speed dv
    free_speed: Tensor  # (C, K)
    state_shape: tuple[int, ...]


class MPCMemory(NamedTuple):
    """The last step's solution; shifted by one step it warm-starts the next."""

    inputs: Tensor  # (C, K)
    duals: Tensor  # (C, K), zero where no bound was active


#: Solver settings: tight enough that u_0 meets SPEC's 1e-4 (float64) / 1e-3
#: (float32) accuracy; polishing then makes solved instances exact.
MPC_QP_SETTINGS = QPSettings(eps_abs=1e-6, eps_rel=1e-6)


class MPC(CFModel):
    """Model predictive controller with a constant-time-gap spacing policy.

    Every step solves the QP in three stages, each exact where it applies: the
    unconstrained minimiser where it lies inside the box; else a few primal-dual
    active-set steps (:func:`solve_box_active_set`); else warm-started ADMM
    (:class:`~torchcf.qp.BoxQP`).

    Args:
        horizon: prediction horizon K [steps].
        settings: ADMM settings.
        active_set_steps: active-set steps before ADMM takes over (0: ADMM only).
    """

    name = "mpc"
    Params = MPCParams
    param_specs = (
        spec("tau", "s", 0.6, 1.4, "desired time gap"),
        spec("R", "s^4/m^2", 0.3, 1.7, "input (comfort) weight"),
        spec("alpha", "s^2", 0.3, 1.7, "speed-difference weight"),
        spec("l", "m", 3.0, 7.0, "standstill distance"),
        spec("amin", "m/s^2", -5.0, -3.0, "deceleration limit"),
        spec("amax", "m/s^2", 3.0, 5.0, "acceleration limit"),
    )
    compilable = False
    chunk_cells = 1 << 20

    def __init__(
        self,
        horizon: int = 5,
        settings: QPSettings | None = None,
        active_set_steps: int = 8,
    ) -> None:
        if horizon < 1:
            raise ValueError(f"MPC horizon must be >= 1, got {horizon}")
        self.horizon = int(horizon)
        self.settings = settings or MPC_QP_SETTINGS
        self.active_set_steps = int(active_set_steps)

    def prepare(
        self, p: MPCParams, dt: float, state_shape: tuple[int, ...]
    ) -> MPCPrepared:
        n_cells = math.prod(state_shape)
        flat = MPCParams(
            *(field.expand(state_shape).reshape(n_cells) for field in p)
        )  # fields (C,)
        hessian, linear = mpc_qp_matrices(
            flat.tau, flat.R, flat.alpha, dt, self.horizon
        )
        # The unconstrained minimiser is linear in z_0: U* = -H^{-1} G z_0. With
        # this (K, 2) map per cell the common case costs two multiply-adds per input.
        free_map = -torch.linalg.solve(hessian, linear)  # (C, K, 2)
        return MPCPrepared(
            params=flat,
            solver=BoxQP(hessian, self.settings),
            linear=linear,
            free_spacing=free_map[:, :, 0].contiguous(),
            free_speed=free_map[:, :, 1].contiguous(),
            state_shape=tuple(state_shape),
        )

    def command_with_memory(
        self, p: Any, obs: Perception, memory: MPCMemory | None
    ) -> tuple[Tensor, MPCMemory]:
        if not isinstance(p, MPCPrepared):
            raise TypeError("MPC.command needs MPC.prepare(params, dt, state_shape)")
        spacing, v, v_lead = (
            torch.broadcast_to(t, p.state_shape).reshape(-1)  # (C,)
            for t in (obs.spacing, obs.v, obs.v_lead)
        )
        q = p.params
        spacing_error = spacing - v * q.tau - q.l  # (C,)
        speed_difference = v_lead - v  # (C,)
        # Exact fast path: an unconstrained minimiser inside the box is the solution.
        inputs = (
            p.free_spacing * spacing_error[:, None]
            + p.free_speed * speed_difference[:, None]
        )  # (C, K)
        lowest, highest = torch.aminmax(inputs, dim=1)
        outside = (lowest < q.amin) | (highest > q.amax)
        duals = (
            torch.zeros_like(inputs)
            if memory is None
            else memory.duals.masked_fill(~outside[:, None], 0.0)
        )
        rest = outside.nonzero().squeeze(1)
        if rest.numel():
            z0 = torch.stack((spacing_error[rest], speed_difference[rest]), dim=1)
            linear_term = torch.einsum("ckj,cj->ck", p.linear[rest], z0)  # (b, K)
            bound_shape = (rest.numel(), self.horizon)
            lower = q.amin[rest, None].expand(bound_shape)
            upper = q.amax[rest, None].expand(bound_shape)
            # Active-set steps from the unconstrained minimiser settle almost every
            # instance exactly; ADMM only gets the few they do not.
            settled = solve_box_active_set(
                p.solver.P.index_select(0, rest),
                linear_term,
                lower,
                upper,
                inputs[rest],
                max_steps=self.active_set_steps,
            )
            inputs = inputs.index_copy(0, rest, settled.x)
            duals = duals.index_copy(0, rest, settled.y)
            keep = ~settled.solved
            rest, linear_term = rest[keep], linear_term[keep]
            lower, upper = lower[keep], upper[keep]
            bound_shape = (rest.numel(), self.horizon)
        if rest.numel():
            warm = None
            if memory is not None:
                # Receding horizon: the rest of the last plan is this step's guess.
                last = memory.inputs[rest]
                warm = torch.cat((last[:, 1:], last[:, -1:]), dim=1)
                last_duals = memory.duals[rest]
                warm_duals = torch.cat((last_duals[:, 1:], last_duals[:, -1:]), dim=1)
            result = p.solver.solve(
                linear_term,
                lower,
                upper,
                x0=warm,
                y0=None if memory is None else warm_duals,
                index=rest,
            )
            inputs = inputs.index_copy(0, rest, result.x)
            duals = duals.index_copy(0, rest, result.y)
        command = inputs[:, 0].reshape(p.state_shape)
        return command, MPCMemory(inputs=inputs, duals=duals)

    def command(self, p: Any, obs: Perception) -> Tensor:
        return self.command_with_memory(p, obs, None)[0]

    def __repr__(self) -> str:
        return f"MPC(horizon={self.horizon})"
