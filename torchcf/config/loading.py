"""Reading, validating and fingerprinting a run configuration.

:func:`load_config` reads a JSON file, applies ``--set`` overrides
(:mod:`torchcf.config.overrides`) and validates it against the schema
(:mod:`torchcf.config.schema`); :func:`config_hash` is the fingerprint a run's
checkpoint and summary carry; :func:`resolved_json` writes a config back.
Apart from the schema because these are file and hash concerns, not fields.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from pydantic import ValidationError

from ..system.files import JSON
from .messages import ConfigError, describe
from .overrides import apply_overrides
from .schema import TrainConfig


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> TrainConfig:
    """Read, override and validate a JSON run configuration.

    Args:
        path: the JSON file.
        overrides: ``dotted.key=VALUE`` items (see :func:`apply_overrides`).

    Returns:
        The validated configuration; ``output`` defaults to ``runs/<file stem>``.

    Raises:
        ConfigError: unreadable file, invalid JSON, not an object, a bad override
            or an invalid configuration.

    Examples:
        >>> import json
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf.config import load_config
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = Path(folder) / "smoke.json"
        ...     raw = {"data": {"path": "demo"}, "models": ["idm"]}
        ...     _ = path.write_text(json.dumps(raw))
        ...     cfg = load_config(path, ["abc.n_particles=600"])
        >>> cfg.abc.n_particles, cfg.output
        (600, 'runs/smoke')
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file '{path}' not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read config file '{path}': {err}") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as err:
        raise ConfigError(
            f"'{path}' is not valid JSON: {err.msg} at line {err.lineno} "
            f"column {err.colno}"
        ) from None
    if not isinstance(raw, dict):
        raise ConfigError(f"'{path}' must hold a JSON object, got {type(raw).__name__}")
    raw = apply_overrides(raw, overrides)
    if raw.get("output") is None:
        raw["output"] = (Path("runs") / path.stem).as_posix()
    return validate_config(raw)


def validate_config(raw: JSON) -> TrainConfig:
    """Validate a configuration object, every error as one :class:`ConfigError`.

    Examples:
        >>> from torchcf.config import ConfigError, validate_config
        >>> cfg = validate_config({"data": {"path": "demo"}, "models": ["IDM"]})
        >>> cfg.models[0].name
        'idm'
        >>> try:
        ...     validate_config({"data": {"path": "demo"}, "abc": {"n_particle": 600}})
        ... except ConfigError as error:
        ...     print(str(error).split(" (")[0])
        abc.n_particle: unknown key
    """
    try:
        return TrainConfig.model_validate(raw)
    except ValidationError as err:
        raise ConfigError(describe(err, TrainConfig)) from None


# Settings that change how a run is executed or reported but not what it learns:
# left out of the hash so that a run can resume with them changed.
_NOT_HASHED: dict[str, bool | set[str]] = {
    "output": True,
    "threads": True,
    "eval": True,
    "diagnose": True,
    # The result does not depend on the chunk size (tested), nor on where the data
    # folder lies: a run may be resumed with other values of these.
    "abc": {"checkpoint_every", "chunk_size"},
    "data": {"root"},
}


def config_hash(cfg: TrainConfig) -> str:
    """Fingerprint of the settings that determine the learned particle sets.

    Everything except ``output``, ``threads``, ``abc.checkpoint_every``,
    ``abc.chunk_size``, ``data.root`` and ``eval`` (none changes the result),
    ``abc.smc`` unless the method is SMC, and ``abc.amortised`` unless it is
    the amortised one (whose ``max_seconds`` a resumed run may change;
    ``estimator`` enters only where set).
    Shorthand and object forms, key order and ``1`` vs ``1.0`` give the same hash.

    Returns:
        The first 16 hex digits of the SHA-256 of the canonical JSON.

    Examples:
        >>> from torchcf.config import TrainConfig, config_hash
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm"])
        >>> moved = cfg.model_copy(update={"output": "elsewhere"})  # not hashed
        >>> len(config_hash(cfg)), config_hash(moved) == config_hash(cfg)
        (16, True)
    """
    payload = cfg.model_dump(mode="json", exclude=_NOT_HASHED)
    method = payload["abc"]["method"]
    # A method's settings do not enter another method's run: the hashes of
    # rejection and SMC runs stay what they were before the later methods'
    # settings existed (checkpoints of earlier runs resume).
    amortised = payload["abc"].pop("amortised")
    if method == "amortised":
        del amortised["max_seconds"]
        if amortised["estimator"] is None:  # trained by the run: as before it existed
            del amortised["estimator"]
        payload["abc"]["amortised"] = amortised
    if method != "smc":
        del payload["abc"]["smc"]
    if method == "rejection":
        del payload["abc"]["method"]
    text = json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def resolved_json(cfg: TrainConfig) -> JSON:
    """The configuration as plain JSON data (models as objects), every default
    filled in; :func:`load_config` of it gives ``cfg`` back.

    Examples:
        >>> from torchcf.config import TrainConfig, resolved_json, validate_config
        >>> cfg = TrainConfig(data={"path": "demo"}, models=["idm"])
        >>> raw = resolved_json(cfg)
        >>> raw["models"], raw["abc"]["n_particles"], validate_config(raw) == cfg
        ([{'name': 'idm', 'prior': None}], 1000000, True)
    """
    return cfg.model_dump(mode="json")
