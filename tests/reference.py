"""Independent scalar reference of the car-following contract (``SPEC.md``).

Written from ``SPEC.md`` alone, without reading the engine, so that tests can
check the PyTorch engine against it:

- ``PRIORS``: the uniform prior boxes of SPEC section 3 (from the released
  ``data/abc-paper/priori/*.csv`` files, with SPEC section 3's notes applied).
- ``command``: the acceleration command ``u`` of SPEC section 3 for one particle.
- ``simulate_pair``: the rollout of SPEC section 2 and the score of SPEC section 4,
  one plain Python loop over time.
- ``integrate_lag_fine``: a fine RK4 integration of HL's actuation lag over one
  step, to check the exact zero-order-hold update of SPEC section 2.

MPC is not covered. Everything is float64 / Python floats.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

# SPEC section 3: parameter order = row order of the prior files (rows "lower,upper").
# Notes applied: FVDM lower bounds of tau and l_int raised from 0 to 0.1; the trailing
# tau row fixed at [0, 0] in OVM_uniform.csv and GFM_uniform.csv dropped.
PRIORS: dict[str, list[tuple[str, float, float]]] = {
    # OVM_uniform.csv
    "ovm": [
        ("kappa", 0.5, 2.0),
        ("v1", 5.0, 8.0),
        ("v2", 20.0, 25.0),
        ("c1", 0.05, 0.2),
        ("c2", 1.5, 1.7),
    ],
    # GFM_uniform.csv
    "gfm": [
        ("K", 0.0, 2.0),
        ("lam", 0.0, 2.0),
        ("v1", 0.0, 10.0),
        ("v2", 0.0, 30.0),
        ("c1", 0.0, 0.2),
        ("c2", 1.0, 2.0),
    ],
    # FVM_uniform.csv
    "fvdm": [
        ("tau", 0.1, 2.0),
        ("lam", 0.0, 2.0),
        ("V1", 0.0, 30.0),
        ("V2", 0.0, 30.0),
        ("l_int", 0.1, 10.0),
        ("beta", 0.0, 30.0),
    ],
    # IDM_uniform.csv
    "idm": [
        ("a", 0.5, 2.0),
        ("b", 1.0, 4.0),
        ("v0", 20.0, 40.0),
        ("T", 0.8, 2.5),
        ("s0", 0.5, 3.0),
        ("delta", 2.0, 5.0),
    ],
    # LL_uniform.csv
    "llctg": [
        ("tau", 0.8, 1.2),
        ("ks", 0.3, 2.3),
        ("kv", 0.3, 2.3),
        ("l", 1.0, 11.0),
    ],
    # LLCS_uniform.csv
    "llcs": [
        ("s0", 5.0, 25.0),
        ("ks", 0.3, 2.3),
        ("kv", 0.3, 2.3),
    ],
    # HL_uniform.csv
    "hl": [
        ("tau", 0.8, 1.2),
        ("TT", 0.1, 0.5),
        ("ks", 0.1, 2.3),
        ("kv", 0.1, 2.3),
        ("ka", -3.0, 0.0),
        ("l", 3.0, 8.0),
    ],
    # MPC_uniform.csv
    "mpc": [
        ("tau", 0.6, 1.4),
        ("R", 0.3, 1.7),
        ("alpha", 0.3, 1.7),
        ("l", 3.0, 7.0),
        ("amin", -5.0, -3.0),
        ("amax", 3.0, 5.0),
    ],
}

POINT_MASS_MODELS = ("ovm", "gfm", "fvdm", "idm", "llctg", "llcs")
IDM_SPACING_FLOOR = 0.1  # SPEC section 2: IDM's s is floored at 0.1 m where it divides


def _ov(v1: float, v2: float, c1: float, c2: float, g: float) -> float:
    """Optimal velocity of OVM/GFM (SPEC section 3): v1 + v2 tanh(c1 g - c2)."""
    return v1 + v2 * math.tanh(c1 * g - c2)


def command(
    model: str,
    theta,
    s: float,
    v: float,
    v_lead: float,
    a: float,
    L: float,
    dt: float = 0.1,
    horizon: int = 5,
) -> float:
    """Acceleration command ``u`` of one particle (SPEC section 3, table).

    MPC (``dt`` and ``horizon`` are its prediction step and horizon) is solved
    exactly by :func:`mpc_command`.

    ``s = x_l - x`` is the front-to-front spacing, ``dv = v_lead - v``, ``a`` the
    follower's realised acceleration state (used by HL only), ``L`` the leader
    length. Arithmetic failures (overflow, invalid power, division by zero) return
    NaN, which makes the rollout invalid (SPEC section 2).
    """
    p = [float(q) for q in theta]
    dv = v_lead - v
    try:
        if model == "ovm":
            kappa, v1, v2, c1, c2 = p
            return kappa * (_ov(v1, v2, c1, c2, s - L) - v)
        if model == "gfm":
            K, lam, v1, v2, c1, c2 = p
            h = 1.0 if -dv > 0 else 0.0  # H(-dv): acts only when closing in
            return K * (_ov(v1, v2, c1, c2, s - L) - v) + lam * h * dv
        if model == "fvdm":
            tau, lam, V1, V2, l_int, beta = p
            V = V1 + V2 * math.tanh((s - L) / l_int - beta)
            return (V - v) / tau + lam * dv
        if model == "idm":
            a_max, b, v0, T_h, s0, delta = p
            s_star = s0 + max(0.0, v * T_h - v * dv / (2.0 * math.sqrt(a_max * b)))
            s_div = max(s, IDM_SPACING_FLOOR)  # floored only where it divides
            return a_max * (1.0 - math.pow(v / v0, delta) - (s_star / s_div) ** 2)
        if model == "llctg":
            tau, ks, kv, l_gap = p
            return ks * (s - v * tau - l_gap) + kv * dv
        if model == "llcs":
            s0, ks, kv = p
            return ks * (s - s0) + kv * dv
        if model == "hl":
            tau, _TT, ks, kv, ka, l_gap = p
            return ks * (s - v * tau - l_gap) + kv * dv + ka * a
        if model == "mpc":
            return mpc_command(p, s, v, v_lead, dt, horizon)
    except (OverflowError, ValueError, ZeroDivisionError):
        return math.nan
    raise ValueError(f"unknown model {model!r}")


def _rmse(sim: list[float], obs, n: int) -> float:
    """Root-mean-square of sim - obs over the first n (valid) steps (SPEC section 4)."""
    total = math.fsum((sim[t] - float(obs[t])) ** 2 for t in range(n))
    return math.sqrt(total / n)


def simulate_pair(
    model: str,
    theta,
    x_lead,
    v_lead,
    x_f,
    v_f,
    a_f,
    dt: float,
    L: float = 5.0,
    weights=(0.5, 0.3, 0.2),
    mask=None,
) -> dict:
    """Simulate one follower behind a replayed leader and score it.

    SPEC section 2 (rollout, invalid rollouts) and section 4 (RMSE errors, score).
    Inputs are length-T series of one pair; ``mask`` is a (T,) bool prefix of valid
    steps (default all valid). Returns the simulated series ``x, v, a`` (float64
    arrays of length T), ``e_p, e_v, e_a, score`` and ``valid``; an invalid rollout
    has ``score = e_p = e_v = e_a = inf``.
    """
    if model not in PRIORS:
        raise ValueError(f"unknown model {model!r}")
    T = len(x_lead)
    dt = float(dt)
    L = float(L)
    if mask is None:
        n_valid = T
    else:
        n_valid = int(sum(bool(m) for m in mask))  # the mask is a prefix
    if n_valid < 1:
        raise ValueError("no valid step")
    is_hl = model == "hl"
    TT = float(theta[1]) if is_hl else 0.0

    x = [0.0] * T
    v = [0.0] * T
    a = [0.0] * T  # the recorded acceleration series

    # Section 2, initial state: x(0) = x_f(0), v(0) = v_f(0); HL also a(0) = a_f(0).
    x[0] = float(x_f[0])
    v[0] = float(v_f[0])
    if is_hl:
        a[0] = float(a_f[0])

    for t in range(T - 1):
        # Section 2: the command from the state at t and the leader at t.
        s = float(x_lead[t]) - x[t]
        u = command(model, theta, s, v[t], float(v_lead[t]), a[t], L, dt=dt)
        try:
            if is_hl:
                # Exact zero-order hold of da/dt = (u - a) / TT over one step.
                e = math.exp(-dt / TT)
                a_next = u + (a[t] - u) * e
                v_next = v[t] + u * dt + (a[t] - u) * TT * (1.0 - e)
                x_next = (
                    x[t]
                    + v[t] * dt
                    + u * dt * dt / 2.0
                    + (a[t] - u) * TT * (dt - TT * (1.0 - e))
                )
                a[t + 1] = a_next
            else:
                # Point mass: a(t) = u(t).
                a[t] = u
                v_next = v[t] + a[t] * dt
                x_next = x[t] + v[t] * dt + a[t] * dt * dt / 2.0
        except (OverflowError, ValueError, ZeroDivisionError):
            x_next = v_next = math.nan
            if is_hl:
                a[t + 1] = math.nan
            else:
                a[t] = math.nan
        # No reversing: v(t+1) = max(v(t+1), 0), x(t+1) = max(x(t+1), x(t)).
        # Written so that NaN propagates (NaN < c is False).
        v[t + 1] = 0.0 if v_next < 0.0 else v_next
        x[t + 1] = x[t] if x_next < x[t] else x_next

    if not is_hl:
        # Section 2: at t = T-1 the command at the final state.
        s = float(x_lead[T - 1]) - x[T - 1]
        a[T - 1] = command(
            model, theta, s, v[T - 1], float(v_lead[T - 1]), 0.0, L, dt=dt
        )

    # Section 2, invalid: any non-finite simulated value, or spacing <= 0, at a
    # valid step.
    valid = True
    for t in range(n_valid):
        if not (math.isfinite(x[t]) and math.isfinite(v[t]) and math.isfinite(a[t])):
            valid = False
        elif float(x_lead[t]) - x[t] <= 0.0:
            valid = False

    if valid:
        # Section 4: RMSE over valid steps, weighted score.
        e_p = _rmse(x, x_f, n_valid)
        e_v = _rmse(v, v_f, n_valid)
        e_a = _rmse(a, a_f, n_valid)
        w0, w1, w2 = (float(w) for w in weights)
        score = w0 * e_p + w1 * e_v + w2 * e_a
    else:
        e_p = e_v = e_a = score = math.inf

    return {
        "x": np.array(x, dtype=np.float64),
        "v": np.array(v, dtype=np.float64),
        "a": np.array(a, dtype=np.float64),
        "e_p": e_p,
        "e_v": e_v,
        "e_a": e_a,
        "score": score,
        "valid": valid,
    }


def integrate_lag_fine(
    u: float,
    a0: float,
    v0: float,
    x0: float,
    TT: float,
    dt: float,
    n_sub: int = 10000,
) -> tuple[float, float, float]:
    """Integrate HL's lag over one step with a constant command (SPEC section 2, HL).

    Solves da/dt = (u - a) / TT, dv/dt = a, dx/dt = v from (x0, v0, a0) over a
    time ``dt`` with ``n_sub`` explicit RK4 sub-steps; returns (x1, v1, a1). No
    clamping is applied (the clamps of section 2 come after the lag update).
    """
    h = dt / n_sub

    def rhs(x: float, v: float, a: float) -> tuple[float, float, float]:
        return v, a, (u - a) / TT

    x, v, a = float(x0), float(v0), float(a0)
    for _ in range(n_sub):
        k1x, k1v, k1a = rhs(x, v, a)
        k2x, k2v, k2a = rhs(x + h / 2 * k1x, v + h / 2 * k1v, a + h / 2 * k1a)
        k3x, k3v, k3a = rhs(x + h / 2 * k2x, v + h / 2 * k2v, a + h / 2 * k2a)
        k4x, k4v, k4a = rhs(x + h * k3x, v + h * k3v, a + h * k3a)
        x += h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v += h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        a += h / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)
    return x, v, a


def mid_prior(model: str) -> list[float]:
    """Centre of the prior box of a model (SPEC section 3 priors)."""
    return [(lo + hi) / 2.0 for _, lo, hi in PRIORS[model]]


def _synthetic_leader(T: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Leader at 15 m/s for 20 s, then braking at 2 m/s^2 to 5 m/s, then steady."""
    x = np.zeros(T)
    v = np.zeros(T)
    x[0], v[0] = 100.0, 15.0
    for t in range(T - 1):
        acc = -2.0 if (t * dt >= 20.0 and v[t] > 5.0) else 0.0
        v[t + 1] = max(v[t] + acc * dt, 5.0)
        x[t + 1] = x[t] + (v[t] + v[t + 1]) / 2.0 * dt
    return x, v


