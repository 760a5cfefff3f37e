"""Inference over a pair set: a pair's result does not depend on the chunk it
is read in."""

from __future__ import annotations

import pytest
import torch

from torchcf.amortised import ParameterSpace, infer, new_estimator
from torchcf.data import PairSet
from torchcf.models import get_model
from torchcf.sim.compiled import compiler_available

from .conftest import TINY


@pytest.fixture(scope="module")
def ragged(leader_pairs) -> PairSet:
    """The leader pairs cut to lengths of 60 to 300 steps."""
    lengths = torch.linspace(60, 300, leader_pairs.n_pairs).long()
    mask = torch.arange(leader_pairs.n_steps)[:, None] < lengths[None, :]
    return PairSet.from_arrays(leader_pairs.series(), dt=leader_pairs.dt, mask=mask)


def test_the_results_have_the_documented_shapes(space, ragged):
    estimator = new_estimator(space, TINY, seed=0)
    posterior = infer(estimator, ragged, 7, seed=0)
    n = ragged.n_pairs
    assert posterior.probabilities.shape == (n, 2)
    assert posterior.model.shape == (n, 7)
    assert posterior.theta.shape == (n, 7, 6)
    pair, theta = posterior.of_model(1)
    assert theta.shape == (int((posterior.model == 1).sum()), 5)
    assert torch.isfinite(theta).all()
    assert pair.tolist() == sorted(pair.tolist())


@pytest.mark.parametrize("chunk_size", [1, 5, 64])
def test_batched_equals_looped(space, ragged, chunk_size):
    """Chunks of 1 pair (each series cut to its own length: the pair alone),
    of 5 and of every pair give the same probabilities and samples."""
    estimator = new_estimator(space, TINY, seed=0)
    reference = infer(estimator, ragged, 20, seed=3, chunk_size=ragged.n_pairs)
    chunked = infer(estimator, ragged, 20, seed=3, chunk_size=chunk_size)
    torch.testing.assert_close(
        chunked.probabilities, reference.probabilities, rtol=1e-5, atol=1e-6
    )
    assert torch.equal(chunked.model, reference.model)
    torch.testing.assert_close(
        chunked.theta, reference.theta, rtol=1e-4, atol=1e-5, equal_nan=True
    )


def test_the_samples_are_a_function_of_the_seed(space, ragged):
    estimator = new_estimator(space, TINY, seed=0)
    first = infer(estimator, ragged, 10, seed=1)
    again = infer(estimator, ragged, 10, seed=1)
    other = infer(estimator, ragged, 10, seed=2)
    assert torch.equal(first.model, again.model)
    torch.testing.assert_close(first.theta, again.theta, equal_nan=True)
    assert not torch.equal(first.model, other.model)


@pytest.mark.skipif(not compiler_available(), reason="no C++ compiler")
def test_compiled_sampling_gives_the_eager_samples(ragged):
    """``compile=True`` draws the same samples through compiled flows (one
    graph per model for every number of samples: two chunk sizes, no
    recompilation needed), up to float32 rounding; one model, one compile."""
    estimator = new_estimator(ParameterSpace([get_model("idm")]), TINY, seed=0)
    eager = infer(estimator, ragged, 20, seed=3)
    for chunk_size in (ragged.n_pairs, 7):
        compiled = infer(estimator, ragged, 20, seed=3, chunk_size=chunk_size,
                         compile=True)  # fmt: skip
        assert torch.equal(compiled.model, eager.model)
        torch.testing.assert_close(
            compiled.theta, eager.theta, rtol=1e-4, atol=1e-4, equal_nan=True
        )
