"""The model registry: lowercase names -> model instances (SPEC section 3).

The same names are the config tags. Models are stateless, so one instance each is
shared by everything.
"""

from __future__ import annotations

import copyreg
from collections.abc import Callable

from ..system.errors import did_you_mean
from .augmented import AugmentedModel
from .base import (
    CFModel,
    FollowerState,
    ParamSpec,
    Perception,
    first_order_lag_advance,
    point_mass_advance,
)
from .effects import EFFECTS, Effect, parse_effect
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


_AUGMENTED: dict[str, AugmentedModel] = {}


def get_model(name_or_model: str | CFModel) -> CFModel:
    """Look a model up by name (case-insensitive); a CFModel is returned as is.

    ``"<model>+<effect>+..."`` (e.g. ``"idm+delay"``) is the pool model wrapped by
    the effects of :mod:`torchcf.models.effects`; its canonical name (effects in
    their canonical order) is the returned model's ``name``.

    Examples:
        >>> from torchcf import get_model
        >>> get_model("IDM").param_names
        ('a', 'b', 'v0', 'T', 's0', 'delta')
        >>> get_model("idm+delay").param_names[-1]
        't_delay'
    """
    if isinstance(name_or_model, CFModel):
        return name_or_model
    key = str(name_or_model).strip().lower()
    if key in MODELS:
        return MODELS[key]
    if key in _AUGMENTED:
        return _AUGMENTED[key]
    base_name, *tokens = split_name(key)
    if base_name not in MODELS:
        where = f" in {name_or_model!r}" if tokens else ""
        raise UnknownModelError(
            f"unknown model {base_name!r}{where}{did_you_mean(base_name, MODELS)}; "
            f"valid names: {', '.join(MODELS)}"
        )
    if not tokens:
        raise UnknownModelError(f"unknown model {name_or_model!r}")
    try:
        effects = [parse_effect(t) for t in tokens]
    except ValueError as error:
        raise UnknownModelError(str(error)) from None
    model = augment(MODELS[base_name], *effects)
    _AUGMENTED[key] = model
    return model


def require_model(model: object, caller: str) -> CFModel:
    """``model`` where it is a model object; anything else raises a one-line
    :class:`TypeError` that names what to pass.

    A model's name is parsed once, where it enters (a config, a command line, a
    saved file: :func:`get_model`); a public function past that point takes
    the object and calls this first, so that a name passed by mistake says how
    to make the object instead of failing deeper in.

    Args:
        model: what the caller was given.
        caller: the public function's name, for the message (``"simulate"``).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.models import require_model
        >>> require_model(get_model("idm"), "simulate").name
        'idm'
        >>> require_model("idm", "simulate")
        Traceback (most recent call last):
            ...
        TypeError: simulate takes a model object, e.g. torchcf.get_model('idm'), ...
    """
    if isinstance(model, CFModel):
        return model
    if isinstance(model, str):
        raise TypeError(
            f"{caller} takes a model object, e.g. torchcf.get_model({model!r}), "
            f"not the name {model!r}"
        )
    raise TypeError(
        f"{caller} takes a model object (torchcf.get_model(name)), "
        f"not a {type(model).__name__}"
    )


def augment(model: CFModel, *effects: Effect) -> CFModel:
    """``model`` wrapped by ``effects`` besides its own: the one instance of that
    variant (``augment(IDM, Delay())`` is ``get_model("idm+delay")``).

    Raises:
        UnknownModelError: an effect cannot wrap the model (``lag`` on HL, which
            has its own actuation lag) or is listed twice.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.models import augment
        >>> from torchcf.models.effects import parse_effect
        >>> augment(get_model("idm"), parse_effect("delay")) is get_model("idm+delay")
        True
    """
    if not effects:
        return model
    try:
        variant = AugmentedModel(model.pool_model, [*model.effects, *effects])
    except ValueError as error:
        raise UnknownModelError(str(error)) from None
    # One instance per canonical name (compiled graphs are cached per instance).
    return _AUGMENTED.setdefault(variant.name, variant)


def _by_name(model: CFModel) -> tuple[Callable[[str], CFModel], tuple[str]]:
    """How a model is pickled (sent to a worker process) or copied: as its name,
    read back as the registry's one instance, so that on the other side it is
    still the dict key that compares by identity."""
    return get_model, (model.name,)


for _kind in (*(type(m) for m in MODELS.values()), AugmentedModel):
    copyreg.pickle(_kind, _by_name)


def split_name(key: str) -> list[str]:
    """Split ``"idm+grade(end=600,knots=4)+lag"`` at the '+' outside parentheses:
    the base model, then each effect's token (an option such as ``end=1e+06``
    keeps its '+').

    Examples:
        >>> from torchcf.models import split_name
        >>> split_name("idm+grade(end=600,knots=4)+lag")
        ['idm', 'grade(end=600,knots=4)', 'lag']
    """
    parts, depth, current = [], 0, ""
    for char in key:
        depth += (char == "(") - (char == ")")
        if char == "+" and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += char
    return [part.strip() for part in parts + [current]]


__all__ = [
    "EFFECTS",
    "MODELS",
    "AugmentedModel",
    "Effect",
    "CFModel",
    "FollowerState",
    "ParamSpec",
    "Perception",
    "UnknownModelError",
    "augment",
    "first_order_lag_advance",
    "get_model",
    "point_mass_advance",
    "require_model",
    "split_name",
]
