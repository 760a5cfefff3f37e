"""Whether a sampler's budget can fill every training pair's buffer.

A calibration keeps per training pair and model its ``SelectionRule.buffer_size``
best particles; the check refuses, before anything is simulated, a budget that
can only leave buffers short:

- rejection, paired layout: a pair receives ``n_particles / N`` particles on
  average; full layout: every particle;
- SMC: its prior round must give every pair ``population`` particles on
  average and every later round a proposal per pair;
- amortised: a pair receives ``samples_per_pair`` samples, and at least one
  training pair must be as long as a training window.

The messages name the settings as ``prefix + name`` (``prefix = "abc."`` where
they come from a run config, :mod:`torchcf.train.settings`).
"""

from __future__ import annotations

import math

from ..abc.smc import SMCSettings, smc_budget
from ..data import PairSet
from ..system.errors import TorchcfError
from .methods import SMC, Amortised, Method, SelectionRule


class CalibrationError(TorchcfError, ValueError):
    """A calibration that cannot be run as asked (one-line message)."""


def check_budget(
    method: Method,
    selection: SelectionRule,
    pairs: PairSet,
    paired: bool = True,
    prefix: str = "",
) -> None:
    """Every training pair must be able to fill its buffer: CalibrationError if
    not (module docstring).

    Args:
        method: the sampler and its budget.
        selection: the N asked for (``top_n``, ``sensitivity_n``).
        pairs: the training pairs.
        paired: the paired layout (a particle per pair) or the full one.
        prefix: prepended to the settings' names in the message.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet, get_model
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 40.0 + 15.0 * t, torch.full_like(t, 15.0)  # [m], [m/s]
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 30.0, v, a], dt=0.1)
        >>> from torchcf.calibration import Rejection, SelectionRule
        >>> check_budget(Rejection(100), SelectionRule(top_n=5), pairs)  # fills it
        >>> check_budget(Rejection(100), SelectionRule(top_n=500), pairs)
        Traceback (most recent call last):
        ...
        torchcf.calibration.budget.CalibrationError: top_n: 500 ...
    """
    if isinstance(method, Amortised):
        _check_amortised(method, selection, pairs, prefix)
        return
    if isinstance(method, SMC):
        check_smc_budget(method.n_particles, pairs.n_pairs, method.settings, prefix)
    n_particles = method.n_particles
    per_pair = n_particles / pairs.n_pairs if paired else n_particles
    for key, n in (
        ("top_n", selection.top_n),
        ("sensitivity_n", max(selection.sensitivity_n)),
    ):
        if n <= per_pair:
            continue
        received = (
            f"{prefix}n_particles = {n_particles} over {pairs.n_pairs} training "
            f"pairs, {per_pair:.3g} per pair on average in the paired layout"
            if paired
            else f"{prefix}n_particles = {n_particles} in the full layout"
        )
        need = n * pairs.n_pairs if paired else n
        raise CalibrationError(
            f"{prefix}{key}: {n} particles per pair asked for, more than a training "
            f"pair receives ({received}); set {prefix}n_particles >= {need} or lower "
            f"{prefix}{key}"
        )


def _check_amortised(
    method: Amortised, selection: SelectionRule, pairs: PairSet, prefix: str
) -> None:
    """A pair's samples must fill the hybrid's top-N, and a training pair must
    be as long as a training window."""
    own = f"{prefix}amortised."
    for key, n in (
        ("top_n", selection.top_n),
        ("sensitivity_n", max(selection.sensitivity_n)),
    ):
        if n > method.samples_per_pair:
            raise CalibrationError(
                f"{prefix}{key}: {n} particles per pair asked for, more than the "
                f"{own}samples_per_pair = {method.samples_per_pair} "
                f"drawn per training pair; set {own}samples_per_pair >= "
                f"{n} or lower {prefix}{key}"
            )
    longest = int(pairs.lengths.max())
    if longest < method.window_steps:
        raise CalibrationError(
            f"{own}window_steps: {method.window_steps} steps, longer "
            f"than every training pair (the longest has {longest}); set it to "
            f"{longest} or less"
        )


def check_smc_budget(
    n_particles: int, n_pairs: int, settings: SMCSettings, prefix: str = ""
) -> None:
    """The refinement needs a population per pair from its prior round and at
    least one proposal per pair and round: CalibrationError if ``n_particles``
    (per model) is short for ``n_pairs`` training pairs."""
    budget = smc_budget(n_particles, n_pairs, settings)
    need = max(
        settings.population * n_pairs / settings.prior_fraction,
        settings.rounds * n_pairs / (1 - settings.prior_fraction),
    )
    if budget.prior < settings.population * n_pairs or budget.per_pair < 1:
        own = f"{prefix}smc."
        raise CalibrationError(
            f"{prefix}n_particles = {n_particles} is too few for method 'smc' "
            f"on {n_pairs} training pairs: its prior round must give every "
            f"pair {own}population = {settings.population} particles on "
            f"average and every later round a proposal per pair; set "
            f"{prefix}n_particles >= {math.ceil(need)} or lower {own}population "
            f"or {own}rounds"
        )


__all__ = ["CalibrationError", "check_budget", "check_smc_budget"]
