"""The examples in the public API's docstrings run, and say what they show."""

from __future__ import annotations

import doctest
import importlib

import pytest

#: Modules whose docstrings hold runnable examples.
MODULES = [
    "torchcf.models",
    "torchcf.data.pairset",
    "torchcf.sim.rollout",
    "torchcf.traffic.sampler",
    "torchcf.predict",
]
#: Public entries (``torchcf.__all__``) that must carry one: the classes and
#: functions a user starts from.
EXAMPLED = ["PairSet", "get_model", "simulate", "HybridSampler"]


@pytest.mark.parametrize("name", MODULES)
def test_the_examples_run(name):
    module = importlib.import_module(name)
    flags = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE
    failed, attempted = doctest.testmod(module, optionflags=flags, verbose=False)
    assert failed == 0
    assert attempted > 0, f"{name}: no example"


@pytest.mark.parametrize("name", EXAMPLED)
def test_the_entry_points_carry_an_example(name):
    import torchcf

    assert ">>> " in (getattr(torchcf, name).__doc__ or ""), name
