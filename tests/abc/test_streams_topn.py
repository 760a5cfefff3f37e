"""Particle streams, the streaming top-N buffer and the hybrid selection."""

from __future__ import annotations

import pytest
import torch

from torchcf.abc.hybrid import pairwise_table, select, select_global, select_per_pair
from torchcf.abc.streams import STREAM_BLOCK, ParticleStream, block_seed, uniforms
from torchcf.abc.topn import TopN, lexsort
from torchcf.models import get_model

# --------------------------------------------------------------------------------------
# Streams


def test_uniforms_do_not_depend_on_how_the_range_is_cut():
    whole = uniforms(7, "idm", 0, 3 * STREAM_BLOCK + 17, 4)
    cuts = [
        0,
        1,
        100,
        STREAM_BLOCK - 1,
        STREAM_BLOCK + 5,
        2 * STREAM_BLOCK,
        3 * STREAM_BLOCK + 17,
    ]
    parts = [
        uniforms(7, "idm", a, b, 4) for a, b in zip(cuts[:-1], cuts[1:], strict=True)
    ]
    assert torch.equal(torch.cat(parts), whole)
    assert whole.dtype == torch.float64
    assert float(whole.min()) >= 0 and float(whole.max()) < 1


def test_streams_differ_by_seed_model_and_block():
    a = uniforms(0, "idm", 0, 10, 3)
    assert not torch.equal(a, uniforms(1, "idm", 0, 10, 3))
    assert not torch.equal(a, uniforms(0, "ovm", 0, 10, 3))
    seeds = {block_seed(0, "idm", b) for b in range(1000)}
    assert len(seeds) == 1000
    assert all(0 <= s < 2**63 for s in seeds)


def test_uniforms_are_uniform():
    u = uniforms(3, "hl", 0, 200_000, 2)
    # mean 1/2 and variance 1/12 within 5 standard errors
    assert abs(float(u.mean()) - 0.5) < 5 * (1 / 12) ** 0.5 / (4e5) ** 0.5
    assert abs(float(u.var()) - 1 / 12) < 1e-3


def test_particle_stream_maps_to_the_box_and_pairs():
    bounds = torch.tensor([[1.0, 2.0], [-5.0, 5.0]], dtype=torch.float64)
    stream = ParticleStream(get_model("idm"), bounds, seed=4, n_pairs=7)
    theta, pair = stream.draw(0, 50_000)
    assert theta.shape == (50_000, 2) and pair.shape == (50_000,)
    assert bool((theta[:, 0] >= 1).all() and (theta[:, 0] < 2).all())
    assert bool((theta[:, 1] >= -5).all() and (theta[:, 1] < 5).all())
    counts = torch.bincount(pair, minlength=7)
    assert counts.numel() == 7 and int(counts.min()) > 6500
    theta2, pair2 = stream.draw(123, 4567)
    assert torch.equal(theta2, theta[123:4567]) and torch.equal(pair2, pair[123:4567])
    full = ParticleStream(get_model("idm"), bounds, seed=4)
    assert full.draw(0, 3)[1] is None
    with pytest.raises(ValueError):
        ParticleStream(get_model("idm"), torch.tensor([[1.0, 1.0]]), seed=0)


def test_a_stream_hashes_its_models_name_as_before():
    """The stream holds the model object and hashes its name: the particles are
    the uniforms of the name itself, and the same as when the stream was given
    the name (the values below, across a block boundary)."""
    bounds = torch.tensor([[1.0, 2.0], [-5.0, 5.0]], dtype=torch.float64)
    model = get_model("idm+delay")
    theta, pair = ParticleStream(model, bounds, seed=4, n_pairs=7).draw(4094, 4098)
    u = uniforms(4, "idm+delay", 4094, 4098, 3)
    assert torch.equal(theta, bounds[:, 0] + (bounds[:, 1] - bounds[:, 0]) * u[:, :2])
    assert torch.equal(pair, (u[:, 2] * 7).long())
    expected = [
        [1.5004389824589648, 2.448530667989507],
        [1.939689979131059, -4.186915380381926],
        [1.9314496846658962, 1.4702347664402655],
        [1.6150291664177905, 1.0768132169700397],
    ]
    assert theta.tolist() == expected and pair.tolist() == [4, 6, 6, 6]


