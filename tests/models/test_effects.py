"""Effects (torchcf.models.effects) against an independent per-particle reference.

The reference below is a plain Python loop over time written from SPEC section 2
and the effects' documented equations; the base models (IDM, LLCTG, LLCS) are
written out by hand, so nothing of torchcf's model code enters it.
"""

from __future__ import annotations

import json
import math
import shutil
import warnings

import numpy as np
import pytest
import torch

from tests.conftest import prior_draws
from torchcf import Execution, PairSet, simulate
from torchcf.config import ConfigError, load_config, validate_config
from torchcf.models import (
    MODELS,
    AugmentedModel,
    Perception,
    UnknownModelError,
    get_model,
)
from torchcf.models.effects import parse_effect

DT = 0.1
GRAVITY = 9.81
LEADER_LENGTH = 5.0
WEIGHTS = (0.5, 0.3, 0.2)
#: Parameters of each effect (by hand, in the documented order); grade: one per knot.
EFFECT_PARAMS = {
    "sync": 1,
    "offset": 1,
    "delay": 1,
    "timegap": 1,
    "asymmetry": 2,
    "saturation": 2,
    "resistance": 1,
    "anticipation": 1,
    "action": 2,
    "lag": 1,
}
CANONICAL = (
    "sync",
    "offset",
    "delay",
    "timegap",
    "anticipation",
    "asymmetry",
    "saturation",
    "resistance",
    "action",
    "lag",
    "grade",
    "bend",
)
#: Effects whose parameters are the values of a road profile, one per knot.
PROFILES = ("grade", "bend")


# ------------------------------------------------------------------- test data
def make_pairs() -> PairSet:
    """Three pairs: leaders braking then accelerating, on absolute road positions.

    Pair 0 starts at 300 m (crosses the 400 m knot of a 4-knot profile on
    [0, 600]), pair 1 at -40 m (before the profile, crosses its start), pair 2 at
    570 m (crosses its end); pair 2 is valid on its first 100 steps only. T = 120
    is not a multiple of the rollout's block, so padding is exercised too.
    """
    n_steps = 120
    t = np.arange(n_steps) * DT
    x_f0 = np.array([300.0, -40.0, 570.0])
    s_init = np.array([22.0, 30.0, 18.0])
    v_init = np.array([14.0, 11.0, 16.0])
    scale = np.array([1.0, 0.7, 1.3])
    a_lead = np.where((t >= 2.0) & (t < 4.5), -2.5, 0.0)
    a_lead = a_lead + np.where((t >= 6.0) & (t < 9.0), 1.8, 0.0)
    a_lead = a_lead[:, None] * scale[None, :]
    v_lead = v_init[None, :] + np.concatenate(
        (np.zeros((1, 3)), np.cumsum(a_lead[:-1] * DT, axis=0))
    )
    x_lead = (x_f0 + s_init)[None, :] + np.concatenate(
        (np.zeros((1, 3)), np.cumsum(0.5 * (v_lead[1:] + v_lead[:-1]) * DT, axis=0))
    )
    spacing = s_init[None, :] + 3.0 * np.sin(0.4 * t)[:, None] * scale[None, :]
    x_follow = x_lead - spacing
    v_follow = np.gradient(x_follow, DT, axis=0)
    a_follow = np.gradient(v_follow, DT, axis=0)
    mask = np.ones((n_steps, 3), dtype=bool)
    mask[100:, 2] = False
    return PairSet.from_arrays(
        (x_lead, v_lead, a_lead, x_follow, v_follow, a_follow),
        dt=DT,
        mask=mask,
        leader_length=LEADER_LENGTH,
        name="effects",
    )


@pytest.fixture(scope="module")
def road() -> PairSet:
    return make_pairs()


# ------------------------------------------------------------------- reference
def base_command(base: str, p: list[float], s: float, v: float, vl: float) -> float:
    """SPEC section 3, by hand."""
    dv = vl - v
    if base == "idm":
        a, b, v0, T, s0, delta = p
        s_star = s0 + max(0.0, v * T - v * dv / (2.0 * math.sqrt(a * b)))
        return a * (1.0 - (v / v0) ** delta - (s_star / max(s, 0.1)) ** 2)
    if base == "llctg":
        tau, ks, kv, ll = p
        return ks * (s - v * tau - ll) + kv * dv
    if base == "llcs":
        s0, ks, kv = p
        return ks * (s - s0) + kv * dv
    raise AssertionError(base)


def split_row(base: str, effects: dict, row: list[float]) -> tuple[list, dict]:
    """Base parameters and each effect's, in canonical order."""
    n_base = {"idm": 6, "llctg": 4, "llcs": 3}[base]
    out, at = {}, n_base
    for name in CANONICAL:
        if name not in effects:
            continue
        count = effects[name]["knots"] if name in PROFILES else EFFECT_PARAMS[name]
        out[name] = row[at : at + count]
        at += count
    assert at == len(row)
    return row[:n_base], out


def road_profile(options: dict, values: list[float], x: float) -> float:
    """A profile's value at road position x (constant beyond its ends; on a
    closed track, ``period`` > 0, x is taken round the lap and the last knot
    joins the first)."""
    if options["knots"] == 1:
        return values[0]
    period = options.get("period", 0.0)
    if period:
        start = options["start"]
        where = start + period * np.arange(options["knots"] + 1) / options["knots"]
        return float(
            np.interp(start + (x - start) % period, where, [*values, values[0]])
        )
    where = np.linspace(options["start"], options["end"], options["knots"])
    return float(np.interp(x, where, values))


