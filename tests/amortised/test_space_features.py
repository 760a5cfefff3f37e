"""The parameter space's maps and the encoder's input channels."""

from __future__ import annotations

import math

import pytest
import torch

from torchcf.amortised import CHANNELS, NoiseLevels, ParameterSpace, pair_features
from torchcf.amortised.features import CENTRE, SCALE, channel_features
from torchcf.amortised.space import latent_to_unit, log_jacobian, unit_to_latent
from torchcf.data import PairSet
from torchcf.models import get_model


def test_the_space_pads_the_narrower_models_with_nan(space):
    assert space.names == ("idm", "ovm")
    assert space.n_params == (6, 5)
    assert space.width == 6
    assert math.isnan(float(space.low[1, 5]))
    assert torch.equal(space.box(1), get_model("ovm").prior_bounds())


def test_unit_coordinates_map_back_and_forth_inside_the_box(space):
    theta = torch.tensor([[1.0, 2.0, 30.0, 1.5, 2.0, 4.0]], dtype=torch.float64)
    unit = space.to_unit(0, theta)
    assert torch.allclose(space.to_theta(0, unit), theta)
    # the flow's space is unbounded; any latent value maps inside the box
    latent = torch.tensor([[-50.0, -3.0, 0.0, 3.0, 50.0, 1e6]])
    inside = space.to_theta(0, latent_to_unit(latent))
    box = space.box(0).to(inside)
    assert bool(((inside >= box[:, 0]) & (inside <= box[:, 1])).all())
    assert torch.isfinite(unit_to_latent(torch.tensor([0.0, 1.0]))).all()


def test_the_jacobian_is_that_of_the_logistic():
    latent = torch.tensor([[-2.0, 0.5, 3.0]], dtype=torch.float64, requires_grad=True)
    unit = latent_to_unit(latent)
    derivative = torch.autograd.grad(unit.sum(), latent)[0]
    assert torch.allclose(log_jacobian(unit.detach()), derivative.log().sum(-1))


def test_boxes_are_checked():
    with pytest.raises(ValueError, match="low < high"):
        ParameterSpace([get_model("llcs")], [torch.tensor([[1.0, 1.0]] * 3)])
    with pytest.raises(ValueError, match="box of shape"):
        ParameterSpace([get_model("llcs")], [torch.zeros(2, 2)])
    with pytest.raises(ValueError, match="twice"):
        ParameterSpace([get_model("idm"), get_model("idm")])


def ragged_pairs() -> PairSet:
    n_steps = 6
    t = torch.arange(n_steps, dtype=torch.float64)[:, None]
    x_lead = 100.0 + 20.0 * t * 0.1 + torch.tensor([[0.0, 5.0]])
    series = (
        x_lead,
        torch.full((n_steps, 2), 20.0, dtype=torch.float64),
        torch.zeros(n_steps, 2, dtype=torch.float64),
        x_lead - 30.0,
        torch.full((n_steps, 2), 19.0, dtype=torch.float64),
        torch.full((n_steps, 2), 0.5, dtype=torch.float64),
    )
    mask = torch.arange(n_steps)[:, None] < torch.tensor([[6, 4]])
    return PairSet.from_arrays(series, dt=0.1, mask=mask)


def test_the_channels_are_the_documented_quantities_and_padding_is_zero():
    features, lengths = pair_features(ragged_pairs())
    assert features.shape == (2, len(CHANNELS), 6)
    assert features.dtype == torch.float32
    assert lengths.tolist() == [6, 4]
    raw = torch.tensor([30.0, 19.0, 1.0, 0.5, 0.0])  # spacing, v, dv, a, a_lead
    expected = torch.asinh((raw - torch.tensor(CENTRE)) / torch.tensor(SCALE))
    assert torch.allclose(features[0, :, 0], expected)
    assert torch.allclose(features[1, :, 3], expected)
    assert torch.count_nonzero(features[1, :, 4:]) == 0


def test_extreme_values_are_compressed():
    big = torch.tensor([[1000.0]])
    features = channel_features(
        big + 1000.0, big * 0, big * 0, (big * 0, big * 0, big * 0 + 50.0)
    )
    assert float(features.abs().max()) < 10.0


def test_the_noise_levels_of_white_noise_are_found():
    generator = torch.Generator().manual_seed(0)
    n_steps, n_pairs = 400, 30
    t = torch.arange(n_steps, dtype=torch.float64)[:, None] * 0.1
    smooth = 20.0 * t + torch.zeros(1, n_pairs, dtype=torch.float64)
    levels = (0.01, 0.05, 0.8)
    noise = [
        level * torch.randn(n_steps, n_pairs, generator=generator, dtype=torch.float64)
        for level in levels
    ]
    x_follow = smooth + noise[0]
    pairs = PairSet.from_arrays(
        (smooth + 40.0, smooth * 0 + 20.0, smooth * 0, x_follow,
         20.0 + noise[1], noise[2]),
        dt=0.1,
    )  # fmt: skip
    found = NoiseLevels.of_pairs(pairs)
    for value, level in zip(
        (found.position, found.speed, found.acceleration), levels, strict=True
    ):
        assert value == pytest.approx(level, rel=0.05)