# --------------------------------------------------------------------------------------
# Top-N


def test_lexsort_orders_by_keys_in_turn():
    a = torch.tensor([1, 0, 1, 0, 1])
    b = torch.tensor([3.0, 2.0, 1.0, 2.0, 1.0])
    c = torch.tensor([0, 5, 9, 4, 2])
    order = lexsort(a, b, c)
    assert order.tolist() == [3, 1, 4, 2, 0]


def brute_force(pair, score, index, n_pairs, capacity):
    """Per pair, the ``capacity`` best finite (score, index) by a full sort."""
    out_score = torch.full((n_pairs, capacity), torch.inf, dtype=torch.float64)
    out_index = torch.full((n_pairs, capacity), -1, dtype=torch.int64)
    for p in range(n_pairs):
        rows = [
            (float(score[i]), int(index[i]))
            for i in range(len(score))
            if int(pair[i]) == p and torch.isfinite(score[i])
        ]
        rows.sort()
        for r, (s, j) in enumerate(rows[:capacity]):
            out_score[p, r], out_index[p, r] = s, j
    return out_score, out_index


@pytest.mark.parametrize("chunk", [1, 7, 64, 1000, 5000])
def test_streaming_equals_brute_force_with_ties_and_invalid(chunk):
    generator = torch.Generator().manual_seed(0)
    m, n_pairs, capacity = 3000, 6, 5
    pair = torch.randint(0, n_pairs, (m,), generator=generator)
    # few distinct values: many ties, broken by the lower index
    score = torch.randint(0, 40, (m,), generator=generator).double() / 4
    score[torch.rand(m, generator=generator) < 0.1] = torch.inf
    score[torch.rand(m, generator=generator) < 0.02] = torch.nan
    index = torch.arange(m)
    theta = torch.stack((index.double(), -index.double()), 1)
    buffer = TopN(n_pairs, capacity, 2)
    # arrive in a shuffled order: the result must not depend on it
    order = torch.randperm(m, generator=generator)
    for start in range(0, m, chunk):
        sl = order[start : start + chunk]
        buffer.push(pair[sl], score[sl], index[sl], theta[sl])
    ref_score, ref_index = brute_force(pair, score, index, n_pairs, capacity)
    assert torch.equal(buffer.score, ref_score)
    assert torch.equal(buffer.index, ref_index)
    filled = buffer.index >= 0
    assert torch.equal(buffer.theta[..., 0][filled], buffer.index[filled].double())


def test_pairs_with_few_valid_particles_keep_empty_slots():
    buffer = TopN(3, 4, 1)
    buffer.push(
        torch.tensor([0, 0, 1]),
        torch.tensor([2.0, 1.0, torch.inf]),
        torch.tensor([10, 11, 12]),
        torch.zeros(3, 1),
    )
    assert buffer.index.tolist() == [[11, 10, -1, -1], [-1] * 4, [-1] * 4]
    assert torch.isinf(buffer.threshold()).all()


def test_push_full_equals_push_of_every_cell():
    generator = torch.Generator().manual_seed(1)
    p, n_pairs = 500, 4
    score = torch.rand(p, n_pairs, generator=generator, dtype=torch.float64)
    score[::7, 1] = torch.inf
    theta = torch.rand(p, 3, generator=generator, dtype=torch.float64)
    index = torch.arange(p)
    full = TopN(n_pairs, 5, 3)
    for start in range(0, p, 64):
        full.push_full(
            score[start : start + 64],
            index[start : start + 64],
            theta[start : start + 64],
        )
    cells = TopN(n_pairs, 5, 3)
    cells.push(
        torch.arange(n_pairs).repeat(p),
        score.reshape(-1),
        index.repeat_interleave(n_pairs),
        theta.repeat_interleave(n_pairs, 0),
    )
    for name in ("score", "index", "theta"):
        assert torch.equal(getattr(full, name), getattr(cells, name))


