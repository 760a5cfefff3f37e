"""Streaming per-pair top-N buffer of ABC rejection (SPEC section 5).

For every training pair the buffer keeps the ``capacity`` particles with the lowest
score, ties broken by the lower particle index, and never stores the others: its
memory is ``N x capacity`` for N pairs, whatever the number of particles streamed
through it, and its content equals a full sort of all scores, whatever order and
chunking the particles arrive in.

Invalid particles (score ``+inf``) never enter. Slots not yet filled hold score
``+inf`` and index ``-1``; a pair with fewer than ``capacity`` valid particles keeps
empty slots.

Offering an entry the buffer already holds (same pair, score and particle index)
changes nothing, so replicas of a buffer that saw different particles merge exactly
(:meth:`TopN.merge`): the distributed trainer (:mod:`torchcf.abc.distributed`)
relies on it.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


def lexsort(*keys: Tensor) -> Tensor:
    """Permutation sorting by ``keys[0]``, then ``keys[1]``, ... (1-D, one length).

    Stable sorts from the least significant key up (like ``numpy.lexsort`` with
    the keys reversed).

    Examples:
        >>> import torch
        >>> pair, score = torch.tensor([1, 0, 1]), torch.tensor([2.0, 5.0, 1.0])
        >>> lexsort(pair, score)  # by pair, then by score
        tensor([1, 2, 0])
    """
    order = torch.arange(keys[0].shape[0], device=keys[0].device)
    for key in reversed(keys):
        order = order[torch.sort(key[order], stable=True).indices]
    return order


class TopN:
    """The ``capacity`` best ``(score, index)`` entries of each of N pairs.

    Args:
        n_pairs: number of pairs, N.
        capacity: entries kept per pair (the largest ``n`` :meth:`first` will be
            asked for).
        n_params: parameters per particle, K (stored with each entry).
        device: where the buffer lives.

    Attributes:
        score: (N, capacity) float64, ascending per pair; ``+inf`` = empty.
        index: (N, capacity) int64 particle index; ``-1`` = empty.
        theta: (N, capacity, K) float64 parameters.

    Examples:
        >>> import torch
        >>> buffer = TopN(n_pairs=2, capacity=2, n_params=1)
        >>> pair, score = torch.tensor([0, 0, 0, 1]), torch.tensor([3.0, 1.0, 2.0, 5.0])
        >>> buffer.push(pair, score, torch.arange(4), torch.zeros(4, 1))
        4
        >>> buffer.index  # per pair, the best particles; -1: an empty slot
        tensor([[ 1,  2],
                [ 3, -1]])
    """

    def __init__(
        self,
        n_pairs: int,
        capacity: int,
        n_params: int,
        device: torch.device | str = "cpu",
    ) -> None:
        if n_pairs < 1 or capacity < 1:
            raise ValueError(f"need n_pairs, capacity >= 1, got {n_pairs}, {capacity}")
        self.score = torch.full((n_pairs, capacity), torch.inf, dtype=torch.float64)
        self.score = self.score.to(device)
        self.index = torch.full(
            (n_pairs, capacity), -1, dtype=torch.int64, device=device
        )
        self.theta = torch.zeros(
            n_pairs, capacity, n_params, dtype=torch.float64, device=device
        )

    @property
    def n_pairs(self) -> int:
        return self.score.shape[0]

    @property
    def capacity(self) -> int:
        return self.score.shape[1]

    def threshold(self) -> Tensor:
        """(N,) score a new particle must not exceed to enter (``+inf``
        while a pair has an empty slot)."""
        return self.score[:, -1]

    def push(self, pair: Tensor, score: Tensor, index: Tensor, theta: Tensor) -> int:
        """Offer candidates; keeps the buffer equal to the best of everything seen.

        Args:
            pair: (Q,) int64 pair position of each candidate.
            score: (Q,) scores (any float dtype; NaN and +inf are rejected).
            index: (Q,) int64 particle indices; a (pair, index) already held, or
                repeated among the candidates, is kept once (a particle's score
                and parameters are a function of its index).
            theta: (Q, K) parameters.

        Returns:
            The number of candidates that passed the threshold test (entered or
            were compared exactly).
        """
        device = self.score.device
        score = score.to(device=device, dtype=torch.float64)
        pair = pair.to(device)
        # Only candidates at or under their pair's current threshold can enter (a
        # tie may still win on the index); this keeps the exact merge small.
        keep = torch.isfinite(score) & (score <= self.threshold()[pair])
        survivors = keep.nonzero().squeeze(1)
        if not survivors.numel():
            return 0
        # Only the pairs a survivor goes to are merged: a chunk's cost is its own
        # size plus capacity per pair it reaches, not the whole buffer's
        # (a refinement round's chunks reach a slice of the pairs; over 10 000
        # pairs a whole-buffer merge per chunk grew with pairs squared).
        touched, local = torch.unique(pair[survivors], return_inverse=True)
        score_t, index_t, theta_t = _merge(
            self.score[touched],
            self.index[touched],
            self.theta[touched],
            local,
            score[survivors],
            index.to(device)[survivors],
            theta.to(device=device, dtype=torch.float64)[survivors],
        )
        self.score[touched], self.index[touched] = score_t, index_t
        self.theta[touched] = theta_t
        return int(survivors.numel())

    def push_full(self, score: Tensor, index: Tensor, theta: Tensor) -> int:
        """Offer particles simulated on every pair (full layout).

        Args:
            score: (P, N) scores; index: (P,) particle indices;
            theta: (P, K).
        """
        device = self.score.device
        score = score.to(device=device, dtype=torch.float64)
        keep = torch.isfinite(score) & (score <= self.threshold()[None, :])
        rows, cols = keep.nonzero(as_tuple=True)
        if not rows.numel():
            return 0
        rows_cpu = rows.to(index.device)
        return self.push(cols, score[rows, cols], index[rows_cpu], theta[rows_cpu])

    def merge(self, score: Tensor, index: Tensor, theta: Tensor) -> None:
        """Merge replicas of this buffer: keep the best of everything they hold.

        Each replica is a buffer of the same shape that saw other particles (or
        some of the same); the result equals one buffer that saw all of them, so
        every process that merges the same replicas holds the same buffer.

        Args:
            score: (R, N, capacity) the replicas' scores.
            index: (R, N, capacity) int64 particle indices (-1 = empty).
            theta: (R, N, capacity, K) parameters.
        """
        expected = (self.n_pairs, self.capacity)
        if score.shape[1:] != expected or index.shape != score.shape:
            raise ValueError(
                f"replicas must be (R, {expected[0]}, {expected[1]}), got "
                f"{tuple(score.shape)} and {tuple(index.shape)}"
            )
        pair = torch.arange(self.n_pairs, device=index.device)[None, :, None]
        pair = pair.expand_as(index)  # (R, N, capacity)
        held = index >= 0
        self.push(pair[held], score[held], index[held], theta[held])

    def first(self, n: int) -> tuple[Tensor, Tensor, Tensor]:
        """The best ``n <= capacity`` entries per pair: score, index, theta."""
        if not 1 <= n <= self.capacity:
            raise ValueError(f"n must be in [1, {self.capacity}], got {n}")
        return self.score[:, :n], self.index[:, :n], self.theta[:, :n]

    def state_dict(self) -> dict[str, Any]:
        return {"score": self.score, "index": self.index, "theta": self.theta}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("score", "index", "theta"):
            value = state[name]
            if value.shape != getattr(self, name).shape:
                raise ValueError(
                    f"buffer {name}: shape {tuple(value.shape)} in the checkpoint, "
                    f"{tuple(getattr(self, name).shape)} expected"
                )
            setattr(self, name, value.to(getattr(self, name).device).clone())


def _merge(
    score: Tensor,
    index: Tensor,
    theta: Tensor,
    pair: Tensor,
    new_score: Tensor,
    new_index: Tensor,
    new_theta: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """The best ``capacity`` entries per row of a buffer slice and candidates.

    Args:
        score, index, theta: (R, capacity), (R, capacity), (R, capacity, K) the
            rows' entries.
        pair: (Q,) int64 row of each candidate; new_score, new_index, new_theta:
            (Q,), (Q,), (Q, K) the candidates.

    Returns:
        The rows' new ``score``, ``index``, ``theta``.
    """
    device = score.device
    n_rows, capacity = score.shape
    all_pair = torch.cat(
        (torch.arange(n_rows, device=device).repeat_interleave(capacity), pair)
    )
    all_score = torch.cat((score.reshape(-1), new_score))
    all_index = torch.cat((index.reshape(-1), new_index))
    all_theta = torch.cat((theta.reshape(-1, theta.shape[-1]), new_theta))
    # Empty slots (index -1) are the only entries scoring inf (push keeps finite
    # scores only), so they sort after every real entry of their pair.
    order = lexsort(all_pair, all_score, all_index)
    # Copies of one entry are adjacent in this order; keep the first only.
    sorted_index = all_index[order]
    copy = torch.zeros_like(order, dtype=torch.bool)
    copy[1:] = (
        (all_pair[order[1:]] == all_pair[order[:-1]])
        & (sorted_index[1:] == sorted_index[:-1])
        & (all_score[order[1:]] == all_score[order[:-1]])
        & (sorted_index[1:] >= 0)
    )
    order = order[~copy]
    sorted_pair = all_pair[order]
    # Rank within the pair: position minus the pair's first position.
    counts = torch.bincount(sorted_pair, minlength=n_rows)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(order.numel(), device=device) - starts[sorted_pair]
    take = rank < capacity
    slot = sorted_pair[take] * capacity + rank[take]
    chosen = order[take]
    # Every row keeps its entries or better ones, so every slot is written.
    out_score = torch.full_like(score, torch.inf)
    out_index = torch.full_like(index, -1)
    out_theta = torch.zeros_like(theta)
    out_score.view(-1)[slot] = all_score[chosen]
    out_index.view(-1)[slot] = all_index[chosen]
    out_theta.view(-1, theta.shape[-1])[slot] = all_theta[chosen]
    return out_score, out_index, out_theta


__all__ = ["TopN", "lexsort"]
