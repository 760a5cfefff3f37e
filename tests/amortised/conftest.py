"""Tiny amortised estimators and their data: two models whose dynamics differ
(IDM and OVM), leaders and followers of heterogeneous synthetic pairs."""

from __future__ import annotations

import pytest

from torchcf.amortised import (
    EncoderSettings,
    EstimatorSettings,
    NoiseLevels,
    ParameterSpace,
    SimulationSettings,
    TrainingSimulator,
)
from torchcf.models import get_model
from torchcf.sim.synthetic import DriverMixture, heterogeneous_pairs

#: Networks a few thousand examples can train in seconds.
TINY = EstimatorSettings(
    encoder=EncoderSettings(width=32, depth=3, strided=3, embedding=32),
    head_width=32,
    transforms=2,
    flow_width=32,
)
#: Idm and OVM drivers of 300 steps, with the simulator's noise: 5 mm (the
#: speed and acceleration noise of ``heterogeneous_pairs`` are then 5 mm/s and
#: 5 mm/s^2 at dt 0.1 s).
MIXTURE = DriverMixture(models=("idm", "ovm"))
NOISE = 0.005
SIMULATION = SimulationSettings(
    window_steps=200,
    noise=NoiseLevels(NOISE, NOISE, NOISE),
    chunk_size=512,
)


@pytest.fixture(autouse=True)
def _one_thread(one_thread):
    """Every test of the package on one torch thread (``tests/conftest.py``)."""


@pytest.fixture(scope="package")
def space() -> ParameterSpace:
    return ParameterSpace([get_model("idm"), get_model("ovm")])


@pytest.fixture(scope="package")
def leader_pairs():
    """The "data set" whose leaders the training replays (24 pairs)."""
    pairs, _ = heterogeneous_pairs(MIXTURE, 24, 300, seed=1, noise=NOISE)
    return pairs


@pytest.fixture(scope="package")
def simulator(space, leader_pairs) -> TrainingSimulator:
    return TrainingSimulator(space, leader_pairs, SIMULATION, seed=0)
