"""The configuration of a training run: ``python -m torchcf.train CONFIG``.

A run is described by one JSON object, validated by :class:`TrainConfig`::

    {
      "data": {"name": "car-model-2"},
      "models": ["idm", {"name": "hl", "prior": {"tau": [0.1, 1.0]}}],
      "abc": {"n_particles": 200000, "top_n": 5},
      "device": "cuda"
    }

Every section rejects unknown keys, so a misspelled or misplaced key fails at load
time instead of being silently ignored. Reading a file, the command-line overrides
(``--set abc.n_particles=200000``) and the fingerprint of a run's settings live in
:mod:`torchcf.config.loading` (``load_config``, ``config_hash``,
``resolved_json``); every problem is a :class:`ConfigError` with a one-line
message that names the key, e.g. ``abc.n_particles: must be > 0, got -5``. The
``--set`` syntax lives in :mod:`torchcf.config.overrides`, the one-line messages
in :mod:`torchcf.config.messages`.

Command line (:mod:`torchcf.config.__main__`)::

    python -m torchcf.config --schema                  # the JSON schema
    python -m torchcf.config CONFIG [--set k=v ...]    # resolved config and hash
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import torch
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from torchcf.config.messages import ConfigError
from torchcf.config.raw import RawSource
from torchcf.data.reader import UNITS, unit_factor
from torchcf.data.registry import DATASETS
from torchcf.models import EFFECTS, MODELS, CFModel, UnknownModelError, get_model
from torchcf.models.effects import parse_effect
from torchcf.system.files import JSON

__all__ = [
    "ABCConfig",
    "AmortisedConfig",
    "AmortisedNetworkConfig",
    "ConfigError",
    "DataConfig",
    "DiagnoseConfig",
    "EvalConfig",
    "ModelSpec",
    "PlausibilityConfig",
    "RefineConfig",
    "SMCConfig",
    "TrainConfig",
]


# Shared by every section: unknown keys are errors, values are immutable after
# validation, and NaN / Infinity (which Python's json accepts) never pass.
_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

_PositiveInt = Annotated[int, Field(gt=0)]
_NonNegativeFloat = Annotated[float, Field(ge=0)]


# --------------------------------------------------------------------- sections
class DataConfig(BaseModel):
    """Which observed pairs to train and test on (:func:`torchcf.config.load_split`)."""

    model_config = _STRICT

    name: str | None = Field(
        None,
        description=(
            f"Registered data set: one of {', '.join(DATASETS)}. "
            "Exactly one of name and path."
        ),
    )
    path: str | None = Field(
        None,
        min_length=1,
        description=(
            "Folder in the six-CSV layout (with Trajectory/ and Testing/ for "
            "split='dataset'). Exactly one of name and path."
        ),
    )
    raw: RawSource | None = Field(
        None,
        description=(
            "A raw trajectory file or folder, extracted into pairs when the run "
            "starts (torchcf.data.extract; the same settings as python -m "
            "torchcf.data extract). Exactly one of name, path and raw."
        ),
    )
    root: str | None = Field(
        None,
        min_length=1,
        description=(
            "Data root holding HDV/ and AV/, for a name only; None looks in "
            "$TORCHCF_DATA, then the cache, then downloads."
        ),
    )
    units: str | None = Field(
        None,
        description=(
            f"Unit system of the files: one of {', '.join(UNITS)}; None takes the "
            "registry's (name) or meta.json's (path), else 'm'."
        ),
    )
    dt: float | None = Field(
        None,
        gt=0,
        description="Sampling interval [s]; None takes the registry's or meta.json's.",
    )
    leader_length: float | None = Field(
        None,
        gt=0,
        description="Leader vehicle length [m]; None takes the registry's or 5.0.",
    )
    drop_duplicates: bool = Field(
        True,
        description=(
            "Keep only the first copy of identical pairs, and drop test pairs "
            "that duplicate a training pair."
        ),
    )
    min_spacing: float | None = Field(
        None,
        ge=0,
        description=(
            "Drop pairs whose minimum front-to-front spacing is under this [m]; "
            "None keeps all."
        ),
    )
    split: Literal["dataset", "kfold"] = Field(
        "dataset",
        description=(
            "'dataset': the data set's own Trajectory/ (train) and Testing/ (test); "
            "'kfold': seeded k-fold over the pairs of the full set."
        ),
    )
    folds: int = Field(3, ge=2, description="Number of folds (split='kfold').")
    fold: int = Field(
        0, ge=0, description="Fold used as the test set, 0 <= fold < folds."
    )
    split_seed: int = Field(
        0, description="Seed of the k-fold permutation of the pairs."
    )

    @field_validator("name")
    @classmethod
    def _known_dataset(cls, name: str | None) -> str | None:
        if name is not None and name not in DATASETS:
            raise ValueError(
                f"unknown dataset {name!r} (known: {', '.join(DATASETS)}); "
                "use path for a folder"
            )
        return name

    @field_validator("units")
    @classmethod
    def _known_units(cls, units: str | None) -> str | None:
        if units is not None:
            unit_factor(units)  # DataError (a ValueError) names the valid ones
        return units

    @model_validator(mode="after")
    def _consistent(self) -> DataConfig:
        given = [k for k in ("name", "path", "raw") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of name (a registered data set), path (a folder) "
                f"and raw (a raw trajectory source), got {', '.join(given) or 'none'} "
                "(--set data.path=DIR alone replaces a config's data set)"
            )
        if self.raw is not None:
            fixed = [
                k
                for k in ("units", "dt", "leader_length", "min_spacing")
                if getattr(self, k) is not None
            ]
            if fixed:
                raise ValueError(
                    f"{', '.join(fixed)}: not used with raw (the extraction sets "
                    "them; see data.raw)"
                )
            if self.split != "dataset":
                raise ValueError(
                    "split='kfold' cannot be used with raw: raw sources are split by "
                    "source group (data.raw.split_by), so no vehicle is on both sides"
                )
        if self.root is not None and self.name is None:
            raise ValueError("root is only used with name, not with path")
        if self.fold >= self.folds:
            raise ValueError(f"fold must be < folds={self.folds}, got {self.fold}")
        if self.split == "dataset":
            # Unused k-fold settings would otherwise be ignored silently (and
            # change the config hash for nothing).
            defaults = type(self).model_fields
            changed = [
                k
                for k in ("folds", "fold", "split_seed")
                if getattr(self, k) != defaults[k].default
            ]
            if changed:
                raise ValueError(
                    f"{', '.join(changed)}: only used with split='kfold', not "
                    "split='dataset'"
                )
        return self


class ModelSpec(BaseModel):
    """One car-following model to calibrate, with optional prior overrides."""

    model_config = _STRICT

    name: str = Field(
        description=(
            f"Registered model: one of {', '.join(MODELS)} (case-insensitive), "
            "optionally augmented with effects: '<model>+<effect>+...' with effects "
            f"from {', '.join(EFFECTS)} (e.g. 'idm+delay', "
            "'llctg+grade(start=0,end=600,knots=4)')."
        )
    )
    prior: dict[str, tuple[float, float]] | None = Field(
        None,
        description=(
            "Uniform prior [low, high] per parameter, replacing the model's default "
            "box for the parameters named (units as the model's parameters)."
        ),
    )

    @field_validator("name")
    @classmethod
    def _known_model(cls, name: str) -> str:
        try:
            model = get_model(name)
        except UnknownModelError as error:
            raise ValueError(str(error)) from None
        # The canonical name, so 'IDM' and 'idm', 'idm+lag+delay' and
        # 'idm+delay+lag' hash alike.
        return model.name

    @field_validator("prior")
    @classmethod
    def _known_params(
        cls, prior: dict[str, tuple[float, float]] | None, info: ValidationInfo
    ) -> dict[str, tuple[float, float]] | None:
        name = info.data.get("name")
        if prior is None or name is None:  # a bad name is already reported
            return prior or None  # {} means no override, as None does
        known = get_model(name).param_names
        for key, (low, high) in prior.items():
            if key not in known:
                raise ValueError(
                    f"unknown parameter {key!r} for {name} (known: {', '.join(known)})"
                )
            if not low < high:
                raise ValueError(f"{key}: needs low < high, got [{low}, {high}]")
        return prior or None

    @model_validator(mode="after")
    def _runnable_bounds(self) -> ModelSpec:
        model = self.model
        if hasattr(model, "check_bounds"):  # effects limit their priors
            model.check_bounds(self.bounds())
        return self

    @property
    def model(self) -> CFModel:
        """The model this spec names, as an object: the name was parsed when the
        config was read, and :func:`get_model` keeps one instance per canonical
        name, so this is that instance, not a new parse."""
        return get_model(self.name)

    @property
    def plain(self) -> bool:
        """A pool model without effects (``idm``, not ``idm+delay``)."""
        return not getattr(self.model, "effects", ())

    def bounds(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """The uniform prior box with the overrides applied.

        Args:
            dtype: dtype of the result.

        Returns:
            (K, 2) tensor of (low, high) per parameter, in the model's order.
        """
        model = self.model
        box = model.prior_bounds(dtype)  # (K, 2)
        for key, (low, high) in (self.prior or {}).items():
            box[model.param_names.index(key)] = torch.tensor([low, high], dtype=dtype)
        return box


class SMCConfig(BaseModel):
    """The sequential refinement (``abc.method = "smc"``, :mod:`torchcf.abc.smc`)."""

    model_config = _STRICT

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
    EstimatorSettings`): the trajectory encoder, the model head and the flows."""

    model_config = _STRICT

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
    pair's best amortised samples (:mod:`torchcf.train.refinement`)."""

    model_config = _STRICT

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
    particles are."""

    model_config = _STRICT

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
    noise: tuple[_NonNegativeFloat, _NonNegativeFloat, _NonNegativeFloat] | None = (
        Field(
            None,
            description=(
                "Standard deviations of the white noise added to the simulated "
                "followers: position [m], speed [m/s], acceleration [m/s^2]; "
                "None: measured from the training pairs' followers (from their "
                "second differences)."
            ),
        )
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


#: Most particles per model: 1e12 take about 12 days at 1e6 particles/s, far
#: beyond any calibration (the paper's uses 1e6); a larger number is a typo.
MAX_PARTICLES = 10**12


class ABCConfig(BaseModel):
    """ABC rejection sampling: particles, buffers and selection (SPEC section 5)."""

    model_config = _STRICT

    n_particles: int = Field(
        1_000_000,
        gt=0,
        description=(
            "Particles simulated per model: prior draws (rejection), or proposals "
            "in all rounds (smc; those outside the prior box count unsimulated). "
            f"At most {MAX_PARTICLES:.0e} (about 12 days at 1e6 particles/s)."
        ),
    )
    method: Literal["rejection", "smc", "amortised"] = Field(
        "rejection",
        description=(
            "'rejection': every particle drawn from the prior (the paper's); "
            "'smc': the same budget spent in rounds that refine, per pair, a "
            "population around the best fits (see abc.smc); 'amortised': one "
            "network trained on simulations proposes every pair's particles "
            "(see abc.amortised; abc.n_particles is not used)."
        ),
    )
    smc: SMCConfig = Field(
        default_factory=SMCConfig, description="Settings of the 'smc' method."
    )
    amortised: AmortisedConfig = Field(
        default_factory=AmortisedConfig,
        description="Settings of the 'amortised' method.",
    )
    layout: Literal["paired", "full"] = Field(
        "paired",
        description=(
            "'paired': each particle on one training pair drawn from the seed "
            "(the paper's down-sampled mode); 'full': every particle on every pair."
        ),
    )
    top_n: int = Field(
        5,
        gt=0,
        description="Particles kept per training pair and model (N of the paper).",
    )
    sensitivity_n: list[_PositiveInt] = Field(
        [5, 10, 15],
        min_length=1,
        description="Alternative top_n values evaluated from the same buffers.",
    )
    chunk_size: int | None = Field(
        None,
        gt=0,
        description="Particles simulated per chunk; None takes the model's default.",
    )
    early_rejection: bool = Field(
        True,
        description=(
            "Stop a particle's rollout once its score so far (a lower bound of its "
            "score) exceeds what its pair's buffer keeps: the same buffers, faster "
            "(SPEC section 2, amended); the stopped rollouts are counted as "
            "rejected early, apart from the invalid ones, which then count the "
            "rollouts that turned invalid before they stopped or ended."
        ),
    )
    seed: int = Field(
        0, ge=0, description="Seed of the counter-based particle and pair streams."
    )
    selection: Literal["per_pair", "global"] = Field(
        "per_pair",
        description=(
            "'per_pair': the hybrid keeps the top_n best across models on every "
            "training pair; 'global': the paper's variant, the global_size best "
            "of the merged set."
        ),
    )
    global_size: int | None = Field(
        None,
        gt=0,
        description=(
            "Size of the global selection (selection='global' only); None means "
            "top_n x the number of training pairs, the per-pair set's size."
        ),
    )
    weights: tuple[_NonNegativeFloat, _NonNegativeFloat, _NonNegativeFloat] = Field(
        (0.5, 0.3, 0.2),
        description=(
            "Score weights of the position [1/m], speed [s/m] and acceleration "
            "[s^2/m] RMSE: g = w_p e_p + w_v e_v + w_a e_a; sum > 0."
        ),
    )
    checkpoint_every: float = Field(
        60.0, gt=0, description="Wall-clock interval between checkpoints [s]."
    )

    @field_validator("weights")
    @classmethod
    def _some_weight(
        cls, weights: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        if sum(weights) <= 0:
            raise ValueError(f"must not all be 0, got {list(weights)}")
        return weights

    @model_validator(mode="after")
    def _smc_is_paired(self) -> ABCConfig:
        if self.method == "smc" and self.layout != "paired":
            raise ValueError("method='smc' refines per pair: it needs layout='paired'")
        if self.method == "amortised" and self.layout != "paired":
            raise ValueError(
                "method='amortised' proposes per pair: it needs layout='paired'"
            )
        return self

    @model_validator(mode="after")
    def _global_only(self) -> ABCConfig:
        if self.global_size is not None and self.selection != "global":
            raise ValueError(
                f"global_size={self.global_size} only applies with selection='global'"
            )
        return self

    @property
    def buffer_size(self) -> int:
        """Capacity of each streaming buffer: the largest N any selection needs."""
        return max(self.top_n, *self.sensitivity_n)

    @field_validator("n_particles", mode="before")
    @classmethod
    def _at_most_max(cls, value: Any) -> Any:
        if isinstance(value, int | float) and not isinstance(value, bool):
            if value > MAX_PARTICLES:
                raise ValueError(
                    f"at most {MAX_PARTICLES:.0e} particles per model (1e12 take "
                    f"about 12 days at 1e6 particles/s), got {value:.3g}"
                )
        return value


class EvalConfig(BaseModel):
    """Evaluation of the learned particle set on the test pairs (SPEC section 6)."""

    model_config = _STRICT

    beta: float = Field(
        0.15,
        ge=0,
        le=1,
        description=(
            "beta of the beta-WS distance: particle marginals >= beta / n_particles "
            "[1]; 0 gives the minimum distance, 1 the WS distance."
        ),
    )
    sinkhorn_reg: float = Field(
        0.05, gt=0, description="Entropic regularisation of Sinkhorn [score units]."
    )
    sinkhorn_max_iter: int = Field(
        10000, gt=0, description="Iteration cap of the Sinkhorn solver."
    )
    bootstrap: int = Field(
        1000,
        ge=0,
        description=(
            "Bootstrap resamples of the test pairs (percentile intervals of the "
            "minimum distance, the predictive coverage and the hybrid's shares, "
            "which resample training pairs); 0: no intervals."
        ),
    )
    bootstrap_transport: int = Field(
        100,
        ge=0,
        description=(
            "Resamples for the WS and beta-WS intervals, at most 'bootstrap': each "
            "resample solves their exact LPs again for every learned set (about "
            "0.3 ms each at 220 particles x 17 pairs: 0.6 s for the 9 sets of "
            "configs/smoke.json at 100); 0: none."
        ),
    )
    level: float = Field(
        0.95, gt=0, lt=1, description="Coverage of the bootstrap intervals [1]."
    )
    seed: int | None = Field(
        None,
        ge=0,
        description="Seed of the bootstrap; None = abc.seed.",
    )
    coverage_levels: list[float] = Field(
        [0.5, 0.9],
        min_length=1,
        description=(
            "Nominal levels of the central predictive bands whose coverage of "
            "the observed spacing and speed is a headline number [1]."
        ),
    )
    coverage_curve: list[float] = Field(
        [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9],
        min_length=1,
        description="Nominal levels of the calibration curve [1].",
    )

    @field_validator("coverage_levels", "coverage_curve")
    @classmethod
    def _levels_in_unit_interval(cls, levels: list[float]) -> list[float]:
        if any(not 0 < q < 1 for q in levels):
            raise ValueError(f"every level must be in (0, 1), got {levels}")
        return sorted(set(levels))

    @model_validator(mode="after")
    def _transport_within_bootstrap(self) -> EvalConfig:
        if self.bootstrap_transport > self.bootstrap:
            raise ValueError(
                f"bootstrap_transport ({self.bootstrap_transport}) must be at most "
                f"bootstrap ({self.bootstrap})"
            )
        return self


class PlausibilityConfig(BaseModel):
    """Plausibility of particles in closed loop (:mod:`torchcf.traffic.battery`).

    With ``filter`` on, calibration rejects particles that collide in the
    battery (emergency braking to a stop, stop-and-go, a cut-in, a standstill
    start) before they enter the buffers, as if their rollout were invalid
    (:mod:`torchcf.abc.screen`).
    """

    model_config = _STRICT

    report: bool = Field(
        True,
        description=(
            "Run the battery on the learned hybrid's particles after training: "
            "per model in summary.json ('plausibility'), TensorBoard and the "
            "evaluation report."
        ),
    )
    filter: bool = Field(
        False,
        description=(
            "Reject particles that collide in the battery during calibration "
            "(counted per model as 'implausible')."
        ),
    )
    reject_string_unstable: bool = Field(
        False,
        description=(
            "With filter: also reject particles whose homogeneous platoon "
            "amplifies a disturbance (string-stability ratio > 1)."
        ),
    )
    speed: float | None = Field(
        None,
        gt=0,
        description=(
            "Cruise speed of the scenarios [m/s]; None: the training pairs' "
            "95th-percentile leader speed."
        ),
    )
    decelerations: list[float] = Field(
        [4.0, 6.0, 8.0],
        min_length=1,
        description="Decelerations of the braking leader [m/s^2], each > 0.",
    )
    collision_spacing: float = Field(
        0.0,
        ge=0,
        description=(
            "Front-to-front spacing at or below which a follower has collided "
            "[m]; 0 is the traffic module's criterion, the leader length bumper "
            "contact."
        ),
    )

    @field_validator("decelerations")
    @classmethod
    def _positive(cls, values: list[float]) -> list[float]:
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"every deceleration must be > 0 m/s^2, got {values}")
        return values


class DiagnoseConfig(BaseModel):
    """Close the loop after training (``python -m torchcf.diagnose RUN_DIR``).

    Residual diagnosis of the run's hybrid, attribution of candidate effects by
    their out-of-sample gain in small ABC runs, re-calibration with the chosen
    effects and evaluation on the test split (:mod:`torchcf.diagnose`).
    """

    model_config = _STRICT

    run_after_training: bool = Field(
        False,
        description=(
            "Run the loop at the end of the study (torchcf train, python -m "
            "torchcf.train)."
        ),
    )
    effects: list[str] = Field(
        list(EFFECTS),
        min_length=1,
        description=(
            f"Candidate effects, from {', '.join(EFFECTS)}; options in brackets, "
            "e.g. 'grade(knots=4)' (a grade without start/end spans the training "
            "pairs' road section)."
        ),
    )
    models: Literal["active", "all"] = Field(
        "active",
        description=(
            "Pool models that get the effects: 'active' = those whose share of the "
            "run's hybrid is at least min_share, 'all' = every model of the run."
        ),
    )
    min_share: float = Field(
        0.05, ge=0, le=1, description="Share that makes a model 'active' [1]."
    )
    n_particles: int = Field(
        50_000,
        gt=0,
        description=(
            "Prior draws per pool model in the small ABC run that starts the "
            "attribution on the fit windows (its S best per pair start the local "
            "search)."
        ),
    )
    population: int = Field(
        20,
        gt=0,
        description=(
            "S: particles per pair every arm keeps and refines by local search "
            "(at least abc.top_n)."
        ),
    )
    local_copies: int = Field(
        32,
        gt=0,
        description="Perturbed copies of every kept particle per local-search round.",
    )
    rounds: int = Field(
        6,
        ge=0,
        description=(
            "Local-search rounds of the pool's fit, of every arm of a comparison "
            "and of the re-calibration."
        ),
    )
    max_rounds: int = Field(
        40,
        gt=0,
        description=(
            "Local-search rounds at most to converge the current model before "
            "each step's comparisons (it stops once two rounds in a row lower "
            "the fit by less than 0.2 %)."
        ),
    )
    fit_fraction: float = Field(
        0.6,
        gt=0.1,
        lt=0.95,
        description=(
            "The share of the data the attribution fits: of every training "
            "pair's steps (validation 'time'), or of the training pairs "
            "(validation 'pairs'); the rest is out of sample."
        ),
    )
    validation: Literal["auto", "time", "pairs", "refit"] = Field(
        "auto",
        description=(
            "How an arm is judged out of sample: 'time' fits the first "
            "fit_fraction of every training pair's steps and scores each pair's "
            "picks on the rest; 'pairs' fits the whole windows of fit_fraction of "
            "the training pairs (a seeded draw) and scores every other pair by "
            "the best of all the picks (the minimum distance on pairs the arms "
            "never saw); 'refit' splits as 'pairs' and refits every held-out "
            "pair by a short search of its own, with and without the effect "
            "(pinned at the value the fit pairs gave), from one start; 'auto': "
            "'refit' where at least log2(permutations + 1) pairs are held out "
            "(15 at the defaults), else 'time'."
        ),
    )
    refit_rounds: int = Field(
        24,
        ge=0,
        description=(
            "Local-search rounds of a held-out pair's refit (validation "
            "'refit'), of refit_slots particles and local_copies / 2 copies each: "
            "at most this many with refit_stop 'calm', exactly this many with "
            "'rounds'."
        ),
    )
    refit_slots: int = Field(
        5,
        gt=0,
        description=(
            "Particles a held-out pair's refit keeps and searches from "
            "(validation 'refit'; a pair's own best with 'time'): the refit's "
            "cost per round is pairs x refit_slots x local_copies / 2 rollouts."
        ),
    )
    refit_stop: Literal["calm", "rounds"] = Field(
        "calm",
        description=(
            "When a held-out pair's refit stops: 'calm' once two rounds in a "
            "row lower the held-out pairs' summed best score by less than "
            "0.2 % (as the fit's search converges; each side of a comparison "
            "is then refitted until neither would gain from more rounds), "
            "'rounds' after exactly refit_rounds rounds."
        ),
    )
    validation_warmup: float = Field(
        0.0,
        ge=0,
        le=10,
        description=(
            "Seconds of recorded history before each validation window [s] "
            "(validation 'time'; with 'auto' it asks for it): the validation "
            "rollout starts this long before the split from the observed state, "
            "and only the steps after the split are scored, so a delay's, a "
            "clock offset's or a lag's memory enters the window filled by the "
            "recorded leader (0: the window starts at the split, its memory a "
            "steady past). Held-out pairs ('pairs', 'refit') are simulated from "
            "their first step."
        ),
    )
    alpha: float = Field(
        0.05,
        gt=0,
        lt=1,
        description=(
            "Family-wise significance level of the whole selection: step s is "
            "tested at alpha / 2^s (the last step the rest), each by the fallback "
            "procedure in the order the fit windows give."
        ),
    )
    levels: Literal["halving", "pointed", "equal"] = Field(
        "halving",
        description=(
            "How a step's level is shared among its tests, in their order: "
            "'halving' gives the i-th test 2^-i of it (the first half, whatever "
            "pointed to it); 'pointed' gives the effects a residual signature "
            "points to half of it in equal shares and the others the other half "
            "in equal shares; 'equal' gives every test the same share "
            "(Bonferroni). The fallback procedure passes a significant test's "
            "level on to the next under each."
        ),
    )
    min_gain: float = Field(
        0.05,
        ge=0,
        lt=1,
        description="Smallest relative out-of-sample score drop that counts [1].",
    )
    max_effects: int = Field(
        3,
        gt=0,
        description=(
            "Forward selection's steps at most: each chooses the significant "
            "effect of largest out-of-sample gain, given those chosen before."
        ),
    )
    permutations: int = Field(
        20_000, ge=1000, description="Sign-flip permutations of the gain test."
    )
    seed: int | None = Field(
        None,
        ge=0,
        description=(
            "Seed of the attribution's prior draws and local search; None = "
            "abc.seed. Another seed checks that the answer is not luck."
        ),
    )
    recalibration: Literal["train", "search"] = Field(
        "train",
        description=(
            "How the chosen effects are re-calibrated on the whole training "
            "windows: 'train' trains every pool model's variant as the run "
            "trained its models (abc.method, abc.n_particles, beside the run's "
            "buffers) against the pool given the same draws again; 'search' "
            "refines the run's best particles by local search, with and without "
            "the effects."
        ),
    )
    detectable: bool = Field(
        True,
        description=(
            "Where the loop chooses nothing (its first step), estimate per "
            "tested effect the "
            "smallest size its test would have found in these data "
            "(:mod:`torchcf.diagnose.power`; one refit per size tried). Off "
            "only to save that time where the sizes are not read (a power "
            "study)."
        ),
    )
    workers: int = Field(
        0,
        ge=0,
        description=(
            "Processes that search a step's effect arms side by side, one "
            "thread each: 0 (auto) one per core where an arm's search rounds "
            "are large enough to pay for starting them, 1 none (the results are "
            "the same either way)."
        ),
    )
    method: Literal["rejection", "smc"] = Field(
        "rejection",
        description=(
            "The small ABC run that starts the attribution: 'rejection' (prior "
            "draws) or 'smc' (the refinement of abc.smc at the same budget); "
            "local search follows either."
        ),
    )

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, effects: list[str]) -> list[str]:
        # parse_effect raises ValueError naming a bad effect or option.
        names = [parse_effect(token).name for token in effects]
        if len(set(names)) != len(names):
            raise ValueError(f"an effect is listed twice: {effects}")
        return [token.strip().lower() for token in effects]

    @model_validator(mode="after")
    def _warmup_in_time(self) -> DiagnoseConfig:
        asked = "validation_warmup" in self.model_fields_set
        held = self.validation in ("pairs", "refit")
        if held and asked and self.validation_warmup > 0:
            raise ValueError(
                "diagnose.validation_warmup applies to validation 'time' only: a "
                f"held-out pair ('{self.validation}') is simulated from its first "
                "step"
            )
        return self


def _models_schema(schema: JSON) -> None:
    """JSON schema of ``models``: items are a name or a ModelSpec object."""
    schema["items"] = {
        "anyOf": [
            {"enum": list(MODELS)},
            {"type": "string", "pattern": "^[A-Za-z]+(\\+.+)+$"},
            schema["items"],
        ]
    }


class TrainConfig(BaseModel):
    """A whole training run: ``python -m torchcf.train CONFIG``."""

    model_config = _STRICT

    data: DataConfig = Field(description="The observed pairs and their split.")
    models: list[ModelSpec] = Field(
        [ModelSpec(name=name) for name in MODELS],
        min_length=1,
        description=(
            "Models to calibrate, each once: a name (shorthand for {'name': ...}) "
            "or a ModelSpec object. Default: all registered models."
        ),
        json_schema_extra=_models_schema,
    )
    abc: ABCConfig = Field(ABCConfig(), description="ABC sampling.")
    eval: EvalConfig = Field(EvalConfig(), description="Evaluation on the test pairs.")
    diagnose: DiagnoseConfig = Field(
        DiagnoseConfig(), description="Closing the loop (residuals -> effects)."
    )
    plausibility: PlausibilityConfig = Field(
        PlausibilityConfig(),
        description="Plausibility of particles in closed loop (battery, filter).",
    )
    output: str | None = Field(
        None,
        min_length=1,
        description=(
            "Output directory; None means runs/<config file stem>. The CLI's "
            "--out overrides it."
        ),
    )
    device: str = Field(
        "cpu",
        description=(
            "torch device, e.g. 'cpu', 'cuda', 'cuda:1' (availability is checked "
            "when the run starts)."
        ),
    )
    dtype: Literal["float32", "float64"] = Field(
        "float32", description="Floating dtype of the simulation."
    )
    threads: int | None = Field(
        None, gt=0, description="CPU threads for torch; None keeps torch's default."
    )
    compile: Literal["auto", "on", "off"] = Field(
        "auto",
        description=(
            "torch.compile of the rollout: 'auto' where it pays off (from 2e8 "
            "particle-steps on the CPU, 1e11 on CUDA), 'on' always (where the "
            "model allows), 'off' never."
        ),
    )

    @field_validator("models", mode="before")
    @classmethod
    def _shorthand(cls, models: Any) -> Any:
        if isinstance(models, list):
            return [{"name": m} if isinstance(m, str) else m for m in models]
        return models

    @field_validator("models")
    @classmethod
    def _unique(cls, models: list[ModelSpec]) -> list[ModelSpec]:
        names = [m.name for m in models]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"each model at most once, got {', '.join(twice)} twice")
        return models

    @field_validator("device")
    @classmethod
    def _torch_device(cls, device: str) -> str:
        try:
            return str(torch.device(device))
        except (RuntimeError, ValueError) as err:
            raise ValueError(f"not a torch device: {device!r} ({err})") from None

    @property
    def torch_dtype(self) -> torch.dtype:
        """:attr:`dtype` as a ``torch.dtype``."""
        return getattr(torch, self.dtype)
