"""Candidate particles of the attribution: drawn, scored and summarised as tensors.

The attribution fits every arm on the fit windows of the training pairs with the
one ABC engine (:mod:`torchcf.abc.rejection`, the paired layout): a model's
first ``n`` prior draws stream through a per-pair top-N buffer
(:func:`prior_particles`), the kept particles are
:class:`~torchcf.abc.particles.Particles` (parameters, pair, score and stream
index, tensors throughout) and the per-pair N best over several sets are the
hybrid's selection (:func:`~torchcf.abc.particles.best_per_pair`).

Shapes: Q particles of a set, N pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..abc.particles import Particles
from ..abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from ..abc.smc import SMCSettings, new_state, parameter_buffer, run_smc, smc_budget
from ..abc.topn import TopN
from ..config import ConfigError, TrainConfig
from ..data import PairSet
from ..models import CFModel, UnknownModelError, get_model
from ..models.effects import parse_effect


def attribution_rollout(cfg: TrainConfig, pairs: PairSet) -> Rollout:
    """How the attribution simulates particles on ``pairs``: the run's precision,
    device, score weights and compile choice, each particle on its own pair."""
    return Rollout(
        pairs,
        True,
        getattr(torch, cfg.dtype),
        torch.device(cfg.device),
        tuple(cfg.abc.weights),
        cfg.compile,
    )


def attribution_seed(cfg: TrainConfig) -> int:
    """``diagnose.seed``, or the run's ``abc.seed`` when it is not set."""
    return cfg.abc.seed if cfg.diagnose.seed is None else cfg.diagnose.seed


def model_bounds(name: str, priors: dict[str, Tensor]) -> Tensor:
    """Prior box (K, 2) float64 of a model or variant, with the run's prior
    overrides (``priors``: pool model -> its box) of its pool model."""
    model = get_model(name)
    bounds = model.prior_bounds(torch.float64)
    base = model.base.name if hasattr(model, "base") else model.name
    if base in priors:
        bounds[: priors[base].shape[0]] = priors[base]
    return bounds


def augmented_variants(pool: Sequence[str], effect: str) -> list[str]:
    """Canonical names of ``m+effect`` for the pool models the effect can wrap.

    (``lag`` cannot wrap HL, which has its own actuation lag.)
    """
    names = []
    for model in pool:
        try:
            names.append(get_model(f"{model}+{effect}").name)
        except UnknownModelError:
            continue
    return names


def variant_of(model: str, effect: str) -> str | None:
    """``model+effect``'s canonical name; None where the effect cannot wrap it."""
    names = augmented_variants([model], effect)
    return names[0] if names else None


def fit_scores(rollout: Rollout, model: str, theta: Tensor, pair: Tensor) -> Tensor:
    """Scores (Q,) float64 on the CPU of particles ``theta`` (Q, K) of ``model``,
    each on its own pair ``pair`` (Q,) of the rollout's pairs (``+inf``:
    invalid)."""
    if theta.shape[0] == 0:
        return torch.empty(0, dtype=torch.float64)
    score, _ = rollout.score(get_model(model), theta, pair)
    return score.cpu()


def prior_particles(
    name: str,
    rollout: Rollout,
    budgets: Sequence[int],
    keep: int,
    bounds: Tensor,
    seed: int,
    fixed: Tensor | None = None,
    smc: SMCSettings | None = None,
) -> list[Particles]:
    """Paired ABC of one model (or variant) on the rollout's pairs: rejection, or
    with ``smc`` the sequential refinement at each budget.

    Args:
        budgets: increasing particle counts; result ``i`` holds the ``keep`` best
            per pair of the first ``budgets[i]`` prior draws of the model's stream
            (streamed through a top-N buffer, nothing else stored; empty slots
            scored ``+inf``), pair-major.
        bounds: the prior box of the drawn parameters (K_drawn, 2).
        seed: the stream's seed (:func:`attribution_seed`).
        fixed: values (K - K_drawn,) of the last parameters, the same for every
            particle (a shared effect's value).
        smc: the refinement's settings; result ``i`` is then the ``keep`` best per
            pair of an SMC run of ``budgets[i]`` proposals (its own run: an SMC
            run of a larger budget is not a continuation of a smaller one).
    """
    model = get_model(name)
    if smc is not None:
        return [
            _refined_particles(model, rollout, budget, keep, bounds, seed, fixed, smc)
            for budget in budgets
        ]
    stream = prior_stream(model.name, bounds, seed, rollout)
    buffer = TopN(rollout.pairs.n_pairs, keep, model.n_params)
    progress = ModelProgress()
    sets = []
    for budget in budgets:
        run_rejection(
            stream,
            buffer,
            rollout,
            budget,
            progress,
            model=model,
            fixed=fixed,
            plan_particles=min(budgets),
        )
        sets.append(Particles.from_buffer(model.name, buffer, keep))
    return sets


