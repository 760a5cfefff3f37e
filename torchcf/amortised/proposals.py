"""Amortised samples as ABC particles: each simulated once on its pair, scored
with the run's distance and offered to its model's per-pair top-N buffer.

The samples of one model (:meth:`PairPosteriors.of_model
<torchcf.amortised.inference.PairPosteriors.of_model>`: a pair and a
parameter vector each, in pair order) are a stretch of proposals of the round
loop that rejection and SMC share (:func:`torchcf.abc.rounds.run_rounds`):
the same rollout and score, the same plausibility screen, early rejection,
progress and checkpoints between rounds. Sample ``i`` of the model is particle
``i`` (the buffers' tie rule), so the buffers after the stretch do not depend
on the chunk or on where a run was cut and resumed.

Shapes: Q samples of the model, K its parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..abc.rejection import Rollout
from ..abc.rounds import (
    NO_HOOKS,
    Chunk,
    ModelProgress,
    Plan,
    Propose,
    RoundHooks,
    Sink,
    Stretch,
    run_rounds,
)
from ..abc.topn import TopN
from ..models import CFModel, require_model


def run_amortised(
    model: CFModel,
    samples: tuple[Tensor, Tensor],
    buffer: TopN,
    rollout: Rollout,
    progress: ModelProgress,
    *,
    hooks: RoundHooks = NO_HOOKS,
    weight_column: bool = False,
) -> None:
    """Offer one model's samples ``progress.next .. Q - 1`` to its buffer.

    Args:
        model: the samples' model.
        samples: ``(pair (Q,) int64, theta (Q, K))``: the training pair of each
            sample (a position in ``rollout.pairs``) and its parameters [SI].
        buffer: the model's per-pair buffer.
        rollout: how particles are simulated and scored (paired layout).
        progress: where to start; updated after every round.
        hooks: the processes, the plausibility screen and what runs between
            rounds (:class:`~torchcf.abc.rounds.RoundHooks`).
        weight_column: the buffer holds one more column, SMC's ``log r``
            (a refinement follows, :func:`torchcf.abc.smc.refine_population`):
            the samples enter with ``log r = 0``, equally weighted.

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm, truth = get_model("idm"), [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]
        >>> pairs = synthetic_pairs(idm, truth, n_pairs=4, n_steps=50)
        >>> samples = (torch.arange(8) % 4, torch.tensor(truth).repeat(8, 1))  # (Q,)
        >>> buffer, progress = TopN(n_pairs=4, capacity=2, n_params=6), ModelProgress()
        >>> run_amortised(idm, samples, buffer, Rollout(pairs), progress)
        >>> progress.next, bool(buffer.score.isfinite().all())
        (8, True)
    """
    model = require_model(model, "run_amortised")
    if not rollout.paired:
        raise ValueError("amortised samples are per pair: the rollout must be paired")
    pair, theta = samples
    n_samples = pair.shape[0]
    planned = max(n_samples, 1)
    compiled = rollout.compiled(model, planned)
    chunk = rollout.chunk(model, planned, compiled)
    run_rounds(
        sample_proposals(pair, theta, weight_column),
        [Sink(buffer)],
        Plan(rollout, model, chunk, compiled),
        progress,
        Stretch(progress.next, n_samples),
        hooks=hooks,
    )


def sample_proposals(
    pair: Tensor, theta: Tensor, weight_column: bool = False
) -> Propose:
    """The samples ``start .. stop - 1`` as a round's proposals (particle index
    = sample index), padded to a batch with copies of the last sample; with
    ``weight_column`` the buffers receive each sample with a last column 0."""
    theta = theta.to(torch.float64)
    last = pair.shape[0] - 1

    def propose(start: int, stop: int, batch: int | None) -> Chunk:
        drawn = batch if batch is not None else stop - start
        rows = torch.arange(start, start + drawn).clamp(max=last)
        index = torch.arange(start, stop)
        if not weight_column:
            return Chunk(theta[rows], pair[rows], index)
        offered = theta[start:stop]
        zero = torch.zeros(offered.shape[0], 1, dtype=theta.dtype)
        return Chunk(theta[rows], pair[rows], index, rows=torch.cat((offered, zero), 1))

    return propose


__all__ = ["run_amortised", "sample_proposals"]
