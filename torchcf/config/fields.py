"""The building blocks every config section shares: a strict pydantic model
configuration and the constrained number types of its fields."""

from __future__ import annotations

from typing import Annotated

from pydantic import ConfigDict, Field

__all__ = ["STRICT", "NonNegativeFloat", "PositiveInt"]

#: Every section rejects unknown keys (a misspelled key fails at load time), is
#: immutable once validated, and refuses NaN and infinity.
STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

PositiveInt = Annotated[int, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]
