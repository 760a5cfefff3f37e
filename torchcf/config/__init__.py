"""The run configuration: :mod:`torchcf.config.schema` (the pydantic schema, its
loader and hash), :mod:`torchcf.config.overrides` (``--set key=VALUE``),
:mod:`torchcf.config.messages` (one-line errors) and ``python -m torchcf.config``
(:mod:`torchcf.config.__main__`).

Re-exports only.
"""

from .schema import (
    ABCConfig,
    ConfigError,
    DataConfig,
    DiagnoseConfig,
    EvalConfig,
    ModelSpec,
    PlausibilityConfig,
    SMCConfig,
    TrainConfig,
    apply_overrides,
    config_hash,
    load_config,
    resolved_json,
    validate_config,
)

__all__ = [
    "ABCConfig",
    "ConfigError",
    "DataConfig",
    "DiagnoseConfig",
    "PlausibilityConfig",
    "EvalConfig",
    "ModelSpec",
    "SMCConfig",
    "TrainConfig",
    "apply_overrides",
    "config_hash",
    "load_config",
    "resolved_json",
    "validate_config",
]
