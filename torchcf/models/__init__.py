"""The model registry: lowercase names -> model instances (SPEC section 3).

The same names are the config tags. Models are stateless, so one instance each is
shared by everything.
"""

from __future__ import annotations

from .base import (
    CFModel,
    FollowerState,
    ParamSpec,
    Perception,
    first_order_lag_advance,
    point_mass_advance,
)
from .hdv import FVDM, GFM, IDM, OVM
from .linear import HL, LLCS, LLCTG
from .mpc import MPC

MODELS: dict[str, CFModel] = {
    model.name: model
    for model in (OVM(), GFM(), FVDM(), IDM(), LLCTG(), LLCS(), HL(), MPC())
}


class UnknownModelError(KeyError, ValueError):
    """Raised for a model name that is not in :data:`MODELS`."""

    def __str__(self) -> str:  # KeyError would quote the whole message
        return str(self.args[0])


def get_model(name_or_model: str | CFModel) -> CFModel:
    """Look a model up by name (case-insensitive); a CFModel is returned as is."""
    if isinstance(name_or_model, CFModel):
        return name_or_model
    key = str(name_or_model).lower()
    if key not in MODELS:
        raise UnknownModelError(
            f"unknown model {name_or_model!r}; valid names: {', '.join(MODELS)}"
        )
    return MODELS[key]


__all__ = [
    "MODELS",
    "CFModel",
    "FollowerState",
    "ParamSpec",
    "Perception",
    "UnknownModelError",
    "first_order_lag_advance",
    "get_model",
    "point_mass_advance",
]
