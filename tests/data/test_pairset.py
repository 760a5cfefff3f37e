"""PairSet: construction, derived sets, and the validation messages."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torchcf.data import DataError, PairSet
from torchcf.data.pairset import SERIES, edge_pad


@pytest.fixture
def pairs(make_arrays) -> PairSet:
    return PairSet.from_arrays(make_arrays(n_steps=6, n_pairs=4), dt=0.1)


def test_from_arrays_defaults(pairs: PairSet) -> None:
    assert (pairs.n_steps, pairs.n_pairs, len(pairs)) == (6, 4, 4)
    assert all(getattr(pairs, f).dtype == torch.float64 for f in SERIES)
    assert pairs.mask.dtype == torch.bool and bool(pairs.mask.all())
    assert pairs.pair_ids == (0, 1, 2, 3)
    assert pairs.lengths.tolist() == [6, 6, 6, 6]
    assert pairs.lengths.dtype == torch.long
    assert (pairs.dt, pairs.leader_length, pairs.split, pairs.notes) == (
        0.1,
        5.0,
        None,
        (),
    )


def test_from_arrays_accepts_lists_and_keeps_tensor_dtype(make_arrays) -> None:
    arrays = make_arrays()
    from_lists = PairSet.from_arrays({k: v.tolist() for k, v in arrays.items()}, dt=1)
    assert from_lists.dtype == torch.float64 and from_lists.dt == 1.0
    tensors = {k: torch.from_numpy(v).float() for k, v in arrays.items()}
    assert PairSet.from_arrays(tensors, dt=0.1).dtype == torch.float32


def test_ragged_input_is_edge_padded(make_arrays) -> None:
    arrays = make_arrays(n_steps=5, n_pairs=2)
    mask = np.ones((5, 2), dtype=bool)
    mask[3:, 1] = False
    for values in arrays.values():
        values[3:, 1] = np.nan  # padding in the input may be anything
    pairs = PairSet.from_arrays(arrays, dt=0.1, mask=mask)
    assert pairs.lengths.tolist() == [5, 3]
    for f in SERIES:
        column = getattr(pairs, f)[:, 1]
        assert torch.isfinite(column).all()
        assert column[3:].eq(column[2]).all()


def test_edge_pad_keeps_valid_steps() -> None:
    values = torch.arange(12.0).reshape(4, 3)
    mask = torch.tensor([[1, 1, 1], [1, 1, 0], [1, 0, 0], [1, 0, 0]], dtype=torch.bool)
    padded = edge_pad(values, mask)
    assert padded.tolist() == [[0, 1, 2], [3, 4, 2], [6, 4, 2], [9, 4, 2]]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_to_converts_floats_never_the_mask(pairs: PairSet, dtype) -> None:
    moved = pairs.to(dtype=dtype)
    assert all(getattr(moved, f).dtype == dtype for f in SERIES)
    assert moved.mask.dtype == torch.bool
    assert torch.equal(moved.x_lead, pairs.x_lead.to(dtype))
    assert moved.pair_ids == pairs.pair_ids and moved.dt == pairs.dt
    assert pairs.to().x_lead.device == pairs.x_lead.device
    with pytest.raises(TypeError, match="floating"):
        pairs.to(dtype=torch.int64)


@pytest.mark.parametrize(
    "index",
    [[2, 0], torch.tensor([2, 0]), np.array([2, 0]), [-2, 0]],
    ids=["list", "tensor", "numpy", "negative"],
)
def test_subset_selects_pairs_and_ids(pairs: PairSet, index) -> None:
    pairs = dataclasses.replace(pairs, pair_ids=(10, 11, 12, 13), notes=("n",))
    sub = pairs.subset(index)
    assert sub.pair_ids == (12, 10) and sub.notes == ("n",)
    for f in (*SERIES, "mask"):
        assert torch.equal(getattr(sub, f), getattr(pairs, f)[:, [2, 0]])


def test_subset_bool_empty_and_out_of_range(pairs: PairSet) -> None:
    assert pairs.subset(torch.tensor([True, False, False, True])).pair_ids == (0, 3)
    empty = pairs.subset([])
    assert empty.n_pairs == 0 and empty.n_steps == pairs.n_steps
    with pytest.raises(IndexError, match="out of range"):
        pairs.subset([4])


def test_frozen_and_short_repr(pairs: PairSet) -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        pairs.dt = 0.2  # type: ignore[misc]
    assert "n_pairs=4" in repr(pairs) and "tensor(" not in repr(pairs)


# ----------------------------------------------------------------- validation
def test_non_positive_spacing_message(make_arrays) -> None:
    arrays = make_arrays(n_steps=15, n_pairs=8)
    arrays["x_follow"][11, 6] = arrays["x_lead"][11, 6] + 0.3
    with pytest.raises(DataError) as err:
        PairSet.from_arrays(arrays, dt=0.1)
    assert str(err.value) == (
        "non-positive spacing x_lead - x_follow = -0.3 m at row 12, column 7 "
        "(pair id 6)"
    )


def test_masked_spacing_and_count(make_arrays) -> None:
    arrays = make_arrays(n_steps=6, n_pairs=2)
    arrays["x_follow"][4:, 1] = arrays["x_lead"][4:, 1]  # zero spacing
    mask = np.ones((6, 2), dtype=bool)
    mask[4:, 1] = False
    # Padding is overwritten, so masked bad steps do not matter ...
    PairSet.from_arrays(arrays, dt=0.1, mask=mask)
    # ... but valid ones do, and the message counts them.
    with pytest.raises(DataError, match=r"= 0 m at row 5, column 2 .*2 such steps"):
        PairSet.from_arrays(arrays, dt=0.1)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_value(make_arrays, bad: float) -> None:
    arrays = make_arrays()
    arrays["v_follow"][2, 1] = bad
    with pytest.raises(DataError, match=r"non-finite v_follow = .* row 3, column 2"):
        PairSet.from_arrays(arrays, dt=0.1)


def test_non_finite_padding_rejected_by_constructor(pairs: PairSet) -> None:
    mask = pairs.mask.clone()
    mask[-1, 0] = False
    a_lead = pairs.a_lead.clone()
    a_lead[-1, 0] = float("nan")
    with pytest.raises(DataError, match=r"row 6, column 1 \(pair id 0\) \(a padding"):
        dataclasses.replace(pairs, a_lead=a_lead, mask=mask)


def test_shapes_disagree(make_arrays) -> None:
    arrays = make_arrays()
    arrays["a_follow"] = arrays["a_follow"][:-1]
    with pytest.raises(DataError, match=r"one \(T, N\) shape.*a_follow=\(4, 3\)"):
        PairSet.from_arrays(arrays, dt=0.1)
    with pytest.raises(DataError, match="mask has shape"):
        PairSet.from_arrays(make_arrays(), dt=0.1, mask=np.ones((5, 2), bool))


@pytest.mark.parametrize(
    ("dt", "match"),
    [
        (None, "dt missing"),
        (0.0, "dt must be finite and > 0"),
        (-0.1, "dt must be finite and > 0"),
        (float("nan"), "dt must be finite and > 0"),
        ("fast", "dt must be a number"),
    ],
)
def test_bad_dt(make_arrays, dt, match: str) -> None:
    with pytest.raises(DataError, match=match):
        PairSet.from_arrays(make_arrays(), dt=dt)


@pytest.mark.parametrize("length", [0.0, -5.0, float("inf")])
def test_bad_leader_length(make_arrays, length: float) -> None:
    with pytest.raises(DataError, match="leader_length must be finite and > 0"):
        PairSet.from_arrays(make_arrays(), dt=0.1, leader_length=length)


def test_mask_not_prefix(make_arrays) -> None:
    mask = np.ones((5, 3), dtype=bool)
    mask[2, 1] = False
    with pytest.raises(
        DataError,
        match=r"not a prefix: False at row 3, column 2 .* True again at row 4",
    ):
        PairSet.from_arrays(make_arrays(), dt=0.1, mask=mask)


def test_pair_without_valid_step(make_arrays) -> None:
    mask = np.ones((5, 3), dtype=bool)
    mask[:, 2] = False
    with pytest.raises(DataError, match="column 3 .* masked everywhere"):
        PairSet.from_arrays(make_arrays(), dt=0.1, mask=mask)


def test_constructor_checks_types(pairs: PairSet) -> None:
    with pytest.raises(DataError, match="mask must be bool"):
        dataclasses.replace(pairs, mask=pairs.mask.long())
    with pytest.raises(DataError, match="one floating dtype"):
        dataclasses.replace(pairs, v_lead=pairs.v_lead.float())
    with pytest.raises(DataError, match="2 pair_ids given for 4 pairs"):
        dataclasses.replace(pairs, pair_ids=(0, 1))
    with pytest.raises(DataError, match="split must be"):
        dataclasses.replace(pairs, split="validation")


def test_steps_keep_the_pairs_and_cut_every_series_and_the_mask():
    from tests.conftest import synthetic_pairs

    pairs = synthetic_pairs(n_pairs=3, n_steps=40)
    part = pairs.steps(10, 25)
    assert (part.n_steps, part.n_pairs, part.pair_ids) == (15, 3, pairs.pair_ids)
    assert torch.equal(part.x_follow, pairs.x_follow[10:25])
    assert torch.equal(part.mask, pairs.mask[10:25])
    assert pairs.steps(30).n_steps == 10
