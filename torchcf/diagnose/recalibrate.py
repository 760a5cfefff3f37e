"""The re-calibration (loop step 3): the chosen effects on the whole training
windows, from the run's own particles, beside the pool searched the same way.

The run searched its pool with ``abc.n_particles`` draws per model; the
re-calibration starts from what that search kept (every model's per-pair
buffer, :func:`run_population`) and spends more on top of it, the same for both
sides (:func:`recalibrate`):

- the **reference** ("before, searched the same way"): the run's particles
  searched by themselves until the search converges (:func:`~torchcf.
  diagnose.search.converge`, at most ``max_rounds`` rounds);
- **after**: the reference, plus the reference's particles lifted to the
  variants of the chosen effects (a driver effect refitted at its design
  points as in the attribution, :func:`~torchcf.diagnose.arms.design_fits`; a
  shared one at the value the attribution found, pinned) and searched the same
  way, one effect after the other in the order chosen.

After holds every particle of the reference, and the reference every particle
of the run, so on the training pairs neither can be worse than what it builds
on: the search effort is at least the run's own, and the test-split change from
the reference to after is the effects', not the search's. Both are written as
run directories (``RUN_DIR/loop/after``, ``RUN_DIR/loop/reference``:
:func:`write_run`) and evaluated on the test split like the run.

Shapes: N pairs, S slots per pair, C buffer slots, K parameters
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

from ..abc.hybrid import hybrid_posterior, pairwise_table, select
from ..abc.particles import Particles
from ..abc.topn import TopN
from ..config import TrainConfig, validate_config
from ..data import PairSet
from ..models import CFModel, get_model, require_model
from ..models.effects import Effect
from ..posterior import Posterior
from ..runs.directory import RunDir
from .arms import Arena, Arm, design_fits, design_values
from .candidates import attribution_rollout, attribution_seed
from .population import Population, merge
from .search import Converging, Limits, Noise, converge, lift, model_bounds


def run_population(posterior: Posterior, size: int) -> Population:
    """The run's particles: per training pair, the ``size`` best over every
    model's buffer (the buffers' pairs are the posterior's training pairs, in
    order)."""
    sets = []
    for name in posterior.models:
        model = get_model(name)  # the posterior's names enter here
        buffer = posterior.buffers[name]
        score = buffer["score"].double()  # (N, C)
        n, c = score.shape
        sets.append(
            Particles(
                model,
                buffer["theta"].double().reshape(n * c, -1),
                torch.arange(n).repeat_interleave(c),
                score.reshape(-1),
                buffer["index"].reshape(-1),
            )
        )
    return Population.from_particles(sets, len(posterior.train_pair_ids), size)


def recalibrate(
    cfg: TrainConfig,
    posterior: Posterior,
    chosen: Sequence[Effect],
    shared: dict[str, list[float]],
    pool: Sequence[CFModel],
    train_pairs: PairSet,
    *,
    tick: Callable[[], None] | None = None,
) -> tuple[Population, Population]:
    """The reference and after (module docstring) on the training pairs.

    Args:
        chosen: the chosen effects, in the order chosen.
        shared: per chosen shared effect name, its value.
        pool: the pool models the effects were tested on (only their particles
            get the effects).
        tick: called after every search round.

    Returns:
        ``(reference, after)``.
    """
    settings = cfg.diagnose
    size = max(settings.population, cfg.abc.top_n)
    rollout = attribution_rollout(cfg, train_pairs)
    seed = attribution_seed(cfg)
    priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
    values = {k: torch.tensor(v, dtype=torch.float64) for k, v in shared.items()}
    start = run_population(posterior, size)

    def ticked(_: Converging) -> None:
        if tick is not None:
            tick()

    def search(
        begin: Population, noise: Noise, parents: dict[CFModel, CFModel]
    ) -> Population:
        bounds = {m: model_bounds(m, priors, values) for m in begin.models}
        searched, _ = converge(
            begin,
            rollout,
            bounds,
            noise,
            parents,
            Limits.of(settings),
            after_round=ticked,
        )
        return searched

    current = {m: m.param_names for m in start.models}
    key = (seed, "recalibration")
    reference = search(start, Noise(key, current), {m: m for m in start.models})
    after = reference
    growing = set(pool)
    for effect in chosen:
        base = _only(after, growing)
        current = {m: m.param_names for m in base.models}
        if effect.shared:
            lifted, lifted_from = lift(base, effect, values[effect.name], rollout)
            begin = merge([lifted], size)
        else:  # the attribution's design points, on the whole windows
            arena = Arena(settings, rollout, rollout, seed, priors, cfg.abc.top_n)
            points = design_values(effect, key)
            fits, lifted_from = design_fits(
                arena, Arm((), base, values), effect, 0, tick or _quiet, points
            )
            begin = merge(fits, size)
        parents = {m: m for m in base.models} | lifted_from
        searched = search(begin, Noise((*key, effect), current, effect), parents)
        after = merge([after, searched], size)
        growing |= set(lifted_from)
    return reference, after


def _quiet() -> None:
    """No progress to show."""


def _only(population: Population, models: set[CFModel]) -> Population:
    """The population's slots of ``models`` alone (the others emptied)."""
    keep = torch.tensor([m in models for m in population.models] + [False])
    held = keep[population.model] & (population.model >= 0)
    return merge(
        [
            Population(
                population.models,
                torch.where(held, population.model, -1),
                torch.where(held[..., None], population.theta, math.nan),
                torch.where(held, population.score, math.inf),
                torch.where(held, population.index, -1),
            )
        ],
        population.size,
    )


