"""The trajectory encoder: a pair's series of any length -> a fixed embedding.

A stack of 1-D convolutions over time (the first ``strided`` of them halve the
time axis), then a masked global pooling (mean and max over the valid steps)
and a two-layer head. Global pooling is what lets one network read a 30 s
training window and a pair's whole series alike.

Shapes: input ``(J, C, T)`` (J series, C channels of
:mod:`torchcf.amortised.features`, T steps) with ``lengths (J,)``; after
convolution ``i`` the time axis is ``T_i`` and a series keeps its first
``l_i`` steps valid (``l_i = ceil(l_{i-1} / 2)`` after a strided layer);
output ``(J, E)``.

Ragged series in one batch read as each series alone: after every layer the
steps past a series' own length are set to zero, which is exactly the zero
padding a convolution reads past the end of a series given alone, so a
series' embedding does not depend on the batch it is in or on its padding
(up to the rounding of the convolution's kernels).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn


@dataclass(frozen=True)
class EncoderSettings:
    """The encoder's size.

    Attributes:
        channels: C, input channels.
        width: feature maps of every convolution.
        depth: convolutions.
        strided: the first ones halve the time axis (stride 2).
        kernel: kernel length [steps] (odd).
        embedding: E, the output's width.

    Examples:
        >>> EncoderSettings(width=8, depth=2, strided=1, embedding=4)
        EncoderSettings(channels=5, width=8, depth=2, strided=1, kernel=5, embedding=4)
    """

    channels: int = 5
    width: int = 48
    depth: int = 4
    strided: int = 3
    kernel: int = 5
    embedding: int = 64

    def __post_init__(self) -> None:
        if self.kernel % 2 != 1 or self.kernel < 1:
            raise ValueError(f"kernel must be odd and >= 1, got {self.kernel}")
        if not 0 <= self.strided <= self.depth or self.depth < 1:
            raise ValueError(
                f"need depth >= 1 and 0 <= strided <= depth, got "
                f"{self.depth}, {self.strided}"
            )


class TrajectoryEncoder(nn.Module):
    """Masked 1-D CNN with global mean and max pooling (module docstring).

    Args:
        settings: the encoder's size.

    Examples:
        >>> import torch
        >>> small = EncoderSettings(width=8, depth=2, strided=1, embedding=4)
        >>> encoder = TrajectoryEncoder(small)
        >>> features = torch.randn(3, 5, 40)  # 3 series of 40 steps, 5 channels
        >>> encoder(features, lengths=torch.tensor([40, 25, 10])).shape  # (J, E)
        torch.Size([3, 4])
    """

    def __init__(self, settings: EncoderSettings = EncoderSettings()) -> None:
        super().__init__()
        self.settings = settings
        pad = settings.kernel // 2
        self.strides = tuple(
            2 if i < settings.strided else 1 for i in range(settings.depth)
        )
        self.convolutions = nn.ModuleList(
            nn.Conv1d(
                settings.channels if i == 0 else settings.width,
                settings.width,
                settings.kernel,
                stride=stride,
                padding=pad,
            )
            for i, stride in enumerate(self.strides)
        )
        self.head = nn.Sequential(
            nn.Linear(2 * settings.width, settings.embedding),
            nn.GELU(),
            nn.Linear(settings.embedding, settings.embedding),
        )

    def forward(self, features: Tensor, lengths: Tensor) -> Tensor:
        """Embed J series.

        Args:
            features: (J, C, T) float32 (zero past each series' length).
            lengths: (J,) int64 valid steps of each series, 1 .. T.

        Returns:
            (J, E) float32.
        """
        lengths = lengths.to(device=features.device, dtype=torch.int64)
        hidden = features * _mask(lengths, features.shape[-1])[:, None, :]
        for convolution, stride in zip(self.convolutions, self.strides, strict=True):
            hidden = nn.functional.gelu(convolution(hidden))  # (J, width, T_i)
            # a stride-2 convolution with padding k // 2 keeps ceil(l / 2) steps
            # whose every input lies inside the series or its zero padding
            lengths = (lengths + stride - 1) // stride
            hidden = hidden * _mask(lengths, hidden.shape[-1])[:, None, :]
        valid = _mask(lengths, hidden.shape[-1])[:, None, :]  # (J, 1, T_i)
        mean = hidden.sum(-1) / lengths[:, None].to(hidden.dtype)  # (J, width)
        peak = hidden.masked_fill(~valid, -torch.inf).amax(-1)  # (J, width)
        return self.head(torch.cat((mean, peak), dim=1))


def _mask(lengths: Tensor, n_steps: int) -> Tensor:
    """(J, n_steps) bool, True on each series' first ``lengths`` steps."""
    steps = torch.arange(n_steps, device=lengths.device)
    return steps[None, :] < lengths[:, None]


__all__ = ["EncoderSettings", "TrajectoryEncoder"]
