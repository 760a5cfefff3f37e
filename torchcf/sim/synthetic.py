"""Synthetic leader-follower pairs: known models and effects, for testing the method.

:func:`synthetic_pairs` draws smooth leader speed profiles (a cruise speed, random
sinusoidal fluctuations and braking/re-acceleration events) and drives followers
with a given model — pool model or effect-augmented, e.g. ``"idm+delay"`` — through
:func:`torchcf.simulate`. Calibrating a pool *without* the effect on such data is
how the close-the-loop tests check that the effect is found.

:class:`Gipps` is a follower *outside* the pool (not in the model registry):
data it drives test the loop where no candidate model is the truth, as with a
user's data.

:func:`heterogeneous_pairs` makes data that look like measured data: every pair
its own driver, drawn from a mixture of models (:class:`DriverMixture`) with
parameters drawn over a box
(the model's prior by default) and kept where it follows plausibly, pairs of
ragged length, measurement noise; one effect, planted in every driver, is what
the loop should find.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ..data import PairSet
from ..models import CFModel, get_model, require_model
from ..models.base import Perception, spec
from .rollout import simulate


class GippsParams(NamedTuple):
    """:class:`Gipps`'s parameters, each broadcast to the state: ``a``, ``b``,
    ``b_lead`` [m/s^2], ``v0`` [m/s], ``tau`` [s], ``size`` [m].

    Examples:
        >>> import torch
        >>> from torchcf.sim.synthetic import Gipps
        >>> p = Gipps().unpack(torch.tensor([[1.5, 3.0, 3.0, 30.0, 0.8, 7.0]]))
        >>> type(p).__name__, p.tau.shape, round(float(p.tau), 3)  # tau [s], (P,)
        ('GippsParams', torch.Size([1]), 0.8)
    """

    a: Tensor
    b: Tensor
    b_lead: Tensor
    v0: Tensor
    tau: Tensor
    size: Tensor


class Gipps(CFModel):
    """Gipps (1981) safe-speed follower, written as an acceleration command.

    Over one reaction time ``tau`` the driver reaches the smaller of a free-road
    speed and the largest speed from which it can still stop behind a leader that
    brakes at ``b_lead``:

    ``v_free = v + 2.5 a tau (1 - v / v0) sqrt(0.025 + v / v0)``,
    ``v_safe = -b tau + sqrt(b^2 tau^2 + b (2 (s - size) - v tau
    + v_lead^2 / b_lead))``,
    ``u = (max(0, min(v_free, v_safe)) - v) / tau`` [m/s^2],

    ``s`` the front-to-front spacing [m] and ``size`` the leader's effective
    length with the standstill margin [m]; a negative root argument (a spacing
    too short to stop) reads 0. Not in the registry: no pool model is Gipps, so
    it stands for the unknown truth of measured data.

    Examples:
        >>> from torchcf.sim.synthetic import Gipps, synthetic_pairs
        >>> gipps = Gipps()  # a, b, b_lead, v0, tau, size (SI)
        >>> theta = [1.5, 3.0, 3.0, 30.0, 0.8, 7.0]
        >>> pairs = synthetic_pairs(gipps, theta, n_pairs=2, n_steps=50)
        >>> gipps.name, gipps.n_params, pairs.n_pairs
        ('gipps', 6, 2)
    """

    name = "gipps"
    Params = GippsParams
    param_specs = (
        spec("a", "m/s^2", 0.5, 3.0, "maximum acceleration"),
        spec("b", "m/s^2", 1.0, 5.0, "most severe braking the driver plans"),
        spec("b_lead", "m/s^2", 1.0, 5.0, "the driver's estimate of the leader's"),
        spec("v0", "m/s", 15.0, 40.0, "desired speed"),
        spec("tau", "s", 0.3, 1.5, "reaction time (the update period)"),
        spec("size", "m", 4.0, 10.0, "leader length plus standstill margin"),
    )

    def command(self, p: GippsParams, obs: Perception) -> Tensor:
        v = obs.v
        ratio = torch.clamp(v / p.v0, min=0.0)
        v_free = v + 2.5 * p.a * p.tau * (1.0 - ratio) * torch.sqrt(0.025 + ratio)
        root = (p.b * p.tau) ** 2 + p.b * (
            2.0 * (obs.spacing - p.size) - v * p.tau + obs.v_lead**2 / p.b_lead
        )
        v_safe = -p.b * p.tau + torch.sqrt(torch.clamp(root, min=0.0))
        target = torch.clamp(torch.minimum(v_free, v_safe), min=0.0)
        return (target - v) / p.tau


def leader_profiles(
    n_pairs: int,
    n_steps: int,
    dt: float = 0.1,
    *,
    seed: int = 0,
    cruise: tuple[float, float] = (10.0, 22.0),
    start: tuple[float, float] = (0.0, 0.0),
) -> tuple[Tensor, Tensor, Tensor]:
    """Leader position, speed and acceleration, ``(T, N)`` float64 each (T =
    ``n_steps``, N = ``n_pairs``).

    Speed = cruise + three random sinusoids (periods 8-40 s, amplitudes 0.5-2.5
    m/s) + two braking events (a 1.5-3 m/s^2 deceleration for 1-2.5 s, then
    recovery over three times as long), clamped at 0. Position is integrated with
    the trapezoidal rule.

    Args:
        cruise: range of the cruise speed [m/s].
        start: range of the leader's initial road position [m].

    Examples:
        >>> from torchcf.sim.synthetic import leader_profiles
        >>> x, v, a = leader_profiles(n_pairs=2, n_steps=100, dt=0.1, seed=0)
        >>> x.shape, x.dtype, bool((v >= 0).all())  # x [m], v [m/s], a [m/s^2]
        (torch.Size([100, 2]), torch.float64, True)
    """
    g = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float, *shape: int) -> Tensor:
        return low + (high - low) * torch.rand(*shape, generator=g, dtype=torch.float64)

    t = torch.arange(n_steps, dtype=torch.float64)[:, None] * dt  # (T, 1)
    speed = uniform(*cruise, 1, n_pairs).expand(n_steps, n_pairs).clone()
    for _ in range(3):
        period = uniform(8.0, 40.0, 1, n_pairs)
        amplitude = uniform(0.5, 2.5, 1, n_pairs)
        phase = uniform(0.0, 2 * math.pi, 1, n_pairs)
        speed += amplitude * torch.sin(2 * math.pi * t / period + phase)
    duration_total = n_steps * dt
    for _ in range(2):
        onset = uniform(0.15, 0.75, 1, n_pairs) * duration_total
        length = uniform(1.0, 2.5, 1, n_pairs)
        rate = uniform(1.5, 3.0, 1, n_pairs)
        # Speed drop ramps down over `length` s, recovers over 3x as long.
        down = torch.clamp((t - onset) / length, 0.0, 1.0)
        up = torch.clamp((t - onset - length) / (3.0 * length), 0.0, 1.0)
        speed -= rate * length * (down - up)
    speed = speed.clamp(min=0.0)
    acceleration = torch.gradient(speed, spacing=dt, dim=0)[0]
    position = uniform(*start, 1, n_pairs) + torch.cat(
        (
            torch.zeros(1, n_pairs, dtype=torch.float64),
            torch.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt, dim=0),
        )
    )
    return position, speed, acceleration


@dataclass(frozen=True)
class Scene:
    """Where synthetic pairs start, and what their set is called.

    Attributes:
        start: range of the leaders' initial road positions [m] (a spread
            puts the pairs on one road, as a road effect needs).
        initial_gap: range of the followers' initial time gap [s]: a follower
            starts at its leader's speed, ``gap * v + 8`` m behind it.
        name: the PairSet's name; None: the generator's own
            (``"synthetic"``, ``"heterogeneous"``).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import Scene, synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> road = Scene(start=(0.0, 500.0), name="one road")  # leaders 0-500 m
        >>> pairs = synthetic_pairs(get_model("idm"), idm, 2, n_steps=50, scene=road)
        >>> pairs.name, bool((pairs.x_lead[0] <= 500.0).all())
        ('one road', True)
    """

    start: tuple[float, float] = (0.0, 0.0)
    initial_gap: tuple[float, float] = (1.0, 2.0)
    name: str | None = None


def synthetic_pairs(
    model: CFModel,
    theta: Tensor | Sequence[float],
    n_pairs: int,
    n_steps: int = 500,
    dt: float = 0.1,
    *,
    seed: int = 0,
    noise: float = 0.0,
    scene: Scene = Scene(),
) -> PairSet:
    """Pairs whose followers are driven by ``model`` with parameters ``theta``.

    Args:
        model: the model object: a registry model, effects allowed
            (``get_model("idm+delay")``), or one outside the registry (e.g.
            :class:`Gipps`, or one wrapped by effects:
            ``AugmentedModel(Gipps(), [parse_effect("delay")])``); a name
            raises :class:`TypeError`.
        theta: ``(K,)`` one particle for every pair, or ``(N, K)`` (N = ``n_pairs``),
            one per pair.
        noise: standard deviation of white noise added to the recorded follower
            position [m] (speed and acceleration get ``noise / dt`` and
            ``noise / dt^2`` scaled by 0.1 and 0.01: measurement-like, small).
        scene: where the leaders and followers start, and the set's name
            (default ``"synthetic"``).

    Returns:
        A PairSet; ``notes`` record the generating model.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm+delay"), idm + [0.5], 3, n_steps=50)
        >>> pairs.n_steps, pairs.n_pairs, pairs.dt, pairs.name  # dt [s]
        (50, 3, 0.1, 'synthetic')
        >>> pairs.notes
        ('followers: idm+delay theta=[1.5, 2.0, 33.0, 1.2, 2.0, 4.0, 0.5]',)
    """
    cf_model = require_model(model, "synthetic_pairs")
    theta = torch.as_tensor(theta, dtype=torch.float64)
    if theta.ndim == 1:
        theta = theta[None].expand(n_pairs, -1)
    x_lead, v_lead, a_lead = leader_profiles(
        n_pairs, n_steps, dt, seed=seed, start=scene.start
    )
    g = torch.Generator().manual_seed(seed + 1)
    gap = _initial_gaps(scene, n_pairs, g)
    x_follow0 = x_lead[0] - gap * v_lead[0] - 8.0
    # A leader-only placeholder set: the follower's first row is its start state.
    seed_set = PairSet.from_arrays(
        (
            x_lead,
            v_lead,
            a_lead,
            x_follow0[None].expand(n_steps, -1),
            v_lead[0][None].expand(n_steps, -1),
            torch.zeros(n_steps, n_pairs, dtype=torch.float64),
        ),
        dt=dt,
    )
    out = simulate(
        cf_model,
        theta,
        seed_set,
        torch.arange(n_pairs),
        dtype=torch.float64,
        return_traj=True,
    )
    if not bool(out.valid.all()):
        raise ValueError(
            f"{cf_model.name}: some synthetic followers crash; change theta"
        )
    x, v, a = out.x, out.v, out.a
    if noise > 0:
        x = x + noise * torch.randn(x.shape, generator=g, dtype=torch.float64)
        v = v + 0.1 * noise / dt * torch.randn(x.shape, generator=g, dtype=x.dtype)
        a = a + 0.01 * noise / dt**2 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    return PairSet.from_arrays(
        (x_lead, v_lead, a_lead, x, v, a),
        dt=dt,
        name=scene.name if scene.name is not None else "synthetic",
        notes=(f"followers: {cf_model.name} theta={theta[0].tolist()}",),
    )


def _initial_gaps(scene: Scene, n: int, g: torch.Generator) -> Tensor:
    """(n,) followers' initial time gaps [s], uniform over the scene's range."""
    low, high = scene.initial_gap
    return low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)


# ------------------------------------------------------- drivers who differ
#: A plausible follower: its mean time gap (spacing minus the leader's length,
#: over its speed, where it moves faster than 2 m/s) lies in this range [s] ...
PLAUSIBLE_TIME_GAP = (0.5, 4.0)
#: ... its bumper-to-bumper gap never falls below this [m] ...
PLAUSIBLE_MIN_GAP = 1.0
#: ... and its acceleration stays within this bound [m/s^2]. A draw that is not
#: plausible is drawn again.
PLAUSIBLE_ACCELERATION = 6.0


class Drivers(NamedTuple):
    """Who drives each pair of :func:`heterogeneous_pairs`.

    Attributes:
        model: (N,) the generating model of each pair, planted effects included
            (``"idm+delay"``).
        theta: (N, K) float64 its parameters, in that model's order; NaN past its
            own K (K: the widest model's).

    Examples:
        >>> from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs
        >>> mixture = DriverMixture(["idm", "ovm"])
        >>> pairs, drivers = heterogeneous_pairs(mixture, n_pairs=3, n_steps=50)
        >>> drivers.model, drivers.theta.shape
        (('idm', 'ovm', 'idm'), torch.Size([3, 6]))
    """

    model: tuple[str, ...]
    theta: Tensor


@dataclass(frozen=True)
class DriverMixture:
    """Who may drive the pairs of :func:`heterogeneous_pairs`: a mixture of
    models in equal shares, each driver's parameters drawn over its model's
    box, and an effect planted in every driver.

    Attributes:
        models: the mixture's pool models (pair j: ``models[j % len(models)]``).
        effect: the planted effect's token (``"delay"``, ``"sync"``,
            ``"grade(start=0,end=1200,knots=7)"``); "": none.
        effect_values: (K_E,) the effect's values, the same in every driver.
        boxes: per model, the (K, 2) box its parameters are drawn over; a
            model not in it (or None): its prior.

    Examples:
        >>> from torchcf.sim.synthetic import DriverMixture
        >>> mixture = DriverMixture(["idm", "ovm"], effect="delay", effect_values=[0.5])
        >>> mixture.names  # a 0.5 s perception delay in every driver
        ['idm+delay', 'ovm+delay']
    """

    models: Sequence[str]
    effect: str = ""
    effect_values: Sequence[float] = ()
    boxes: Mapping[str, Tensor] | None = None

    @property
    def names(self) -> list[str]:
        """Each model's name with the effect (``"idm+delay"``)."""
        effect = self.effect
        return [f"{m}+{effect}" if effect else m for m in self.models]

    @property
    def variants(self) -> list[CFModel]:
        """Each driver's model with the effect, as an object: the mixture is
        described by names, and this is where they are parsed."""
        return [get_model(name) for name in self.names]


