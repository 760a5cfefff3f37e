"""Residual signatures: what the residual of the fit windows points to.

Before anything is re-calibrated, the residual of the current model's best
particle per pair, on the fit windows, is searched for the structures that
effects leave (:func:`signatures`). Each signature reduces a pair to one number
(an excess response lag, a spacing bias, a slope), and is tested across pairs by
a two-sided sign-flip test: the pairs are independent, so the p-value is exact,
unlike a pooled test over thousands of autocorrelated samples (which real data
make "significant" for everything). A signature with p < :data:`FOUND` is
*found*; it points to the effects of the library that leave it
(:data:`POINTS_TO`), and those effects are tested first
(:func:`torchcf.diagnose.selection.attribution.test_order`). A signature that no effect
of
the library leaves names the family of model it suggests instead
(:data:`FAMILIES`).

The signatures, per pair (``e_s, e_v, e_a``: closed-loop residuals observed -
simulated of spacing [m], speed, acceleration; ``r``: the one-step acceleration
residual from the observed state, :func:`~torchcf.diagnose.signatures.road.
one_step_residual`):

- ``response lag`` [s]: the lag at which the follower's observed acceleration
  correlates best with its leader's, minus the same lag of the simulated
  follower (pairs whose leader barely accelerates are skipped): > 0 the
  followers answer later than the model (delay, clock offset, actuation lag),
  < 0 earlier (anticipation);
- ``spacing bias`` [m]: the mean of ``e_s`` (a sensor offset the model's own
  gap cannot take up);
- ``road position`` [1]: the share of ``r``'s variance that a profile of road
  position, fitted on the other pairs, explains on this one (grade, bend; only
  where the pairs share a road frame);
- ``closing vs opening`` [m/s^2]: the mean of ``r`` while closing in (leader
  slower) minus while falling back (asymmetry);
- ``drag`` [m/s^2 per (m/s)^2]: the slope of ``r`` on the squared speed
  (resistance);
- ``command strength`` [1]: the slope of ``r`` on the model's acceleration:
  < 0, the follower realises less than commanded (saturation, actuation lag);
- ``gap vs speed`` [s]: the slope of ``e_s`` on the speed: a time gap that
  depends on speed otherwise than the models' (``timegap``, either sign);
- ``drift`` [m/s]: the slope of ``e_s`` on time: parameters that drift within
  a window (no effect of the library).

The covariates of these three (which side, the speed, the model's
acceleration) are those of the *simulated* follower :data:`COVARIATE_LAG_S`
before the residual's step (:func:`simulated_covariates`), not the observed
ones: ``r(t)`` carries the measurement noise of the observed state at t (the
model commands from it), and so would covariates taken from that state. With
the model that made the data and position noise of 5 cm alone, the observed
covariates found all three at p 0.0005 (errors in variables), the simulated
ones none; these still point to an actuation lag, asymmetry and drag, and to
saturation, which the observed ones missed (p 0.95)
(`tests/diagnose/test_attribution.py`). The lag keeps the leader's noise out as
well where it is white or correlated over less than the lag (correlated over
0.5 s, 30 noise-only pairs gave command strength p 0.026: the lag lowers that
false alarm, it does not remove it).

Shapes: N pairs (:mod:`torchcf.typing`); series are per pair, valid steps only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...system.records import Record
from ..significance import two_sided_sign_flip

#: p-value (across pairs) under which a signature is found.
FOUND = 0.05
#: Longest response lag searched [s].
MAX_LAG_S = 4.0
#: Pairs whose leader's acceleration correlates less than this with the
#: follower's at every lag carry no response lag.
MIN_RESPONSE_CORRELATION = 0.3
#: Samples a pair needs on each side (closing / falling back).
MIN_SIDE = 20
#: Permutations of the signatures' sign-flip tests.
PERMUTATIONS = 10_000
#: How long [s] before the one-step residual's step its covariates are taken
#: from the simulated follower (at least one step; module docstring).
COVARIATE_LAG_S = 0.2

#: Which effects leave each signature, by the sign of its mean (``+``, ``-``).
POINTS_TO: dict[str, dict[str, tuple[str, ...]]] = {
    "response lag": {"+": ("delay", "sync", "lag"), "-": ("anticipation",)},
    "spacing bias": {"+": ("offset",), "-": ("offset",)},
    "road position": {"+": ("grade", "bend")},
    "closing vs opening": {"+": ("asymmetry",), "-": ("asymmetry",)},
    "drag": {"-": ("resistance",)},
    "command strength": {"-": ("saturation", "lag")},
    "gap vs speed": {"+": ("timegap",), "-": ("timegap",)},
    "drift": {},
}
#: The model family a signature suggests where no effect of the library
#: explains it; where the two signs tell different stories, one per sign
#: (:func:`family_of`).
FAMILIES: dict[str, str | dict[str, str]] = {
    "response lag": "a response delay beyond the library's priors",
    "spacing bias": "a spacing measured from another reference point",
    "road position": "a road effect at a finer resolution than the knots tried",
    "closing vs opening": "separate models for closing in and falling back "
    "(regime switching)",
    # the residual's slope on v^2: negative, the follower loses speed the model
    # keeps (resistance, which the library has); positive, it gains at speed
    # what the model takes away, which no effect of the library gives
    "drag": {
        "-": "a speed-dependent resistance",
        "+": "acceleration that grows with speed beyond the model's (a free-road "
        "term that brakes too early: its own desired speed or exponent; a "
        "speed-dependent thrust)",
    },
    # the residual's slope on the model's command: negative, the response is
    # weaker (saturation, lag); positive, stronger than any effect makes it
    "command strength": {
        "-": "a command that saturates or is filtered",
        "+": "a response stronger than the model's command (a gain above one)",
    },
    "gap vs speed": "a speed-dependent time gap",
    "drift": "parameters that drift within a window (regime switching, "
    "changing conditions)",
}
#: Unit of each signature's per-pair value.
UNITS = {
    "response lag": "s",
    "spacing bias": "m",
    "road position": "1",
    "closing vs opening": "m/s^2",
    "drag": "1/m",
    "command strength": "1",
    "gap vs speed": "s",
    "drift": "m/s",
}


@dataclass(frozen=True)
class SignatureRow(Record):
    """A signature's test as a row of ``loop.json``'s ``signatures`` (and of
    ``loop.md``'s table): :meth:`Signature.report`.

    Attributes:
        signature: its name; unit: its per-pair value's (:data:`UNITS`).
        mean, median: of the per-pair values (median None: no pair carries one).
        n_pairs: the pairs that carry one.
        p_value: two-sided sign-flip p-value of a zero mean.
        found: p < :data:`FOUND` (over at least two pairs).
        points_to: the effects that leave it with the sign found.
        family: the model family it suggests where no effect leaves it.
    """

    signature: str
    unit: str
    mean: float
    median: float | None
    n_pairs: int
    p_value: float
    found: bool
    points_to: tuple[str, ...]
    family: str | None


@dataclass(frozen=True)
class Signature:
    """One signature's test across pairs.

    Attributes:
        name: the signature (module docstring).
        values: (N',) its per-pair values (pairs that carry one).
        mean: their mean, in :data:`UNITS`.
        p_value: two-sided sign-flip p-value of a zero mean.
        points_to: the effects that leave it with the sign found (none when it
            is not found or no effect of the library leaves it).
    """

    name: str
    values: np.ndarray
    mean: float
    p_value: float

    @property
    def found(self) -> bool:
        return self.values.size >= 2 and self.p_value < FOUND

    @property
    def sign(self) -> str:
        return "+" if self.mean >= 0 else "-"

    @property
    def points_to(self) -> tuple[str, ...]:
        if not self.found:
            return ()
        return POINTS_TO.get(self.name, {}).get(self.sign, ())

    @property
    def family(self) -> str | None:
        """The model family it suggests when found and no effect leaves it."""
        if self.found and not self.points_to:
            return family_of(self.name, self.mean)
        return None

    def report(self) -> SignatureRow:
        """The test as a row (its per-pair values summed up)."""
        return SignatureRow(
            signature=self.name,
            unit=UNITS[self.name],
            mean=self.mean,
            median=float(np.median(self.values)) if self.values.size else None,
            n_pairs=int(self.values.size),
            p_value=self.p_value,
            found=self.found,
            points_to=self.points_to,
            family=self.family,
        )


def family_of(name: str, mean: float) -> str:
    """The family of model signature ``name`` suggests with a mean of ``mean``
    (:data:`FAMILIES`)."""
    family = FAMILIES[name]
    if isinstance(family, str):
        return family
    return family["+" if mean >= 0 else "-"]


def _slope(y: np.ndarray, x: np.ndarray) -> float:
    """OLS slope of ``y`` on ``x`` with an intercept (NaN: ``x`` constant)."""
    x = x - x.mean()
    denominator = float(x @ x)
    return float(x @ (y - y.mean()) / denominator) if denominator > 0 else np.nan


def peak_lag(y: np.ndarray, u: np.ndarray, steps: int) -> tuple[int, float]:
    """The lag (steps, 0..``steps``) of the largest correlation of ``y(t)`` with
    ``u(t - lag)``, and that correlation."""
    best, best_r = 0, -np.inf
    for lag in range(min(steps, y.size - 10) + 1):
        a, b = y[lag:], u[: u.size - lag]
        if a.std() == 0 or b.std() == 0:
            continue
        r = float(np.corrcoef(a, b)[0, 1])
        if r > best_r:
            best, best_r = lag, r
    return best, best_r


def response_lag(series: dict[str, list[np.ndarray]], dt: float) -> np.ndarray:
    """Per pair, the observed minus the simulated response lag [s] (module
    docstring); pairs whose observed follower correlates less than
    :data:`MIN_RESPONSE_CORRELATION` with its leader are left out."""
    lags = response_lags(series, int(round(MAX_LAG_S / dt)))
    return np.array([(observed - simulated) * dt for _, observed, simulated in lags])


def response_lags(
    series: dict[str, list[np.ndarray]], steps: int
) -> list[tuple[int, int, int]]:
    """Per pair of the residual ``series`` that carries one, ``(its position in
    the series, the observed follower's lag, the simulated one's)`` [steps,
    0..``steps``] of the largest correlation with the leader's acceleration;
    pairs shorter than ``steps + 20`` valid steps, or whose observed follower
    correlates less than :data:`MIN_RESPONSE_CORRELATION`, are left out."""
    out = []
    for j, (a_obs, e_a, a_lead) in enumerate(
        zip(series["a"], series["acceleration"], series["a_lead"], strict=True)
    ):
        ok = np.isfinite(a_obs) & np.isfinite(e_a) & np.isfinite(a_lead)
        a_obs, a_sim, a_lead = a_obs[ok], (a_obs - e_a)[ok], a_lead[ok]
        if a_obs.size < steps + 20:
            continue
        lag_obs, r_obs = peak_lag(a_obs, a_lead, steps)
        if r_obs < MIN_RESPONSE_CORRELATION:
            continue
        lag_sim, _ = peak_lag(a_sim, a_lead, steps)
        out.append((j, lag_obs, lag_sim))
    return out


def _per_pair(fn: Callable[..., float], *columns: list[np.ndarray]) -> np.ndarray:
    values = []
    for arrays in zip(*columns, strict=True):
        ok = np.all([np.isfinite(a) for a in arrays], axis=0)
        value = fn(*(a[ok] for a in arrays))
        if np.isfinite(value):
            values.append(value)
    return np.array(values)


def _side_difference(r: np.ndarray, dv: np.ndarray) -> float:
    closing, opening = dv < 0, dv > 0
    if closing.sum() < MIN_SIDE or opening.sum() < MIN_SIDE:
        return np.nan
    return float(r[closing].mean() - r[opening].mean())


def road_share(
    one_step: dict[str, list[np.ndarray]], profile: Any, folds: int = 5
) -> np.ndarray:
    """Per pair, the share of its one-step residual's variance (around the other
    pairs' mean) that the road ``profile`` (a :class:`~torchcf.models.effects.
    RoadProfile`), fitted on the other folds of pairs, explains. The fit and the
    level weigh each pair by :func:`~torchcf.diagnose.signatures.road.pair_weights` (one
    pair with a residual of tens of m/s^2 would otherwise set the profile every
    other pair is judged by)."""
    from .road import (  # the profile's regression
        _basis,
        fit_profile,
        pair_weights,
    )

    x, r = one_step["x"], one_step["acceleration"]
    n = len(x)
    weights = pair_weights(r)
    folds = min(folds, n)
    out = np.full(n, np.nan)
    for fold in range(folds):
        train = [j for j in range(n) if j % folds != fold]
        held = [j for j in range(n) if j % folds == fold]
        if not train:
            continue
        beta = fit_profile(profile, x, r, weights, train)
        mass = sum(weights[j] * r[j].size for j in train)
        level = sum(weights[j] * float(r[j].sum()) for j in train) / max(mass, 1e-300)
        for j in held:
            flat = float(((r[j] - level) ** 2).sum())
            fitted = float(((_basis(profile, x[j]) @ beta - r[j]) ** 2).sum())
            if flat > 0:
                out[j] = 1.0 - fitted / flat
    return out[np.isfinite(out)]


def simulated_covariates(
    closed: dict[str, list[np.ndarray]],
    one_step: dict[str, list[np.ndarray]],
    lag: int,
) -> dict[str, list[np.ndarray]]:
    """The one-step residual with the simulated follower's covariates ``lag``
    steps before it.

    Args:
        closed: closed-loop residual series (observed - simulated) with the
            observed covariates, every pair with a particle.
        one_step: the one-step residual of the same pairs (those with at least
            two valid steps), its steps the first of ``closed``'s.
        lag: steps (>= 1).

    Returns:
        per pair (T_j - lag steps): ``acceleration`` (the one-step residual
        r(t) [m/s^2]) beside the simulated follower's ``v`` [m/s], ``dv``
        (leader minus simulated follower speed [m/s]) and ``predicted``
        (its acceleration [m/s^2]) at t - lag.
    """
    keep = [j for j, v in enumerate(closed["v"]) if v.size >= 2]
    if len(keep) != len(one_step["acceleration"]):
        raise ValueError(
            f"{len(one_step['acceleration'])} one-step series for {len(keep)} pairs"
        )
    out: dict[str, list[np.ndarray]] = {
        "acceleration": [],
        "v": [],
        "dv": [],
        "predicted": [],
    }
    for j, r in zip(keep, one_step["acceleration"], strict=True):
        steps = r.size
        if steps <= lag:
            continue
        speed_error = closed["speed"][j][:steps]  # observed - simulated
        before = slice(0, steps - lag)
        out["acceleration"].append(r[lag:])
        out["v"].append((closed["v"][j][:steps] - speed_error)[before])
        out["dv"].append((closed["dv"][j][:steps] + speed_error)[before])
        out["predicted"].append(
            (closed["a"][j][:steps] - closed["acceleration"][j][:steps])[before]
        )
    return out


def signatures(
    closed: dict[str, list[np.ndarray]],
    one_step: dict[str, list[np.ndarray]],
    dt: float,
    road_profile: Any | None = None,
    seed: int = 0,
) -> list[Signature]:
    """Every signature of the module docstring, tested across pairs.

    Args:
        closed: closed-loop residual series of the fit windows
            (:func:`~torchcf.diagnose.signatures.series.residual_series`).
        one_step: their one-step residual (:func:`~torchcf.diagnose.signatures.road.
            one_step_residual`).
        dt: step [s].
        road_profile: the road profile to test (None: the pairs have a frame
            each, no road signature).
        seed: the sign-flip tests' seed.
    """
    times = [np.arange(e.size) * dt for e in closed["spacing"]]
    lagged = simulated_covariates(closed, one_step, max(1, round(COVARIATE_LAG_S / dt)))
    r = lagged["acceleration"]
    values = {
        "response lag": response_lag(closed, dt),
        "spacing bias": _per_pair(np.mean, closed["spacing"]),
        "closing vs opening": _per_pair(_side_difference, r, lagged["dv"]),
        "drag": _per_pair(lambda r, v: _slope(r, v * v), r, lagged["v"]),
        "command strength": _per_pair(_slope, r, lagged["predicted"]),
        "gap vs speed": _per_pair(_slope, closed["spacing"], closed["v"]),
        "drift": _per_pair(_slope, closed["spacing"], times),
    }
    if road_profile is not None:
        values["road position"] = road_share(one_step, road_profile)
    out = []
    for name in POINTS_TO:
        if name not in values:
            continue
        v = values[name]
        p = two_sided_sign_flip(v, PERMUTATIONS, seed) if v.size >= 2 else 1.0
        if name == "road position":  # one-sided: a profile that explains
            p = p / 2 if v.size and v.mean() > 0 else 1.0
        out.append(Signature(name, v, float(v.mean()) if v.size else 0.0, p))
    return out


def pointed_effects(found: list[Signature]) -> dict[str, list[str]]:
    """Per effect name, the found signatures that point to it."""
    out: dict[str, list[str]] = {}
    for signature in found:
        for effect in signature.points_to:
            out.setdefault(effect, []).append(signature.name)
    return out


__all__ = [
    "COVARIATE_LAG_S",
    "FAMILIES",
    "family_of",
    "FOUND",
    "MAX_LAG_S",
    "POINTS_TO",
    "UNITS",
    "Signature",
    "SignatureRow",
    "pointed_effects",
    "peak_lag",
    "response_lag",
    "response_lags",
    "road_share",
    "signatures",
    "simulated_covariates",
]
