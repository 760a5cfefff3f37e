"""Residual series of a calibrated run and their structure tests (loop step 1).

Every training pair is driven by its best hybrid particle (:func:`best_particles`);
the residuals ``observed - simulated`` (spacing [m], speed [m/s], acceleration
[m/s^2]) and the covariates the effects act on (:func:`residual_series`) are
tested for structure by :mod:`torchcf.diagnose.signatures.residuals`
(:func:`residual_tests`): autocorrelation (Ljung-Box), lagged cross-correlation
with the leader's acceleration and the speed difference (0-3 s), dependence on own
speed and speed squared, on the sign of the speed difference, on the spacing
level, on the road position and on time.

Shapes: T steps, N pairs, K parameters (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ...abc.particles import Particles, best_per_pair
from ...data import PairSet
from ...models import CFModel, get_model
from ...posterior import Posterior
from ...sim.rollout import simulate
from ...system.errors import TorchcfError
from ...system.records import Record
from . import residuals as rt

#: A pair's best particle per model: ``{model: (theta (k, K) float64, pair position
#: (k,) int64)}``.
BestParticles = dict[CFModel, tuple[Tensor, Tensor]]

#: The channels tested, residuals ``observed - simulated``.
CHANNELS = ("spacing", "speed", "acceleration")


class DiagnoseError(TorchcfError, RuntimeError):
    """A run that cannot be diagnosed (one-line message)."""


@dataclass(frozen=True)
class ResidualRow(Record):
    """One structure test of one residual channel, pooled over pairs (a row of
    ``loop.json``'s ``residuals_before`` and ``residuals_after``).

    Attributes:
        channel: the residual (:data:`CHANNELS`).
        test: the test (``"autocorrelation"``, ``"own speed"``, ...:
            :func:`residual_tests`).
        statistic, p_value: the test's (None: it could not run).
        effect: its effect size, a float or per regressor (:mod:`torchcf.
            diagnose.residuals`; None: not finite).
        n: samples used, summed over pairs; n_pairs: pairs tested (None: none).
    """

    channel: str
    test: str
    statistic: float | None
    p_value: float | None
    effect: float | dict[str, float | None] | None
    n: int
    n_pairs: int | None


def best_particles(posterior: Posterior, pairs: PairSet) -> BestParticles:
    """The hybrid's best particle on every training pair, grouped by model.

    Ties go to the model listed first in the run, then to the earlier particle of
    the model's hybrid set.

    Returns:
        ``{model: (theta (k, K) float64, pair position (k,) int64)}``, positions
        ascending, models in the order of their first pair; every pair with a
        hybrid particle appears under exactly one model.
    """
    position_of = {int(pid): i for i, pid in enumerate(pairs.pair_ids)}
    sets = []
    for name in posterior.models:  # run order: the set's position breaks ties
        particles = posterior.hybrid[name]
        position = torch.tensor(
            [position_of.get(int(pid), -1) for pid in particles.pair_ids.tolist()],
            dtype=torch.int64,
        )
        known = position >= 0  # (h,) kept for a pair of ``pairs``
        sets.append(
            Particles(
                get_model(name),  # the posterior's names enter here
                particles.theta[known].double(),
                position[known],
                particles.score[known].double(),
                torch.zeros(int(known.sum()), dtype=torch.int64),  # row order decides
            )
        )
    return {s.model: (s.theta, s.pair) for s in best_per_pair(sets, 1) if len(s)}


def residual_series(
    best: BestParticles, pairs: PairSet, dtype: torch.dtype = torch.float64
) -> dict[str, list[np.ndarray]]:
    """Residuals and covariates of every pair driven by its particle, valid steps only.

    Returns:
        lists (one float64 array per pair, pairs in position order) under
        ``spacing, speed, acceleration`` (observed - simulated, [m], [m/s],
        [m/s^2]) and the covariates ``v`` (observed own speed), ``dv`` (leader -
        follower speed), ``s`` (observed spacing), ``x`` (road position),
        ``a`` (observed own acceleration), ``a_lead`` (leader acceleration).
    """
    sim_x = torch.full((pairs.n_steps, pairs.n_pairs), math.nan, dtype=torch.float64)
    sim_v, sim_a = sim_x.clone(), sim_x.clone()
    for model, (theta, position) in best.items():
        out = simulate(
            model, theta.to(dtype), pairs, position, dtype=dtype, return_traj=True
        )
        sim_x[:, position] = out.x.double().cpu()
        sim_v[:, position] = out.v.double().cpu()
        sim_a[:, position] = out.a.double().cpu()
    obs = {k: t.double().cpu() for k, t in pairs.series().items()}
    columns = {
        # s_obs - s_sim = (x_lead - x_obs) - (x_lead - x_sim) = x_sim - x_obs
        "spacing": sim_x - obs["x_follow"],
        "speed": obs["v_follow"] - sim_v,
        "acceleration": obs["a_follow"] - sim_a,
        "v": obs["v_follow"],
        "dv": obs["v_lead"] - obs["v_follow"],
        "s": obs["x_lead"] - obs["x_follow"],
        "x": obs["x_follow"],
        "a": obs["a_follow"],
        "a_lead": obs["a_lead"],
    }
    mask = pairs.mask.cpu()
    covered = torch.isfinite(sim_x).all(0)  # (N,) pairs with a particle
    out: dict[str, list[np.ndarray]] = {key: [] for key in columns}
    for j in torch.nonzero(covered).squeeze(1).tolist():
        valid = mask[:, j]
        for key, table in columns.items():
            out[key].append(table[valid, j].numpy())
    return out


def residual_tests(
    series: dict[str, list[np.ndarray]], dt: float, period: float | None = None
) -> list[ResidualRow]:
    """The structure tests of every residual channel, one row each.

    ``road position`` is a linear trend in ``x`` on an open road, and the lap's
    first harmonic on a closed track of lap length ``period`` [m]
    (:func:`~torchcf.diagnose.signatures.residuals.lap_dependence`).

    Returns:
        one row per (channel, test), pooled over pairs.
    """
    rows = []
    for channel in CHANNELS:
        e = series[channel]
        tests = {
            "autocorrelation": lambda e=e: rt.ljung_box(e, lags=10),
            "xcorr leader acceleration": lambda e=e: rt.cross_correlation(
                e, series["a_lead"], dt
            ),
            "xcorr speed difference": lambda e=e: rt.cross_correlation(
                e, series["dv"], dt
            ),
            "own speed": lambda e=e: rt.speed_dependence(e, series["v"]),
            "asymmetry": lambda e=e: rt.asymmetry(e, series["dv"]),
            "spacing level": lambda e=e: rt.spacing_dependence(e, series["s"]),
            "road position": lambda e=e: (
                rt.lap_dependence(e, series["x"], period)
                if period
                else rt.position_dependence(e, series["x"])
            ),
            "drift": lambda e=e: rt.drift(e, dt),
        }
        for test, run in tests.items():
            (row,) = rt.summarize([run()])
            rows.append(
                ResidualRow(
                    channel=channel,
                    test=test,
                    statistic=row["statistic"],
                    p_value=row["p_value"],
                    effect=row["effect"],
                    n=row["n"],
                    n_pairs=row["n_pairs"],
                )
            )
    return rows


def diagnose_residuals(
    posterior: Posterior, pairs: PairSet, dtype: torch.dtype = torch.float64
) -> tuple[list[ResidualRow], dict[str, list[np.ndarray]]]:
    """Residual series of the hybrid's best particle per pair and their tests.

    Raises:
        DiagnoseError: no pair has a hybrid particle.
    """
    series = residual_series(best_particles(posterior, pairs), pairs, dtype)
    if not series["spacing"]:
        raise DiagnoseError("no training pair has a hybrid particle to diagnose")
    return residual_tests(series, pairs.dt, pairs.road_period), series


__all__ = [
    "CHANNELS",
    "BestParticles",
    "DiagnoseError",
    "ResidualRow",
    "best_particles",
    "diagnose_residuals",
    "residual_series",
    "residual_tests",
]
