"""The re-calibration (loop step 3): the chosen effects searched as the run
searched its models, written as run directories for the test split.

The run drew ``N = abc.n_particles`` particles per model with its sampler
(``abc.method``: rejection or SMC) and kept every model's per-pair best ``C``
(its buffers). This re-calibration spends the same again on every pool model,
once with the effects and once without:

- **after**: each pool model's variant with the chosen effects (``idm+delay``)
  trained exactly as the run trained a model: the same sampler, ``N`` particles
  from its own stream (seed, variant name), the run's prior box of the pool
  model and the effect's own prior, the same plausibility filter; beside the
  run's buffers, so the after hybrid is the run's models and the variants
  competing pair by pair under the run's selection (a variant that does not
  help is simply not picked).
- **reference** ("before, searched the same way"): the pool models that a
  variant wraps given ``N`` more particles. Rejection continues each pool
  model's own stream from particle ``N`` to ``2N`` into the run's buffer:
  exactly the run with twice the draws for those models. SMC refines each
  pool model again with a seed derived from the run's and its best ``C`` per
  pair are merged into the run's buffer.

An amortised run (``abc.method = "amortised"``) is re-calibrated by
**rejection** at ``N = abc.n_particles``: its estimator was trained on the pool
models, not on the variants, and its samples are no stream to continue. So
after's variants are rejection's ``N`` prior draws each, and the reference
merges ``N`` fresh prior draws of each wrapped pool model (a seed derived from
the run's, as for SMC) into the run's buffer. ``abc.n_particles`` then sets the
re-calibration's cost alone.

So after and reference hold the run's particles and ``N`` more per pool model
drawn the run's way: the test-split change from the reference to after is the
effects', not the search's, and neither can be worse than the run on the
training pairs. Nothing is refined around the training pairs' optima, so the
spread of particles that covers drivers the run never saw is the run's own.

The run's sampler, rollout and budget come from its config through the one
translation training uses (:func:`torchcf.calibration.of_config.setup_of`).
Both are written as run directories (``RUN_DIR/loop/after``,
``RUN_DIR/loop/reference``: :func:`write_run`, their config
:func:`recalibration_config`) and evaluated on the test split like the run.

A shared effect (one value for every pair) is held at the value the attribution
found where its parameters are the variant's last (the samplers draw the others
and append it, as the attribution's shared search does); ahead of a driver
effect (``idm+offset+delay``) it is drawn from the box the attribution found it
in (:attr:`~torchcf.diagnose.selection.attribution.EffectSelection.shared_priors`):
:func:`searched_box`.

Every model's finished buffer is kept in ``RUN_DIR/loop/retrain.pt``
(:class:`~torchcf.diagnose.selection.attribution.Ledger`), so an interrupted
re-calibration resumes at the model it was in.

Shapes: N pairs, C buffer slots, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..abc.hybrid import hybrid_posterior, pairwise_table, select
from ..abc.rejection import ModelProgress, Rollout, prior_stream, run_rejection
from ..abc.rounds import RoundHooks
from ..abc.screen import PlausibilityScreen
from ..abc.topn import TopN
from ..calibration import SMC, Rejection, Tracker, calibrate
from ..calibration.of_config import setup_of
from ..config import TrainConfig, validate_config
from ..data import PairSet
from ..models import CFModel, require_model
from ..posterior import Posterior
from ..runs.directory import RunDir
from ..runs.summary import Pairwise, RecalibrationSummary
from .arms.search import derive_seed, model_bounds
from .selection.attribution import EffectSelection, Ledger, ledger_key
from .setup import LoopSetup

#: Buffers per model name, as TopN states (``score`` (N, C), ``index`` (N, C),
#: ``theta`` (N, C, K)).
Buffers = dict[str, dict[str, Tensor]]


def variants_of(
    models_after: Sequence[CFModel], run_models: Sequence[str]
) -> list[CFModel]:
    """The variants of the after model: its models the run does not have (the
    run's models by name, as its posterior lists them)."""
    return [m for m in models_after if m.name not in run_models]


@dataclass(frozen=True)
class FinalModel:
    """The selection's final model, as the re-calibration trains it.

    Attributes:
        models: the pool and the variants of the chosen effects, as model
            objects (the run's buffers and the ledger are keyed by their
            ``name``).
        shared: per chosen shared effect name, its value (K_E,).
        shared_priors: per chosen shared effect token, the box it was found
            in: per parameter name, ``(low, high)``.
    """

    models: Sequence[CFModel]
    shared: dict[str, list[float]] = field(default_factory=dict)
    shared_priors: dict[str, dict[str, tuple[float, float]]] = field(
        default_factory=dict
    )

    def __post_init__(self) -> None:
        for model in self.models:
            require_model(model, "FinalModel")

    @classmethod
    def of(cls, selection: EffectSelection) -> FinalModel:
        """The final model of a forward selection (:func:`attribute_effects
        <torchcf.diagnose.selection.attribution.attribute_effects>`)."""
        return cls(list(selection.models), selection.shared, selection.shared_priors)


def retrain(
    cfg: TrainConfig,
    posterior: Posterior,
    final: FinalModel,
    pool: Sequence[CFModel],
    train_pairs: PairSet,
    *,
    screen: PlausibilityScreen | None = None,
    ledger: Path | None = None,
    tick: Callable[[int], None] | None = None,
) -> tuple[Buffers, Buffers]:
    """The reference's and after's buffers (module docstring).

    Args:
        final: the final model of the selection (its models, and its shared
            effects' values and boxes).
        pool: the pool models; those a variant wraps get ``N`` more particles
            in the reference (:func:`wrapped`).
        screen: the run's plausibility filter (``plausibility.filter``), built
            by the caller (:func:`torchcf.traffic.configured.plausibility_screen`);
            None when it is off.
        ledger: where finished models are kept (None: nowhere, no resume).
        tick: called with the particles done after every round of every model.

    Returns:
        ``(reference, after)``: the reference's buffers of the run's models,
        after's of the run's models and the variants (the run's buffers where
        a model is not searched again).
    """
    run_models = list(posterior.models)
    variants = variants_of(final.models, run_models)
    rollout = setup_of(cfg, train_pairs).rollout
    priors = {spec.name: spec.bounds(torch.float64) for spec in cfg.models}
    shared = final.shared
    values = {k: torch.tensor(v, dtype=torch.float64) for k, v in shared.items()}
    names = [m.name for m in final.models]
    key = ledger_key(LoopSetup.of(cfg), [m.name for m in pool], names)
    book = Ledger(ledger, f"retrain|{key}|{json.dumps(shared, sort_keys=True)}")
    run_buffers = {m: _run_buffer(posterior, m) for m in run_models}

    def kept(label: str, compute: Callable[[], dict[str, Tensor]]) -> Any:
        entry = book.get(label)
        if entry is None:
            entry = compute()
            book.put(label, entry)
        elif tick is not None:
            tick(cfg.abc.n_particles)
        return entry

    reference = dict(run_buffers)
    for model in wrapped(variants, pool):
        name = model.name
        reference[name] = kept(
            f"reference:{name}",
            lambda model=model, name=name: _more_of(
                cfg, model, priors[name], run_buffers[name], rollout, screen, tick
            ),
        )
    after = dict(run_buffers)
    for variant in variants:
        bounds, fixed = searched_box(
            variant, model_bounds(variant, priors, values), final.shared_priors
        )
        after[variant.name] = kept(
            f"after:{variant.name}",
            lambda variant=variant, bounds=bounds, fixed=fixed: _trained(
                cfg, variant, bounds, cfg.abc.seed, rollout, screen, tick, fixed
            ),
        )
    return reference, after


def wrapped(variants: Sequence[CFModel], pool: Sequence[CFModel]) -> list[CFModel]:
    """The pool models the variants wrap, in pool order: those after spends
    ``N`` particles on (``lag`` cannot wrap HL: HL gets none either way)."""
    bases = {v.pool_model.name for v in variants}
    return [m for m in pool if m.name in bases]


def _run_buffer(posterior: Posterior, name: str) -> dict[str, Tensor]:
    """The run's buffer of ``name`` with its own parameters (``K_m`` columns, as
    many as the posterior records for the model)."""
    raw = posterior.buffers[name]
    k = len(posterior.hybrid[name].param_names)
    return {
        "score": raw["score"].double(),
        "index": raw["index"].long(),
        "theta": raw["theta"].double()[..., :k],
    }


def _more_of(
    cfg: TrainConfig,
    model: CFModel,
    bounds: Tensor,
    run_buffer: dict[str, Tensor],
    rollout: Rollout,
    screen: PlausibilityScreen | None,
    tick: Callable[[int], None] | None,
) -> dict[str, Tensor]:
    """The run's buffer of pool model ``model`` after ``N`` more particles drawn
    the run's way (module docstring: the reference)."""
    n_particles = cfg.abc.n_particles
    if cfg.abc.method != "rejection":  # SMC again, or amortised: rejection's
        seed = derive_seed(cfg.abc.seed, "reference", model.name)
        fresh = _trained(cfg, model, bounds, seed, rollout, screen, tick)
        capacity = run_buffer["score"].shape[1]
        parts = [(b["score"], b["index"], b["theta"]) for b in (run_buffer, fresh)]
        return best_entries(parts, capacity)
    n, capacity = run_buffer["score"].shape
    buffer = TopN(n, capacity, model.n_params)
    buffer.load_state_dict(run_buffer)
    progress = ModelProgress(next=n_particles)
    run_rejection(
        prior_stream(model, bounds, cfg.abc.seed, rollout),
        buffer,
        rollout,
        2 * n_particles,
        progress,
        plan_particles=n_particles,
        hooks=RoundHooks(screen=screen, after_round=_ticker(tick, start=n_particles)),
    )
    return _cpu(buffer.state_dict())


def _trained(
    cfg: TrainConfig,
    model: CFModel,
    bounds: Tensor,
    seed: int,
    rollout: Rollout,
    screen: PlausibilityScreen | None,
    tick: Callable[[int], None] | None,
    fixed: Tensor | None = None,
) -> dict[str, Tensor]:
    """``model``'s buffer after ``N`` particles from its stream of ``seed``,
    calibrated by the run's sampler (:func:`torchcf.calibration.calibrate`, as
    :func:`torchcf.train.train` calibrates a model; an amortised run's:
    rejection, module docstring) over ``bounds``, ``(K_drawn, 2)``; with
    ``fixed``, its last parameters held there (appended to every slot's
    ``theta``)."""
    setup = setup_of(cfg, rollout.pairs)
    method = setup.method
    if not isinstance(method, SMC):
        method = Rejection(cfg.abc.n_particles)
    box = bounds if fixed is None else torch.cat((bounds, fixed[:, None].expand(-1, 2)))
    result = calibrate(
        rollout,
        {model: box},
        method,
        selection=setup.selection,
        seed=seed,
        screen=screen,
        tracker=_Ticking(tick),
    )
    buffer = result.posterior.buffers[model.name]
    return _cpu({key: buffer[key] for key in ("score", "index", "theta")})


class _Ticking(Tracker):
    """A calibration's tracker that reports the particles done since the last
    call to ``tick`` (None: nothing)."""

    def __init__(self, tick: Callable[[int], None] | None) -> None:
        super().__init__()
        self.tick, self.done = tick, 0

    def round(self, name: str, progress: ModelProgress, rollout: Rollout) -> None:
        if self.tick is not None:
            self.tick(progress.next - self.done)
        self.done = progress.next


def searched_box(
    model: CFModel,
    bounds: Tensor,
    shared_priors: dict[str, dict[str, tuple[float, float]]],
) -> tuple[Tensor, Tensor | None]:
    """What a variant's sampler draws, ``(K_drawn, 2)``, and the values of its
    last ``K - K_drawn`` parameters, held (None: all drawn).

    ``bounds`` (:func:`~torchcf.diagnose.arms.search.model_bounds`) pin a shared
    effect with a zero-width row. Pinned rows that are the last ones are held
    (the samplers draw a box of positive width only); a pinned row before a
    drawn one (a recording effect ahead of a driver effect in the variant's
    name) is drawn from the box the attribution found it in.
    """
    pinned = bounds[:, 0] == bounds[:, 1]
    drawn = int(pinned.numel())
    while drawn and bool(pinned[drawn - 1]):
        drawn -= 1
    fixed = bounds[drawn:, 0].clone() if drawn < pinned.numel() else None
    out = bounds[:drawn].clone()
    boxes = {p: box for prior in shared_priors.values() for p, box in prior.items()}
    names = model.param_names
    for column in torch.nonzero(pinned[:drawn]).flatten().tolist():
        if names[column] not in boxes:
            raise ValueError(f"{model.name}: no box for the shared {names[column]}")
        out[column] = torch.tensor(boxes[names[column]], dtype=torch.float64)
    return out, fixed


def _ticker(
    tick: Callable[[int], None] | None, start: int
) -> Callable[[ModelProgress, bool], None] | None:
    """A sampler's ``after_round`` that reports the particles done since the
    last call to ``tick``."""
    if tick is None:
        return None
    done = [start]

    def after_round(progress: ModelProgress, _due: bool) -> None:
        tick(progress.next - done[0])
        done[0] = progress.next

    return after_round


def _cpu(state: dict[str, Tensor]) -> dict[str, Tensor]:
    """A TopN state on the CPU, score and theta float64."""
    return {
        "score": state["score"].detach().double().cpu(),
        "index": state["index"].detach().long().cpu(),
        "theta": state["theta"].detach().double().cpu(),
    }


def buffers_in_order(buffers: Buffers, models: Sequence[str]) -> list[TopN]:
    """``buffers`` as TopN objects in the order of ``models``."""
    out = []
    for name in models:
        state = buffers[name]
        n, capacity, k = state["theta"].shape
        buffer = TopN(n, capacity, k)
        buffer.load_state_dict(state)
        out.append(buffer)
    return out


# ------------------------------------------------------------- run directories
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
        buffers: every model's buffer, in the order of ``cfg.models``.
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
        RecalibrationSummary(
            dataset=dataset,
            shares=dict(learned.shares),
            hybrid_size=sum(len(p) for p in learned.hybrid.values()),
            pairwise=Pairwise(
                models=tuple(names),
                table=tuple(tuple(round(float(v), 6) for v in row) for row in table),
            ),
            recalibration=how,
        )
    )
    return run


__all__ = [
    "Buffers",
    "FinalModel",
    "best_entries",
    "buffers_in_order",
    "recalibration_config",
    "retrain",
    "write_run",
    "searched_box",
    "variants_of",
    "wrapped",
]
