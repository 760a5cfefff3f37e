"""One-line messages for configuration errors.

:class:`ConfigError` is what every configuration problem raises; :func:`describe`
turns pydantic's ValidationError into one line that names the key, e.g.
``abc.n_particles: must be > 0, got -5``, and suggests the intended key for a
misspelled one.
"""

from __future__ import annotations

import difflib
import typing
from collections.abc import Sequence
from typing import Any

from pydantic import BaseModel, ValidationError

from torchcf.system.errors import TorchcfError

__all__ = ["ConfigError", "describe"]


class ConfigError(TorchcfError, ValueError):
    """A run configuration is unreadable or invalid; the message is one line."""

    def __init__(self, message: str) -> None:
        # One line whatever the source: the CLIs print it after "error: ".
        super().__init__(" ".join(str(message).split()))


def describe(err: ValidationError, root: type[BaseModel]) -> str:
    """One line for a ValidationError of ``root`` (the validated model): the
    first three problems, joined by "; "."""
    errors = err.errors(include_url=False)
    text = "; ".join(_describe_one(e, root) for e in errors[:3])
    if len(errors) > 3:
        text += f"; and {len(errors) - 3} more"
    return text


def _describe_one(error: Any, root: type[BaseModel]) -> str:
    loc = _dotted(error["loc"])
    kind, ctx, value = error["type"], error.get("ctx", {}), error.get("input")
    got = f", got {_short(value)}"
    if kind == "missing":
        return f"{loc}: required"
    if kind == "extra_forbidden":
        return f"{loc}: unknown key{_known_keys(error['loc'], root)}"
    if kind in _BOUNDS:
        op, name = _BOUNDS[kind]
        return f"{loc}: must be {op} {ctx[name]}{got}"
    if kind == "too_short" and ctx.get("min_length") == 1:
        return f"{loc}: must not be empty"
    if kind == "value_error":
        # Our validators' messages already carry the value.
        return f"{loc}: {error['msg'].removeprefix('Value error, ')}"
    msg = error["msg"]
    return f"{loc}: {msg[:1].lower()}{msg[1:]}{got}"


_BOUNDS = {
    "greater_than": (">", "gt"),
    "greater_than_equal": (">=", "ge"),
    "less_than": ("<", "lt"),
    "less_than_equal": ("<=", "le"),
}


def _dotted(loc: Sequence[int | str]) -> str:
    """``('models', 2, 'prior')`` -> ``models[2].prior``; () -> ``config``."""
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else f".{part}"
    return text.lstrip(".") or "config"


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _known_keys(loc: Sequence[int | str], root: type[BaseModel]) -> str:
    """`` (known: ...)`` for an unknown key, with a guess at the intended one."""
    section: Any = root
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        field = section.model_fields.get(part)
        section = _section(field.annotation) if field is not None else None
        if section is None:
            return ""
    known = list(section.model_fields)
    guess = difflib.get_close_matches(str(loc[-1]), known, n=1)
    hint = f"; did you mean {guess[0]!r}?" if guess else ""
    return f" (known: {', '.join(known)}){hint}"


def _section(annotation: Any) -> type[BaseModel] | None:
    """The config class inside an annotation (``list[ModelSpec]`` -> ModelSpec)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _section(arg)
        if found is not None:
            return found
    return None
