"""The conditional density of (model, parameters) given a pair's series.

``q(m, theta | x) = q(m | x) q_m(theta | x)``:

- the encoder (:class:`~torchcf.amortised.encoder.TrajectoryEncoder`) maps the
  series ``x`` to an embedding ``e`` (E values);
- the *model head*, a two-layer perceptron of ``e``, gives the M models'
  logits: ``q(m | x)`` is their softmax;
- *one flow per model*, a neural spline flow of zuko (``zuko.flows.NSF``,
  coupling layers: sampling is one pass per layer) conditioned on ``e``, is the
  density of the model's parameters in the unbounded space ``z = logit(u)`` of
  the unit-cube coordinate ``u`` of its prior box
  (:mod:`~torchcf.amortised.space`), so that every sample lies in the box.

Shapes: J series (``features (J, C, T)``, ``lengths (J,)``); parameters of
several models share a ``(J, K)`` tensor, NaN past a model's own K_m; ``n``
samples per series.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
import zuko
from torch import Tensor, nn

from ..sim.compiled import compile_any_batch
from .encoder import EncoderSettings, TrajectoryEncoder
from .space import (
    ParameterSpace,
    latent_to_unit,
    log_jacobian,
    unit_to_latent,
)


@dataclass(frozen=True)
class EstimatorSettings:
    """The estimator's size.

    Attributes:
        encoder: the trajectory encoder's.
        head_width: hidden units of the model head.
        transforms: spline coupling layers per flow.
        flow_width: hidden units of each layer's two-layer conditioner.
        bins: spline bins.

    Examples:
        >>> tiny = EstimatorSettings(EncoderSettings(width=8), transforms=1)
        >>> tiny.encoder.width, tiny.transforms, tiny.head_width
        (8, 1, 64)
    """

    encoder: EncoderSettings = field(default_factory=EncoderSettings)
    head_width: int = 64
    transforms: int = 3
    flow_width: int = 64
    bins: int = 8


class Draws(NamedTuple):
    """Samples of (model, parameters), n per series.

    Attributes:
        model: (J, n) int64, the model's position in the space.
        theta: (J, n, K) parameters [SI] inside the model's box, NaN past its
            own K_m; float32.

    Examples:
        >>> import torch
        >>> draws = Draws(model=torch.tensor([[0, 1]]), theta=torch.zeros(1, 2, 6))
        >>> model, theta = draws  # a named tuple
        >>> model.shape, theta.shape
        (torch.Size([1, 2]), torch.Size([1, 2, 6]))
    """

    model: Tensor
    theta: Tensor


class AmortisedEstimator(nn.Module):
    """``q(m, theta | x)`` over a :class:`ParameterSpace` (module docstring).

    Args:
        space: the models and their prior boxes (the flows' sizes follow it).
        settings: the networks' sizes.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.amortised import ParameterSpace
        >>> estimator = AmortisedEstimator(ParameterSpace([get_model("idm")]))
        >>> features, lengths = torch.zeros(2, 5, 30), torch.tensor([30, 20])
        >>> estimator.model_probabilities(features, lengths)  # one model: certain
        tensor([[1.],
                [1.]])
        >>> estimator.sample(features, lengths, n=4).theta.shape  # (J, n, K)
        torch.Size([2, 4, 6])
    """

    def __init__(
        self, space: ParameterSpace, settings: EstimatorSettings = EstimatorSettings()
    ) -> None:
        super().__init__()
        self.space = space
        self.settings = settings
        embedding = settings.encoder.embedding
        self.encoder = TrajectoryEncoder(settings.encoder)
        self.head = nn.Sequential(
            nn.Linear(embedding, settings.head_width),
            nn.GELU(),
            nn.Linear(settings.head_width, space.n_models),
        )
        self.flows = nn.ModuleList(
            zuko.flows.NSF(
                features=k,
                context=embedding,
                transforms=settings.transforms,
                bins=settings.bins,
                hidden_features=(settings.flow_width, settings.flow_width),
                passes=2 if k > 1 else None,  # coupling: one pass to sample
            )
            for k in space.n_params
        )
        self._compiled: dict[int, Callable[[Tensor, Tensor], Tensor]] = {}

    def embed(self, features: Tensor, lengths: Tensor) -> Tensor:
        """(J, C, T) series, (J,) lengths -> (J, E) embeddings."""
        return self.encoder(features, lengths)

    def model_logits(self, embedding: Tensor) -> Tensor:
        """(J, E) embeddings -> (J, M) logits of ``q(m | x)``."""
        return self.head(embedding)

    def latent_log_prob(self, embedding: Tensor, model: Tensor, unit: Tensor) -> Tensor:
        """``log q(m | x) + log q_m(z | x)`` in the flows' unbounded space: the
        training loss's negative (the box's Jacobian is a constant of theta).

        Args:
            embedding: (J, E).
            model: (J,) int64 model positions.
            unit: (J, K) unit-cube coordinates, NaN past each model's K_m.

        Returns:
            (J,) float32.
        """
        log_model = torch.log_softmax(self.model_logits(embedding), dim=1)
        total = log_model.gather(1, model[:, None]).squeeze(1)
        parts = torch.zeros_like(total)
        for m, flow in enumerate(self.flows):
            rows = (model == m).nonzero().squeeze(1)
            if not rows.numel():
                continue
            k = self.space.n_params[m]
            latent = unit_to_latent(unit[rows, :k].to(embedding))
            parts = parts.index_put((rows,), flow(embedding[rows]).log_prob(latent))
        return total + parts

    def log_prob(
        self, model: Tensor, theta: Tensor, features: Tensor, lengths: Tensor
    ) -> Tensor:
        """``log q(m, theta | x)``, the density over (model, parameters in SI
        units): the latent density plus the box's Jacobian.

        Args:
            model: (J,) int64 model positions.
            theta: (J, K) parameters [SI], NaN past each model's K_m; inside
                the box.
            features: (J, C, T) float32 series; lengths: (J,) int64.

        Returns:
            (J,) float32.
        """
        space = self.space
        unit = torch.full_like(theta, math.nan, dtype=torch.float64)
        jacobian = torch.zeros(theta.shape[0], dtype=torch.float64)
        for m in range(space.n_models):
            rows = (model == m).nonzero().squeeze(1)
            k = space.n_params[m]
            unit[rows, :k] = space.to_unit(m, theta[rows, :k].to(torch.float64))
            # d theta / d z = span * u (1 - u): its log is subtracted
            jacobian[rows] = log_jacobian(unit[rows, :k]) + space.log_span(m)
        embedding = self.embed(features, lengths)
        latent = self.latent_log_prob(embedding, model, unit)
        return latent - jacobian.to(latent)

    def draw(
        self,
        embedding: Tensor,
        uniform: Tensor,
        normal: Tensor,
        compiled: bool = False,
    ) -> Draws:
        """Samples from given random numbers: sample ``i`` of series ``j`` takes
        the model whose cumulative probability first exceeds ``uniform[j, i]``
        and the parameters its flow maps ``normal[j, i, :K_m]`` to.

        A sample depends on its own series and random numbers alone (every
        operation is per row), so samples do not depend on the batch.

        Args:
            embedding: (J, E).
            uniform: (J, n) in [0, 1).
            normal: (J, n, K) standard normal.
            compiled: each flow's inverse through ``torch.compile`` (one graph
                per model for any number of samples; the same samples up to
                float32 rounding; the compilation pays from millions of samples,
                ``reports/bench/amortised.md``).

        Returns:
            :class:`Draws`.
        """
        n_series, n = uniform.shape
        probabilities = torch.softmax(self.model_logits(embedding), dim=1)
        cumulative = probabilities.cumsum(1)  # (J, M)
        model = torch.searchsorted(
            cumulative, uniform.to(cumulative).contiguous(), right=True
        )
        model = model.clamp_(max=self.space.n_models - 1)  # (J, n)
        theta = torch.full(
            (n_series, n, self.space.width), math.nan, dtype=embedding.dtype
        )
        flat_model = model.reshape(-1)
        flat_normal = normal.reshape(n_series * n, -1).to(embedding)
        series = torch.arange(n_series).repeat_interleave(n)  # (J n,)
        flat_theta = theta.view(n_series * n, -1)
        for m, flow in enumerate(self.flows):
            rows = (flat_model == m).nonzero().squeeze(1)
            if not rows.numel():
                continue
            k = self.space.n_params[m]
            context = embedding[series[rows]]
            inverse = self._compiled_inverse(m) if compiled else _inverse(flow)
            latent = inverse(context, flat_normal[rows, :k])
            unit = latent_to_unit(latent)
            flat_theta[rows, :k] = self.space.to_theta(m, unit)
        return Draws(model, theta)

    def _compiled_inverse(self, model: int) -> Callable[[Tensor, Tensor], Tensor]:
        """The inverse of flow ``model``, compiled once per estimator."""
        if model not in self._compiled:
            self._compiled[model] = compile_any_batch(_inverse(self.flows[model]))
        return self._compiled[model]

    def sample(
        self,
        features: Tensor,
        lengths: Tensor,
        n: int,
        generator: torch.Generator | None = None,
    ) -> Draws:
        """``n`` samples of (model, parameters) for each of J series, the random
        numbers drawn from ``generator`` (for samples that are a pure function
        of each pair, :func:`torchcf.amortised.inference.infer`).

        Args:
            features: (J, C, T) float32; lengths: (J,) int64.
            n: samples per series.
        """
        n_series = features.shape[0]
        uniform = torch.rand(n_series, n, generator=generator)
        normal = torch.randn(n_series, n, self.space.width, generator=generator)
        with torch.no_grad():
            return self.draw(self.embed(features, lengths), uniform, normal)

    def model_probabilities(self, features: Tensor, lengths: Tensor) -> Tensor:
        """(J, M) ``q(m | x)`` of J series."""
        with torch.no_grad():
            return torch.softmax(self.model_logits(self.embed(features, lengths)), 1)


def _inverse(flow: nn.Module) -> Callable[[Tensor, Tensor], Tensor]:
    """(context (R, E), normal (R, K_m)) -> latent (R, K_m): the flow's map
    from its base distribution to the parameters' unbounded space."""

    def inverse(context: Tensor, normal: Tensor) -> Tensor:
        return flow(context).transform.inv(normal)

    return inverse


def new_estimator(
    space: ParameterSpace,
    settings: EstimatorSettings = EstimatorSettings(),
    seed: int = 0,
) -> AmortisedEstimator:
    """A freshly initialised estimator, its weights a function of ``seed``
    alone (the global random state is left as it was).

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> from torchcf.amortised import ParameterSpace
        >>> space = ParameterSpace([get_model("idm"), get_model("ovm")])
        >>> one, two = new_estimator(space, seed=1), new_estimator(space, seed=1)
        >>> all(torch.equal(p, q) for p, q in zip(one.parameters(), two.parameters()))
        True
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return AmortisedEstimator(space, settings)


__all__ = ["AmortisedEstimator", "Draws", "EstimatorSettings", "new_estimator"]
