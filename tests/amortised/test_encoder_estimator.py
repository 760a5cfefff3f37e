"""The encoder's shapes and padding; the estimator's densities and samples."""

from __future__ import annotations

import math

import pytest
import torch

from torchcf.amortised import (
    EncoderSettings,
    TrajectoryEncoder,
    new_estimator,
)
from torchcf.amortised.space import unit_to_latent

from .conftest import TINY


def test_the_encoder_embeds_series_of_any_length():
    encoder = TrajectoryEncoder(EncoderSettings(width=8, embedding=6))
    for n_steps in (1, 7, 300):
        features = torch.randn(3, 5, n_steps)
        out = encoder(features, torch.full((3,), n_steps))
        assert out.shape == (3, 6) and torch.isfinite(out).all()


def test_a_padded_series_embeds_as_the_series_alone():
    """Series of 9 to 40 steps padded into one batch: each embeds as given
    alone (the masks after every layer equal the convolution's zero
    padding), whatever the padding holds."""
    torch.manual_seed(0)
    encoder = TrajectoryEncoder(EncoderSettings(width=8, embedding=6, strided=3))
    lengths = torch.tensor([40, 9, 23, 24, 1])
    padded = torch.randn(5, 5, 40) * 3  # junk past each length
    batch = encoder(padded, lengths)
    for j, length in enumerate(lengths.tolist()):
        alone = encoder(padded[j : j + 1, :, :length], lengths[j : j + 1])
        torch.testing.assert_close(batch[j : j + 1], alone, rtol=1e-5, atol=1e-6)


def test_samples_have_the_documented_shapes_and_lie_in_the_box(space):
    estimator = new_estimator(space, TINY, seed=0)
    features = torch.randn(4, 5, 50)
    draws = estimator.sample(features, torch.full((4,), 50), 300, torch.Generator())
    assert draws.model.shape == (4, 300) and draws.model.dtype == torch.int64
    assert draws.theta.shape == (4, 300, 6)
    assert set(draws.model.unique().tolist()) == {0, 1}
    for m in range(2):
        theta = draws.theta[draws.model == m]
        k = space.n_params[m]
        box = space.box(m).to(theta)
        assert torch.isfinite(theta[:, :k]).all()
        assert bool(((theta[:, :k] >= box[:, 0]) & (theta[:, :k] <= box[:, 1])).all())
        assert theta[:, k:].isnan().all()
    probabilities = estimator.model_probabilities(features, torch.full((4,), 50))
    assert probabilities.shape == (4, 2)
    torch.testing.assert_close(probabilities.sum(1), torch.ones(4))


def test_the_weights_are_a_function_of_the_seed(space):
    state = new_estimator(space, TINY, seed=3).state_dict()
    again = new_estimator(space, TINY, seed=3).state_dict()
    other = new_estimator(space, TINY, seed=4).state_dict()
    assert all(torch.equal(state[k], again[k]) for k in state)
    assert not all(torch.equal(state[k], other[k]) for k in state)


def test_the_density_integrates_to_one_over_models_and_boxes(space):
    """``sum_m E_{theta ~ U(box_m)}[q(m, theta | x) vol_m] = 1``: the latent
    density, the box's Jacobian and the model head make one normalised density
    over (model, theta in SI units)."""
    estimator = new_estimator(space, TINY, seed=0)
    features = torch.randn(1, 5, 60)
    n = 20_000
    generator = torch.Generator().manual_seed(0)
    total = 0.0
    with torch.no_grad():
        for m in range(space.n_models):
            k = space.n_params[m]
            unit = torch.rand(n, k, generator=generator, dtype=torch.float64)
            theta = torch.full((n, space.width), math.nan, dtype=torch.float64)
            theta[:, :k] = space.to_theta(m, unit)
            log_q = estimator.log_prob(
                torch.full((n,), m),
                theta,
                features.expand(n, -1, -1),
                torch.full((n,), 60),
            )
            volume = math.exp(space.log_span(m))
            total += float(log_q.double().exp().mean()) * volume
    assert total == pytest.approx(1.0, abs=0.03)


def test_the_flows_are_trainable(space, simulator):
    """A few Adam steps on one batch lower its loss; every parameter of the
    networks gets a gradient, and every log density is finite."""
    estimator = new_estimator(space, TINY, seed=0)
    batch = simulator.draw("trainable", 128)
    lengths = torch.full((len(batch),), batch.features.shape[-1])
    optimiser = torch.optim.Adam(estimator.parameters(), lr=3e-3)
    losses = []
    for _ in range(15):
        embedding = estimator.embed(batch.features, lengths)
        log_prob = estimator.latent_log_prob(embedding, batch.model, batch.unit)
        assert torch.isfinite(log_prob).all()
        loss = -log_prob.mean()
        optimiser.zero_grad()
        loss.backward()
        if not losses:
            missing = [
                name
                for name, p in estimator.named_parameters()
                if p.grad is None or not torch.isfinite(p.grad).all()
            ]
            assert not missing, missing
        optimiser.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] - 0.5


def test_log_prob_is_the_latent_density_less_the_box_jacobian(space, simulator):
    estimator = new_estimator(space, TINY, seed=1)
    batch = simulator.draw("density", 16)
    lengths = torch.full((16,), batch.features.shape[-1])
    theta = batch.theta(space)
    with torch.no_grad():
        log_q = estimator.log_prob(batch.model, theta, batch.features, lengths)
        embedding = estimator.embed(batch.features, lengths)
        latent = estimator.latent_log_prob(embedding, batch.model, batch.unit)
    for j in range(16):
        m = int(batch.model[j])
        k = space.n_params[m]
        unit = batch.unit[j, :k]
        jacobian = float((unit * (1 - unit)).log().sum()) + space.log_span(m)
        assert float(log_q[j]) == pytest.approx(float(latent[j]) - jacobian, abs=1e-4)
    assert torch.isfinite(unit_to_latent(batch.unit[:, :5])).all()