def heterogeneous_pairs(
    mixture: DriverMixture,
    n_pairs: int,
    n_steps: int = 500,
    dt: float = 0.1,
    *,
    seed: int = 0,
    noise: float = 0.0,
    lengths: tuple[float, float] = (1.0, 1.0),
    scene: Scene = Scene(),
) -> tuple[PairSet, Drivers]:
    """Pairs whose followers differ from one another, as measured drivers do.

    Pair j is driven by ``mixture.models[j % len(models)]`` (equal shares of a
    mixture), with its own parameters drawn uniformly over the model's box
    (``mixture.boxes``, by default its prior) and, when ``mixture.effect`` is
    given, that effect at ``mixture.effect_values`` (K_E,) in every driver: a
    behavioural effect of every driver, or a recording effect of the whole
    data set. A draw is kept only where it follows plausibly with the effect
    (a valid rollout, a mean time gap in :data:`PLAUSIBLE_TIME_GAP`, a gap of
    at least :data:`PLAUSIBLE_MIN_GAP`, an acceleration within
    :data:`PLAUSIBLE_ACCELERATION`); otherwise the pair's driver and leader
    are drawn again (so the drivers are the box's plausible part, not the
    whole box). Leaders as in :func:`leader_profiles`.

    Args:
        mixture: the drivers' models, boxes and planted effect.
        n_steps: T, steps of the longest pair.
        lengths: range of each pair's valid share of ``n_steps`` (ragged pairs,
            a prefix mask), drawn uniformly.
        noise: measurement noise as in :func:`synthetic_pairs` [m].
        scene: where the leaders and followers start (a spread of leader
            positions puts the pairs on one road, as a road effect needs),
            and the set's name (default ``"heterogeneous"``).

    Returns:
        the pairs, and who drives them (:class:`Drivers`).

    Raises:
        ValueError: no plausible driver in many draws (the box or the effect
            leaves none).

    Examples:
        >>> from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs
        >>> mixture = DriverMixture(["idm", "ovm"], effect="delay", effect_values=[0.5])
        >>> pairs, drivers = heterogeneous_pairs(
        ...     mixture, n_pairs=4, n_steps=50, lengths=(0.5, 1.0), seed=0
        ... )
        >>> pairs.n_pairs, pairs.name, drivers.model[:2]
        (4, 'heterogeneous', ('idm+delay', 'ovm+delay'))
        >>> bool((pairs.mask.sum(0) >= 25).all())  # ragged: each 25 to 50 steps
        True
    """
    models = mixture.models
    if not models:
        raise ValueError("heterogeneous_pairs: give at least one model")
    g = torch.Generator().manual_seed(seed)
    names = mixture.names
    width = max(variant.n_params for variant in mixture.variants)
    want = [len(range(i, n_pairs, len(models))) for i in range(len(models))]
    found: list[list[tuple[Tensor, Tensor]]] = [[] for _ in models]
    for _ in range(50):  # batches of candidates, until every model has its share
        short = [i for i in range(len(models)) if len(found[i]) < want[i]]
        if not short:
            break
        batch = max(16, 2 * max(want[i] - len(found[i]) for i in short))
        drawn = _plausible_batch(mixture, scene, batch, n_steps, dt, g)
        for i, theta, series in drawn:
            found[i].append((theta, series))
    short = [names[i] for i in range(len(models)) if len(found[i]) < want[i]]
    if short:
        raise ValueError(
            f"heterogeneous_pairs: too few plausible drivers of {', '.join(short)} "
            "in 50 batches; widen the box or lower the effect"
        )
    order = [i % len(models) for i in range(n_pairs)]  # pair j: model j % M
    taken = [0] * len(models)
    chosen = []
    for i in order:
        theta, series = found[i][taken[i]]
        taken[i] += 1
        chosen.append((i, theta, series))
    series = torch.stack([r[2] for r in chosen], dim=2)  # (6, T, N)
    theta = torch.full((n_pairs, width), math.nan, dtype=torch.float64)
    for j, r in enumerate(chosen):
        theta[j, : r[1].numel()] = r[1]
    x_lead, v_lead, a_lead, x, v, a = series
    if noise > 0:
        x = x + noise * torch.randn(x.shape, generator=g, dtype=torch.float64)
        v = v + 0.1 * noise / dt * torch.randn(x.shape, generator=g, dtype=x.dtype)
        a = a + 0.01 * noise / dt**2 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    share = lengths[0] + (lengths[1] - lengths[0]) * torch.rand(
        n_pairs, generator=g, dtype=torch.float64
    )
    valid = torch.clamp((share * n_steps).round().long(), 2, n_steps)
    mask = torch.arange(n_steps)[:, None] < valid[None, :]
    drivers = Drivers(tuple(names[r[0]] for r in chosen), theta)
    mix = ", ".join(dict.fromkeys(drivers.model))
    name = scene.name if scene.name is not None else "heterogeneous"
    pairs = PairSet.from_arrays(
        (x_lead, v_lead, a_lead, x, v, a), dt=dt, mask=mask, name=name,
        notes=(f"followers: {mix}, one driver per pair",),
    )  # fmt: skip
    return pairs, drivers


