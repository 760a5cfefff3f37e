"""A simulation demo: each model's prior particles on CAR MODEL II training pairs.

    torchcf demo [--particles 200000] [--dataset NAME] [--data-root DIR]

Draws particles uniformly from each model's default prior, simulates each on one
randomly chosen training pair (the paper's down-sampled layout), and gives per
model the best and median score, the invalid fraction and the throughput
(:func:`prior_rollouts`; the command line that prints them:
:mod:`torchcf.cli.demo`). This is the engine underneath ABC; ``torchcf train``
builds on it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from ..data import PairSet
from ..models import MODELS
from ..sim.rollout import simulate


@dataclass(frozen=True)
class DemoRow:
    """One model's prior particles on the pairs.

    Examples:
        >>> from dataclasses import fields
        >>> from torchcf.study.demo import DemoRow
        >>> [f.name for f in fields(DemoRow)]
        ['model', 'best', 'median', 'invalid', 'steps_per_second']
    """

    model: str
    best: float  # the smallest valid score (inf: none valid)
    median: float  # the median valid score (inf: none valid)
    invalid: float  # the fraction of invalid rollouts
    steps_per_second: float  # particle-steps simulated per second


def prior_rollouts(pairs: PairSet, particles: int, seed: int = 0) -> Iterator[DemoRow]:
    """Per model, ``particles`` draws of its default prior simulated, each on one
    random pair of ``pairs`` (one generator seeded ``seed`` for all models).

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> from torchcf.study.demo import prior_rollouts
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=2, n_steps=60)
        >>> rows = list(prior_rollouts(pairs, particles=200))
        >>> [row.model for row in rows] == list(MODELS)  # each registered model
        True
        >>> all(0 <= row.invalid <= 1 for row in rows)  # invalid rollouts' share
        True
    """
    generator = torch.Generator().manual_seed(seed)
    for name, model in MODELS.items():
        bounds = model.prior_bounds(torch.float32)
        unit = torch.rand(particles, model.n_params, generator=generator)
        theta = bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * unit
        pair_index = torch.randint(0, pairs.n_pairs, (particles,), generator=generator)
        start = time.perf_counter()
        out = simulate(model, theta, pairs, pair_index)
        elapsed = time.perf_counter() - start
        valid_scores = out.score[out.valid]
        best = float(valid_scores.min()) if valid_scores.numel() else float("inf")
        median = float(valid_scores.median()) if valid_scores.numel() else float("inf")
        yield DemoRow(
            name,
            best,
            median,
            float((~out.valid).float().mean()),
            particles * pairs.n_steps / elapsed,
        )
