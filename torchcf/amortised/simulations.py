"""The amortised estimator's training set: followers simulated by torchcf's own
rollout behind the data set's own leaders.

One simulated example (``J`` of them in a set):

1. a model ``m`` drawn uniformly among the space's M models, and its parameters
   uniformly over its prior box (:class:`~torchcf.amortised.space.ParameterSpace`);
2. a *leader window*: a training pair drawn uniformly among those at least
   ``window_steps`` valid steps long, and a start drawn uniformly among the
   windows that fit in its valid steps. Shorter pairs are skipped, not padded:
   every example then has one length, and a window holds only observed steps;
3. the follower simulated over the window by :func:`torchcf.sim.rollout.simulate`
   (SPEC section 2, paired layout: many examples in one batch), from the
   observed follower's state at the window's start, as ABC's rollouts start;
4. white measurement noise added to the simulated follower's position, speed
   and acceleration (:class:`NoiseLevels`);
5. the encoder's input of the window (:func:`~torchcf.amortised.features.
   channel_features`): ``(C, T_w)`` for ``T_w = window_steps``.

An invalid rollout (a non-finite value or a collision, SPEC section 2) is
discarded and counted: the estimator learns the prior restricted to valid
rollouts, as ABC can never select an invalid particle. The models are drawn in
equal shares before the discard, as ABC streams the same number of particles
per model.

Reproducible and bounded in memory: a set is drawn in chunks of
``chunk_size`` examples, chunk ``c`` of set ``name`` from its own generator
seeded by a hash of ``(seed, name, c)`` (:func:`torchcf.abc.streams.block_seed`).
A set is a pure function of ``(seed, name, n, settings)``, whichever sets were
drawn before it; ``chunk_size`` is part of that definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from ..abc.streams import block_seed
from ..data import PairSet
from ..sim.rollout import Execution, simulate
from .features import channel_features
from .space import ParameterSpace


@dataclass(frozen=True)
class NoiseLevels:
    """Standard deviations of the white noise added to a simulated follower,
    as measurement noise of the data.

    The defaults are the roughness of the paper's CAR MODEL I and II followers
    (:meth:`of_pairs`, rounded): smooth positions and speeds, noisy
    accelerations.

    Attributes:
        position: [m].
        speed: [m/s].
        acceleration: [m/s^2].

    Examples:
        >>> NoiseLevels()
        NoiseLevels(position=0.005, speed=0.03, acceleration=1.0)
        >>> NoiseLevels(position=0.0, speed=0.0, acceleration=0.0)  # noise-free
        NoiseLevels(position=0.0, speed=0.0, acceleration=0.0)
    """

    position: float = 0.005
    speed: float = 0.03
    acceleration: float = 1.0

    def __post_init__(self) -> None:
        for name in ("position", "speed", "acceleration"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"noise {name} must be finite and >= 0, got {value}")

    @classmethod
    def of_pairs(cls, pairs: PairSet) -> NoiseLevels:
        """The white-noise level of each follower series of ``pairs``, from its
        second differences: for a smooth signal plus white noise of standard
        deviation ``s``, ``x(t+1) - 2 x(t) + x(t-1)`` has standard deviation
        ``s sqrt(6)`` (the signal's own part is of order ``dt^2``). Over the
        steps whose three points are valid."""
        valid = pairs.mask[2:] & pairs.mask[1:-1] & pairs.mask[:-2]  # (T - 2, N)
        levels = []
        for series in (pairs.x_follow, pairs.v_follow, pairs.a_follow):
            second = series[2:] - 2 * series[1:-1] + series[:-2]
            values = second[valid].to(torch.float64)
            std = float(values.std()) if values.numel() > 1 else 0.0
            levels.append(std / math.sqrt(6.0))
        return cls(*levels)


@dataclass(frozen=True)
class SimulationSettings:
    """How the training examples are simulated.

    Attributes:
        window_steps: T_w, steps of a leader window (300: 30 s at ``dt`` 0.1 s).
        noise: the measurement noise added to the follower.
        chunk_size: examples drawn and simulated together (memory: a chunk's
            trajectories and features, ``chunk_size x C x T_w`` float32); part
            of a set's definition.
        execution: how the rollouts run (device, compilation; the rollout's
            chunks), :class:`torchcf.sim.rollout.Execution`.

    Examples:
        >>> settings = SimulationSettings(window_steps=100, chunk_size=256)  # 10 s
        >>> settings.window_steps, settings.noise.acceleration
        (100, 1.0)
    """

    window_steps: int = 300
    noise: NoiseLevels = field(default_factory=NoiseLevels)
    chunk_size: int = 2048
    execution: Execution = Execution(compile="off")

    def __post_init__(self) -> None:
        if self.window_steps < 2:
            raise ValueError(f"window_steps must be >= 2, got {self.window_steps}")
        if self.chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {self.chunk_size}")


class SimulatedSet(NamedTuple):
    """Simulated examples (their valid ones) and how many were drawn.

    Attributes:
        features: (J, C, T_w) float32, the encoder's input.
        model: (J,) int64, the model's position in the space.
        unit: (J, K) float64 unit-cube coordinates of the parameters
            (:mod:`~torchcf.amortised.space`), NaN past the model's own K_m.
        drawn: (M,) int64 examples drawn per model, valid or not.
        invalid: (M,) int64 examples discarded per model (invalid rollouts).

    Examples:
        >>> import torch
        >>> one = SimulatedSet(torch.zeros(2, 5, 30), torch.tensor([0, 1]),
        ...                    torch.full((2, 6), 0.5, dtype=torch.float64),
        ...                    drawn=torch.tensor([1, 2]), invalid=torch.tensor([0, 1]))
        >>> both = SimulatedSet.concat([one, one])
        >>> len(both), both.n_drawn, both.n_invalid
        (4, 6, 2)
    """

    features: Tensor
    model: Tensor
    unit: Tensor
    drawn: Tensor
    invalid: Tensor

    def __len__(self) -> int:
        return self.model.shape[0]

    @property
    def n_drawn(self) -> int:
        """Examples drawn (simulations run), valid or not."""
        return int(self.drawn.sum())

    @property
    def n_invalid(self) -> int:
        """Examples discarded."""
        return int(self.invalid.sum())

    def theta(self, space: ParameterSpace) -> Tensor:
        """(J, K) float64 parameters [SI], NaN past each model's own K_m."""
        theta = torch.full_like(self.unit, math.nan)
        for m in range(space.n_models):
            rows = (self.model == m).nonzero().squeeze(1)
            k = space.n_params[m]
            theta[rows, :k] = space.to_theta(m, self.unit[rows, :k])
        return theta

    @classmethod
    def concat(cls, sets: list[SimulatedSet]) -> SimulatedSet:
        """The examples of ``sets`` one after the other; counts summed."""
        return cls(
            features=torch.cat([s.features for s in sets]),
            model=torch.cat([s.model for s in sets]),
            unit=torch.cat([s.unit for s in sets]),
            drawn=torch.stack([s.drawn for s in sets]).sum(0),
            invalid=torch.stack([s.invalid for s in sets]).sum(0),
        )


class TrainingSimulator:
    """Draws training sets of a space's models behind a pair set's leaders.

    Args:
        space: the models and their prior boxes.
        pairs: the training pairs whose leaders (and followers' starting states)
            the examples replay.
        settings: the window, noise and chunks.
        seed: the seed every set is a function of.

    Raises:
        ValueError: no pair is ``window_steps`` valid steps long.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> from torchcf.amortised import ParameterSpace
        >>> idm = get_model("idm")
        >>> pairs = synthetic_pairs(idm, [1.5, 2.0, 33.0, 1.2, 2.0, 4.0], 4, n_steps=50)
        >>> space = ParameterSpace([idm, get_model("ovm")])
        >>> settings = SimulationSettings(window_steps=40)  # 4 s windows
        >>> examples = TrainingSimulator(space, pairs, settings).draw("set-0", 32)
        >>> examples.features.shape[1:], examples.n_drawn  # (C, T_w), drawn
        (torch.Size([5, 40]), 32)
    """

    def __init__(
        self,
        space: ParameterSpace,
        pairs: PairSet,
        settings: SimulationSettings = SimulationSettings(),
        seed: int = 0,
    ) -> None:
        window = settings.window_steps
        lengths = pairs.lengths.cpu()
        self.eligible = (lengths >= window).nonzero().squeeze(1)  # (N',)
        if not self.eligible.numel():
            raise ValueError(
                f"no training pair has {window} valid steps (the longest has "
                f"{int(lengths.max())}); lower window_steps"
            )
        self.space = space
        self.pairs = pairs
        self.settings = settings
        self.seed = int(seed)
        self._lengths = lengths

    def draw(self, name: str, n: int) -> SimulatedSet:
        """Set ``name`` of ``n`` drawn examples (its valid ones kept).

        Args:
            name: the set's name (the training's ``"validation"`` and
                ``"set-0"``, ``"set-1"``, ...): enters the seed of its chunks.
            n: examples drawn.
        """
        if n < 1:
            raise ValueError(f"draw at least one example, got {n}")
        size = self.settings.chunk_size
        chunks = [
            self.draw_chunk(name, c, min(size, n - c * size))
            for c in range(math.ceil(n / size))
        ]
        return SimulatedSet.concat(chunks)

    def draw_chunk(self, name: str, chunk: int, n: int) -> SimulatedSet:
        """Chunk ``chunk`` of set ``name``: its first ``n`` examples (at most
        ``chunk_size``); the module docstring's steps 1-5."""
        space, window = self.space, self.settings.window_steps
        generator = torch.Generator().manual_seed(
            block_seed(self.seed, f"amortised/{name}", chunk)
        )
        # Every draw of the whole chunk first, in a fixed order: a chunk's
        # first n examples are the same whatever n.
        size = self.settings.chunk_size
        model = torch.randint(space.n_models, (size,), generator=generator)[:n]
        unit = torch.rand(size, space.width, generator=generator, dtype=torch.float64)
        unit = unit[:n]
        pick = torch.randint(self.eligible.numel(), (size,), generator=generator)
        pair = self.eligible[pick[:n]]
        slack = (self._lengths[pair] - window + 1).to(torch.float64)
        offset = torch.rand(size, generator=generator, dtype=torch.float64)[:n]
        start = (offset * slack).long().clamp(max=slack.long() - 1)
        noise = torch.randn(3, window, size, generator=generator)[:, :, :n]
        windows = self._windows(pair, start)
        follower = [torch.empty(window, n, dtype=torch.float32) for _ in range(3)]
        valid = torch.zeros(n, dtype=torch.bool)
        drawn = torch.zeros(space.n_models, dtype=torch.int64)
        for m, cf_model in enumerate(space.models):
            rows = (model == m).nonzero().squeeze(1)
            drawn[m] = rows.numel()
            if not rows.numel():
                continue
            k = space.n_params[m]
            unit[rows, k:] = math.nan
            theta = space.to_theta(m, unit[rows, :k]).to(torch.float32)
            out = simulate(
                cf_model,
                theta,
                windows,
                rows,
                dtype=torch.float32,
                return_traj=True,
                execution=self.settings.execution,
            )
            for series, simulated in zip(follower, (out.x, out.v, out.a), strict=True):
                series[:, rows] = simulated.to(series.device)
            valid[rows] = out.valid.cpu()
        invalid = torch.bincount(model[~valid], minlength=space.n_models)
        levels = self.settings.noise
        noisy = tuple(
            series + level * draws
            for series, level, draws in zip(
                follower,
                (levels.position, levels.speed, levels.acceleration),
                noise,
                strict=True,
            )
        )
        # Invalid rollouts may hold inf or NaN: dropped before the features.
        keep = valid.nonzero().squeeze(1)
        features = channel_features(
            windows.x_lead[:, keep],
            windows.v_lead[:, keep],
            windows.a_lead[:, keep],
            tuple(series[:, keep] for series in noisy),
        )
        return SimulatedSet(features, model[keep], unit[keep], drawn, invalid)

    def _windows(self, pair: Tensor, start: Tensor) -> PairSet:
        """The leader windows, as a pair set of ``len(pair)`` pairs of T_w
        steps: column j is pair ``pair[j]`` from step ``start[j]`` (its
        follower's first row is the simulation's starting state)."""
        steps = torch.arange(self.settings.window_steps)[:, None]  # (T_w, 1)
        rows = (start[None, :] + steps).to(self.pairs.device)  # (T_w, J)
        columns = pair[None, :].to(self.pairs.device)
        picked = {f: t[rows, columns] for f, t in self.pairs.series().items()}
        return PairSet(
            **picked,
            mask=torch.ones_like(rows, dtype=torch.bool),
            dt=self.pairs.dt,
            leader_length=self.pairs.leader_length,
            name=f"{self.pairs.name} windows",
        )


__all__ = [
    "NoiseLevels",
    "SimulatedSet",
    "SimulationSettings",
    "TrainingSimulator",
]
