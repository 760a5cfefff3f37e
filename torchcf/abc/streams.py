"""Reproducible particle streams (SPEC section 5).

Particle ``j`` of model ``m`` (and, in the paired layout, the training pair it is
simulated on) is a pure function of ``(seed, m, j)``: a run gives the same particles
whatever its chunk size, its number of workers, or where it was interrupted and
resumed.

How: the stream is cut into fixed blocks of :data:`STREAM_BLOCK` particles. Block
``b`` is drawn by its own ``torch.Generator`` (Mersenne Twister) seeded with a
SplitMix64 hash of ``(seed, model name, b)``, as a ``(STREAM_BLOCK, K + 1)`` table
of float64 uniforms in [0, 1): columns ``0 .. K-1`` map to the parameters, column
``K`` to the pair. Any range of particles is then read from the blocks it overlaps.
The block size is part of the stream's definition, not a tuning knob.

The model enters through a CRC-32 of its name, not its position in the config, so
reordering or dropping models leaves every other model's particles unchanged:
:func:`block_seed` and :func:`uniforms` take the name (the bytes hashed), and a
:class:`ParticleStream` holds the model object and hashes its ``name``.
"""

from __future__ import annotations

import zlib

import torch
from torch import Tensor

from ..models import CFModel, require_model

#: Particles per generator block (part of the definition of every stream).
STREAM_BLOCK = 4096

_MASK64 = (1 << 64) - 1


def _splitmix64(value: int) -> int:
    """One SplitMix64 output for state ``value`` (Steele, Lea & Flood 2014)."""
    z = (value + 0x9E3779B97F4A7C15) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def block_seed(seed: int, model: str, block: int) -> int:
    """Generator seed of block ``block`` of model ``model``'s stream: a 63-bit hash
    of the run's seed, the model's name (its canonical name: the bytes that
    enter the hash) and the block."""
    h = _splitmix64(seed & _MASK64)
    h = _splitmix64(h ^ zlib.crc32(model.encode()))
    h = _splitmix64(h ^ (block & _MASK64))
    return h >> 1  # torch seeds are taken modulo 2^64; keep them non-negative


def uniforms(seed: int, model: str, start: int, stop: int, width: int) -> Tensor:
    """Uniforms of particles ``start .. stop-1``: ``(stop - start, width)`` float64.

    Row ``i`` depends only on ``(seed, model, start + i, width)``; ``model`` is the
    model's name, hashed by :func:`block_seed`.
    """
    if not 0 <= start <= stop:
        raise ValueError(f"need 0 <= start <= stop, got {start}, {stop}")
    if stop == start:
        return torch.empty(0, width, dtype=torch.float64)
    first, last = start // STREAM_BLOCK, (stop - 1) // STREAM_BLOCK
    parts = []
    generator = torch.Generator()
    for block in range(first, last + 1):
        generator.manual_seed(block_seed(seed, model, block))
        table = torch.rand(
            STREAM_BLOCK, width, generator=generator, dtype=torch.float64
        )
        lo = max(start - block * STREAM_BLOCK, 0)
        hi = min(stop - block * STREAM_BLOCK, STREAM_BLOCK)
        parts.append(table[lo:hi])
    return torch.cat(parts)


class ParticleStream:
    """The particles of one model: uniform prior box, and a pair per particle.

    The stream draws the model's first ``K_drawn`` parameters; a variant whose
    last ones are held (a shared effect's one value for every pair) carries
    their values in ``fixed``, appended to every drawn particle before it is
    simulated (:class:`torchcf.abc.rounds.Plan`).

    Args:
        model: the simulated model (object); its ``name`` enters the stream's
            hash (:func:`block_seed`), so a stream depends on the name alone.
        bounds: (K_drawn, 2) float64 ``[low, high]`` per drawn parameter.
        seed: the run's seed.
        n_pairs: training pairs for the paired layout, or None (full layout).
        fixed: (K - K_drawn,) float64 values of the model's last parameters,
            the same for every particle; None: every parameter is drawn.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> idm = get_model("idm")
        >>> stream = ParticleStream(idm, idm.prior_bounds(), seed=0, n_pairs=3)
        >>> theta, pair = stream.draw(0, 5)  # particles 0 .. 4
        >>> theta.shape, pair.shape
        (torch.Size([5, 6]), torch.Size([5]))
        >>> torch.equal(stream.draw(2, 4)[0], theta[2:4])  # whatever the chunking
        True
    """

    def __init__(
        self,
        model: CFModel,
        bounds: Tensor,
        seed: int,
        n_pairs: int | None = None,
        fixed: Tensor | None = None,
    ) -> None:
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        if bounds.ndim != 2 or bounds.shape[1] != 2:
            raise ValueError(f"bounds must be (K, 2), got {tuple(bounds.shape)}")
        if not bool((bounds[:, 0] < bounds[:, 1]).all()):
            raise ValueError("every prior needs low < high")
        if n_pairs is not None and n_pairs < 1:
            raise ValueError(f"n_pairs must be >= 1, got {n_pairs}")
        self.model = require_model(model, "ParticleStream")
        self.bounds = bounds
        self.seed = int(seed)
        self.n_pairs = n_pairs
        self.fixed = fixed

    def draw(self, start: int, stop: int) -> tuple[Tensor, Tensor | None]:
        """Particles ``start .. stop-1``.

        Returns:
            theta: (stop - start, K) float64, ``low + (high - low) u``;
            pair: (stop - start,) int64 uniform over ``0 .. n_pairs-1`` (paired), else
                None.
        """
        k = self.bounds.shape[0]
        u = uniforms(self.seed, self.model.name, start, stop, k + 1)
        low, high = self.bounds[:, 0], self.bounds[:, 1]
        theta = low + (high - low) * u[:, :k]
        if self.n_pairs is None:
            return theta, None
        pair = (u[:, k] * self.n_pairs).long().clamp_(max=self.n_pairs - 1)
        return theta, pair


__all__ = ["STREAM_BLOCK", "ParticleStream", "block_seed", "uniforms"]
