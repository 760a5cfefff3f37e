"""The settings of the ABC methods beside rejection (``abc.smc`` and
``abc.amortised`` of :class:`~torchcf.config.schema.ABCConfig`): the sequential
refinement (:mod:`torchcf.abc.smc`) and the amortised estimator
(:mod:`torchcf.amortised`), its network and its optional refinement."""

from __future__ import annotations

from pydantic import BaseModel, Field

from torchcf.config.fields import STRICT, NonNegativeFloat

__all__ = ["AmortisedConfig", "AmortisedNetworkConfig", "RefineConfig", "SMCConfig"]


class SMCConfig(BaseModel):
    """The sequential refinement (``abc.method = "smc"``, :mod:`torchcf.abc.smc`).

    Examples:
        >>> from torchcf.config import SMCConfig
        >>> smc = SMCConfig(rounds=4)
        >>> smc.population, smc.rounds, smc.prior_fraction
        (50, 4, 0.25)
    """

    model_config = STRICT

    population: int = Field(
        50,
        gt=1,
        description="Particles per training pair carried from round to round.",
    )
    rounds: int = Field(
        12, gt=0, description="Refinement rounds after the prior round."
    )
    prior_fraction: float = Field(
        0.25,
        gt=0,
        lt=1,
        description="Share of abc.n_particles drawn from the prior (round 0).",
    )
    quantile: float = Field(
        0.5,
        gt=0,
        le=1,
        description=(
            "Threshold schedule: a round accepts the proposals scoring at most this "
            "quantile of the previous population's scores."
        ),
    )


class AmortisedNetworkConfig(BaseModel):
    """The amortised estimator's size (:class:`torchcf.amortised.
    EstimatorSettings`): the trajectory encoder, the model head and the flows.

    Examples:
        >>> from torchcf.config import AmortisedNetworkConfig
        >>> network = AmortisedNetworkConfig(encoder_width=16, embedding=32)
        >>> network.encoder_depth, network.embedding, network.bins
        (4, 32, 8)
    """

    model_config = STRICT

    encoder_width: int = Field(
        48, gt=0, description="Feature maps of every convolution of the encoder."
    )
    encoder_depth: int = Field(
        4,
        gt=0,
        description=(
            "Convolutions of the encoder; the first three (or all, if fewer) "
            "halve the time axis."
        ),
    )
    embedding: int = Field(
        64,
        gt=0,
        description="Width of the encoder's output, the series' summary (E).",
    )
    head_width: int = Field(64, gt=0, description="Hidden units of the model head.")
    transforms: int = Field(
        3, gt=0, description="Spline coupling layers of each model's flow."
    )
    flow_width: int = Field(
        64,
        gt=0,
        description="Hidden units of each coupling layer's two-layer conditioner.",
    )
    bins: int = Field(8, gt=1, description="Bins of each spline.")


class RefineConfig(BaseModel):
    """The optional refinement of an amortised run: per model and training
    pair, a short SMC (:mod:`torchcf.abc.smc`) whose first population is the
    pair's best amortised samples (:mod:`torchcf.calibration.refinement`).

    Examples:
        >>> from torchcf.config import RefineConfig
        >>> refine = RefineConfig(rounds=3)
        >>> refine.rounds * refine.per_pair  # simulations per pair and model
        150
    """

    model_config = STRICT

    rounds: int = Field(
        0,
        ge=0,
        description=(
            "SMC rounds after the amortised samples; 0: no refinement. A pair "
            "receives rounds * per_pair simulations per model."
        ),
    )
    per_pair: int = Field(
        50, gt=0, description="Proposals per training pair, model and round."
    )
    population: int = Field(
        20,
        gt=1,
        description=(
            "Particles per training pair carried from round to round; the first "
            "population is the pair's best amortised samples of the model."
        ),
    )
    quantile: float = Field(
        0.5,
        gt=0,
        le=1,
        description=(
            "Threshold schedule: a round accepts the proposals scoring at most "
            "this quantile of the previous population's scores."
        ),
    )


class AmortisedConfig(BaseModel):
    """The amortised method (``abc.method = "amortised"``,
    :mod:`torchcf.amortised`): one estimator of (model, parameters) given a
    pair's series, trained on simulations behind the training pairs' leaders,
    whose samples for every training pair are scored and kept as rejection's
    particles are.

    Examples:
        >>> from torchcf.config import AmortisedConfig
        >>> amortised = AmortisedConfig(samples_per_pair=100, refine={"rounds": 2})
        >>> amortised.refine.rounds, amortised.network.bins, amortised.noise
        (2, 8, None)
    """

    model_config = STRICT

    samples_per_pair: int = Field(
        200,
        gt=0,
        description=(
            "Samples of (model, parameters) drawn per training pair from its "
            "amortised posterior; each is simulated once on its pair, scored with "
            "the run's distance and offered to its model's top-N buffer, as a "
            "rejection particle is."
        ),
    )
    window_steps: int = Field(
        300,
        ge=2,
        description=(
            "Steps of the leader windows the estimator is trained on (300: 30 s "
            "at dt 0.1 s); a training pair shorter than it lends no leader."
        ),
    )
    noise: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] | None = Field(
        None,
        description=(
            "Standard deviations of the white noise added to the simulated "
            "followers: position [m], speed [m/s], acceleration [m/s^2]; "
            "None: measured from the training pairs' followers (from their "
            "second differences)."
        ),
    )
    estimator: str | None = Field(
        None,
        description=(
            "A trained estimator to use instead of training one: the "
            "amortised.pt of an earlier amortised run, or that run's directory, "
            "whose models, prior boxes and network are this config's; its "
            "training settings are then not used. It is copied into the run "
            "directory. None: train one."
        ),
    )
    simulations_per_epoch: int = Field(
        20_000,
        gt=0,
        description="Simulations drawn for an epoch's training set.",
    )
    reuse: int = Field(
        1,
        gt=0,
        description=(
            "Epochs each simulated set serves: 1 draws fresh simulations every "
            "epoch; max_epochs trains on one fixed set."
        ),
    )
    max_epochs: int = Field(40, gt=0, description="Training epochs at most.")
    max_seconds: float | None = Field(
        None,
        gt=0,
        description=(
            "Training time at most [s] (the epoch under way ends early); None: "
            "no limit. A limit makes the estimator depend on the machine's speed; "
            "a resumed run may change it."
        ),
    )
    validation_simulations: int = Field(
        4_000,
        gt=0,
        description=(
            "Simulations of the validation set, whose loss stops the training "
            "early and picks the weights kept."
        ),
    )
    batch_size: int = Field(256, gt=0, description="Simulations per gradient step.")
    learning_rate: float = Field(1e-3, gt=0, description="Adam's learning rate.")
    patience: int = Field(
        5,
        gt=0,
        description="Epochs without a lower validation loss before stopping.",
    )
    network: AmortisedNetworkConfig = Field(
        default_factory=AmortisedNetworkConfig,
        description="The estimator's size.",
    )
    refine: RefineConfig = Field(
        default_factory=RefineConfig,
        description=(
            "A short SMC per training pair and model started from the amortised "
            "samples (off unless refine.rounds > 0)."
        ),
    )
