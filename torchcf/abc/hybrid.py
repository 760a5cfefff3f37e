"""Hybrid model selection from the per-model top-N buffers (SPEC section 5).

Per pair (default): merge the models' ``n`` best particles on that pair (``n``:
the top-N size, config ``abc.top_n``) and keep the ``n`` best across models;
``Theta_hybrid`` is the union over the N pairs (``n x N`` entries, a particle
accepted on two pairs counting twice). The share ``beta_m`` of model m is its
fraction of ``Theta_hybrid``.

Global (the paper's Eq. 6-7): merge every model's per-pair ``n`` best into one set
and keep its ``N^A`` best (the paper's symbol), whatever their pairs.

Ties: by score, then lower particle index (SPEC), then the model's position in the
run's model list (the SPEC leaves ties across models open: particle indices of
different models are different streams), then the pair.

Everything here reads buffers only: the pairwise table (the hybrid built from two
models alone) and the sensitivity over ``n`` need no new simulation.

Shapes: M models, N pairs, ``n`` entries per pair, Q candidates (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..models import CFModel, require_model
from ..posterior import ModelParticles, Posterior
from .topn import TopN, lexsort


@dataclass(frozen=True)
class Selection:
    """Members of a hybrid: which buffer entries were kept.

    Attributes:
        member: (M, N, n) bool, entry ``[m, p, r]`` = the ``r``-th best
            particle of model ``m`` on pair ``p`` is in the hybrid.
        models: the model names, in buffer order.

    Examples:
        >>> import torch
        >>> member = torch.tensor([[[True], [True]], [[False], [True]]])  # (2, 2, 1)
        >>> hybrid = Selection(member, ("idm", "ovm"))
        >>> hybrid.counts(), {m: round(s, 2) for m, s in hybrid.shares().items()}
        (tensor([2, 1]), {'idm': 0.67, 'ovm': 0.33})
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
    """Scores and indices of the first ``n`` entries: (M, N, n) each."""
    scores = torch.stack([b.first(n)[0] for b in buffers])
    indices = torch.stack([b.first(n)[1] for b in buffers])
    return scores, indices


def rank_per_pair(
    score: Tensor, index: Tensor, source: Tensor, pair: Tensor, n: int
) -> tuple[Tensor, Tensor]:
    """The one tie rule of torchcf: per pair, candidates ordered by score, then the
    lower particle index, then the source (the model's position in the run's list).

    Args:
        score: (Q,) float64 candidates' scores (``+inf``: invalid or empty slot).
        index: (Q,) int64 particle indices.
        source: (Q,) int64 position of each candidate's model (or set).
        pair: (Q,) int64 pair of each candidate.
        n: candidates kept per pair.

    Returns:
        ``member`` (Q,) bool: among the ``n`` best of its pair and finite; and
        ``order`` (Q,) int64: the candidates sorted by pair, then the tie rule.

    Examples:
        >>> import torch
        >>> score = torch.tensor([1.0, 1.0, 1.0, 4.0])  # a three-way tie on pair 0
        >>> index, source = torch.tensor([5, 2, 2, 0]), torch.tensor([0, 1, 0, 0])
        >>> pair = torch.tensor([0, 0, 0, 1])
        >>> member, order = rank_per_pair(score, index, source, pair, n=1)
        >>> member, order  # pair 0: index 2 beats 5, then source 0 beats 1
        (tensor([False, False,  True,  True]), tensor([2, 1, 0, 3]))
    """
    order = lexsort(pair, score, index, source)  # (Q,) pair-major
    sorted_pair = pair[order]
    count = torch.bincount(
        sorted_pair, minlength=int(pair.max()) + 1 if pair.numel() else 0
    )
    first_of_pair = torch.cumsum(count, 0) - count  # (N,)
    rank = torch.arange(order.numel()) - first_of_pair[sorted_pair]
    member = torch.zeros_like(score, dtype=torch.bool)
    member[order] = (rank < n) & torch.isfinite(score[order])
    return member, order


def select_per_pair(
    buffers: Sequence[TopN], models: Sequence[str], n: int
) -> Selection:
    """Per-pair hybrid: for every pair, the ``n`` best of the models' ``n`` best.

    Args:
        buffers: one :class:`TopN` per model (same pairs, capacity >= n).
        models: their names.
        n: entries kept per pair (the top-N size).

    Examples:
        >>> import torch
        >>> a, b = TopN(n_pairs=2, capacity=1, n_params=1), TopN(2, 1, 1)
        >>> pair, index, theta = torch.arange(2), torch.arange(2), torch.zeros(2, 1)
        >>> a.push(pair, torch.tensor([1.0, 4.0]), index, theta)  # scores on pairs 0, 1
        2
        >>> b.push(pair, torch.tensor([2.0, 3.0]), index, theta)
        2
        >>> select_per_pair([a, b], ["idm", "ovm"], n=1).shares()  # a pair each
        {'idm': 0.5, 'ovm': 0.5}
    """
    scores, indices = _stack(buffers, n)  # (M, N, n)
    model = torch.arange(scores.shape[0])[:, None, None].expand_as(scores)
    pair = torch.arange(scores.shape[1])[None, :, None].expand_as(scores)
    member, _ = rank_per_pair(
        scores.reshape(-1), indices.reshape(-1), model.reshape(-1), pair.reshape(-1), n
    )
    return Selection(member.reshape(scores.shape), tuple(models))