if __name__ == "__main__":
    dt, T = 0.1, 400
    x_l, v_l = _synthetic_leader(T, dt)

    # Observed follower: the IDM at mid-prior parameters, so IDM must score 0.
    ref = simulate_pair(
        "idm", mid_prior("idm"), x_l, v_l,
        np.full(T, 70.0), np.full(T, 15.0), np.zeros(T), dt,
    )  # fmt: skip
    # Only x_f(0), v_f(0) (and a_f(0) for HL) above were used; now the real one.
    x_f, v_f, a_f = ref["x"], ref["v"], ref["a"]
    assert ref["valid"]

    for name in PRIORS:
        out = simulate_pair(name, mid_prior(name), x_l, v_l, x_f, v_f, a_f, dt)
        print(
            f"{name:6s} valid={out['valid']!s:5s} score={out['score']:10.4f} "
            f"e_p={out['e_p']:9.4f} e_v={out['e_v']:8.4f} e_a={out['e_a']:8.4f}"
        )
        if name == "idm":
            assert out["score"] < 1e-12, out["score"]

    # Mask: scoring only a prefix.
    mask = np.arange(T) < 150
    out = simulate_pair("ovm", mid_prior("ovm"), x_l, v_l, x_f, v_f, a_f, dt, mask=mask)
    print(f"ovm on a 150-step prefix: score={out['score']:.4f}")

    # Invalid rollout: a follower starting ahead of the leader.
    out = simulate_pair("llcs", mid_prior("llcs"), x_l, v_l, x_l + 1.0, v_f, a_f, dt)
    assert not out["valid"] and out["score"] == math.inf
    print("collision -> invalid, score inf")

    # HL exact zero-order-hold step against a fine RK4 integration.
    u, a0, v0, x0, TT = 1.3, -0.7, 12.0, 3.0, 0.3
    e = math.exp(-dt / TT)
    exact = (
        x0 + v0 * dt + u * dt * dt / 2.0 + (a0 - u) * TT * (dt - TT * (1.0 - e)),
        v0 + u * dt + (a0 - u) * TT * (1.0 - e),
        u + (a0 - u) * e,
    )
    fine = integrate_lag_fine(u, a0, v0, x0, TT, dt)
    err = max(abs(p - q) for p, q in zip(exact, fine, strict=True))
    print(f"HL exact step vs RK4: max abs diff {err:.2e}")
    assert err < 1e-12


