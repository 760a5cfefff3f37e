"""What a calibration returns (:class:`Calibration`), read from its buffers.

The hybrid is the selection over every model's per-pair buffer
(:func:`torchcf.abc.select`, the ``log r`` column of a weighted buffer dropped),
the posterior its members (:func:`torchcf.abc.hybrid_posterior`); beside it
the pairwise table (every model against every other alone), the shares at the
other N of ``SelectionRule.sensitivity_n``, each model's record (particles,
invalid rollouts, time, thresholds) and, under SMC, the shares with the
prior's Occam factor (:func:`torchcf.abc.smc.evidence_shares`).

Shapes: M models, N training pairs, B buffer slots.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..abc.hybrid import Selection as Chosen
from ..abc.hybrid import hybrid_posterior, pairwise_table, select
from ..abc.rejection import ModelProgress
from ..abc.smc import (
    evidence_shares,
    parameter_buffer,
    prior_mass,
    proposals_per_pair,
    smc_budget,
)
from ..abc.topn import TopN
from ..data import PairSet
from ..models import CFModel
from ..posterior import Posterior
from ..runs.summary import AmortisedResult, ModelResult, SMCBudgetResult, SMCResult
from .methods import SMC, Method, SelectionRule, weighted
from .priors import held_values
from .state import CalibrationState


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibration's result.

    Attributes:
        posterior: the hybrid: per model its members (parameters, scores,
            pairs) and its whole buffer (:class:`~torchcf.posterior.Posterior`).
        pairwise: ``(M, M)`` the share of model i in the hybrid of {i, j}
            alone (:func:`torchcf.abc.pairwise_table`).
        sensitivity: per N of ``SelectionRule.sensitivity_n``, the shares of the
            hybrid of that N.
        per_model: per model, its stream's record (particles, invalid rollouts,
            seconds, per-pair N-th best scores).
        seconds: wall time of the calibration [s].
        stream_seconds: the models' simulation and selection time, summed
            (resumed streams' earlier time included) [s].
        smc: SMC's settings, budget and evidence shares (SMC only).
        amortised: how the estimator was trained (amortised only).

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 40.0 + 15.0 * t, torch.full_like(t, 15.0)  # [m], [m/s]
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 30.0, v, a], dt=0.1)
        >>> from torchcf.calibration import Rejection, calibrate
        >>> result = calibrate(pairs, [get_model("idm")], Rejection(500))
        >>> result.shares, result.pairwise.shape, result.per_model["idm"].particles
        ({'idm': 1.0}, torch.Size([1, 1]), 500)
    """

    posterior: Posterior
    pairwise: Tensor
    sensitivity: dict[int, dict[str, float]]
    per_model: dict[str, ModelResult]
    seconds: float
    stream_seconds: float
    smc: SMCResult | None = None
    amortised: AmortisedResult | None = field(default=None)

    @property
    def shares(self) -> dict[str, float]:
        """Each model's share of the hybrid (its relative likelihood)."""
        return dict(self.posterior.shares)

    @property
    def models(self) -> list[str]:
        """The models' names, in the calibration's order."""
        return list(self.posterior.models)


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def model_result(
    buffer: TopN, progress: ModelProgress, top_n: int, cells: int
) -> ModelResult:
    """One model's record, from its buffer (``(N, B)`` scores) and progress;
    ``cells``: cells per particle (1 paired, the pairs in the full layout)."""
    nth = buffer.first(top_n)[0][:, -1]  # (N,) N-th best score per pair
    finite = nth[torch.isfinite(nth)]
    return ModelResult(
        particles=progress.next,
        invalid=progress.invalid,
        invalid_rate=progress.invalid / max(progress.next * cells, 1),
        implausible=progress.implausible,
        seconds=round(progress.seconds, 3),
        particles_per_s=progress.next / max(progress.seconds, 1e-9),
        best_score=_finite_or_none(float(buffer.score[:, 0].min())),
        threshold=_finite_or_none(float(finite.mean())) if finite.numel() else None,
        threshold_max=_finite_or_none(float(nth.max())),
        thresholds=tuple(_finite_or_none(float(v)) for v in nth),
        pairs_short_of_n=int((~torch.isfinite(nth)).sum()),
        stopped=progress.stopped,
    )


