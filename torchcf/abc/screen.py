"""Plausibility in calibration: keep implausible particles out of the buffers.

With ``plausibility.filter`` on, a particle that collides in the plausibility
battery (:func:`torchcf.traffic.check_plausibility`; with
``plausibility.reject_string_unstable`` also one whose homogeneous platoon
amplifies a disturbance) is treated as an invalid rollout: its score becomes
``+inf`` before it is offered to a buffer, and it is counted (``implausible``
per model in summary.json: the rejected particles that would otherwise have
entered a buffer, the only ones tested).

**Only candidates are tested.** The battery costs a few hundred rollouts per
particle, so it runs only on particles that could enter a buffer: a particle
enters a pair's buffer only if it is among the ``capacity`` best of its chunk
for that pair and at or under the buffer's current threshold (which only falls
as particles are offered). :meth:`PlausibilityScreen.screen` tests those; where
some are rejected, the next ones of their pairs become candidates, until every
pair's ``capacity`` best remaining candidates passed. The buffers therefore
end exactly as if every particle had been tested, whatever the chunking, at a
cost of about ``capacity x N`` tests per chunk early on and far fewer later.

Shapes: P particles, N pairs, K parameters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..models import CFModel
from .topn import TopN, lexsort


@dataclass(frozen=True)
class PlausibilityScreen:
    """The calibration's plausibility filter.

    Attributes:
        implausible: ``(model, theta (Q, K)) -> (Q,) bool``, the particles to
            reject (:func:`torchcf.traffic.battery.rejects`: those that collide
            in the battery, string-unstable ones if asked). The engine knows
            nothing of the battery: the caller (training) hands it in.
    """

    implausible: Callable[[CFModel, Tensor], Tensor]

    def screen(
        self,
        model: CFModel,
        buffer: TopN,
        score: Tensor,
        index: Tensor,
        theta: Tensor,
        pair: Tensor | None,
        cleared: Tensor | None = None,
    ) -> tuple[Tensor, int]:
        """The chunk's scores with its implausible candidates set to ``+inf``.

        Args:
            buffer: the buffer the chunk is about to be offered to (read only).
            score: (P,) with ``pair`` (paired layout) or (P, N) (full layout).
            index: (P,) particle indices (ties in a pair go to the lower one).
            theta: (P, K) the simulated parameters.
            pair: (P,) each particle's pair, or None for the full layout.
            cleared: (P,) bool, the particles an earlier screen of the same
                chunk found plausible (not tested again); updated in place with
                those this one finds plausible. (SMC screens a chunk for its
                two buffers.)

        Returns:
            the screened scores (a copy where any was rejected) and the number
            of particles rejected.
        """
        entry_score, entry_pair, entry_row = _entries(score, pair)
        threshold = buffer.threshold().to(entry_score.device)
        capacity = buffer.capacity
        n_rows = theta.shape[0]
        checked = torch.zeros(n_rows, dtype=torch.bool, device=entry_score.device)
        if cleared is not None:
            checked |= cleared.to(checked.device)
        rejected = torch.zeros_like(checked)
        entry_index = index.to(entry_score.device)[entry_row]
        while True:
            live = (
                torch.isfinite(entry_score)
                & (entry_score <= threshold[entry_pair])
                & ~rejected[entry_row]
            )
            top = _best_per_pair(
                live, entry_pair, entry_score, entry_index, capacity
            )  # entries that would enter now
            need = torch.unique(entry_row[top])
            need = need[~checked[need]]
            if not need.numel():
                break
            bad = self.implausible(model, theta[need.to(theta.device)].double())
            checked[need] = True
            rejected[need[bad.to(need.device)]] = True
        if cleared is not None:
            cleared |= (checked & ~rejected).to(cleared.device)
        count = int(rejected.sum())
        if count == 0:
            return score, 0
        screened = score.clone()
        screened[rejected.to(score.device)] = torch.inf
        return screened, count


def _entries(score: Tensor, pair: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Flat (E,) score, pair and particle row of every (particle, pair) entry."""
    if pair is not None:
        rows = torch.arange(score.shape[0], device=score.device)
        return score.double(), pair.to(score.device), rows
    n_rows, n_pairs = score.shape
    rows = torch.arange(n_rows, device=score.device).repeat_interleave(n_pairs)
    cols = torch.arange(n_pairs, device=score.device).repeat(n_rows)
    return score.double().reshape(-1), cols, rows


def _best_per_pair(
    live: Tensor, pair: Tensor, score: Tensor, index: Tensor, capacity: int
) -> Tensor:
    """Positions of the live entries among their pair's ``capacity`` best by
    ``(score, index)``."""
    candidates = live.nonzero().squeeze(1)
    if not candidates.numel():
        return candidates
    order = candidates[lexsort(pair[candidates], score[candidates], index[candidates])]
    sorted_pair = pair[order]
    first = torch.ones_like(sorted_pair, dtype=torch.bool)
    first[1:] = sorted_pair[1:] != sorted_pair[:-1]
    start = torch.cummax(
        torch.where(first, torch.arange(order.numel(), device=order.device), 0), 0
    ).values
    rank = torch.arange(order.numel(), device=order.device) - start
    return order[rank < capacity]


__all__ = ["PlausibilityScreen"]
