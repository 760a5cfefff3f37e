"""What the encoder reads of a pair: five normalised channels over time.

One function serves the training set (:mod:`torchcf.amortised.simulations`,
a simulated follower behind a leader window) and inference
(:mod:`torchcf.amortised.inference`, a pair's whole observed series), so the
two can never read a pair differently.

The channels, each ``asinh((value - CENTRE) / SCALE)`` with fixed constants
(no statistic of a data set enters, so a trained estimator reads every data
set alike). The ``asinh`` is nearly the identity over the range of measured
driving (``|.| < 1``) and a logarithm beyond it, so that the prior's extreme
followers (a follower hundreds of metres behind, accelerations of tens of
m/s^2) stay within a few units instead of dominating a training batch:

====  ==================================================  =========  =======
 c    quantity                                            centre     scale
====  ==================================================  =========  =======
 0    spacing ``x_lead - x_follow`` [m]                   30 m       15 m
 1    follower speed ``v_follow`` [m/s]                   15 m/s     10 m/s
 2    speed difference ``v_lead - v_follow`` [m/s]        0          2 m/s
 3    follower acceleration ``a_follow`` [m/s^2]          0          1 m/s^2
 4    leader acceleration ``a_lead`` [m/s^2]              0          1 m/s^2
====  ==================================================  =========  =======

The leader's speed is channel 1 plus channel 2's value; the leader's and the
follower's positions enter only through the spacing (a model sees nothing
else of them). Padded steps (``mask`` False) are set to zero, which is what
the encoder's convolutions read past a series' end
(:class:`torchcf.amortised.encoder.TrajectoryEncoder`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:
    from ..data import PairSet

#: The channels' names, in order (``C = 5``).
CHANNELS = ("spacing", "v_follow", "dv", "a_follow", "a_lead")
#: Per channel: the value subtracted [m, m/s, m/s, m/s^2, m/s^2] ...
CENTRE = (30.0, 15.0, 0.0, 0.0, 0.0)
#: ... and the scale it is divided by (same units).
SCALE = (15.0, 10.0, 2.0, 1.0, 1.0)


def channel_features(
    x_lead: Tensor,
    v_lead: Tensor,
    a_lead: Tensor,
    follower: tuple[Tensor, Tensor, Tensor],
    mask: Tensor | None = None,
) -> Tensor:
    """The encoder's input of N series (module docstring), float32.

    Args:
        x_lead, v_lead, a_lead: (T, N) leader position [m], speed [m/s] and
            acceleration [m/s^2].
        follower: the follower's (T, N) position [m], speed [m/s] and
            acceleration [m/s^2].
        mask: (T, N) bool valid steps (a prefix per column); None: all valid.

    Returns:
        (N, C, T) float32, zero on padded steps.

    Examples:
        >>> import torch
        >>> x_lead, v = torch.full((3, 2), 60.0), torch.full((3, 2), 15.0)  # (T, N)
        >>> a = torch.zeros(3, 2)
        >>> features = channel_features(x_lead, v, a, (x_lead - 30.0, v, a))
        >>> features.shape, float(features.abs().max())  # 30 m at 15 m/s: the centre
        (torch.Size([2, 5, 3]), 0.0)
    """
    x_follow, v_follow, a_follow = follower
    values = (
        x_lead - x_follow,
        v_follow,
        v_lead - v_follow,
        a_follow,
        a_lead,
    )
    stacked = torch.stack(
        [
            torch.asinh((value.to(torch.float32) - centre) / scale)
            for value, centre, scale in zip(values, CENTRE, SCALE, strict=True)
        ]
    )  # (C, T, N)
    if mask is not None:
        stacked = stacked * mask[None].to(torch.float32)
    return stacked.permute(2, 0, 1).contiguous()  # (N, C, T)


def pair_features(pairs: PairSet) -> tuple[Tensor, Tensor]:
    """A pair set's observed series as the encoder reads them.

    Returns:
        features: (N, C, T) float32 (:func:`channel_features`);
        lengths: (N,) int64 valid steps of each pair.

    Examples:
        >>> import torch
        >>> from torchcf import PairSet
        >>> t = torch.arange(100, dtype=torch.float64)[:, None] * 0.1  # (T, 1) [s]
        >>> x_lead, v = 40.0 + 15.0 * t, torch.full_like(t, 15.0)
        >>> a = torch.zeros_like(t)
        >>> pairs = PairSet.from_arrays([x_lead, v, a, x_lead - 30.0, v, a], dt=0.1)
        >>> features, lengths = pair_features(pairs)
        >>> features.shape, lengths
        (torch.Size([1, 5, 100]), tensor([100]))
    """
    features = channel_features(
        pairs.x_lead,
        pairs.v_lead,
        pairs.a_lead,
        (pairs.x_follow, pairs.v_follow, pairs.a_follow),
        pairs.mask,
    )
    return features, pairs.lengths.to(torch.int64)


__all__ = ["CENTRE", "CHANNELS", "SCALE", "channel_features", "pair_features"]