# ---------------------------------------------------------------------------- MPC
def mpc_cost(theta, z0, inputs, dt: float) -> float:
    """SPEC 3's MPC cost, by simulating the prediction model step by step.

    ``z_{k+1} = A z_k + B u_k``, ``A = [[1, dt], [0, 1]]``,
    ``B = [-tau dt - dt - dt^2/2, -dt]``; cost
    ``sum_{k=1..K} z_k' diag(1, alpha) z_k + R sum_k u_k^2``.
    """
    tau, R, alpha = theta[0], theta[1], theta[2]
    b_s, b_v = -tau * dt - dt - dt * dt / 2.0, -dt
    e, w = float(z0[0]), float(z0[1])
    cost = 0.0
    for u in inputs:
        e, w = e + dt * w + b_s * u, w + b_v * u
        cost += e * e + alpha * w * w + R * u * u
    return cost


def mpc_qp(theta, z0, dt: float, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Hessian H and gradient g at 0 of :func:`mpc_cost` (exact: it is quadratic)."""
    zero = np.zeros(horizon)
    c0 = mpc_cost(theta, z0, zero, dt)
    unit = np.eye(horizon)
    single = [mpc_cost(theta, z0, unit[i], dt) for i in range(horizon)]
    minus = [mpc_cost(theta, z0, -unit[i], dt) for i in range(horizon)]
    g = np.array([(single[i] - minus[i]) / 2.0 for i in range(horizon)])
    H = np.empty((horizon, horizon))
    for i in range(horizon):
        for j in range(horizon):
            both = mpc_cost(theta, z0, unit[i] + unit[j], dt)
            H[i, j] = both - single[i] - single[j] + c0
    return H, g


def solve_box_qp_exact(H, g, lower, upper) -> np.ndarray:
    """argmin 1/2 u'Hu + g'u on a box, by enumerating active sets (small n only).

    For each assignment of every variable to {free, lower, upper} (fewest active
    first), solve the reduced system and accept the first point satisfying the
    KKT conditions; for a strictly convex QP it is the unique minimiser.
    """
    n = len(g)
    if n > 6:  # 3^n active sets is too many: bounded least squares (scipy's BVLS)
        return _solve_box_qp_bvls(H, g, lower, upper)
    assignments = sorted(
        itertools.product((0, -1, 1), repeat=n), key=lambda a: sum(map(abs, a))
    )
    for assignment in assignments:
        u = np.zeros(n)
        free = [i for i in range(n) if assignment[i] == 0]
        for i in range(n):
            if assignment[i] < 0:
                u[i] = lower[i]
            elif assignment[i] > 0:
                u[i] = upper[i]
        if free:
            fixed = [i for i in range(n) if assignment[i] != 0]
            rhs = -g[free] - H[np.ix_(free, fixed)] @ u[fixed]
            u[free] = np.linalg.solve(H[np.ix_(free, free)], rhs)
            tol = 1e-12 * (1.0 + np.abs(u[free]).max())
            if np.any(u[free] < lower[free] - tol) or np.any(
                u[free] > upper[free] + tol
            ):
                continue
        gradient = H @ u + g  # = -multiplier; >= 0 at a lower, <= 0 at an upper bound
        scale = 1e-9 * (1.0 + np.abs(gradient).max())
        ok = all(
            (assignment[i] >= 0 or gradient[i] >= -scale)
            and (assignment[i] <= 0 or gradient[i] <= scale)
            for i in range(n)
        )
        if ok:
            return u
    raise RuntimeError("no active set satisfies the KKT conditions")


def _solve_box_qp_bvls(H, g, lower, upper) -> np.ndarray:
    """The same QP as bounded least squares ``||L'u + L^-1 g||^2``, ``H = L L'``."""
    from scipy.optimize import lsq_linear

    chol = np.linalg.cholesky(H)
    target = -np.linalg.solve(chol, g)
    result = lsq_linear(chol.T, target, bounds=(lower, upper), method="bvls", tol=1e-14)
    return result.x


def mpc_command(theta, s: float, v: float, v_lead: float, dt: float, horizon: int):
    """First input of the exact MPC solution (SPEC section 3)."""
    tau, _R, _alpha, l_gap, amin, amax = theta
    z0 = (s - v * tau - l_gap, v_lead - v)
    H, g = mpc_qp(theta, z0, dt, horizon)
    lower, upper = np.full(horizon, amin), np.full(horizon, amax)
    return float(solve_box_qp_exact(H, g, lower, upper)[0])
