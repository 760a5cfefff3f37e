"""Training / test splits of a pair set: the data set's own split or seeded k-fold.

Plain arguments only: the step from a run's configuration to these calls is
:func:`torchcf.config.load_split`, above both. A configuration chooses one of
three ways:

* ``split="dataset"``: the data set's own split, ``Trajectory/`` for training and
  ``Testing/`` for testing (see :mod:`torchcf.data.registry` for the quirks handled
  on the way, e.g. the train-to-test leak of CAR MODEL II). A folder extracted
  with ``--test-fraction 0`` has no ``Testing/``: training takes its pairs, a
  step that needs test pairs says there are none (:func:`has_test_split`).
* ``raw``: a raw trajectory source, extracted when the run starts
  (:func:`torchcf.data.importer.extract_source`) and split by source group
  (:func:`group_split`).
* ``split="kfold"``: the full set is cut into ``folds`` nearly equal parts by a
  seeded permutation of the pairs; part ``fold`` is the test set, the rest the
  training set (SPEC section 6, cross-validation).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from torchcf.data.pairset import DataError, PairSet
from torchcf.data.registry import DATASETS, SPLITS, load_pairs

__all__ = ["group_split", "has_test_split", "kfold_split", "split_pairs"]


def has_test_split(source: str | os.PathLike[str]) -> bool:
    """Whether ``split="dataset"`` has test pairs: a named data set always
    has them; a folder has them in ``Testing/``, which an extraction with
    ``--test-fraction 0`` does not write (its training split is all of it).

    Examples:
        >>> import tempfile
        >>> from torchcf.data.splits import has_test_split
        >>> has_test_split("car-model-1")  # a named data set
        True
        >>> with tempfile.TemporaryDirectory() as folder:  # no Testing/ in it
        ...     print(has_test_split(folder))
        False
    """
    if isinstance(source, str) and source in DATASETS:
        return True
    return (Path(source) / SPLITS["test"]).is_dir()


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

    Examples:
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import kfold_split
        >>> train, test = kfold_split(pairs, folds=2, fold=0, seed=0)
        >>> train.n_pairs, test.n_pairs, train.split, test.split
        (2, 2, 'train', 'test')
        >>> sorted(train.pair_ids + test.pair_ids)
        [0, 1, 2, 3]
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


def split_pairs(
    source: str,
    split: str = "dataset",
    *,
    folds: int = 5,
    fold: int = 0,
    seed: int = 0,
    require_test: bool = True,
    **load_options: Any,
) -> tuple[PairSet, PairSet | None]:
    """The training and test pairs of a named data set or a six-CSV folder.

    Args:
        source: a registered data set's name or a folder path
            (:func:`torchcf.data.registry.load_pairs`).
        split: ``"dataset"`` (the set's own ``Trajectory/`` and ``Testing/``) or
            ``"kfold"`` (fold ``fold`` of ``folds`` of the full set, permuted
            under ``seed``: :func:`kfold_split`).
        folds: the k-fold split's number of folds; ignored for ``"dataset"``.
        fold: the test fold, in ``[0, folds)``; ignored for ``"dataset"``.
        seed: the k-fold permutation's seed; ignored for ``"dataset"``.
        require_test: a folder without a test split (:func:`has_test_split`)
            is an error; False gives None as its test pairs (training needs
            none).
        **load_options: passed to :func:`load_pairs` (``units``, ``dt``,
            ``leader_length``, ``data_root``, ``download``, ``cleaning``).

    Returns:
        ``(train, test)`` PairSets in SI units (float64, as loaded); ``test`` is
        None only with ``require_test=False``.

    Raises:
        DataError: the data cannot be loaded, the split is unknown, the k-fold
            split is impossible, or test pairs are required and there are none.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchcf import get_model
        >>> from torchcf.sim.synthetic import synthetic_pairs
        >>> idm = [1.5, 2.0, 33.0, 1.2, 2.0, 4.0]  # a, b, v0, T, s0, delta (SI)
        >>> pairs = synthetic_pairs(get_model("idm"), idm, n_pairs=4, n_steps=50)
        >>> from torchcf.data import split_pairs
        >>> from torchcf.data.writer import write_six_csv
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     write_six_csv(pairs, folder)  # the full set
        ...     write_six_csv(pairs.subset([0, 1, 2]), Path(folder) / "Trajectory")
        ...     write_six_csv(pairs.subset([3]), Path(folder) / "Testing")
        ...     train, test = split_pairs(folder, dt=0.1)
        ...     folded = split_pairs(folder, "kfold", folds=2, fold=1, seed=0, dt=0.1)
        >>> train.n_pairs, test.n_pairs
        (3, 1)
        >>> [part.n_pairs for part in folded]
        [2, 2]
    """
    if split == "dataset":
        train = load_pairs(source, "train", **load_options)
        if has_test_split(source):
            return train, load_pairs(source, "test", **load_options)
        if require_test:
            raise DataError(
                f"no test split: '{source}' has no Testing/ folder (an extraction "
                "with --test-fraction 0 writes none), and evaluating a run needs "
                "test pairs: extract with --test-fraction > 0, or set "
                "data.split='kfold'"
            )
        return train, None
    if split == "kfold":
        full = load_pairs(source, None, **load_options)
        return kfold_split(full, folds, fold, seed)
    raise DataError(f"split must be 'dataset' or 'kfold', got {split!r}")


def group_split(
    index: pd.DataFrame, split_by: str, test_fraction: float, seed: int = 0
) -> tuple[pd.DataFrame, list[int], list[int]]:
    """Assign whole source groups to the test split until it holds its share.

    Groups (``split_by``: the follower ``(run, follower)``, the couple
    ``(run, follower, leader)`` or the ``run``) of an extraction's pair index
    (:func:`torchcf.data.extract.extract_pairs`) are visited in a random order
    seeded with ``seed``; a group joins the test split while the test
    split holds fewer than ``round(test_fraction * N)`` pairs (at least one)
    and at least one group is left for training.

    Returns:
        ``(index with its 'split' column filled, train pair ids, test pair ids)``.

    Raises:
        DataError: a test share is asked for but there is only one group.

    Examples:
        >>> import pandas as pd
        >>> from torchcf.data.splits import group_split
        >>> index = pd.DataFrame(
        ...     {"pair": [0, 1, 2, 3], "run": "r", "follower": ["A", "A", "B", "C"]}
        ... )
        >>> index, train, test = group_split(index, "follower", test_fraction=0.25)
        >>> len(train) + len(test), list(index["split"]).count("test") == len(test)
        (4, True)
    """
    keys = {
        "follower": ["run", "follower"],
        "couple": ["run", "follower", "leader"],
        "run": ["run"],
    }[split_by]
    group = index.groupby(keys, sort=True).ngroup().to_numpy()
    n_groups = int(group.max()) + 1
    index = index.copy()
    if test_fraction == 0:
        index["split"] = "train"
        return index, index["pair"].tolist(), []
    if n_groups < 2:
        raise DataError(
            f"the pairs come from one {split_by} only: a split by "
            f"{split_by} needs two (use --split-by couple or run, or "
            "--test-fraction 0)"
        )
    target = max(1, int(round(test_fraction * len(index))))
    order = np.random.default_rng(seed).permutation(n_groups)
    test_groups: list[int] = []
    in_test = 0
    for g in order[:-1]:  # the last group always trains
        if in_test >= target:
            break
        test_groups.append(int(g))
        in_test += int((group == g).sum())
    is_test = np.isin(group, test_groups)
    index["split"] = np.where(is_test, "test", "train")
    return (
        index,
        index.loc[~is_test, "pair"].tolist(),
        index.loc[is_test, "pair"].tolist(),
    )
