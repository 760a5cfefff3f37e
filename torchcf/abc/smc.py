"""Sequential refinement: ABC population Monte Carlo per pair (``abc.method = "smc"``).

Rejection (:mod:`torchcf.abc.rejection`) draws every particle from the prior. SMC
spends the same budget in rounds and concentrates the later ones where the score
is low, per training pair and per model (Beaumont, Cornuet, Marin & Robert 2009,
"Adaptive approximate Bayesian computation", Biometrika 96; the threshold schedule
of Del Moral, Doucet & Jasra 2012):

- **round 0** (``prior_fraction`` of the budget): prior draws of the model's
  stream, exactly the rejection engine's particles ``0 .. n_0 - 1`` (each on its
  stream-drawn pair); per pair the ``population`` best form the first population,
  equally weighted;
- **round t = 1 .. R**: per pair ``q`` proposals (``q`` = the rest of the budget
  split evenly over rounds and pairs). Proposal ``j`` of pair ``p`` picks a parent
  ``theta_i`` of the pair's population with probability ``w_i`` and moves it by a
  Gaussian step **in the logit of the prior box**, ``z = logit((theta - low) /
  width)`` per parameter: ``z' = z_i + N(0, Sigma_p)``, ``Sigma_p = 2 Cov_w(z of
  population_p) + (4e-3)^2 I`` (twice the weighted covariance, Beaumont et al.'s
  scale for a Gaussian random walk; the small diagonal, 1e-3 of the box's width
  at its centre, keeps a collapsed population proposing). Every proposal lies in
  the box, and near a bound the steps shrink with the room left, so a parameter
  whose fit lies at its bound is refined there instead of wasting proposals
  outside (why, measured: ``reports/smc/design.md``). The proposals of every
  pair are simulated on their pair in one batched rollout per chunk, whatever
  their pair.
- **threshold**: ``eps_t,p`` = the ``quantile`` of the previous population's
  scores. The round's accepted set starts with the previous population's members
  at or under ``eps_t,p`` (elitism), and the proposals with score ``<= eps_t,p``
  are offered to it; the ``population`` best (score, then particle index) form
  the next population. So the threshold never rises, and a population never
  falls below ``quantile`` of its size, however few proposals a round accepts
  (a population of a handful of particles says little about where the fit
  is: ``reports/smc/design.md``).
- **weights** (uniform prior ``pi`` on the box): a particle of round ``t``
  carries ``log r = log pi_z(z) - log q_t(z)``, ``q_t(z) = sum_i w_i N(z; z_i,
  Sigma_p)``, the density of the proposal it was drawn from and
  ``pi_z(z) = prod_k s(z_k) (1 - s(z_k))`` (``s`` the logistic function) the
  prior's, both in the logit space (prior draws: ``r = 1``); it keeps it in later
  rounds. A population's weights are ``w ~ r`` over its members, whatever round
  drew them: each is an importance sample of the prior from its own proposal.

Every simulated particle is also offered to the model's per-pair top-N buffer,
as in rejection: the hybrid, its shares and every report read those buffers. The
buffers carry ``log r`` as an extra last column (:func:`parameter_buffer` drops
it for the posterior).

**Reproducible**: proposal ``j`` of round ``t`` is a pure function of ``(seed,
model, t, j)`` (counter-based uniforms, :func:`torchcf.abc.streams.uniforms`) and
of the round's population, which is a function of the buffers of the round
before; buffers keep exactly the best by ``(score, particle index)``. So the result
does not depend on the chunk size or the number of processes, and a run resumed
from a checkpoint at any round boundary or chunk ends identical to an
uninterrupted one.

**Budget** (per model): ``n_particles`` proposals in all: ``n_0 = round(
prior_fraction n_particles)`` prior draws, then ``q = floor((n_particles - n_0) /
(rounds N))`` per pair and round; the rest (fewer than ``rounds N``) is not spent.
Every proposal is simulated (the kernel never leaves the box).

**Evidence**: for every buffer entry ``r`` is an importance weight of the prior
with respect to its proposal, so ``P_m,p(score <= tau) ~ (1 / M_m,p) sum r
1[score <= tau]`` over the model's proposals on pair ``p`` (``M_m,p`` of them)
estimates the prior mass of model ``m`` that fits pair ``p`` within ``tau``
(:func:`evidence_shares`): what rejection's shares measure, with the prior's Occam
factor.

**Structure**: the chunks of a round are the round loop's
(:mod:`torchcf.abc.rounds`, shared with rejection: shard, simulate, screen, push,
progress and checkpoints). SMC supplies per round its proposals (round 0 the
prior stream's, later rounds those of the kernel fitted to the population,
:class:`~torchcf.abc.kernel.SMCKernel`) and where they go (the model's buffer,
and the round's accepted set below the threshold); at a round's end it weighs the
round's particles and makes the next population.

Shapes: N pairs, K parameters, ``pop`` = ``population`` (:mod:`torchcf.typing`).

Design record (the designs tried and what chose these): ``reports/smc/design.md``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..models import CFModel
from ..sim.rollout import COMPILE_CHUNK_MULTIPLE
from .kernel import KERNEL_FLOOR, SMCKernel
from .rejection import Rollout
from .rounds import (
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
from .streams import ParticleStream, uniforms
from .topn import TopN

#: The kernel's space a checkpoint records (:class:`SMCState`): one written
#: before the refinement stepped in the logit of the box (no entry: the box
#: itself) does not continue.
KERNEL_SPACE = "logit"


@dataclass(frozen=True)
class SMCSettings:
    """The refinement's settings (config section ``abc.smc``).

    Attributes:
        population: particles per pair carried from round to round.
        rounds: refinement rounds after the prior round.
        prior_fraction: share of the budget drawn from the prior (round 0).
        quantile: the next threshold is this quantile of a population's scores.
        kernel_scale: the kernel's covariance over the population's (2; the
            engine's, not the config's).

    Examples:
        >>> SMCSettings(population=20, rounds=4)
        SMCSettings(population=20, rounds=4, prior_fraction=0.25, quantile=0.5,
                    kernel_scale=2.0)
        >>> smc_budget(100_000, n_pairs=10, settings=SMCSettings(rounds=5)).per_pair
        1500
    """

    population: int = 50
    rounds: int = 12
    prior_fraction: float = 0.25
    quantile: float = 0.5
    kernel_scale: float = 2.0


@dataclass(frozen=True)
class Budget:
    """How one model's ``n_particles`` are spent (module docstring).

    Attributes:
        prior: prior draws of round 0 (``n_0``).
        per_pair: proposals per pair in every later round (``q``).
        rounds: later rounds.
        n_pairs: pairs.
    """

    prior: int
    per_pair: int
    rounds: int
    n_pairs: int

    @property
    def per_round(self) -> int:
        """Proposals of one later round, all pairs."""
        return self.per_pair * self.n_pairs

    @property
    def total(self) -> int:
        """Proposals in all (at most ``n_particles``)."""
        return self.prior + self.rounds * self.per_round

    def round_size(self, t: int) -> int:
        """Proposals of round ``t``."""
        return self.prior if t == 0 else self.per_round

    def first_index(self, t: int) -> int:
        """Particle index of round ``t``'s first proposal (indices are unique per
        model: the buffers' tie rule)."""
        return 0 if t == 0 else self.prior + (t - 1) * self.per_round


