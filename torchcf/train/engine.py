"""From a config to the ABC engine (:mod:`torchcf.abc`): what a run hands it.

- the device a process simulates on (:func:`run_device`);
- the particle budget checked against the training pairs (:func:`check_budget`,
  and for ``abc.method = "smc"`` the refinement's budget, for ``"amortised"``
  its samples and windows);
- the refinement's settings for an amortised run (:func:`refine_settings`;
  SMC's, :func:`~torchcf.abc.configured.smc_settings`, and how the particles
  are simulated, :func:`~torchcf.abc.configured.rollout_of`, are
  :mod:`torchcf.abc.configured`'s: the loop's re-calibration uses them too);
- every model's per-pair top-N buffer, progress and refinement state, fresh or
  from the checkpoint (:func:`build_buffers`);

Units: SI throughout (m, s, m/s); ``abc.n_particles`` counts particles per
model; a buffer is ``(N, B)`` scores for ``N`` training pairs and ``B =
abc.buffer_size`` slots, with ``K`` parameter columns (``K + 1`` under SMC: the
log of the importance weight's ratio, ``log r``; and under an amortised run's
refinement).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch

from ..abc.configured import smc_settings
from ..abc.distributed import Group
from ..abc.rejection import ModelProgress
from ..abc.smc import SMCSettings, new_state, smc_budget
from ..abc.topn import TopN
from ..config import ConfigError, TrainConfig
from ..data import PairSet
from ..models import CFModel, require_model
from .checkpoint import RunError, RunState

# --------------------------------------------------------------------------------------
# Device and budget


def run_device(cfg: TrainConfig, group: Group) -> torch.device:
    """The device this process simulates on; ConfigError if it is not there."""
    device = group.run_device(cfg.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(
                f"device: {cfg.device!r} asked for but CUDA is not available"
            )
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ConfigError(
                f"device: {str(device)!r} asked for but only "
                f"{torch.cuda.device_count()} CUDA device(s) are visible"
            )
    return device


def check_budget(cfg: TrainConfig, pairs: PairSet) -> None:
    """Every training pair must be able to fill its buffer: ConfigError if not.

    In the paired layout a pair receives ``n_particles / n_pairs`` particles on
    average, in the full layout every particle; asking for more than that per pair
    (``top_n`` or an N of ``sensitivity_n``) can only leave buffers short.
    """
    abc = cfg.abc
    if abc.method == "smc":
        check_smc_budget(abc.n_particles, pairs.n_pairs, smc_settings(cfg))
    if abc.method == "amortised":
        check_amortised_budget(cfg, pairs)
        return
    paired = abc.layout == "paired"
    per_pair = abc.n_particles / pairs.n_pairs if paired else abc.n_particles
    for key, n in (("top_n", abc.top_n), ("sensitivity_n", max(abc.sensitivity_n))):
        if n <= per_pair:
            continue
        received = (
            f"abc.n_particles = {abc.n_particles} over {pairs.n_pairs} training "
            f"pairs, {per_pair:.3g} per pair on average in the paired layout"
            if paired
            else f"abc.n_particles = {abc.n_particles} in the full layout"
        )
        need = n * pairs.n_pairs if paired else n
        raise ConfigError(
            f"abc.{key}: {n} particles per pair asked for, more than a training "
            f"pair receives ({received}); set abc.n_particles >= {need} or lower "
            f"abc.{key}"
        )


def check_amortised_budget(cfg: TrainConfig, pairs: PairSet) -> None:
    """The amortised method draws ``abc.amortised.samples_per_pair`` samples
    per training pair (over all models) and trains on leader windows of
    ``abc.amortised.window_steps``: ConfigError if a pair's samples cannot
    fill the hybrid's top-N, or no training pair is as long as a window."""
    settings = cfg.abc.amortised
    for key, n in (
        ("top_n", cfg.abc.top_n),
        ("sensitivity_n", max(cfg.abc.sensitivity_n)),
    ):
        if n > settings.samples_per_pair:
            raise ConfigError(
                f"abc.{key}: {n} particles per pair asked for, more than the "
                f"abc.amortised.samples_per_pair = {settings.samples_per_pair} "
                f"drawn per training pair; set abc.amortised.samples_per_pair >= "
                f"{n} or lower abc.{key}"
            )
    longest = int(pairs.lengths.max())
    if longest < settings.window_steps:
        raise ConfigError(
            f"abc.amortised.window_steps: {settings.window_steps} steps, longer "
            f"than every training pair (the longest has {longest}); set it to "
            f"{longest} or less"
        )


