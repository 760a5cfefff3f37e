"""The attribution's start: particles drawn by the ABC engine on the fit windows.

The attribution starts from a small ABC run of every pool model with the one ABC
engine (:mod:`torchcf.abc.rejection`, the paired layout): a model's first ``n``
prior draws stream through a per-pair top-N buffer (:func:`prior_particles`),
and the kept particles are :class:`~torchcf.abc.particles.Particles`
(parameters, pair, score and stream index, tensors throughout).

Shapes: Q particles of a set, N pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from ...abc.particles import Particles
from ...abc.rejection import ModelProgress, Rollout, run_rejection
from ...abc.rounds import RoundHooks
from ...abc.smc import SMCSettings, new_state, parameter_buffer, run_smc, smc_budget
from ...abc.streams import ParticleStream
from ...abc.topn import TopN
from ...config import ConfigError


def prior_particles(
    stream: ParticleStream,
    rollout: Rollout,
    budgets: Sequence[int],
    keep: int,
    smc: SMCSettings | None = None,
    progress: Callable[[float], None] | None = None,
) -> list[Particles]:
    """Paired ABC of one model (or variant) on the rollout's pairs: rejection, or
    with ``smc`` the sequential refinement at each budget.

    Args:
        stream: the model's prior stream on the rollout's pairs
            (:func:`~torchcf.abc.rejection.prior_stream` of the model, the
            prior box of the drawn parameters (K_drawn, 2), the seed
            the loop's seed (:attr:`~torchcf.diagnose.setup.LoopSetup.seed`),
            and the values (K - K_drawn,) of the last
            parameters where they are held, the same for every particle: a
            shared effect's value).
        budgets: increasing particle counts; result ``i`` holds the ``keep`` best
            per pair of the first ``budgets[i]`` prior draws of the model's stream
            (streamed through a top-N buffer, nothing else stored; empty slots
            scored ``+inf``), pair-major.
        smc: the refinement's settings; result ``i`` is then the ``keep`` best per
            pair of an SMC run of ``budgets[i]`` proposals (its own run: an SMC
            run of a larger budget is not a continuation of a smaller one).
        progress: called with the share of the largest budget each round of
            rejection simulated (the shares sum to 1); SMC calls it once, at
            the end.
    """
    model = stream.model
    if smc is not None:
        sets = [
            _refined_particles(stream, rollout, budget, keep, smc) for budget in budgets
        ]
        if progress is not None:
            progress(1.0)
        return sets
    buffer = TopN(rollout.pairs.n_pairs, keep, model.n_params)
    streamed = ModelProgress()
    total, reported = max(budgets), [0]

    def after_round(state: ModelProgress, _due: bool) -> None:
        if progress is not None:
            progress((state.next - reported[0]) / total)
            reported[0] = state.next

    sets = []
    for budget in budgets:
        run_rejection(
            stream,
            buffer,
            rollout,
            budget,
            streamed,
            plan_particles=min(budgets),
            hooks=RoundHooks(after_round=after_round),
        )
        sets.append(Particles.from_buffer(model, buffer, keep))
    return sets


def _refined_particles(
    stream: ParticleStream,
    rollout: Rollout,
    budget: int,
    keep: int,
    smc: SMCSettings,
) -> Particles:
    """The ``keep`` best per pair of one SMC run of ``budget`` proposals."""
    model, fixed = stream.model, stream.fixed
    n_pairs, k_drawn = rollout.pairs.n_pairs, stream.bounds.shape[0]
    buffer = TopN(n_pairs, keep, k_drawn + 1)
    state = new_state(n_pairs, smc, k_drawn)
    if smc_budget(budget, n_pairs, smc).per_pair < 1:
        raise ConfigError(
            f"diagnose.method = 'smc': diagnose.n_particles gives {budget} "
            f"particles, no proposal per pair and round ({n_pairs} pairs, "
            f"abc.smc.rounds = {smc.rounds}); raise it or lower the rounds"
        )
    run_smc(stream, buffer, rollout, budget, smc, ModelProgress(), state)
    particles = Particles.from_buffer(model, parameter_buffer(buffer), keep)
    if fixed is None:
        return particles
    theta = torch.cat((particles.theta, fixed.expand(len(particles), -1)), dim=1)
    return Particles(model, theta, particles.pair, particles.score, particles.index)


__all__ = [
    "prior_particles",
]
