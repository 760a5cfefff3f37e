"""Scores of a prediction, as calibration studies report them.

Every score is of the follower's position on the pair's recorded steps; since
the simulated and the recorded follower share the recorded leader, the error of
position is the error of spacing (``s_sim - s_obs = x_obs - x_sim``).

- **Spacing RMSE** of one prediction per pair, ``sqrt(mean_t (s_pred(t) -
  s_obs(t))^2)`` [m]; over pairs its mean, median and the pooled RMSE
  ``sqrt(sum_j sum_t e^2 / sum_j T_j)`` (long pairs weigh more).
- **ADE / FDE** of a draw: the mean and the final absolute displacement [m] of
  the follower; ``minADE`` and ``minFDE`` their least over a pair's draws (the
  trajectory-prediction literature's scores of a set of draws).
- **Coverage** of a band: the share of a pair's recorded steps (its first, the
  shared start, left out) whose recorded spacing lies within the band, pooled
  over the pairs' steps.
- **Collisions**: the share of rollouts that collided (or blew up).

Shapes: T steps, N pairs, D draws per pair (:mod:`torchcf.typing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from ..system.records import Record


@dataclass(frozen=True)
class SpacingRMSE(Record):
    """Per-pair spacing RMSE over pairs [m] (module docstring).

    Attributes:
        mean, median, pooled: over the pairs the prediction is valid on.
        pairs: those pairs; collided: the pairs it collided on (left out).
    """

    mean: float | None
    median: float | None
    pooled: float | None
    pairs: int
    collided: int


def per_pair_rmse(error: Tensor, mask: Tensor) -> np.ndarray:
    """``(N,)`` the RMSE [m] of ``error`` (T, N) over each pair's ``mask``ed
    steps (NaN where the error is not finite on one of them)."""
    e = np.where(mask.numpy(), error.numpy(), 0.0)
    bad = ~np.isfinite(e).all(0)
    e = np.where(np.isfinite(e), e, 0.0)
    rmse = np.sqrt((e**2).sum(0) / np.maximum(mask.numpy().sum(0), 1))
    return np.where(bad, np.nan, rmse)


def summarize_rmse(error: Tensor, mask: Tensor) -> tuple[SpacingRMSE, np.ndarray]:
    """The summary and the ``(N,)`` per-pair RMSE (NaN: collided) of a
    prediction's spacing ``error`` (T, N) on the ``mask``ed steps."""
    rmse = per_pair_rmse(error, mask)
    ok = np.isfinite(rmse)
    steps = mask.numpy().sum(0)
    squared = (rmse[ok] ** 2 * steps[ok]).sum()
    return (
        SpacingRMSE(
            mean=_stat(np.mean, rmse[ok]),
            median=_stat(np.median, rmse[ok]),
            pooled=float(math.sqrt(squared / steps[ok].sum())) if ok.any() else None,
            pairs=int(ok.sum()),
            collided=int((~ok).sum()),
        ),
        rmse,
    )


def displacement(error: Tensor, mask: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(ADE, FDE)`` [m] of position errors ``error`` (T, ...) over the
    ``mask``ed steps (T, N) broadcast over the trailing axes: each ``(...)``,
    NaN where an error is not finite."""
    e = np.abs(error.numpy())
    m = mask.numpy().reshape(mask.shape + (1,) * (e.ndim - 2))
    counted = np.where(m, e, 0.0)
    ade = counted.sum(0) / np.maximum(m.sum(0), 1)
    last = mask.numpy().sum(0) - 1  # (N,) each pair's last recorded step
    fde = np.take_along_axis(e, last.reshape((1, -1) + (1,) * (e.ndim - 2)), 0)[0]
    bad = ~np.isfinite(np.where(m, e, 0.0)).all(0)
    return np.where(bad, np.nan, ade), np.where(bad, np.nan, fde)


def coverage(observed: Tensor, low: Tensor, high: Tensor, mask: Tensor) -> float:
    """The share of recorded steps after the first (``mask`` (T, N)) whose
    ``observed`` (T, N) lies within ``[low, high]`` (T, N)."""
    counted = mask.clone()
    counted[0] = False  # the shared start: inside every band
    inside = (observed >= low) & (observed <= high) & counted
    return float(inside.sum()) / max(int(counted.sum()), 1)


def _stat(fn, values: np.ndarray) -> float | None:
    return float(fn(values)) if values.size else None


__all__ = [
    "SpacingRMSE",
    "coverage",
    "displacement",
    "per_pair_rmse",
    "summarize_rmse",
]
