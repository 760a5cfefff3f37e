"""The model class judged on the test split (torchcf.diagnose.selection.on_test)."""

from __future__ import annotations

import torch

from torchcf.abc.particles import Particles
from torchcf.config import validate_config
from torchcf.diagnose import Population
from torchcf.diagnose.arms.refit import Pin
from torchcf.diagnose.selection.on_test import chosen_value, class_on_test
from torchcf.diagnose.setup import LoopSetup
from torchcf.models import get_model
from torchcf.models.effects import parse_effect
from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs

IDM = [1.2, 2.0, 30.0, 1.3, 2.0, 4.0]


def test_a_chosen_effects_value_is_its_shared_value_or_its_estimate():
    delay, offset = parse_effect("delay"), parse_effect("offset")
    shared = {"offset": [-2.5]}
    estimates = {"delay": {"t_delay": 0.7}}
    assert chosen_value(offset, shared, estimates).tolist() == [-2.5]
    assert chosen_value(delay, shared, estimates).tolist() == [0.7]
    assert chosen_value(delay, {}, {}).tolist() == list(delay.neutral)


def _population(model: str, theta: torch.Tensor, n_pairs: int) -> Population:
    q = theta.shape[0]
    particles = Particles(
        get_model(model),
        theta.double(),
        torch.arange(q) % n_pairs,
        torch.zeros(q, dtype=torch.float64),
        torch.arange(q),
    )
    return Population.from_particles([particles], n_pairs, q // n_pairs + 1)


def test_the_class_with_a_true_delay_fits_new_delayed_drivers_better():
    """Test drivers who all answer 0.8 s late: refitted with the delay pinned
    at 0.8 s they fit better than refitted without it, on nearly every pair."""
    mixture = DriverMixture(("idm",), "delay", (0.8,))
    test, _ = heterogeneous_pairs(mixture, 16, n_steps=300, seed=3, noise=0.05)
    cfg = validate_config(
        {
            "data": {"path": "synthetic"},
            "models": ["idm"],
            "abc": {"n_particles": 100, "top_n": 4},
            "diagnose": {"refit_slots": 3, "refit_rounds": 6, "local_copies": 8},
        }
    )
    box = get_model("idm").prior_bounds(torch.float64)
    g = torch.Generator().manual_seed(1)
    theta = box[:, 0] + torch.rand(64, 6, generator=g, dtype=torch.float64) * (
        box[:, 1] - box[:, 0]
    )
    start = _population("idm", theta, 16)
    delayed = torch.cat([theta, torch.full((64, 1), 0.8, dtype=torch.float64)], 1)
    final = _population("idm+delay", delayed, 16)
    pin = Pin(parse_effect("delay"), torch.tensor([0.8], dtype=torch.float64))
    found = class_on_test(LoopSetup.of(cfg), start, final, [pin], test)
    assert found.pairs == 16
    assert found.change < -0.1 and found.better >= 12
    assert found.p_value < 0.01
    assert found.pinned == {"delay": {"t_delay": 0.8}}
    assert len(found.per_pair["with"]) == 16
