"""A driver predicted from a history of its own: the first seconds of a new pair
give the driver's own posterior, which predicts the rest.

Given the first ``history`` seconds of a pair (steps ``0..k``, ``k = history /
dt``), :func:`driver_posterior` finds the particles that reproduce them, ABC's
rejection on the pair's own history with the hybrid as the prior over drivers:

1. **candidates**: the hybrid's particles, every model's (at most
   ``MAX_CANDIDATES``, a seeded uniform choice beyond), and, for a run with an
   amortised estimator, ``AMORTISED_SAMPLES`` draws of ``q(m, theta | history)``;
   each is simulated on the history and scored by SPEC section 4's score; the
   best ``keep`` are the driver's posterior;
2. optionally (``rounds`` > 0, off by default) **a search of the pair's own**:
   ``rounds`` times its ``ELITE`` best get ``copies`` perturbed copies each
   (normal steps of ``SCALES[c % 3]`` times each parameter's prior width,
   clipped to the prior box), scored on the history, the best ``keep`` kept.
   A few seconds of one driver do not identify a model's parameters: the
   search fits the history's noise and predicts the rest worse than the
   hybrid's own particles (``reports/predict.md`` measures both), so the
   posterior keeps many (``keep``) rather than the few best.

:func:`predict_rest` then simulates the kept particles from the recorded state
at step ``k`` behind the recorded leader to the pair's end; the prediction is
their per-step median spacing. A pair with fewer than ``MIN_REST`` seconds after
its history is not predicted.

Shapes: T steps, N pairs, Q candidates, E kept particles per pair
(:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..abc.streams import block_seed
from ..data import PairSet
from ..models import CFModel
from .population import SCALES
from .rollouts import Particles, follow, padded, steps_between
from .trained import TrainedRun

#: Hybrid particles tried per pair at most.
MAX_CANDIDATES = 16384
#: Draws of the amortised posterior per pair (runs with an estimator).
AMORTISED_SAMPLES = 256
#: Particles refined per pair and round.
ELITE = 8
#: The shortest rest [s] a pair needs to be predicted.
MIN_REST = 5.0
#: The shrunk search's rounds and copies per pair and round.
SHRINK_ROUNDS = 30
SHRINK_COPIES = 32


@dataclass(frozen=True)
class DriverPosterior:
    """Per pair, the particles that reproduce its history best.

    Attributes:
        particles: ``E`` per pair, pair-major (particle ``j * E + e``).
        score: ``(N, E)`` float64 their scores on the history, ascending.
        history_steps: k, the last step of the history.
    """

    particles: Particles
    score: Tensor
    history_steps: int


def history_steps(pairs: PairSet, history: float) -> int:
    """k: the step ``history`` seconds in."""
    return int(round(history / pairs.dt))


def predictable(pairs: PairSet, history: float) -> Tensor:
    """``(N,)`` bool, the pairs with at least :data:`MIN_REST` seconds after
    their history."""
    k = history_steps(pairs, history)
    rest = pairs.lengths.cpu() - 1 - k
    return rest * pairs.dt >= MIN_REST


def driver_posterior(
    run: TrainedRun,
    pairs: PairSet,
    history: float,
    *,
    keep: int = 100,
    rounds: int = 0,
    copies: int = 8,
    seed: int = 0,
    own_excluded: bool = False,
) -> DriverPosterior:
    """Every pair's own posterior from its first ``history`` seconds (module
    docstring). Every pair must be :func:`predictable`. ``own_excluded``: a
    pair's own hybrid particles (by pair id) are not its candidates (a
    training pair judged as if new)."""
    k = history_steps(pairs, history)
    past = steps_between(pairs, 0, k + 1)
    models = tuple(run.hybrid_models)
    model_of, theta, source = _candidates(run, list(models), past, seed)
    score = _scores(models, model_of, theta, past)  # (N, Q)
    if own_excluded:
        ids = torch.tensor(pairs.pair_ids)[:, None]
        score = torch.where(source == ids, torch.full_like(score, math.inf), score)
    keep = min(keep, model_of.shape[1])
    low, width = _boxes(run, models)
    normals = pair_normals(
        pairs, seed, "refine", (rounds, ELITE * copies, theta.shape[2])
    )
    held = max(keep, ELITE)
    model_of, theta, score = _best(model_of, theta, score, held)
    scales = torch.tensor([SCALES[c % len(SCALES)] for c in range(copies)]).double()
    for r in range(rounds):
        parent_model = model_of[:, :ELITE].repeat_interleave(copies, 1)  # (N, E*C)
        parent = theta[:, :ELITE].repeat_interleave(copies, 1)  # (N, E*C, K)
        steps = normals[:, r]
        size = scales.repeat(ELITE)[None, :, None] * width[parent_model]
        moved = torch.clamp(parent + steps * size, min=low[parent_model])
        moved = torch.minimum(moved, low[parent_model] + width[parent_model])
        moved_score = _scores(models, parent_model, moved, past)
        model_of, theta, score = _best(
            torch.cat([model_of, parent_model], 1),
            torch.cat([theta, moved], 1),
            torch.cat([score, moved_score], 1),
            held,
        )
    n = pairs.n_pairs
    particles = Particles(
        models,
        model_of[:, :keep].reshape(-1),
        theta[:, :keep].reshape(n * keep, -1),
        torch.arange(n).repeat_interleave(keep),
    )
    return DriverPosterior(particles, score[:, :keep], k)


def shrunk_fit(
    model: CFModel,
    center: Tensor,
    prior: Tensor,
    pairs: PairSet,
    history: float,
    strength: float,
    *,
    seed: int = 0,
) -> DriverPosterior:
    """Every pair's own vector of ``model`` from its first ``history`` seconds,
    shrunk toward the population's vector ``center`` (K,) inside ``prior``
    (K, 2): the minimum of

        S_history(theta) + strength * sum_k ((theta_k - center_k) / w_k)^2

    (``w_k`` the prior's width: a Gaussian prior around the population's
    vector, the posterior's mode), found by :data:`SHRINK_ROUNDS` rounds of
    :data:`SHRINK_COPIES` perturbed copies of each pair's best so far (steps
    of ``SCALES[r % 3]`` times the prior's width), from the center."""
    k = history_steps(pairs, history)
    past = steps_between(pairs, 0, k + 1)
    n, width = pairs.n_pairs, (prior[:, 1] - prior[:, 0]).double()
    center = center.double()
    rounds, copies = SHRINK_ROUNDS, SHRINK_COPIES
    normals = pair_normals(pairs, seed, "shrink", (rounds, copies, len(center)))

    def objective(theta: Tensor) -> Tensor:  # (N, C, K) -> (N, C)
        c = theta.shape[1]
        particles = Particles(
            (model,),
            torch.zeros(n * c, dtype=torch.int64),
            theta.reshape(n * c, -1),
            torch.arange(n).repeat_interleave(c),
        )
        fit = follow(particles, past, trajectories=False).score.reshape(n, c)
        return fit + strength * (((theta - center) / width) ** 2).sum(-1)

    best = center.expand(n, 1, -1).clone()
    best_value = objective(best)[:, 0]
    best = best[:, 0]
    for r in range(rounds):
        moved = best[:, None] + normals[:, r] * SCALES[r % len(SCALES)] * width
        moved = torch.maximum(torch.minimum(moved, prior[:, 1]), prior[:, 0])
        value, which = objective(moved).min(1)
        better = value < best_value
        best[better] = moved[better, which[better]]
        best_value = torch.where(better, value, best_value)
    particles = Particles(
        (model,), torch.zeros(n, dtype=torch.int64), best, torch.arange(n)
    )
    return DriverPosterior(particles, best_value[:, None], k)


def predict_rest(
    posterior: DriverPosterior, pairs: PairSet
) -> tuple[PairSet, Tensor, Tensor]:
    """The pairs after their history, driven by each pair's posterior.

    Returns:
        ``(rest, median, collided)``: the pairs' steps from k on (their
        :class:`~torchcf.data.PairSet`, the follower starting from its recorded
        state at k), ``(T_rest, N)`` the kept particles' median spacing [m]
        per step (NaN past a pair's end; a particle that collided left out),
        ``(N,)`` int64 the kept particles that collided.
    """
    rest = steps_between(pairs, posterior.history_steps)
    paths = follow(posterior.particles, rest)
    keep = posterior.score.shape[1]
    x = paths.x.reshape(rest.n_steps, rest.n_pairs, keep)
    gap = rest.x_lead.double().cpu()[:, :, None] - x - rest.leader_length
    valid = paths.valid.reshape(1, rest.n_pairs, keep)
    gap = torch.where(valid, gap, torch.full_like(gap, math.nan))
    median = torch.nanquantile(gap, 0.5, dim=2)  # NaN where every one collided
    median[~rest.mask.cpu()] = math.nan
    collided = (~paths.valid).reshape(rest.n_pairs, keep).sum(1)
    return rest, median, collided


# ----------------------------------------------------------------- the search
def pair_normals(
    pairs: PairSet, seed: int, label: str, shape: tuple[int, ...]
) -> Tensor:
    """``(N, *shape)`` float64 standard normals, each pair's from a generator
    of its own (seeded by ``seed``, ``label`` and its id): a pair's search does
    not depend on the pairs searched with it."""
    return torch.stack(
        [
            torch.randn(
                shape,
                generator=torch.Generator().manual_seed(
                    block_seed(seed, label, int(i))
                ),
                dtype=torch.float64,
            )
            for i in pairs.pair_ids
        ]
    )


def _candidates(
    run: TrainedRun, models: list[CFModel], past: PairSet, seed: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``(model_of (N, Q), theta (N, Q, K), source (N, Q))`` every pair's
    candidates: the hybrid's particles (at most :data:`MAX_CANDIDATES`, a
    seeded choice) with the training pair each was kept for, and, with an
    estimator, the pair's amortised draws (source -1)."""
    model_of, theta = padded(models, [run.particles(m) for m in models])
    source = torch.cat([run.posterior.hybrid[m.name].pair_ids.long() for m in models])
    if len(model_of) > MAX_CANDIDATES:
        generator = torch.Generator().manual_seed(seed)
        pick = torch.randperm(len(model_of), generator=generator)[:MAX_CANDIDATES]
        model_of, theta, source = model_of[pick], theta[pick], source[pick]
    n = past.n_pairs
    model_of = model_of.expand(n, -1)
    theta = theta.expand(n, -1, -1)
    source = source.expand(n, -1)
    if run.estimator is None:
        return model_of, theta, source
    drawn_model, drawn = _amortised(run, models, past, seed)
    width = theta.shape[2]
    drawn = torch.nn.functional.pad(
        drawn, (0, width - drawn.shape[2]), value=float("nan")
    )
    return (
        torch.cat([model_of, drawn_model], 1),
        torch.cat([theta, drawn[..., :width]], 1),
        torch.cat([source, torch.full(drawn_model.shape, -1)], 1),
    )


def _amortised(
    run: TrainedRun, models: list[CFModel], past: PairSet, seed: int
) -> tuple[Tensor, Tensor]:
    """``(model_of (N, A), theta (N, A, K_s))`` the estimator's draws of each
    pair's posterior given its history (the estimator's model order mapped to
    the run's)."""
    from ..amortised.inference import infer  # only runs with an estimator

    found = infer(
        run.estimator, past.to(dtype=torch.float32), AMORTISED_SAMPLES, seed=seed
    )
    names = [m.name for m in models]
    absent = [name not in names for name in run.estimator.space.names]
    mapping = torch.tensor(
        [
            0 if a else names.index(n)
            for n, a in zip(run.estimator.space.names, absent, strict=True)
        ]
    )
    theta = found.theta.double()
    # a model the hybrid holds no particle of: its draws left out (NaN: invalid)
    theta[torch.tensor(absent)[found.model]] = float("nan")
    return mapping[found.model], theta


def _scores(
    models: tuple[CFModel, ...], model_of: Tensor, theta: Tensor, past: PairSet
) -> Tensor:
    """``(N, Q)`` float64 each pair's candidates' scores on its history."""
    n, q = model_of.shape
    particles = Particles(
        models,
        model_of.reshape(-1),
        theta.reshape(n * q, -1),
        torch.arange(n).repeat_interleave(q),
    )
    return follow(particles, past, trajectories=False).score.reshape(n, q)


def _best(model_of: Tensor, theta: Tensor, score: Tensor, held: int):
    """Each pair's ``held`` best candidates, ascending by score (stable)."""
    order = torch.argsort(score, dim=1, stable=True)[:, :held]
    return (
        torch.gather(model_of, 1, order),
        torch.gather(theta, 1, order[:, :, None].expand(-1, -1, theta.shape[2])),
        torch.gather(score, 1, order),
    )


def _boxes(run: TrainedRun, models: tuple[CFModel, ...]) -> tuple[Tensor, Tensor]:
    """``(low (M, K), width (M, K))`` the models' prior boxes, zero-padded."""
    width = max(len(m.param_names) for m in models)
    low = torch.zeros((len(models), width), dtype=torch.float64)
    span = torch.zeros_like(low)
    for i, model in enumerate(models):
        box = run.priors[model.name]
        low[i, : len(box)] = box[:, 0]
        span[i, : len(box)] = box[:, 1] - box[:, 0]
    return low, span


__all__ = [
    "MIN_REST",
    "DriverPosterior",
    "driver_posterior",
    "history_steps",
    "predict_rest",
    "predictable",
    "shrunk_fit",
]
