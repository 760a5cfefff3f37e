"""Identifiability of a found effect: does the data tell it apart from the model?

Some effects trade off against a pool model's own parameters: a constant
spacing offset ``d_offset`` against a standstill gap ``s0`` (LLCS perceives
``s + d_offset - s0``: only the difference is identified), a short delay against
an actuation lag. The accepted particles then lie along a ridge, and the
effect's value alone means little.

Measured on the re-calibrated run's buffers (the ``buffer_size`` best particles
of every augmented model on every training pair): each parameter is centred per
pair (so that the pairs' different drivers do not make a correlation of their
own), the centred values are pooled over pairs, and the Pearson correlation of
every effect parameter with every model parameter is taken. The report gives,
per effect parameter, its strongest partner; ``|r| >=``
:data:`RIDGE_CORRELATION` flags a trade-off.

Shapes: N pairs, C buffer slots, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...models import get_model
from ...models.effects import Effect
from ...posterior import Posterior
from ...system.records import Record

#: |Pearson r| from which an effect parameter is reported as traded off against
#: a model parameter.
RIDGE_CORRELATION = 0.7
#: Pairs need this many finite particles to enter the pooled correlation.
MIN_PER_PAIR = 3


def within_pair_correlation(theta: Tensor, score: Tensor) -> tuple[Tensor, int]:
    """(K, K) Pearson correlation of the parameters, centred per pair.

    Args:
        theta: (N, C, K) buffered particles.
        score: (N, C) their scores (``+inf``: an empty slot).

    Returns:
        the correlation matrix (NaN where a parameter does not vary) and the
        number of pairs used.
    """
    held = torch.isfinite(score)  # (N, C)
    usable = held.sum(1) >= MIN_PER_PAIR  # (N,)
    theta, held = theta[usable].double(), held[usable]
    weight = held.double()[..., None]  # (N, C, 1)
    count = weight.sum(1, keepdim=True)
    mean = (theta * weight).sum(1, keepdim=True) / count
    centred = ((theta - mean) * weight).reshape(-1, theta.shape[-1])  # (N C, K)
    covariance = centred.T @ centred
    scale = torch.sqrt(torch.diagonal(covariance))
    # a constant parameter divides 0 by 0: NaN, left out by the caller
    correlation = covariance / (scale[:, None] * scale[None, :])
    return correlation, int(usable.sum())


@dataclass(frozen=True)
class Partner(Record):
    """An effect parameter's strongest partner among a model's own parameters.

    Attributes:
        partner: the model parameter.
        r: their within-pair Pearson correlation (pooled over pairs).
        traded_off: ``|r| >=`` :data:`RIDGE_CORRELATION`.
        n_pairs: the pairs the correlation pools.
    """

    partner: str
    r: float
    traded_off: bool
    n_pairs: int


#: Per chosen effect's token, per augmented model carrying it, per effect
#: parameter: its strongest partner (:func:`effect_identifiability`).
Identifiability = dict[str, dict[str, dict[str, Partner]]]


def effect_identifiability(
    posterior: Posterior, chosen: list[Effect]
) -> Identifiability:
    """Per chosen effect and per augmented model carrying it, each effect
    parameter's strongest partner among the model's parameters (a model where
    no parameter has one is left out; an effect no model carries maps to
    ``{}``)."""
    report: Identifiability = {}
    for effect in chosen:
        names = [p.name for p in effect.param_specs]
        per_model: dict[str, dict[str, Partner]] = {}
        for model_name, buffer in posterior.buffers.items():
            model = get_model(model_name)
            if effect.name not in model.effect_kinds:
                continue
            base = list(model.pool_model.param_names)
            columns = list(model.param_names)
            theta = buffer["theta"][..., : len(columns)]
            correlation, n_pairs = within_pair_correlation(theta, buffer["score"])
            rows: dict[str, Partner] = {}
            for name in names:
                i = columns.index(name)
                partners = {
                    other: float(correlation[i, columns.index(other)])
                    for other in base
                    if math.isfinite(float(correlation[i, columns.index(other)]))
                }
                if not partners:
                    continue
                partner = max(partners, key=lambda k: abs(partners[k]))
                r = partners[partner]
                rows[name] = Partner(
                    partner=partner,
                    r=r,
                    traded_off=abs(r) >= RIDGE_CORRELATION,
                    n_pairs=n_pairs,
                )
            if rows:
                per_model[model_name] = rows
        report[effect.token] = per_model
    return report


__all__ = [
    "Identifiability",
    "MIN_PER_PAIR",
    "Partner",
    "RIDGE_CORRELATION",
    "effect_identifiability",
    "within_pair_correlation",
]