def reference_rollout(
    base: str, effects: dict, row: list[float], pairs: PairSet, n: int
) -> dict:
    """One particle on pair n: SPEC section 2 with the effects; absolute positions.

    ``effects`` maps an effect name to its options (grade: start, end, knots).
    """
    p, q = split_row(base, effects, [float(v) for v in row])
    xl, vl, xo, vo, ao = (
        s[:, n].double().numpy()
        for s in (
            pairs.x_lead,
            pairs.v_lead,
            pairs.x_follow,
            pairs.v_follow,
            pairs.a_follow,
        )
    )
    mask = pairs.mask[:, n].numpy()
    n_steps = len(xl)
    x, v, a = float(xo[0]), float(vo[0]), float(ao[0])
    hist_s, hist_vl = [], []  # perceived (after offset) values at 0 .. t
    hist_xl, hist_vls = [], []  # the leader's recorded position and speed (sync)
    held = None  # action points: (command, dv, spacing) at the last one
    xs, vs, accs = [], [], []
    sq = [0.0, 0.0, 0.0]
    valid = True
    for t in range(n_steps):
        s_true = float(xl[t]) - x
        s_p, vl_p = s_true, float(vl[t])
        if "sync" in q:  # the leader's record t_sync ago, own position now
            hist_xl.append(float(xl[t]))
            hist_vls.append(float(vl[t]))
            steps = q["sync"][0] / DT
            k = math.floor(steps)
            f = steps - k

            def past_sync(h, j, t=t):
                return h[max(t - j, 0)]

            xl_p = (1 - f) * past_sync(hist_xl, k) + f * past_sync(hist_xl, k + 1)
            s_p = xl_p - x
            vl_p = (1 - f) * past_sync(hist_vls, k) + f * past_sync(hist_vls, k + 1)
        if "offset" in q:
            s_p = s_p + q["offset"][0]
        if "delay" in q:
            hist_s.append(s_p)
            hist_vl.append(vl_p)
            steps = q["delay"][0] / DT
            k = math.floor(steps)
            f = steps - k

            def past(h, j, t=t):
                return h[max(t - j, 0)]  # before the first step: a steady past

            s_p = (1 - f) * past(hist_s, k) + f * past(hist_s, k + 1)
            vl_p = (1 - f) * past(hist_vl, k) + f * past(hist_vl, k + 1)
        if "timegap" in q:  # a time gap growing with the own (measured) speed
            s_p = s_p - q["timegap"][0] * v * v
        v_p = v
        if "anticipation" in q:  # constant-speed extrapolation, t_ant ahead
            t_ant = q["anticipation"][0]
            s_p, v_p = s_p + t_ant * (vl_p - v), max(v + t_ant * a, 0.0)
        u = base_command(base, p, s_p, v_p, vl_p)
        if "asymmetry" in q:
            g_close, g_open = q["asymmetry"]
            u = u * (g_close if float(vl[t]) < v else g_open)
        if "saturation" in q:
            low, high = q["saturation"]
            u = min(max(u, low), high)
        if "resistance" in q:
            u = u - q["resistance"][0] * v * v
        if "action" in q:  # hold the command until the situation has changed
            ap_dv, ap_ds = q["action"]
            dv = float(vl[t]) - v
            if (
                held is None
                or abs(dv - held[1]) > ap_dv
                or abs(s_true - held[2]) > ap_ds * held[2]
            ):
                held = (u, dv, s_true)
            u = held[0]
        if "grade" in q:
            u = u - GRAVITY * road_profile(effects["grade"], q["grade"], x)
        if "bend" in q:
            limit = road_profile(effects["bend"], q["bend"], x)
            u = min(u, (limit - v) / 1.0)
        recorded = a if "lag" in q else u
        xs.append(x)
        vs.append(v)
        accs.append(recorded)
        if mask[t]:
            sq[0] += (x - float(xo[t])) ** 2
            sq[1] += (v - float(vo[t])) ** 2
            sq[2] += (recorded - float(ao[t])) ** 2
            finite = all(math.isfinite(z) for z in (x, v, recorded))
            if not finite or s_true <= 0:
                valid = False
        if "lag" in q:
            lag = q["lag"][0]
            e = math.exp(-DT / lag)
            x_new = x + v * DT + u * DT**2 / 2 + (a - u) * lag * (DT - lag * (1 - e))
            v_new = v + u * DT + (a - u) * lag * (1 - e)
            a = u + (a - u) * e
        else:
            x_new = x + v * DT + u * DT**2 / 2
            v_new = v + u * DT
            a = u
        x, v = max(x_new, x), max(v_new, 0.0)
    count = max(int(mask.sum()), 1)
    errors = [math.sqrt(total / count) for total in sq]
    score = sum(w * e for w, e in zip(WEIGHTS, errors, strict=True))
    return {
        "x": np.array(xs),
        "v": np.array(vs),
        "a": np.array(accs),
        "e_p": errors[0],
        "e_v": errors[1],
        "e_a": errors[2],
        "score": score if valid else math.inf,
        "valid": valid,
    }