# ------------------------------------------------------------- run directories
def model_buffers(
    posterior: Posterior, population: Population, models: Sequence[CFModel]
) -> list[TopN]:
    """Per model, its per-pair best ``C`` (the run's buffer capacity) over the
    run's buffer (by the model's name) and the population's slots of that model
    (an entry held by both is kept once)."""
    n = population.n_pairs
    capacity = next(iter(posterior.buffers.values()))["score"].shape[1]
    out = []
    for model in models:
        name, k = model.name, model.n_params
        parts = []
        if name in posterior.buffers:
            b = posterior.buffers[name]
            parts.append(
                (b["score"].double(), b["index"], b["theta"].double()[..., :k])
            )
        pair, slot = population.model_slots(model)
        score = torch.full((n, population.size), math.inf, dtype=torch.float64)
        index = torch.full((n, population.size), -1, dtype=torch.int64)
        theta = torch.full((n, population.size, k), math.nan, dtype=torch.float64)
        score[pair, slot] = population.score[pair, slot]
        index[pair, slot] = population.index[pair, slot]
        theta[pair, slot] = population.theta[pair, slot, :k]
        parts.append((score, index, theta))
        buffer = TopN(n, capacity, k)
        buffer.load_state_dict(best_entries(parts, capacity))
        out.append(buffer)
    return out


def best_entries(
    parts: list[tuple[Tensor, Tensor, Tensor]], capacity: int
) -> dict[str, Tensor]:
    """Per pair the ``capacity`` best of the parts' entries by (score, index),
    repeats (same score and index) once, as a TopN state."""
    score = torch.cat([p[0] for p in parts], dim=1)
    index = torch.cat([p[1] for p in parts], dim=1)
    theta = torch.cat([p[2] for p in parts], dim=1)
    order = torch.arange(score.shape[1]).expand_as(score)
    for key in (index, score):
        order = order.gather(
            1, torch.sort(key.gather(1, order), dim=1, stable=True).indices
        )
    score, index = score.gather(1, order), index.gather(1, order)
    theta = theta.gather(1, order[..., None].expand_as(theta))
    repeat = torch.zeros_like(score, dtype=torch.bool)
    repeat[:, 1:] = (score[:, 1:] == score[:, :-1]) & (index[:, 1:] == index[:, :-1])
    score = torch.where(repeat | ~torch.isfinite(score), math.inf, score)
    keep = torch.sort(~torch.isfinite(score), dim=1, stable=True).indices
    score, index = score.gather(1, keep), index.gather(1, keep)
    theta = theta.gather(1, keep[..., None].expand_as(theta))
    empty = ~torch.isfinite(score)
    index = torch.where(empty, -1, index)
    theta = torch.where(empty[..., None], 0.0, theta)
    pad = max(capacity - score.shape[1], 0)
    if pad:
        n, k = score.shape[0], theta.shape[2]
        score = torch.cat((score, torch.full((n, pad), math.inf, dtype=score.dtype)), 1)
        index = torch.cat((index, torch.full((n, pad), -1, dtype=index.dtype)), 1)
        theta = torch.cat((theta, torch.zeros(n, pad, k, dtype=theta.dtype)), 1)
    return {
        "score": score[:, :capacity].contiguous(),
        "index": index[:, :capacity].contiguous(),
        "theta": theta[:, :capacity].contiguous(),
    }


