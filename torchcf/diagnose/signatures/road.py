"""Road effects at the data's resolution (loop step 2, before the attribution).

A road effect (:class:`~torchcf.models.effects.RoadProfile`: ``grade``, ``bend``)
is one function of road position for every pair, so it is offered only where the
pairs' positions are positions on one road (:func:`shares_road_frame`). A bare
``grade`` or ``bend`` spans the training pairs' road section with knots
:data:`ROAD_SPACINGS` apart, the spacing chosen by cross-validation over pairs
(:func:`choose_spacing`): the *one-step* acceleration residual of the run's best
particle per pair (:func:`one_step_residual`: from the observed state at every
step, the observed speed change against the model's one-step prediction), on the
attribution's fit windows only, is regressed on the profile's hat functions, fitted
on all folds but one and scored on the held-out pairs. A road effect that acts as
an acceleration offset ``-g G(x)`` leaves ``r(x) = -g G(x)`` in the one-step
residual exactly, whereas in the closed-loop residual a feedback controller has
already compensated most of it. The coarsest spacing within one standard error
of the least held-out squared error wins (the one-standard-error rule of
Hastie, Tibshirani & Friedman, *The Elements of Statistical Learning*, 7.10),
the standard error being that of the *paired* difference of the fold errors:
the folds hold different pairs, whose residuals differ in size far more than two
spacings differ on one fold, so the spread of a fold's total error would hide
any profile finer than the coarsest.
Every regression weighs down a pair whose residual is far noisier than the
others' (:func:`pair_weights`, a Huber weight over pairs): the pairs' residuals
can be of very different sizes (a stiff model, FVDM with tau near 0.1 s,
commands tens of m/s^2 from a measured state it never reaches in closed loop),
and unweighted, one such pair out of 50 made 96 % of the squared error of a
measured data set and turned the road signature negative.
The regression on all pairs also gives the grade search its first candidate
(:func:`grade_seed`), which a random search in tens of knot values could not
find; a bend's first candidate is the speed no follower exceeds near each knot
(:func:`bend_seed`).

Shapes: N pairs, T steps (:mod:`torchcf.typing`); residual series are per pair,
valid steps only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ...data import PairSet
from ...models import FollowerState, Perception
from ...models.effects import GRAVITY, Bend, Grade, RoadProfile, parse_effect
from ...sim.rollout import realise
from ...system.files import JSON
from .series import BestParticles

#: Knot spacings [m] a bare road effect chooses from (coarse to fine).
ROAD_SPACINGS = (400.0, 200.0, 100.0, 50.0)
#: Fewest knots of a profile round a closed track: with two, a lap's knots
#: could both sit where a tilted circle is level (its lowest and highest
#: points) and miss the whole grade.
MIN_LAP_KNOTS = 3
#: Folds of the spacing's cross-validation (pairs dealt round-robin).
FOLDS = 5
#: Pairs whose first follower positions all lie within this much [m] are taken
#: to have a frame each (unless the data declare otherwise).
SAME_START = 1.0
#: Margin [m/s] of a bend's first candidate over the highest speed driven at a
#: knot (:func:`bend_seed`): a limit right at the envelope would cap the
#: acceleration of every follower near it.
BEND_SEED_MARGIN = 1.0
#: Half-width [m] of the road stretch around a knot whose speeds give the
#: bend's first candidate there (narrow: the limit changes between knots).
BEND_SEED_WINDOW = 50.0
#: Ridge added to the normal equations (relative to their trace), so knots no
#: pair reaches stay at 0 instead of making the fit singular.
RIDGE = 1e-6
#: A pair whose residual scale exceeds this many times the median pair's is
#: weighed down to count as one of that scale (:func:`pair_weights`).
OUTLIER_SCALE = 3.0
#: 1.4826 MAD estimates a Gaussian's standard deviation.
MAD_TO_SIGMA = 1.4826


def shares_road_frame(pairs: PairSet) -> tuple[bool, str]:
    """Whether the pairs' positions are on one road, and why.

    Declared by the data (``meta.json``'s ``road_frame``, or the named data
    set's registry entry) when they say; otherwise the pairs share a road when
    their first follower positions differ (spread over :data:`SAME_START`): pairs
    recorded on one road start where they were found. Pairs that all start at
    the same position are taken to have a frame each (positions measured from
    each pair's start); a test track with one start line says so in
    ``meta.json``.
    """
    if pairs.road_frame is not None:
        where = "declared by the data"
        return bool(pairs.road_frame), where
    start = pairs.x_follow[0].double()
    spread = float(start.max() - start.min()) if pairs.n_pairs else 0.0
    if spread > SAME_START:
        return True, (
            f"undeclared; the pairs start at different positions (spread "
            f"{spread:.0f} m), positions on one road"
        )
    return False, (
        "undeclared; every pair starts at the same position, a frame per pair "
        '(write "road_frame": true in the data\'s meta.json if they share a road)'
    )


def one_step_residual(best: BestParticles, pairs: PairSet) -> dict[str, list]:
    """The one-step acceleration residual of every pair's particle.

    At every valid step t (but the last) the follower is put in its observed
    state, the model commands from the observed perception and realises one step
    (:func:`torchcf.sim.rollout.realise`); the residual is what the *command* missed
    [m/s^2], so that an effect acting on the command (a grade's ``-g G(x)``)
    appears in it whole, whatever the realisation:

    - a point mass: ``(v_obs(t + 1) - v_pred(t + 1)) / dt`` (= ``a_obs(t) -
      u(t)``);
    - a model whose acceleration is a state (HL's actuation lag, the ``lag``
      effect): ``(a_obs(t + 1) - a_pred(t + 1)) / k``, ``k = da(t + 1)/du``
      (``1 - exp(-dt / tau)`` for a first-order lag). Its one-step *speed*
      residual would carry only about ``k / 2`` of a command offset (the lag has
      barely started to pass it on), about a tenth at tau = 0.5 s and dt = 0.1 s.

    Memory-carrying models start from a steady past at every step (a delay
    effect is not a pool model; the MPC's memory only warm-starts its solver).

    Returns:
        lists (one float64 array per pair with a particle, pairs in position
        order, valid steps but the last) under ``x`` (observed road position
        [m]), ``v`` (observed speed [m/s]), ``dv`` (leader minus follower speed
        [m/s]), ``predicted`` (the model's one-step acceleration ``(v_pred(t +
        1) - v(t)) / dt`` [m/s^2]) and ``acceleration`` (the residual).
    """
    obs = {k: t.double().cpu() for k, t in pairs.series().items()}
    keys = ("x", "v", "dv", "predicted", "acceleration")
    out: dict[str, list[np.ndarray]] = {key: [] for key in keys}
    rows: dict[int, tuple[np.ndarray, ...]] = {}
    for model, (theta, position) in best.items():
        for row, j in enumerate(position.tolist()):
            steps = int(pairs.mask[:, j].sum()) - 1
            if steps < 1:
                continue
            state = FollowerState(
                x=obs["x_follow"][:steps, j],
                v=obs["v_follow"][:steps, j],
                a=obs["a_follow"][:steps, j],
            )
            perception = Perception(
                spacing=obs["x_lead"][:steps, j] - state.x,
                v=state.v,
                v_lead=obs["v_lead"][:steps, j],
                a=state.a,
                leader_length=pairs.leader_length,
                position=state.x,
            )
            params = model.unpack(theta[row : row + 1].double().expand(steps, -1))
            params = model.prepare(params, pairs.dt, (steps,))
            memory = model.initial_memory(params, perception)
            command, _ = model.command_with_memory(params, perception, memory)
            moved = realise(model, params, state, command, pairs.dt)
            residual = (obs["v_follow"][1 : steps + 1, j] - moved.v) / pairs.dt
            if model.acceleration_is_state:
                residual = _command_residual(
                    model,
                    params,
                    state,
                    command,
                    obs["a_follow"][1 : steps + 1, j] - moved.a,
                    residual,
                    pairs.dt,
                )
            rows[j] = (
                state.x.numpy(),
                state.v.numpy(),
                (perception.v_lead - state.v).numpy(),
                ((moved.v - state.v) / pairs.dt).numpy(),
                residual.numpy(),
            )
    for j in sorted(rows):
        for key, values in zip(keys, rows[j], strict=True):
            out[key].append(values)
    return out


def _command_residual(
    model: Any,
    params: Any,
    state: FollowerState,
    command: Tensor,
    a_missed: Tensor,
    speed_residual: Tensor,
    dt: float,
) -> Tensor:
    """``a_missed / k`` with ``a_missed = a_obs(t + 1) - a_pred(t + 1)`` and ``k =
    da(t + 1)/du`` of the model's realisation (:meth:`CFModel.advance`, linear in
    the command for a lag), found by a unit step of the command. Where ``k`` is
    ~0 (nothing passes the command on) the speed residual stands."""
    plain = model.advance(params, state, command, dt).a
    gain = model.advance(params, state, command + 1.0, dt).a - plain
    usable = gain.abs() > 1e-6
    return torch.where(
        usable, a_missed / torch.where(usable, gain, 1.0), speed_residual
    )


def _least_squares(design: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Ridge-stabilised least squares ``argmin |design b - target|^2``."""
    gram = design.T @ design
    gram += RIDGE * max(np.trace(gram), 1.0) / gram.shape[0] * np.eye(gram.shape[0])
    return np.linalg.solve(gram, design.T @ target)


def _basis(profile: RoadProfile, x: np.ndarray) -> np.ndarray:
    return profile.basis(torch.from_numpy(x)).numpy()


def pair_weights(residual: list[np.ndarray]) -> np.ndarray:
    """(N,) regression weight of each pair [1]: 1, or less for a pair whose
    residual is far noisier than the others'.

    ``w_j = min(1, (c sigma_med / sigma_j)^2)`` with ``c =``
    :data:`OUTLIER_SCALE`, ``sigma_j`` the robust step-to-step scale of pair j's
    residual (:func:`_step_scale`) and ``sigma_med`` the median pair's: a Huber
    weight over pairs. Pairs of one scale count alike, as in the unweighted
    fit (weighing every pair by its own inverse variance favoured the quietest
    pairs and chose knots too fine for a smooth synthetic grade, which the loop
    then missed); a pair c times noisier than the median counts as if its
    residual were only that noisy. Pairs with fewer than two samples weigh 0.
    """
    scales = np.array([_step_scale(r) for r in residual])
    weights = np.where([r.size > 1 for r in residual], 1.0, 0.0)
    sized = scales[(scales > 0) & (weights > 0)]
    if not sized.size:
        return weights
    bound = OUTLIER_SCALE * float(np.median(sized))
    noisy = scales > bound
    weights[noisy] = (bound / scales[noisy]) ** 2
    return weights


def _step_scale(r: np.ndarray) -> float:
    """Robust standard deviation of a series' white part [its unit]: 1.4826
    MAD of its first differences over sqrt(2) (blind to what varies slowly,
    such as the road profile being fitted); 0 for fewer than two samples."""
    if r.size < 2:
        return 0.0
    steps = np.diff(r)
    spread = float(np.median(np.abs(steps - np.median(steps))))
    return MAD_TO_SIGMA * spread / math.sqrt(2)


def fit_profile(
    profile: RoadProfile,
    x: list[np.ndarray],
    residual: list[np.ndarray],
    weights: np.ndarray,
    pairs: list[int] | None = None,
) -> np.ndarray:
    """(K,) knot values of the profile's weighted least-squares fit to the
    residual [the residual's unit], on ``pairs`` (default all): ``argmin sum_j
    w_j |basis(x_j) b - r_j|^2``."""
    chosen = range(len(x)) if pairs is None else pairs
    root = {j: math.sqrt(weights[j]) for j in chosen}
    design = np.concatenate([_basis(profile, x[j]) * root[j] for j in chosen])
    target = np.concatenate([residual[j] * root[j] for j in chosen])
    return _least_squares(design, target)


def cross_validated_error(
    profile: RoadProfile,
    x: list[np.ndarray],
    residual: list[np.ndarray],
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """(F,) held-out weighted squared error of the profile's regression per fold,
    ``F = FOLDS`` folds over pairs (pair j in fold ``j % FOLDS``), summed over the
    fold's pairs: ``sum_j w_j |basis(x_j) b - r_j|^2`` [1] with the weights of
    :func:`pair_weights` (default)."""
    weights = pair_weights(residual) if weights is None else weights
    folds = min(FOLDS, len(x))
    per_fold = []
    for fold in range(folds):
        train = [j for j in range(len(x)) if j % folds != fold]
        held = [j for j in range(len(x)) if j % folds == fold]
        beta = fit_profile(profile, x, residual, weights, train)
        per_fold.append(
            sum(
                weights[j]
                * float(((_basis(profile, x[j]) @ beta - residual[j]) ** 2).sum())
                for j in held
            )
        )
    return np.array(per_fold)


def paired_standard_error(errors: np.ndarray, least: np.ndarray) -> float:
    """Standard error of the summed difference of two spacings' fold errors
    (F,): ``sqrt(F)`` times the spread of the per-fold differences."""
    difference = errors - least
    if difference.size < 2:
        return 0.0
    return float(math.sqrt(difference.size) * difference.std(ddof=1))


@dataclass(frozen=True)
class RoadChoice:
    """A bare road effect resolved at the data's resolution.

    Attributes:
        effect: the effect with its section and knots, e.g.
            ``grade(start=12,end=1700,knots=35)``.
        spacing: the chosen knot spacing [m].
        errors: held-out squared error per spacing tried.
        standard_errors: per spacing, the standard error of its error's
            difference to the least (paired over folds).
        seed: a first candidate of the knot values (grade: from the regression;
            bend: the speed envelope),
            or None.
    """

    effect: RoadProfile
    spacing: float
    errors: dict[float, float]
    standard_errors: dict[float, float]
    seed: Tensor | None

    def report(self) -> JSON:
        """As ``loop.json``'s ``road.profiles`` holds it."""
        return {
            "effect": self.effect.token,
            "spacing": self.spacing,
            "cv_error": {f"{k:g}": v for k, v in self.errors.items()},
        }


@dataclass(frozen=True)
class RoadOffer:
    """How road effects were offered to the attribution.

    Attributes:
        frame: the pairs share one road frame (road effects offered).
        reason: why (:func:`shares_road_frame`).
        skipped: the configured road effects left out (no shared frame).
        profiles: per bare road effect, its knot spacing chosen on the data.
    """

    frame: bool
    reason: str
    skipped: list[RoadProfile]
    profiles: list[RoadChoice]

    def to_json(self) -> JSON:
        """As ``loop.json``'s ``road``."""
        return {
            "frame": self.frame,
            "reason": self.reason,
            "skipped": [effect.token for effect in self.skipped],
            "profiles": [choice.report() for choice in self.profiles],
        }


def choose_spacing(
    kind: type[RoadProfile],
    start: float,
    end: float,
    series: dict[str, list[np.ndarray]],
    period: float = 0.0,
) -> RoadChoice:
    """The knot spacing of a bare road effect by cross-validation (module
    docstring), on the residual ``series`` of the part the arms are fitted on.
    Samples where the residual is not finite (a command the model cannot give
    at the observed state) are left out. On a closed track (``period`` > 0,
    the lap length [m]; ``end`` unused) the profile is periodic with at least
    :data:`MIN_LAP_KNOTS` knots round the lap."""
    series = finite_samples(series)
    x, residual = series["x"], series["acceleration"]
    errors: dict[float, float] = {}
    standard: dict[float, float] = {}
    profiles: dict[float, RoadProfile] = {}
    folds: dict[float, np.ndarray] = {}
    weights = pair_weights(residual)
    for spacing in ROAD_SPACINGS:
        if period:
            knots = max(MIN_LAP_KNOTS, round(period / spacing))
            effect = kind(start=start, period=period, knots=knots)
        else:
            knots = max(2, round((end - start) / spacing) + 1)
            effect = kind(start=start, end=end, knots=knots)
        if knots in {p.knots for p in profiles.values()}:
            continue  # a short road: coarser spacings give the same profile
        profiles[spacing] = effect
        folds[spacing] = cross_validated_error(effect, x, residual, weights)
        errors[spacing] = float(folds[spacing].sum())
    # The one-standard-error rule: the coarsest spacing within one standard
    # error of the least error (finer knots must earn their parameters).
    least = min(errors, key=errors.get)
    for spacing in errors:
        standard[spacing] = paired_standard_error(folds[spacing], folds[least])
    best = max(s for s in errors if errors[s] - errors[least] <= standard[s])
    effect = profiles[best]
    seed = None
    if isinstance(effect, Grade):
        seed = grade_seed(effect, x, residual, weights)
    elif isinstance(effect, Bend) and "v" in series:
        seed = bend_seed(effect, x, series["v"])
    return RoadChoice(effect, best, errors, standard, seed)


def finite_samples(series: dict[str, list[np.ndarray]]) -> dict[str, list[np.ndarray]]:
    """The series with, per pair, only the steps where the position and the
    acceleration residual are finite (every series cut alike)."""
    keep = [
        np.isfinite(x) & np.isfinite(r)
        for x, r in zip(series["x"], series["acceleration"], strict=True)
    ]
    return {
        key: [a[k] for a, k in zip(arrays, keep, strict=True)]
        for key, arrays in series.items()
    }


def grade_seed(
    effect: Grade,
    x: list[np.ndarray],
    residual: list[np.ndarray],
    weights: np.ndarray | None = None,
) -> Tensor:
    """Knot values (K,) of the grade that explains the acceleration residual,
    ``r_a ~ -g G(x)`` (each pair weighted by ``weights``, default
    :func:`pair_weights`), clipped to the prior."""
    weights = pair_weights(residual) if weights is None else weights
    beta = fit_profile(effect, x, residual, weights)
    low, high = effect.param_specs[0].lower, effect.param_specs[0].upper
    return torch.from_numpy(np.clip(-beta / GRAVITY, low, high))


def profile_agreement(
    reference: str,
    reference_values: dict[str, float],
    fitted: str,
    fitted_values: dict[str, float],
    positions: Tensor,
) -> float:
    """Pearson correlation of two road profiles over ``positions`` [m].

    How well a learned profile (a chosen effect's name, e.g.
    ``"grade(start=-49,end=1041,knots=4)"``, with its knot values by parameter
    name) follows a known one (a survey, or the profile synthetic data were
    made with), whatever their knots: both are evaluated at the same road
    positions. Scale-free, so a profile of the right shape but damped amplitude
    still scores high; compare amplitudes separately where they matter.

    Args:
        reference, fitted: road-effect tokens (:func:`parse_effect`).
        reference_values, fitted_values: knot values by parameter name
            (``grade_0 ...``), in the profile's unit.
        positions: (G,) road positions [m], e.g. where the followers drove.

    Returns:
        The correlation in [-1, 1]; NaN when either profile is constant there.
    """
    curves = []
    for token, values in ((reference, reference_values), (fitted, fitted_values)):
        effect = parse_effect(token)
        if not isinstance(effect, RoadProfile):
            raise ValueError(f"{token!r} is not a road effect")
        knots = torch.tensor(
            [values[p.name] for p in effect.param_specs], dtype=torch.float64
        )
        # (knots, 1): one profile, broadcast over the (G,) positions
        curves.append(effect.profile((knots[:, None],), positions.double()))
    return float(torch.corrcoef(torch.stack(curves))[0, 1])


def bend_seed(effect: Bend, x: list[np.ndarray], v: list[np.ndarray]) -> Tensor:
    """Knot values (K,) of a speed limit no follower exceeds: at each knot, the
    highest observed follower speed within :data:`BEND_SEED_WINDOW` of it (or
    within half a knot spacing, where nobody drove that close) plus
    :data:`BEND_SEED_MARGIN`, clipped to the prior; knots no pair reaches get
    the prior's upper bound (no limit). A limit the driving presses against is
    where it binds; the search starts there and moves knots up where it does
    not."""
    positions = torch.from_numpy(np.concatenate(x))
    speeds = np.concatenate(v)
    half = (
        effect.spacing / 2.0 if effect.knots > 1 else (effect.end - effect.start) / 2.0
    )
    low, high = effect.param_specs[0].lower, effect.param_specs[0].upper
    seed = np.full(effect.knots, high)
    for k, at in enumerate(effect.knot_positions):
        distance = effect.distance_to(positions, at).numpy()
        for window in (min(half, BEND_SEED_WINDOW), half):
            near = distance <= window
            if near.any():
                seed[k] = speeds[near].max() + BEND_SEED_MARGIN
                break
    return torch.from_numpy(np.clip(seed, low, high))


__all__ = [
    "BEND_SEED_MARGIN",
    "BEND_SEED_WINDOW",
    "FOLDS",
    "MAD_TO_SIGMA",
    "MIN_LAP_KNOTS",
    "OUTLIER_SCALE",
    "ROAD_SPACINGS",
    "SAME_START",
    "RoadChoice",
    "bend_seed",
    "RoadOffer",
    "choose_spacing",
    "cross_validated_error",
    "finite_samples",
    "fit_profile",
    "grade_seed",
    "one_step_residual",
    "pair_weights",
    "profile_agreement",
    "shares_road_frame",
]