def test_buffer_state_round_trip():
    buffer = TopN(2, 3, 1)
    buffer.push(
        torch.tensor([0, 1]),
        torch.tensor([1.0, 2.0]),
        torch.tensor([0, 1]),
        torch.ones(2, 1),
    )
    other = TopN(2, 3, 1)
    other.load_state_dict(buffer.state_dict())
    assert torch.equal(other.index, buffer.index)
    with pytest.raises(ValueError, match="shape"):
        TopN(2, 4, 1).load_state_dict(buffer.state_dict())


# --------------------------------------------------------------------------------------
# Hybrid


def filled(scores, indices, n_params=1):
    """A buffer holding the given per-pair (score, index) lists."""
    n_pairs, capacity = len(scores), len(scores[0])
    buffer = TopN(n_pairs, capacity, n_params)
    for p in range(n_pairs):
        s = torch.tensor(scores[p], dtype=torch.float64)
        buffer.push(
            torch.full((capacity,), p),
            s,
            torch.tensor(indices[p]),
            torch.zeros(capacity, n_params),
        )
    return buffer


def test_per_pair_hybrid_by_hand():
    # pair 0: A has 1, 4; B has 2, 3 -> best two: A1, B2. pair 1: A 5, 6; B 1, 2 -> B, B
    a = filled([[1.0, 4.0], [5.0, 6.0]], [[0, 1], [2, 3]])
    b = filled([[2.0, 3.0], [1.0, 2.0]], [[0, 1], [2, 3]])
    sel = select_per_pair([a, b], ["a", "b"], 2)
    assert sel.member[0].tolist() == [[True, False], [False, False]]
    assert sel.member[1].tolist() == [[True, False], [True, True]]
    assert sel.shares() == {"a": 0.25, "b": 0.75}
    # N = 1: pair 0 -> A, pair 1 -> B
    assert select_per_pair([a, b], ["a", "b"], 1).shares() == {"a": 0.5, "b": 0.5}


def test_ties_across_models_go_to_the_lower_index_then_the_first_model():
    a = filled([[1.0]], [[5]])
    b = filled([[1.0]], [[3]])
    assert select_per_pair([a, b], ["a", "b"], 1).shares() == {"a": 0.0, "b": 1.0}
    c = filled([[1.0]], [[5]])
    assert select_per_pair([a, c], ["a", "c"], 1).shares() == {"a": 1.0, "c": 0.0}


def test_global_hybrid_by_hand():
    a = filled([[1.0, 4.0], [5.0, 6.0]], [[0, 1], [2, 3]])
    b = filled([[2.0, 3.0], [1.5, 2.5]], [[0, 1], [2, 3]])
    sel = select_global([a, b], ["a", "b"], 2, 3)  # best 3 of 8: a1, b1.5, b2
    assert sel.counts().tolist() == [1, 2]
    assert select([a, b], ["a", "b"], 2, mode="global").counts().tolist() == [1, 3]


def test_pairwise_table_is_complementary():
    generator = torch.Generator().manual_seed(2)
    buffers = []
    for k in range(3):
        scores = (torch.rand(5, 4, generator=generator) + k * 0.2).sort(1).values
        buffers.append(filled(scores.tolist(), torch.arange(20).reshape(5, 4).tolist()))
    table = pairwise_table(buffers, ["x", "y", "z"], 4)
    assert torch.allclose(
        table + table.T,
        torch.ones(3, 3, dtype=torch.float64) + torch.eye(3, dtype=torch.float64),
    )
    assert torch.equal(torch.diagonal(table), torch.ones(3, dtype=torch.float64))
    # the table row of a model pair equals the hybrid of those two alone
    two = select_per_pair([buffers[0], buffers[2]], ["x", "z"], 4).shares()
    assert table[0, 2] == pytest.approx(two["x"])