def smc_budget(n_particles: int, n_pairs: int, settings: SMCSettings) -> Budget:
    """The budget split of module docstring."""
    prior = int(round(settings.prior_fraction * n_particles))
    per_pair = (n_particles - prior) // (settings.rounds * n_pairs)
    return Budget(prior, per_pair, settings.rounds, n_pairs)


@dataclass
class SMCState:
    """Where one model's refinement stands (a checkpoint holds it).

    Its size is that of two per-pair populations, whatever the rounds done, and
    nothing once the refinement is finished (a finished model's checkpoint entry
    is its round alone: over 10 000 pairs each population is 30 MB).

    Attributes:
        round: the round under way (``rounds + 1`` when done).
        next: proposals of this round already offered.
        shape: ``(N, pop, K + 1)`` of the accepted set, built when a round starts.
        accepted: this round's accepted proposals, per pair the ``population``
            best; ``theta`` (N, pop, K + 1), its last column ``log r``. None
            before the first round and once finished.
        population: the previous round's accepted particles (empty in round 0
            and once finished): ``theta`` (N, pop, K + 1), ``score`` (N, pop),
            ``+inf`` where a pair has fewer, and their particle ``index`` (N, pop).
    """

    round: int = 0
    next: int = 0
    shape: tuple[int, int, int] = (1, 1, 1)
    accepted: TopN | None = None
    population: dict[str, Tensor] = field(default_factory=dict)

    def state_dict(self) -> dict[str, Any]:
        return {
            "round": self.round,
            "next": self.next,
            "accepted": None if self.accepted is None else self.accepted.state_dict(),
            "population": dict(self.population),
            "space": KERNEL_SPACE,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a saved state into this one (ValueError if its shapes or its
        kernel are not this run's)."""
        # Checkpoints from before the logit kernel carry no space: the box's.
        saved = state.get("space", "box")
        if saved != KERNEL_SPACE:
            raise ValueError(
                f"its refinement steps in the {saved!r} space, this version's in "
                f"the {KERNEL_SPACE!r} space; start the run again"
            )
        self.round = int(state["round"])
        self.next = int(state["next"])
        self.accepted = None
        if state["accepted"] is not None:
            self.accepted = TopN(*self.shape)
            self.accepted.load_state_dict(state["accepted"])
        self.population = {
            k: v if k == "index" else v.to(torch.float64)
            for k, v in dict(state["population"]).items()
        }

    def finish(self) -> None:
        """Drop what only a round in progress needs."""
        self.next, self.accepted, self.population = 0, None, {}


def new_state(n_pairs: int, settings: SMCSettings, n_params: int) -> SMCState:
    """A refinement at its start (round 0); its buffers are built when it runs."""
    return SMCState(shape=(n_pairs, settings.population, n_params + 1))


def parameter_buffer(buffer: TopN) -> TopN:
    """The buffer with its ``log r`` column dropped: ``theta`` (N, capacity, K)."""
    plain = TopN(buffer.n_pairs, buffer.capacity, buffer.theta.shape[-1] - 1)
    plain.score, plain.index = buffer.score, buffer.index
    plain.theta = buffer.theta[..., :-1]
    return plain


# -------------------------------------------------------------- the rounds
def run_smc(
    stream: ParticleStream,
    buffer: TopN,
    rollout: Rollout,
    n_particles: int,
    settings: SMCSettings,
    progress: ModelProgress,
    state: SMCState,
    *,
    hooks: RoundHooks = NO_HOOKS,
) -> None:
    """Run one model's refinement to its end (module docstring).

    Args:
        stream: the model's prior stream on the rollout's pairs
            (:func:`~torchcf.abc.rejection.prior_stream`): the simulated
            model (its name keys the refinement's streams too), the seed, the
            (K_drawn, 2) float64 prior box of the searched parameters and, for
            a variant searched in its first parameters only, the ``(K -
            K_drawn,)`` values of the others, appended to every particle
            before it is simulated (a shared effect's one value for all pairs;
            the buffers hold the searched parameters only).
        buffer: the model's per-pair top-N buffer, ``theta`` (N, capacity,
            K_drawn + 1).
        rollout: how particles are simulated (paired layout).
        n_particles: the model's budget.
        settings: the refinement's settings.
        progress: proposals offered so far (updated after every chunk round).
        state: where the refinement stands (updated; a checkpoint saves it).
        hooks: the processes sharing the work, the plausibility filter and
            what runs between rounds (:class:`~torchcf.abc.rounds.RoundHooks`),
            as in :func:`~torchcf.abc.run_rejection`.
    """
    if not rollout.paired:
        raise ValueError("SMC refines per pair: it needs the paired layout")
    if stream.n_pairs != rollout.pairs.n_pairs:
        raise ValueError(
            f"the stream's particles go to {stream.n_pairs} pairs, the rollout "
            f"has {rollout.pairs.n_pairs}: make it with prior_stream(..., rollout)"
        )
    budget = smc_budget(n_particles, rollout.pairs.n_pairs, settings)
    if budget.per_pair < 1:
        raise ValueError(
            f"{n_particles} particles leave no proposal per pair and round "
            f"({rollout.pairs.n_pairs} pairs, {settings.rounds} rounds)"
        )
    schedule = (budget, settings, n_particles)
    _run_from(stream, buffer, rollout, schedule, progress, state, hooks)


def refine_population(
    stream: ParticleStream,
    buffer: TopN,
    rollout: Rollout,
    budget: Budget,
    settings: SMCSettings,
    progress: ModelProgress,
    state: SMCState,
    *,
    hooks: RoundHooks = NO_HOOKS,
) -> None:
    """Refine, per pair, particles a buffer already holds: SMC's rounds ``1 ..
    budget.rounds`` after a round 0 made elsewhere (an amortised estimator's
    samples, :mod:`torchcf.calibration.refinement`).

    Round 0 is the buffer's content: per pair its ``population`` best entries
    form the first population (:func:`seed_population`), with the ``log r`` its
    rows carry (0: equally weighted); the later rounds are :func:`run_smc`'s.

    Args:
        stream: the model's prior stream (its model, seed, box and fixed
            values; no particle is drawn from it).
        buffer: the model's per-pair buffer, ``theta`` (N, capacity, K + 1),
            holding round 0's particles, indices ``0 .. budget.prior - 1``.
        rollout: how particles are simulated (paired layout).
        budget: ``prior`` the particles of round 0 (the later rounds' indices
            follow them), ``per_pair`` and ``rounds`` the refinement's.
        settings: the kernel's settings (``rounds`` and ``prior_fraction`` are
            the budget's, not read).
        progress: proposals offered so far (``budget.prior`` after round 0).
        state: where the refinement stands (round 0: not started).
        hooks: as in :func:`run_smc`.
    """
    if not rollout.paired:
        raise ValueError("SMC refines per pair: it needs the paired layout")
    if state.round == 0:
        seed_population(state, buffer, settings)
    schedule = (budget, settings, budget.total - budget.prior)
    _run_from(stream, buffer, rollout, schedule, progress, state, hooks)


def seed_population(state: SMCState, buffer: TopN, settings: SMCSettings) -> None:
    """Round 0 from a buffer: per pair its ``population`` best entries become
    the population (the ``log r`` of their last column kept), and round 1 starts
    with its elite accepted, as after a prior round (:func:`_next_population`)."""
    seed = TopN(buffer.n_pairs, settings.population, buffer.theta.shape[-1])
    rows, slots = torch.isfinite(buffer.score).nonzero(as_tuple=True)
    seed.push(
        rows, buffer.score[rows, slots], buffer.index[rows, slots],
        buffer.theta[rows, slots],
    )  # fmt: skip
    state.accepted = seed
    _next_population(state, settings, buffer.n_pairs, buffer)


def _run_from(
    stream: ParticleStream,
    buffer: TopN,
    rollout: Rollout,
    schedule: tuple[Budget, SMCSettings, int],
    progress: ModelProgress,
    state: SMCState,
    hooks: RoundHooks,
) -> None:
    """The rounds ``state.round .. budget.rounds`` of one model's refinement;
    ``schedule``: its budget, its settings and the particles whose count
    decides whether the rollout runs compiled."""
    budget, settings, planned = schedule
    model = stream.model
    compiled = rollout.compiled(model, planned)
    chunk = _round_chunk(rollout, model, budget.per_round, compiled)
    plan = Plan(rollout, model, chunk, compiled, stream.fixed)
    bounds = stream.bounds
    if state.accepted is None and state.round <= budget.rounds:
        state.accepted = TopN(*state.shape)

    def reached(done: int) -> None:  # a checkpoint saves the state
        state.next = done

    while state.round <= budget.rounds:
        kernel = (
            SMCKernel.fit(state.population, bounds, settings.kernel_scale)
            if state.round
            else None
        )
        run_rounds(
            _round_proposals(kernel, stream, state.round, budget),
            _round_sinks(buffer, state, settings),
            plan,
            progress,
            Stretch(
                state.next,
                budget.round_size(state.round),
                budget.first_index(state.round),
            ),
            reached=reached,
            hooks=hooks,
        )
        began = time.perf_counter()
        if kernel is not None:
            _weigh_round(kernel, buffer, state, budget)
        _next_population(state, settings, rollout.pairs.n_pairs, buffer)
        progress.seconds += time.perf_counter() - began
    state.finish()
    progress.next = budget.total  # proposals made (the rest is not spent)


def _round_chunk(
    rollout: Rollout, model: CFModel, per_round: int, compiled: bool
) -> int:
    """Particles per simulate call: a refinement round in equal chunks of at most
    the rollout's chunk. A round is one batched rollout (or a few), never a chunk
    padded far past what it proposes: where whole chunks are simulated (compiled
    blocks, the MPC), a round of 1.2 chunks would otherwise simulate 2. Set by the
    plan alone, so results stay independent of timing."""
    most = rollout.chunk(model, max(per_round, 1), compiled)
    pieces = -(-per_round // most)
    chunk = -(-per_round // max(pieces, 1))
    if compiled:
        chunk = -(-chunk // COMPILE_CHUNK_MULTIPLE) * COMPILE_CHUNK_MULTIPLE
    return max(chunk, 1)


def _round_proposals(
    kernel: SMCKernel | None, stream: ParticleStream, t: int, budget: Budget
) -> Propose:
    """Round ``t``'s proposals for the round loop (:data:`~torchcf.abc.rounds.
    Propose`): round 0 the prior stream's particles (their pairs drawn by the
    stream, ``r = 1``), later rounds the kernel's (:func:`_proposals`). A batch
    is padded with copies of the first. The buffers hold the searched parameters
    and a ``log r`` column, filled in at the end of the round
    (:func:`_weigh_round`)."""
    first_index = budget.first_index(t)

    def propose(start: int, stop: int, batch: int | None) -> Chunk:
        if kernel is None:
            theta, pair = stream.draw(start, stop)
        else:
            key = f"{stream.model.name}/smc{t}"
            theta, pair = _proposals(
                kernel, stream.seed, key, start, stop, budget.per_pair
            )
        index = first_index + start + torch.arange(theta.shape[0])
        real = theta.shape[0]
        if not real:
            return Chunk(theta, pair, index)
        pad = batch - real if batch is not None else 0
        zero = torch.zeros(real, 1, dtype=theta.dtype)
        return Chunk(
            torch.cat((theta, theta[:1].expand(pad, -1))),
            torch.cat((pair, pair[:1].expand(pad))),
            index,
            rows=torch.cat((theta, zero), 1),
        )

    return propose


def _proposals(
    kernel: SMCKernel,
    seed: int,
    stream_key: str,
    start: int,
    stop: int,
    per_pair: int,
) -> tuple[Tensor, Tensor]:
    """A refinement round's proposals ``start .. stop - 1``, pair-major (``per_pair``
    per pair), from the round's own counter-based uniforms (``stream_key`` =
    ``"<model>/smc<t>"``).

    Returns:
        ``theta`` (Q, K), ``pair`` (Q,).
    """
    k = kernel.bounds.shape[0]
    u = uniforms(seed, stream_key, start, stop, 1 + k)  # (Q, 1 + K)
    pair = torch.arange(start, stop) // per_pair
    return kernel.propose(u, pair), pair


def _round_sinks(buffer: TopN, state: SMCState, settings: SMCSettings) -> list[Sink]:
    """Where a round's proposals go: every one to the model's buffer, those at or
    under the round's threshold to its accepted set (none in round 0)."""
    if state.round:
        epsilon = thresholds(state.population["score"], settings.quantile)
    else:
        epsilon = torch.full((buffer.n_pairs,), math.inf, dtype=torch.float64)
    return [Sink(buffer), Sink(state.accepted, ceiling=epsilon)]


def _weigh_round(
    kernel: SMCKernel, buffer: TopN, state: SMCState, budget: Budget
) -> None:
    """End of round ``t``: ``log r`` of the round's particles still held in the
    buffer and the accepted set, computed once, in the buffers' order, so that
    it does not depend on how the round was chunked or sharded."""
    first = budget.first_index(state.round)
    stop = first + budget.round_size(state.round)
    for held in (buffer, state.accepted):
        mine = (held.index >= first) & (held.index < stop)  # (N, capacity)
        if bool(mine.any()):
            log_r = kernel.grid_log_prior_ratio(held.theta[..., :-1])
            held.theta[..., -1] = torch.where(mine, log_r, held.theta[..., -1])


def thresholds(score: Tensor, quantile: float) -> Tensor:
    """(N,) the ``quantile`` of each pair's finite population scores (``+inf``
    for a pair without a population): the lower of the two central order
    statistics, so that it is a score the population holds."""
    ordered = torch.sort(score, dim=1).values  # (N, pop), +inf last
    count = torch.isfinite(ordered).sum(1)  # (N,)
    rank = torch.floor(quantile * (count - 1).clamp(min=0)).long()
    value = ordered.gather(1, rank[:, None])[:, 0]
    return torch.where(count > 0, value, math.inf)


def _next_population(
    state: SMCState, settings: SMCSettings, n_pairs: int, buffer: TopN
) -> None:
    """End of a round: its accepted set becomes the population, and the next
    round starts with the population's members at or under its threshold
    already accepted (module docstring, 'elitism')."""
    done = state.accepted
    state.population = {
        "theta": done.theta.clone(),
        "score": done.score.clone(),
        "index": done.index.clone(),
    }
    state.round += 1
    state.next = 0
    state.accepted = TopN(n_pairs, settings.population, buffer.theta.shape[-1])
    score = state.population["score"]  # (N, pop)
    epsilon = thresholds(score, settings.quantile)  # (N,)
    elite = torch.isfinite(score) & (score <= epsilon[:, None])
    rows, slots = elite.nonzero(as_tuple=True)
    state.accepted.push(
        rows,
        score[rows, slots],
        state.population["index"][rows, slots],
        state.population["theta"][rows, slots],
    )


# ------------------------------------------------------------- the evidence
def proposals_per_pair(
    model: CFModel, bounds: Tensor, seed: int, budget: Budget
) -> Tensor:
    """(N,) int64: how many of the model's proposals went to each pair (the prior
    round's stream-drawn pairs, then ``q`` per pair and round)."""
    stream = ParticleStream(model, bounds, seed, budget.n_pairs)
    counts = torch.zeros(budget.n_pairs, dtype=torch.int64)
    step = 1 << 20
    for start in range(0, budget.prior, step):
        _, pair = stream.draw(start, min(start + step, budget.prior))
        counts += torch.bincount(pair, minlength=budget.n_pairs)
    return counts + budget.rounds * budget.per_pair


def prior_mass(buffer: TopN, proposals: Tensor, tau: Tensor) -> Tensor:
    """(N,) the model's prior mass within ``tau`` (N,) per pair: ``(1 / M_p) sum
    r 1[score <= tau_p]`` over the buffer's entries (module docstring)."""
    inside = buffer.score <= tau[:, None]  # (N, capacity)
    r = torch.exp(buffer.theta[..., -1])
    return torch.where(inside, r, 0.0).sum(1) / proposals.clamp(min=1)


def evidence_shares(names: Sequence[str], masses: Sequence[Tensor]) -> dict[str, float]:
    """Per model, its share of the prior mass that fits, per pair normalised over
    the models and averaged over the pairs where any model fits."""
    mass = torch.stack(list(masses))  # (M, N)
    total = mass.sum(0)  # (N,)
    fits = total > 0
    share = (mass[:, fits] / total[fits]).mean(1) if fits.any() else mass[:, 0] * 0
    return {name: float(s) for name, s in zip(names, share, strict=True)}


__all__ = [
    "KERNEL_FLOOR",
    "Budget",
    "SMCKernel",
    "SMCSettings",
    "SMCState",
    "evidence_shares",
    "new_state",
    "parameter_buffer",
    "prior_mass",
    "proposals_per_pair",
    "refine_population",
    "run_smc",
    "seed_population",
    "smc_budget",
    "thresholds",
]
