"""The peer baseline: one particle at a time, a Python loop over time steps, NumPy.

This is how the paper's released implementation simulates (its ``CF_Model.
simulator``): for one parameter vector and one leader-follower pair it allocates
NumPy arrays of length T, walks ``for t in range(T - 1)`` updating the follower
from scalar expressions, and scores the trajectory; ABC then calls it once per
particle. Written here from SPEC sections 2-4 (not copied), so that its scores can
be checked against torchcf's on the same particles: ``tools/bench_models.py`` times
it per particle-step and reports torchcf's speed-up over it.

MPC solves its box QP at every step with OSQP (one solver per particle, updated
and warm-started from step to step), which is faster than the released code's
per-step ``qpsolvers.solve_qp`` on the uncondensed problem: the speed-up reported
for MPC is a lower bound.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys

import numpy as np

#: IDM's spacing floor where it divides (SPEC section 2).
IDM_SPACING_FLOOR = 0.1


def _command(model: str, p: np.ndarray, s, v, v_lead, a, length: float):
    """The acceleration command of SPEC section 3 for one particle, scalars."""
    dv = v_lead - v
    if model == "ovm":
        kappa, v1, v2, c1, c2 = p
        return kappa * (v1 + v2 * np.tanh(c1 * (s - length) - c2) - v)
    if model == "gfm":
        k, lam, v1, v2, c1, c2 = p
        closing = 1.0 if dv < 0 else 0.0
        return k * (v1 + v2 * np.tanh(c1 * (s - length) - c2) - v) + lam * closing * dv
    if model == "fvdm":
        tau, lam, big_v1, big_v2, l_int, beta = p
        optimal = big_v1 + big_v2 * np.tanh((s - length) / l_int - beta)
        return (optimal - v) / tau + lam * dv
    if model == "idm":
        a_max, b, v0, headway, s0, delta = p
        s_star = s0 + max(0.0, v * headway - v * dv / (2.0 * np.sqrt(a_max * b)))
        return a_max * (
            1.0 - (v / v0) ** delta - (s_star / max(s, IDM_SPACING_FLOOR)) ** 2
        )
    if model == "llctg":
        tau, ks, kv, gap = p
        return ks * (s - v * tau - gap) + kv * dv
    if model == "llcs":
        s0, ks, kv = p
        return ks * (s - s0) + kv * dv
    if model == "hl":
        tau, _lag, ks, kv, ka, gap = p
        return ks * (s - v * tau - gap) + kv * dv + ka * a
    raise ValueError(f"no command for {model!r}")


class _MPCSolver:
    """The MPC's condensed box QP of one particle (SPEC section 3), OSQP per step.

    ``min_U (Phi z0 + G U)' Qbar (Phi z0 + G U) + R U'U`` s.t. ``amin <= U <=
    amax``; the Hessian depends on the particle only, so one OSQP problem is set
    up per particle and only the linear term changes from step to step.
    """

    def __init__(self, p: np.ndarray, dt: float, horizon: int) -> None:
        import osqp
        from scipy import sparse

        tau, r, alpha, self.gap, amin, amax = p
        self.tau = tau
        a_mat = np.array([[1.0, dt], [0.0, 1.0]])
        b_vec = np.array([-tau * dt - dt - dt * dt / 2.0, -dt])
        q_mat = np.diag([1.0, alpha])
        phi = np.zeros((2 * horizon, 2))
        gamma = np.zeros((2 * horizon, horizon))
        power = np.eye(2)
        for k in range(horizon):
            power = a_mat @ power  # A^(k+1)
            phi[2 * k : 2 * k + 2] = power
            for j in range(k + 1):
                gamma[2 * k : 2 * k + 2, j] = (
                    np.linalg.matrix_power(a_mat, k - j) @ b_vec
                )
        q_bar = np.kron(np.eye(horizon), q_mat)
        hessian = 2.0 * (gamma.T @ q_bar @ gamma + r * np.eye(horizon))
        self.linear = 2.0 * gamma.T @ q_bar @ phi  # q = linear @ z0
        self.solver = osqp.OSQP()
        self.solver.setup(
            P=sparse.csc_matrix(np.triu(hessian)),
            q=np.zeros(horizon),
            A=sparse.identity(horizon, format="csc"),
            l=np.full(horizon, amin),
            u=np.full(horizon, amax),
            eps_abs=1e-9,
            eps_rel=1e-9,
            max_iter=20000,
            polishing=True,
            verbose=False,
        )

    def command(self, s, v, v_lead) -> float:
        z0 = np.array([s - v * self.tau - self.gap, v_lead - v])
        self.solver.update(q=self.linear @ z0)
        return float(self.solver.solve().x[0])


@contextlib.contextmanager
def quiet_stdout():
    """Silence file descriptor 1: OSQP 1.x prints polishing notes even with
    ``verbose=False``."""
    sys.stdout.flush()
    saved = os.dup(1)
    with open(os.devnull, "w") as devnull:
        os.dup2(devnull.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)


def simulate_one(
    model: str,
    p: np.ndarray,
    x_lead: np.ndarray,
    v_lead: np.ndarray,
    x_obs: np.ndarray,
    v_obs: np.ndarray,
    a_obs: np.ndarray,
    dt: float,
    length: float = 5.0,
    weights: tuple[float, float, float] = (0.5, 0.3, 0.2),
    horizon: int = 5,
) -> float:
    """Score of one particle ``p`` on one pair (SPEC sections 2 and 4).

    Args:
        model: registry name.
        p: (K,) parameters.
        x_lead, v_lead, x_obs, v_obs, a_obs: (T,) the pair, all steps valid.
        dt: step [s]; length: leader length [m].

    Returns:
        the score, ``inf`` for an invalid rollout.
    """
    n_steps = len(x_lead)
    xf = np.zeros(n_steps)
    vf = np.zeros(n_steps)
    af = np.zeros(n_steps)
    xf[0], vf[0] = x_obs[0], v_obs[0]
    lagged = model == "hl"
    mpc = _MPCSolver(p, dt, horizon) if model == "mpc" else None
    if lagged:
        af[0] = a_obs[0]
        decay = math.exp(-dt / p[1])
        lag = p[1]
    with np.errstate(all="ignore"):
        for t in range(n_steps - 1):
            s = x_lead[t] - xf[t]
            if mpc is not None:
                u = mpc.command(s, vf[t], v_lead[t])
            else:
                u = _command(model, p, s, vf[t], v_lead[t], af[t], length)
            if lagged:
                af[t + 1] = u + (af[t] - u) * decay
                v_next = vf[t] + u * dt + (af[t] - u) * lag * (1.0 - decay)
                x_next = (
                    xf[t]
                    + vf[t] * dt
                    + u * dt * dt / 2.0
                    + (af[t] - u) * lag * (dt - lag * (1.0 - decay))
                )
            else:
                af[t] = u
                v_next = vf[t] + u * dt
                x_next = xf[t] + vf[t] * dt + u * dt * dt / 2.0
            vf[t + 1] = 0.0 if v_next < 0.0 else v_next  # NaN passes through
            xf[t + 1] = xf[t] if x_next < xf[t] else x_next
        if not lagged:
            s = x_lead[-1] - xf[-1]
            if mpc is not None:
                af[-1] = mpc.command(s, vf[-1], v_lead[-1])
            else:
                af[-1] = _command(model, p, s, vf[-1], v_lead[-1], af[-1], length)
        finite = np.isfinite(xf).all() and np.isfinite(vf).all()
        if not (finite and np.isfinite(af).all()) or (x_lead - xf <= 0).any():
            return math.inf
        e_p = np.sqrt(np.mean((xf - x_obs) ** 2))
        e_v = np.sqrt(np.mean((vf - v_obs) ** 2))
        e_a = np.sqrt(np.mean((af - a_obs) ** 2))
    return float(weights[0] * e_p + weights[1] * e_v + weights[2] * e_a)


__all__ = ["quiet_stdout", "simulate_one"]