def check_smc_budget(n_particles: int, n_pairs: int, settings: SMCSettings) -> None:
    """The refinement needs a population per pair from its prior round and at
    least one proposal per pair and round: ConfigError if ``n_particles`` (per
    model) is short for ``n_pairs`` training pairs."""
    budget = smc_budget(n_particles, n_pairs, settings)
    need = max(
        settings.population * n_pairs / settings.prior_fraction,
        settings.rounds * n_pairs / (1 - settings.prior_fraction),
    )
    if budget.prior < settings.population * n_pairs or budget.per_pair < 1:
        raise ConfigError(
            f"abc.n_particles = {n_particles} is too few for method 'smc' "
            f"on {n_pairs} training pairs: its prior round must give every "
            f"pair abc.smc.population = {settings.population} particles on "
            f"average and every later round a proposal per pair; set "
            f"abc.n_particles >= {math.ceil(need)} or lower abc.smc.population "
            "or abc.smc.rounds"
        )


def refine_settings(cfg: TrainConfig) -> SMCSettings | None:
    """The refinement's settings of an amortised run (``abc.amortised.refine``,
    :mod:`torchcf.train.refinement`) as the SMC engine's; None without one."""
    refine = cfg.abc.amortised.refine
    if cfg.abc.method != "amortised" or refine.rounds == 0:
        return None
    return SMCSettings(
        population=refine.population, rounds=refine.rounds, quantile=refine.quantile
    )


def weighted_buffers(cfg: TrainConfig) -> SMCSettings | None:
    """The SMC settings whose buffers carry the ``log r`` column: SMC's, or an
    amortised run's refinement; None: the buffers hold the parameters alone."""
    if cfg.abc.method == "smc":
        return smc_settings(cfg)
    return refine_settings(cfg)


# --------------------------------------------------------------------------------------
# Buffers


def build_buffers(
    models: Sequence[CFModel],
    n_pairs: int,
    buffer_size: int,
    smc: SMCSettings | None,
    state: RunState,
    checkpoint: Path,
) -> None:
    """Every model's buffer into ``state`` (from the checkpoint where it has
    one), its progress and, for SMC (``smc`` given), its refinement state, whose
    buffer carries one more column, ``log r``.

    Args:
        models: the run's model objects (``spec.model`` of each config entry),
            in the config's order; each buffer is keyed by the model's name.
        n_pairs: training pairs ``N``.
        buffer_size: slots per pair ``B`` (``abc.buffer_size``).
        smc: the refinement's settings; None for rejection.
        state: the run state; its saved buffers (a resumed run) are loaded.
        checkpoint: the checkpoint's path, for the error message.

    Raises:
        RunError: a saved buffer or refinement state does not fit this run.
    """
    for model in models:
        name = require_model(model, "build_buffers").name
        n_params = len(model.param_names)
        buffer = TopN(n_pairs, buffer_size, n_params + (smc is not None))
        refinement = None if smc is None else new_state(n_pairs, smc, n_params)
        try:
            if name in state.saved_buffers:
                buffer.load_state_dict(state.saved_buffers[name])
            if refinement is not None and name in state.saved_smc:
                refinement.load_state_dict(state.saved_smc[name])
        except (KeyError, ValueError, TypeError) as error:
            raise RunError(
                f"--resume: {checkpoint} does not match this run ({error})"
            ) from None
        state.buffers[name] = buffer
        if refinement is not None:
            state.smc[name] = refinement
        state.progress.setdefault(name, ModelProgress())


__all__ = [
    "build_buffers",
    "check_amortised_budget",
    "check_budget",
    "check_smc_budget",
    "refine_settings",
    "run_device",
    "weighted_buffers",
]
