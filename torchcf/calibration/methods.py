"""What a calibration is asked to do: its sampler (:data:`Method`) and how its
hybrid is read from the buffers (:class:`SelectionRule`).

Three samplers, each a frozen record with its own budget:

- :class:`Rejection`: ``n_particles`` prior draws per model, every one
  simulated on (paired layout) its own training pair or (full layout) every
  pair, the best kept per pair (:func:`torchcf.abc.run_rejection`);
- :class:`SMC`: the same budget spent as a prior round and refinement rounds
  per pair (:func:`torchcf.abc.run_smc`, settings :class:`~torchcf.abc.
  SMCSettings`);
- :class:`Amortised`: an estimator of (model, parameters) given a pair
  trained on simulations, ``samples_per_pair`` of its samples scored per
  training pair (:mod:`torchcf.amortised`), optionally refined per pair
  (:class:`Refinement`).

Units: SI throughout (m, s, m/s); particle counts are per model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..abc.smc import Budget, SMCSettings
from ..amortised import EstimatorSettings, NoiseLevels, TrainingSettings


@dataclass(frozen=True)
class Rejection:
    """ABC rejection (the paper's sampler).

    Attributes:
        n_particles: prior draws per model.

    Examples:
        >>> Rejection(n_particles=20_000)
        Rejection(n_particles=20000)
    """

    n_particles: int = 1_000_000

    def __post_init__(self) -> None:
        _at_least_one("n_particles", self.n_particles)


@dataclass(frozen=True)
class SMC:
    """Sequential Monte Carlo ABC per training pair.

    Attributes:
        n_particles: simulations per model, the prior round's and the
            refinement rounds' together.
        settings: population, rounds, quantile and kernel.

    Examples:
        >>> SMC(n_particles=50_000, settings=SMCSettings(population=20, rounds=4))
        SMC(n_particles=50000, settings=SMCSettings(population=20, rounds=4, ...))
    """

    n_particles: int = 1_000_000
    settings: SMCSettings = field(default_factory=SMCSettings)

    def __post_init__(self) -> None:
        _at_least_one("n_particles", self.n_particles)


@dataclass(frozen=True)
class Refinement:
    """An amortised calibration's refinement: its samples are round 0 of a
    short SMC per training pair (:mod:`torchcf.calibration.refinement`).

    Attributes:
        rounds: SMC rounds after the samples.
        per_pair: proposals per pair, model and round.
        population: per pair, the best samples of a model that form round 0.
        quantile: the next threshold is this quantile of a population's scores.

    Examples:
        >>> Refinement(rounds=2, per_pair=32).budget(samples=1_000, n_pairs=10).total
        1640
    """

    rounds: int = 3
    per_pair: int = 64
    population: int = 20
    quantile: float = 0.5

    def __post_init__(self) -> None:
        for name in ("rounds", "per_pair", "population"):
            _at_least_one(name, getattr(self, name))

    @property
    def settings(self) -> SMCSettings:
        """The SMC engine's settings of this refinement."""
        return SMCSettings(
            population=self.population, rounds=self.rounds, quantile=self.quantile
        )

    def budget(self, samples: int, n_pairs: int) -> Budget:
        """A model's budget after its ``samples`` amortised samples on
        ``n_pairs`` pairs: particle indices ``0 .. samples - 1`` are the
        samples, round ``t``'s proposals follow."""
        return Budget(samples, self.per_pair, self.rounds, n_pairs)


@dataclass(frozen=True)
class Amortised:
    """Amortised inference: one estimator of (model, parameters) given a pair,
    trained on simulations of the calibration's models over their prior boxes
    behind the pairs' leaders, then ``samples_per_pair`` samples per pair
    scored into the buffers as rejection's particles are.

    Attributes:
        samples_per_pair: samples drawn per training pair, over all models.
        window_steps: steps of the leader windows the estimator trains on.
        noise: measurement noise added to the simulated followers; None: the
            pairs' own roughness (:meth:`NoiseLevels.of_pairs
            <torchcf.amortised.NoiseLevels.of_pairs>`).
        training: the training's budget and optimiser (its ``seed`` is
            replaced by the calibration's).
        network: the estimator's size.
        refine: the per-pair refinement of the samples; None: none.
        estimator: a finished estimator to reuse instead of training one: a
            training checkpoint (``amortised.pt``) or a run directory holding
            one, of the same models, boxes and network.
        compile: compile the flows' sampling: ``"on"``, ``"off"`` or
            ``"auto"`` (from :data:`~torchcf.calibration.estimator_samples.
            COMPILE_MIN_SAMPLES` samples on, where a C++ compiler is there).

    Examples:
        >>> Amortised(samples_per_pair=200, window_steps=100).refine is None
        True
    """

    samples_per_pair: int = 2_000
    window_steps: int = 300
    noise: NoiseLevels | None = None
    training: TrainingSettings = field(default_factory=TrainingSettings)
    network: EstimatorSettings = field(default_factory=EstimatorSettings)
    refine: Refinement | None = None
    estimator: Path | None = None
    compile: str = "auto"

    def __post_init__(self) -> None:
        _at_least_one("samples_per_pair", self.samples_per_pair)
        _at_least_one("window_steps", self.window_steps)
        if self.compile not in ("auto", "on", "off"):
            raise ValueError(
                f"compile must be 'auto', 'on' or 'off', got {self.compile!r}"
            )


#: A calibration's sampler.
Method = Rejection | SMC | Amortised


@dataclass(frozen=True)
class SelectionRule:
    """How the hybrid is read from the per-pair buffers
    (:func:`torchcf.abc.select`).

    Attributes:
        top_n: particles kept per pair and model (the paper's N).
        sensitivity_n: other N whose shares are reported from the same
            buffers.
        mode: ``"per_pair"`` (the paper's: per pair the best N over all
            models) or ``"global"``.
        global_size: the hybrid's size under ``"global"``; None: N per pair.

    Examples:
        >>> SelectionRule(top_n=5, sensitivity_n=(10, 15)).buffer_size
        15
    """

    top_n: int = 5
    sensitivity_n: tuple[int, ...] = (5, 10, 15)
    mode: str = "per_pair"
    global_size: int | None = None

    def __post_init__(self) -> None:
        _at_least_one("top_n", self.top_n)
        for n in self.sensitivity_n:
            _at_least_one("sensitivity_n", n)
        if self.mode not in ("per_pair", "global"):
            raise ValueError(f"mode must be 'per_pair' or 'global', got {self.mode!r}")
        if self.global_size is not None and self.mode != "global":
            raise ValueError("global_size only applies with mode='global'")

    @property
    def buffer_size(self) -> int:
        """Slots kept per pair and model: the largest N asked for."""
        return max(self.top_n, *self.sensitivity_n)


def weighted(method: Method) -> SMCSettings | None:
    """The SMC settings under which a model's buffer carries the ``log r``
    column beside its parameters (SMC's; an amortised calibration's
    refinement's); None: the buffers hold the parameters alone."""
    if isinstance(method, SMC):
        return method.settings
    if isinstance(method, Amortised) and method.refine is not None:
        return method.refine.settings
    return None


def method_name(method: Method) -> str:
    """The sampler's name as configs and records spell it."""
    return {Rejection: "rejection", SMC: "smc", Amortised: "amortised"}[type(method)]


def _at_least_one(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


__all__ = [
    "SMC",
    "Amortised",
    "Method",
    "Refinement",
    "Rejection",
    "SelectionRule",
    "method_name",
    "weighted",
]