def _refined_particles(
    model: CFModel,
    rollout: Rollout,
    budget: int,
    keep: int,
    bounds: Tensor,
    seed: int,
    fixed: Tensor | None,
    smc: SMCSettings,
) -> Particles:
    """The ``keep`` best per pair of one SMC run of ``budget`` proposals."""
    n_pairs, k_drawn = rollout.pairs.n_pairs, bounds.shape[0]
    buffer = TopN(n_pairs, keep, k_drawn + 1)
    state = new_state(n_pairs, smc, k_drawn)
    if smc_budget(budget, n_pairs, smc).per_pair < 1:
        raise ConfigError(
            f"diagnose.method = 'smc': diagnose.n_particles gives {budget} "
            f"particles, no proposal per pair and round ({n_pairs} pairs, "
            f"abc.smc.rounds = {smc.rounds}); raise it or lower the rounds"
        )
    run_smc(
        model.name,
        bounds,
        seed,
        buffer,
        rollout,
        budget,
        smc,
        ModelProgress(),
        state,
        model=model,
        fixed=fixed,
    )
    particles = Particles.from_buffer(model.name, parameter_buffer(buffer), keep)
    if fixed is None:
        return particles
    theta = torch.cat((particles.theta, fixed.expand(len(particles), -1)), dim=1)
    return Particles(
        model.name, theta, particles.pair, particles.score, particles.index
    )


def compose_theta(
    model: str, variant: str, theta: Tensor, effect_values: Tensor
) -> Tensor:
    """Parameters (..., K_variant) of ``variant`` = ``model`` plus one effect, from
    the model's ``theta`` (..., K_model) and the effect's ``effect_values``
    (..., K_E), placed by parameter name (the effect's columns need not be the
    last: effects keep their canonical order in a name)."""
    have = get_model(model).param_names
    names = get_model(variant).param_names
    added = [n for n in names if n not in have]
    columns = [
        theta[..., have.index(n)] if n in have else effect_values[..., added.index(n)]
        for n in names
    ]
    return torch.stack(columns, dim=-1)


def pinned_box(
    variant: str, priors: dict[str, Tensor], shared: dict[str, Tensor]
) -> tuple[Tensor, Tensor | None]:
    """A variant's prior box (K, 2) with every shared (road) effect it carries
    pinned at its one value, and those values (the trailing parameters: shared
    effects come last in a name), or None.

    Args:
        priors: the run's prior box per pool model (:func:`model_bounds`).
        shared: per shared effect token name (``"grade"``), its value (K_E,).
    """
    model = get_model(variant)
    box = model_bounds(variant, priors)
    values = [
        shared[e.name]
        for e in getattr(model, "effects", ())
        if e.shared and e.name in shared
    ]
    if not values:
        return box, None
    fixed = torch.cat(values).to(torch.float64)
    box[box.shape[0] - fixed.numel() :] = fixed[:, None].expand(-1, 2)
    return box, fixed


def validation_scores(picks: Sequence[Particles], rollout: Rollout) -> np.ndarray:
    """Median out-of-sample score of each pair's picks on the rollout's pairs (its
    validation windows).

    Returns:
        (N,) float64 ndarray; ``inf`` where more than half of a pair's picks are
        invalid or it has none.
    """
    n_pairs = rollout.pairs.n_pairs
    scores = [fit_scores(rollout, s.model, s.theta, s.pair) for s in picks]
    score = torch.cat(scores).numpy() if scores else np.empty(0)
    pair = torch.cat([s.pair for s in picks]).numpy() if picks else np.empty(0, int)
    order = np.argsort(pair, kind="stable")
    groups = np.split(score[order], np.cumsum(np.bincount(pair, minlength=n_pairs)))
    return np.array(
        [np.median(group) if group.size else np.inf for group in groups[:n_pairs]]
    )


def effect_estimate(picks: Sequence[Particles], effect: str) -> dict[str, float]:
    """Median of the effect's parameters over the picks of its variants."""
    names = [p.name for p in parse_effect(effect).param_specs]
    token = effect.split("(")[0]
    values = [
        s.theta[:, [get_model(s.model).param_names.index(n) for n in names]]
        for s in picks
        if len(s) and token in [t.split("(")[0] for t in s.model.split("+")[1:]]
    ]
    if not values:
        return {}
    median = torch.cat(values).median(dim=0).values
    return dict(zip(names, median.tolist(), strict=True))


__all__ = [
    "attribution_rollout",
    "attribution_seed",
    "augmented_variants",
    "compose_theta",
    "effect_estimate",
    "fit_scores",
    "model_bounds",
    "pinned_box",
    "prior_particles",
    "validation_scores",
    "variant_of",
]
