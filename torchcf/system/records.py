"""Typed records of results, and their JSON.

Results travel between modules as frozen dataclasses; a :class:`Record` is one
whose JSON object is its fields, in the declared order: :meth:`Record.to_json`
gives the object a file holds (key order included) and :meth:`Record.from_json`
reads it back (``from_json(r.to_json()) == r``). A record whose file lays its
fields out otherwise (flattened, or with optional keys) overrides the two.

The helpers turn field values into JSON content and back: :func:`to_json_value`
(records by their ``to_json``, tuples as lists), :func:`frozen` (lists as
tuples, a record's sequences) and :func:`copy_json` (a deep copy of JSON
content, so that a record never shares a container with its caller).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, fields
from typing import Any, Self

from .files import JSON


def to_json_value(value: Any) -> Any:
    """``value`` as JSON content: records (anything with a ``to_json``) by their
    ``to_json``, tuples as lists, mapping keys as strings; a fresh copy of every
    container.

    Examples:
        >>> from torchcf.system.records import to_json_value
        >>> to_json_value({"levels": (0.5, 0.9), 1: [(1, 2)]})
        {'levels': [0.5, 0.9], '1': [[1, 2]]}
    """
    if isinstance(value, Record) or callable(getattr(value, "to_json", None)):
        return value.to_json()
    if isinstance(value, list | tuple):
        return [to_json_value(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): to_json_value(v) for k, v in value.items()}
    return value


def frozen(value: Any) -> Any:
    """JSON content with its lists as tuples (a record's sequences).

    Examples:
        >>> from torchcf.system.records import frozen
        >>> frozen([0.5, [1, 2]])
        (0.5, (1, 2))
    """
    if isinstance(value, list | tuple):
        return tuple(frozen(v) for v in value)
    return value


def copy_json(value: Any) -> Any:
    """A deep copy of JSON content (its containers, not its scalars).

    Examples:
        >>> from torchcf.system.records import copy_json
        >>> raw = {"pairs": [1, 2]}
        >>> copied = copy_json(raw)
        >>> copied == raw, copied["pairs"] is raw["pairs"]
        (True, False)
    """
    if isinstance(value, Mapping):
        return {k: copy_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [copy_json(v) for v in value]
    return value


class Record:
    """A frozen record whose JSON object is its fields, in order (a base of
    frozen dataclasses).

    Examples:
        >>> from dataclasses import dataclass
        >>> from torchcf.system.records import Record
        >>> @dataclass(frozen=True)
        ... class Band(Record):
        ...     level: float
        ...     bounds: tuple[float, float]
        >>> band = Band(0.9, (1.5, 2.5))
        >>> band.to_json()
        {'level': 0.9, 'bounds': [1.5, 2.5]}
        >>> Band.from_json(band.to_json()) == band
        True
    """

    def to_json(self) -> JSON:
        """The JSON object: every field, in the declared order."""
        return {f.name: to_json_value(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_json(cls, raw: Mapping[str, Any]) -> Self:
        """The record of a JSON object holding exactly its fields (sequences as
        tuples; a field with a default may be missing).

        Raises:
            KeyError: a field without a default is missing.
            ValueError: an unknown key.
        """
        names = [f.name for f in fields(cls)]
        unknown = [key for key in raw if key not in names]
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown key(s) {unknown}")
        # a field with a default may be missing (a file written before it)
        defaulted = {f.name for f in fields(cls) if f.default is not MISSING}
        return cls(
            **{
                name: frozen(raw[name])
                for name in names
                if name in raw or name not in defaulted
            }
        )


__all__ = ["Record", "copy_json", "frozen", "to_json_value"]
