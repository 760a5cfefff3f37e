"""The hybrid's predictive distribution of a pair: its median and bands.

The hybrid is a distribution over drivers: a new pair's follower is one driver
of it, unknown. Each pair gets ``draws`` particles drawn uniformly from the
hybrid's particles pooled over its models (so each model is drawn at its share),
with replacement, from a generator of the pair's own (the prediction's seed
and the pair's id); each drives
the pair behind its recorded leader from the recorded start. Per step, the
spacing of the draws gives the **predictive median** and the **bands** of 50 %
(quantiles 0.25-0.75) and 90 % (0.05-0.95). A draw that collides is counted
and left out of the median, the bands and the draws' scores: from the
collision on its trajectory is physically meaningless (SPEC section 2), and
kept it widens the bands by drivers that cannot exist (on NGSIM I-80 the 90 %
band covered 96.5 % of the recorded steps with them, 94.3 % without).

Shapes: T steps, N pairs, D draws per pair, H hybrid particles
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..abc.streams import block_seed
from ..data import PairSet
from .rollouts import Particles, follow, padded
from .trained import TrainedRun

#: Quantiles of the bands: 90 % low, 50 % low, median, 50 % high, 90 % high.
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
#: Pairs simulated at once (bounds the memory of T x chunk x D trajectories).
PAIRS_PER_CHUNK = 64


@dataclass(frozen=True)
class Bands:
    """The hybrid's predictive spacing of every pair [m].

    Attributes:
        quantiles: ``(5, T, N)`` float64 the spacing's :data:`QUANTILES` per
            step (NaN past a pair's recorded steps).
        draw_error: ``(T, N, D)`` float64 the draws' position error ``x_sim -
            x_obs`` [m] (the negative spacing error; NaN for a draw that
            collided).
        collided: ``(N,)`` int64 the pair's draws that collided.
        draws: D.
    """

    quantiles: Tensor
    draw_error: Tensor
    collided: Tensor
    draws: int

    @property
    def median(self) -> Tensor:
        return self.quantiles[2]


def hybrid_draws(run: TrainedRun, pairs: PairSet, draws: int, seed: int) -> Particles:
    """``draws`` particles of the hybrid per pair, pair-major (particle ``j *
    draws + d`` is pair j's draw d; module docstring). A pair's draws come from
    a generator of its own, seeded by ``seed`` and its id: they do not depend
    on the other pairs predicted with it."""
    models = run.hybrid_models
    model_of, theta = padded(models, [run.particles(m) for m in models])
    pick = torch.cat(
        [
            torch.randint(
                len(model_of),
                (draws,),
                generator=torch.Generator().manual_seed(
                    block_seed(seed, "predict", int(pair_id))
                ),
            )
            for pair_id in pairs.pair_ids
        ]
    )
    pair_index = torch.arange(pairs.n_pairs).repeat_interleave(draws)
    return Particles(tuple(models), model_of[pick], theta[pick], pair_index)


def predictive_bands(run: TrainedRun, pairs: PairSet, draws: int, seed: int) -> Bands:
    """The hybrid's median and bands on every pair of ``pairs`` (module
    docstring); the draws of pair j do not depend on the other pairs."""
    particles = hybrid_draws(run, pairs, draws, seed)
    quantiles, errors, collided = [], [], []
    for start in range(0, pairs.n_pairs, PAIRS_PER_CHUNK):
        chunk = list(range(start, min(start + PAIRS_PER_CHUNK, pairs.n_pairs)))
        part = pairs.subset(chunk)
        rows = torch.arange(start * draws, (start + len(chunk)) * draws)
        paths = follow(particles.rows(int(rows[0]), int(rows[-1]) + 1, start), part)
        x = paths.x.reshape(part.n_steps, len(chunk), draws)
        x_obs = part.x_follow.double().cpu()[:, :, None]
        gap = part.x_lead.double().cpu()[:, :, None] - x - part.leader_length
        valid = paths.valid.reshape(1, len(chunk), draws)
        gap = torch.where(valid, gap, torch.full_like(gap, float("nan")))
        levels = torch.tensor(QUANTILES, dtype=torch.float64)
        q = torch.nanquantile(gap, levels, dim=2)  # (5, T, n); NaN: all collided
        q[:, ~part.mask.cpu()] = math.nan
        quantiles.append(q)
        errors.append(torch.where(valid, x - x_obs, torch.full_like(x, float("nan"))))
        collided.append((~paths.valid).reshape(len(chunk), draws).sum(1))
    return Bands(
        quantiles=torch.cat(quantiles, 2),
        draw_error=torch.cat(errors, 1),
        collided=torch.cat(collided),
        draws=draws,
    )


__all__ = ["QUANTILES", "Bands", "hybrid_draws", "predictive_bands"]