def smc_result(
    method: SMC,
    priors: Mapping[CFModel, Tensor],
    seed: int,
    n_pairs: int,
    buffers: Mapping[str, TopN],
    chosen: Chosen,
    top_n: int,
) -> SMCResult:
    """SMC's settings, budget and the shares with the prior's Occam factor
    (:func:`torchcf.abc.smc.evidence_shares`)."""
    names = [model.name for model in priors]
    settings = method.settings
    budget = smc_budget(method.n_particles, n_pairs, settings)
    scores = torch.stack([buffers[m].first(top_n)[0] for m in names])  # (M, N, n)
    member = torch.where(chosen.member, scores, -math.inf)
    tau = member.amax(dim=(0, 2))  # (N,) the hybrid's worst member per pair
    masses = []
    for model, box in priors.items():
        drawn = box[: box.shape[0] - held_values(box).numel()]
        proposals = proposals_per_pair(model, drawn, seed, budget)
        masses.append(prior_mass(buffers[model.name], proposals, tau))
    return SMCResult(
        settings=dict(settings.__dict__),
        budget=SMCBudgetResult(
            prior_draws=budget.prior,
            proposals_per_pair_and_round=budget.per_pair,
            rounds=budget.rounds,
            proposals=budget.total,
            unspent=method.n_particles - budget.total,
        ),
        evidence_shares=evidence_shares(names, masses),
    )


def with_held(buffer: TopN, box: Tensor) -> TopN:
    """A buffer of the drawn parameters with the held ones (the box's last
    rows of zero width) appended to every slot's ``theta`` (N, B, K)."""
    held = held_values(box)
    if not held.numel():
        return buffer
    full = TopN(buffer.n_pairs, buffer.capacity, buffer.theta.shape[-1] + held.numel())
    full.score, full.index = buffer.score, buffer.index
    tail = held.to(buffer.theta).expand(*buffer.theta.shape[:2], -1)
    full.theta = torch.cat((buffer.theta, tail), dim=-1)
    return full


def read_calibration(
    priors: Mapping[CFModel, Tensor],
    method: Method,
    selection: SelectionRule,
    seed: int,
    pairs: PairSet,
    state: CalibrationState,
    cells: int,
    seconds: float,
) -> Calibration:
    """The hybrid and its records, read from the buffers of ``state``.

    Args:
        priors: the models (in the calibration's order) and their prior boxes.
        method: the sampler.
        selection: how the hybrid is read.
        seed: the calibration's seed.
        pairs: the training pairs (the posterior's ids and label).
        state: the state after the streams.
        cells: rollouts per particle (1 paired, N in the full layout).
        seconds: the calibration's wall time [s].
    """
    models = list(priors)
    names = [model.name for model in models]
    buffers = [state.buffers[name] for name in names]
    if weighted(method) is not None:  # the hybrid reads the parameters alone
        buffers = [
            with_held(parameter_buffer(buffer), priors[model])
            for buffer, model in zip(buffers, models, strict=True)
        ]
    how = {"mode": selection.mode, "global_size": selection.global_size}
    chosen = select(buffers, names, selection.top_n, **how)
    table = pairwise_table(buffers, names, selection.top_n, **how)
    sensitivity = {
        n: select(buffers, names, n, **how).shares()
        for n in sorted(set(selection.sensitivity_n))
    }
    posterior = hybrid_posterior(
        buffers,
        models,
        chosen,
        selection.top_n,
        torch.as_tensor(pairs.pair_ids, dtype=torch.int64),
        dataset=pairs.name,
        mode=selection.mode,
    )
    smc = None
    if isinstance(method, SMC):
        smc = smc_result(
            method, priors, seed, pairs.n_pairs, state.buffers, chosen, selection.top_n
        )
    per_model = {
        name: model_result(
            state.buffers[name], state.progress[name], selection.top_n, cells
        )
        for name in names
    }
    stream_seconds = sum(state.progress[name].seconds for name in names)
    return Calibration(
        posterior, table, sensitivity, per_model, seconds, stream_seconds, smc
    )


__all__ = ["Calibration", "model_result", "read_calibration", "smc_result"]