def select_global(
    buffers: Sequence[TopN], models: Sequence[str], n: int, size: int
) -> Selection:
    """Global hybrid: the ``size`` (``N^A``) best of all models' per-pair ``n`` best.

    Examples:
        >>> import torch
        >>> a, b = TopN(n_pairs=2, capacity=1, n_params=1), TopN(2, 1, 1)
        >>> pair, index, theta = torch.arange(2), torch.arange(2), torch.zeros(2, 1)
        >>> a.push(pair, torch.tensor([1.0, 4.0]), index, theta)  # scores on pairs 0, 1
        2
        >>> b.push(pair, torch.tensor([2.0, 3.0]), index, theta)
        2
        >>> select_global([a, b], ["idm", "ovm"], n=1, size=1).shares()  # score 1.0
        {'idm': 1.0, 'ovm': 0.0}
    """
    if size < 1:
        raise ValueError(f"size (N^A) must be >= 1, got {size}")
    scores, indices = _stack(buffers, n)  # (M, N, n)
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
    ``n x n_pairs``).

    Examples:
        >>> import torch
        >>> a, b = TopN(n_pairs=2, capacity=1, n_params=1), TopN(2, 1, 1)
        >>> pair, index, theta = torch.arange(2), torch.arange(2), torch.zeros(2, 1)
        >>> a.push(pair, torch.tensor([1.0, 4.0]), index, theta)  # scores on pairs 0, 1
        2
        >>> b.push(pair, torch.tensor([2.0, 3.0]), index, theta)
        2
        >>> select([a, b], ["idm", "ovm"], 1, mode="global").member.squeeze(2)
        tensor([[ True, False],
                [ True, False]])
    """
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

    Examples:
        >>> import torch
        >>> a, b = TopN(n_pairs=2, capacity=1, n_params=1), TopN(2, 1, 1)
        >>> pair, index, theta = torch.arange(2), torch.arange(2), torch.zeros(2, 1)
        >>> a.push(pair, torch.tensor([1.0, 4.0]), index, theta)  # scores on pairs 0, 1
        2
        >>> b.push(pair, torch.tensor([2.0, 3.0]), index, theta)
        2
        >>> pairwise_table([a, b], ["idm", "ovm"], 1, mode="global", global_size=1)
        tensor([[1., 1.],
                [0., 1.]], dtype=torch.float64)
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


def hybrid_posterior(
    buffers: Sequence[TopN],
    models: Sequence[CFModel],
    selection: Selection,
    n: int,
    train_pair_ids: Tensor,
    *,
    dataset: str,
    mode: str,
) -> Posterior:
    """The learned set: the hybrid's members with their scores, pairs and stream
    indices, and every model's full buffer.

    Args:
        buffers: one :class:`TopN` per model, in the run's model order.
        models: their model objects (``spec.model`` of the run's config
            entries), in the same order; the posterior is keyed by their names.
        selection: the hybrid (:func:`select` over the same buffers and ``n``).
        n: entries kept per pair (the top-N size).
        train_pair_ids: (N,) int64 data-set ids of the training pairs.
        dataset: the data set's label.
        mode: the selection mode ("per_pair" or "global").

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> buffer = TopN(n_pairs=2, capacity=1, n_params=6)  # the IDM's K = 6
        >>> buffer.push(torch.arange(2), torch.tensor([1.0, 2.0]), torch.arange(2),
        ...             torch.full((2, 6), 1.5, dtype=torch.float64))
        2
        >>> hybrid = select([buffer], ["idm"], n=1)
        >>> posterior = hybrid_posterior([buffer], [get_model("idm")], hybrid, 1,
        ...     torch.tensor([7, 9]), dataset="demo", mode="per_pair")
        >>> posterior.shares, posterior.hybrid["idm"].pair_ids
        ({'idm': 1.0}, tensor([7, 9]))
    """
    models = [require_model(model, "hybrid_posterior") for model in models]
    hybrid = {}
    saved = {}
    for m, (model, buffer) in enumerate(zip(models, buffers, strict=True)):
        name = model.name
        score, index, theta = buffer.first(n)
        # member[m] is (N, n); rows, ranks: (Q,) each, model m's Q members.
        rows, ranks = selection.member[m].nonzero(as_tuple=True)
        param_names = tuple(model.param_names)
        hybrid[name] = ModelParticles(
            param_names,
            theta[rows, ranks].clone(),
            score[rows, ranks].clone(),
            train_pair_ids[rows],
            index[rows, ranks].clone(),
        )
        saved[name] = {"param_names": list(param_names), **buffer.state_dict()}
    return Posterior(
        dataset=dataset,
        selection=mode,
        top_n=n,
        models=tuple(model.name for model in models),
        shares=selection.shares(),
        train_pair_ids=train_pair_ids,
        hybrid=hybrid,
        buffers=saved,
    )


__all__ = [
    "Selection",
    "hybrid_posterior",
    "rank_per_pair",
    "pairwise_table",
    "select",
    "select_global",
    "select_per_pair",
]
