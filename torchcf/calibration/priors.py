"""The models' prior boxes of a calibration.

A box is ``(K, 2)`` float64, (low, high) per parameter in the model's order
[SI units]. Its last rows of zero width hold those parameters at one value
(a shared effect's, found by the loop): the samplers draw the others and
append the held values to every particle.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from ..models import CFModel, require_model


def held_values(box: Tensor) -> Tensor:
    """``(K_held,)`` the values of a box's last rows of zero width: the
    parameters held at one value, not drawn (the first rows, however narrow,
    are drawn)."""
    pinned = box[:, 0] == box[:, 1]
    drawn = int(pinned.numel())
    while drawn and bool(pinned[drawn - 1]):
        drawn -= 1
    return box[drawn:, 0].clone()


def drawn_and_held(box: Tensor) -> tuple[Tensor, Tensor | None]:
    """A prior box ``(K, 2)`` as the box its sampler draws, ``(K_drawn, 2)``,
    and the values of the held last parameters (None: every one drawn)."""
    held = held_values(box)
    if not held.numel():
        return box, None
    return box[: box.shape[0] - held.numel()], held


def prior_boxes(
    models: Sequence[CFModel] | Mapping[CFModel, Tensor],
) -> dict[CFModel, Tensor]:
    """Every model's prior box ``(K, 2)`` float64: its own default, or the
    mapping's; ValueError for a name that is not a model or a box of another
    shape.

    Examples:
        >>> from torchcf import get_model
        >>> boxes = prior_boxes([get_model("idm"), get_model("ovm")])
        >>> [(model.name, tuple(box.shape)) for model, box in boxes.items()]
        [('idm', (6, 2)), ('ovm', (5, 2))]
    """
    if isinstance(models, Mapping):
        boxes = {}
        for model, box in models.items():
            model = require_model(model, "calibrate")
            box = torch.as_tensor(box, dtype=torch.float64)
            if box.shape != (model.n_params, 2):
                raise ValueError(
                    f"{model.name}: prior box of shape {tuple(box.shape)}, "
                    f"expected ({model.n_params}, 2)"
                )
            boxes[model] = box
    else:
        names = [require_model(m, "calibrate").name for m in models]
        if len(set(names)) != len(names):
            raise ValueError(f"calibrate: a model is given twice ({names})")
        boxes = {m: m.prior_bounds(torch.float64) for m in models}
    if not boxes:
        raise ValueError("calibrate: no model given")
    return boxes


__all__ = ["drawn_and_held", "held_values", "prior_boxes"]
