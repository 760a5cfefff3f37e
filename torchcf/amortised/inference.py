"""Amortised inference: every pair of a pair set in batched forward passes.

For each pair, its whole observed series (any length: the encoder pools over
time) gives the models' probabilities ``q(m | x)`` and ``n`` samples of
(model, parameters) from ``q(m, theta | x)``.

The pairs are read in chunks of ``chunk_size`` (one forward pass of the
encoder per chunk, the chunk's series cut to its longest pair). The random
numbers of pair ``j`` (its position in the set) come from its own generator,
seeded by a hash of ``(seed, j)`` (:func:`torchcf.abc.streams.block_seed`),
and every network operation is per pair, so a pair's result does not depend on
the chunk size or on the other pairs of its chunk (up to the rounding of the
convolution and matrix kernels on batches of different sizes).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ..abc.streams import block_seed
from ..data import PairSet
from .estimator import AmortisedEstimator
from .features import pair_features


class PairPosteriors(NamedTuple):
    """The amortised posterior of N pairs.

    Attributes:
        probabilities: (N, M) float32 ``q(m | x)`` of each pair.
        model: (N, n) int64 the sampled models' positions in the space.
        theta: (N, n, K) float32 the sampled parameters [SI], each inside its
            model's prior box, NaN past the model's own K_m.
        n_params: (K_m,) per model of the space.

    Examples:
        >>> import torch
        >>> theta = torch.tensor([[[1.0, 2.0], [3.0, float("nan")], [5.0, 6.0]]])
        >>> model = torch.tensor([[0, 1, 0]])  # (N, n): one pair, 3 samples
        >>> posteriors = PairPosteriors(torch.tensor([[0.75, 0.25]]), model, theta,
        ...                             n_params=(2, 1))
        >>> pair, samples = posteriors.of_model(0)  # 3 samples, 2 of model 0
        >>> pair, samples
        (tensor([0, 0]), tensor([[1., 2.],
                [5., 6.]]))
    """

    probabilities: Tensor
    model: Tensor
    theta: Tensor
    n_params: tuple[int, ...]

    def of_model(self, model: int) -> tuple[Tensor, Tensor]:
        """The samples of model ``model``: ``(pair (Q,) int64, theta (Q, K_m))``
        in pair order, Q the samples that drew it."""
        pair, sample = (self.model == model).nonzero(as_tuple=True)
        return pair, self.theta[pair, sample, : self.n_params[model]]


def infer(
    estimator: AmortisedEstimator,
    pairs: PairSet,
    n_samples: int,
    *,
    seed: int = 0,
    chunk_size: int = 1024,
    compile: bool = False,
) -> PairPosteriors:
    """The models' probabilities and ``n_samples`` samples per pair.

    Args:
        estimator: the trained estimator.
        pairs: the N pairs (on the CPU).
        n_samples: n, samples of (model, parameters) per pair.
        seed: the samples are a function of it and each pair's position.
        chunk_size: pairs per forward pass.
        compile: the flows' sampling compiled
            (:meth:`AmortisedEstimator.draw`; the same samples up to float32
            rounding).

    Returns:
        :class:`PairPosteriors`.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> from torchcf.amortised import ParameterSpace, new_estimator
        >>> idm = get_model("idm")
        >>> pairs = synthetic_pairs(idm, [1.5, 2.0, 33.0, 1.2, 2.0, 4.0], 4, n_steps=50)
        >>> estimator = new_estimator(ParameterSpace([idm, get_model("ovm")]))
        >>> posteriors = infer(estimator, pairs, n_samples=8)  # an untrained estimator
        >>> posteriors.probabilities.shape, posteriors.theta.shape  # (N, M), (N, n, K)
        (torch.Size([4, 2]), torch.Size([4, 8, 6]))
    """
    if n_samples < 1 or chunk_size < 1:
        raise ValueError(
            f"n_samples and chunk_size must be >= 1, got {n_samples}, {chunk_size}"
        )
    features, lengths = pair_features(pairs)
    n_pairs, width = pairs.n_pairs, estimator.space.width
    probabilities, models, thetas = [], [], []
    estimator.eval()
    with torch.no_grad():
        for start in range(0, n_pairs, chunk_size):
            stop = min(start + chunk_size, n_pairs)
            chunk_lengths = lengths[start:stop]
            longest = int(chunk_lengths.max())
            embedding = estimator.embed(
                features[start:stop, :, :longest], chunk_lengths
            )
            uniform, normal = _pair_random_numbers(seed, start, stop, n_samples, width)
            draws = estimator.draw(embedding, uniform, normal, compiled=compile)
            probabilities.append(torch.softmax(estimator.model_logits(embedding), 1))
            models.append(draws.model)
            thetas.append(draws.theta)
    return PairPosteriors(
        torch.cat(probabilities),
        torch.cat(models),
        torch.cat(thetas),
        estimator.space.n_params,
    )


def _pair_random_numbers(
    seed: int, start: int, stop: int, n: int, width: int
) -> tuple[Tensor, Tensor]:
    """The random numbers of pairs ``start .. stop-1``: ``(stop - start, n)``
    uniforms and ``(stop - start, n, K)`` standard normals, pair ``j``'s from
    its own generator."""
    uniform = torch.empty(stop - start, n)
    normal = torch.empty(stop - start, n, width)
    generator = torch.Generator()
    for row, pair in enumerate(range(start, stop)):
        generator.manual_seed(block_seed(seed, "amortised/inference", pair))
        uniform[row] = torch.rand(n, generator=generator)
        normal[row] = torch.randn(n, width, generator=generator)
    return uniform, normal


__all__ = ["PairPosteriors", "infer"]
