"""Hybrid model selection from the per-model top-N buffers (SPEC section 5).

Per pair (default): merge the models' N best particles on that pair and keep the N
best across models; ``Theta_hybrid`` is the union over pairs (``N x n_pairs``
entries, a particle accepted on two pairs counting twice). The share ``beta_m`` of
model m is its fraction of ``Theta_hybrid``.

Global (the paper's Eq. 6-7): merge every model's per-pair N best into one set and
keep its ``N^A`` best, whatever their pairs.

Ties: by score, then lower particle index (SPEC), then the model's position in the
run's model list (the SPEC leaves ties across models open: particle indices of
different models are different streams), then the pair.

Everything here reads buffers only: the pairwise table (the hybrid built from two
models alone) and the sensitivity over N need no new simulation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .topn import TopN, lexsort


@dataclass(frozen=True)
class Selection:
    """Members of a hybrid: which buffer entries were kept.

    Attributes:
        member: (M, n_pairs, N) bool, entry ``[m, p, r]`` = the ``r``-th best
            particle of model ``m`` on pair ``p`` is in the hybrid.
        models: the model names, in buffer order.
    """

    member: Tensor
    models: tuple[str, ...]

    def counts(self) -> Tensor:
        """(M,) int64 number of hybrid entries per model."""
        return self.member.sum(dim=(1, 2))

    def shares(self) -> dict[str, float]:
        """``beta_m`` per model (0 for every model if the hybrid is empty)."""
        counts = self.counts()
        total = int(counts.sum())
        return {
            name: (float(c) / total if total else 0.0)
            for name, c in zip(self.models, counts.tolist(), strict=True)
        }


def _stack(buffers: Sequence[TopN], n: int) -> tuple[Tensor, Tensor]:
    """Scores and indices of the first ``n`` entries: (M, n_pairs, n) each."""
    scores = torch.stack([b.first(n)[0] for b in buffers])
    indices = torch.stack([b.first(n)[1] for b in buffers])
    return scores, indices


def select_per_pair(
    buffers: Sequence[TopN], models: Sequence[str], n: int
) -> Selection:
    """Per-pair hybrid: for every pair, the ``n`` best of the models' ``n`` best.

    Args:
        buffers: one :class:`TopN` per model (same pairs, capacity >= n).
        models: their names.
        n: N.
    """
    scores, indices = _stack(buffers, n)  # (M, P, n)
    n_models, n_pairs, _ = scores.shape
    # Per pair, candidates in (model, rank) order: (P, M * n).
    cand_score = scores.permute(1, 0, 2).reshape(n_pairs, -1)
    cand_index = indices.permute(1, 0, 2).reshape(n_pairs, -1)
    cand_model = torch.arange(n_models).repeat_interleave(n).expand(n_pairs, -1)
    member = torch.zeros(n_pairs, n_models * n, dtype=torch.bool)
    for p in range(n_pairs):  # n_pairs is small (tens); each sort is M * n long
        order = lexsort(cand_score[p], cand_index[p], cand_model[p])[:n]
        member[p, order] = torch.isfinite(cand_score[p, order])
    member = member.reshape(n_pairs, n_models, n).permute(1, 0, 2)
    return Selection(member.contiguous(), tuple(models))


def select_global(
    buffers: Sequence[TopN], models: Sequence[str], n: int, size: int
) -> Selection:
    """Global hybrid: the ``size`` (``N^A``) best of all models' per-pair ``n`` best."""
    if size < 1:
        raise ValueError(f"size (N^A) must be >= 1, got {size}")
    scores, indices = _stack(buffers, n)  # (M, P, n)
    n_models, n_pairs, _ = scores.shape
    model = torch.arange(n_models)[:, None, None].expand_as(scores)
    pair = torch.arange(n_pairs)[None, :, None].expand_as(scores)
    flat = [t.reshape(-1) for t in (scores, indices, model, pair)]
    order = lexsort(*flat)[:size]
    member = torch.zeros(scores.numel(), dtype=torch.bool)
    member[order] = torch.isfinite(flat[0][order])
    return Selection(member.reshape(scores.shape), tuple(models))


def select(
    buffers: Sequence[TopN],
    models: Sequence[str],
    n: int,
    *,
    mode: str = "per_pair",
    global_size: int | None = None,
) -> Selection:
    """:func:`select_per_pair` or :func:`select_global` (``global_size`` default
    ``n x n_pairs``)."""
    if mode == "per_pair":
        return select_per_pair(buffers, models, n)
    if mode == "global":
        size = global_size if global_size is not None else n * buffers[0].n_pairs
        return select_global(buffers, models, n, size)
    raise ValueError(f"selection must be 'per_pair' or 'global', got {mode!r}")


def pairwise_table(
    buffers: Sequence[TopN],
    models: Sequence[str],
    n: int,
    *,
    mode: str = "per_pair",
    global_size: int | None = None,
) -> Tensor:
    """(M, M) float64: ``[i, j]`` = share of model i in the hybrid of {i, j} alone.

    The diagonal is 1 (a model alone); ``[i, j] + [j, i] = 1`` where that hybrid is
    not empty.
    """
    n_models = len(buffers)
    table = torch.ones(n_models, n_models, dtype=torch.float64)
    for i in range(n_models):
        for j in range(i + 1, n_models):
            pair_sel = select(
                [buffers[i], buffers[j]],
                [models[i], models[j]],
                n,
                mode=mode,
                global_size=global_size,
            )
            counts = pair_sel.counts().double()
            total = counts.sum()
            share_i = float(counts[0] / total) if total > 0 else 0.0
            share_j = float(counts[1] / total) if total > 0 else 0.0
            table[i, j], table[j, i] = share_i, share_j
    return table


__all__ = [
    "Selection",
    "pairwise_table",
    "select",
    "select_global",
    "select_per_pair",
]
