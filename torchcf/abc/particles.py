"""Particle sets kept as tensors, and the hybrid's per-pair selection over them.

A search that refines particles outside a streaming buffer (the diagnosis loop's
local search) holds them as :class:`Particles`: one model's parameters, the pair
each particle is fitted to, its score and a particle index for the tie rule. The
per-pair selection over several sets is the hybrid's
(:func:`~torchcf.abc.hybrid.rank_per_pair`: score, then lower particle index,
then the set's position in the list).

Shapes: Q particles of the set, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..models import CFModel, require_model
from .hybrid import rank_per_pair
from .topn import TopN


@dataclass(frozen=True)
class Particles:
    """Particles of one model (or variant), each on one pair.

    Attributes:
        model: the model object, a variant included (:func:`torchcf.get_model`
            makes it from a name); a name raises :class:`TypeError`.
        theta: (Q, K) float64 parameters.
        pair: (Q,) int64 pair position of each particle.
        score: (Q,) float64 score on its pair (``+inf``: invalid).
        index: (Q,) int64 particle index, the tie-breaker among equal scores: the
            stream index of a prior draw; a perturbed copy inherits its parent's.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> pair, score = torch.tensor([0, 0, 1]), torch.tensor([2.0, 1.0, 3.0])
        >>> found = Particles(get_model("idm"), torch.zeros(3, 6), pair, score,
        ...                   torch.arange(3))
        >>> len(found), found.take(found.pair == 0).score
        (3, tensor([2., 1.]))
    """

    model: CFModel
    theta: Tensor
    pair: Tensor
    score: Tensor
    index: Tensor

    def __post_init__(self) -> None:
        require_model(self.model, "Particles")

    def __len__(self) -> int:
        return self.score.shape[0]

    def take(self, rows: Tensor) -> Particles:
        """The particles at ``rows`` (a (Q,) bool mask or int64 positions)."""
        return Particles(
            self.model,
            self.theta[rows],
            self.pair[rows],
            self.score[rows],
            self.index[rows],
        )

    @classmethod
    def from_buffer(cls, model: CFModel, buffer: TopN, n: int) -> Particles:
        """A buffer's ``n`` best per pair (empty slots included, scored ``+inf``),
        pair-major."""
        score, index, theta = buffer.first(n)  # (N, n), (N, n), (N, n, K)
        return cls(
            model,
            theta.reshape(-1, theta.shape[-1]).clone(),
            torch.arange(buffer.n_pairs).repeat_interleave(n),
            score.reshape(-1).clone(),
            index.reshape(-1).clone(),
        )


def best_per_pair(sets: Sequence[Particles], n: int) -> list[Particles]:
    """Per pair, the ``n`` best finite-score particles over all ``sets``.

    The hybrid's per-pair selection with its tie rule (score, particle index, the
    set's position). The result holds one set per model that has a chosen
    particle (sets of the same model merge), in the order in which the models
    first appear when the chosen particles are listed pair by pair, best first;
    within a set, particles are in that order too, so a caller that walks the
    result draws its random numbers in a fixed order.

    Examples:
        >>> import torch
        >>> from torchcf import get_model
        >>> idm, ovm = get_model("idm"), get_model("ovm")
        >>> mine = Particles(idm, torch.zeros(2, 6), torch.tensor([0, 1]),
        ...                  torch.tensor([1.0, 5.0]), torch.arange(2))
        >>> theirs = Particles(ovm, torch.zeros(2, 5), torch.tensor([0, 1]),
        ...                    torch.tensor([2.0, 3.0]), torch.arange(2))
        >>> [(s.model.name, s.pair.tolist()) for s in best_per_pair([mine, theirs], 1)]
        [('idm', [0]), ('ovm', [1])]
    """
    if not sets:
        return []
    score = torch.cat([s.score for s in sets])
    index = torch.cat([s.index for s in sets])
    pair = torch.cat([s.pair for s in sets])
    lengths = torch.tensor([len(s) for s in sets])
    source = torch.repeat_interleave(torch.arange(len(sets)), lengths)  # (Q,)
    member, order = rank_per_pair(score, index, source, pair, n)
    chosen = order[member[order]]  # (Q',) flat positions, pair-major, best first

    models = [s.model for s in sets]
    # A particle's row in the concatenation of its model's sets (list order).
    offset_in_model = torch.zeros(len(sets), dtype=torch.int64)
    seen: dict[CFModel, int] = {}
    for k, s in enumerate(sets):
        offset_in_model[k] = seen.get(s.model, 0)
        seen[s.model] = int(offset_in_model[k]) + len(s)
    first_row = torch.cumsum(lengths, 0) - lengths
    model_row = (
        torch.arange(score.numel()) - first_row[source] + offset_in_model[source]
    )

    result = []
    for model in dict.fromkeys(models[k] for k in source[chosen].tolist()):
        ks = [k for k, s in enumerate(sets) if s.model is model]
        merged = _concat([sets[k] for k in ks])
        mine = chosen[torch.isin(source[chosen], torch.tensor(ks))]
        result.append(merged.take(model_row[mine]))
    return result


def _concat(parts: Sequence[Particles]) -> Particles:
    """One set from sets of the same model, in list order."""
    if len(parts) == 1:
        return parts[0]
    return Particles(
        parts[0].model,
        torch.cat([p.theta for p in parts]),
        torch.cat([p.pair for p in parts]),
        torch.cat([p.score for p in parts]),
        torch.cat([p.index for p in parts]),
    )


__all__ = ["Particles", "best_per_pair"]
