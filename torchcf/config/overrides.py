"""Command-line overrides of a configuration: ``--set dotted.key=VALUE``."""

from __future__ import annotations

import copy
import json
from collections.abc import Sequence
from typing import Any

from torchcf.config.messages import ConfigError
from torchcf.system.files import JSON

__all__ = ["DATA_SOURCES", "apply_overrides"]

#: The keys of ``data`` that name where the pairs come from; a config gives
#: exactly one, so an override that sets one replaces the others.
DATA_SOURCES = ("name", "path", "raw")


def apply_overrides(raw: JSON, overrides: Sequence[str]) -> JSON:
    """Set ``dotted.key=VALUE`` items in a copy of a configuration object.

    VALUE is parsed as JSON (``200000``, ``[1, 0, 0]``, ``true``, ``null``), and
    taken as a plain string where it is not JSON, so ``device=cpu`` needs no
    quotes. Missing intermediate objects are created; a numeric component
    indexes an existing list (``models.0.name=idm``), and a model given by name
    becomes an object when a key inside it is set. Setting one source of the
    data (``data.name``, ``data.path`` or ``data.raw``, :data:`DATA_SOURCES`) to
    a value drops the others: ``--set data.path=DIR`` on a config that names a
    data set reads DIR instead.

    Args:
        raw: the configuration object, not modified.
        overrides: the items, applied in order.

    Returns:
        A new configuration object.

    Raises:
        ConfigError: an item without ``=``, an empty key or component, or a path
            through a value that is neither an object nor a list.

    Examples:
        >>> from torchcf.config import apply_overrides
        >>> raw = {"data": {"name": "car-model-1"}, "abc": {"top_n": 5}}
        >>> apply_overrides(raw, ["abc.n_particles=600", "data.path=demo",
        ...                 "device=cpu"])
        {'data': {'path': 'demo'}, 'abc': {'top_n': 5, 'n_particles': 600},
         'device': 'cpu'}
    """
    out = copy.deepcopy(raw)
    for item in overrides:
        key, sep, text = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise ConfigError(f"override {item!r}: expected dotted.key=VALUE")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        node: JSON | list[Any] = out
        for depth, part in enumerate(parts[:-1]):
            node = _child(node, part, item, ".".join(parts[: depth + 1]))
        if isinstance(node, dict):
            node[parts[-1]] = value
            if _is_data_source(parts) and value is not None:
                for other in DATA_SOURCES:
                    if other != parts[-1]:
                        node.pop(other, None)
        else:
            node[_index(node, parts[-1], item, key)] = value
    return out


def _is_data_source(parts: list[str]) -> bool:
    """Whether the override's key is ``data.name``, ``data.path`` or ``data.raw``."""
    return len(parts) == 2 and parts[0] == "data" and parts[1] in DATA_SOURCES


def _child(
    node: JSON | list[Any], part: str, item: str, where: str
) -> JSON | list[Any]:
    """``node[part]`` for an override, created as ``{}`` when missing."""
    if isinstance(node, dict):
        if node.get(part) is None:
            node[part] = {}
        child = node[part]
    else:
        index = _index(node, part, item, where)
        if isinstance(node[index], str):
            # The models shorthand: "idm" becomes {"name": "idm"}.
            node[index] = {"name": node[index]}
        child = node[index]
    if not isinstance(child, dict | list):
        raise ConfigError(f"override {item!r}: {where} is {child!r}, not an object")
    return child


def _index(node: list[Any], part: str, item: str, where: str) -> int:
    if not part.isdigit() or int(part) >= len(node):
        raise ConfigError(
            f"override {item!r}: {where}: {part!r} is not an index of a list "
            f"of {len(node)}"
        )
    return int(part)
