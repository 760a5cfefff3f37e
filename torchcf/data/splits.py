"""Training / test splits of a pair set: the data set's own split or seeded k-fold.

The run configuration (:class:`torchcf.config.DataConfig`) chooses one of three ways:

* ``split="dataset"``: the data set's own split, ``Trajectory/`` for training and
  ``Testing/`` for testing (see :mod:`torchcf.data.registry` for the quirks handled
  on the way, e.g. the train-to-test leak of CAR MODEL II).
* ``raw``: a raw trajectory source, extracted when the run starts
  (:func:`torchcf.data.importer.extract_source`) and split by source group
  (:func:`torchcf.data.extract.group_split`).
* ``split="kfold"``: the full set is cut into ``folds`` nearly equal parts by a
  seeded permutation of the pairs; part ``fold`` is the test set, the rest the
  training set (SPEC section 6, cross-validation).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchcf.data.importer import extract_source
from torchcf.data.pairset import DataError, PairSet
from torchcf.data.registry import load_pairs

if TYPE_CHECKING:
    # Typing only: torchcf.config imports torchcf.data, so a runtime import here
    # would be circular.
    from torchcf.config import DataConfig

__all__ = ["kfold_split", "load_split"]


def kfold_split(
    pairs: PairSet, folds: int, fold: int, seed: int
) -> tuple[PairSet, PairSet]:
    """Split the pairs into training and test sets, fold ``fold`` of ``folds``.

    The pair positions ``0 .. N-1`` are shuffled by ``torch.randperm`` under a
    ``torch.Generator`` seeded with ``seed`` and cut into ``folds`` consecutive
    parts as ``np.array_split`` does (the first ``N % folds`` parts hold one pair
    more). Over ``fold = 0 .. folds-1`` the test sets partition the pairs.

    Args:
        pairs: the (T, N) pair set to split, usually the full set.
        folds: number of parts, >= 2.
        fold: the part used as the test set, ``0 <= fold < folds``.
        seed: seed of the permutation; the same seed gives the same folds.

    Returns:
        ``(train, test)``: (T, N - N_test) and (T, N_test) PairSets (N_test: the
        fold's pairs), each in ascending order of position in ``pairs``, with
        ``split`` set to "train" and "test".

    Raises:
        DataError: ``folds < 2``, ``fold`` out of range, or fewer pairs than folds
            (a fold would be empty).
    """
    if folds < 2:
        raise DataError(f"folds must be >= 2, got {folds}")
    if not 0 <= fold < folds:
        raise DataError(f"fold must be in [0, {folds}), got {fold}")
    if pairs.n_pairs < folds:
        raise DataError(
            f"{pairs.n_pairs} pairs cannot be split into {folds} folds: "
            "every fold needs at least one pair"
        )
    generator = torch.Generator().manual_seed(seed)
    order = torch.randperm(pairs.n_pairs, generator=generator).numpy()  # (N,)
    parts = np.array_split(order, folds)
    test = np.sort(parts[fold])
    train = np.sort(np.concatenate([p for i, p in enumerate(parts) if i != fold]))
    return (
        dataclasses.replace(pairs.subset(train.tolist()), split="train"),
        dataclasses.replace(pairs.subset(test.tolist()), split="test"),
    )


def load_split(data: DataConfig, *, download: bool = True) -> tuple[PairSet, PairSet]:
    """Load the training and test pairs a run configuration asks for.

    Args:
        data: the ``data`` section of the run configuration (anything with the
            attributes of :class:`torchcf.config.DataConfig`).
        download: allow fetching missing files of a named set into the cache.

    Returns:
        ``(train, test)`` PairSets in SI units (float64, as loaded).

    Raises:
        DataError: the data cannot be loaded, or the k-fold split is impossible.
    """
    raw = getattr(data, "raw", None)
    if raw is not None:
        extraction = extract_source(
            raw.source,
            raw.format,
            reader_options=raw.reader_options(),
            options=raw.extract_options(),
        )
        if extraction.test is None:
            raise DataError("data.raw.test_fraction is 0: a run needs test pairs")
        return extraction.train, extraction.test
    source = data.name if data.name is not None else data.path
    if source is None:
        raise DataError("data: give a dataset name or a folder path")
    options = dict(
        units=data.units,
        dt=data.dt,
        leader_length=data.leader_length,
        data_root=data.root,
        download=download,
        drop_duplicates=data.drop_duplicates,
        min_spacing=data.min_spacing,
    )
    if data.split == "dataset":
        return (
            load_pairs(source, "train", **options),
            load_pairs(source, "test", **options),
        )
    if data.split == "kfold":
        full = load_pairs(source, None, **options)
        return kfold_split(full, data.folds, data.fold, data.split_seed)
    raise DataError(f"split must be 'dataset' or 'kfold', got {data.split!r}")