IDM = [1.2, 2.0, 30.0, 1.2, 2.0, 4.0]
IDM_B = [0.8, 1.5, 25.0, 1.6, 3.0, 4.0]
LLCTG = [1.0, 0.3, 0.6, 5.0]
LLCTG_B = [1.4, 0.15, 0.9, 7.0]
LLCS = [20.0, 0.15, 0.8]
GRADE4 = {"start": 0.0, "end": 600.0, "knots": 4}

# (name, base, {effect: options}, theta rows)
CASES = [
    ("idm+sync", "idm", {"sync": {}}, [IDM + [0.5], IDM_B + [1.23], IDM + [0.0]]),
    (
        "llctg+sync+offset+delay",
        "llctg",
        {"sync": {}, "offset": {}, "delay": {}},
        [LLCTG + [0.7, -1.5, 0.4], LLCTG_B + [0.25, 2.0, 1.1]],
    ),
    ("idm+anticipation", "idm", {"anticipation": {}}, [IDM + [0.9], IDM_B + [1.8]]),
    (
        "llctg+delay+anticipation",
        "llctg",
        {"delay": {}, "anticipation": {}},
        [LLCTG + [1.2, 1.0], LLCTG_B + [2.6, 0.3]],
    ),
    (
        "llctg+action",
        "llctg",
        {"action": {}},
        [LLCTG + [0.4, 0.05], LLCTG_B + [0.9, 0.15], LLCTG + [0.0, 0.0]],
    ),
    (
        "idm+action+lag",
        "idm",
        {"action": {}, "lag": {}},
        [IDM + [0.3, 0.1, 0.6], IDM_B + [1.0, 0.02, 0.2]],
    ),
    (
        "idm+bend(start=0,end=600,knots=4)",
        "idm",
        {"bend": GRADE4},
        [IDM + [30.0, 12.0, 8.0, 25.0], IDM_B + [6.0, 20.0, 35.0, 9.0]],
    ),
    (
        "llcs+delay+anticipation+action+lag+grade(end=600,knots=4)"
        "+bend(start=0,end=600,knots=4)",
        "llcs",
        {
            "delay": {},
            "anticipation": {},
            "action": {},
            "lag": {},
            "grade": GRADE4,
            "bend": GRADE4,
        },
        [
            LLCS
            + [0.7, 0.5, 0.2, 0.05, 0.4]
            + [0.04, -0.03, 0.06, -0.05]
            + [20.0, 9.0, 14.0, 30.0],
        ],
    ),
    ("llctg+offset", "llctg", {"offset": {}}, [LLCTG + [-3.0], LLCTG_B + [4.5]]),
    ("idm+offset", "idm", {"offset": {}}, [IDM + [2.5], IDM + [0.0]]),
    (
        "llcs+delay",
        "llcs",
        {"delay": {}},
        [LLCS + [0.35], LLCS + [0.0], LLCS + [2.0]],  # fractional, zero, max
    ),
    ("idm+delay", "idm", {"delay": {}}, [IDM + [0.35], IDM_B + [1.27], IDM + [0.0]]),
    (
        "llctg+delay(max_delay=0.55)",
        "llctg",
        {"delay": {}},
        [LLCTG + [0.55], LLCTG_B + [0.3], LLCTG + [0.05]],
    ),
    (
        "idm+asymmetry",
        "idm",
        {"asymmetry": {}},
        [IDM + [1.5, 0.7], IDM_B + [0.6, 1.8], IDM + [1.0, 1.0]],
    ),
    (
        "llctg+saturation",
        "llctg",
        {"saturation": {}},
        [LLCTG + [-1.5, 0.8], LLCTG_B + [-3.0, 2.0], LLCTG + [-8.0, 4.0]],
    ),
    (
        "idm+resistance",
        "idm",
        {"resistance": {}},
        [IDM + [2e-3], IDM_B + [1e-3], IDM + [0.0]],
    ),
    (
        "llctg+grade(knots=1)",
        "llctg",
        {"grade": {"start": 0.0, "end": 2000.0, "knots": 1}},
        [LLCTG + [0.05], LLCTG_B + [-0.04]],
    ),
    (
        "llctg+grade(start=0,end=600,knots=4)",
        "llctg",
        {"grade": GRADE4},
        [LLCTG + [0.04, -0.03, 0.06, -0.05], LLCTG_B + [-0.02, 0.05, 0.0, 0.07]],
    ),
    (
        "idm+grade(start=100,end=500,knots=3)",
        "idm",
        {"grade": {"start": 100.0, "end": 500.0, "knots": 3}},
        [IDM + [0.03, -0.06, 0.05], IDM_B + [-0.04, 0.02, 0.08]],
    ),
    (
        # A closed track of 250 m: the pairs (from -40 m to beyond 600 m) go
        # round it several times, through the last knot's join to the first.
        "idm+grade(start=-30,knots=4,period=250)",
        "idm",
        {"grade": {"start": -30.0, "knots": 4, "period": 250.0}},
        [IDM + [0.03, -0.06, 0.05, 0.02], IDM_B + [-0.04, 0.02, 0.08, -0.07]],
    ),
    (
        "idm+timegap",
        "idm",
        {"timegap": {}},
        [IDM + [0.02], IDM_B + [-0.01], IDM + [0.0]],
    ),
    (
        # after a delay (the delayed spacing) and before anticipation (the
        # measured own speed)
        "llctg+delay+timegap+anticipation",
        "llctg",
        {"delay": {}, "timegap": {}, "anticipation": {}},
        [LLCTG + [0.4, 0.015, 0.8], LLCTG_B + [1.1, -0.02, 0.3]],
    ),
    ("idm+lag", "idm", {"lag": {}}, [IDM + [0.3], IDM_B + [0.8], IDM + [0.05]]),
    ("llcs+lag", "llcs", {"lag": {}}, [LLCS + [0.5], LLCS + [1.5]]),
    (
        "idm+offset+delay+asymmetry+saturation+resistance+grade(end=600,knots=4)+lag",
        "idm",
        {
            "offset": {},
            "delay": {},
            "asymmetry": {},
            "saturation": {},
            "resistance": {},
            "grade": GRADE4,
            "lag": {},
        },
        [
            IDM + [1.5, 0.45, 1.3, 0.8, -2.0, 1.0, 1e-3, 0.4, 0.04, -0.03, 0.06, -0.05],
            IDM_B + [-2.0, 1.0, 0.7, 1.6, -4.0, 3.0, 0.0, 0.15, -0.02, 0.05, 0.0, 0.07],
        ],
    ),
    (
        # The name in a non-canonical order: the parameter order is canonical.
        "llctg+lag+grade(knots=1)+delay+offset",
        "llctg",
        {
            "offset": {},
            "delay": {},
            "grade": {"start": 0.0, "end": 2000.0, "knots": 1},
            "lag": {},
        },
        [LLCTG + [1.0, 0.25, 0.6, 0.03], LLCTG_B + [-1.0, 0.8, 0.2, -0.05]],
    ),
]