def _plausible_batch(
    mixture: DriverMixture,
    scene: Scene,
    batch: int,
    n_steps: int,
    dt: float,
    g: torch.Generator,
) -> list[tuple[int, Tensor, Tensor]]:
    """One batch of candidate drivers (each model's share of ``batch``) and
    their leaders; the plausible ones, in the order drawn, as ``(model
    position, theta, series (6, T): leader x, v, a, follower x, v, a)``."""
    models, variants, boxes = mixture.models, mixture.variants, mixture.boxes
    leader_seed = int(torch.randint(0, 2**62, (1,), generator=g))
    x_lead, v_lead, a_lead = leader_profiles(
        batch, n_steps, dt, seed=leader_seed, start=scene.start
    )
    gap = _initial_gaps(scene, batch, g)
    x0 = x_lead[0] - gap * v_lead[0] - 8.0
    first = PairSet.from_arrays(
        (x_lead, v_lead, a_lead, x0[None].expand(n_steps, -1),
         v_lead[0][None].expand(n_steps, -1),
         torch.zeros(n_steps, batch, dtype=torch.float64)),
        dt=dt,
    )  # fmt: skip
    which = torch.arange(batch) % len(models)
    kept = []
    plant = torch.as_tensor(list(mixture.effect_values), dtype=torch.float64)
    for i, (model, variant) in enumerate(zip(models, variants, strict=True)):
        index = (which == i).nonzero().squeeze(1)
        box = (boxes or {}).get(model)
        if box is None:
            box = variant.pool_model.prior_bounds(torch.float64)
        u = torch.rand(index.numel(), box.shape[0], generator=g, dtype=torch.float64)
        own = box[:, 0] + u * (box[:, 1] - box[:, 0])
        theta = torch.cat((own, plant.expand(index.numel(), -1)), dim=1)
        out = simulate(
            variant, theta, first, index, dtype=torch.float64, return_traj=True
        )
        ok = out.valid & _plausible(out, x_lead[:, index], first.leader_length)
        for j in ok.nonzero().squeeze(1).tolist():
            p = int(index[j])
            series = torch.stack(
                (x_lead[:, p], v_lead[:, p], a_lead[:, p],
                 out.x[:, j], out.v[:, j], out.a[:, j])
            )  # fmt: skip
            kept.append((p, i, theta[j], series))
    return [row[1:] for row in sorted(kept, key=lambda row: row[0])]


def _plausible(out, x_lead: Tensor, leader_length: float) -> Tensor:
    """(P,) bool: the simulated followers (T, P) that follow plausibly (the
    bounds of :func:`heterogeneous_pairs`)."""
    gap = x_lead - out.x - leader_length  # (T, P) bumper to bumper [m]
    moving = out.v > 2.0
    headway = torch.where(moving, gap / out.v.clamp(min=2.0), 0.0)
    count = moving.sum(0).clamp(min=1)
    mean_headway = headway.sum(0) / count
    low, high = PLAUSIBLE_TIME_GAP
    return (
        (gap.min(0).values >= PLAUSIBLE_MIN_GAP)
        & (mean_headway >= low)
        & (mean_headway <= high)
        & (out.a.abs().max(0).values <= PLAUSIBLE_ACCELERATION)
        & (moving.sum(0) > 0)
    )
