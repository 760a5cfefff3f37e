"""The configuration of a training run: ``torchcf train CONFIG``.

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

Command line (:mod:`torchcf.cli.config`)::

    torchcf config --schema                  # the JSON schema
    torchcf config CONFIG [--set k=v ...]    # resolved config and hash
"""

from __future__ import annotations

import math
from typing import Any, Literal

import torch
from pydantic import (
    BaseModel,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from torchcf.config.diagnose import DiagnoseConfig
from torchcf.config.fields import STRICT, NonNegativeFloat, PositiveInt
from torchcf.config.messages import ConfigError
from torchcf.config.methods import AmortisedConfig, SMCConfig
from torchcf.config.raw import RawSource
from torchcf.data.reader import UNITS, unit_factor
from torchcf.data.registry import DATASETS
from torchcf.models import EFFECTS, MODELS, CFModel, UnknownModelError, get_model
from torchcf.system.files import JSON

__all__ = [
    "ABCConfig",
    "ConfigError",
    "DataConfig",
    "EvalConfig",
    "ModelSpec",
    "PlausibilityConfig",
    "TrainConfig",
]


# Shared by every section: unknown keys are errors, values are immutable after
# validation, and NaN / Infinity (which Python's json accepts) never pass.


# --------------------------------------------------------------------- sections
class DataConfig(BaseModel):
    """Which observed pairs to train and test on (:func:`torchcf.config.load_split`).

    Examples:
        >>> from torchcf.config import DataConfig
        >>> data = DataConfig(path="data/extracted", split="kfold", folds=5, fold=2)
        >>> data.name, data.split, data.folds, data.fold
        (None, 'kfold', 5, 2)
    """

    model_config = STRICT

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
            "starts (torchcf.data.extract; the same settings as torchcf data "
            "extract). Exactly one of name, path and raw."
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
    """One car-following model to calibrate, with optional prior overrides.

    Examples:
        >>> from torchcf.config import ModelSpec
        >>> spec = ModelSpec(name="IDM", prior={"T": (0.5, 2.0)})  # T: time headway [s]
        >>> spec.name, tuple(spec.bounds().shape), spec.bounds()[3].tolist()
        ('idm', (6, 2), [0.5, 2.0])
    """

    model_config = STRICT

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


#: Most particles per model: 1e12 take about 12 days at 1e6 particles/s, far
#: beyond any calibration (the paper's uses 1e6); a larger number is a typo.
MAX_PARTICLES = 10**12


class ABCConfig(BaseModel):
    """ABC rejection sampling: particles, buffers and selection (SPEC section 5).

    Examples:
        >>> from torchcf.config import ABCConfig
        >>> abc = ABCConfig(n_particles=600, top_n=5, sensitivity_n=[5, 20])
        >>> abc.method, abc.buffer_size
        ('rejection', 20)
    """

    model_config = STRICT

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
    sensitivity_n: list[PositiveInt] = Field(
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
    weights: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = Field(
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
    """Evaluation of the learned particle set on the test pairs (SPEC section 6).

    Examples:
        >>> from torchcf.config import EvalConfig
        >>> evaluation = EvalConfig(bootstrap=200, coverage_levels=[0.9, 0.5, 0.9])
        >>> evaluation.bootstrap_transport, evaluation.coverage_levels  # sorted, unique
        (100, [0.5, 0.9])
    """

    model_config = STRICT

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

    Examples:
        >>> from torchcf.config import PlausibilityConfig
        >>> screen = PlausibilityConfig(filter=True, decelerations=[6.0])  # [m/s^2]
        >>> screen.report, screen.filter, screen.decelerations
        (True, True, [6.0])
    """

    model_config = STRICT

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
    """A whole training run: ``torchcf train CONFIG``.

    Examples:
        >>> from torchcf.config import TrainConfig
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm", "ovm"])
        >>> [m.name for m in cfg.models], cfg.abc.n_particles, cfg.device
        (['idm', 'ovm'], 1000000, 'cpu')
    """

    model_config = STRICT

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
            "particle-steps on the CPU, 1e11 on CUDA; an amortised run's "
            "sampling from 1e7 samples), 'on' always (where the model allows), "
            "'off' never."
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