def assert_matches_reference(out, base, effects, theta, pairs):
    n_valid = 0
    for j in range(theta.shape[0]):
        for n in range(pairs.n_pairs):
            ref = reference_rollout(base, effects, theta[j].tolist(), pairs, n)
            n_valid += ref["valid"]
            assert bool(out.valid[j, n]) == ref["valid"], (j, n)
            if not ref["valid"]:  # a crash (a 2 s delay on a braking leader)
                assert math.isinf(float(out.score[j, n]))
            for key in ("score", "e_p", "e_v", "e_a"):
                if not ref["valid"] and key != "score":
                    continue
                assert float(getattr(out, key)[j, n]) == pytest.approx(
                    ref[key], rel=1e-9, abs=1e-9
                ), (key, j, n)
            for key in ("x", "v", "a"):
                np.testing.assert_allclose(
                    getattr(out, key)[:, j, n].numpy(),
                    ref[key],
                    # rtol: past pair 2's end the padded leader stands still
                    # and the follower brakes hard into it (masked steps).
                    rtol=1e-10,
                    atol=1e-9,
                    err_msg=f"{key} particle {j} pair {n}",
                )
    assert n_valid >= 0.6 * theta.shape[0] * pairs.n_pairs, "mostly valid rollouts"


# --------------------------------------------------- 1. independent reference
@pytest.mark.parametrize(
    ("name", "base", "effects", "rows"), CASES, ids=[c[0] for c in CASES]
)
def test_matches_independent_reference(name, base, effects, rows, road):
    theta = torch.tensor(rows, dtype=torch.float64)
    out = simulate(get_model(name), theta, road, dtype=torch.float64, return_traj=True)
    assert_matches_reference(out, base, effects, theta, road)


def test_delay_history_is_a_steady_past(road):
    """Within t_delay of the start the follower perceives the first perception."""
    s0, ks, kv = LLCS
    theta = torch.tensor([LLCS + [0.8]], dtype=torch.float64)  # 8 steps
    out = simulate(
        get_model("llcs+delay"), theta, road, dtype=torch.float64, return_traj=True
    )
    for n in range(road.n_pairs):
        s_first = float(road.x_lead[0, n] - road.x_follow[0, n])
        vl_first = float(road.v_lead[0, n])
        for t in range(9):  # t = 8 perceives step 0 exactly too
            v = float(out.v[t, 0, n])
            expected = ks * (s_first - s0) + kv * (vl_first - v)
            assert float(out.a[t, 0, n]) == pytest.approx(expected, abs=1e-12)
        # ... and afterwards it perceives the step 8 steps before.
        t = 20
        s_past = float(road.x_lead[t - 8, n] - out.x[t - 8, 0, n])
        vl_past = float(road.v_lead[t - 8, n])
        expected = ks * (s_past - s0) + kv * (vl_past - float(out.v[t, 0, n]))
        assert float(out.a[t, 0, n]) == pytest.approx(expected, abs=1e-9)


def test_augmented_command_sees_a_steady_past():
    model = get_model("llcs+delay")
    theta = torch.tensor([[15.0, 0.25, 0.5, 0.7]], dtype=torch.float64)
    params = model.prepare(model.unpack(theta), DT, (1,))
    t64 = lambda value: torch.tensor([value], dtype=torch.float64)  # noqa: E731
    obs = Perception(t64(30.0), t64(12.0), t64(10.0), t64(0.0), LEADER_LENGTH)
    u = model.command(params, obs)
    assert float(u[0]) == pytest.approx(0.25 * (30.0 - 15.0) + 0.5 * (10.0 - 12.0))


