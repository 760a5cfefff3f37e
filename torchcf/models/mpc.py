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
step warm-starts from the previous solution: its active set is the first guess of
the active-set stage, and, shifted by one step, it starts ADMM.

Shapes (:mod:`torchcf.typing`): ``B`` QPs, one per simulated cell, each in the
``n = K`` inputs of the horizon (the QP's ``n`` variables).
"""

from __future__ import annotations

import math
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor

from ..qp import BoxQP, QPSettings
from .base import CFModel, Perception, rows_of, spec


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
        horizon: K, the QP's ``n`` inputs.

    Returns:
        H: (B, n, n) symmetric positive definite; G: (B, n, 2), ``n = K``.
    """
    batch, dtype, device = tau.shape[0], tau.dtype, tau.device
    b_spacing = -tau * dt - dt - 0.5 * dt * dt  # (B,) first entry of matrix B
    b_speed = -dt  # second entry of matrix B
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
    linear = 2.0 * weighted.transpose(1, 2) @ phi  # (B, n, 2)
    return hessian, linear


class MPCParams(NamedTuple):
    tau: Tensor
    R: Tensor
    alpha: Tensor
    l: Tensor  # noqa: E741 - the paper's standstill distance
    amin: Tensor
    amax: Tensor


class MPCPrepared(NamedTuple):
    """An MPC chunk ready to run: flattened parameters and the factorised QPs.

    Every field is over the B = prod(state shape) simulated cells, one QP each.
    """

    params: MPCParams  # fields (B,)
    solver: BoxQP  # B box QPs of n = K variables
    linear: Tensor  # (B, n, 2): q = linear @ z_0
    # (n, B) each, batch-last: the unconstrained U* = free_spacing e + free_speed dv
    # and its bounds test are then n contiguous rows of B (the batch-first
    # (B, n) layout's reductions over n = 5 cost 2.4x more on the CPU)
    free_spacing: Tensor
    free_speed: Tensor
    state_shape: tuple[int, ...]


class MPCDraft(NamedTuple):
    """A step's plan before the box is enforced (:meth:`MPC.draft_with_memory`)."""

    inputs: Tensor  # (n, B) the unconstrained plan, batch-last
    outside: Tensor  # (B,) bool: the plan leaves the box (the QP must be solved)
    spacing_error: Tensor  # (B,) z_0[0] = s - v tau - l [m]
    speed_difference: Tensor  # (B,) z_0[1] = dv [m/s]


class MPCMemory(NamedTuple):
    """The last step's solution; shifted by one step it warm-starts the next."""

    inputs: Tensor  # (n, B), batch-last as MPCPrepared.free_spacing


#: Solver settings: tight enough that u_0 meets SPEC's 1e-4 (float64) / 1e-3
#: (float32) accuracy; polishing then makes solved instances exact.
MPC_QP_SETTINGS = QPSettings(eps_abs=1e-6, eps_rel=1e-6)


class MPC(CFModel):
    """Model predictive controller with a constant-time-gap spacing policy.

    Every step solves the QP in three stages, each exact where it applies: the
    unconstrained minimiser where it lies inside the box (a precomputed linear map
    of ``z_0``); else :class:`~torchcf.qp.BoxQP`'s active-set steps; else its
    warm-started ADMM.

    Args:
        horizon: prediction horizon K [steps], the QP's ``n`` variables.
        settings: ADMM settings.
        method: ``"auto"`` (the stages above) or ``"admm"`` (ADMM alone after the
            fast path; for testing the solver).
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
    #: The QP's data-dependent stages cannot be traced; the unconstrained plan
    #: and its bounds test (every cell, every step) compile with the step.
    compilable = False
    corrects = True
    #: 65 536 QPs per simulate call: on 2 CPU threads the smallest batch at full
    #: throughput (torch splits an elementwise op over threads by 32 768
    #: elements; larger batches leave the cache: a million CAR MODEL II particles
    #: took 18.3 s in chunks of 2^16, 19.3 s of 2^17, 23.4 s in one), and a
    #: million paired particles are 16 rounds, each a progress update and a
    #: chance to checkpoint. The scores were the same, bit for bit, at all three.
    chunk_cells = 1 << 16
    batch_size_invariant = False

    def __init__(
        self,
        horizon: int = 5,
        settings: QPSettings | None = None,
        method: Literal["auto", "admm"] = "auto",
    ) -> None:
        if horizon < 1:
            raise ValueError(f"MPC horizon must be >= 1, got {horizon}")
        self.horizon = int(horizon)
        self.settings = settings or MPC_QP_SETTINGS
        if method not in ("auto", "admm"):
            raise ValueError(f"method must be 'auto' or 'admm', got {method!r}")
        self.method = method

    def prepare(
        self, p: MPCParams, dt: float, state_shape: tuple[int, ...]
    ) -> MPCPrepared:
        n_cells = math.prod(state_shape)
        flat = MPCParams(
            *(field.expand(state_shape).reshape(n_cells) for field in p)
        )  # fields (B,)
        hessian, linear = mpc_qp_matrices(
            flat.tau, flat.R, flat.alpha, dt, self.horizon
        )
        solver = BoxQP(hessian, self.settings)
        # The unconstrained minimiser is linear in z_0: U* = -H^{-1} G z_0. With
        # this (n, 2) map per cell (from the solver's cached inverse) the common
        # case costs two multiply-adds per input.
        return MPCPrepared(
            params=flat,
            solver=solver,
            linear=linear,
            free_spacing=solver.unconstrained(linear[:, :, 0]).T.contiguous(),
            free_speed=solver.unconstrained(linear[:, :, 1]).T.contiguous(),
            state_shape=tuple(state_shape),
        )

    def select_particles(
        self, p: Any, memory: MPCMemory | None, rows: Tensor
    ) -> tuple[MPCPrepared, MPCMemory | None]:
        """The chunk's particles ``rows`` alone, their factorised QPs taken as
        they are (not factorised again: a batch of another size could take
        other kernels, :attr:`batch_size_invariant`)."""
        if len(p.state_shape) == 1:
            cells = rows
        else:  # the full layout: a particle's cells are a row of (P, N)
            width = p.state_shape[1]
            columns = torch.arange(width, device=rows.device)
            cells = (rows[:, None] * width + columns).reshape(-1)
        kept = MPCPrepared(
            params=rows_of(p.params, cells),
            solver=p.solver.take(cells),
            linear=p.linear.index_select(0, cells),
            free_spacing=p.free_spacing.index_select(1, cells),
            free_speed=p.free_speed.index_select(1, cells),
            state_shape=(rows.numel(), *p.state_shape[1:]),
        )
        if memory is None:
            return kept, None
        return kept, MPCMemory(inputs=memory.inputs.index_select(1, cells))

    def draft_with_memory(
        self, p: Any, obs: Perception, memory: MPCMemory | None
    ) -> tuple[MPCDraft, MPCMemory | None]:
        """The unconstrained plan of every cell and where it leaves the box:
        elementwise, compiled with the rest of the step (:attr:`corrects`)."""
        if not isinstance(p, MPCPrepared):
            raise TypeError("MPC.command needs MPC.prepare(params, dt, state_shape)")
        q = p.params
        # In a rollout the perception has the state's shape (its speed is the
        # state's): broadcast against each other, not to p.state_shape, whose
        # ints would fix a compiled graph's particle count. A direct call may
        # give parts of it (a scalar speed): those are expanded to the state.
        parts = torch.broadcast_tensors(obs.spacing, obs.v, obs.v_lead)
        if parts[0].numel() != q.tau.numel():
            parts = tuple(t.expand(p.state_shape) for t in parts)
        spacing, v, v_lead = (t.reshape(-1) for t in parts)  # (B,)
        spacing_error = spacing - v * q.tau - q.l  # (B,)
        speed_difference = v_lead - v  # (B,)
        # Exact fast path: an unconstrained minimiser inside the box is the solution.
        inputs = (
            p.free_spacing * spacing_error + p.free_speed * speed_difference
        )  # (n, B)
        # rows' min and max, then one compare each: 5x cheaper than .any(0) of
        # the (n, B) comparisons, and NaN stays inside either way
        outside = (inputs.amin(0) < q.amin) | (inputs.amax(0) > q.amax)  # (B,)
        return MPCDraft(inputs, outside, spacing_error, speed_difference), memory

    def correct(
        self, p: Any, pending: MPCDraft, memory: MPCMemory | None
    ) -> tuple[Tensor, MPCMemory]:
        """The QP solved where the unconstrained plan leaves the box; the first
        input is the command (data-dependent: eager)."""
        inputs, outside, spacing_error, speed_difference = pending
        q = p.params
        rest = outside.nonzero().squeeze(1)
        if rest.numel():
            z0 = torch.stack((spacing_error[rest], speed_difference[rest]), dim=1)
            linear_term = torch.einsum("ckj,cj->ck", p.linear[rest], z0)  # (b, n)
            bound_shape = (rest.numel(), self.horizon)
            warm = last = None
            if memory is not None:
                # Receding horizon: the rest of the last plan starts ADMM (BoxQP
                # derives the duals from it, which starts ADMM better than shifted
                # duals would). The last plan itself, unshifted, is the better guess
                # of the active set: saturated inputs tend to stay saturated.
                last = memory.inputs[:, rest].T  # (b, n)
                warm = torch.cat((last[:, 1:], last[:, -1:]), dim=1)
            result = p.solver.solve(
                linear_term,
                q.amin[rest, None].expand(bound_shape),
                q.amax[rest, None].expand(bound_shape),
                x0=warm,
                index=rest,
                method=self.method,
                active_guess=last,
            )
            inputs.index_copy_(1, rest, result.x.T)  # the draft's own plan
        command = inputs[0].reshape(p.state_shape)
        return command, MPCMemory(inputs=inputs)

    def command_with_memory(
        self, p: Any, obs: Perception, memory: MPCMemory | None
    ) -> tuple[Tensor, MPCMemory]:
        return self.correct(p, *self.draft_with_memory(p, obs, memory))

    def command(self, p: Any, obs: Perception) -> Tensor:
        return self.command_with_memory(p, obs, None)[0]

    def __repr__(self) -> str:
        return f"MPC(horizon={self.horizon})"
