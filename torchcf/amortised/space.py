"""The space the amortised estimator works in: M models, each with its uniform
prior box, and the map of a box onto an unbounded space.

A parameter vector ``theta`` of model ``m`` (K_m values in SI units, the
model's order) is carried as its *unit-cube coordinate*
``u = (theta - low) / (high - low)`` in ``[0, 1]^K_m``, and a flow works on
``z = logit(u)``, unbounded, so that every flow sample maps back inside the box:
``theta = low + (high - low) sigmoid(z)``. The density changes by the
Jacobian ``log |d theta / d z| = sum_k log(high_k - low_k) + log u_k + log(1 - u_k)``.

Several models' parameters share one ``(.., K)`` tensor, K the largest K_m of
the models; the columns past a model's own K_m hold NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from ..models import CFModel, require_model

#: The unit-cube coordinate is kept this far inside (0, 1) before its logit, so
#: that a prior bound (or a float32 sigmoid rounded to 1) stays finite.
UNIT_MARGIN = 1e-6


class ParameterSpace:
    """M models and their uniform prior boxes.

    Args:
        models: the M model objects, in the order of the estimator's model head.
        bounds: per model, its ``(K_m, 2)`` box of ``[low, high]`` in SI units
            (``low < high``); None: each model's own prior
            (:meth:`CFModel.prior_bounds`).

    Attributes:
        models: the models, as given.
        names: their names.
        low, high: (M, K) float64 box bounds, NaN past a model's own K_m.
        n_params: (K_m,) per model.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> space = ParameterSpace([get_model("idm"), get_model("ovm")])
        >>> space.names, space.n_params, space.width
        (('idm', 'ovm'), (6, 5), 6)
        >>> space.to_theta(0, torch.full((6,), 0.5))  # the centre of the IDM's box
        tensor([ 1.2500,  2.5000, 30.0000,  1.6500,  1.7500,  3.5000])
    """

    def __init__(
        self, models: Sequence[CFModel], bounds: Sequence[Tensor] | None = None
    ) -> None:
        self.models = tuple(require_model(m, "ParameterSpace") for m in models)
        if not self.models:
            raise ValueError("ParameterSpace needs at least one model")
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"models listed twice: {names}")
        if bounds is None:
            bounds = [m.prior_bounds(torch.float64) for m in self.models]
        if len(bounds) != len(self.models):
            raise ValueError(f"{len(bounds)} boxes for {len(self.models)} models")
        self.names = tuple(names)
        self.n_params = tuple(m.n_params for m in self.models)
        width = max(self.n_params)
        self.low = torch.full((len(names), width), math.nan, dtype=torch.float64)
        self.high = self.low.clone()
        for i, (model, box) in enumerate(zip(self.models, bounds, strict=True)):
            box = torch.as_tensor(box, dtype=torch.float64)
            if box.shape != (model.n_params, 2):
                raise ValueError(
                    f"{model.name}: box of shape {tuple(box.shape)}, "
                    f"needs ({model.n_params}, 2)"
                )
            if not bool((box[:, 0] < box[:, 1]).all()):
                raise ValueError(f"{model.name}: every prior needs low < high")
            self.low[i, : model.n_params] = box[:, 0]
            self.high[i, : model.n_params] = box[:, 1]

    @property
    def n_models(self) -> int:
        """M."""
        return len(self.models)

    @property
    def width(self) -> int:
        """K, the largest K_m: the columns of a shared parameter tensor."""
        return self.low.shape[1]

    def box(self, model: int) -> Tensor:
        """Model ``model``'s ``(K_m, 2)`` float64 box."""
        k = self.n_params[model]
        return torch.stack((self.low[model, :k], self.high[model, :k]), dim=1)

    def to_theta(self, model: int, unit: Tensor) -> Tensor:
        """``(.., K_m)`` unit-cube coordinates of model ``model`` -> parameters
        [SI], in the box; the dtype of ``unit``."""
        k = self.n_params[model]
        low = self.low[model, :k].to(unit)
        span = self.high[model, :k].to(unit) - low
        return low + span * unit.clamp(0.0, 1.0)

    def to_unit(self, model: int, theta: Tensor) -> Tensor:
        """``(.., K_m)`` parameters [SI] of model ``model`` -> unit-cube
        coordinates; the dtype of ``theta``."""
        k = self.n_params[model]
        low = self.low[model, :k].to(theta)
        return (theta - low) / (self.high[model, :k].to(theta) - low)

    def log_span(self, model: int) -> float:
        """``sum_k log(high_k - low_k)`` of model ``model``: the log volume of
        its box (``-log`` of its prior density)."""
        k = self.n_params[model]
        return float(torch.log(self.high[model, :k] - self.low[model, :k]).sum())

    def __repr__(self) -> str:
        return f"ParameterSpace({', '.join(self.names)})"


def unit_to_latent(unit: Tensor) -> Tensor:
    """Unit-cube coordinates -> the flow's unbounded space, ``logit(u)``, with
    ``u`` kept :data:`UNIT_MARGIN` inside (0, 1)."""
    return torch.logit(unit.clamp(UNIT_MARGIN, 1.0 - UNIT_MARGIN))


def latent_to_unit(latent: Tensor) -> Tensor:
    """The flow's unbounded space -> unit-cube coordinates, ``sigmoid(z)``."""
    return torch.sigmoid(latent)


def log_jacobian(unit: Tensor) -> Tensor:
    """``sum_k log u_k (1 - u_k)`` over the last dimension: ``log |du / dz|``
    at ``u = sigmoid(z)`` (the box's span is :meth:`ParameterSpace.log_span`),
    with ``u`` kept :data:`UNIT_MARGIN` inside (0, 1)."""
    unit = unit.clamp(UNIT_MARGIN, 1.0 - UNIT_MARGIN)
    return (torch.log(unit) + torch.log1p(-unit)).sum(-1)


__all__ = [
    "UNIT_MARGIN",
    "ParameterSpace",
    "latent_to_unit",
    "log_jacobian",
    "unit_to_latent",
]