def test_delay_outside_its_history_is_refused(road):
    theta = torch.tensor([LLCS + [0.6]], dtype=torch.float64)
    with pytest.raises(ValueError, match="t_delay"):
        simulate(
            get_model("llcs+delay(max_delay=0.55)"), theta, road, dtype=torch.float64
        )
    with pytest.raises(ValueError, match="t_delay"):
        simulate(get_model("llcs+delay"), torch.tensor([LLCS + [-0.1]]), road)


# --------------------------------------------- 2. neutral parameters = the base
# In canonical order (the all-effects case concatenates them).
NEUTRAL = {
    "offset": [0.0],
    "delay": [0.0],
    "timegap": [0.0],
    "anticipation": [0.0],
    "asymmetry": [1.0, 1.0],
    "saturation": [-1e9, 1e9],
    "resistance": [0.0],
    "action": [0.0, 0.0],
    "grade(start=0,end=600,knots=4)": [0.0, 0.0, 0.0, 0.0],
    "bend(start=0,end=600,knots=4)": [1e9, 1e9, 1e9, 1e9],
}
NEUTRAL_BASES = ["idm", "llctg", "fvdm", "hl", "mpc"]


def _neutral_cases():
    tokens = list(NEUTRAL)
    for base in NEUTRAL_BASES:
        for token in tokens:
            yield base, [token]
        yield base, tokens


@pytest.mark.parametrize(
    ("base", "tokens"),
    list(_neutral_cases()),
    ids=[f"{b}+{'+'.join(t)}" for b, t in _neutral_cases()],
)
def test_neutral_parameters_reproduce_the_base(base, tokens, road):
    if base == "mpc" and len(tokens) == 1 and tokens[0] != "delay":
        pytest.skip("MPC: the delay and all-effects cases suffice (slow solver)")
    theta = prior_draws(MODELS[base], 4, seed=13)
    neutral = [v for token in tokens for v in NEUTRAL[token]]
    extra = torch.tensor(neutral, dtype=torch.float64).expand(4, -1)
    name = "+".join([base, *tokens])
    plain = simulate(
        get_model(base), theta, road, dtype=torch.float64, return_traj=True
    )
    augmented = simulate(
        get_model(name),
        torch.cat((theta, extra), 1),
        road,
        dtype=torch.float64,
        return_traj=True,
    )
    tol = 1e-6 if base == "mpc" else 0.0
    for key in ("score", "e_p", "e_v", "e_a", "valid", "x", "v", "a"):
        torch.testing.assert_close(
            getattr(augmented, key),
            getattr(plain, key),
            rtol=tol,
            atol=tol,
            equal_nan=True,
            msg=lambda m, key=key: f"{name} {key}: {m}",
        )


# ------------------------------------------- 3. layouts, batching, compilation
ALL = "idm+offset+delay+asymmetry+saturation+resistance+grade(end=600,knots=4)+lag"


def all_effects_theta(n: int, seed: int = 0) -> torch.Tensor:
    """Draws from the prior of ALL, t_delay inside [0, max_delay]."""
    return prior_draws(get_model(ALL), n, seed=seed)


@pytest.mark.parametrize("name", [ALL, "llctg+delay+grade(start=-50,end=700)"])
def test_batched_equals_looped(name, road):
    theta = prior_draws(get_model(name), 5, seed=3)
    batched = simulate(
        get_model(name), theta, road, dtype=torch.float64, return_traj=True
    )
    for j in range(5):
        for n in range(road.n_pairs):
            single = simulate(
                get_model(name),
                theta[j : j + 1],
                road.subset([n]),
                dtype=torch.float64,
                return_traj=True,
            )
            for key in ("score", "valid"):
                assert torch.equal(
                    getattr(single, key)[0, 0], getattr(batched, key)[j, n]
                )
            for key in ("x", "v", "a"):
                torch.testing.assert_close(
                    getattr(single, key)[:, 0, 0],
                    getattr(batched, key)[:, j, n],
                    rtol=0,
                    atol=1e-9,
                    equal_nan=True,
                )


@pytest.mark.parametrize("name", [ALL, "llcs+delay(max_delay=0.55)+grade(knots=1)"])
def test_paired_equals_full_layout_diagonal(name, road):
    n = 12
    theta = prior_draws(get_model(name), n, seed=4)
    if "max_delay=0.55" in name:  # the default t_delay prior reaches 1.5 s
        theta[:, 3] = theta[:, 3] * 0.55 / 1.5
    index = torch.arange(n) % road.n_pairs
    full = simulate(get_model(name), theta, road, dtype=torch.float64, return_traj=True)
    paired = simulate(
        get_model(name), theta, road, index, dtype=torch.float64, return_traj=True
    )
    rows = torch.arange(n)
    for key in ("score", "e_p", "e_v", "e_a", "valid"):
        torch.testing.assert_close(
            getattr(paired, key), getattr(full, key)[rows, index], rtol=0, atol=1e-9
        )
    for key in ("x", "v", "a"):
        torch.testing.assert_close(
            getattr(paired, key),
            getattr(full, key)[:, rows, index],
            rtol=0,
            atol=1e-9,
            equal_nan=True,
        )


