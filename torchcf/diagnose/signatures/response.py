"""The response time of the data and of the calibrated models.

Two measures, each answering its own question:

**Correlation lag on the recorded pairs** (what the data show, and whether the
calibrated models show the same). Per pair, the lag (0 to
:data:`RESPONSE_MAX_LAG_S`) of the largest correlation of the follower's
acceleration with its leader's: of the observed follower and of the pair's
best particle driven behind the recorded leader. Pairs whose observed follower
correlates less than
:data:`~torchcf.diagnose.signatures.families.MIN_RESPONSE_CORRELATION`
with its leader at every lag carry none and are left out of both. The lag
searched is twice the residual signature's
(:data:`~torchcf.diagnose.signatures.families.MAX_LAG_S`): on measured highway driving
the followers' median reaches that signature's 4 s, and a median at the edge of
the search says nothing. In everyday driving the leader's changes are small
and slow; a follower that lets its spacing absorb them answers late, so this
lag is often longer than a test track's.

**Perturbation response** (the figure published for commercial ACCs, e.g. 1.7-
2.5 s on five cars in Makridis et al. 2020's platoon tests). Every pair's best
particle follows a standard leader (:class:`Perturbation`): it cruises for
``settle`` seconds at the pair's median observed speed ``v0``, from the pair's
median observed spacing, so that the follower settles at its own equilibrium;
then the leader brakes at ``rate`` by ``drop`` (``drop_share * v0``, at most
``max_drop``), holds, and accelerates back at ``rate``. The response time is
the shift ``tau`` (0 to :data:`RESPONSE_MAX_LAG_S`, on the grid of ``dt``) of
the leader's speed that the follower's matches best,

    tau* = argmin_tau sqrt(mean_{t >= t_p} (v_f(t) - v_l(t - tau))^2),

over the steps from the leader's first braking step ``t_p`` to the end. A
rollout that fails (a collision, a non-finite state) carries none.

**The same measure on the recorded pairs' braking events** (what the data's
own perturbations show; :func:`event_shifts`). An event: the leader, steady for
``EVENT_STEADY`` seconds (its speed's standard deviation under
``EVENT_STEADY_SPREAD``), falls ``EVENT_ONSET`` below that level (the onset)
and at least ``EVENT_DROP`` below it within ``EVENT_WITHIN`` seconds; the
shift of the leader's speed that the follower's matches best over the
``EVENT_WINDOW`` seconds from its onset, of the observed follower and of the
pair's best particle behind the recorded leader. Everyday
driving holds few such events (a pair carries at most one per window), so this
is the figure to set beside the perturbation response where the data have them.

Shapes: P particles, T steps (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import torch

from ...data import PairSet
from ...models import CFModel
from ...sim.rollout import simulate
from ...system.records import Record
from .families import MAX_LAG_S, response_lags
from .series import BestParticles

#: Longest response time searched [s] (module docstring).
RESPONSE_MAX_LAG_S = 2 * MAX_LAG_S
#: A braking event of the recorded leader (module docstring): the drop [m/s],
#: the time it takes at most [s], the steady time before it [s] and the spread
#: of speed [m/s] that counts as steady, the window the shift is fitted on [s].
EVENT_DROP = 2.0
EVENT_WITHIN = 5.0
EVENT_STEADY = 2.0
EVENT_STEADY_SPREAD = 0.5
EVENT_WINDOW = 15.0
#: The onset: the first step this far [m/s] below the steady level.
EVENT_ONSET = 0.2
#: Lowest cruising speed of the perturbation [m/s]: below it a stop-and-go
#: follower's response is the start-up's, not car following's.
MIN_CRUISE_SPEED = 5.0


@dataclass(frozen=True)
class Perturbation:
    """The standard leader of the perturbation response (module docstring).

    Attributes:
        settle: cruising before the braking [s].
        rate: the leader's braking and accelerating rate [m/s^2].
        drop_share: the speed drop as a share of the cruising speed.
        max_drop: the largest speed drop [m/s].
        hold: time at the lower speed [s].
        after: time after the leader is back at the cruising speed [s].
    """

    settle: float = 60.0
    rate: float = 1.0
    drop_share: float = 0.25
    max_drop: float = 5.0
    hold: float = 10.0
    after: float = 30.0

    def leader_speed(self, v0: np.ndarray, dt: float) -> tuple[np.ndarray, int]:
        """``(T, N)`` the leader's speed [m/s] at cruising speeds ``v0`` (N,),
        and the step ``t_p`` of its first braking."""
        drop = np.minimum(self.drop_share * v0, self.max_drop)
        ramp = drop / self.rate  # (N,) [s]
        t_p = int(round(self.settle / dt))
        length = self.settle + 2 * float(ramp.max()) + self.hold + self.after
        t = np.arange(int(round(length / dt)) + 1)[:, None] * dt - self.settle
        down = np.clip(t * self.rate, 0.0, drop)  # braking, then holding
        back = np.clip((t - ramp - self.hold) * self.rate, 0.0, drop)
        return v0 - down + back, t_p


@dataclass(frozen=True)
class ResponseTimes(Record):
    """The response times of the data and of the calibrated models [s]
    (module docstring): medians over pairs.

    Attributes:
        data: the observed followers' correlation lag (None: no pair carries
            one).
        data_quartiles: its 25 % and 75 % quantiles.
        model: the pairs' best particles' correlation lag (the hybrid's own,
            on the same pairs as ``data``).
        model_quartiles: its 25 % and 75 % quantiles.
        by_model: per model (the model of each pair's best particle), its
            pairs' median correlation lag.
        pairs: pairs that carry a correlation lag; per_model: per model, its.
        perturbation: the pairs' best particles' perturbation response
            (None: none carries one).
        perturbation_quartiles: its 25 % and 75 % quantiles.
        perturbation_by_model: per model, its pairs' median perturbation
            response.
        perturbation_pairs: pairs that carry one.
        events: the recorded leaders' braking events (:func:`event_shifts`).
        event_data, event_data_quartiles: the observed followers' shift on
            them, median and quartiles (None: no event).
        event_model, event_model_quartiles: the best particles' on the same.
    """

    data: float | None
    data_quartiles: tuple[float, float] | None
    model: float | None
    model_quartiles: tuple[float, float] | None
    by_model: dict[str, float]
    pairs: int
    per_model: dict[str, int]
    perturbation: float | None = None
    perturbation_quartiles: tuple[float, float] | None = None
    perturbation_by_model: dict[str, float] | None = None
    perturbation_pairs: int = 0
    events: int = 0
    event_data: float | None = None
    event_data_quartiles: tuple[float, float] | None = None
    event_model: float | None = None
    event_model_quartiles: tuple[float, float] | None = None


def response_times(
    best: BestParticles,
    series: dict[str, list[np.ndarray]],
    pairs: PairSet,
    perturbation: Perturbation = Perturbation(),
) -> ResponseTimes:
    """The response times of ``pairs`` driven by their ``best`` particles
    (``series``: their residual series, one entry per pair with a particle, in
    position order)."""
    dt = pairs.dt
    models = sorted(
        (int(p), model.name)
        for model, (_, positions) in best.items()
        for p in positions.tolist()
    )
    if len(models) != len(series["a"]):  # a pair whose rollout failed: no names
        models = [(j, "?") for j in range(len(series["a"]))]
    lags = response_lags(series, int(round(RESPONSE_MAX_LAG_S / dt)))
    observed = [lag * dt for _, lag, _ in lags]
    simulated = [lag * dt for _, _, lag in lags]
    names = [models[j][1] for j, _, _ in lags]
    steps = {
        model.name: perturbation_response(model, theta, pairs, position, perturbation)
        for model, (theta, position) in best.items()
    }
    perturbed = {k: v[np.isfinite(v)].tolist() for k, v in steps.items()}
    every = [t for values in perturbed.values() for t in values]
    events = event_shifts(series, dt)
    event_data = [observed for observed, _ in events]
    event_model = [simulated for _, simulated in events if np.isfinite(simulated)]
    return ResponseTimes(
        data=_median(observed),
        data_quartiles=_quartiles(observed),
        model=_median(simulated),
        model_quartiles=_quartiles(simulated),
        by_model=_medians(zip(names, simulated, strict=True)),
        pairs=len(observed),
        per_model=dict(Counter(names)),
        perturbation=_median(every),
        perturbation_quartiles=_quartiles(every),
        perturbation_by_model={
            k: float(np.median(v)) for k, v in perturbed.items() if v
        },
        perturbation_pairs=len(every),
        events=len(events),
        event_data=_median(event_data),
        event_data_quartiles=_quartiles(event_data),
        event_model=_median(event_model),
        event_model_quartiles=_quartiles(event_model),
    )


def perturbation_response(
    model: CFModel,
    theta: torch.Tensor,
    pairs: PairSet,
    position: torch.Tensor,
    perturbation: Perturbation = Perturbation(),
) -> np.ndarray:
    """``(P,)`` the perturbation response [s] of particles ``theta`` (P, K),
    each at the cruising speed and spacing of its pair ``position`` (P,) in
    ``pairs`` (module docstring); NaN where the rollout fails."""
    if len(position) == 0:
        return np.zeros(0)
    scene = perturbation_pairs(pairs, position, perturbation)
    out = simulate(
        model,
        theta.double(),
        scene.pairs,
        torch.arange(len(position)),
        dtype=torch.float64,
        return_traj=True,
    )
    v_follow = out.v.double().cpu().numpy()  # (T, P)
    return speed_shift(v_follow, scene.v_lead, scene.start, pairs.dt)


@dataclass(frozen=True)
class _Scene:
    pairs: PairSet  # (T, P) the standard leader, one column per particle
    v_lead: np.ndarray  # (T, P) [m/s]
    start: int  # the leader's first braking step


def perturbation_pairs(
    pairs: PairSet, position: torch.Tensor, perturbation: Perturbation
) -> _Scene:
    """One pair per entry of ``position``: the standard leader at that pair's
    median observed speed, the follower starting at its median observed spacing
    (its recorded series past the first step are the leader's moved back by
    it: only the start is used)."""
    dt, columns = pairs.dt, position.cpu().long()
    mask = pairs.mask.cpu()[:, columns]
    v0 = np.maximum(_masked_median(pairs.v_follow, mask, columns), MIN_CRUISE_SPEED)
    spacing = _masked_median(pairs.x_lead - pairs.x_follow, mask, columns)
    v_lead, start = perturbation.leader_speed(v0, dt)
    a_lead = np.vstack([np.diff(v_lead, axis=0) / dt, np.zeros((1, v0.size))])
    # Positions exact for piecewise-constant acceleration (the trapezoid).
    steps = (v_lead[1:] + v_lead[:-1]) * dt / 2
    x_lead = spacing + np.vstack([np.zeros((1, v0.size)), np.cumsum(steps, axis=0)])
    scene = PairSet.from_arrays(
        [x_lead, v_lead, a_lead, x_lead - spacing, v_lead, a_lead],
        dt=dt,
        leader_length=pairs.leader_length,
        name="perturbation",
    )
    return _Scene(scene, v_lead, start)


def speed_shift(
    v_follow: np.ndarray, v_lead: np.ndarray, start: int, dt: float
) -> np.ndarray:
    """``(P,)`` per column, the shift [s] of ``v_lead`` (T, P) that ``v_follow``
    (T, P) matches best over the steps from ``start`` on (module docstring);
    NaN where ``v_follow`` is not finite there."""
    steps = min(int(round(RESPONSE_MAX_LAG_S / dt)), start)
    follower = v_follow[start:]  # (W, P)
    errors = np.stack(
        [
            np.sqrt(
                np.mean(
                    (follower - v_lead[start - lag : v_lead.shape[0] - lag]) ** 2, 0
                )
            )
            for lag in range(steps + 1)
        ]
    )  # (lags, P)
    shift = errors.argmin(0) * dt
    return np.where(np.isfinite(follower).all(0), shift, np.nan)


def event_shifts(
    series: dict[str, list[np.ndarray]], dt: float
) -> list[tuple[float, float]]:
    """``(observed, simulated)`` speed shift [s] on every braking event of the
    recorded leaders in the residual ``series`` (module docstring; ``v`` the
    observed follower's speed, ``dv`` the leader's minus it, ``speed`` the
    observed minus the simulated follower's)."""
    steps = int(round(RESPONSE_MAX_LAG_S / dt))
    window = int(round(EVENT_WINDOW / dt))
    out = []
    for v, dv, e_v in zip(series["v"], series["dv"], series["speed"], strict=True):
        v_lead = v + dv
        for onset in braking_onsets(v_lead, dt, earliest=steps, room=window):
            around = slice(onset - steps, onset + window)
            follow = np.stack([v[around], (v - e_v)[around]], 1)  # (W, 2)
            lead = np.stack([v_lead[around]] * 2, 1)
            observed, simulated = speed_shift(follow, lead, steps, dt)
            out.append((float(observed), float(simulated)))
    return out


def braking_onsets(
    v_lead: np.ndarray, dt: float, earliest: int, room: int
) -> list[int]:
    """The steps where a braking event of ``v_lead`` (T,) begins (module
    docstring), none before ``earliest`` nor with fewer than ``room`` steps
    after it; events do not overlap."""
    steady, within = int(round(EVENT_STEADY / dt)), int(round(EVENT_WITHIN / dt))
    onsets, t = [], max(earliest, steady)
    while t + room <= v_lead.size:
        before = v_lead[t - steady : t]
        level = before.mean()
        if (
            v_lead[t] < level - EVENT_ONSET
            and level - v_lead[t : t + within + 1].min() >= EVENT_DROP
            and before.std() < EVENT_STEADY_SPREAD
        ):
            onsets.append(t)
            t += room
        else:
            t += 1
    return onsets


def _masked_median(values: torch.Tensor, mask: torch.Tensor, columns) -> np.ndarray:
    table = values.double().cpu()[:, columns].numpy()
    return np.array(
        [np.median(table[mask[:, j].numpy(), j]) for j in range(table.shape[1])]
    )


def _median(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def _quartiles(values: list[float]) -> tuple[float, float] | None:
    if not values:
        return None
    low, high = np.percentile(values, [25, 75])
    return float(low), float(high)


def _medians(named) -> dict[str, float]:
    by_model: dict[str, list[float]] = {}
    for name, value in named:
        by_model.setdefault(name, []).append(value)
    return {k: float(np.median(v)) for k, v in by_model.items()}


__all__ = [
    "RESPONSE_MAX_LAG_S",
    "Perturbation",
    "braking_onsets",
    "event_shifts",
    "ResponseTimes",
    "perturbation_pairs",
    "perturbation_response",
    "response_times",
    "speed_shift",
]
