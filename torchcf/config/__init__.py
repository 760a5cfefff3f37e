"""The run configuration: :mod:`torchcf.config.schema` (the pydantic schema),
with its ABC methods' settings in :mod:`torchcf.config.methods`, the loop's in
:mod:`torchcf.config.diagnose` and their shared field types in
:mod:`torchcf.config.fields`,
:mod:`torchcf.config.loading` (its loader and hash),
:mod:`torchcf.config.overrides` (``--set key=VALUE``),
:mod:`torchcf.config.pairs` (the ``data`` section to its pairs: :func:`load_split`),
:mod:`torchcf.config.messages` (one-line errors) and the ``torchcf config``
command (:mod:`torchcf.cli.config`).

Re-exports only.
"""

from .diagnose import DiagnoseConfig
from .loading import config_hash, load_config, resolved_json, validate_config
from .messages import ConfigError
from .methods import AmortisedConfig, AmortisedNetworkConfig, RefineConfig, SMCConfig
from .overrides import apply_overrides
from .pairs import load_index, load_split
from .schema import (
    ABCConfig,
    DataConfig,
    EvalConfig,
    ModelSpec,
    PlausibilityConfig,
    TrainConfig,
)

__all__ = [
    "ABCConfig",
    "AmortisedConfig",
    "AmortisedNetworkConfig",
    "ConfigError",
    "DataConfig",
    "DiagnoseConfig",
    "PlausibilityConfig",
    "RefineConfig",
    "EvalConfig",
    "ModelSpec",
    "SMCConfig",
    "TrainConfig",
    "apply_overrides",
    "config_hash",
    "load_config",
    "load_index",
    "load_split",
    "resolved_json",
    "validate_config",
]