@pytest.mark.parametrize("paired", [False, True])
def test_chunk_size_invariance(paired, road):
    theta = all_effects_theta(7, seed=5)
    index = torch.arange(7) % road.n_pairs if paired else None
    whole = simulate(
        get_model(ALL), theta, road, index, dtype=torch.float64, return_traj=True
    )
    for chunk in (1, 3, 4):
        chunked = simulate(
            get_model(ALL),
            theta,
            road,
            index,
            dtype=torch.float64,
            return_traj=True,
            execution=Execution(chunk_size=chunk),
        )
        for key in ("score", "valid", "x", "v", "a"):
            torch.testing.assert_close(
                getattr(chunked, key),
                getattr(whole, key),
                rtol=0,
                atol=1e-12,
                equal_nan=True,
            )


@pytest.mark.slow  # about a minute of compilation on a 2-core CPU
@pytest.mark.compile
@pytest.mark.skipif(shutil.which("g++") is None, reason="no C++ compiler")
def test_compiled_equals_eager(road):
    """One compiled graph (seconds of compilation): a perception effect with
    memory, a command effect reading the position and the lag."""
    name = "llcs+delay+grade(end=600,knots=4)+lag"
    theta = prior_draws(get_model(name), 6, seed=6)
    index = torch.arange(6) % road.n_pairs
    kwargs = {"dtype": torch.float64, "return_traj": True}
    eager = simulate(
        get_model(name),
        theta,
        road,
        index,
        execution=Execution(compile=False),
        **kwargs,
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compiled = simulate(
            get_model(name),
            theta,
            road,
            index,
            execution=Execution(compile=True),
            **kwargs,
        )
    fallbacks = [str(w.message) for w in caught if "compile failed" in str(w.message)]
    assert not fallbacks, fallbacks  # it really ran compiled
    for key in ("score", "e_p", "e_v", "e_a", "valid", "x", "v", "a"):
        torch.testing.assert_close(
            getattr(compiled, key),
            getattr(eager, key),
            rtol=1e-9,
            atol=1e-9,
            equal_nan=True,
        )


# -------------------------------------------------------------- 4. names, config
def test_canonical_order_is_one_object():
    model = get_model("idm+lag+delay")
    assert model is get_model("idm+delay+lag")
    assert model is get_model(" IDM + Lag+DELAY ")
    assert isinstance(model, AugmentedModel)
    assert model.name == "idm+delay+lag"
    assert model.param_names == MODELS["idm"].param_names + ("t_delay", "t_lag")
    assert model.acceleration_is_state
    assert get_model(model) is model
    assert get_model(model.name) is model


@pytest.mark.parametrize(
    ("given", "canonical"),
    [
        ("llctg+grade(start=0,end=600,knots=4)", "llctg+grade(end=600,knots=4)"),
        ("llctg+grade(knots=4,end=600)", "llctg+grade(end=600,knots=4)"),
        ("idm+delay(max_delay=2)", "idm+delay(max_delay=2)"),
        ("idm+delay(max_delay=3)", "idm+delay"),
        ("idm+grade", "idm+grade"),
        (
            "idm+grade(start=-50.5,end=700,knots=2)",
            "idm+grade(start=-50.5,end=700,knots=2)",
        ),
    ],
)
def test_options_round_trip_in_the_name(given, canonical):
    model = get_model(given)
    assert model.name == canonical
    assert get_model(canonical) is model


def test_grade_options_set_the_parameters():
    model = get_model("llctg+grade(start=0,end=600,knots=4)")
    grade = model.effects[0]
    assert grade.knot_positions == [0.0, 200.0, 400.0, 600.0]
    assert model.param_names[-4:] == ("grade_0", "grade_1", "grade_2", "grade_3")
    assert get_model("llctg+grade").n_params == 4 + 3  # default: 3 knots
    assert model.uses_position and not MODELS["llctg"].uses_position


@pytest.mark.parametrize(
    "name",
    [
        "llctg+grade(start=12345.67,end=23456.78,knots=2)",
        "idm+delay(max_delay=1.2345678)",
    ],
)
def test_long_options_round_trip_exactly(name):
    """An option with more than 6 significant digits keeps its value in the name.

    Parsed afresh (the registry caches the first instance under its name, which
    would hide a name that reads back as another model in a new process).
    """
    model = get_model(name)
    fresh = AugmentedModel(model.base, [parse_effect(e.token) for e in model.effects])
    assert fresh.name == model.name
    assert vars(fresh.effects[0]) == vars(model.effects[0])


@pytest.mark.parametrize(
    ("name", "needle"),
    [
        ("idm+warp", "unknown effect"),
        ("idm+delay+delay", "twice"),
        ("idm+delay(max_delay=1)+delay", "twice"),
        ("hl+lag", "actuation lag"),
        ("idm+delay(max_delay=abc)", "key=number"),
        ("idm+delay(max_delay)", "key=number"),
        ("idm+delay(speed=1)", "speed"),
        ("idm+delay(max_delay=-1)", "max_delay"),
        ("idm+grade(knots=0)", "knots"),
        ("idm+grade(knots=2.5)", "knots"),
        ("idm+grade(start=5,end=5)", "end > start"),
        ("warp+delay", "unknown model"),
    ],
)
def test_bad_names_are_refused(name, needle):
    with pytest.raises(UnknownModelError) as info:
        get_model(name)
    assert needle in str(info.value)


BASE_CONFIG = {"data": {"name": "car-model-2"}}


def test_config_accepts_an_augmented_model(tmp_path):
    raw = {
        **BASE_CONFIG,
        "models": [
            {"name": "idm+delay", "prior": {"t_delay": [0.2, 1.0]}},
            {"name": "IDM+lag+delay"},
        ],
    }
    path = tmp_path / "run.json"
    path.write_text(json.dumps(raw), encoding="utf-8")
    cfg = load_config(path)
    assert [m.name for m in cfg.models] == ["idm+delay", "idm+delay+lag"]
    box = cfg.models[0].bounds()
    assert box[-1].tolist() == [0.2, 1.0]
    assert box[:-1].tolist() == MODELS["idm"].prior_bounds().tolist()


@pytest.mark.parametrize(
    ("model", "needle"),
    [
        ({"name": "idm+delay", "prior": {"t_delay": [0.2, 3.5]}}, "max_delay"),
        ({"name": "idm+lag", "prior": {"t_lag": [0.0, 0.5]}}, "t_lag"),
        ({"name": "idm+lag", "prior": {"t_lag": [-0.1, 0.5]}}, "t_lag"),
        ({"name": "hl+lag"}, "actuation lag"),
        ({"name": "idm+delay", "prior": {"t_lag": [0.1, 0.5]}}, "t_lag"),
    ],
)
def test_config_rejects_what_the_effects_cannot_run(model, needle):
    with pytest.raises(ConfigError) as info:
        validate_config({**BASE_CONFIG, "models": [model]})
    assert needle in str(info.value)


def test_config_accepts_a_longer_delay_history():
    model = {"name": "idm+delay(max_delay=4)", "prior": {"t_delay": [0.2, 3.5]}}
    cfg = validate_config({**BASE_CONFIG, "models": [model]})
    assert cfg.models[0].name == "idm+delay(max_delay=4)"


# ------------------------------------------ 5. each effect changes the trajectory
ACTIVE = [
    ("llctg+offset", [-4.0], [0.0]),
    ("llctg+delay", [0.5], [0.0]),
    ("llctg+timegap", [0.02], [0.0]),
    ("llctg+asymmetry", [1.6, 1.0], [1.0, 1.0]),  # g_close only: leaders brake
    ("llctg+saturation", [-1.0, 0.5], [-1e9, 1e9]),
    ("llctg+resistance", [2e-3], [0.0]),
    ("llctg+grade(knots=1)", [0.05], [0.0]),
    ("llctg+grade(start=0,end=600,knots=4)", [0.0, 0.0, 0.06, 0.0], [0.0] * 4),
    ("llctg+anticipation", [1.5], [0.0]),
    ("llctg+action", [0.8, 0.15], [0.0, 0.0]),
    ("llctg+bend(start=0,end=600,knots=4)", [8.0, 8.0, 8.0, 8.0], [1e9] * 4),
]


@pytest.mark.parametrize(
    ("name", "active", "neutral"), ACTIVE, ids=[a[0] for a in ACTIVE]
)
def test_every_effect_changes_the_trajectory(name, active, neutral, road):
    rows = [LLCTG + active, LLCTG + neutral]
    out = simulate(
        get_model(name), torch.tensor(rows), road, dtype=torch.float64, return_traj=True
    )
    gap = (out.x[:, 0] - out.x[:, 1]).abs().amax(0)  # (N,)
    assert bool((gap > 0.05).any()), gap
    plain = simulate(
        get_model("llctg"), torch.tensor([LLCTG]), road, dtype=torch.float64
    )
    torch.testing.assert_close(out.score[1], plain.score[0], rtol=0, atol=0)


def test_lag_changes_the_trajectory(road):
    lagged = simulate(
        get_model("llctg+lag"), torch.tensor([LLCTG + [0.8]]), road, return_traj=True
    )
    plain = simulate(get_model("llctg"), torch.tensor([LLCTG]), road, return_traj=True)
    gap = (lagged.x[:, 0] - plain.x[:, 0]).abs().amax(0)
    assert bool((gap > 0.05).all()), gap
    # the recorded acceleration is the lagged state: it starts at the observed one
    torch.testing.assert_close(lagged.a[0, 0], road.a_follow[0].float())


def test_grade_reads_the_absolute_position(road):
    """A grade only inside (200, 500) m acts on pair 0 (from 300 m), not on pair 1
    (-40 m .. below 200 m) nor pair 2 (from 570 m): positions are absolute."""
    name = "llctg+grade(start=0,end=600,knots=7)"
    rows = [LLCTG + [0.0, 0.0, 0.0, 0.05, 0.05, 0.0, 0.0], LLCTG + [0.0] * 7]
    out = simulate(
        get_model(name), torch.tensor(rows), road, dtype=torch.float64, return_traj=True
    )
    gap = (out.x[:, 0] - out.x[:, 1]).abs().amax(0)
    assert float(gap[0]) > 0.05
    assert float(out.x[:, :, 1].max()) < 200.0  # pair 1 never reaches the grade
    assert float(out.x[:, :, 2].min()) > 500.0  # pair 2 is past it
    assert float(gap[1]) == 0.0 and float(gap[2]) == 0.0


def test_a_road_profile_at_a_nan_position_is_nan_not_an_error():
    """An exploding rollout reaches a NaN position: the profile must stay NaN
    (the rollout is then invalid), not index out of bounds."""
    for token in ("grade(start=0,end=600,knots=4)", "bend(start=0,end=600,knots=4)"):
        effect = parse_effect(token)
        values = effect.prepare(
            tuple(torch.tensor([0.01 * (k + 1)]) for k in range(4)), DT
        )
        position = torch.tensor([float("nan"), 300.0, float("inf"), -float("inf")])
        out = effect.profile(values, position)
        assert torch.isnan(out[0]) and torch.isfinite(out[1:]).all()


@pytest.mark.parametrize("knots", [1, 2, 3, 7])
def test_a_lap_profile_is_periodic_continuous_and_its_basis_is_linear(knots):
    """On a closed track a position and the same position a lap on (or back)
    read one value; the profile is continuous where the last knot joins the
    first; ``basis @ values`` is the profile (the diagnosis regresses on it)."""
    effect = parse_effect(f"grade(start=12.5,period=900,knots={knots})")
    assert vars(parse_effect(effect.token)) == vars(effect)  # the name round-trips
    values = torch.linspace(-0.03, 0.05, knots, dtype=torch.float64)
    q = effect.prepare(tuple(values[:, None]), DT)
    x = torch.linspace(-2000.0, 3000.0, 5001, dtype=torch.float64)
    here = effect.profile(q, x)
    for laps in (-2, 1, 3):
        torch.testing.assert_close(effect.profile(q, x + laps * 900.0), here)
    join = torch.tensor([12.5 + 900.0 - 1e-6, 12.5 + 900.0, 12.5], dtype=x.dtype)
    ends = effect.profile(q, join)
    torch.testing.assert_close(
        ends, torch.full_like(ends, float(values[0])), atol=1e-8, rtol=0
    )
    torch.testing.assert_close(effect.basis(x) @ values, here)
    assert torch.allclose(effect.basis(x).sum(-1), torch.ones_like(here))


def test_a_lap_profile_is_refused_a_period_that_is_no_length():
    for bad in ("-5", "inf"):
        with pytest.raises(ValueError, match="period must be a lap length"):
            parse_effect(f"grade(period={bad},knots=4)")


def test_sync_at_zero_is_the_model_up_to_rounding(road):
    """t_sync = 0 perceives (s + x) - x: the model itself within rounding."""
    theta = torch.tensor([IDM + [0.0]], dtype=torch.float64)
    synced = simulate(
        get_model("idm+sync"), theta, road, dtype=torch.float64, return_traj=True
    )
    plain = simulate(
        get_model("idm"), theta[:, :-1], road, dtype=torch.float64, return_traj=True
    )
    torch.testing.assert_close(synced.x, plain.x, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(synced.score, plain.score, rtol=1e-9, atol=1e-9)


def test_sync_differs_from_a_delay(road):
    """A log offset delays the leader only; a perception delay delays the whole
    spacing (the follower's own position too)."""
    synced = simulate(
        get_model("idm+sync"), torch.tensor([IDM + [0.8]]), road, dtype=torch.float64
    )
    delayed = simulate(
        get_model("idm+delay"), torch.tensor([IDM + [0.8]]), road, dtype=torch.float64
    )
    assert bool((synced.score - delayed.score).abs().max() > 1e-3)


def test_a_name_splits_at_the_plus_signs_outside_parentheses():
    """An option written with an exponent (``end=1e+06``) keeps its '+'; the
    effect kinds drop the options."""
    from torchcf.models import split_name

    name = "idm+grade(end=1e+06,knots=4)+lag"
    assert split_name(name) == ["idm", "grade(end=1e+06,knots=4)", "lag"]
    assert get_model(name).effect_kinds == ("lag", "grade")  # canonical order
    assert get_model("idm").effect_kinds == ()
    assert {"t_lag", "grade_3"} <= set(get_model(name).param_names)  # parsed whole


def test_a_variant_is_built_from_objects_not_names():
    """``augment`` wraps a model by effect objects: the registry's one instance
    of the variant, the same as its name parsed; effects are equal by token."""
    from torchcf.models import UnknownModelError, augment

    idm, delay = get_model("idm"), parse_effect("delay")
    variant = augment(idm, delay)
    assert variant is get_model("idm+delay") and augment(idm) is idm
    assert augment(variant, parse_effect("lag")) is get_model("idm+lag+delay")
    assert variant.pool_model is idm and idm.pool_model is idm
    assert variant.effect_kinds == ("delay",) and idm.effect_kinds == ()
    same = parse_effect("grade(end=600.0)")
    assert same == parse_effect("grade(end=600)") and hash(same) == hash(
        parse_effect("grade(end=600)")
    )
    assert delay != parse_effect("lag") and delay != "delay"
    with pytest.raises(UnknownModelError, match="actuation lag"):
        augment(get_model("hl"), parse_effect("lag"))


def test_a_model_pickles_as_the_registrys_one_instance():
    """A model sent to a worker process (or copied) comes back as the registry's
    instance of its name, so it stays the same dict key there."""
    import copy
    import pickle

    for name in ("idm", "mpc", "idm+delay", "llctg+lag+grade(end=600,knots=4)"):
        model = get_model(name)
        assert pickle.loads(pickle.dumps(model)) is model
        assert copy.deepcopy({model: 1}) == {model: 1}