def recalibration_config(
    cfg: TrainConfig,
    models: Sequence[CFModel],
    shared_priors: dict[str, dict[str, tuple[float, float]]],
) -> TrainConfig:
    """The run's config with ``models`` (the run's, then the variants, as
    model objects: the config is where they leave as names), each variant with
    its pool model's prior and, for a shared effect, the box its value was
    found in; no loop after it, no output of its own."""
    raw = cfg.model_dump(mode="json")
    present = {spec["name"] for spec in raw["models"]}
    priors = {spec["name"]: spec["prior"] for spec in raw["models"]}
    for model in models:
        model = require_model(model, "recalibration_config")
        if model.name in present:
            continue
        prior = dict(priors.get(model.base.name) or {})
        for effect in model.effects:
            box = shared_priors.get(effect.token) or shared_priors.get(effect.name)
            if box:
                prior |= {k: list(v) for k, v in box.items()}
        raw["models"].append({"name": model.name, "prior": prior or None})
        present.add(model.name)
    raw["diagnose"]["run_after_training"] = False
    raw["output"] = None
    return validate_config(raw)


def write_run(
    out: Path,
    cfg: TrainConfig,
    posterior: Posterior,
    buffers: Sequence[TopN],
    dataset: str,
    how: str,
) -> RunDir:
    """A run directory of a re-calibration: ``config.json``, ``posterior.pt``
    (the hybrid of ``buffers``) and ``summary.json``, ready for
    :func:`torchcf.evaluation.evaluate.evaluate_run`.

    Args:
        cfg: its config (:func:`recalibration_config`).
        buffers: every model's buffer, in the order of ``cfg.models``
            (:func:`model_buffers` for a searched population).
        dataset: the run's data set label (its summary's).
        how: how the buffers were made, for ``summary.json``.
    """
    run = RunDir(out)
    run.prepare()
    names = [spec.name for spec in cfg.models]
    kwargs = {"mode": cfg.abc.selection, "global_size": cfg.abc.global_size}
    selection = select(buffers, names, cfg.abc.top_n, **kwargs)
    table = pairwise_table(buffers, names, cfg.abc.top_n, **kwargs)
    learned = hybrid_posterior(
        buffers,
        [spec.model for spec in cfg.models],
        selection,
        cfg.abc.top_n,
        posterior.train_pair_ids,
        dataset=posterior.dataset,
        mode=cfg.abc.selection,
    )
    run.write_config(cfg)
    run.save_posterior(learned)
    run.write_summary(
        {
            "dataset": dataset,
            "shares": learned.shares,
            "hybrid_size": sum(len(p) for p in learned.hybrid.values()),
            "pairwise": {
                "models": names,
                "table": [[round(float(v), 6) for v in row] for row in table],
                "meaning": "table[i][j]: share of models[i] in the hybrid of "
                "{i, j} alone",
            },
            "recalibration": how,
        }
    )
    return run


__all__ = [
    "best_entries",
    "model_buffers",
    "recalibrate",
    "recalibration_config",
    "run_population",
    "write_run",
]
